"""The report reads exactly the files it is given (the workflow names every input); its accuracy
table leads with the ceilings, per-target R² as a fraction of them, and re-render columns."""

import csv
import json
import shutil
from pathlib import Path

import pytest

from psdfactory import PsdError
from psdfactory.manifest import write_shard
from psdfactory.report import ReportInputs, accuracy_table, build_report, rerenders_of

from .conftest import tiny_config


def test_inputs_are_matched_to_the_configured_architectures_and_datasets():
    cfg = tiny_config()
    cfg["train"]["architectures"] = ["resnet18", "efficientnet_b0"]
    two = ["a.json", "b.json"]
    inputs = ReportInputs.from_lists(cfg, two, ["a.png", "b.png"], ["a.csv", "b.csv"], two, ["s.parquet"],
                                     ["r/tiny/contact_sheet.png"], ["compare.json", "compare.png"])
    assert inputs.metrics["efficientnet_b0"].name == "b.json"
    assert inputs.contact_sheets["tiny"] == Path("r/tiny/contact_sheet.png")
    assert inputs.compare[1].name == "compare.png"
    with pytest.raises(PsdError, match="scatters: 1 files for 2 entries"):
        ReportInputs.from_lists(cfg, two, ["a.png"], ["a.csv", "b.csv"], two, ["s.parquet"])
    with pytest.raises(PsdError, match="contact sheets"):
        ReportInputs.from_lists(cfg, two, ["a.png", "b.png"], ["a.csv", "b.csv"], two, ["s.parquet"],
                                ["r/tiny/contact_sheet.png", "r/other/contact_sheet.png"])


def test_dataset_files_are_matched_by_their_folder_whatever_the_config_order():
    """The rule lists a dataset's files in the config's order; the config reaches the report as
    JSON with sorted keys (as the workflow passes every stage's params), so position alone would
    give one dataset another's ceilings and contact sheet."""
    cfg = tiny_config()
    cfg["datasets"] = {"train": cfg["datasets"]["tiny"], "ood_test": cfg["datasets"]["tiny"]}
    rule_order = list(cfg["datasets"])
    as_passed = json.loads(json.dumps(cfg, sort_keys=True))
    assert list(as_passed["datasets"]) != rule_order  # the order the report sees differs
    n = len(as_passed["train"]["architectures"])
    per_arch = (["m.json"] * n, ["s.png"] * n, ["h.csv"] * n, ["b.json"] * n, ["s.parquet"])
    inputs = ReportInputs.from_lists(as_passed, *per_arch, [f"r/{d}/contact_sheet.png" for d in rule_order],
                                     ceilings=[f"r/{d}/ceiling.json" for d in rule_order])
    for d in rule_order:
        assert inputs.ceilings[d] == Path(f"r/{d}/ceiling.json")
        assert inputs.contact_sheets[d] == Path(f"r/{d}/contact_sheet.png")
    with pytest.raises(PsdError, match="ceilings: expected one file in the folder of each dataset"):
        ReportInputs.from_lists(as_passed, *per_arch, ceilings=["r/train/ceiling.json", "r/train/ceiling.json"])


