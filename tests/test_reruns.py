"""After a config edit, only what the edit changed is regenerated (Snakemake dry runs).

The two built working directories are shared by the tests of this module; a test that changes
files works on its own copy (`own_copy`), so the tests pass in any order and alone."""

import copy

import pytest
import yaml

from .workflow_helpers import REPO, own_copy, planned_jobs, planned_wildcards, snakemake, write_config

pytestmark = pytest.mark.workflow

BASE = {
    "seed": 11,
    "datasets": {
        "a": {"n_scenes": 3, "shard_size": 2, "table_size": 40, "count": [8, 12],
              "size": {"mean": [4, 6], "sigma": [1, 2], "bounds": [1, 8]}},
        "b": {"n_scenes": 2, "shard_size": 2, "table_size": 40, "count": [8, 12], "shape": "granule",
              "size": {"mean": [5, 7], "sigma": [1, 2], "bounds": [1, 8]}},
    },
    "render": {"resolution": 32},
    "train": {"datasets": ["a"]},
    "show": {"compare_backends": 0},  # `all` would otherwise need Blender (checked as the DAG is built)
}


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    work = tmp_path_factory.mktemp("work")
    cfg = copy.deepcopy(BASE)
    cfg["results"] = "results"  # relative to the working directory: copies of it stay whole
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


def test_every_run_reads_the_workflow_profile_and_schedules_greedily(built):
    # profiles/default (beside the Snakefile) holds the workflow's command-line defaults
    prof = yaml.safe_load((REPO / "profiles" / "default" / "config.yaml").read_text(encoding="utf-8"))
    assert prof["scheduler"] == "greedy"
    _, r = dry(*built)
    assert f"Using workflow specific profile {REPO / 'profiles' / 'default'}" in r.stdout + r.stderr


def test_more_scenes_only_new_scenes_and_affected_shards(built):
    work, cfg = built
    cfg = copy.deepcopy(cfg)
    cfg["datasets"]["a"]["n_scenes"] = 5  # shard 0 = scenes 0-1 untouched, shard 1 gains scene 3, shard 2 is new
    jobs, r = dry(work, cfg)
    for rule in ("sample", "simulate", "render", "label"):
        assert sorted(planned_wildcards(r, rule)) == ["dataset=a, scene=a-000003", "dataset=a, scene=a-000004"]
    assert sorted(planned_wildcards(r, "manifest_shard")) == ["dataset=a, shard=00001", "dataset=a, shard=00002"]


BOTH_MODES = pytest.mark.parametrize("mode, stages", [
    ("built", ("sample", "simulate", "render", "label")),  # one job per scene (5 scenes)
    ("built_batched", ("sample_batch", "simulate_batch", "render_batch", "label_batch")),  # 3 batches of <= 2
], ids=["one-job-per-scene", "batches"])


@BOTH_MODES
def test_render_setting_reruns_render_and_downstream_only(request, mode, stages):
    work, cfg = request.getfixturevalue(mode)
    cfg = copy.deepcopy(cfg)
    cfg["render"]["light_elevation_deg"] = [40, 60]
    jobs, _ = dry(work, cfg)
    sample, simulate, render, label = stages
    n = 5 if mode == "built" else 3
    assert jobs[sample] == 0 and jobs[simulate] == 0
    assert jobs[render] == n and jobs[label] == n and jobs["manifest_shard"] == 3


def test_one_datasets_size_distribution_only_touches_that_dataset(built):
    work, cfg = built
    cfg = copy.deepcopy(cfg)
    cfg["datasets"]["b"]["size"]["mean"] = [5.5, 7]
    jobs, r = dry(work, cfg)
    for rule in ("sample", "simulate", "render", "label"):
        assert sorted(planned_wildcards(r, rule)) == ["dataset=b, scene=b-000000", "dataset=b, scene=b-000001"]
    assert planned_wildcards(r, "manifest_shard") == ["dataset=b, shard=00000"]


@BOTH_MODES
def test_training_setting_touches_no_scene_job(request, mode, stages):
    work, cfg = request.getfixturevalue(mode)
    cfg = copy.deepcopy(cfg)
    cfg["train"]["epochs"] = 3
    jobs, _ = dry(work, cfg, target="all")
    assert jobs["train"] == 3  # the models are (re)made ...
    assert all(jobs[r] == 0 for r in stages + ("manifest_shard",))  # ... from the scenes as they are


