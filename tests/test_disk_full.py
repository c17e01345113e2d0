"""A full disk: a write that finds no space stops the job with a message naming the disk and the
file, leaves no temporary file and nothing under a final name that is not whole; once space is
freed, a rerun ends byte for byte as a run that never met a full disk.

The tests that need a real small filesystem mount a tmpfs (we run as root in CI); where mounting
is not permitted they skip, and the unit tests below check the message with a simulated ENOSPC."""

from __future__ import annotations

import errno
import json
import os
import shutil
import subprocess
import sys
from contextlib import contextmanager
from pathlib import Path

import pytest

from psdfactory import cli
from psdfactory import config as psd_config
from psdfactory.io import DiskFullError, atomic_path, disk_full, mount_point, write_json

from .conftest import make_scene, tiny_config
from .test_interrupt import CFG, scene_tree
from .workflow_helpers import snakemake, write_config

FULL = "no space left on device: the filesystem mounted at"


# ---- a simulated ENOSPC: the message, wherever mounting is impossible ---------------------------


def enospc(*args, **kwargs):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def test_a_full_disk_stops_the_stage_with_the_disk_and_the_file_named(tiny_results, tmp_path, monkeypatch, capsys):
    from PIL import Image

    cfg, root = tiny_results
    scene = tmp_path / "s"
    shutil.copytree(root / "tiny" / "scenes" / "tiny-000000", scene)
    for f in ("image.png", "mask.png", "render.json"):
        (scene / f).unlink()
    monkeypatch.setattr(Image.Image, "save", enospc)
    rc = cli.main(["render", "--params", json.dumps(psd_config.render_params(cfg)), str(scene)])
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert rc == 2
    assert err.startswith(f"psdfactory render: error: {FULL} {mount_point(scene)} (")
    assert f"writing {scene / 'image.png'} failed" in err and "Free space there" in err
    left = sorted(p.name for p in scene.iterdir())
    assert "image.png" not in left and not [n for n in left if ".tmp" in n], left  # no image, no temporary file


def test_a_full_disk_stops_a_batch_at_once(tiny_results, tmp_path, monkeypatch):
    """Every other scene of the batch would fail the same way: the first full write ends it."""
    from PIL import Image

    from psdfactory.scene.stages import run_scenes

    cfg, root = tiny_results
    dirs = [shutil.copytree(root / "tiny" / "scenes" / f"tiny-{i:06d}", tmp_path / f"tiny-{i:06d}") for i in range(3)]
    calls = []
    monkeypatch.setattr(Image.Image, "save", lambda *a, **k: calls.append(1) or enospc())
    with pytest.raises(DiskFullError, match="no space left on device"):
        run_scenes("render", psd_config.render_params(cfg), dirs)
    assert len(calls) == 1


def test_libraries_that_lose_the_errno_are_caught_by_the_free_space(tmp_path, monkeypatch):
    """PyTorch's zip writer says "file write failed" in a RuntimeError: the filesystem's free
    blocks tell a full disk from another failure."""
    full = os.statvfs_result((4096, 4096, 512, 0, 0, 100, 0, 0, 0, 255))
    monkeypatch.setattr(os, "statvfs", lambda p: full)
    with pytest.raises(DiskFullError, match=f"{FULL} .* is full; writing {tmp_path / 'model.pt'} failed"):
        with atomic_path(tmp_path / "model.pt") as tmp:
            tmp.write_bytes(b"half")
            raise RuntimeError("PytorchStreamWriter failed writing file data/0: file write failed")
    assert list(tmp_path.iterdir()) == []
    monkeypatch.undo()
    assert not disk_full(RuntimeError("a bug"), tmp_path)
    with pytest.raises(RuntimeError, match="a bug"):  # not a full disk: the error as it was
        with atomic_path(tmp_path / "model.pt"):
            raise RuntimeError("a bug")
    assert list(tmp_path.iterdir()) == []


def test_a_full_disk_outside_the_atomic_writes_is_said_at_the_command_line(tmp_path, monkeypatch, capsys):
    """Writes not made through io.atomic_path (predict's rows, a log) reach the CLI's edge as
    OSError ENOSPC: the same one line, naming the file, exit code 2."""
    path = tmp_path / "psd.csv.partial.csv"

    def full(a):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))

    monkeypatch.setattr(cli, "cmd_check_config", full)
    assert cli.main(["check-config", "x.yaml"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"psdfactory check-config: error: {FULL} {mount_point(tmp_path)}") and str(path) in err

    def other(a):
        raise OSError(errno.EIO, os.strerror(errno.EIO), str(path))

    monkeypatch.setattr(cli, "cmd_check_config", other)
    with pytest.raises(OSError, match="Input/output error"):  # not ours to rephrase
        cli.main(["check-config", "x.yaml"])


def test_a_temporary_file_left_by_a_killed_writer_goes_with_the_next_write(tmp_path):
    stale = tmp_path / ".labels.json.ab_12xyz.tmp.json"  # as tempfile.mkstemp names it
    other = tmp_path / ".spec.json.ab_12xyz.tmp.json"
    stale.write_text("{")
    other.write_text("{")
    write_json(tmp_path / "labels.json", {"a": 1})
    assert sorted(p.name for p in tmp_path.iterdir()) == [other.name, "labels.json"]  # only its own


# ---- a real small filesystem (tmpfs) --------------------------------------------------------------


@contextmanager
def small_disk(where: Path, size: str):
    """A tmpfs of `size` mounted at `where`, unmounted afterwards; skips where mounting fails."""
    where.mkdir(parents=True, exist_ok=True)
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(where)],
                       capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here (needs root or CAP_SYS_ADMIN): {r.stderr.strip()}")
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], check=False)


