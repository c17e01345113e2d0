"""The instance network's training targets from a mask (foreground, boundary, distance, size
map), its loss, and random crops of image and targets together."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from scipy import ndimage
from torch.nn import functional as F

from ... import PsdError
from ...io import read_png
from ..augment import view
from ..data import sizes_px_by_id
from .draw import instance_outlines

# the maps the network predicts, in this order; "size": the log size of the particle a pixel
# belongs to (its true sieve size, in pixels, however much of it is hidden), encoded in [0, 1]
MAPS = ("foreground", "boundary", "distance", "size")
MASK_MAPS = MAPS[:3]  # what a model trained before the size map predicts
SIZE_RANGE_PX = (0.5, 1024.0)  # sizes the size map can express (log-linear in between)
SIZE_OCTAVES = float(np.log2(SIZE_RANGE_PX[1] / SIZE_RANGE_PX[0]))  # the size map's span: 1.0 in its units


# ---------------------------------------------------------------------------------------------
# targets


def encode_size(size_px: np.ndarray) -> np.ndarray:
    """Sizes in pixels → the size map's values in [0, 1] (log-linear over SIZE_RANGE_PX)."""
    lo, hi = np.log2(SIZE_RANGE_PX)
    return np.clip((np.log2(np.maximum(size_px, 1e-9)) - lo) / (hi - lo), 0.0, 1.0)


def decode_size(value: np.ndarray) -> np.ndarray:
    """The size map's values in [0, 1] → sizes in pixels."""
    lo, hi = np.log2(SIZE_RANGE_PX)
    return np.exp2(lo + np.asarray(value, dtype=np.float64) * (hi - lo))


def size_target(mask: np.ndarray, size_px_by_id: np.ndarray) -> np.ndarray:
    """float32 H×W: each instance pixel the encoded true size of its particle (`size_px_by_id[k]`
    for mask id k), 0 on the background (the loss only looks at instance pixels)."""
    m = np.asarray(mask).astype(np.int64)
    if m.max(initial=0) >= len(size_px_by_id):
        raise PsdError(f"the mask has id {int(m.max())} but sizes are known for ids < {len(size_px_by_id)}")
    lut = encode_size(np.nan_to_num(np.asarray(size_px_by_id, float), nan=1.0)).astype(np.float32)
    lut[0] = 0.0
    return lut[m]