def _fake_results(root, arch: str) -> dict:
    """The files of a trained, evaluated and benchmarked model, without training one."""
    (root / "eval").mkdir(parents=True)
    per = {"r2": 0.5, "mse": 1.0, "mae": 0.8, "rel_err": 0.1}
    metrics = {"arch": arch, "weights": "none (pretrained: none)", "precision": "fp32",
               "datasets": {"tiny": {"n": 3, "split": "all", "overall": dict(per), "d10": per, "d50": per, "d90": per,
                                     "mean_r2": 0.5, "order_violations": 0.0}}}
    (root / "eval" / "metrics.json").write_text(json.dumps(metrics))
    speed = {"images_per_s": 10.0, "ms_per_image": 100.0, "batch": 2}
    bench = {"arch": arch, "weights": "none", "r2_change": 0.0,
             "cpu": {"summary": "test CPU"},
             "results": [{"device": "cpu", "input_size": 32, "params_m": 11.2, "gflops": 0.1, "speedup_batched": 1.0,
                          "fast_key": "fp32", "max_r2_change": 0.005, "skipped": {},
                          "paths": {"fp32": {"name": "fp32 eager", "batch1": speed, "batched": speed},
                                    "fast": {"name": "fp32 eager", "batch1": speed, "batched": speed}}}]}
    (root / "bench.json").write_text(json.dumps(bench))
    with open(root / "history.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["epoch", "train_loss", "val_loss", "val_mae_mm", "lr", "seconds"])
        w.writerows([[1, 1.0, 1.2, 0.9, 1e-3, 1.0], [2, 0.5, 0.7, 0.6, 1e-3, 1.0]])
    return {"metrics": root / "eval" / "metrics.json", "bench": root / "bench.json", "history": root / "history.csv"}


@pytest.mark.slow
def test_report_reads_the_named_files_only(tiny_results, tmp_path):
    cfg, scenes_root = tiny_results
    res = tmp_path / "res"
    shutil.copytree(scenes_root, res)
    dirs = sorted((res / "tiny" / "scenes").iterdir())
    m = res / "tiny" / "manifest"
    shard = m / "scenes" / "shard-00000.parquet"
    write_shard(dirs[:2], res, {"test": 1.0}, shard, m / "particles" / "shard-00000.parquet")
    # a stale shard in the same folder (say, from a run with more scenes): not named, not read
    write_shard(dirs[2:], res, {"test": 1.0}, m / "scenes" / "shard-00001.parquet",
                m / "particles" / "shard-00001.parquet")
    files = _fake_results(tmp_path / "model", "resnet18")
    image = dirs[0] / "image.png"
    cfg = dict(cfg, train=dict(cfg["train"], architectures=["resnet18"]))
    inputs = ReportInputs(metrics={"resnet18": files["metrics"]}, scatters={"resnet18": image},
                          histories={"resnet18": files["history"]}, bench={"resnet18": files["bench"]},
                          manifests=[shard], contact_sheets={"tiny": image})
    html, md = tmp_path / "out" / "report.html", tmp_path / "out" / "report.md"
    build_report(cfg, inputs, html, md)
    text = md.read_text()
    assert "| tiny | 2 | 0 | 0 | 2 |" in text  # the two scenes of the named shard, not three
    assert "![Contact sheet: tiny](figures/contact_sheet_tiny.png)" in text and "| resnet18 |" in text
    assert (tmp_path / "out" / "figures" / "scatter_resnet18.png").read_bytes() == image.read_bytes()
    assert "data:image/png;base64," in html.read_text()

    bench = json.loads(files["bench"].read_text())
    files["bench"].write_text(json.dumps({**bench, "arch": "efficientnet_b0"}))  # another model's benchmark
    with pytest.raises(PsdError, match="the bench of 'efficientnet_b0', not of 'resnet18'"):
        build_report(cfg, inputs, html, md)


def _metrics(r2s):
    per = {n: {"r2": r, "mse": 1.0, "mae": 0.5, "rel_err": 0.1}
           for n, r in zip(("d10", "d50", "d90"), r2s, strict=True)}
    return {**per, "overall": {"r2": 0.98, "mse": 1.0, "mae": 0.5}, "order_violations": 0.0}


def test_accuracy_table_shows_fractions_of_the_ceiling_and_the_rerender_column():
    metrics = {"net": {"datasets": {"train": _metrics([0.36, 0.90, 0.49]), "again": _metrics([-0.5, 0.45, 0.2])}}}
    ceiling = {"visible": {"d10_mm": 0.72, "d50_mm": 0.95, "d90_mm": 0.98}, "sampling": None}
    head, rows = accuracy_table(metrics, "train", ceiling, {"again": "Cycles (again)"})
    assert head[:4] == ["model", "R² d10 (of ceiling)", "R² d50 (of ceiling)", "R² d90 (of ceiling)"]
    assert head[4:7] == [f"R² {n} on Cycles (again) renders" for n in ("d10", "d50", "d90")]
    assert rows[0][:4] == ["ceiling: true sizes of the visible particles", "0.720", "0.950", "0.980"]
    net = rows[1]
    assert net[:4] == ["net", "0.360 (50 %)", "0.900 (95 %)", "0.490 (50 %)"]
    assert net[4:7] == ["-0.500 (-69 %)", "0.450 (47 %)", "0.200 (20 %)"]
    assert all(len(r) == len(head) for r in rows)
    # the footprint ceiling (perfect segmentation) follows, as a fraction of the visible one
    ceiling["footprints"] = {"d10_mm": 0.36, "d50_mm": 0.855, "d90_mm": 0.49}
    head, rows = accuracy_table(metrics, "train", ceiling)
    assert rows[1][:4] == ["ceiling: perfect segmentation (footprints of the true masks)", "0.360 (50 %)",
                           "0.855 (90 %)", "0.490 (50 %)"]
    assert rows[2][0] == "net"
    # no ceiling known: plain R², no ceiling row
    head, rows = accuracy_table(metrics, "train")
    assert rows[0][1] == "0.360" and len(rows) == 1


def test_rerenders_are_found_and_named_by_their_renderer():
    cfg = tiny_config(n_scenes=8, split={"train": 0.5, "val": 0.25, "test": 0.25})
    cfg["datasets"]["again"] = {"rerender_of": {"dataset": "tiny"}, "render": {"backend": "cycles"}}
    cfg["datasets"]["more"] = {"rerender_of": {"dataset": "tiny", "split": ["train", "val"]}}
    assert rerenders_of(cfg, "tiny") == {"again": "Cycles (again)"}  # `more` is training images, not a test
    assert rerenders_of(cfg, "again") == {}
