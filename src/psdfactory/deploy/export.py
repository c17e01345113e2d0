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
    `max_r2_change` (default ``quantize.MAX_R2_CHANGE``) from the fp32 model's.

    The export is one unit: every input is checked first, the files are written into a new
    hidden folder beside `out_dir`, and that folder replaces `out_dir` only when all of them
    are made and checked. A failed export leaves `out_dir` as it was; an export folder never
    holds parts of two models."""
    import shutil
    import tempfile

    from ..io import current_umask

    out_dir, model_path = Path(out_dir), Path(model_path)
    if out_dir.exists() and not out_dir.is_dir():
        raise PsdError(f"--out-dir {out_dir} is a file; give a folder")
    if model_path.resolve().is_relative_to(out_dir.resolve()):
        raise PsdError(f"--out-dir {out_dir} holds the model {model_path}, which the export would replace; "
                       "give another folder")
    if int8_results is not None:
        shards = Path(int8_results) / dataset / "manifest" / "scenes"
        if not shards.is_dir():
            raise PsdError(f"--int8 {int8_results}: no manifest of dataset {dataset!r} at {shards} to calibrate on "
                           "(give the results root of a run, and --dataset)")
    try:
        out_dir.parent.mkdir(parents=True, exist_ok=True)
        stage = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", suffix=".export", dir=out_dir.parent))
        stage.chmod(0o777 & ~current_umask())
    except OSError as e:
        raise PsdError(f"--out-dir {out_dir}: cannot write in {out_dir.parent} ({e.strerror})") from None
    try:
        report = _export_into(model_path, stage, int8_results, dataset, max_r2_change)
        old = out_dir.with_name(stage.name + ".old")
        if out_dir.exists():
            out_dir.rename(old)
        stage.rename(out_dir)
        shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
    for part in report.values():  # the paths the report names: where the files are now
        if isinstance(part, dict) and "path" in part:
            part["path"] = str(out_dir / Path(part["path"]).name)
    write_json(out_dir / "export.json", report)
    logger.info(f"exported to {out_dir}/")
    return report


def _export_into(model_path: Path, out_dir: Path, int8_results: Path | None, dataset: str,
                 max_r2_change: float | None) -> dict:
    from ..learn.runtime import load_model
    from .quantize import MAX_R2_CHANGE, require_onnxruntime

    require_onnxruntime("export (it checks the ONNX model against PyTorch)")
    max_r2_change = MAX_R2_CHANGE if max_r2_change is None else max_r2_change
    model, meta = load_model(model_path, "cpu")
    model = model.float().eval()
    if meta["arch"] == "instances":
        if int8_results is not None:
            raise PsdError("int8 export is not available for the instance estimator (its maps feed a watershed; "
                           "only the fp32 network is exported)")
        return export_instances(model, meta, out_dir)
    size = meta["input_size"]
    x = torch.randn(2, 3, size, size)
    with torch.inference_mode():
        ref = main_output(model(x)).numpy()

    from .quantize import OutputOnly, export_onnx

    wrapped = OutputOnly(model).eval()
    out_dir.mkdir(parents=True, exist_ok=True)
    kind = f"{meta.get('size_definition', 'b-axis')} size, {meta.get('weighting', 'number')}-weighted"
    report = {"arch": meta["arch"], "input_size": size,
              "input": "float32 Nx3xSxS, RGB/255 normalised with ImageNet mean/std",
              "output": f"float32 Nx3: d10, d50, d90 in mm ({kind})", "mm_per_px": meta["mm_per_px"]}

    ts_path = out_dir / "model.torchscript.pt"
    with torch.no_grad():
        traced = torch.jit.trace(wrapped, x)
    with atomic_path(ts_path) as tmp, open(tmp, "wb") as f:
        torch.jit.save(traced, f)  # through a file object: given a path, the archive is named after the temp file
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


def export_instances(model, meta: dict, out_dir: Path) -> dict:
    """The instance estimator's network as ONNX — images (N×3×H×W, any H and W) in, its maps
    (N×C×H×W, C = len(meta["maps"]): foreground, boundary, distance and the size map, each in
    [0, 1]) out — checked against PyTorch at
    two sizes, with meta.json (scale, post-processing settings, read-out). The watershed,
    measurement and read-out stay in Python: `psdfactory predict --model model.onnx` runs them."""
    import onnxruntime as ort

    from ..learn.instances import InstanceMaps

    wrapped = InstanceMaps(model.float().eval()).eval()
    out_dir.mkdir(parents=True, exist_ok=True)
    onnx_path = out_dir / "model.onnx"
    size = int(meta["input_size"])
    with atomic_path(onnx_path) as tmp:
        torch.onnx.export(wrapped, (torch.zeros(1, 3, size, size),), str(tmp), input_names=["images"],
                          output_names=["maps"],
                          dynamic_axes={"images": {0: "batch", 2: "height", 3: "width"},
                                        "maps": {0: "batch", 2: "height", 3: "width"}}, dynamo=False)
    sess = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
    diffs = []
    for shape in ((2, 3, size, size), (1, 3, size // 2 + 3, size - 5)):  # the export's size and an odd one
        x = torch.randn(*shape, generator=torch.Generator().manual_seed(0))
        with torch.inference_mode():
            ref = wrapped(x).numpy()
        got = sess.run(None, {"images": x.numpy()})[0]
        if got.shape != ref.shape:
            raise PsdError(f"onnx export gives maps of shape {got.shape} for input {tuple(shape)}, PyTorch {ref.shape}")
        diffs.append(float(np.abs(got - ref).max()))
    diff = max(diffs)
    if not diff < 1e-3:
        raise PsdError(f"onnx export differs from PyTorch by {diff:.2e} (tolerance 1e-3 on maps in [0, 1])")
    logger.info(f"onnx: {onnx_path} (max |difference| vs PyTorch {diff:.1e} on the maps; "
                "post-processing stays in Python)")
    report = {"arch": meta["arch"], "input_size": size, "mm_per_px": meta["mm_per_px"],
              "input": "float32 Nx3xHxW (any H, W), RGB/255 normalised with ImageNet mean/std, at mm_per_px",
              "output": "float32 NxCxHxW maps in [0, 1], C = len(maps): foreground, boundary, normalised distance, "
                        "size map (log size of each pixel's particle); average them over the views "
                        "meta.json's tta names, then post-process with "
                        "psdfactory.learn.instances.InstanceEstimator (watershed, measurement, read-out in meta.json)",
              "onnx": {"path": str(onnx_path), "max_abs_diff": diff},
              "torchscript": None, "not_exported": "TorchScript and int8: not for the instance estimator"}
    write_json(out_dir / "export.json", report)
    write_json(out_dir / "meta.json", meta)
    return report
