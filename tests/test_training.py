"""Training, resume, evaluation, benchmark, report, predict and export on a tiny dataset."""

import json
import logging
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
import torch

from psdfactory import PsdError
from psdfactory import config as psd_config

from .conftest import split_dataset, tiny_config

SPLITS = ["train"] * 6 + ["val"] * 2 + ["test"] * 2


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """10 tiny scenes at 32 px with a fixed train/val/test split, and their manifest."""
    root = tmp_path_factory.mktemp("res")
    split_dataset(root, SPLITS)
    return root


def param_slice(**over) -> dict:
    p = psd_config.train_params(tiny_config(), "resnet18")  # the schema's defaults, then these
    p.update(pretrained="none", epochs=6, batch_size=3, lr=3e-3, input_size=32, precision="fp32", seed=1,
             early_stopping_patience=50)
    p.update(over)
    return p


def params(**over):
    from psdfactory.learn.train import TrainParams

    return TrainParams.from_dict(param_slice(**over))


@pytest.fixture(scope="module")
def trained(dataset, tmp_path_factory):
    from psdfactory.learn.train import train

    out = tmp_path_factory.mktemp("model")
    summary = train(params(), dataset, out)
    return out, summary


def test_fp16_training_runs_with_its_loss_scaler_and_keeps_it_in_the_resumable_checkpoint(dataset, tmp_path):
    """train.precision fp16 (a GPU without bf16; here on the CPU, which autocasts fp16 too): the
    training steps with its loss scaler to a model, and last.pt holds the scaler's state for a resume."""
    from psdfactory.learn.runtime import load_checkpoint
    from psdfactory.learn.train import train

    summary = train(params(precision="fp16", epochs=2), dataset, tmp_path)
    assert summary["precision"] == "fp16" and (tmp_path / "model.pt").is_file()
    ck = load_checkpoint(tmp_path / "checkpoints" / "last.pt", "training checkpoint")
    assert ck["grad_scaler"]["scale"] > 0  # GradScaler.state_dict(), plain numbers


@pytest.mark.slow
def test_training_lowers_loss_and_writes_outputs(trained):
    import csv

    out, summary = trained
    rows = list(csv.DictReader(open(out / "history.csv")))
    assert len(rows) == 6
    losses = [float(r["train_loss"]) for r in rows]
    assert min(losses[1:]) < 0.7 * losses[0]  # 6 scenes in batches of 3: the loss drops, then wanders
    assert (out / "model.pt").is_file() and (out / "checkpoints" / "best.pt").is_file()
    assert any((out / "tensorboard").iterdir())
    assert summary["arch"] == "resnet18" and summary["input_size"] == 32
    assert summary["best_epoch"] == 1 + int(np.argmin([float(r["val_loss"]) for r in rows]))


@pytest.mark.slow
def test_resume_after_interruption_matches_uninterrupted(dataset, trained, tmp_path, monkeypatch, caplog):
    import csv

    from psdfactory.learn import cnn as train_mod

    out = tmp_path / "m"
    real = train_mod.run_epoch
    calls = {"n": 0}

    def crash_on_third(*a, **k):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(train_mod, "run_epoch", crash_on_third)
    with pytest.raises(KeyboardInterrupt):
        train_mod.CnnRegressor.train(params(), dataset, out)
    assert not (out / "model.pt").exists()
    monkeypatch.setattr(train_mod, "run_epoch", real)
    caplog.set_level(logging.INFO, logger="psdfactory")
    train_mod.CnnRegressor.train(params(), dataset, out)
    assert any("resuming resnet18 from epoch 3" in m for m in caplog.messages)
    resumed = [float(r["train_loss"]) for r in csv.DictReader(open(out / "history.csv"))]
    straight = [float(r["train_loss"]) for r in csv.DictReader(open(trained[0] / "history.csv"))]
    np.testing.assert_allclose(resumed, straight, rtol=1e-5)


@pytest.mark.slow
def test_sigkill_mid_training_and_at_the_model_then_the_rerun_resumes_to_the_same_model(dataset, tmp_path):
    """`psdfactory train` killed with SIGKILL (nothing gets to clean up) as it renames its
    resume checkpoint after epoch 3, and as it renames model.pt: no model.pt is left, and the
    same command resumes from checkpoints/last.pt to the uninterrupted run's losses and model."""
    import csv

    from .sigkill import psdfactory

    def train(out, **kw):
        return psdfactory(["train", "--params", json.dumps(param_slice()), "--results", str(dataset),
                           "--out-dir", str(out), "--threads", "1"], **kw)

    def losses(out):
        return [(float(r["train_loss"]), float(r["val_loss"])) for r in csv.DictReader(open(out / "history.csv"))]

    ref, log = tmp_path / "ref", tmp_path / "renames.txt"
    r = train(ref, record=log)
    assert r.returncode == 0, r.stderr[-3000:]
    renamed = log.read_text().split()
    made = {p for p in ref.rglob("*") if p.is_file() and "tensorboard" not in p.parts}  # (event logs: appended)
    assert made <= {Path(f) for f in renamed}, "a training output not written through a rename"
    ckpts = [k for k, f in enumerate(renamed, 1) if f.endswith("last.pt")]
    model = renamed.index(str(ref / "model.pt")) + 1
    for k, resumes in ((ckpts[2], "from epoch 3"), (model, "from epoch 7")):
        out = tmp_path / f"kill{k}"
        r = train(out, kill_at=k)
        assert r.returncode == -9 and not (out / "model.pt").exists(), r.stderr[-2000:]
        r = train(out)
        assert r.returncode == 0 and f"resuming resnet18 {resumes}" in r.stderr, r.stderr[-3000:]
        assert losses(out) == losses(ref)
        assert (out / "model.pt").read_bytes() == (ref / "model.pt").read_bytes()


