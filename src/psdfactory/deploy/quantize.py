"""Inference through ONNX Runtime: export to ONNX, static int8 quantisation calibrated on
training images (QDQ, per-channel int8 weights, uint8 activations), and a runner.

ONNX Runtime pays on CPUs with and without int8 dot-product instructions: measured 84 vs 12
images/s (ResNet-50, 224 px, batch 16, 2 threads, int8 vs PyTorch fp32 eager) on an Intel CPU
with AVX512-VNNI, and 32.5 (int8) / 15.5 (fp32) vs 7.5 on an AMD EPYC with AVX2 only. Which
path is used is decided by timing, in ``benchmark``; every path must keep the accuracy budget.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import torch
from torch import nn

from .. import PsdError
from ..io import atomic_path
from ..psd import NAMES

# A faster inference path (and an int8 export) must keep the R² of every target (d10, d50, d90) on the test
# split within ± this of the fp32 model's (`r2_change`). Not the pooled "overall" R²: pooling the three
# targets spans their whole range (d10 to d90), so it stays near 1 and moved by 0.002 where int8 took
# ResNet-50's d90 R² from 0.22 to 0.09 (docs/performance.md).
MAX_R2_CHANGE = 0.005
# ... and, for a model that finds grains, find the grains fp32 finds: instance-mask F1 against fp32's at least
# this on every test image
MIN_GRAIN_F1 = 0.99


def r2_change(metrics: dict, base: dict) -> tuple[float, str]:
    """The change of R² from `base` to `metrics` (`learn.metrics.regression_metrics` of the same scenes) of
    the target that moved most, signed, and that target's name: what MAX_R2_CHANGE bounds."""
    name = max(NAMES, key=lambda n: abs(metrics[n]["r2"] - base[n]["r2"]))
    return float(metrics[name]["r2"] - base[name]["r2"]), name


def r2_moves(metrics: dict, base: dict) -> str:
    """Each target's R² from `base` to `metrics`, for a log line: 'd10 / d50 / d90 0.219 → 0.185 / ...'."""
    return f"{' / '.join(NAMES)} " + " / ".join(f"{base[n]['r2']:.3f} → {metrics[n]['r2']:.3f}" for n in NAMES)


def require_onnxruntime(what: str) -> None:
    """A clear error where ONNX Runtime is missing, naming what needed it."""
    from ..learn import capability

    if not capability.onnxruntime_available():
        raise PsdError(f"{what} needs ONNX Runtime, which is not installed here: pip install onnxruntime "
                       "(or use the PyTorch model.pt)")


def export_onnx(module: nn.Module, size: int, path: Path, output_name: str = "d_mm", any_size: bool = False) -> Path:
    """fp32 ONNX of an estimator's inference module (`Estimator.inference_module`) with a dynamic
    batch: input `images` (N×3×S×S, normalised; N×3×H×W, any H and W, with `any_size`), output
    `output_name`."""
    module = module.float().eval()
    axes = {0: "batch", 2: "height", 3: "width"} if any_size else {0: "batch"}
    with atomic_path(path) as tmp:
        torch.onnx.export(module, (torch.zeros(1, 3, size, size),), str(tmp), input_names=["images"],
                          output_names=[output_name], dynamic_axes={"images": axes, output_name: axes}, dynamo=False)
    return Path(path)


N_CALIBRATION = 64  # training images that calibrate the int8 activation ranges


def calibration_images(results_root: Path, dataset: str, size: int, n: int = N_CALIBRATION) -> np.ndarray:
    """Up to `n` of a dataset's training images, normalised, as float32 N×3×S×S."""
    from ..learn.data import manifest_rows, normalised_images

    rows = manifest_rows(results_root, dataset, ("train",))[:n]
    if not rows:
        raise PsdError(f"dataset {dataset!r} under {results_root} has no training scenes to calibrate int8 on")
    return normalised_images(results_root, rows, size)[0].numpy()


def quantize_int8(fp32_onnx: Path, int8_onnx: Path, calibration: np.ndarray, batch: int = 8) -> Path:
    """Static int8 quantisation; `calibration` is N×3×S×S float32 (normalised training images)."""
    from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_static
    from onnxruntime.quantization.shape_inference import quant_pre_process

    class Reader(CalibrationDataReader):
        def __init__(self):
            self.batches = iter(calibration[i : i + batch] for i in range(0, len(calibration), batch))

        def get_next(self):
            b = next(self.batches, None)
            return None if b is None else {"images": np.ascontiguousarray(b, dtype=np.float32)}

    with tempfile.TemporaryDirectory() as tmp:
        pre = Path(tmp) / "pre.onnx"
        quant_pre_process(str(fp32_onnx), str(pre))
        with atomic_path(int8_onnx) as out:
            quantize_static(str(pre), str(out), Reader(), quant_format=QuantFormat.QDQ, per_channel=True,
                            activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8)
    return Path(int8_onnx)


class OrtModel:
    """An ONNX model in an ONNX Runtime CPU session with a fixed number of threads."""

    def __init__(self, path: Path, threads: int):
        import onnxruntime as ort

        so = ort.SessionOptions()
        so.intra_op_num_threads = max(1, threads)
        so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        self.session = ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])

    def __call__(self, images: np.ndarray) -> np.ndarray:
        return self.session.run(None, {"images": np.ascontiguousarray(images, dtype=np.float32)})[0]

    def predict(self, images: np.ndarray, batch: int = 32) -> np.ndarray:
        """Predictions for many images, `batch` at a time."""
        return np.concatenate([self(images[i : i + batch]) for i in range(0, len(images), batch)])
