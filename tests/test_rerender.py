"""Re-render datasets: the scenes of another dataset rendered again, nothing simulated."""

import filecmp

import pytest

from psdfactory import PsdError
from psdfactory import config as psd_config
from psdfactory.io import read_json
from psdfactory.manifest import build_shard
from psdfactory.scene.stages import run_scenes, up_to_date
from psdfactory.seeding import assign_split, scene_entropy

from .conftest import make_scene, tiny_config


def rerender_config(n_scenes=8, train=("tiny",), **over):
    cfg = tiny_config(n_scenes=n_scenes, split={"train": 0.5, "val": 0.25, "test": 0.25})
    raw = {"seed": cfg["seed"], "train": {"datasets": list(train)}, "render": {"resolution": 64},
           "datasets": {"tiny": {k: cfg["datasets"]["tiny"][k] for k in ("n_scenes", "shard_size", "table_size",
                                                                          "count", "size", "split")},
                        "again": {"rerender_of": {"dataset": "tiny"}, "render": {"resolution": 48}, **over}}}
    return psd_config.validate(raw)


def make_rerender(cfg: dict, root):
    """The 8 scenes of `tiny`, then every stage of the re-render `again`: its scene folders."""
    for i in range(8):
        make_scene(cfg, root / "tiny" / "scenes" / f"tiny-{i:06d}", index=i)
    dirs = [root / "again" / "scenes" / f"again-{k:06d}" for k in range(cfg["datasets"]["again"]["n_scenes"])]
    for stage in ("sample", "simulate", "render", "label"):
        params = (getattr(psd_config, f"{stage}_params")(cfg, "again") if stage != "label"
                  else psd_config.label_params(cfg))
        run_scenes(stage, params, dirs)
    return dirs


def test_a_rerender_takes_its_sources_test_scenes_and_settings():
    cfg = rerender_config()
    src, again = cfg["datasets"]["tiny"], cfg["datasets"]["again"]
    test = [i for i in range(8) if assign_split(scene_entropy(cfg["seed"], "tiny", i), src["split"]) == "test"]
    assert psd_config.source_indices(cfg, "again") == test and again["n_scenes"] == len(test) > 0
    assert again["size"] == src["size"] and again["count"] == src["count"]
    assert psd_config.dataset_splits(cfg, "again") == {"test"} and again["split"] == src["split"]
    assert psd_config.render_params(cfg, "again")["resolution"] == 48
    assert psd_config.render_params(cfg, "tiny")["resolution"] == 64
    assert psd_config.render_params(cfg, "again")["exposure"] == psd_config.render_params(cfg, "tiny")["exposure"]
    assert psd_config.simulate_params(cfg, "again") == {"copy_from_source": True}
    capped = rerender_config(n_scenes=1)
    assert psd_config.source_indices(capped, "again") == test[:1]


@pytest.mark.parametrize("over,expect", [
    ({"count": [1, 2]}, "datasets.again: a re-render takes its scenes from its source; drop count"),
    ({"rerender_of": {"dataset": "nope"}}, "datasets.again.rerender_of.dataset: 'nope' is not one"),
    ({"rerender_of": {"dataset": "tiny", "split": "holdout"}}, "has no split 'holdout'"),
    ({"rerender_of": {"dataset": "tiny", "split": ["train", "holdout"]}}, "has no split 'holdout'"),
    ({"render": {"backend": "povray"}}, "datasets.again.render.backend"),
    ({"render": {"exposure": [2, 1]}}, "datasets.again.render.exposure"),
])
def test_bad_rerender_configs_name_the_key(over, expect):
    with pytest.raises(PsdError, match=expect.replace("(", r"\(").replace(".", r"\.")):
        rerender_config(**over)