def regrow(where: Path, size: str) -> None:
    """More room on the small disk, its files kept (what freeing space or a larger volume does)."""
    subprocess.run(["mount", "-o", f"remount,size={size}", str(where)], check=True)


def fill(where: Path, leave: int) -> Path:
    """A file that takes all but about `leave` bytes of the filesystem at `where`."""
    st = os.statvfs(where)
    filler = where / "filler.bin"
    with open(filler, "wb") as f:
        f.write(b"\0" * max(0, st.f_bavail * st.f_frsize - leave))
    return filler


def psdfactory(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "psdfactory.cli", *args], capture_output=True, text=True)


def files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.slow
def test_render_on_a_full_tmpfs_then_space_freed_reruns_byte_identical(tmp_path):
    cfg = tiny_config(n_scenes=1)
    cfg["render"]["resolution"] = 128
    ref = make_scene(cfg, tmp_path / "ref" / "tiny-000000")
    render = json.dumps(psd_config.render_params(cfg))
    with small_disk(tmp_path / "disk", "2m") as disk:
        scene = disk / "results" / "tiny" / "scenes" / "tiny-000000"
        scene.mkdir(parents=True)
        for f in ("spec.json", "geometry.npz", "poses.parquet", "simulate.json"):
            shutil.copyfile(ref / f, scene / f)
        filler = fill(disk, leave=8 * 1024)  # the 128² image alone needs more
        r = psdfactory("render", "--params", render, str(scene))
        assert r.returncode == 2, r.stderr
        line = r.stderr.strip().splitlines()[-1]
        assert line.startswith(f"psdfactory render: error: {FULL} {disk} (2.0 MB, ") and "image.png failed" in line
        done = files(scene)
        assert not [n for n in done if ".tmp" in n]  # no temporary file
        assert "image.png" not in done and "render.json" not in done  # nothing that looks complete

        filler.unlink()  # space freed
        r = psdfactory("render", "--params", render, str(scene))
        assert r.returncode == 0, r.stderr
        assert {n: b for n, b in files(scene).items() if not n.startswith("stages")} == \
               {n: b for n, b in files(ref).items() if not n.startswith("stages") and n not in ("labels.json",
                                                                                                 "particles.parquet")}


@pytest.mark.workflow
def test_snakemake_on_a_small_disk_stops_then_completes_identical_once_it_grows(tmp_path):
    straight, small = tmp_path / "straight", tmp_path / "small"
    straight.mkdir()
    write_config(straight / "c.yaml", CFG)
    r = snakemake("-j2", "scenes", "--configfile", "c.yaml", workdir=straight)
    assert r.returncode == 0, r.stderr[-3000:]
    reference = scene_tree(straight / "results")

    with small_disk(tmp_path / "disk", "160k") as disk:
        small.mkdir()
        write_config(small / "c.yaml", {**CFG, "results": str(disk / "results")})
        r = snakemake("-j2", "scenes", "--configfile", "c.yaml", workdir=small)
        assert r.returncode != 0, "the run fit on the small disk"
        # the job logs sit on the full disk and may not take the verdict: the console always has it
        said = [line for line in (r.stdout + r.stderr).splitlines() if FULL in line]
        assert said and said[0].split(": error: ", 1)[1].startswith(f"{FULL} {disk} (160.0 KB, "), r.stderr[-3000:]
        logged = [line for log in (disk / "results").rglob("*.log") for line in log.read_text().splitlines()
                  if FULL in line]
        assert set(logged) <= set(said)  # where a log could take it, the same line
        half = scene_tree(disk / "results")
        assert [k for k in half if ".tmp" in k] == []
        assert [k for k in half if half[k] != reference.get(k)] == []  # what is there is whole

        regrow(disk, "64m")
        r = snakemake("-j2", "scenes", "--configfile", "c.yaml", workdir=small)
        assert r.returncode == 0, (r.stdout + r.stderr)[-3000:]
        done = scene_tree(disk / "results")
        assert sorted(done) == sorted(reference) and [k for k in done if done[k] != reference[k]] == []
