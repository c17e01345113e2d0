"""One tiny end-to-end run of the Snakemake workflow (system-level)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from psdfactory.config import load_config
from psdfactory.scene.render.cycles import DEFAULT_PYTHON

from .test_photo_sets import make_photo_set, photo_spec
from .workflow_helpers import REPO, snakemake, write_config

# the report's side-by-side of both render backends needs Blender (`make test` installs it)
HAS_BLENDER = DEFAULT_PYTHON.is_file() or os.environ.get("PSD_BLENDER_PYTHON") or os.environ.get("PSD_REQUIRE_BLENDER")
COMPARE = 2 if HAS_BLENDER else 0

pytestmark = pytest.mark.workflow
PLUGINS = Path(__file__).parent / "plugins"
# the default config's instance read-out and views, as `make demo` trains them
DEFAULT_INSTANCES = load_config(REPO / "config" / "config.yaml")["train"]["instances"]

TINY = {
    "seed": 7,  # gives the 5 train scenes 2 train / 2 val / 1 test
    "datasets": {
        "train": {
            "n_scenes": 5, "shard_size": 2, "table_size": 50, "count": [20, 30],
            "split": {"train": 0.5, "val": 0.25, "test": 0.25},
            "size": {"mean": [4, 7], "sigma": [2, 3], "bounds": [1, 10]},
        },
        "ood": {
            "n_scenes": 1, "shard_size": 4, "table_size": 50, "count": [20, 25], "shape": "granule",
            "split": {"test": 1.0}, "size": {"mean": [6, 8], "sigma": [1, 2], "bounds": [1, 10]},
        },
        # the train dataset's test scene rendered again: by Cycles where Blender is installed
        "again": {"rerender_of": {"dataset": "train"},
                  "render": {"backend": "cycles" if COMPARE else "tiny", "light_elevation_deg": [30, 40]}},
    },
    "render": {"resolution": 48},
    "train": {
        "epochs": 1, "batch_size": 2, "precision": "fp32", "pretrained": "none",
        "lr_schedule": "onecycle", "size_cells": 1.0,  # the default config's recipe
        # the paper's three CNNs, the instance estimator, and a third kind from an outside package
        # (tests/plugins: declared in the psdfactory.estimators entry-point group, on PYTHONPATH)
        "architectures": ["resnet50", "inception_v3", "efficientnet_b0", "instances", "meancolour"],
        "input_size": {"resnet50": 32, "inception_v3": 75, "efficientnet_b0": 32, "instances": 32, "meancolour": 32},
        "instances": {k: DEFAULT_INSTANCES[k] for k in ("readout", "tta")},
    },
    "benchmark": {"batch_size": 2, "seconds": 0.05, "repeats": 1},
    "show": {"compare_backends": COMPARE},
}


def test_tiny_workflow_end_to_end(tmp_path):
    # a photo set (config `photos`): one small photo with its reference mask and d-values, made here
    photos = {"field": photo_spec(make_photo_set(tmp_path / "photos", n=1, size=(120, 120)))}  # 60 mm a side
    cfgfile = write_config(tmp_path / "tiny.yaml", dict(TINY, results=str(tmp_path / "results"), photos=photos))
    # PyTorch's portable path, as on a CPU without AVX-512/bf16/VNNI: the run must not care
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(PLUGINS), os.environ.get("PYTHONPATH")]))}
    r = snakemake("-j2", "--configfile", str(cfgfile), workdir=tmp_path, env={**env, "ATEN_CPU_CAPABILITY": "avx2"})
    assert r.returncode == 0, r.stderr[-3000:]
    res = tmp_path / "results"
    scenes = pq.read_table(res / "train" / "manifest" / "scenes")
    assert sorted(scenes.column("scene_id").to_pylist()) == [f"train-{i:06d}" for i in range(5)]
    assert len(list((res / "train" / "manifest" / "scenes").glob("shard-*.parquet"))) == 3
    # the datasets, the models and their figures, and the run lock the workflow held (README: two runs)
    assert sorted(p.name for p in res.iterdir()) == [".psdfactory.lock", "again", "bench", "eval", "models", "ood",
                                                     "report", "train"]
    # the re-render: the train dataset's one test scene, same poses, other renderer, nothing simulated
    again = pq.read_table(res / "again" / "manifest" / "scenes").to_pylist()
    test = [r for r in scenes.to_pylist() if r["split"] == "test"]
    assert len(again) == len(test) == 1 and again[0]["d50_mm"] == test[0]["d50_mm"]
    assert again[0]["render_backend"] == ("cycles" if COMPARE else "tiny")
    src = res / "train" / "scenes" / test[0]["scene_id"]
    copied = res / "again" / "scenes" / "again-000000" / "poses.parquet"
    assert copied.read_bytes() == (src / "poses.parquet").read_bytes()
    assert "takes its settled poses from" in (res / "again" / "logs" / "simulate" / "again-000000.log").read_text()
    for ds in ("train", "ood", "again"):
        ceiling = json.loads((res / ds / "ceiling.json").read_text())
        assert ceiling["n_scenes"] >= 1 and "footprints" in ceiling
    ood = pq.read_table(res / "ood" / "manifest" / "scenes")
    assert ood.column("split").to_pylist() == ["test"] and ood.column("shape_type").to_pylist() == ["granule"]
    parts = pq.read_table(res / "train" / "manifest" / "particles")
    assert parts.num_rows == sum(scenes.column("n_particles").to_pylist())
    assert (res / "train" / "contact_sheet.png").is_file()
    assert (res / "train" / "logs" / "simulate" / "train-000001.log").read_text().count("settled") >= 1
    # the training half: one model per architecture, evaluation, benchmark, report
    for arch in ("resnet50", "inception_v3", "efficientnet_b0"):
        assert (res / "models" / arch / "model.pt").is_file()
        metrics = json.loads((res / "eval" / arch / "metrics.json").read_text())
        assert set(metrics["datasets"]) == {"train", "ood", "again"}
        bench = json.loads((res / "bench" / f"{arch}.json").read_text())
        assert bench["cpu"]["forced_isa"] == "avx2" and not bench["cpu"]["native_bf16"]
        assert {"fp32", "channels_last", "fast"} <= set(bench["results"][0]["paths"])
    # the instance estimator goes the same way, with its own figures
    assert (res / "models" / "instances" / "model.pt").is_file()
    metrics = json.loads((res / "eval" / "instances" / "metrics.json").read_text())
    assert set(metrics["datasets"]) == {"train", "ood", "again"}
    assert all("f1" in m["segmentation"] and "raw" in m for m in metrics["datasets"].values())
    bench = json.loads((res / "bench" / "instances.json").read_text())
    assert {"fp32", "channels_last", "fast"} <= set(bench["results"][0]["paths"])
    # the plug-in estimator: trained, evaluated, benchmarked and reported like the built-in ones
    metrics = json.loads((res / "eval" / "meancolour" / "metrics.json").read_text())
    assert metrics["arch"] == "meancolour" and set(metrics["datasets"]) == {"train", "ood", "again"}
    assert (res / "bench" / "meancolour.json").is_file()
    html = (res / "report" / "report.html").read_text()
    assert "Inference speed" in html and "efficientnet_b0" in html and "Instance estimator" in html
    assert "meancolour" in html
    # every model on the photo set: its figures, a row per photo, an overlay each; the report shows them
    for arch in TINY["train"]["architectures"]:
        d = res / "eval" / arch / "photos" / "field"
        m = json.loads((d / "metrics.json").read_text())
        assert m["arch"] == arch and list(m["photos"]) == ["a.png"] and (d / "overlays" / "a.png").is_file()
        assert m["finds_grains"] == (arch == "instances") and ("detection" in m["pooled"]) == (arch == "instances")
        assert m["photos"]["a.png"]["reference_mm"] == {"d10": 4.0, "d50": 6.0, "d90": 8.0}
        assert len((d / "photos.csv").read_text().splitlines()) == 2
    assert "<h2>Photos: field</h2>" in html and "photos: 1 photo vs reference (ellipse-minor)" in html
    # and users predict with it and export it through the CLI
    image = str(res / "train" / "scenes" / "train-000000" / "image.png")
    model = str(res / "models" / "meancolour" / "model.pt")
    cli = [sys.executable, "-m", "psdfactory.cli"]
    p = subprocess.run([*cli, "predict", "--model", model, "--out", str(tmp_path / "p.csv"), image], env=env,
                       capture_output=True, text=True)
    assert p.returncode == 0 and "meancolour" in p.stderr, p.stderr[-2000:]
    p = subprocess.run([*cli, "export", "--model", model, "--out-dir", str(tmp_path / "exp")], env=env,
                       capture_output=True, text=True)
    assert p.returncode == 0 and (tmp_path / "exp" / "model.onnx").is_file(), p.stderr[-2000:]
    assert f"R² d50 on {'Cycles' if COMPARE else 'TinyRenderer'} (again) renders" in html
    if COMPARE:
        rows = json.loads((res / "report" / "backends" / "compare.json").read_text())["scenes"]
        assert [r["scene_id"] for r in rows] == ["train-000000", "train-000001"]
        assert all(r["mask_agreement_off_edges"] > 0.99 for r in rows)
        assert "TinyRenderer and Blender Cycles" in html
    # a second run has nothing to do
    r = snakemake("-n", "--configfile", str(cfgfile), workdir=tmp_path, env=env)
    assert r.returncode == 0 and "Nothing to be done" in r.stdout + r.stderr


def test_lint_is_clean(tmp_path):
    r = snakemake("--lint", "--configfile", str(REPO / "config" / "config.yaml"), workdir=tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
