"""After a config edit, only what the edit changed is regenerated (Snakemake dry runs)."""

import copy

import pytest

from .workflow_helpers import planned_jobs, planned_wildcards, snakemake, write_config

pytestmark = pytest.mark.workflow

SCENE_RULES = ("sample", "simulate", "render", "label", "manifest_shard")

BASE = {
    "seed": 11,
    "datasets": {
        "a": {"n_scenes": 3, "shard_size": 2, "table_size": 40, "count": [8, 12],
              "size": {"mean": [4, 6], "sigma": [1, 2], "bounds": [1, 8]}},
        "b": {"n_scenes": 2, "shard_size": 2, "table_size": 40, "count": [8, 12], "shape": "granule",
              "size": {"mean": [5, 7], "sigma": [1, 2], "bounds": [1, 8]}},
    },
    "render": {"resolution": 32},
    "train": {"dataset": "a"},
}


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    work = tmp_path_factory.mktemp("work")
    cfg = copy.deepcopy(BASE)
    cfg["results"] = str(work / "results")
    r = snakemake("-j2", "scenes", "--configfile", str(write_config(work / "c.yaml", cfg)), workdir=work)
    assert r.returncode == 0, r.stderr[-3000:]
    return work, cfg


def dry(work, cfg, target="scenes"):
    path = write_config(work / "edited.yaml", cfg)
    r = snakemake("-n", target, "--configfile", str(path), workdir=work)
    assert r.returncode == 0, r.stderr[-3000:]
    return planned_jobs(r), r


def test_nothing_changed_nothing_to_do(built):
    jobs, r = dry(*built)
    assert not jobs and "Nothing to be done" in r.stdout + r.stderr


def test_more_scenes_only_new_scenes_and_affected_shards(built):
    work, cfg = built
    cfg = copy.deepcopy(cfg)
    cfg["datasets"]["a"]["n_scenes"] = 5  # shard 0 = scenes 0-1 untouched, shard 1 gains scene 3, shard 2 is new
    jobs, r = dry(work, cfg)
    for rule in ("sample", "simulate", "render", "label"):
        assert sorted(planned_wildcards(r, rule)) == ["dataset=a, scene=a-000003", "dataset=a, scene=a-000004"]
    assert sorted(planned_wildcards(r, "manifest_shard")) == ["dataset=a, shard=00001", "dataset=a, shard=00002"]


def test_render_setting_reruns_render_and_downstream_only(built):
    work, cfg = built
    cfg = copy.deepcopy(cfg)
    cfg["render"]["light_elevation_deg"] = [40, 60]
    jobs, _ = dry(work, cfg)
    assert jobs["sample"] == 0 and jobs["simulate"] == 0
    assert jobs["render"] == 5 and jobs["label"] == 5 and jobs["manifest_shard"] == 3


def test_one_datasets_size_distribution_only_touches_that_dataset(built):
    work, cfg = built
    cfg = copy.deepcopy(cfg)
    cfg["datasets"]["b"]["size"]["mean"] = [5.5, 7]
    jobs, r = dry(work, cfg)
    for rule in ("sample", "simulate", "render", "label"):
        assert sorted(planned_wildcards(r, rule)) == ["dataset=b, scene=b-000000", "dataset=b, scene=b-000001"]
    assert planned_wildcards(r, "manifest_shard") == ["dataset=b, shard=00000"]


def test_training_setting_touches_no_scene_job(built):
    work, cfg = built
    cfg = copy.deepcopy(cfg)
    cfg["train"]["epochs"] = 3
    jobs, _ = dry(work, cfg, target="all")
    assert jobs["train"] == 3  # the models are (re)made ...
    assert all(jobs[r] == 0 for r in SCENE_RULES)  # ... from the scenes as they are


def test_deleted_image_regenerates_that_scene_only(built):
    work, cfg = built
    (work / "results" / "a" / "scenes" / "a-000001" / "image.png").unlink()
    jobs, r = dry(work, cfg)
    assert jobs["sample"] == 0 and jobs["simulate"] == 0
    assert planned_wildcards(r, "render") == ["dataset=a, scene=a-000001"]
    assert planned_wildcards(r, "label") == ["dataset=a, scene=a-000001"]
    assert planned_wildcards(r, "manifest_shard") == ["dataset=a, shard=00000"]