def test_rerendered_scenes_reuse_particles_poses_and_labels(tmp_path):
    cfg = rerender_config()
    root = tmp_path / "results"
    dirs = make_rerender(cfg, root)
    for k, d in enumerate(dirs):
        spec = read_json(d / "spec.json")
        src = root / "tiny" / "scenes" / spec["source"]["scene_id"]
        assert spec["source"]["index"] == psd_config.source_indices(cfg, "again")[k]
        assert spec["scene_id"] == d.name and spec["dataset"] == "again" and spec["index"] == k
        assert spec["entropy"] == read_json(src / "spec.json")["entropy"]  # the same random streams
        for f in ("geometry.npz", "poses.parquet"):
            assert filecmp.cmp(d / f, src / f, shallow=False), f
        a, b = read_json(d / "labels.json"), read_json(src / "labels.json")
        same = ("d10_mm", "d50_mm", "d90_mm", "d50_v_mm")
        assert [a[k] for k in same] == [b[k] for k in same]
        assert a["resolution"] == 48 and b["resolution"] == 64
    scenes, _ = build_shard(dirs, root, cfg["datasets"]["again"]["split"])
    assert set(scenes.column("split").to_pylist()) == {"test"}
    # the source's poses change → the re-render's copy is out of date; its own render settings are not
    sim = psd_config.sample_params(cfg, "again")
    assert all(up_to_date("sample", psd_config.rerender_scene_params(sim, k), d) for k, d in enumerate(dirs))
    src0 = root / "tiny" / "scenes" / read_json(dirs[0] / "spec.json")["source"]["scene_id"]
    (src0 / "poses.parquet").touch()
    assert not up_to_date("simulate", psd_config.simulate_params(cfg, "again"), dirs[0])
    assert up_to_date("simulate", psd_config.simulate_params(cfg, "again"), dirs[-1]) or len(dirs) == 1


def test_a_missing_source_scene_is_named(tmp_path):
    cfg = rerender_config()
    d = tmp_path / "results" / "again" / "scenes" / "again-000000"
    with pytest.raises(PsdError, match="re-renders tiny-0000.*run the source dataset's stages first"):
        run_scenes("sample", psd_config.sample_params(cfg, "again"), [d])


def test_a_rerender_of_the_training_splits_trains_beside_its_source_and_is_never_a_test(tmp_path):
    """train.datasets [tiny, again] with again = the train and val scenes of tiny rendered again
    (mixed-backend training): each re-rendered scene keeps its source's split, training reads both
    datasets' train/val scenes, and `again` is not among the evaluated datasets (models train on it)."""
    import pyarrow.parquet as pq

    from psdfactory.learn.data import training_rows
    from psdfactory.learn.evaluate import eval_rows
    from psdfactory.manifest import write_shard

    cfg = rerender_config(rerender_of={"dataset": "tiny", "split": ["train", "val"]}, train=["tiny", "again"])
    src = cfg["datasets"]["tiny"]
    split = {i: assign_split(scene_entropy(cfg["seed"], "tiny", i), src["split"]) for i in range(8)}
    assert psd_config.source_indices(cfg, "again") == [i for i in range(8) if split[i] in ("train", "val")]
    root = tmp_path / "results"
    dirs = make_rerender(cfg, root)
    for ds, scene_dirs in (("tiny", sorted((root / "tiny" / "scenes").iterdir())), ("again", dirs)):
        write_shard(scene_dirs, root, psd_config.manifest_params(cfg, ds)["split"],
                    root / ds / "manifest" / "scenes" / "shard-00000.parquet",
                    root / ds / "manifest" / "particles" / "shard-00000.parquet")
    again = pq.read_table(root / "again" / "manifest" / "scenes").to_pylist()
    assert [r["split"] for r in again] == [split[i] for i in psd_config.source_indices(cfg, "again")]
    train, val, _ = training_rows(root, cfg["train"]["datasets"])
    assert sorted(r["scene_id"] for r in train) == sorted([f"tiny-{i:06d}" for i in range(8) if split[i] == "train"]
                                                          + [r["scene_id"] for r in again if r["split"] == "train"])
    assert {r["dataset"] for r in val} == {"tiny", "again"}
    assert psd_config.evaluation_datasets(cfg) == ["tiny"]  # `again` is training scenes only: never a test
    assert [r["split"] for r in eval_rows(root, "tiny")] == ["test"] * sum(v == "test" for v in split.values())


@pytest.mark.parametrize("datasets,expect", [
    (["tiny", "nope"], "train.datasets: 'nope' is not one of the configured datasets"),
    (["tiny", "tiny"], "train.datasets: lists a dataset twice"),
    (["again"], "train.datasets: none of again has 'train' scenes"),
    (["tiny", "again"], "train.datasets: 'again' has no train or val scenes (only test)"),
    (["again", "again"], "train.datasets: none of again, again has 'train' scenes"),  # a duplicate, checked on
])
def test_bad_training_dataset_lists_name_the_problem(datasets, expect):
    with pytest.raises(PsdError, match=expect.replace("(", r"\(").replace(")", r"\)")):
        rerender_config(train=datasets)
