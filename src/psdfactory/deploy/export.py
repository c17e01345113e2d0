"""``psdfactory export``: a trained model as ONNX and TorchScript, each checked against the
PyTorch output, and optionally as int8 ONNX, calibrated on training images and checked on the
test split."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch

from .. import PsdError
from ..io import atomic_path, write_json
from ..learn.models import main_output

logger = logging.getLogger(__name__)


def export(model_path: Path, out_dir: Path, int8_results: Path | None = None, dataset: str = "train",
           max_r2_change: float | None = None) -> dict:
    """ONNX and TorchScript copies of a model, each checked against the PyTorch output; with
    `int8_results` (a results root) also ``model.int8.onnx``, calibrated on the dataset's
    training images and refused if its overall R² on the test split moves more than
    `max_r2_change` (default ``quantize.MAX_R2_CHANGE``) from the fp32 model's."""
    from ..learn.runtime import load_model
    from .quantize import MAX_R2_CHANGE, require_onnxruntime

    require_onnxruntime("export (it checks the ONNX model against PyTorch)")
    max_r2_change = MAX_R2_CHANGE if max_r2_change is None else max_r2_change
    model, meta = load_model(model_path, "cpu")
    model = model.float().eval()
    size = meta["input_size"]
    x = torch.randn(2, 3, size, size)
    with torch.inference_mode():
        ref = main_output(model(x)).numpy()

    from .quantize import OutputOnly, export_onnx

    wrapped = OutputOnly(model).eval()
    out_dir.mkdir(parents=True, exist_ok=True)
    report = {"arch": meta["arch"], "input_size": size,
              "input": "float32 Nx3xSxS, RGB/255 normalised with ImageNet mean/std",
              "output": "float32 Nx3: d10, d50, d90 in mm (number-weighted)", "mm_per_px": meta["mm_per_px"]}

    ts_path = out_dir / "model.torchscript.pt"
    with torch.no_grad():
        traced = torch.jit.trace(wrapped, x)
    with atomic_path(ts_path) as tmp:
        traced.save(str(tmp))
    loaded = torch.jit.load(str(ts_path))
    with torch.inference_mode():
        ts_out = loaded(x).numpy()
    report["torchscript"] = {"path": str(ts_path), "max_abs_diff_mm": float(np.abs(ts_out - ref).max())}

    onnx_path = out_dir / "model.onnx"
    export_onnx(model, size, onnx_path)
    import onnxruntime as ort

    sess = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
    onnx_out = sess.run(None, {"images": x.numpy()})[0]
    report["onnx"] = {"path": str(onnx_path), "max_abs_diff_mm": float(np.abs(onnx_out - ref).max())}
    for k in ("torchscript", "onnx"):
        diff = report[k]["max_abs_diff_mm"]
        if not diff < 1e-3:
            raise PsdError(f"{k} export differs from PyTorch by {diff:.2e} mm (tolerance 1e-3 mm)")
        logger.info(f"{k}: {report[k]['path']} (max |difference| vs PyTorch {diff:.1e} mm)")
    if int8_results is not None:
        report["int8"] = export_int8(model, meta, onnx_path, out_dir / "model.int8.onnx", Path(int8_results), dataset,
                                     max_r2_change)
    write_json(out_dir / "export.json", report)
    write_json(out_dir / "meta.json", meta)
    return report


def export_int8(model, meta: dict, fp32_onnx: Path, out: Path, results_root: Path, dataset: str,
                max_r2_change: float) -> dict:
    from ..learn.data import normalised_images
    from ..learn.evaluate import eval_rows
    from ..learn.metrics import regression_metrics
    from .quantize import OrtModel, calibration_images, quantize_int8

    size = meta["input_size"]
    calib = calibration_images(results_root, dataset, size)
    tmp_out = out.with_name(".candidate." + out.name)
    quantize_int8(fp32_onnx, tmp_out, calib)
    x, y = normalised_images(results_root, eval_rows(results_root, dataset), size)
    ort = OrtModel(tmp_out, torch.get_num_threads())
    with torch.inference_mode():
        p32 = main_output(model(x)).numpy()
    p8 = ort.predict(x.numpy())
    r2_32, r2_8 = regression_metrics(y, p32)["overall"]["r2"], regression_metrics(y, p8)["overall"]["r2"]
    info = {"path": str(out), "calibration_images": len(calib), "test_scenes": len(y), "r2_fp32": r2_32,
            "r2_int8": r2_8, "r2_change": r2_8 - r2_32, "max_abs_diff_mm": float(np.abs(p8 - p32).max())}
    if abs(r2_8 - r2_32) > max_r2_change:
        tmp_out.unlink()
        raise PsdError(f"int8 model refused: overall R² {r2_8:.4f} vs fp32 {r2_32:.4f} on {len(y)} test scenes "
                       f"(change {r2_8 - r2_32:+.4f}, allowed ±{max_r2_change}); use the fp32 model.onnx")
    tmp_out.replace(out)
    logger.info(f"int8: {out} (R² {r2_32:.4f} → {r2_8:.4f} on {len(y)} test scenes; calibrated on {len(calib)} images)")
    return info
