"""The estimator interface: a third estimator, declared by an outside package in the
``psdfactory.estimators`` entry-point group (tests/plugins/psd_meancolour.py), trains, evaluates,
benchmarks, reports, predicts and exports through `learn.estimator.Estimator` alone — none of
train/evaluate/predict/export/benchmark names it."""

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from psdfactory import PsdError

from .test_training import dataset, param_slice  # noqa: F401  (the fixture and the parameter slice)

PLUGINS = Path(__file__).parent / "plugins"
SRC = Path(__file__).parents[1] / "src" / "psdfactory"


@pytest.fixture
def plugin(monkeypatch):
    monkeypatch.syspath_prepend(str(PLUGINS))  # a folder on the path with a .dist-info: "installed"
    yield "meancolour"
    sys.modules.pop("psd_meancolour", None)


def test_the_registry_finds_built_ins_plugins_and_refuses_the_rest(plugin):
    from psdfactory.learn.cnn import CnnRegressor
    from psdfactory.learn.instances.estimator import InstanceEstimator
    from psdfactory.learn.registry import check_architectures, estimator_class

    assert estimator_class("instances") is InstanceEstimator
    assert estimator_class("resnet18") is CnnRegressor and estimator_class("efficientnet_b0") is CnnRegressor
    assert estimator_class(plugin).__name__ == "MeanColour"
    check_architectures(["instances", plugin, "resnet50"])
    with pytest.raises(PsdError, match=r"'resnet5000'.*meancolour"):
        check_architectures(["resnet5000"])
    with pytest.raises(PsdError, match="unknown architecture 'nope'"):
        estimator_class("nope")


def test_no_module_outside_the_estimators_branches_on_an_architecture():
    """train, evaluate, predict, export and benchmark ask the estimator, never `arch == ...`."""
    for f in ("learn/train.py", "learn/evaluate.py", "learn/runtime.py", "deploy/predict.py", "deploy/export.py",
              "deploy/benchmark.py", "report.py"):
        text = (SRC / f).read_text()
        assert '== "instances"' not in text and '!= "instances"' not in text, f


def test_a_third_estimator_plugs_in_end_to_end(plugin, dataset, tmp_path):  # noqa: F811
    from psdfactory.deploy.benchmark import benchmark
    from psdfactory.deploy.export import export
    from psdfactory.deploy.predict import predict_files
    from psdfactory.learn.evaluate import evaluate
    from psdfactory.learn.train import train_from_params

    summary = train_from_params(param_slice(arch=plugin, epochs=3), dataset, tmp_path / "m")
    model = tmp_path / "m" / "model.pt"
    assert summary["arch"] == plugin and model.is_file() and (tmp_path / "m" / "history.csv").is_file()
    assert (tmp_path / "m" / "checkpoints" / "last.pt").is_file()  # the shared loop's resumable checkpoint
    res = evaluate(model, dataset, ["tiny"], tmp_path / "ev", device="cpu")
    m = res["datasets"]["tiny"]
    assert m["n"] == 2 and np.isfinite(m["overall"]["mae"])
    assert json.loads((tmp_path / "ev" / "metrics.json").read_text())["arch"] == plugin
    b = benchmark(model, dataset, "tiny", batch=2, seconds=0.02, repeats=1, device="cpu")
    assert [x["device"] for x in b["results"]] == ["cpu"]  # a device named is the only one timed
    r = b["results"][0]
    assert r["paths"]["fast"]["batched"]["images_per_s"] > 0 and "int8" not in r["paths"]  # it offers no int8
    images = sorted(str(p) for p in (dataset / "tiny" / "scenes").glob("*/image.png"))[:3]
    rows = predict_files(model, images)
    assert len(rows) == 3 and all(not r["error"] and r["d10_mm"] <= r["d90_mm"] for r in rows)
    with pytest.raises(PsdError, match="need a model that finds grains"):
        predict_files(model, images, overlay_dir=tmp_path / "o")
    with pytest.raises(PsdError, match="which the export would replace"):  # the export folder replaces its model
        export(model, model.parent)
    assert model.is_file()
    rep = export(model, tmp_path / "exp")
    assert rep["onnx"]["max_abs_diff"] < 1e-3 and rep["torchscript"]["max_abs_diff"] < 1e-3
    from_onnx = predict_files(tmp_path / "exp" / "model.onnx", images)
    np.testing.assert_allclose([r["d50_mm"] for r in from_onnx], [r["d50_mm"] for r in rows], rtol=1e-4)
