"""Images and targets from the manifests, as tensors for training and evaluation."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F

from .. import PsdError
from ..io import read_png
from ..manifest import read_scenes
from ..psd import TARGETS

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def manifest_rows(results_root: Path, dataset: str, splits: tuple[str, ...] | None = None) -> list[dict]:
    rows = read_scenes(results_root, dataset).sort_by("index").to_pylist()
    if splits is not None:
        rows = [r for r in rows if r["split"] in splits]
    return rows


def training_rows(results_root: Path, datasets: tuple[str, ...] | list[str]
                  ) -> tuple[list[dict], list[dict], list[dict]]:
    """The train and val scenes of every training dataset, together (e.g. TinyRenderer and Cycles
    renders of the same scenes), and all their rows (the training fingerprint's input)."""
    rows = [r for ds in datasets for r in manifest_rows(results_root, ds)]
    train = [r for r in rows if r["split"] == "train"]
    val = [r for r in rows if r["split"] == "val"]
    if not train or not val:
        raise PsdError(f"training datasets {', '.join(datasets)} (train.datasets, or train.<arch>.datasets): "
                       f"{len(train)} train and {len(val)} val scenes; "
                       "training needs both (datasets.<name>.split and n_scenes)")
    return train, val, rows


def particles_by_scene(results_root: Path, datasets: tuple[str, ...] | list[str],
                       columns: tuple[str, ...] | None = None) -> dict[str, dict[str, np.ndarray]]:
    """scene_id → {column: array} of the particle manifests of `datasets` (by default
    manifest.PARTICLE_READ_COLUMNS: particle_id, size_mm, z_mm)."""
    from ..manifest import PARTICLE_READ_COLUMNS, read_particles

    cols = tuple(columns or PARTICLE_READ_COLUMNS)
    return {k: v for ds in datasets for k, v in read_particles(results_root, ds, cols).items()}


def sizes_px_by_id(particles: dict[str, np.ndarray], mm_per_px: float) -> np.ndarray:
    """True sieve size in pixels per mask id (= particle_id + 1; NaN where no particle) of one
    scene's rows of `data.particles_by_scene`."""
    pid = np.asarray(particles["particle_id"], dtype=np.int64)
    out = np.full(int(pid.max(initial=-1)) + 2, np.nan)
    out[pid + 1] = np.asarray(particles["size_mm"], float) / float(mm_per_px)
    return out


def label_definition(rows: list[dict]) -> dict[str, str]:
    """What the scenes' targets d*_mm are of: {"size_definition": ..., "weighting": ...}, the same
    for every row (a model learns one definition; mixing two would teach it neither)."""
    kinds = {(r.get("size_definition"), r.get("weighting")) for r in rows}
    if len(kinds) != 1 or None in next(iter(kinds)):
        found = ", ".join(sorted(f"{d} ({w})" for d, w in kinds if d)) or "none"
        raise PsdError(f"the training scenes' labels are not of one size definition and weighting (found: {found}); "
                       "rerun the label jobs of every training dataset with one labels.size_definition")
    (definition, weighting), = kinds
    return {"size_definition": definition, "weighting": weighting}


def targets(rows: list[dict]) -> torch.Tensor:
    return torch.tensor([[r[t] for t in TARGETS] for r in rows], dtype=torch.float32).reshape(-1, len(TARGETS))


def split_summary(y: np.ndarray, mm_per_px: np.ndarray, resolution: np.ndarray) -> dict:
    """What training needs of a split before reading it, from its scenes' targets (N x 3, mm),
    scales and render sizes: the scene count, the statistics of its targets (models.TargetStats)
    and its median scale and render size (a model's meta)."""
    from .models import TargetStats

    return {"scenes": len(y), "target_stats": asdict(TargetStats.from_targets(torch.as_tensor(np.asarray(y)))),
            "mm_per_px": float(np.median(mm_per_px)), "resolution": int(np.median(resolution))}


def to_input(image: np.ndarray, size: int | None) -> torch.Tensor:
    """uint8 HxWx3 → uint8 3xSxS (area-averaged resize when shrinking)."""
    t = torch.from_numpy(np.array(image, dtype=np.uint8, copy=True)).permute(2, 0, 1)
    if size is not None and t.shape[1:] != (size, size):
        t = F.interpolate(t[None].float(), size=(size, size), mode="bilinear", antialias=True, align_corners=False)[0]
        t = t.round().clamp(0, 255).to(torch.uint8)
    return t


def normalise(batch_u8: torch.Tensor) -> torch.Tensor:
    """uint8 Nx3xHxW → float, ImageNet mean/std (what torchvision's backbones expect)."""
    mean = torch.tensor(IMAGENET_MEAN, device=batch_u8.device).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD, device=batch_u8.device).view(1, 3, 1, 1)
    return (batch_u8.float() / 255.0 - mean) / std


class SceneImages(torch.utils.data.Dataset):
    """Scenes of a manifest as (uint8 image at the model's input size, targets in mm).

    Decoded and resized images are cached in memory after first use (a 5000-scene dataset at
    224 px is 750 MB), so later epochs cost no PNG decoding.
    """

    def __init__(self, results_root: Path, rows: list[dict], size: int, cache: bool = True):
        if not rows:
            raise PsdError("no scenes to load")
        self.root = Path(results_root)
        self.rows = rows
        self.size = size
        self.y = targets(rows)
        self.cache: dict[int, torch.Tensor] | None = {} if cache else None

    def __len__(self) -> int:
        return len(self.rows)

    def __getitem__(self, i: int) -> tuple[torch.Tensor, torch.Tensor]:
        if self.cache is not None and i in self.cache:
            return self.cache[i], self.y[i]
        x = to_input(read_png(self.root / self.rows[i]["image_path"]), self.size)
        if self.cache is not None:
            self.cache[i] = x
        return x, self.y[i]


def normalised_images(results_root: Path, rows: list[dict], size: int) -> tuple[torch.Tensor, np.ndarray]:
    """Scenes as one normalised float batch (N×3×S×S) and their targets in mm."""
    ds = SceneImages(results_root, rows, size, cache=False)
    xs, ys = zip(*(ds[i] for i in range(len(ds))), strict=True)
    return normalise(torch.stack(xs)), torch.stack(ys).numpy()