def test_deleted_image_regenerates_that_scene_only(built, tmp_path):
    work, cfg = own_copy(built[0], tmp_path / "work"), built[1]
    (work / "results" / "a" / "scenes" / "a-000001" / "image.png").unlink()
    jobs, r = dry(work, cfg)
    assert jobs["sample"] == 0 and jobs["simulate"] == 0
    assert planned_wildcards(r, "render") == ["dataset=a, scene=a-000001"]
    assert planned_wildcards(r, "label") == ["dataset=a, scene=a-000001"]
    assert planned_wildcards(r, "manifest_shard") == ["dataset=a, shard=00000"]


def test_a_dry_run_changes_nothing_in_any_state(built, built_batched, tmp_path):
    """Fresh, partial (a manifest shard gone), and with a scene file deleted by hand, in both
    modes: `snakemake -n` plans the repair and writes, removes or touches nothing."""
    fresh = tmp_path / "fresh"
    fresh.mkdir()
    dry(fresh, built[1])
    assert sorted(p.name for p in fresh.iterdir() if p.name != ".snakemake") == ["edited.yaml"]
    for i, (src, cfg) in enumerate((built, built_batched)):
        work = own_copy(src, tmp_path / f"work{i}")
        results = work / "results"
        (results / "a" / "scenes" / "a-000001" / "image.png").unlink()
        (results / "b" / "manifest" / "scenes" / "shard-00000.parquet").unlink()
        tree = tree_digest(results)
        jobs, r = dry(work, cfg)
        assert tree_digest(results) == tree
        assert planned_wildcards(r, "render") == ["dataset=a, scene=a-000001"]
        assert jobs["manifest_shard"] >= 1


def tree_digest(root):
    """Every file under root with its size, mtime and content hash."""
    import hashlib

    def digest(p):
        return p.stat().st_size, p.stat().st_mtime_ns, hashlib.sha256(p.read_bytes()).hexdigest()

    return {str(p.relative_to(root)): digest(p) for p in sorted(root.rglob("*")) if p.is_file()}


# ---- scenes_per_job > 1: batch jobs that skip up-to-date scenes ----------------------------

BATCH_RULES = ("sample_batch", "simulate_batch", "render_batch", "label_batch")


def scene_mtimes(results, dataset):
    return {p.relative_to(results).as_posix(): p.stat().st_mtime_ns
            for p in (results / dataset / "scenes").rglob("*") if p.is_file()}


@pytest.fixture(scope="module")
def built_batched(tmp_path_factory):
    work = tmp_path_factory.mktemp("batched")
    cfg = copy.deepcopy(BASE)
    cfg["results"] = "results"
    cfg["scenes_per_job"] = 2  # a: batches {0,1}, {2}; b: {0,1}
    r = snakemake("-j2", "scenes", "--configfile", str(write_config(work / "c.yaml", cfg)), workdir=work)
    assert r.returncode == 0, r.stderr[-3000:]
    return work, cfg


def test_batched_scenes_equal_one_job_per_scene(built, built_batched):
    """The grouping of scenes into jobs does not change a single output byte."""
    per_scene, batched = built[0] / "results", built_batched[0] / "results"
    for ds, n in (("a", 3), ("b", 2)):
        for i in range(n):
            for f in ("image.png", "mask.png", "labels.json", "poses.parquet"):
                rel = f"{ds}/scenes/{ds}-{i:06d}/{f}"
                assert (per_scene / rel).read_bytes() == (batched / rel).read_bytes(), rel
    assert not any(planned_jobs(dry(*built_batched)[1]).values())


