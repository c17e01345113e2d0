import copy

import pytest
import yaml

from psdfactory import PsdError
from psdfactory import config as psd_config
from psdfactory.config import load_config

from .conftest import REPO, tiny_config
from .workflow_helpers import snakemake, write_config


def test_default_and_paper_configs_are_valid():
    cfg = load_config(REPO / "config" / "config.yaml")
    assert cfg["physics"]["timestep_s"] == pytest.approx(1 / 240)  # a default filled in
    assert cfg["datasets"]["train"]["placement"]["candidates"] == 4
    paper = load_config(REPO / "config" / "paper.yaml")
    assert paper["datasets"]["train"]["count"] == [1000, 1350]  # as the paper's published renders
    assert paper["render"]["resolution"] == 512
    full = load_config(REPO / "config" / "cpu-full.yaml")  # trains on both renderers, tests on both
    looks = {d: psd_config.dataset_render(full, d)["backend"] for d in full["train"]["datasets"]}
    assert looks == {"train": "tiny", "train_cycles_train": "cycles"}
    assert psd_config.dataset_splits(full, "train_cycles_train") == {"train", "val"}
    assert "train_cycles_train" not in psd_config.evaluation_datasets(full)
    assert {"train_cycles", "unseen_cycles"} <= set(psd_config.evaluation_datasets(full))


@pytest.mark.parametrize("name", sorted(p.name for p in (REPO / "config").glob("*.yaml")))
def test_every_shipped_config_is_valid(name):
    assert load_config(REPO / "config" / name)["datasets"]


def test_the_general_recipe_is_the_defaults_scenes_plus_the_gravel_look():
    """config/general.yaml says its crushed rock is the default's scenes (the same draws) and its beds
    config/gravel.yaml's look: both copies are checked here, so that an edit of one shows."""
    general, default = load_config(REPO / "config" / "general.yaml"), load_config(REPO / "config" / "config.yaml")
    gravel = load_config(REPO / "config" / "gravel.yaml")
    assert general["seed"] == default["seed"] and general["render"] == default["render"]
    assert general["labels"] == default["labels"] and general["photos"] == default["photos"]
    for name, ds in default["datasets"].items():
        assert general["datasets"][name] == ds, name
    look = {k: v for k, v in gravel["render"].items() if k not in ("backend", "resolution", "cycles")}
    beds = general["datasets"]["beds"]["render"]
    assert {k: beds[k] for k in look} == look
    assert beds["backend"] == "tiny" and beds["resolution"] == default["render"]["resolution"]
    assert {k: general["datasets"]["beds"][k] for k in ("shape", "shape_params", "table_size", "count", "size")} == {
        k: gravel["datasets"]["gravel"][k] for k in ("shape", "shape_params", "table_size", "count", "size")}
    p = psd_config.train_params(general, "instances")
    assert p["epochs"] == 100 and set(p["settings"]["calibration_datasets"]) < set(p["datasets"])
    assert "beds" in p["datasets"] and "beds" not in p["settings"]["calibration_datasets"]


@pytest.mark.parametrize("name", ["paper.yaml", "paper-cpu.yaml"])
def test_the_paper_configs_draw_the_papers_label_statistics(name):
    """The labels (b-axis: the drawn sizes' number-weighted percentiles) of the paper configs'
    scenes average within 10 % of the paper's test labels (d10 2.55, d50 7.31, d90 12.01 mm),
    as bench/paper_labels.py prints; the Table 1 ranges (mu 6-12, sigma 6-8) were 12-37 % off."""
    import numpy as np

    from psdfactory.psd import weighted_percentiles
    from psdfactory.scene.sampling import SampleParams, draw_sizes

    cfg = load_config(REPO / "config" / name)
    assert cfg["labels"]["size_definition"] == "b-axis"
    y = np.array([weighted_percentiles(draw_sizes(SampleParams.from_dict(psd_config.sample_params(cfg, "train", i)))[3],
                                       None) for i in range(150)])
    np.testing.assert_allclose(y.mean(axis=0), [2.55, 7.31, 12.01], rtol=0.10)


@pytest.mark.parametrize(
    "mutate,expect",
    [
        (lambda c: c["datasets"]["train"].update(count=[300, 100]), "datasets.train.count"),
        (lambda c: c["datasets"]["train"].update(n_scene=5), "n_scene"),
        (lambda c: c["datasets"]["train"].update(n_scenes="many"), "datasets.train.n_scenes"),
        (lambda c: c["datasets"]["train"]["size"].update(bounds=[20, 0.1]), "datasets.train.size.bounds"),
        (lambda c: c["datasets"]["train"].update(shape="cube"), "datasets.train.shape"),
        (lambda c: c["render"].update(backend="povray"), "render.backend"),
        (lambda c: c["datasets"]["train"].update(table_size=30), "do not fit"),
        (lambda c: c["datasets"]["train"].update(shape="mesh"), "mesh_files"),
        (lambda c: c.update(datasets={"bad-name": {"n_scenes": 1}}), "bad-name"),
    ],
)
def test_bad_config_names_the_key(tmp_path, mutate, expect):
    cfg = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    mutate(cfg)
    path = tmp_path / "c.yaml"
    path.write_text(yaml.safe_dump(cfg))
    with pytest.raises(PsdError, match="invalid config") as e:
        load_config(path)
    assert expect in str(e.value) and str(e.value).startswith(f"{path}: invalid config")


