"""A dense training signal for the CNN regressors (`train.size_cells`, its loss weight).

Three numbers per image are all a regressor learns from, and from ~100 images on a CPU that
teaches it the renderer's look rather than the particles. The factory knows every pixel's
particle and that particle's true sieve size, so each image can say far more: here the
backbone's last feature map (the input of its global pooling, e.g. 8×8 cells at 256 px) learns to
tell, per cell, which particle sizes cover it — a histogram of the sieve sizes of the cell's
pixels over half-octave bins, with the table as one more bin. A 1×1 convolution (`CellHead`)
reads it off the features; its soft cross-entropy is added to the regression loss. The head
exists only in training: the saved model is the plain regressor.

- `size_code_map`: one scene's mask → uint8 H×W, 0 = table, else the particle's log2 sieve size
  in pixels on a 1/16-octave code (`encode_log2_px`), so that a magnified image shifts every
  code by 16·log2(s) exactly (`shift_codes`, used by the scale augmentation).
- `cell_targets`: code maps → N×C×h×w fractions per cell (C = bins + table; sum 1).
- `FeatureTap`: catches the input of the model's ``avgpool`` (torchvision's CNNs all pool there).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from .. import PsdError

CODES_PER_OCTAVE = 16
LOG2_PX_MIN = -2.0  # code 1 = a quarter of a pixel; 255 = 2^13.9 px: every size an image can show
BIN_OCTAVES = 0.5  # histogram bins of half an octave ...
BIN_EDGES_LOG2_PX = tuple(np.arange(0.0, 6.0, BIN_OCTAVES).tolist())  # ... from 1 px to 45 px, open at both ends
N_CLASSES = len(BIN_EDGES_LOG2_PX) + 2  # the table + the bins (below the first edge, between, above the last)


def encode_log2_px(size_px: np.ndarray) -> np.ndarray:
    """Sizes in pixels → codes 1..255 (log2 on a 1/16-octave grid from 1/4 px); NaN → 0."""
    s = np.asarray(size_px, dtype=float)
    code = np.round((np.log2(np.maximum(np.nan_to_num(s, nan=1.0), 1e-9)) - LOG2_PX_MIN) * CODES_PER_OCTAVE) + 1
    return np.where(np.isfinite(s) & (s > 0), np.clip(code, 1, 255), 0).astype(np.uint8)


def size_code_map(mask: np.ndarray, size_px_by_id: np.ndarray) -> np.ndarray:
    """uint8 H×W: 0 on the table, else the code of the true sieve size (pixels) of the particle
    each pixel shows (`size_px_by_id[k]` for mask id k)."""
    m = np.asarray(mask).astype(np.int64)
    if m.ndim != 2:
        raise PsdError(f"an instance mask must be 2-D, got shape {m.shape}")
    if m.max(initial=0) >= len(size_px_by_id):
        raise PsdError(f"the mask has id {int(m.max())} but sizes are known for ids < {len(size_px_by_id)}")
    lut = encode_log2_px(np.asarray(size_px_by_id, dtype=float))
    lut[0] = 0
    return lut[m]


def resize_codes(codes: torch.Tensor, size: int) -> torch.Tensor:
    """uint8 H×W code map → size×size (nearest: codes are labels), every code shifted for the
    change of pixel size (a particle s px wide becomes s·size/W px wide)."""
    h, w = codes.shape[-2:]
    if (h, w) == (size, size):
        return codes
    out = F.interpolate(codes[None, None].float(), size=(size, size), mode="nearest")[0, 0].to(torch.uint8)
    return shift_codes(out, size / w)


def shift_codes(codes: torch.Tensor, factor: float) -> torch.Tensor:
    """The codes of an image magnified by `factor` (every particle `factor` times larger)."""
    if factor == 1.0:
        return codes
    step = round(math.log2(factor) * CODES_PER_OCTAVE)
    shifted = (codes.to(torch.int16) + step).clamp(1, 255).to(torch.uint8)
    return torch.where(codes > 0, shifted, codes)


def code_classes(codes: torch.Tensor) -> torch.Tensor:
    """Code maps (uint8 …×H×W) → class maps (int64): 0 = table, 1.. = size bins."""
    log2_px = (codes.float() - 1) / CODES_PER_OCTAVE + LOG2_PX_MIN
    edges = torch.tensor(BIN_EDGES_LOG2_PX, device=codes.device)
    bins = torch.bucketize(log2_px, edges, right=True) + 1
    return torch.where(codes > 0, bins, torch.zeros_like(bins))


def cell_targets(codes: torch.Tensor, grid: tuple[int, int]) -> torch.Tensor:
    """N×H×W code maps → N×N_CLASSES×h×w: the share of each cell's pixels in each class."""
    onehot = F.one_hot(code_classes(codes), N_CLASSES).permute(0, 3, 1, 2).float()
    return F.adaptive_avg_pool2d(onehot, grid)