@pytest.mark.slow
def test_other_settings_do_not_resume(dataset, trained, tmp_path, caplog):
    from psdfactory.learn.train import train

    out = tmp_path / "m"
    shutil.copytree(trained[0], out)
    caplog.set_level(logging.INFO, logger="psdfactory")
    train(params(epochs=1, lr=1e-3), dataset, out)
    assert any("ignoring" in m for m in caplog.messages) and not any("resuming" in m for m in caplog.messages)


@pytest.mark.slow
def test_needs_train_and_val(dataset, tmp_path):
    from psdfactory.learn.train import train

    with pytest.raises(PsdError, match="0 val scenes"):
        import pyarrow.parquet as pq2

        root = tmp_path / "r"
        shutil.copytree(dataset, root)
        f = root / "tiny" / "manifest" / "scenes" / "shard-00000.parquet"
        t = pq2.read_table(f)
        t = t.set_column(t.schema.get_field_index("split"), "split", pa.array(["train"] * 10))
        pq2.write_table(t, f)
        train(params(), root, tmp_path / "m")


@pytest.mark.slow
def test_evaluate_benchmark_report(dataset, trained, tmp_path):
    from psdfactory.deploy.benchmark import benchmark
    from psdfactory.io import write_json
    from psdfactory.learn.evaluate import evaluate, plot_history
    from psdfactory.report import ReportInputs, build_report

    model_dir, _ = trained
    root = tmp_path / "res"
    shutil.copytree(dataset, root)
    shutil.copytree(model_dir, root / "models" / "resnet18")
    ev = root / "eval" / "resnet18"
    res = evaluate(root / "models" / "resnet18" / "model.pt", root, ["tiny"], ev)
    m = res["datasets"]["tiny"]
    assert m["n"] == 2 and m["split"] == "test" and m["order_violations"] == 0.0
    assert set(m["overall"]) == {"r2", "mse", "mae"}
    preds = (ev / "predictions.csv").read_text().splitlines()
    assert len(preds) == 3 and "pred_d50_mm" in preds[0]
    plot_history(root / "models" / "resnet18" / "history.csv", "resnet18", ev / "loss_curve.png")
    from PIL import Image

    with Image.open(ev / "loss_curve.png") as im:  # a 5 × 3.5 in figure at 100 dpi
        assert im.format == "PNG" and im.size == (500, 350)
        assert len(np.unique(np.asarray(im.convert("L")))) > 2  # curves, axes and labels: not a blank canvas

    b = benchmark(root / "models" / "resnet18" / "model.pt", root, "tiny", batch=2, seconds=0.05, repeats=2)
    r = b["results"][0]
    assert r["paths"]["fp32"]["batch1"]["images_per_s"] > 0 and r["paths"]["fast"]["batched"]["batch"] == 2
    assert r["params_m"] == pytest.approx(11.18, abs=0.05) and r["gflops"] > 0
    assert abs(b["r2_change"]) < 0.05
    from psdfactory.learn.capability import detect

    if detect().onnxruntime:  # ONNX Runtime fp32 and int8 are timed on any CPU
        int8 = r["paths"]["int8"]
        assert int8["batched"]["images_per_s"] > 0 and int8["calibration_images"] > 0
        assert abs(int8["accuracy"]["overall"]["r2"] - r["paths"]["fp32"]["accuracy"]["overall"]["r2"]) < 0.1
        assert r["paths"]["ort_fp32"]["accuracy"]["overall"]["r2"] == pytest.approx(
            r["paths"]["fp32"]["accuracy"]["overall"]["r2"], abs=1e-4)
    assert r["paths"]["fast"]["name"] == r["paths"][r["fast_key"]]["name"]
    write_json(root / "bench" / "resnet18.json", b)

    cfg = tiny_config()
    cfg["train"]["architectures"] = ["resnet18"]
    html, md = root / "report" / "report.html", root / "report" / "report.md"
    (root / "tiny" / "contact_sheet.png").write_bytes((ev / "scatter.png").read_bytes())
    inputs = ReportInputs(metrics={"resnet18": ev / "metrics.json"}, scatters={"resnet18": ev / "scatter.png"},
                          histories={"resnet18": root / "models" / "resnet18" / "history.csv"},
                          bench={"resnet18": root / "bench" / "resnet18.json"},
                          manifests=[root / "tiny" / "manifest" / "scenes" / "shard-00000.parquet"],
                          contact_sheets={"tiny": root / "tiny" / "contact_sheet.png"})
    build_report(cfg, inputs, html, md)
    text = html.read_text()
    assert "data:image/png;base64," in text and "R² overall" in text and "resnet18" in text
    assert "Warning:" not in text  # pretrained: none is no fallback to warn about
    assert "| resnet18 |" in md.read_text()

    # `psdfactory report` killed with SIGKILL at each of its renames, then run again
    from .sigkill import kill_at_every_rename

    given = {"metrics": ev / "metrics.json", "scatters": ev / "scatter.png", "bench": root / "bench" / "resnet18.json",
             "histories": root / "models" / "resnet18" / "history.csv",
             "contact-sheets": root / "tiny" / "contact_sheet.png",
             "manifests": root / "tiny" / "manifest" / "scenes" / "shard-00000.parquet"}

    def prepare(folder):
        args = ["report", "--params", json.dumps(cfg)]
        for i, (flag, src) in enumerate(given.items()):
            dst = folder / "in" / str(i) / src.parent.name / src.name  # a dataset's file stays in its folder
            dst.parent.mkdir(parents=True)
            shutil.copyfile(src, dst)
            args += [f"--{flag}", str(dst)]
        return args + ["--html", str(folder / "report" / "report.html"), "--md", str(folder / "report" / "report.md")]

    def undated(rel, data):  # "Generated 2025-06-01 10:00 by ...": the minute it was made
        dated = rel.startswith("report/")
        return re.sub(rb"Generated \d{4}-\d\d-\d\d \d\d:\d\d", b"Generated", data) if dated else data

    assert kill_at_every_rename(tmp_path / "killed", prepare, normalise=undated) >= 6  # figures, copies, md, html


