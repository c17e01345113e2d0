from __future__ import annotations

import logging
import os
from pathlib import Path

import pytest

from psdfactory import config as psd_config
from psdfactory.scene.stages import run_label, run_render, run_sample, run_simulate

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True)
def _psdfactory_log_level_restored():
    """`psdfactory.cli.main` sets the package's log level (--quiet, --verbose): put it back after
    each test, so that no test depends on what an earlier one ran."""
    logger = logging.getLogger("psdfactory")
    level = logger.level
    yield
    logger.setLevel(level)


@pytest.fixture(autouse=True, scope="session")
def _predict_cache_in_tmp(tmp_path_factory):
    """predict's ONNX copies and timings (deploy/fastpath.py) go to a folder of the test run, not
    to the user's ~/.cache (subprocesses inherit it)."""
    old = os.environ.get("PSDFACTORY_CACHE")
    os.environ["PSDFACTORY_CACHE"] = str(tmp_path_factory.mktemp("psdfactory-cache"))
    yield
    if old is None:
        os.environ.pop("PSDFACTORY_CACHE", None)
    else:
        os.environ["PSDFACTORY_CACHE"] = old


def tiny_config(**dataset_overrides) -> dict:
    """A validated config with one tiny dataset (fast physics and rendering)."""
    ds = {
        "n_scenes": 3,
        "shard_size": 2,
        "table_size": 60,
        "count": [30, 40],
        "size": {"mean": [5, 8], "sigma": [2, 3], "bounds": [1, 12]},
    }
    ds.update(dataset_overrides)
    cfg = {"seed": 7, "datasets": {"tiny": ds}, "render": {"resolution": 64}, "train": {"datasets": ["tiny"]}}
    return psd_config.validate(cfg)


def make_scene(cfg: dict, scene_dir: Path, dataset: str = "tiny", index: int = 0) -> Path:
    run_sample(psd_config.sample_params(cfg, dataset, index), scene_dir)
    run_simulate(psd_config.simulate_params(cfg), scene_dir)
    run_render(psd_config.render_params(cfg), scene_dir)
    run_label(psd_config.label_params(cfg), scene_dir)
    return scene_dir


@pytest.fixture(scope="session")
def tiny_results(tmp_path_factory) -> tuple[dict, Path]:
    """Three fully processed tiny scenes under <root>/tiny/scenes/."""
    cfg = tiny_config()
    root = tmp_path_factory.mktemp("results")
    for i in range(3):
        make_scene(cfg, root / "tiny" / "scenes" / f"tiny-{i:06d}", index=i)
    return cfg, root


def split_dataset(root: Path, splits: list[str], resolution: int = 32, dataset: str = "tiny") -> list[Path]:
    """len(splits) tiny scenes of `dataset` under `root` with their manifest, scene i in splits[i]
    (the scenes' own split draws replaced: a test needs known counts per split); their folders."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from psdfactory.manifest import write_shard

    cfg = tiny_config(n_scenes=len(splits), count=[15, 25])
    cfg["render"]["resolution"] = resolution
    dirs = [make_scene(cfg, root / dataset / "scenes" / f"{dataset}-{i:06d}", dataset, index=i)
            for i in range(len(splits))]
    m = root / dataset / "manifest"
    write_shard(dirs, root, {"train": 1.0}, m / "scenes" / "shard-00000.parquet",
                m / "particles" / "shard-00000.parquet")
    t = pq.read_table(m / "scenes" / "shard-00000.parquet")
    t = t.set_column(t.schema.get_field_index("split"), "split", pa.array(splits))
    pq.write_table(t, m / "scenes" / "shard-00000.parquet")
    return dirs
