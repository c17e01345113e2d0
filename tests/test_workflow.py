"""One tiny end-to-end run of the Snakemake workflow (system-level)."""

import subprocess
import sys
from pathlib import Path

import pyarrow.parquet as pq
import pytest
import yaml

from .conftest import REPO

pytestmark = pytest.mark.workflow

TINY = {
    "seed": 3,
    "datasets": {
        "train": {
            "n_scenes": 3, "shard_size": 2, "table_size": 50, "count": [20, 30],
            "size": {"mean": [4, 7], "sigma": [2, 3], "bounds": [1, 10]},
        },
        "ood": {
            "n_scenes": 1, "shard_size": 4, "table_size": 50, "count": [20, 25], "shape": "granule",
            "split": {"test": 1.0}, "size": {"mean": [6, 8], "sigma": [1, 2], "bounds": [1, 10]},
        },
    },
    "render": {"resolution": 48},
}


def snakemake(*args, cwd=REPO):
    exe = Path(sys.executable).with_name("snakemake")
    return subprocess.run([str(exe), *args], cwd=cwd, capture_output=True, text=True)


def test_tiny_workflow_end_to_end(tmp_path):
    cfg = dict(TINY, results=str(tmp_path / "results"))
    cfgfile = tmp_path / "tiny.yaml"
    cfgfile.write_text(yaml.safe_dump(cfg))
    r = snakemake("-j2", "--configfile", str(cfgfile))
    assert r.returncode == 0, r.stderr[-3000:]
    res = tmp_path / "results"
    scenes = pq.read_table(res / "train" / "manifest" / "scenes")
    assert sorted(scenes.column("scene_id").to_pylist()) == ["train-000000", "train-000001", "train-000002"]
    assert len(list((res / "train" / "manifest" / "scenes").glob("shard-*.parquet"))) == 2
    ood = pq.read_table(res / "ood" / "manifest" / "scenes")
    assert ood.column("split").to_pylist() == ["test"] and ood.column("shape_type").to_pylist() == ["granule"]
    parts = pq.read_table(res / "train" / "manifest" / "particles")
    assert parts.num_rows == sum(scenes.column("n_particles").to_pylist())
    assert (res / "train" / "contact_sheet.png").is_file()
    assert (res / "train" / "logs" / "simulate" / "train-000001.log").read_text().count("settled") >= 1
    # a second run has nothing to do
    r = snakemake("-n", "--configfile", str(cfgfile))
    assert r.returncode == 0 and "Nothing to be done" in r.stdout + r.stderr


def test_lint_is_clean():
    r = snakemake("--lint")
    assert r.returncode == 0, r.stdout + r.stderr