def cell_loss(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Soft cross-entropy of the cells' predicted class shares, averaged over cells."""
    return -(target * F.log_softmax(logits.float(), dim=1)).sum(dim=1).mean()


class FeatureTap:
    """Catches the input of `model.avgpool` (the backbone's last feature map) on every forward."""

    def __init__(self, model: nn.Module, arch: str):
        pool = getattr(model, "avgpool", None)
        if not isinstance(pool, nn.Module):
            raise PsdError(f"train.size_cells needs a CNN that pools its last feature map in an `avgpool` layer; "
                           f"{arch} has none (set train.size_cells: 0 for it)")
        self.features: torch.Tensor | None = None
        self.handle = pool.register_forward_pre_hook(self._catch)

    def _catch(self, module, args) -> None:
        self.features = args[0]

    def remove(self) -> None:
        self.handle.remove()


class CellHead(nn.Module):
    """Feature map (N×C×h×w) → per-cell logits of the size classes (N×N_CLASSES×h×w)."""

    def __init__(self, channels: int):
        super().__init__()
        self.conv = nn.Conv2d(channels, N_CLASSES, 1)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return self.conv(features)


def feature_channels(model: nn.Module, tap: FeatureTap, size: int) -> int:
    """Channels of the tapped feature map, from one forward pass of a blank image."""
    was = model.training
    model.eval()
    with torch.no_grad():
        model(torch.zeros(1, 3, size, size, device=next(model.parameters()).device))
    model.train(was)
    if tap.features is None:
        raise PsdError("the model's avgpool layer was not reached in a forward pass")
    return int(tap.features.shape[1])


def scene_codes(mask: np.ndarray, particles: dict[str, np.ndarray], mm_per_px: float, size: int) -> torch.Tensor:
    """A scene's size-code map at the network's input size (uint8 size×size), from its full-size
    instance mask and its particles' rows (`data.particles_by_scene`): what the dense size task
    trains on, from scene folders and packs alike."""
    from .data import sizes_px_by_id

    return resize_codes(torch.from_numpy(size_code_map(mask, sizes_px_by_id(particles, mm_per_px))), size)


class ScenesWithSizeCodes(torch.utils.data.Dataset):
    """A `data.SceneImages` whose items carry the scene's size-code map as a fourth channel
    (uint8 4×S×S, so that flips and rotations move image and codes together), and its targets."""

    def __init__(self, scenes, particles: dict[str, dict[str, np.ndarray]]):
        self.scenes = scenes
        self.particles = particles
        self.cache: dict[int, torch.Tensor] = {}

    def __len__(self) -> int:
        return len(self.scenes)

    def codes(self, i: int) -> torch.Tensor:
        if i not in self.cache:
            from ..io import read_png

            r = self.scenes.rows[i]
            if r["scene_id"] not in self.particles:
                raise PsdError(f"the particle manifest has no rows for {r['scene_id']}")
            self.cache[i] = scene_codes(read_png(self.scenes.root / r["mask_path"]), self.particles[r["scene_id"]],
                                        float(r["mm_per_px"]), self.scenes.size)
        return self.cache[i]

    def __getitem__(self, i: int) -> tuple[torch.Tensor, torch.Tensor]:
        x, y = self.scenes[i]
        return torch.cat([x, self.codes(i)[None]]), y