def test_a_user_mesh_that_is_not_a_solid_is_refused_with_its_key_and_file(tmp_path):
    """Checked when the config is read (Snakemake's parse, check-config): before any scene."""
    from .test_shapes import bad_meshes

    meshes = bad_meshes(tmp_path)
    good, open_box = str(meshes["box.stl"][0]), str(meshes["open_box.obj"][0])
    cfg = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    cfg["datasets"]["train"].update(shape="mesh", shape_params={"mesh_files": [good, open_box]})
    path = write_config(tmp_path / "c.yaml", cfg)
    with pytest.raises(PsdError) as e:
        load_config(path)
    assert (f"datasets.train.shape_params.mesh_files[1]: particle mesh {open_box} is not a closed solid"
            in str(e.value)), str(e.value)
    assert "mesh_files[0]" not in str(e.value)
    cfg["datasets"]["train"]["shape_params"]["mesh_files"] = [good]
    load_config(write_config(path, cfg))


def test_unreadable_config(tmp_path):
    with pytest.raises(PsdError, match="not found"):
        load_config(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("datasets: [unclosed\n")
    with pytest.raises(PsdError, match="not valid YAML"):
        load_config(bad)


def test_stage_params_only_hold_their_slice():
    a = tiny_config()
    b = tiny_config()
    b["render"]["resolution"] = 128
    b["physics"]["friction"] = 0.9
    b["datasets"]["tiny"]["split"] = {"train": 1.0}
    assert psd_config.sample_params(a, "tiny", 0) == psd_config.sample_params(b, "tiny", 0)
    assert psd_config.label_params(a) == psd_config.label_params(b)
    assert psd_config.render_params(a) != psd_config.render_params(b)
    assert psd_config.simulate_params(a) != psd_config.simulate_params(b)
    assert psd_config.manifest_params(a, "tiny") != psd_config.manifest_params(b, "tiny")


def test_the_schema_is_one_file_that_the_package_ships():
    """The workflow and `psdfactory check-config` read this file; a wheel carries it."""
    import fnmatch
    import tomllib

    assert psd_config.SCHEMA.is_file() and not psd_config.SCHEMA.is_symlink()
    data = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]
    assert any(fnmatch.fnmatch(psd_config.SCHEMA.name, pat) for pat in data["psdfactory"])


def test_shards():
    cfg = tiny_config(n_scenes=5, shard_size=2)
    assert psd_config.n_shards(cfg, "tiny") == 3
    assert list(psd_config.shard_indices(cfg, "tiny", 2)) == [4]


def test_snakemake_refuses_bad_config_before_any_job(tmp_path):
    cfg = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    cfg["datasets"]["train"]["size"]["sigma"] = [8, 6]
    cfg["results"] = "results"
    path = write_config(tmp_path / "broken.yaml", cfg)
    # a real run (not -n) of one sample job: had the config passed, its folder would exist
    r = snakemake("-j1", "results/train/scenes/train-000000/spec.json", "--configfile", str(path), workdir=tmp_path)
    assert r.returncode != 0
    out = r.stdout + r.stderr
    assert "datasets.train.size.sigma" in out and "lo <= hi" in out and f"{path}: invalid config" in out
    assert not (tmp_path / "results").exists()


@pytest.mark.parametrize("section, key", [("markings", "veins"), ("markings", "speckle_mm"),
                                          ("distractors", "brightness")])
def test_a_reversed_range_of_the_markings_or_distractors_is_refused_by_name(section, key):
    cfg = tiny_config()
    cfg["render"][section] = {"probability": 0.5, key: [0.9, 0.3]}
    with pytest.raises(PsdError, match=rf"render\.{section}\.{key}: \[0\.9, 0\.3\] must have lo <= hi"):
        psd_config.validate(cfg)


def test_a_dataset_of_training_scenes_only_is_never_evaluated():
    """More training scenes without a test split (in train.datasets, or only the instance
    estimator's) are not scored: evaluated whole, they would be read on the scenes the models
    learnt. A dataset without a test split that nothing trains on is evaluated whole."""
    cfg = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    more = dict(cfg["datasets"]["train"], n_scenes=20, split={"train": 0.85, "val": 0.15})
    cfg["datasets"].update(more=more, spare=dict(more))
    cfg["train"]["datasets"] = ["train", "more"]
    cfg = psd_config.validate(cfg)
    evaluated = psd_config.evaluation_datasets(cfg)
    assert "more" not in evaluated and "spare" in evaluated
    assert {"train", "ood_test", "train_cycles"} <= set(evaluated)
    cfg["train"]["datasets"] = ["train"]
    cfg["train"]["instances"]["datasets"] = ["train", "spare"]
    assert "spare" not in psd_config.evaluation_datasets(cfg) and "more" in psd_config.evaluation_datasets(cfg)


def test_a_config_with_nothing_to_evaluate_on_is_refused():
    cfg = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    cfg["datasets"] = {"train": dict(cfg["datasets"]["train"], split={"train": 0.85, "val": 0.15})}
    cfg["photos"] = {}
    with pytest.raises(PsdError, match="datasets: none to evaluate the models on"):
        psd_config.validate(cfg)


@pytest.mark.parametrize("train, expect", [
    ({"input_size": {"inception_v3": 64}}, "train.input_size.inception_v3 = 64 is below the 75 px"),
    ({"crop": 64}, "train.crop = 64 is below the 75 px that inception_v3 accepts"),
    ({"crop": 200, "input_size": {"inception_v3": 299}}, "train.crop = 200: inception_v3 at 299 px trains its"),
])
def test_an_input_or_window_a_network_cannot_take_is_refused_when_the_config_is_read(train, expect):
    """Not hours later, when the training job starts after the scenes."""
    cfg = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    cfg["train"].update(train)
    with pytest.raises(PsdError, match=expect):
        psd_config.validate(copy.deepcopy(cfg))
    cfg["train"]["architectures"] = ["resnet50", "instances"]  # without InceptionV3 each is fine
    psd_config.validate(cfg)