def instance_targets(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(foreground, boundary, distance) of an instance mask (0 = background, k = one particle):
    foreground and boundary as bool H×W, distance float32 H×W in [0, 1] — each instance's
    Euclidean distance transform (to the nearest pixel of another id or the background; the
    image border is no boundary) divided by its own maximum."""
    m = np.asarray(mask)
    if m.ndim != 2 or not np.issubdtype(m.dtype, np.integer):
        raise PsdError(f"an instance mask must be a 2-D integer array, got {m.dtype} {m.shape}")
    m = m.astype(np.int64, copy=False)
    fg = m > 0
    boundary = instance_outlines(m)
    dist = np.zeros(m.shape, dtype=np.float32)
    for k, sl in enumerate(ndimage.find_objects(m), start=1):
        if sl is None:
            continue
        win = tuple(slice(max(s.start - 1, 0), min(s.stop + 1, n)) for s, n in zip(sl, m.shape, strict=True))
        inside = m[win] == k
        if inside.all():  # fills its window up to the image border on every side
            d = np.ones(inside.shape)
        else:
            d = ndimage.distance_transform_edt(inside)
        dmax = d[inside].max()
        dist[win][inside] = (d[inside] / dmax).astype(np.float32)
    return fg, boundary, dist


def grain_mask(mask: np.ndarray, ecd_px_by_id: np.ndarray, min_share: float) -> np.ndarray:
    """`mask` with the particles taught as grains only: those of which at least `min_share` of the
    silhouette they would show alone (an area of π/4 × `ecd_px_by_id`², the resting particle's
    equivalent-circle diameter in pixels, per mask id) is in view, and those cut by the image's
    border (their silhouette is partly outside the image, not hidden). The rest — glimpses of
    particles deep in a bed, seen through the gaps between the ones on top — become background,
    as a person outlining the grains of a photo leaves them out. `min_share` 0 keeps every one."""
    if min_share <= 0 or not mask.any():
        return mask
    visible = np.bincount(mask.ravel(), minlength=len(ecd_px_by_id))
    ids = np.arange(len(visible))
    full = np.full(len(visible), np.nan)
    n = min(len(visible), len(ecd_px_by_id))
    full[:n] = np.pi / 4.0 * np.asarray(ecd_px_by_id[:n], float) ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        glimpsed = (ids > 0) & (visible > 0) & (visible < min_share * full)  # NaN (no particle row): kept
    border = np.unique(np.concatenate([mask[0], mask[-1], mask[:, 0], mask[:, -1]]))
    glimpsed[border] = False
    return np.where(glimpsed[mask], 0, mask).astype(mask.dtype)


def target_stack(mask: np.ndarray, size_px_by_id: np.ndarray | None = None) -> torch.Tensor:
    """The targets of one mask as a float32 C×H×W tensor in the order of MAPS: foreground,
    boundary, distance, and with `size_px_by_id` (true size in pixels per mask id) the size."""
    fg, bd, dist = instance_targets(mask)
    maps = [fg.astype(np.float32), bd.astype(np.float32), dist]
    if size_px_by_id is not None:
        maps.append(size_target(mask, size_px_by_id))
    return torch.from_numpy(np.stack(maps))


def instance_loss(logits: torch.Tensor, targets: torch.Tensor, boundary_pos_weight: float) -> tuple[torch.Tensor, dict]:
    """BCE(foreground) + BCE(boundary, positive-weighted) + L1(distance) on foreground pixels,
    and with a size map + L1(log2 size, in octaves) on foreground pixels."""
    logits = logits.float()
    fg, bd, dist = targets[:, 0], targets[:, 1], targets[:, 2]
    l_fg = F.binary_cross_entropy_with_logits(logits[:, 0], fg)
    pw = torch.tensor(boundary_pos_weight, device=logits.device)
    l_bd = F.binary_cross_entropy_with_logits(logits[:, 1], bd, pos_weight=pw)
    n_fg = fg.sum().clamp_min(1.0)
    l_d = ((torch.sigmoid(logits[:, 2]) - dist).abs() * fg).sum() / n_fg
    parts = {"fg": l_fg, "boundary": l_bd, "distance": l_d}
    if logits.shape[1] > 3:
        parts["size"] = ((torch.sigmoid(logits[:, 3]) - targets[:, 3]).abs() * fg).sum() / n_fg * SIZE_OCTAVES
    total = sum(parts.values())
    return total, {k: float(v.detach()) for k, v in parts.items()}


def boundary_weight(targets: torch.Tensor) -> float:
    """Background-to-boundary pixel ratio of the training targets, within [1, 10]."""
    p = float(targets[:, 1].mean())
    return float(min(10.0, max(1.0, (1 - p) / max(p, 1e-6))))


# ---------------------------------------------------------------------------------------------
# augmentation of image and targets together


def random_crops(images: torch.Tensor, targets: torch.Tensor, idx: torch.Tensor, size: int,
                 gen: torch.Generator, d4: bool = True,
                 scale: tuple[float, float] = (1.0, 1.0)) -> tuple[torch.Tensor, torch.Tensor]:
    """Random size×size crops of images[idx] (uint8 N×3×H×W) and their targets (float N×C×H×W,
    MAPS), with `d4` each turned by a random element of the square's symmetry group, the same for
    both. With `scale` (lo, hi) ≠ (1, 1) each crop is also magnified by s, log-uniform in
    [lo, hi] (`zoom`): every grain looks s times larger, as at another mm per px."""
    h, w = images.shape[-2:]
    xs, ts = [], []
    for i in idx.tolist():
        win = size
        if tuple(scale) != (1.0, 1.0):
            lo, hi = np.log(scale[0]), np.log(scale[1])
            s = float(np.exp(lo + (hi - lo) * float(torch.rand((), generator=gen))))
            win = int(np.clip(round(size / s), 8, min(h, w)))
        r0 = int(torch.randint(0, h - win + 1, (1,), generator=gen))
        c0 = int(torch.randint(0, w - win + 1, (1,), generator=gen))
        x = images[i, :, r0 : r0 + win, c0 : c0 + win]
        t = targets[i, :, r0 : r0 + win, c0 : c0 + win]
        if win != size:
            x, t = zoom(x, t, size)
        if not d4:
            xs.append(x)
            ts.append(t)
            continue
        k = int(torch.randint(0, 4, (1,), generator=gen))
        flip = bool(torch.randint(0, 2, (1,), generator=gen))
        xs.append(view(x, k, flip))
        ts.append(view(t, k, flip))
    return torch.stack(xs), torch.stack(ts)


def zoom(image: torch.Tensor, target: torch.Tensor, size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """A square crop (uint8 3×w×w, its targets C×w×w) resized to size×size, the targets kept
    true to the resized image: foreground and distance (per grain, scale-free) interpolated,
    foreground thresholded at 1/2; the boundary kept a thin line (area-weighted, ≥ 1/4 of a
    pixel's area, so that shrinking does not break it); the size map (log size in px, 0 off the
    grains) averaged over the grain pixels under each new pixel and moved by the magnification's
    octaves."""
    w = image.shape[-1]
    s = size / w
    aa = s < 1  # antialias when shrinking
    x = F.interpolate(image[None].float(), size=(size, size), mode="bilinear", align_corners=False, antialias=aa)[0]
    x = x.round().clamp(0, 255).to(torch.uint8)
    t = F.interpolate(target[None], size=(size, size), mode="bilinear", align_corners=False, antialias=aa)[0]
    out = t.clone()
    fg = t[0] > 0.5
    out[0] = fg.float()
    out[1] = (t[1] >= 0.25).float()
    out[2] = t[2] * fg
    if t.shape[0] > 3:  # the size map: averaged over the grain pixels under each new pixel, s times larger
        den = t[0].clamp_min(1e-6)
        out[3] = torch.where(fg, ((t[3] / den) + float(np.log2(s)) / SIZE_OCTAVES).clamp(0, 1),
                             torch.zeros_like(t[3]))
    return x, out



# ---------------------------------------------------------------------------------------------
# data


def load_scenes(results_root: Path, rows: list[dict], particles: dict[str, dict[str, np.ndarray]] | None = None,
                min_visible_share: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """uint8 N×3×H×W images and float32 N×C×H×W targets (MAPS; the size map with `particles`,
    `data.particles_by_scene` of the rows' datasets) of manifest rows (all one size); with
    `min_visible_share`, of the grains `grain_mask` keeps (`particles` must hold ``ecd_mm``)."""
    xs, ts = [], []
    for r in rows:
        img = read_png(Path(results_root) / r["image_path"])
        mask = read_scene_mask(results_root, r, particles, min_visible_share)
        if img.shape[:2] != mask.shape:
            raise PsdError(f"{r['scene_id']}: image {img.shape[:2]} and mask {mask.shape} differ in size")
        sizes = None
        if particles is not None:
            sizes = sizes_px_by_id(_scene_particles(particles, r), float(r["mm_per_px"]))
        xs.append(torch.from_numpy(np.array(img, dtype=np.uint8, copy=True)).permute(2, 0, 1))
        ts.append(target_stack(mask, sizes))
    if len({tuple(x.shape) for x in xs}) > 1:
        raise PsdError("the instance estimator trains on images of one size; this dataset mixes sizes")
    return torch.stack(xs), torch.stack(ts)


def _scene_particles(particles: dict[str, dict[str, np.ndarray]], row: dict) -> dict[str, np.ndarray]:
    if row["scene_id"] not in particles:
        raise PsdError(f"the particle manifest has no rows for {row['scene_id']}")
    return particles[row["scene_id"]]


def read_scene_mask(results_root: Path, row: dict, particles: dict[str, dict[str, np.ndarray]] | None,
                    min_visible_share: float) -> np.ndarray:
    """A manifest row's instance mask; with `min_visible_share` > 0, of the grains `grain_mask` keeps."""
    mask = read_png(Path(results_root) / row["mask_path"])
    if min_visible_share <= 0:
        return mask
    if particles is None:
        raise PsdError("teaching glimpsed particles as background (train.instances.min_visible_share) needs "
                       "the particle manifest")
    p = _scene_particles(particles, row)
    if "ecd_mm" not in p:
        raise PsdError("teaching glimpsed particles as background (train.instances.min_visible_share) needs the "
                       "particles' ecd_mm (data.particles_by_scene with that column)")
    ecd_px = sizes_px_by_id({**p, "size_mm": p["ecd_mm"]}, float(row["mm_per_px"]))
    return grain_mask(mask, ecd_px, min_visible_share)
