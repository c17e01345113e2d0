"""The instance-based estimator (architecture name ``instances``): segment every particle, measure
it, then read the PSD off the measured particles.

- **Network** (`InstanceNet`): a torchvision ResNet-18 trunk cut after ``layer2`` (stride 8;
  ImageNet weights with ``train.pretrained`` as for the CNNs) and a light U-Net decoder with skips
  at strides 4, 2 and 1, predicting four maps (MAPS) at the input's resolution, any size: a
  foreground logit, a boundary logit, a logit of the normalised distance to the instance's
  boundary and a logit of the size map.
- **Targets** from ``mask.png`` (`instance_targets`): foreground = mask > 0; boundary = instance
  pixels with a 4-neighbour of another id (the background included); distance = each
  instance's own Euclidean distance transform divided by its maximum (1 at its centre, so a
  3-px grain and a 30-px one get seeds alike); size (`size_target`) = the true sieve size in
  pixels of the particle a pixel belongs to, from the particle manifest, log-encoded in [0, 1]
  — however much of the particle is hidden, so the network learns to see a whole grain in a
  part of it, and a merged or split instance still reads its grains' sizes.
- **Loss** (`instance_loss`): BCE(foreground) + BCE(boundary, positive-weighted by the
  background / boundary ratio of the training masks) + L1(distance) + L1(log2 size, in octaves)
  on foreground pixels.
- **Training** on random crops of the training split (``train.input_size.instances`` px) with
  flips / 90° rotations applied to image and targets alike and the photometric jitter of
  `augment.photometric` on the image (it changes no target); model selection by validation
  loss on the full validation images. Then, with the best weights: the post-processing
  settings (thresholds, h-maxima depth, seed merging) are picked by F1 at IoU 0.5 against the
  validation masks, and a ridge read-out from `particles.instance_stats` to the labels is fitted
  on the training and validation scenes' *predicted* instances (the camera cannot see hidden
  fines; the read-out learns what they add), reading the statistics ``train.instances.readout``
  names (READOUTS: the footprints', and with ``footprints+size_map`` the size map's too). All of
  it is stored as plain lists in the model file's meta.
- **Inference** (`InstanceEstimator`): full image → maps (with ``train.instances.tta``
  averaged over views of the image — its quarter turns and mirror images, each turned back,
  `averaged_maps`; off by default) → `split_instances` → `measure_instances`
  at the image's mm per pixel (sieve size per ``train.instances.sieve_method``: by default the
  footprint's min Feret diameter; ``size_map``, the size map's median over the instance, reads
  partly hidden grains whole but misreads the fines and transfers worse to Cycles renders —
  measured in the README) → raw number-weighted d10/d50/d90 of the instances not touching
  the image edge (`psd_from_instances`) and the calibrated d10/d50/d90 (the read-out; sorted so
  that d10 ≤ d50 ≤ d90).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from scipy import ndimage
from torch import nn
from torch.nn import functional as F

from .. import PsdError
from ..io import read_png
from ..psd import SOLID_DEFINITIONS, TARGETS
from .particles import (
    DEFAULT_SIEVE_METHOD,
    MAP_READOUT_FEATURES,
    READOUT_FEATURES,
    SIEVE_METHODS,
    STAT_NAMES,
    InstanceMeasurements,
    instance_outlines,
    instance_stats,
    measure_instances,
    psd_from_instances,
    sieve_size,
    split_instances,
)
from .readout import apply_readout

logger = logging.getLogger(__name__)

ARCH = "instances"
TRUNK = "resnet18"
DECODER = (64, 32, 16)  # channels of the decoder stages at strides 4, 2, 1
FULL_RES = 8  # channels of the full-resolution skip
# the maps the network predicts, in this order; "size": the log size of the particle a pixel
# belongs to (its true sieve size, in pixels, however much of it is hidden), encoded in [0, 1]
MAPS = ("foreground", "boundary", "distance", "size")
MASK_MAPS = MAPS[:3]  # what a model trained before the size map predicts
SIZE_RANGE_PX = (0.5, 1024.0)  # sizes the size map can express (log-linear in between)
DEFAULT_POSTPROCESS = {"threshold": 0.5, "h": 0.2, "min_distance": 0.0, "min_area_px": 4, "use_boundary": True}
# the post-processing grid searched on the validation masks after training
POSTPROCESS_GRID = {"h": (0.1, 0.2, 0.35, 0.5), "use_boundary": (False, True), "min_distance": (0.0, 3.0)}
# what the calibrated read-out may read (train.instances.readout): the instances' footprint
# statistics, or those and the same statistics of the size map
READOUTS = {"footprints": READOUT_FEATURES, "footprints+size_map": MAP_READOUT_FEATURES}
# test-time augmentation (train.instances.tta): the maps averaged over these views of the image,
# each (quarter turns, mirrored) and turned back — the symmetries the training crops are drawn
# under, so each view is an image of the kind the network learnt
TTA_VIEWS = {
    "none": ((0, False),),
    "flips": ((0, False), (0, True), (2, False), (2, True)),
    "d4": tuple((k, flip) for k in range(4) for flip in (False, True)),
}


@dataclass(frozen=True)
class InstanceSettings:
    """`train.instances` in the config: what only the instance estimator's training uses
    (defaults: the schema's)."""

    crops_per_image: int  # random crops of each training image per epoch
    photometric: float  # strength of the camera/light augmentation of the image (0 = off)
    lr: float  # Adam learning rate
    sieve_method: str  # min_feret | ellipse_minor | size_map
    readout: str  # footprints | footprints+size_map: what the calibrated read-out reads (READOUTS)
    tta: str  # none | flips | d4: the views of each image whose maps are averaged (TTA_VIEWS)

    @classmethod
    def from_dict(cls, d: dict) -> InstanceSettings:
        from ..config import config_fields

        s = cls(**config_fields(cls, d, "train.instances"))
        if s.sieve_method not in SIEVE_METHODS:
            raise PsdError(f"train.instances.sieve_method must be one of {', '.join(SIEVE_METHODS)}")
        if s.readout not in READOUTS:
            raise PsdError(f"train.instances.readout must be one of {', '.join(READOUTS)}")
        if s.tta not in TTA_VIEWS:
            raise PsdError(f"train.instances.tta must be one of {', '.join(TTA_VIEWS)}")
        return s


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


def target_stack(mask: np.ndarray, size_px_by_id: np.ndarray | None = None) -> torch.Tensor:
    """The targets of one mask as a float32 C×H×W tensor in the order of MAPS: foreground,
    boundary, distance, and with `size_px_by_id` (true size in pixels per mask id) the size."""
    fg, bd, dist = instance_targets(mask)
    maps = [fg.astype(np.float32), bd.astype(np.float32), dist]
    if size_px_by_id is not None:
        maps.append(size_target(mask, size_px_by_id))
    return torch.from_numpy(np.stack(maps))


# ---------------------------------------------------------------------------------------------
# the network


def _cbr(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


class InstanceNet(nn.Module):
    """ResNet-18 trunk (stem, layer1, layer2; stride 8) + U-Net decoder → N×C×H×W logits (the
    first `n_maps` of MAPS) at the input's size, for any H, W ≥ 1."""

    def __init__(self, trunk: nn.Module | None = None, decoder: tuple[int, ...] = DECODER, full: int = FULL_RES,
                 n_maps: int = len(MAPS)):
        super().__init__()
        if trunk is None:
            import torchvision

            trunk = torchvision.models.resnet18(weights=None)
        self.stem = nn.Sequential(trunk.conv1, trunk.bn1, trunk.relu)  # stride 2, 64
        self.pool = trunk.maxpool
        self.layer1 = trunk.layer1  # stride 4, 64
        self.layer2 = trunk.layer2  # stride 8, 128
        self.full = _cbr(3, full)
        skips = (64, 64, full)
        ups, prev = [], 128
        for c, s in zip(decoder, skips, strict=True):
            ups.append(_cbr(prev + s, c))
            prev = c
        self.up = nn.ModuleList(ups)
        self.head = nn.Conv2d(prev, n_maps, 1)
        with torch.no_grad():  # start near the class balance: a dense bed is mostly foreground, rarely boundary
            self.head.bias.copy_(torch.tensor([1.0, -1.0, 0.0, 0.0][:n_maps]))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        f0 = self.full(x)
        f1 = self.stem(x)
        f2 = self.layer1(self.pool(f1))
        y = self.layer2(f2)
        for up, skip in zip(self.up, (f2, f1, f0), strict=True):
            y = F.interpolate(y, size=skip.shape[-2:], mode="bilinear", align_corners=False)
            y = up(torch.cat([y, skip], dim=1))
        return self.head(y)


class InstanceMaps(nn.Module):
    """The network with its logits turned into maps in [0, 1] (what inference and ONNX use)."""

    def __init__(self, net: nn.Module):
        super().__init__()
        self.net = net

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(self.net(images).float())


def build_instance_net(pretrained: str = "none") -> tuple[InstanceNet, str]:
    """The instance network; its trunk with ImageNet weights as `train.pretrained` says (auto:
    when they can be had, else from scratch with a warning). Returns (net, weights used)."""
    import warnings

    import torchvision

    from .models import load_imagenet_weights

    trunk = torchvision.models.resnet18(weights=None)
    used = "none (trained from scratch)"
    if pretrained in ("imagenet", "auto"):
        try:
            trunk.load_state_dict(load_imagenet_weights(TRUNK))
            used = f"imagenet ({TRUNK} trunk)"
        except PsdError as e:
            if pretrained == "imagenet":
                raise
            msg = (f"train.pretrained: auto — no ImageNet weights for the {TRUNK} trunk of {ARCH}; "
                   f"training from scratch. ({e})")
            warnings.warn(msg, stacklevel=2)
            logger.warning(msg)
            used = "none (auto: ImageNet weights unavailable, trained from scratch)"
    elif pretrained != "none":
        raise PsdError(f"train.pretrained must be auto, imagenet or none, got {pretrained!r}")
    return InstanceNet(trunk, n_maps=len(MAPS)), used


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
        octaves = float(np.log2(SIZE_RANGE_PX[1] / SIZE_RANGE_PX[0]))
        parts["size"] = ((torch.sigmoid(logits[:, 3]) - targets[:, 3]).abs() * fg).sum() / n_fg * octaves
    total = sum(parts.values())
    return total, {k: float(v.detach()) for k, v in parts.items()}


def boundary_weight(targets: torch.Tensor) -> float:
    """Background-to-boundary pixel ratio of the training targets, within [1, 10]."""
    p = float(targets[:, 1].mean())
    return float(min(10.0, max(1.0, (1 - p) / max(p, 1e-6))))


# ---------------------------------------------------------------------------------------------
# augmentation of image and targets together


def random_crops(images: torch.Tensor, targets: torch.Tensor, idx: torch.Tensor, size: int,
                 gen: torch.Generator, d4: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """Random size×size crops of images[idx] (uint8 N×3×H×W) and their targets (float N×3×H×W),
    with `d4` each turned by a random element of the square's symmetry group, the same for both."""
    h, w = images.shape[-2:]
    xs, ts = [], []
    for i in idx.tolist():
        r0 = int(torch.randint(0, h - size + 1, (1,), generator=gen))
        c0 = int(torch.randint(0, w - size + 1, (1,), generator=gen))
        x = images[i, :, r0 : r0 + size, c0 : c0 + size]
        t = targets[i, :, r0 : r0 + size, c0 : c0 + size]
        if not d4:
            xs.append(x)
            ts.append(t)
            continue
        k = int(torch.randint(0, 4, (1,), generator=gen))
        flip = bool(torch.randint(0, 2, (1,), generator=gen))
        xs.append(view(x, k, flip))
        ts.append(view(t, k, flip))
    return torch.stack(xs), torch.stack(ts)


def view(x: torch.Tensor, k: int, flip: bool) -> torch.Tensor:
    """`x` (…×H×W) turned by k quarter turns, then mirrored left-right with `flip`."""
    x = torch.rot90(x, k, dims=(-2, -1))
    return torch.flip(x, dims=(-1,)) if flip else x


def unview(x: torch.Tensor, k: int, flip: bool) -> torch.Tensor:
    """The inverse of `view`: maps of a viewed image back in the image's own frame."""
    x = torch.flip(x, dims=(-1,)) if flip else x
    return torch.rot90(x, -k, dims=(-2, -1))


def averaged_maps(maps_fn, x: torch.Tensor, views: tuple[tuple[int, bool], ...]) -> np.ndarray:
    """The mean of `maps_fn` (N×3×H×W → N×C×H×W maps) over `views` of the images `x`, each
    view's maps turned back into the image's frame (test-time augmentation; any H, W)."""
    total = None
    for k, flip in views:
        m = torch.from_numpy(np.asarray(maps_fn(view(x, k, flip).contiguous()), dtype=np.float32))
        m = unview(m, k, flip)
        total = m if total is None else total + m
    return (total / len(views)).numpy()


# ---------------------------------------------------------------------------------------------
# from maps to instances, to the PSD, to the calibrated read-out


def postprocess(maps: np.ndarray, settings: dict) -> np.ndarray:
    """Instance mask (uint16) from one image's 3×H×W maps (foreground, boundary, distance, all in
    [0, 1]): the watershed of `split_instances` on the predicted distance (multiplied by
    1 − boundary with `use_boundary`), seeds its h-maxima."""
    fg, bd, dist = (np.asarray(maps[i], dtype=np.float32) for i in range(3))
    if settings.get("use_boundary", True):
        dist = dist * (1.0 - bd)
    return split_instances(fg, distance=dist, threshold=settings["threshold"], h=settings["h"],
                           min_distance=settings["min_distance"], min_area_px=int(settings["min_area_px"]))


def raw_psd(m: InstanceMeasurements, method: str) -> dict | None:
    """Number- and volume-weighted PSD of the instances not touching the edge (all of them when
    every one does); None without any instance."""
    if not len(m):
        return None
    include = ~m.touches_edge if (~m.touches_edge).any() else None
    return psd_from_instances(sieve_size(m, method), m.volume_mm3, include=include)


@dataclass
class InstanceResult:
    """What the estimator found in one image."""

    mask: np.ndarray  # uint16 H×W at the network's resolution
    measurements: InstanceMeasurements
    stats: np.ndarray  # instance_stats, in the order of STAT_NAMES
    raw: np.ndarray  # number-weighted d10/d50/d90 of the instances not touching the edge (NaN without any)
    calibrated: np.ndarray  # the read-out's d10/d50/d90
    sizes_mm: np.ndarray  # sieve-size estimate per instance, in the order of measurements.ids
    psd: dict | None = field(default=None)  # psd_from_instances of the same instances


class InstanceEstimator:
    """Images → instance masks, measurements and d10/d50/d90. `maps_fn` runs the network: a
    normalised float32 N×3×H×W tensor → N×3×H×W maps in [0, 1] (PyTorch or ONNX Runtime)."""

    def __init__(self, maps_fn, meta: dict):
        self.maps_fn = maps_fn
        self.meta = meta
        self.post = dict(meta.get("postprocess") or DEFAULT_POSTPROCESS)
        self.method = meta.get("sieve_method", DEFAULT_SIEVE_METHOD)
        self.readout = meta.get("readout")
        self.views = TTA_VIEWS[meta.get("tta", "none")]  # a model from before TTA: one view

    def maps(self, images_u8: torch.Tensor) -> np.ndarray:
        """The maps of uint8 N×3×H×W images, averaged over the model's test-time views."""
        from .data import normalise

        return averaged_maps(self.maps_fn, normalise(images_u8), self.views)

    def analyse_maps(self, maps: np.ndarray, mm_per_px: float, post: dict | None = None) -> InstanceResult:
        mask = postprocess(maps, post or self.post)
        return self.result(mask, mm_per_px, size_map_px(maps))

    def result(self, mask: np.ndarray, mm_per_px: float, size_px: np.ndarray | None = None) -> InstanceResult:
        m = measure_instances(mask, mm_per_px, volume_from=self.method, size_map_px=size_px)
        stats = instance_stats(m, self.method)
        psd = raw_psd(m, self.method)
        raw = np.array([psd[k] for k in TARGETS]) if psd else np.full(3, np.nan)
        cal = apply_readout(self.readout, stats)[0] if self.readout else raw.copy()
        return InstanceResult(mask, m, stats, raw, cal, sieve_size(m, self.method), psd)

    def analyse(self, images_u8: torch.Tensor, mm_per_px: float | list[float]) -> list[InstanceResult]:
        """uint8 N×3×H×W → one result per image (mm per pixel: one for all, or one each)."""
        scales = mm_per_px if isinstance(mm_per_px, (list, tuple)) else [mm_per_px] * len(images_u8)
        maps = self.maps(images_u8)
        return [self.analyse_maps(mp, s) for mp, s in zip(maps, scales, strict=True)]


def size_map_px(maps: np.ndarray) -> np.ndarray | None:
    """The size map of one image's maps (C×H×W), decoded to pixels; None for a model without one."""
    return decode_size(maps[MAPS.index("size")]) if len(maps) > MAPS.index("size") else None


def torch_maps_fn(model: nn.Module, device: torch.device | str = "cpu", precision: str = "fp32"):
    """`maps_fn` for a loaded InstanceNet (fp32, or bf16/fp16 autocast)."""
    from contextlib import nullcontext

    wrapped = InstanceMaps(model).eval()
    dev = torch.device(device)
    dtype = {"bf16": torch.bfloat16, "fp16": torch.float16}.get(precision)

    def run(x: torch.Tensor) -> np.ndarray:
        with torch.inference_mode(), (torch.autocast(dev.type, dtype=dtype) if dtype else nullcontext()):
            return wrapped(x.to(dev)).float().cpu().numpy()

    return run


# ---------------------------------------------------------------------------------------------
# data


def sizes_px_by_id(particles: dict[str, np.ndarray], mm_per_px: float) -> np.ndarray:
    """True sieve size in pixels per mask id (= particle_id + 1; NaN where no particle) of one
    scene's rows of `read_particles`."""
    pid = np.asarray(particles["particle_id"], dtype=np.int64)
    out = np.full(int(pid.max(initial=-1)) + 2, np.nan)
    out[pid + 1] = np.asarray(particles["size_mm"], float) / float(mm_per_px)
    return out


def load_scenes(results_root: Path, rows: list[dict],
                particles: dict[str, dict[str, np.ndarray]] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """uint8 N×3×H×W images and float32 N×C×H×W targets (MAPS; the size map with `particles`,
    `read_particles` of the rows' dataset) of manifest rows (all one size)."""
    xs, ts = [], []
    for r in rows:
        img = read_png(Path(results_root) / r["image_path"])
        mask = read_png(Path(results_root) / r["mask_path"])
        if img.shape[:2] != mask.shape:
            raise PsdError(f"{r['scene_id']}: image {img.shape[:2]} and mask {mask.shape} differ in size")
        sizes = None
        if particles is not None:
            if r["scene_id"] not in particles:
                raise PsdError(f"the particle manifest has no rows for {r['scene_id']}")
            sizes = sizes_px_by_id(particles[r["scene_id"]], float(r["mm_per_px"]))
        xs.append(torch.from_numpy(np.array(img, dtype=np.uint8, copy=True)).permute(2, 0, 1))
        ts.append(target_stack(mask, sizes))
    if len({tuple(x.shape) for x in xs}) > 1:
        raise PsdError("the instance estimator trains on images of one size; this dataset mixes sizes")
    return torch.stack(xs), torch.stack(ts)


def all_maps(est: InstanceEstimator, images: torch.Tensor, batch: int = 4) -> np.ndarray:
    return np.concatenate([est.maps(images[i : i + batch]) for i in range(0, len(images), batch)])


# ---------------------------------------------------------------------------------------------
# evaluation: the CNNs' metrics, plus segmentation and particle sizes


def read_particles(results_root: Path, dataset: str) -> dict[str, dict[str, np.ndarray]]:
    """scene_id → {particle_id, size_mm, z_mm} arrays from a dataset's particle manifest."""
    import pyarrow.parquet as pq

    path = Path(results_root) / dataset / "manifest" / "particles"
    if not path.is_dir():
        raise PsdError(f"no particle manifest at {path}")
    t = pq.read_table(path, columns=["scene_id", "particle_id", "size_mm", "z_mm"])
    ids = np.asarray(t.column("scene_id").to_pylist())
    cols = {k: np.asarray(t.column(k)) for k in ("particle_id", "size_mm", "z_mm")}
    order = np.argsort(ids, kind="stable")
    uniq, start = np.unique(ids[order], return_index=True)
    return {str(u): {k: v[g] for k, v in cols.items()} for u, g in zip(uniq, np.split(order, start[1:]), strict=True)}


def fully_visible(true_mask: np.ndarray, z_by_id: np.ndarray) -> np.ndarray:
    """Boolean per mask id (index = id): the particle touches neither the image edge nor any
    particle whose centre lies higher (which could hide part of it)."""
    m = np.asarray(true_mask).astype(np.int64)
    n = len(z_by_id)
    ok = np.zeros(n, dtype=bool)
    present = np.unique(m[m > 0])
    ok[present[present < n]] = True
    border = np.concatenate([m[0], m[-1], m[:, 0], m[:, -1]])
    ok[border[(border > 0) & (border < n)]] = False
    for a, b in ((m[:, :-1], m[:, 1:]), (m[:-1, :], m[1:, :])):
        sel = (a != b) & (a > 0) & (b > 0) & (a < n) & (b < n)
        a, b = a[sel], b[sel]
        ok[a[z_by_id[b] > z_by_id[a]]] = False
        ok[b[z_by_id[a] > z_by_id[b]]] = False
    return ok


def size_errors(est_mm: np.ndarray, true_mm: np.ndarray) -> dict:
    """Median and 90th percentile of |est − true| / true, and the median signed ratio − 1."""
    est_mm, true_mm = np.asarray(est_mm, float), np.asarray(true_mm, float)
    if not len(est_mm):
        return {"n": 0, "median": None, "p90": None, "median_bias": None}
    rel = np.abs(est_mm - true_mm) / true_mm
    return {"n": int(len(rel)), "median": float(np.median(rel)), "p90": float(np.percentile(rel, 90)),
            "median_bias": float(np.median(est_mm / true_mm) - 1)}


# ---------------------------------------------------------------------------------------------
# model files


def net_from_meta(meta: dict) -> InstanceNet:
    """An untrained InstanceNet of the shape a model file's meta describes."""
    if meta.get("trunk", TRUNK) != TRUNK:
        raise PsdError(f"unknown trunk {meta.get('trunk')!r} for {ARCH}")
    return InstanceNet(decoder=tuple(meta.get("decoder", DECODER)), full=int(meta.get("full_res_channels", FULL_RES)),
                       n_maps=len(meta.get("maps", MASK_MAPS)))


def readout_problems(meta: dict) -> list[str]:
    """What is wrong with an instance model's network shape, post-processing and read-out (plain
    data in model.pt's meta and an export's meta.json); empty when it is fine."""
    import math

    def num(v) -> bool:
        return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)

    def nums(v, n: int) -> bool:
        return isinstance(v, list) and len(v) == n and all(num(x) for x in v)

    problems = []
    if meta.get("trunk", TRUNK) != TRUNK:
        problems.append(f"trunk must be {TRUNK!r}")
    dec = meta.get("decoder", list(DECODER))
    if not (isinstance(dec, list) and len(dec) == len(DECODER)
            and all(isinstance(c, int) and not isinstance(c, bool) and 1 <= c <= 1024 for c in dec)):
        problems.append(f"decoder must be {len(DECODER)} channel counts")
    full = meta.get("full_res_channels", FULL_RES)
    if not (isinstance(full, int) and not isinstance(full, bool) and 1 <= full <= 1024):
        problems.append("full_res_channels must be a channel count")
    post = meta.get("postprocess")
    if not isinstance(post, dict) or not all(num(post.get(k)) for k in ("threshold", "h", "min_distance",
                                                                          "min_area_px")):
        problems.append("postprocess is missing or not valid")
    maps = meta.get("maps", list(MASK_MAPS))
    if not (isinstance(maps, list) and tuple(maps) in (MASK_MAPS, MAPS)):
        problems.append(f"maps must be {list(MASK_MAPS)} or {list(MAPS)}")
    if meta.get("tta", "none") not in TTA_VIEWS:
        problems.append(f"tta must be one of {', '.join(TTA_VIEWS)}")
    if meta.get("sieve_method") not in SIEVE_METHODS:
        problems.append(f"sieve_method must be one of {', '.join(SIEVE_METHODS)}")
    elif meta["sieve_method"] == "size_map" and (not isinstance(maps, list) or "size" not in maps):
        problems.append("sieve_method 'size_map' needs a network that predicts the size map")
    for name, ro in [("readout", meta.get("readout")), *((f"readouts.{k}", v) for k, v in _readouts(meta))]:
        if ro is not None:
            problems += _one_readout_problems(name, ro, maps, nums)
    if not isinstance(meta.get("readouts", {}), dict):
        problems.append("readouts must map solid size definitions to read-outs")
    else:
        problems += [f"readouts.{k}: not a solid size definition ({', '.join(SOLID_DEFINITIONS)})"
                     for k in meta.get("readouts", {}) if k not in SOLID_DEFINITIONS]
    return problems


def _readouts(meta: dict) -> list[tuple[str, object]]:
    ro = meta.get("readouts")
    return list(ro.items()) if isinstance(ro, dict) else []


def _one_readout_problems(name: str, ro: object, maps: object, nums) -> list[str]:
    feats = ro.get("features") if isinstance(ro, dict) else None
    if not (isinstance(feats, list) and feats and all(f in STAT_NAMES for f in feats)):
        return [f"{name}.features must name instance statistics ({', '.join(STAT_NAMES)}); "
                "a model from an older psdfactory: train it again"]
    if any(f.startswith("map_") for f in feats) and (not isinstance(maps, list) or "size" not in maps):
        return [f"{name}.features read the size map, which this network does not predict"]
    nf = len(feats)
    ok = (all(nums(ro.get(k), nf) for k in ("impute", "mean", "scale"))
          and isinstance(ro.get("weights"), list) and len(ro["weights"]) == nf + 1
          and all(nums(w, 3) for w in ro["weights"]))
    return [] if ok else [f"{name} must hold impute/mean/scale ({nf} numbers each) and weights ({nf + 1} × 3)"]


def resize_mask(mask: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Nearest-neighbour resize of an instance mask (ids kept)."""
    if mask.shape == tuple(shape):
        return mask
    r = np.minimum((np.arange(shape[0]) + 0.5) * mask.shape[0] / shape[0], mask.shape[0] - 1).astype(int)
    c = np.minimum((np.arange(shape[1]) + 0.5) * mask.shape[1] / shape[1], mask.shape[1] - 1).astype(int)
    return mask[r[:, None], c[None, :]]
