"""Running a stage over many scene folders: skipping what is up to date, failures, progress."""

from __future__ import annotations

import os
import time

import pytest

from psdfactory import PsdError
from psdfactory import config as psd_config
from psdfactory.io import read_json
from psdfactory.scene.stages import record_path, run_scenes, up_to_date

from .conftest import tiny_config


@pytest.fixture()
def sampled(tmp_path):
    cfg = tiny_config(count=[10, 14])
    dirs = [tmp_path / f"tiny-{i:06d}" for i in range(3)]
    run_scenes("sample", psd_config.sample_params(cfg, "tiny"), dirs)
    return cfg, dirs


@pytest.mark.slow
def test_sample_takes_the_index_from_the_folder_and_records_its_params(sampled):
    cfg, dirs = sampled
    for i, d in enumerate(dirs):
        assert read_json(d / "spec.json")["index"] == i
        assert read_json(record_path(d, "sample"))["params"] == psd_config.sample_params(cfg, "tiny", i)
        assert up_to_date("sample", psd_config.sample_params(cfg, "tiny", i), d)


@pytest.mark.slow
def test_up_to_date_follows_outputs_inputs_and_params(sampled):
    cfg, dirs = sampled
    params = psd_config.simulate_params(cfg)
    summary = run_scenes("simulate", params, dirs, skip_up_to_date=True, jobs=2)
    assert sorted(summary["ran"]) == [d.name for d in dirs]
    assert all(up_to_date("simulate", params, d) for d in dirs)
    # nothing to do the second time
    assert run_scenes("simulate", params, dirs, skip_up_to_date=True)["ran"] == []
    # other params, a newer input, a missing output: each makes one scene stale
    assert not up_to_date("simulate", {**params, "friction": 0.3}, dirs[0])
    later = time.time() + 5
    os.utime(dirs[1] / "spec.json", (later, later))
    (dirs[2] / "poses.parquet").unlink()
    assert sorted(run_scenes("simulate", params, dirs, skip_up_to_date=True)["ran"]) == [dirs[1].name, dirs[2].name]


@pytest.mark.slow
def test_a_failing_scene_names_itself_keeps_the_others_and_writes_no_stamp(sampled, tmp_path):
    cfg, dirs = sampled
    (dirs[1] / "spec.json").write_text("{ not json")
    stamp = tmp_path / "stamp.json"
    with pytest.raises(PsdError, match=r"simulate failed for 1 of 3 scenes(.|\n)*tiny-000001(.|\n)*not valid JSON"):
        run_scenes("simulate", psd_config.simulate_params(cfg), dirs, skip_up_to_date=True, jobs=2, stamp=stamp)
    assert not stamp.exists()
    assert (dirs[0] / "poses.parquet").is_file() and (dirs[2] / "poses.parquet").is_file()
    assert not (dirs[1] / "poses.parquet").exists()


def test_a_stage_needs_its_inputs(tmp_path):
    cfg = tiny_config()
    with pytest.raises(PsdError, match="missing spec.json"):
        run_scenes("render", psd_config.render_params(cfg), [tmp_path / "tiny-000000"])


def test_sample_refuses_a_folder_of_another_dataset(tmp_path):
    cfg = tiny_config()
    with pytest.raises(PsdError, match="does not belong to dataset 'tiny'"):
        run_scenes("sample", psd_config.sample_params(cfg, "tiny"), [tmp_path / "other-000000"])


def test_missing_scene_files_lists_what_is_gone_from_existing_scenes_without_a_stat_per_file(tmp_path, monkeypatch):
    from psdfactory.scene.stages import SCENE_FILES, missing_scene_files

    root = tmp_path / "scenes"
    for sid, gone in (("a-000000", ()), ("a-000001", ("image.png", "labels.json"))):
        (root / sid).mkdir(parents=True)
        for f in SCENE_FILES:
            if f not in gone:
                (root / sid / f).write_bytes(b"")
    (root / "a-000003").write_text("a file where a scene folder would be")

    def no_stat(*a, **k):
        raise AssertionError("stat per file")

    monkeypatch.setattr(os, "stat", no_stat)
    monkeypatch.setattr(os.path, "exists", no_stat)
    ids = ["a-000000", "a-000001", "a-000002", "a-000003"]
    assert missing_scene_files(str(root), ids) == [f"{root}/a-000001/image.png", f"{root}/a-000001/labels.json"]
    assert missing_scene_files(str(tmp_path / "none"), ids) == []