@pytest.mark.slow
def test_predict_good_and_bad_files(dataset, trained, tmp_path, capsys):
    from psdfactory.cli import main

    model = trained[0] / "model.pt"
    imgs = tmp_path / "imgs"
    imgs.mkdir()
    shutil.copy(dataset / "tiny" / "scenes" / "tiny-000008" / "image.png", imgs / "a.png")
    shutil.copy(dataset / "tiny" / "scenes" / "tiny-000009" / "image.png", imgs / "c.png")
    (imgs / "b.png").write_bytes(b"not a png at all")
    out = tmp_path / "pred.json"
    code = main(["predict", "--model", str(model), "--out", str(out), str(imgs), str(tmp_path / "missing.png")])
    assert code == 1
    rows = json.loads(out.read_text())
    assert [r["image"].rsplit("/", 1)[-1] for r in rows] == ["a.png", "b.png", "c.png", "missing.png"]
    good = [r for r in rows if not r["error"]]
    assert len(good) == 2 and all(r["d10_mm"] <= r["d50_mm"] <= r["d90_mm"] for r in good)
    assert "not a readable image" in rows[1]["error"] and "missing image" in rows[3]["error"]
    captured = capsys.readouterr()
    assert "expects images at" in captured.err and "2 of 4 images failed (each one's row says why)" in captured.err
    # the same image given with its scale: rescaled to the model's scale, same prediction
    px = json.loads((dataset / "tiny" / "scenes" / "tiny-000008" / "render.json").read_text())["mm_per_px"]
    assert main(["predict", "--model", str(model), "--mm-per-px", str(px), "--out", str(tmp_path / "p.csv"),
                 str(imgs / "a.png")]) == 0
    line = (tmp_path / "p.csv").read_text().splitlines()[1].split(",")
    assert float(line[2]) == pytest.approx(good[0]["d50_mm"], rel=1e-4)


def test_prepare_rescales_to_the_model_scale():
    from psdfactory.deploy.predict import network_scale, prepare

    meta = {"mm_per_px": 0.5, "image_resolution": 256, "input_size": 128}
    assert network_scale(meta) == 1.0
    img = np.zeros((100, 300, 3), np.uint8)
    assert prepare(img, meta, mm_per_px=0.5).shape == (1, 3, 50, 150)
    assert prepare(img, meta, mm_per_px=None).shape == (1, 3, 128, 128)


@pytest.mark.slow
def test_export_matches_pytorch(trained, tmp_path):
    from psdfactory.deploy.export import export

    rep = export(trained[0] / "model.pt", tmp_path / "exp")
    assert (tmp_path / "exp" / "model.onnx").is_file() and (tmp_path / "exp" / "model.torchscript.pt").is_file()
    assert rep["onnx"]["max_abs_diff"] < 1e-3 and rep["torchscript"]["max_abs_diff"] < 1e-3
    ts = torch.jit.load(str(tmp_path / "exp" / "model.torchscript.pt"))
    out = ts(torch.randn(3, 3, 32, 32))
    assert out.shape == (3, 3)
    # the same model exported twice (two commands): the same files, byte for byte
    for run in ("a", "b"):
        r = subprocess.run([sys.executable, "-m", "psdfactory.cli", "export", "--model", str(trained[0] / "model.pt"),
                            "--out-dir", str(tmp_path / run)], capture_output=True, text=True)
        assert r.returncode == 0, r.stderr[-2000:]
    for f in ("model.torchscript.pt", "model.onnx", "meta.json"):
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes(), f


@pytest.mark.slow
def test_a_failed_export_leaves_the_folder_as_it_was(dataset, trained, tmp_path):
    """An export is one unit: inputs checked first, files made in a hidden folder and swapped in
    whole, so a failure (bad --int8 results root, an int8 model refused) leaves an earlier export
    untouched and no half of a new one beside it."""
    from psdfactory.deploy.export import export

    model, out = trained[0] / "model.pt", tmp_path / "deploy"
    export(model, out)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    r = subprocess.run([sys.executable, "-m", "psdfactory.cli", "export", "--model", str(model), "--out-dir", str(out),
                        "--int8", str(tmp_path / "nonexistent")], capture_output=True, text=True)
    err = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(err) == 1 and "--int8" in err[0] and "no manifest" in err[0], r.stderr
    with pytest.raises(PsdError, match="int8 model refused"):
        export(model, out, int8_results=dataset, dataset="tiny", max_r2_change=-1)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["deploy"]  # no staging folder left behind
    (tmp_path / "file").write_text("x")
    with pytest.raises(PsdError, match="is a file; give a folder"):
        export(model, tmp_path / "file")
    with pytest.raises(PsdError, match="holds the model"):
        export(model, trained[0])


@pytest.mark.slow
def test_int8_export_is_checked_and_predicts_like_pytorch(dataset, trained, tmp_path):
    from psdfactory.deploy.export import export
    from psdfactory.deploy.predict import predict_files

    model = trained[0] / "model.pt"
    # a budget no model can meet: refused, and nothing left under the final name
    with pytest.raises(PsdError, match="int8 model refused"):
        export(model, tmp_path / "strict", int8_results=dataset, dataset="tiny", max_r2_change=-1)
    assert not list((tmp_path / "strict").glob("*int8*"))
    # a budget every model meets (per-target R² on 2 near-equal test scenes runs to the thousands)
    rep = export(model, tmp_path / "exp", int8_results=dataset, dataset="tiny", max_r2_change=float("inf"))
    assert rep["int8"]["calibration_images"] > 0 and (tmp_path / "exp" / "model.int8.onnx").is_file()
    img = dataset / "tiny" / "scenes" / "tiny-000008" / "image.png"
    ref = predict_files(model, [str(img)])[0]
    for name in ("model.onnx", "model.int8.onnx"):
        got = predict_files(tmp_path / "exp" / name, [str(img)])[0]
        tol = 1e-3 if name == "model.onnx" else 0.1 * ref["d90_mm"]
        assert all(abs(got[k] - ref[k]) <= tol for k in ("d10_mm", "d50_mm", "d90_mm")), (name, got, ref)
    (tmp_path / "exp" / "meta.json").unlink()
    with pytest.raises(PsdError, match="meta.json"):
        predict_files(tmp_path / "exp" / "model.onnx", [str(img)])


