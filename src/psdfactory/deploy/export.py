"""``psdfactory export``: a trained model as ONNX and TorchScript, each checked against the
PyTorch output, and optionally as int8 ONNX, calibrated on training images and checked on the
test split."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch

from .. import PsdError
from ..io import atomic_dir, atomic_path, is_within, write_json
from ..psd import NAMES

logger = logging.getLogger(__name__)


def export(model_path: Path, out_dir: Path, int8_results: Path | None = None, dataset: str = "train",
           max_r2_change: float | None = None) -> dict:
    """ONNX and TorchScript copies of a model, each checked against the PyTorch output; with
    `int8_results` (a results root) also ``model.int8.onnx``, calibrated on the dataset's
    training images and refused if the R² of any target on the test split moves more than
    `max_r2_change` (default ``quantize.MAX_R2_CHANGE``) from the fp32 model's.

    The export is one unit: every input is checked first, the files are written into a new
    hidden folder beside `out_dir`, and that folder replaces `out_dir` only when all of them
    are made and checked. A failed export leaves `out_dir` as it was; an export folder never
    holds parts of two models."""
    out_dir, model_path = Path(out_dir), Path(model_path)
    if is_within(model_path, out_dir):
        raise PsdError(f"--out-dir {out_dir} holds the model {model_path}, which the export would replace; "
                       "give another folder")
    if int8_results is not None:
        shards = Path(int8_results) / dataset / "manifest" / "scenes"
        if not shards.is_dir():
            raise PsdError(f"--int8 {int8_results}: no manifest of dataset {dataset!r} at {shards} to calibrate on "
                           "(give the results root of a run, and --dataset)")
    with atomic_dir(out_dir, "--out-dir", ".export") as stage:
        report = _export_into(model_path, stage, int8_results, dataset, max_r2_change)
    for part in report.values():  # the paths the report names: where the files are now
        if isinstance(part, dict) and "path" in part:
            part["path"] = str(out_dir / Path(part["path"]).name)
    write_json(out_dir / "export.json", report)
    logger.info(f"exported to {out_dir}/")
    return report


def _export_into(model_path: Path, out_dir: Path, int8_results: Path | None, dataset: str,
                 max_r2_change: float | None) -> dict:
    """The estimator's inference module (`Estimator.inference_module`: normalised images in, the
    outputs its `read` takes out) as ONNX — any image size where the estimator takes any
    (`any_size`) — and TorchScript where it allows, each checked against PyTorch; with
    `int8_results` an int8 ONNX where it allows, checked on the test split; meta.json beside."""
    from ..learn.runtime import load_estimator
    from .quantize import MAX_R2_CHANGE, export_onnx, require_onnxruntime

    require_onnxruntime("export (it checks the ONNX model against PyTorch)")
    max_r2_change = MAX_R2_CHANGE if max_r2_change is None else max_r2_change
    est = load_estimator(model_path, "cpu")
    meta, arch = est.meta, est.arch
    if int8_results is not None and not est.int8:
        raise PsdError(f"int8 export is not available for {arch} (its outputs feed post-processing whose accuracy "
                       "int8 is not checked against; only the fp32 network is exported)")
    module = est.inference_module().float().eval()
    size = int(meta["input_size"])
    gen = torch.Generator().manual_seed(0)
    shapes = [(2, 3, size, size)] + ([(1, 3, size // 2 + 3, size - 5)] if est.any_size else [])  # + an odd size
    inputs = [torch.randn(*s, generator=gen) for s in shapes]
    with torch.inference_mode():
        refs = [module(x).numpy() for x in inputs]
    out_dir.mkdir(parents=True, exist_ok=True)
    kind = f"{meta.get('size_definition', 'b-axis')} size, {meta.get('weighting', 'number')}-weighted"
    report = {"arch": arch, "input_size": size, "mm_per_px": meta["mm_per_px"],
              "input": ("float32 Nx3xHxW (any H, W), RGB/255 normalised with ImageNet mean/std, at mm_per_px"
                        if est.any_size else "float32 Nx3xSxS, RGB/255 normalised with ImageNet mean/std"),
              "output": f"{est.output_doc} ({kind})", "torchscript": None}

    def check(name: str, run) -> dict:
        diffs = []
        for x, ref in zip(inputs, refs, strict=True):
            got = run(x)
            if got.shape != ref.shape:
                raise PsdError(f"{name} export gives outputs of shape {got.shape} for input {tuple(x.shape)}, "
                               f"PyTorch {ref.shape}")
            diffs.append(float(np.abs(got - ref).max()))
        diff = max(diffs)
        if not diff < 1e-3:
            raise PsdError(f"{name} export differs from PyTorch by {diff:.2e} (tolerance 1e-3)")
        logger.info(f"{name}: max |difference| vs PyTorch {diff:.1e}")
        return {"max_abs_diff": diff}

    if est.torchscript:
        ts_path = out_dir / "model.torchscript.pt"
        with torch.no_grad():
            traced = torch.jit.trace(module, inputs[0])
        with atomic_path(ts_path) as tmp, open(tmp, "wb") as f:
            torch.jit.save(traced, f)  # through a file object: given a path, the archive is named after the temp file
        loaded = torch.jit.load(str(ts_path))
        with torch.inference_mode():
            report["torchscript"] = {"path": str(ts_path), **check("torchscript", lambda x: loaded(x).numpy())}
    onnx_path = out_dir / "model.onnx"
    export_onnx(module, size, onnx_path, est.output_name, est.any_size)
    import onnxruntime as ort

    sess = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
    report["onnx"] = {"path": str(onnx_path), **check("onnx", lambda x: sess.run(None, {"images": x.numpy()})[0])}
    missing = [k for k, ok in (("TorchScript", est.torchscript), ("int8", est.int8)) if not ok]
    if missing:
        report["not_exported"] = f"{' and '.join(missing)}: not for {arch}"
    if int8_results is not None:
        report["int8"] = export_int8(est, onnx_path, out_dir / "model.int8.onnx", Path(int8_results), dataset,
                                     max_r2_change)
    write_json(out_dir / "export.json", report)
    write_json(out_dir / "meta.json", meta)
    return report


def export_int8(est, fp32_onnx: Path, out: Path, results_root: Path, dataset: str, max_r2_change: float) -> dict:
    """int8 ONNX calibrated on the dataset's training images, refused when the R² of any target on
    the test split moves more than `max_r2_change` from the fp32 model's (`quantize.r2_change`)."""
    from ..learn.estimator import predictions, rows_readings
    from ..learn.evaluate import eval_rows
    from ..learn.metrics import regression_metrics
    from .quantize import OrtModel, calibration_images, quantize_int8, r2_change, r2_moves

    size = est.meta["input_size"]
    calib = calibration_images(results_root, dataset, size)
    tmp_out = out.with_name(".candidate." + out.name)
    quantize_int8(fp32_onnx, tmp_out, calib)
    rows = eval_rows(results_root, dataset)
    ort = OrtModel(tmp_out, torch.get_num_threads())
    r32, y = rows_readings(est, results_root, rows)
    r8, _ = rows_readings(est.with_runner(lambda x: ort(x.numpy())), results_root, rows)
    p32, p8 = predictions(r32), predictions(r8)
    m32, m8 = regression_metrics(y, p32), regression_metrics(y, p8)
    change, target = r2_change(m8, m32)
    info = {"path": str(out), "calibration_images": len(calib), "test_scenes": len(y),
            "r2_fp32": {n: m32[n]["r2"] for n in NAMES}, "r2_int8": {n: m8[n]["r2"] for n in NAMES},
            "r2_change": change, "r2_change_target": target, "max_abs_diff_mm": float(np.abs(p8 - p32).max())}
    if abs(change) > max_r2_change:
        tmp_out.unlink()
        raise PsdError(f"int8 model refused: {target} R² {m8[target]['r2']:.4f} vs fp32 {m32[target]['r2']:.4f} on "
                       f"{len(y)} test scenes (change {change:+.4f}, allowed ±{max_r2_change} on every target); use "
                       "the fp32 model.onnx")
    tmp_out.replace(out)
    logger.info(f"int8: {out} (R² {r2_moves(m8, m32)} on {len(y)} test scenes; calibrated on {len(calib)} images)")
    return info
