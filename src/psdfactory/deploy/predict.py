"""``psdfactory predict``: d10/d50/d90 in mm for new images, with a ``model.pt`` or an exported ``.onnx``."""

from __future__ import annotations

import csv
import logging
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F

from .. import PsdError
from ..io import atomic_path, read_png, write_json
from ..learn.data import normalise, to_input
from ..learn.models import main_output

logger = logging.getLogger(__name__)
IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp"}


NOT_PHOTOS = {"mask.png"}  # the factory's instance masks, found beside its images in a results folder


def expand_inputs(paths: list[str]) -> list[Path]:
    """Files as given; folders → their image files, subfolders included (sorted by path),
    skipping the factory's ``mask.png`` files and hidden folders."""
    out: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            out += sorted(f for f in p.rglob("*") if f.suffix.lower() in IMAGE_SUFFIXES and f.name not in NOT_PHOTOS
                          and not any(part.startswith(".") for part in f.relative_to(p).parts) and f.is_file())
        else:
            out.append(p)
    return out


def network_scale(meta: dict) -> float:
    """mm per pixel of the network's input: training images are resized to the input size."""
    return meta["mm_per_px"] * meta["image_resolution"] / meta["input_size"]


def prepare(image: np.ndarray, meta: dict, mm_per_px: float | None) -> torch.Tensor:
    """uint8 image → uint8 1x3xHxW tensor at the scale the network was trained on."""
    if mm_per_px is None:
        return to_input(image, meta["input_size"])[None]  # same field of view as training assumed
    scale = mm_per_px / network_scale(meta)
    h, w = image.shape[:2]
    size = (max(32, round(h * scale)), max(32, round(w * scale)))
    t = torch.from_numpy(np.array(image, dtype=np.uint8, copy=True)).permute(2, 0, 1)[None].float()
    t = F.interpolate(t, size=size, mode="bilinear", antialias=True, align_corners=False)
    return t.round().clamp(0, 255).to(torch.uint8)


def load_predictor(model_path: Path, device: str = "cpu"):
    """→ (function: normalised float N×3×S×S tensor → N×3 mm array, meta). A `model.pt` runs in
    PyTorch; an exported `.onnx` (fp32 or int8, with the export's meta.json beside it) runs in
    ONNX Runtime on the CPU."""
    model_path = Path(model_path)
    if model_path.suffix == ".onnx":
        import json

        from ..learn.runtime import meta_problems
        from .quantize import OrtModel, require_onnxruntime

        require_onnxruntime(f"the ONNX model {model_path}")

        meta_path = model_path.with_name("meta.json")
        if not model_path.is_file():
            raise PsdError(f"model file not found: {model_path}")
        if not meta_path.is_file():
            raise PsdError(f"{meta_path} is missing: an ONNX model needs the meta.json that `psdfactory export` writes beside it")
        if meta_path.stat().st_size > 1_000_000:
            raise PsdError(f"{meta_path} refused: {meta_path.stat().st_size} bytes is far more than an export's meta.json holds")
        try:
            meta = json.loads(meta_path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
            raise PsdError(f"{meta_path} is not readable JSON ({e})") from None
        problems = meta_problems(meta)
        if problems:
            raise PsdError(f"{meta_path} refused: " + "; ".join(problems))
        ort = OrtModel(model_path, torch.get_num_threads())
        return (lambda x: ort(x.numpy())), meta
    from ..learn.runtime import load_model, pick_device

    dev = pick_device(device)
    model, meta = load_model(model_path, dev)

    def run(x: torch.Tensor) -> np.ndarray:
        with torch.inference_mode():
            return main_output(model(x.to(dev))).float().cpu().numpy()

    return run, meta


def predict_files(model_path: Path, inputs: list[str], mm_per_px: float | None = None, device: str = "cpu") -> list[dict]:
    run, meta = load_predictor(model_path, device)
    logger.info(f"model {meta['arch']} ({model_path}): expects images at {meta['mm_per_px']:.4f} mm/px "
        f"({meta['image_resolution']} px over {meta['mm_per_px'] * meta['image_resolution']:.0f} mm); "
        f"network input {meta['input_size']} px = {network_scale(meta):.4f} mm/px")
    if mm_per_px is None:
        logger.info("no --mm-per-px given: each image is taken to cover the same field of view as the training images")
    files = expand_inputs(inputs)
    if not files:
        raise PsdError("no image files given")
    rows = []
    for f in files:
        try:
            d = run(normalise(prepare(read_png(f), meta, mm_per_px)))[0]
            rows.append({"image": str(f), "d10_mm": float(d[0]), "d50_mm": float(d[1]), "d90_mm": float(d[2]), "error": ""})
        except PsdError as e:
            rows.append({"image": str(f), "d10_mm": None, "d50_mm": None, "d90_mm": None, "error": str(e)})
    return rows


def write_predictions(rows: list[dict], out: Path) -> None:
    if out.suffix.lower() == ".json":
        write_json(out, rows)
        return
    with atomic_path(out) as tmp, open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["image", "d10_mm", "d50_mm", "d90_mm", "error"])
        w.writeheader()
        w.writerows(rows)