def test_train_params_slice_ignores_scene_settings():
    a = tiny_config()
    b = tiny_config()
    b["render"]["resolution"] = 512
    assert psd_config.train_params(a, "resnet50") == psd_config.train_params(b, "resnet50")
    b["train"]["epochs"] = 3
    assert psd_config.train_params(a, "resnet50") != psd_config.train_params(b, "resnet50")
    assert psd_config.train_params(a, "inception_v3")["input_size"] == 299


def test_load_model_rejects_other_files(tmp_path):
    from psdfactory.learn.runtime import load_model

    bad = tmp_path / "x.pt"
    torch.save({"hello": 1}, bad)
    with pytest.raises(PsdError, match="not a psdfactory model"):
        load_model(bad)
    with pytest.raises(PsdError, match="not found"):
        load_model(tmp_path / "none.pt")


class _WritesAFile:
    """Unpickling this calls open(path, "w"): a stand-in for code hidden in a model file."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return (open, (self.path, "w"))


def test_a_crafted_model_file_is_refused_and_runs_nothing(tmp_path, capsys):
    from psdfactory.cli import main
    from psdfactory.learn.runtime import load_model

    victim = tmp_path / "pwned.txt"
    evil = tmp_path / "model.pt"
    torch.save({"meta": {"arch": "resnet18"}, "state_dict": {}, "payload": _WritesAFile(victim)}, evil)
    assert not victim.exists()
    with pytest.raises(PsdError, match="refused: it holds Python objects.*could run code "
                                       r"\(Unsupported global: GLOBAL io.open\).*weights_only=True.*runs nothing") as e:
        load_model(evil)
    msg = str(e.value)
    assert str(evil) in msg and "\x1b" not in msg and "weights_only` set to `False`" not in msg
    img = tmp_path / "a.png"
    from PIL import Image

    Image.new("RGB", (32, 32)).save(img)
    assert main(["predict", "--model", str(evil), str(img)]) == 2
    assert "refused" in capsys.readouterr().err
    assert not victim.exists()  # nothing in the file ran


def test_the_accuracy_budget_holds_every_target_not_the_pooled_r2():
    """A path that keeps the pooled R² (d10..d90 together: near 1 whatever one target does) but moves d90's
    R² by 0.13 — as int8 did to a default ResNet-50 — is over the budget."""
    from psdfactory.deploy.benchmark import choose_fast
    from psdfactory.deploy.quantize import MAX_R2_CHANGE, r2_change
    from psdfactory.learn.metrics import regression_metrics

    rng = np.random.default_rng(0)
    y = np.column_stack([rng.uniform(2, 4, 14), rng.uniform(7, 10, 14), rng.uniform(14, 16, 14)])
    p32 = y + rng.normal(0, 0.3, y.shape)
    p8 = p32.copy()
    p8[:, 2] += rng.normal(0, 0.25, 14)  # d90 only, a little noisier
    m32, m8 = regression_metrics(y, p32), regression_metrics(y, p8)
    assert abs(m8["overall"]["r2"] - m32["overall"]["r2"]) < MAX_R2_CHANGE  # the pooled R² hardly moves ...
    change, target = r2_change(m8, m32)
    assert target == "d90" and change == pytest.approx(m8["d90"]["r2"] - m32["d90"]["r2"])
    assert abs(change) > MAX_R2_CHANGE  # ... d90's does
    assert r2_change(m32, m32) == (0.0, "d10")
    paths = {"fp32": {"batched": {"images_per_s": 10}, "r2_change": 0.0},
             "int8": {"batched": {"images_per_s": 80}, "r2_change": change}}
    assert choose_fast(paths) == "fp32"


def test_fast_path_is_the_fastest_within_the_accuracy_budget():
    from psdfactory.deploy.benchmark import choose_fast

    def path(ips, dr2):
        return {"batched": {"images_per_s": ips}, "r2_change": dr2}

    paths = {"fp32": path(10, 0.0), "bf16": path(30, -0.001), "int8": path(80, -0.002)}
    assert choose_fast(paths) == "int8"
    paths["int8"]["r2_change"] = -0.02  # too inaccurate: the budget refuses it
    assert choose_fast(paths) == "bf16"
    paths["int8"]["r2_change"] = +0.02  # "better" by this much is as different: refused too
    assert choose_fast(paths) == "bf16"
    paths["bf16"]["r2_change"] = -0.01  # nothing faster in budget: fp32 itself
    assert choose_fast(paths) == "fp32"
    paths["bf16"]["r2_change"] = None  # measured without a dataset: speed alone decides
    assert choose_fast(paths) == "bf16"
    assert choose_fast({"fp32": path(10, 0.0)}) == "fp32"  # a CPU with no other candidate


# -- every capability combination (issue: no crash on a CPU without bf16/VNNI, or without ONNX Runtime) --

COMBINATIONS = {  # name → (native bf16, int8 dot products, onnxruntime installed)
    "neither": (False, False, True),
    "bf16_only": (True, False, True),
    "vnni_only": (False, True, True),
    "both": (True, True, True),
    "no_onnxruntime": (False, False, False),
}


@pytest.fixture(params=list(COMBINATIONS))
def capabilities(request, monkeypatch):
    """This machine as it would look with the given features (the detection patched)."""
    from psdfactory.learn import capability

    bf16, vnni, ort = COMBINATIONS[request.param]
    real = capability.detect()
    caps = capability.Capabilities(
        machine="x86_64", cpu_model=f"test CPU ({request.param})", flags=("avx2", "fma"),
        torch_isa="AVX512" if bf16 else "AVX2", forced_isa="", native_bf16=bf16, int8_dot=vnni,
        onnxruntime=ort and real.onnxruntime)
    monkeypatch.setattr(capability, "detect", lambda: caps)
    if not ort:
        monkeypatch.setattr(capability, "onnxruntime_available", lambda: False)
    return caps


@pytest.mark.slow
def test_benchmark_report_and_predict_in_every_capability_combination(dataset, trained, capabilities, tmp_path):
    from psdfactory.cli import main
    from psdfactory.deploy.benchmark import benchmark
    from psdfactory.io import write_json
    from psdfactory.learn.evaluate import evaluate
    from psdfactory.learn.runtime import pick_precision
    from psdfactory.report import ReportInputs, build_report

    root = tmp_path / "res"
    shutil.copytree(dataset, root)
    shutil.copytree(trained[0], root / "models" / "resnet18")
    model = root / "models" / "resnet18" / "model.pt"
    evaluate(model, root, ["tiny"], root / "eval" / "resnet18")
    b = benchmark(model, root, "tiny", batch=2, seconds=0.02, repeats=1)
    r = b["results"][0]
    measured = {k for k in r["paths"] if k != "fast"}
    expected = {"fp32", "channels_last"} | ({"bf16"} if capabilities.native_bf16 else set()) | (
        {"ort_fp32", "int8"} if capabilities.onnxruntime else set())
    assert measured == expected
    assert set(r["skipped"]) == {"bf16", "ort_fp32", "int8"} - expected
    assert r["fast_key"] in measured and abs(r["paths"]["fast"]["r2_change"]) <= r["max_r2_change"]
    assert b["cpu"]["cpu_model"] == capabilities.cpu_model
    assert pick_precision("auto", torch.device("cpu")) == ("bf16" if capabilities.native_bf16 else "fp32")
    write_json(root / "bench" / "resnet18.json", b)

    cfg = tiny_config()
    cfg["train"]["architectures"] = ["resnet18"]
    html, md = root / "report" / "report.html", root / "report" / "report.md"
    ev = root / "eval" / "resnet18"
    inputs = ReportInputs(metrics={"resnet18": ev / "metrics.json"}, scatters={"resnet18": ev / "scatter.png"},
                          histories={"resnet18": root / "models" / "resnet18" / "history.csv"},
                          bench={"resnet18": root / "bench" / "resnet18.json"},
                          manifests=[root / "tiny" / "manifest" / "scenes" / "shard-00000.parquet"])
    build_report(cfg, inputs, html, md)
    text = md.read_text()
    assert capabilities.cpu_model in text
    for key in measured:  # every measured path has a row; the chosen one is starred
        name = r["paths"][key]["name"]
        assert f"| {name}{' ★' if key == r['fast_key'] else ''} |" in text, name

    img = dataset / "tiny" / "scenes" / "tiny-000008" / "image.png"
    out = tmp_path / "p.csv"
    assert main(["predict", "--model", str(model), "--out", str(out), str(img)]) == 0
    assert float(out.read_text().splitlines()[1].split(",")[2]) > 0
    if not capabilities.onnxruntime:  # an ONNX model cannot run: said clearly, no traceback
        onnx = tmp_path / "model.onnx"
        onnx.write_bytes(b"x")
        assert main(["predict", "--model", str(onnx), str(img)]) == 2
        with pytest.raises(PsdError, match="needs ONNX Runtime.*pip install onnxruntime"):
            from psdfactory.deploy.export import export

            export(model, tmp_path / "exp")


def test_predict_finds_images_in_subfolders_and_skips_masks(tmp_path):
    from psdfactory.deploy.predict import expand_inputs

    for rel in ("a/scenes/s1/image.png", "a/scenes/s1/mask.png", "a/scenes/s2/image.png", "b.jpg", "c.txt",
                ".hidden/x.png", "a/.snap/y.png"):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_bytes(b"")
    found = [str(p.relative_to(tmp_path)) for p in expand_inputs([str(tmp_path)])]
    assert found == ["a/scenes/s1/image.png", "a/scenes/s2/image.png", "b.jpg"]
    assert expand_inputs([str(tmp_path / "a/scenes/s1/mask.png")]) == [tmp_path / "a/scenes/s1/mask.png"]  # named: kept


GOOD_META = {"arch": "resnet18", "input_size": 32, "image_resolution": 32, "mm_per_px": 0.5,
             "target_stats": {"mean": [1.0, 2.0, 3.0], "std": [0.5, 0.5, 0.5], "part_mean": [1.0, 1.0, 1.0],
                              "part_std": [0.2, 0.2, 0.2]}}


def test_onnx_meta_json_with_wrong_types_is_refused(tmp_path):
    from psdfactory.deploy.predict import load_predictor
    from psdfactory.learn.runtime import meta_problems

    good = GOOD_META
    assert meta_problems(good) == []
    assert meta_problems([1, 2]) == ["it must hold a JSON object / dict"]
    bad = {**good, "input_size": "32", "mm_per_px": -1}
    assert [p.split(" ")[0] for p in meta_problems(bad)] == ["input_size", "mm_per_px"]
    for stats in ({**good["target_stats"], "std": [0.5, 0.5]}, {**good["target_stats"], "std": [0.5, 0.0, 0.5]},
                  {**good["target_stats"], "mean": ["1", 2, 3]}, {"mean": [1, 2, 3]}, [1, 2, 3]):
        assert [p.split(" ")[0] for p in meta_problems({**good, "target_stats": stats})] == ["target_stats"], stats
    assert [p.split(" ")[0] for p in meta_problems({**good, "input_size": 10**9, "image_resolution": True,
                                                    "arch": "os.system"})] == ["arch", "input_size", "image_resolution"]
    (tmp_path / "model.onnx").write_bytes(b"not onnx")
    (tmp_path / "meta.json").write_text(json.dumps(bad))
    with pytest.raises(PsdError, match="meta.json refused: input_size is missing or not valid"):
        load_predictor(tmp_path / "model.onnx")
    (tmp_path / "meta.json").write_text("{oops")
    with pytest.raises(PsdError, match="not readable JSON"):
        load_predictor(tmp_path / "model.onnx")
    (tmp_path / "meta.json").write_text(json.dumps({**good, "pad": "x" * 2_000_000}))
    with pytest.raises(PsdError, match="meta.json refused: .* bytes"):
        load_predictor(tmp_path / "model.onnx")


def test_a_model_file_with_a_hostile_meta_is_refused_before_anything_is_built(tmp_path):
    """Plain data that loads safely, but would make predict resize every image to 10⁹ px."""
    from psdfactory.learn.runtime import load_model

    f = tmp_path / "model.pt"
    torch.save({"meta": {**GOOD_META, "input_size": 10**9}, "state_dict": {}}, f)
    with pytest.raises(PsdError, match=r"model.pt is not a psdfactory model: its meta is refused: input_size"):
        load_model(f)
    torch.save([1, 2, 3], f)
    with pytest.raises(PsdError, match="not a psdfactory model .*list"):
        load_model(f)


def test_a_model_psdfactory_writes_loads_with_weights_only(tmp_path):
    from psdfactory.learn.models import TargetStats, build_model
    from psdfactory.learn.runtime import load_model, save_model

    stats = TargetStats(**GOOD_META["target_stats"])
    model, _ = build_model("resnet18", stats, "none", size=32)
    save_model(tmp_path / "model.pt", model, {**GOOD_META, "params": {"scale_augment": (1.0, 1.0)}})
    loaded, meta = load_model(tmp_path / "model.pt")
    assert meta["input_size"] == 32 and meta["params"]["scale_augment"] == (1.0, 1.0)
    x = torch.rand(1, 3, 32, 32)
    torch.testing.assert_close(loaded(x), model.eval()(x))


def test_the_resume_checkpoint_is_plain_data_that_loads_with_weights_only(tmp_path):
    """last.pt as the fit loop writes it (Adam, ReduceLROnPlateau, generator states, history,
    extra modules, fp16's loss scaler) loads with weights_only=True, and restores the optimizer,
    scheduler, loss scale and random streams exactly."""
    from psdfactory.learn.fit import FitTask, _resume, _state
    from psdfactory.learn.runtime import LrSchedule, load_checkpoint, loss_scaler

    model, head = torch.nn.Linear(3, 3), torch.nn.Linear(3, 2)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    sched = LrSchedule(opt, "plateau", 5, 1, 0.5, 1)
    model(torch.rand(4, 3)).sum().backward()
    opt.step()
    sched.after_epoch(0.5)
    gen, loader_gen = torch.Generator().manual_seed(1), torch.Generator().manual_seed(2)
    scaler = loss_scaler("cpu", "fp16")  # an fp16 training's loss scaler, its scale lowered
    scaler.scale(torch.tensor(1.0))
    scaler.update(new_scale=1024.0)
    task = FitTask(model, opt, sched, lambda bar: 0.0, lambda: {"val_loss": 0.0}, 4, modules={"head": head},
                   generators={"gen": gen, "loader_gen": loader_gen}, scaler=scaler)
    history = [{"epoch": 1, "train_loss": 0.5, "val_loss": 0.4, "val_mae_mm": 0.3, "lr": 1e-3, "seconds": 1.0}]
    torch.save(_state(task, "abc", 0, history, np.float64(0.4), 1, 0), tmp_path / "last.pt")
    ck = load_checkpoint(tmp_path / "last.pt", "training checkpoint")
    assert ck["best"] == 0.4 and ck["history"] == history
    expected = torch.rand(5, generator=torch.Generator().manual_seed(1))
    model2, head2 = torch.nn.Linear(3, 3), torch.nn.Linear(3, 2)
    opt2 = torch.optim.Adam(model2.parameters(), lr=1e-3)
    sched2 = LrSchedule(opt2, "plateau", 5, 1, 0.5, 1)
    g2, lg2 = torch.Generator(), torch.Generator()
    task2 = FitTask(model2, opt2, sched2, lambda bar: 0.0, lambda: {"val_loss": 0.0}, 4, modules={"head": head2},
                    generators={"gen": g2, "loader_gen": lg2}, scaler=loss_scaler("cpu", "fp16"))
    assert _resume(task2, tmp_path / "last.pt", "other", "m")[0] == 0  # another fingerprint: a fresh start
    start, hist, best, best_epoch, stale = _resume(task2, tmp_path / "last.pt", "abc", "m")
    assert (start, hist, best, best_epoch, stale) == (1, history, 0.4, 1, 0)
    assert sched2.sched.best == 0.5
    assert torch.equal(head2.weight, head.weight) and torch.equal(model2.weight, model.weight)
    assert torch.equal(torch.rand(5, generator=g2), expected)
    assert task2.scaler.get_scale() == 1024.0  # fp16's loss scale goes on where it was
    ck = torch.load(tmp_path / "last.pt", weights_only=True)  # a checkpoint of before, {device, state}, resumes too
    ck["grad_scaler"] = {"device": "cpu", "state": ck["grad_scaler"]}
    torch.save(ck, tmp_path / "old.pt")
    task2.scaler = loss_scaler("cpu", "fp16")
    _resume(task2, tmp_path / "old.pt", "abc", "m")
    assert task2.scaler.get_scale() == 1024.0


def test_optimise_step_steps_and_names_the_lr_key_when_the_loss_diverges():
    from psdfactory import PsdError
    from psdfactory.learn.runtime import optimise_step

    model = torch.nn.Linear(3, 1)
    opt = torch.optim.SGD(model.parameters(), lr=0.1)
    x = torch.ones(4, 3)
    before = model.weight.detach().clone()
    loss = optimise_step(model, opt, x, lambda out: out.square().mean(), torch.device("cpu"), "fp32", "train.lr")
    assert loss > 0 and not torch.equal(model.weight, before)
    with pytest.raises(PsdError, match="lower train.instances.lr"):
        optimise_step(model, opt, x, lambda out: out.sum() * float("nan"), torch.device("cpu"), "fp32",
                      "train.instances.lr")


def test_onecycle_rises_to_lr_then_falls_to_a_thousandth_over_exactly_the_budgeted_steps():
    from psdfactory import PsdError
    from psdfactory.learn.runtime import LrSchedule

    opt = torch.optim.Adam(torch.nn.Linear(2, 1).parameters(), lr=1e-3)
    sched = LrSchedule(opt, "onecycle", epochs=4, steps_per_epoch=25, lr_factor=0.5, lr_patience=1)
    lrs = [opt.param_groups[0]["lr"]]
    for _ in range(4):
        for _ in range(25):
            opt.step()
            sched.after_step()
            lrs.append(opt.param_groups[0]["lr"])
        sched.after_epoch(1.0)  # the validation loss does not move a one-cycle schedule
    peak = int(np.argmax(lrs))
    assert lrs[0] == pytest.approx(1e-4) and max(lrs) == pytest.approx(1e-3)
    assert 10 <= peak <= 20  # 15 % of the 100 steps
    assert lrs[-1] == pytest.approx(1e-6, rel=0.05) and np.all(np.diff(lrs[peak:]) <= 0)
    sched.after_step()  # a step past the budget (e.g. a last short batch) keeps the final rate
    assert opt.param_groups[0]["lr"] == pytest.approx(lrs[-1])

    opt = torch.optim.Adam(torch.nn.Linear(2, 1).parameters(), lr=1e-3)
    plateau = LrSchedule(opt, "plateau", epochs=4, steps_per_epoch=25, lr_factor=0.5, lr_patience=1)
    plateau.after_step()
    for loss in (1.0, 1.0, 1.0):
        plateau.after_epoch(loss)
    assert opt.param_groups[0]["lr"] == pytest.approx(5e-4)
    with pytest.raises(PsdError, match="train.lr_schedule must be one of plateau, onecycle"):
        LrSchedule(opt, "cosine", 4, 25, 0.5, 1)


@pytest.mark.parametrize(("schedule", "epochs_run"), [("plateau", 4), ("onecycle", 8)])
def test_early_stopping_ends_a_plateau_training_and_leaves_a_one_cycle_schedule_its_epochs(schedule, epochs_run,
                                                                                             tmp_path):
    """Validation losses that last improve at epoch 2: with patience 2 the plateau schedule stops after epoch 4; a
    one-cycle schedule runs its 8 epochs (its rate is lowest only at their end). Both keep epoch 2's weights."""
    from psdfactory.learn.fit import FitTask, fit
    from psdfactory.learn.runtime import LrSchedule

    model = torch.nn.Linear(2, 1)
    opt = torch.optim.SGD(model.parameters(), lr=0.1)
    sched = LrSchedule(opt, schedule, epochs=8, steps_per_epoch=1, lr_factor=0.5, lr_patience=1)
    losses = iter([3.0, 1.0, 2.0, 2.5, 1.5, 1.2, 1.1, 1.05])
    weights = []

    def train_epoch(bar) -> float:
        with torch.no_grad():
            model.weight.add_(1.0)  # each epoch's weights differ: the kept ones name their epoch
        opt.step()
        sched.after_step()
        weights.append(model.weight[0, 0].item())
        return 1.0

    task = FitTask(model, opt, sched, train_epoch, lambda: {"val_loss": next(losses)}, 1)
    res = fit(task, "toy", 8, 2, tmp_path, "fp", {"arch": "toy"})
    assert len(res.history) == epochs_run and res.best_epoch == 2 and res.best_loss == 1.0
    assert res.stop_reason == ("max epochs" if schedule == "onecycle" else
                               "early stopping (no better val loss for 2 epochs)")
    assert model.weight[0, 0].item() == pytest.approx(weights[1])  # the best epoch's weights, not the last


def interrupted_then_resumed(p, dataset, out, monkeypatch):
    """Train with `p` into `out`, interrupted in the second epoch, then run again (it resumes)."""
    from psdfactory.learn import cnn as train_mod

    real, calls = train_mod.run_epoch, {"n": 0}

    def crash_on_second(*a, **k):
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(train_mod, "run_epoch", crash_on_second)
    with pytest.raises(KeyboardInterrupt):
        train_mod.CnnRegressor.train(p, dataset, out)
    monkeypatch.setattr(train_mod, "run_epoch", real)
    train_mod.CnnRegressor.train(p, dataset, out)
    return out


def test_onecycle_training_resumes_to_the_same_losses(dataset, tmp_path, monkeypatch):
    import csv

    from psdfactory.learn import cnn as train_mod

    straight = tmp_path / "straight"
    train_mod.CnnRegressor.train(params(lr_schedule="onecycle", epochs=3), dataset, straight)
    out = interrupted_then_resumed(params(lr_schedule="onecycle", epochs=3), dataset, tmp_path / "resumed",
                                   monkeypatch)
    rows = [list(csv.DictReader(open(d / "history.csv"))) for d in (straight, out)]
    np.testing.assert_allclose([float(r["train_loss"]) for r in rows[1]], [float(r["train_loss"]) for r in rows[0]],
                               rtol=1e-5)
    np.testing.assert_allclose([float(r["lr"]) for r in rows[1]], [float(r["lr"]) for r in rows[0]])
    assert float(rows[0][-1]["lr"]) < float(rows[0][0]["lr"]) / 10  # decayed by the last epoch


def test_size_cells_train_a_plain_regressor_and_resume(dataset, tmp_path, monkeypatch):
    import csv

    from psdfactory.learn import cnn as train_mod
    from psdfactory.learn.runtime import load_checkpoint, load_model

    p = params(size_cells=1.0, epochs=3, input_size=64)
    straight = tmp_path / "straight"
    summary = train_mod.CnnRegressor.train(p, dataset, straight)
    assert summary["params"]["size_cells"] == 1.0
    state = load_checkpoint(straight / "model.pt")["state_dict"]
    assert not any("cell" in k for k in state)  # the head is for training only
    model, meta = load_model(straight / "model.pt")
    assert model(torch.zeros(1, 3, 64, 64)).shape == (1, 3)
    plain = tmp_path / "plain"
    train_mod.CnnRegressor.train(params(epochs=3, input_size=64), dataset, plain)
    losses = [[float(r["train_loss"]) for r in csv.DictReader(open(d / "history.csv"))] for d in (straight, plain)]
    assert all(a > b for a, b in zip(*losses, strict=True))  # the size-histogram loss is added

    out = interrupted_then_resumed(p, dataset, tmp_path / "resumed", monkeypatch)
    resumed = [float(r["train_loss"]) for r in csv.DictReader(open(out / "history.csv"))]
    np.testing.assert_allclose(resumed, losses[0], rtol=1e-5)
    # under bf16 autocast (what precision: auto picks where bf16 is faster) the head reads fp32 features
    train_mod.CnnRegressor.train(params(size_cells=1.0, epochs=1, input_size=64, precision="bf16"), dataset,
                                 tmp_path / "bf16")
    assert (tmp_path / "bf16" / "model.pt").is_file()


def test_crop_trains_on_windows_labelled_by_their_particles_and_reads_whole_images(dataset, tmp_path, monkeypatch):
    """train.crop: each training step sees random windows of the images (and of their size codes,
    the dense task's fourth channel) at the same scale, each labelled by the particles whose centre
    lies in it; the model reads whole images; the windows are the seed's (two runs give the same
    losses, and a run interrupted and resumed too) and differ from the whole-image run."""
    import csv

    from psdfactory.learn import cnn as cnn_mod
    from psdfactory.learn import windows as windows_mod
    from psdfactory.learn.runtime import load_model

    seen = []
    real = windows_mod.SceneWindows.__getitem__

    def spy(self, i):
        x, y = real(self, i)
        seen.append((tuple(x.shape), y.numpy().copy(), self.scenes[i][1].numpy().copy()))
        return x, y

    monkeypatch.setattr(windows_mod.SceneWindows, "__getitem__", spy)
    validated = []
    real_predict = cnn_mod.predict_batches

    def predict_spy(model, loader, *a, **k):
        validated.append(tuple(next(iter(loader))[0].shape[-2:]))
        return real_predict(model, loader, *a, **k)

    monkeypatch.setattr(cnn_mod, "predict_batches", predict_spy)
    p = params(size_cells=1.0, epochs=2, input_size=64, crop=40)
    losses = []
    for name in ("a", "b"):
        cnn_mod.CnnRegressor.train(p, dataset, tmp_path / name)
        losses.append([float(r["train_loss"]) for r in csv.DictReader(open(tmp_path / name / "history.csv"))])
    assert seen and all(shape == (4, 40, 40) for shape, _, _ in seen)
    window_y, scene_y = np.array([s[1] for s in seen]), np.array([s[2] for s in seen])
    assert (np.diff(window_y, axis=1) >= 0).all()  # d10 <= d50 <= d90
    assert not np.allclose(window_y, scene_y)  # a window's labels are its particles', not the scene's
    assert validated and set(validated) == {(64, 64)}  # validation reads whole images
    assert losses[0] == losses[1]
    model, meta = load_model(tmp_path / "a" / "model.pt")
    assert meta["params"]["crop"] == 40
    cnn_mod.CnnRegressor.train(params(size_cells=1.0, epochs=2, input_size=64), dataset, tmp_path / "whole")
    whole = [float(r["train_loss"]) for r in csv.DictReader(open(tmp_path / "whole" / "history.csv"))]
    assert whole != losses[0]
    out = interrupted_then_resumed(p, dataset, tmp_path / "resumed", monkeypatch)
    resumed = [float(r["train_loss"]) for r in csv.DictReader(open(out / "history.csv"))]
    np.testing.assert_allclose(resumed, losses[0], rtol=1e-5)  # the windows' generator is in the checkpoint


def test_crop_is_refused_with_a_pack_which_holds_no_particle_positions(tmp_path):
    from psdfactory.learn.cnn import pack_data

    with pytest.raises(PsdError, match=r"train.crop = 40: each window is labelled by the particles inside it"):
        pack_data(params(crop=40), tmp_path / "pack", 64, False, 0, None, crop=40)


def test_crop_size_is_off_at_or_above_the_input_and_refuses_what_the_network_cannot_take():
    from psdfactory.learn.models import crop_size

    assert crop_size("resnet50", 0, 256) == 0
    assert crop_size("resnet50", 256, 256) == 0 and crop_size("resnet50", 300, 256) == 0
    assert crop_size("resnet50", 128, 256) == 128
    with pytest.raises(PsdError, match=r"train.crop = 64 is below the 75 px that inception_v3 accepts"):
        crop_size("inception_v3", 64, 256)
    assert crop_size("inception_v3", 96, 256) == 96
    # at 299 px InceptionV3 trains its auxiliary head, which a smaller window cannot feed
    with pytest.raises(PsdError, match=r"train.crop = 200: inception_v3 at 299 px trains its auxiliary head"):
        crop_size("inception_v3", 200, 299)
    assert crop_size("inception_v3", 299, 320) == 299 and crop_size("resnet50", 200, 299) == 200


def test_the_training_slice_holds_crop_only_when_it_is_on():
    """A slice without train.crop (every slice written before it, and with it off) is the same as
    before, so no trained model's params change; TrainParams reads its absence as off."""
    from psdfactory.learn.train import TrainParams

    cfg = psd_config.validate(tiny_config())
    off = psd_config.train_params(cfg, "resnet18")
    assert "crop" not in off and TrainParams.from_dict(off).crop == 0
    cfg["train"]["crop"] = 64
    assert psd_config.train_params(cfg, "resnet18")["crop"] == 64
    assert TrainParams.from_dict(psd_config.train_params(cfg, "resnet18")).crop == 64


def test_a_crop_below_32_px_is_a_config_error():
    cfg = tiny_config()
    cfg["train"]["crop"] = 16
    with pytest.raises(PsdError, match="invalid config: .*crop"):
        psd_config.validate(cfg)
    cfg["train"]["crop"] = 0
    assert psd_config.validate(cfg)["train"]["crop"] == 0
