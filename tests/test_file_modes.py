"""Files the project writes carry the user's umask (0o666 & ~umask), for shared filesystems."""

import os
import stat

import numpy as np
import pytest

from psdfactory.io import write_json, write_npz, write_png


@pytest.fixture
def umask():
    old = os.umask(0o022)
    yield lambda m: os.umask(m)
    os.umask(old)


@pytest.mark.parametrize("mask,mode", [(0o022, 0o644), (0o002, 0o664), (0o077, 0o600)])
def test_outputs_get_the_users_umask(tmp_path, umask, mask, mode):
    umask(mask)
    write_json(tmp_path / "a.json", {"x": 1})
    write_npz(tmp_path / "b.npz", x=np.zeros(3))
    write_png(tmp_path / "c.png", np.zeros((4, 4, 3), np.uint8))
    for name in ("a.json", "b.npz", "c.png"):
        assert stat.S_IMODE((tmp_path / name).stat().st_mode) == mode, name


def test_a_log_gets_the_users_umask(tmp_path, umask):
    import subprocess
    import sys

    umask(0o002)
    log = tmp_path / "run.log"
    r = subprocess.run([sys.executable, "-m", "psdfactory.cli", "--log", str(log), "check-config",
                        str(tmp_path / "missing.yaml")], capture_output=True, text=True)
    assert r.returncode == 2 and log.is_file()
    assert stat.S_IMODE(log.stat().st_mode) == 0o664
