"""SIGKILL at every write of every scene stage (sample, simulate, render, label, a batch with its
stamp) and of a manifest shard: the process killed at each rename of io.atomic_path — the
temporary file whole, the final name not yet there — leaves no half file under a final name and
a stage that does not look done, and rerunning the command ends byte for byte as a run that was
never killed. Training and the report: tests/test_training.py."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from psdfactory import config as psd_config
from psdfactory.scene.stages import STAGES

from .sigkill import kill_at_every_rename, without

pytestmark = pytest.mark.slow

STAGE_PARAMS = {"sample": lambda c: psd_config.sample_params(c, "tiny"), "simulate": psd_config.simulate_params,
                "render": psd_config.render_params, "label": psd_config.label_params}


def copy_inputs(src: Path, dst: Path, names) -> Path:
    dst.mkdir(parents=True)
    for f in names:
        shutil.copyfile(src / f, dst / f)
    return dst


@pytest.mark.parametrize("stage", list(STAGES))
def test_sigkill_at_every_write_of_a_scene_stage(stage, tiny_results, tmp_path):
    cfg, root = tiny_results
    base = root / "tiny" / "scenes" / "tiny-000000"
    params = json.dumps(STAGE_PARAMS[stage](cfg))

    def prepare(folder: Path) -> list[str]:
        scene = copy_inputs(base, folder / "tiny-000000", STAGES[stage].inputs)
        return [stage, "--params", params, str(scene)]

    renames = kill_at_every_rename(tmp_path, prepare)
    assert renames == len(STAGES[stage].outputs) + 1  # its outputs, then the record of the params it ran with


def test_sigkill_at_every_write_of_a_batch_then_the_rerun_skips_what_was_done(tiny_results, tmp_path):
    cfg, _ = tiny_results
    params = json.dumps(psd_config.sample_params(cfg, "tiny"))

    def prepare(folder: Path) -> list[str]:
        folder.mkdir(parents=True)
        dirs = [str(folder / f"tiny-{i:06d}") for i in range(2)]
        return ["sample", "--params", params, "--skip-up-to-date", "--stamp", str(folder / "batch-00000.json"), *dirs]

    # the stamp's "ran" lists the scenes the rerun made (those the killed run had not finished)
    # and "seconds" its time: both left out of the comparison, the stamp itself is compared
    stamp = without("ran", "seconds")
    n = kill_at_every_rename(tmp_path, prepare, normalise=lambda rel, data: stamp(data) if rel == "batch-00000.json"
                             else data)
    assert n == 2 * 3 + 1


def test_sigkill_at_every_write_of_a_manifest_shard(tiny_results, tmp_path):
    _, root = tiny_results

    def prepare(folder: Path) -> list[str]:
        dirs = []
        for i in range(3):
            d = folder / "tiny" / "scenes" / f"tiny-{i:06d}"
            shutil.copytree(root / "tiny" / "scenes" / f"tiny-{i:06d}", d)
            dirs.append(str(d))
        m = folder / "tiny" / "manifest"
        return ["manifest", "--params", json.dumps({"split": {"train": 0.8, "val": 0.1, "test": 0.1}}),
                "--results", str(folder), "--scenes-out", str(m / "scenes" / "shard-00000.parquet"),
                "--particles-out", str(m / "particles" / "shard-00000.parquet"), *dirs]

    assert kill_at_every_rename(tmp_path, prepare) == 2