def test_batched_reruns_regenerate_only_the_scenes_that_changed(built_batched, tmp_path):
    """Runs for real: a deleted image, then more scenes — and checks which files were rewritten."""
    work, cfg = own_copy(built_batched[0], tmp_path / "work"), built_batched[1]
    results = work / "results"
    image = results / "a" / "scenes" / "a-000001" / "image.png"
    before_bytes = image.read_bytes()
    before = scene_mtimes(results, "a")
    image.unlink()
    tree = tree_digest(results)
    jobs, r = dry(work, cfg)
    assert tree_digest(results) == tree  # a dry run changes nothing (it used to remove a stamp)
    assert "a-000001/image.png is missing" in r.stderr
    assert planned_wildcards(r, "render") == ["dataset=a, scene=a-000001"]  # that scene's own render job
    assert not any(jobs[rule] for rule in BATCH_RULES)
    r = snakemake("-j2", "scenes", "--configfile", str(work / "edited.yaml"), workdir=work)
    assert r.returncode == 0, r.stderr[-3000:]
    assert image.read_bytes() == before_bytes  # regenerated, identical
    after = scene_mtimes(results, "a")
    changed = {k for k in after if after[k] != before.get(k)}
    assert changed and all(k.startswith("a/scenes/a-000001/") for k in changed), changed
    assert not any(k.startswith("a/scenes/a-000001/") and "sample" in k for k in changed)

    # more scenes: 3 → 5; batch 1 ({2} → {2, 3}) reruns but skips scene 2; batch 2 is new
    cfg = copy.deepcopy(cfg)
    cfg["datasets"]["a"]["n_scenes"] = 5
    jobs, r = dry(work, cfg)
    for rule in BATCH_RULES:
        assert sorted(planned_wildcards(r, rule)) == ["dataset=a, batch=00001", "dataset=a, batch=00002"]
    before = scene_mtimes(results, "a")
    r = snakemake("-j2", "scenes", "--configfile", str(work / "edited.yaml"), workdir=work)
    assert r.returncode == 0, r.stderr[-3000:]
    after = scene_mtimes(results, "a")
    assert all(after[k] == v for k, v in before.items())  # no existing scene file rewritten
    assert {k.split("/")[2] for k in set(after) - set(before)} == {"a-000003", "a-000004"}
    assert "1 of 2 scenes to run, 1 up to date" in (results / "a" / "logs" / "sample" / "batch-00001.log").read_text()
    assert not any(planned_jobs(dry(work, cfg)[1]).values())


def test_a_rerender_of_the_training_splits_adds_only_its_scenes_and_feeds_training(built):
    """train.datasets [a, a_more], a_more = a's train and val scenes rendered again: the dry run
    plans a_more's scenes alone (a is up to date; its test scenes are not re-rendered) and a
    training job that reads both datasets' manifests."""
    from psdfactory import config as psd_config

    work, cfg = built
    cfg = copy.deepcopy(cfg)
    cfg["datasets"]["a_more"] = {"rerender_of": {"dataset": "a", "split": ["train", "val"]},
                                 "render": {"resolution": 24}}
    cfg["train"]["datasets"] = ["a", "a_more"]
    n = len(psd_config.source_indices(psd_config.validate(copy.deepcopy(cfg)), "a_more"))
    assert 0 < n <= cfg["datasets"]["a"]["n_scenes"]
    jobs, r = dry(work, cfg, target="results/models/resnet50/model.pt")
    for rule in ("sample", "simulate", "render", "label"):
        assert sorted(planned_wildcards(r, rule)) == [f"dataset=a_more, scene=a_more-{k:06d}" for k in range(n)]
    assert jobs["train"] == 1
    assert "results/a_more/manifest/scenes/shard-00000.parquet" in r.stdout + r.stderr


def test_the_instance_estimator_trains_on_its_own_datasets_and_the_cnns_on_theirs(built):
    """train.instances.datasets [a, a_more]: the instance estimator's training job reads both
    datasets' manifests, a CNN's only train.datasets' (a): more scene families for the grain finder
    retrain no CNN."""
    work, cfg = built
    cfg = copy.deepcopy(cfg)
    cfg["datasets"]["a_more"] = {"rerender_of": {"dataset": "a", "split": ["train", "val"]},
                                 "render": {"resolution": 24}}
    cfg["train"]["architectures"] = ["resnet50", "instances"]
    cfg["train"].setdefault("instances", {})["datasets"] = ["a", "a_more"]
    more = "results/a_more/manifest/scenes/shard-00000.parquet"
    jobs, r = dry(work, cfg, target="results/models/instances/model.pt")
    assert jobs["train"] == 1 and more in r.stdout + r.stderr
    jobs, r = dry(work, cfg, target="results/models/resnet50/model.pt")
    assert jobs["train"] == 1 and more not in r.stdout + r.stderr


def test_a_measured_seed_spread_goes_into_the_report(built, tmp_path):
    """bench/seed_spread.py writes <results>/seed_spread/spread.json outside the DAG: once it exists the
    report takes it as an input (and is made again when it changes)."""
    work = own_copy(built[0], tmp_path / "work")
    cfg = built[1]
    _, r = dry(work, cfg, target="all")
    assert "--spread" not in r.stdout + r.stderr
    (work / "results" / "seed_spread").mkdir()
    (work / "results" / "seed_spread" / "spread.json").write_text("{}")
    path = write_config(work / "edited.yaml", cfg)
    r = snakemake("-n", "-p", "all", "--configfile", str(path), workdir=work)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "--spread results/seed_spread/spread.json" in r.stdout + r.stderr
