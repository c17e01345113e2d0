"""`kill -9` of a running `snakemake -j2` (Snakemake and every job it runs, mid-render), then
`--unlock` and `--rerun-incomplete`: the results are byte for byte those of a run that was never
interrupted — every output is written atomically, so no half file is taken as done."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from psdfactory.runlock import LOCK_NAME

from .workflow_helpers import REPO, snakemake, write_config

pytestmark = pytest.mark.workflow

CFG = {
    "seed": 5,
    "results": "results",
    "datasets": {"a": {"n_scenes": 6, "shard_size": 3, "table_size": 40, "count": [10, 14],
                       "size": {"mean": [4, 6], "sigma": [1, 2], "bounds": [1, 8]}}},
    "render": {"resolution": 48},
    "train": {"datasets": ["a"]},
    "show": {"compare_backends": 0},
}


def scene_tree(results: Path) -> dict[str, bytes]:
    """Every file of the datasets but the logs (which hold timings and the kill) and the run lock
    (which names its last holder); simulate.json without its wall-clock seconds (`wall_s`, the
    one figure that is not reproducible)."""
    tree = {}
    for p in sorted(results.rglob("*")):
        if p.is_file() and "logs" not in p.relative_to(results).parts and p.name != LOCK_NAME:
            data = p.read_bytes()
            if p.name == "simulate.json" and p.parent.name != "stages":  # not the stage record
                d = json.loads(data)
                assert isinstance(d.pop("wall_s"), float)
                data = json.dumps(d, sort_keys=True).encode()
            tree[str(p.relative_to(results))] = data
    return tree


def test_kill_9_mid_render_then_rerun_incomplete_is_byte_identical(tmp_path):
    straight, killed = tmp_path / "straight", tmp_path / "killed"
    for w in (straight, killed):
        w.mkdir()
        write_config(w / "c.yaml", CFG)
    r = snakemake("-j2", "scenes", "--configfile", "c.yaml", workdir=straight)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "snakemake" in json.loads((straight / "results" / LOCK_NAME).read_text())["command"]  # the run held it

    cmd = [str(Path(sys.executable).with_name("snakemake")), "-s", str(REPO / "Snakefile"), "-d", str(killed),
           "-j2", "scenes", "--configfile", "c.yaml"]
    proc = subprocess.Popen(cmd, cwd=killed, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    logs = killed / "results" / "a" / "logs" / "render"
    deadline = time.time() + 300
    while time.time() < deadline and proc.poll() is None and not (logs.is_dir() and any(logs.iterdir())):
        time.sleep(0.01)
    assert proc.poll() is None, "the run ended before a render job started"
    os.killpg(proc.pid, signal.SIGKILL)  # Snakemake and its running jobs, as when the machine goes away
    proc.wait()
    rendered = len(list((killed / "results" / "a" / "scenes").glob("*/image.png")))
    assert rendered < 6  # killed with renders still to do

    r = snakemake("--unlock", "scenes", "--configfile", "c.yaml", workdir=killed)
    assert r.returncode == 0, r.stderr[-3000:]
    r = snakemake("-j2", "scenes", "--configfile", "c.yaml", "--rerun-incomplete", workdir=killed)
    assert r.returncode == 0, (r.stdout + r.stderr)[-3000:]
    a, b = scene_tree(straight / "results"), scene_tree(killed / "results")
    assert sorted(a) == sorted(b)
    assert [k for k in a if a[k] != b[k]] == []
    assert not [p for p in (killed / "results").rglob("*.tmp*")]  # no temporary file left behind
