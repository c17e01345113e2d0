"""SIGKILL at every rename of a command, then the same command again: what the kill leaves is
never a half file under a final name, and the rerun ends byte for byte as a run that was never
killed (with `killhook/sitecustomize.py`, a test-only hook on the commands' PYTHONPATH)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

KILLHOOK = Path(__file__).with_name("killhook")


def psdfactory(args: list[str], kill_at: int = 0, record: Path | None = None) -> subprocess.CompletedProcess:
    """`psdfactory ARGS` in a fresh Python, killed at its `kill_at`-th os.replace (0: not killed),
    recording every os.replace's destination in `record`."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("PSD_TEST_")}
    env["PYTHONPATH"] = os.pathsep.join([str(KILLHOOK)] + [p for p in [env.get("PYTHONPATH")] if p])
    if kill_at:
        env["PSD_TEST_KILL_AT_REPLACE"] = str(kill_at)
    if record:
        env["PSD_TEST_RECORD_REPLACES"] = str(record)
    return subprocess.run([sys.executable, "-m", "psdfactory.cli", *args], env=env, capture_output=True, text=True)


Skip = Callable[[str], bool]
Normalise = Callable[[str, bytes], bytes]


def without(*keys: str) -> Callable[[bytes], bytes]:
    """A JSON file's bytes without these keys (figures that are not reproducible: timings)."""
    def strip(data: bytes) -> bytes:
        d = json.loads(data)
        for k in keys:
            d.pop(k, None)
        return json.dumps(d, sort_keys=True).encode()

    return strip


def tree(root: Path, skip: Skip = lambda rel: False, normalise: Normalise = lambda rel, data: data) -> dict[str, bytes]:
    """Every file under root by relative path (normalised); simulate.json without its wall-clock
    seconds."""
    out = {}
    for p in sorted(root.rglob("*")):
        rel = p.relative_to(root).as_posix()
        if not p.is_file() or skip(rel):
            continue
        data = p.read_bytes()
        if p.name == "simulate.json" and p.parent.name != "stages":
            data = without("wall_s")(data)
        out[rel] = normalise(rel, data)
    return out


def kill_at_every_rename(work: Path, prepare: Callable[[Path], list[str]], skip: Skip = lambda rel: False,
                         normalise: Normalise = lambda rel, data: data) -> int:
    """`prepare(folder)` lays out a command's inputs in a fresh folder and returns its arguments.
    Runs it once through (recording its renames), checks that every file it made was moved into
    place by a rename (written atomically), then for each rename k: a fresh folder, the command
    killed with SIGKILL at rename k, every final file it left whole (equal to the uninterrupted
    run's) and the stage visibly unfinished (an output missing), then the same command again,
    which must end byte for byte as the uninterrupted run with no temporary file left. Returns
    the number of renames (kill points)."""
    ref, log = work / "ref", work / "renames.txt"
    args = prepare(ref)
    before = tree(ref, skip, normalise)
    r = psdfactory(args, record=log)
    assert r.returncode == 0, r.stderr[-3000:]
    done = tree(ref, skip, normalise)
    renamed = log.read_text().split()
    made = [rel for rel in done if done[rel] != before.get(rel)]
    assert made, "the command wrote nothing"
    not_atomic = [rel for rel in made if str((ref / rel).absolute()) not in renamed]
    assert not not_atomic, f"written in place, not through a rename: {not_atomic}"
    for k in range(1, len(renamed) + 1):
        folder = work / f"kill{k}"
        args = prepare(folder)
        r = psdfactory(args, kill_at=k)
        assert r.returncode == -signal.SIGKILL, (k, r.returncode, r.stderr[-2000:])
        left = tree(folder, skip, normalise)
        half = [rel for rel, data in left.items() if ".tmp" not in rel and data != done.get(rel)]
        assert not half, f"killed at rename {k}: a final file that is not the finished one: {half}"
        assert set(done) - set(left), f"killed at rename {k}, the command looks finished"
        r = psdfactory(args)
        assert r.returncode == 0, (k, r.stderr[-3000:])
        again = tree(folder, skip, normalise)
        assert sorted(again) == sorted(done), (k, sorted(set(again) ^ set(done)))
        assert [rel for rel in done if again[rel] != done[rel]] == [], k
    return len(renamed)
