"""`InstanceEstimator`: the `learn.estimator.Estimator` that segments every grain, measures it and
reads the PSD off the grains — its network's maps (averaged over test-time views), the watershed,
the measurement, the raw PSD and the calibrated read-out; evaluation adds segmentation P/R/F1 and
the matched grains' size errors; it can read every solid size definition it has a read-out for and
measure the footprint ones."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from ... import PsdError
from ...psd import FOOTPRINT_DEFINITIONS, GRAIN_WEIGHTINGS, NAMES, SOLID_DEFINITIONS, TARGETS, weighted_percentiles
from ..augment import TTA_VIEWS, unview, view
from ..estimator import GRAIN_PROBE_KEY, GRAIN_SIZE_KEYS, DatasetScorer, Estimator, Reading, model_definition
from ..readout import apply_readout, outside_domain
from . import ARCH
from .measure import DEFAULT_SIEVE_METHOD, SIEVE_METHODS, InstanceMeasurements, measure_instances, sieve_size
from .net import FULL_RES, GRID_PX, RECEPTIVE_RADIUS_PX, TRUNK, TRUNK_STAGES, InstanceMaps, decoder_for, net_from_meta
from .scoring import f1_score, fully_visible, match_instances, size_errors
from .stats import STAT_NAMES, instance_stats, raw_psd
from .targets import MAPS, MASK_MAPS, decode_size
from .watershed import DEFAULT_POSTPROCESS, postprocess

logger = logging.getLogger(__name__)

MIN_GRAIN_PIXELS = 64  # fewer pixels taken for grains than this: no apparent grain size (apparent_grain_px)


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
    size_map_px: np.ndarray | None = None  # the network's size map, decoded to pixels (None without one)
    # the statistics the read-out extrapolates from (readout.outside_domain; its reading is held, apply_readout)
    readout_outside: tuple[str, ...] = ()


def footprint_percentiles(m: InstanceMeasurements, definition: str, weighting: str, where: str) -> np.ndarray:
    """d10/d50/d90 (mm) of measured grains in a footprint definition (feret-min, feret-max, ecd),
    weighted by number, footprint area or volume; grains touching the image's edge are left out
    (their size there is not theirs)."""
    size = {"feret-min": m.min_feret_mm, "feret-max": m.max_feret_mm, "ecd": m.eq_diameter_mm}[definition]
    whole = ~m.touches_edge
    if not whole.any():
        raise PsdError(f"{where}: no whole grain found (every one touches the image's edge): no {definition} "
                       "to measure")
    weights = {"number": None, "area": m.area_mm2, "volume": m.volume_mm3}[weighting]
    return weighted_percentiles(size[whole], None if weights is None else weights[whole])


def to_grid(n: int) -> int:
    """`n` px rounded up to a multiple of GRID_PX."""
    return -(-n // GRID_PX) * GRID_PX


def grid_shape(h: int, w: int) -> tuple[int, int]:
    """H, W rounded up to multiples of GRID_PX: the size the network runs an H×W image at (`on_grid`)."""
    return to_grid(h), to_grid(w)


def on_grid(x: torch.Tensor) -> torch.Tensor:
    """N×C×H×W `x` padded at its bottom and right, by repeating its last row and column, to `grid_shape`."""
    h, w = x.shape[-2:]
    gh, gw = grid_shape(h, w)
    return F.pad(x, (0, gw - w, 0, gh - h), mode="replicate") if (gh, gw) != (h, w) else x


def averaged_maps(maps_fn, x: torch.Tensor, views: tuple[tuple[int, bool], ...]) -> np.ndarray:
    """The mean of `maps_fn` (N×3×H×W → N×C×H×W maps) over `views` of the images `x`, each
    view's maps turned back into the image's frame (test-time augmentation; any H, W). The images
    are put on the stride grid first (`on_grid`), so that the maps of a tile starting on the grid
    are those of one pass: each of the network's strided maps is then exactly half the size of the
    one before, and its decoder's upsampling puts every pixel where one pass puts it (off the grid
    the ratio of two sizes, so each pixel's place, depends on the image's whole size); and a turned
    or mirrored view starts at a corner on the grid too, so every view samples the image at the
    same pixels (one that started at an off-grid far corner would put its strides elsewhere in a
    tile than in the whole image)."""
    h, w = x.shape[-2:]
    x = on_grid(x)
    total = None
    for k, flip in views:
        m = torch.from_numpy(np.asarray(maps_fn(view(x, k, flip).contiguous()), dtype=np.float32))
        m = unview(m, k, flip)
        total = m if total is None else total + m
    return (total / len(views))[..., :h, :w].contiguous().numpy()


def size_map_px(maps: np.ndarray) -> np.ndarray | None:
    """The size map of one image's maps (C×H×W), decoded to pixels; None for a model without one."""
    return decode_size(maps[MAPS.index("size")]) if len(maps) > MAPS.index("size") else None


def tile_margin(stages: int) -> int:
    """The overlap (px, on the grid of GRID_PX) that tiles of an image need for a trunk of `stages` stages: its
    maps' receptive radius rounded up."""
    return to_grid(RECEPTIVE_RADIUS_PX[stages])


class InstanceEstimator(Estimator):
    """Images → instance masks, measurements and d10/d50/d90. `run` runs the network: a
    normalised float32 N×3×H×W tensor → N×C×H×W maps in [0, 1] (PyTorch or ONNX Runtime)."""

    any_size = True
    finds_grains = True
    torchscript = False
    # its maps at a pixel depend on the input within the network's receptive field only, and the watershed runs
    # on the stitched maps once: tiles need to overlap by that radius, not by a grain (none is ever cut); the
    # class's for the default trunk, each model's own for its trunk (__init__)
    tile_margin_px = tile_margin(TRUNK_STAGES)
    int8 = False  # its maps feed a watershed: int8 is not offered (and not measured) for it
    output_name = "maps"
    output_doc = ("float32 NxCxHxW maps in [0, 1], C = len(maps): foreground, boundary, normalised distance, size map "
                  "(log size of each pixel's particle); run each image padded at its bottom and right (last row and "
                  "column repeated) to multiples of 32 px, average the maps over the views meta.json's tta names, cut "
                  "them back to the image, then post-process with psdfactory.learn.instances.estimator."
                  "InstanceEstimator (watershed, measurement, read-out in meta.json)")

    def __init__(self, meta: dict, run=None, net: nn.Module | None = None):
        super().__init__(meta, run, net)
        self.post = dict(meta.get("postprocess") or DEFAULT_POSTPROCESS)
        self.method = meta.get("sieve_method", DEFAULT_SIEVE_METHOD)
        self.readout = meta.get("readout")
        self.views = TTA_VIEWS[meta.get("tta", "none")]  # a model from before TTA: one view
        self.tile_margin_px = tile_margin(meta.get("trunk_stages", TRUNK_STAGES))

    @property
    def readout_held(self) -> bool:
        """Its read-out holds a reading within the label / visible-size ratios it was fitted on
        (`readout.apply_readout`): one fitted since the ratios are recorded."""
        return bool(self.readout) and self.readout.get("ratio_lo") is not None

    # ---- the interface -----------------------------------------------------------------------

    @classmethod
    def train(cls, params, results_root: Path, out_dir: Path, settings: dict | None = None) -> dict:
        """From the scene folders only (whole masks at render size, cropped as it trains): no pack."""
        from .training import InstanceSettings, train_instances

        if settings is None:
            raise PsdError(f"arch {ARCH!r} needs the train.{ARCH} settings (config.train_params gives them)")
        return train_instances(params, InstanceSettings.from_dict(settings), results_root, out_dir, cls)

    @classmethod
    def build_net(cls, meta: dict) -> nn.Module:
        return net_from_meta(meta)

    @classmethod
    def meta_problems(cls, meta: dict) -> list[str]:
        return readout_problems(meta)

    def inference_module(self) -> nn.Module:
        return InstanceMaps(super().inference_module()).eval()

    def outputs(self, images_u8: torch.Tensor) -> np.ndarray:
        """The maps of uint8 N×3×H×W images, averaged over the model's test-time views."""
        from ..data import normalise

        return averaged_maps(self.run, normalise(images_u8), self.views)

    def read(self, outputs: np.ndarray, mm_per_px: list[float]) -> list[Reading]:
        return [self.reading(self.analyse_maps(mp, s)) for mp, s in zip(outputs, mm_per_px, strict=True)]

    @classmethod
    def definitions(cls, meta: dict) -> tuple[str, ...]:
        """Its own definition, the other solid ones it has a read-out for, and the footprint ones
        (measured on the whole grains it finds)."""
        return (model_definition(meta), *(meta.get("readouts") or {}), *FOOTPRINT_DEFINITIONS)

    @classmethod
    def weightings(cls, meta: dict, definition: str) -> tuple[str, ...]:
        """A solid definition's read-out is fitted to labels of the training weighting only; the
        footprint definitions, measured on the grains found, are weighted by number, footprint
        area or volume alike."""
        if definition in FOOTPRINT_DEFINITIONS:
            own = meta.get("weighting", "number")
            return (own, *(w for w in GRAIN_WEIGHTINGS if w != own))
        return super().weightings(meta, definition)

    def in_definition(self, reading: Reading, definition: str, weighting: str, where: str) -> np.ndarray:
        """d10/d50/d90 in the definition asked: the model's own read-out, another solid
        definition's read-out, or a footprint definition measured on the whole grains it found
        (those touching the image's edge left out: their size there is not theirs), weighted by
        number, footprint area or volume."""
        res = reading.grains
        if definition == model_definition(self.meta):
            return res.calibrated
        if definition in FOOTPRINT_DEFINITIONS:
            return footprint_percentiles(res.measurements, definition, weighting, where)
        return apply_readout(self.meta["readouts"][definition], res.stats[None])[0]

    def scorer(self, results_root: Path, dataset: str) -> DatasetScorer:
        return SegmentationScorer(self, results_root, dataset)

    def apparent_grain_px(self, outputs: np.ndarray) -> float | None:
        """The median of the size map (decoded to px) over the pixels the network takes for grains:
        an area-weighted median grain size. None without a size map or with under
        `MIN_GRAIN_PIXELS` grain pixels."""
        size_px = size_map_px(outputs)
        if size_px is None:
            return None
        grain = outputs[MAPS.index("foreground")] > self.post["threshold"]
        if grain.sum() < MIN_GRAIN_PIXELS:
            return None
        return float(np.median(size_px[grain]))

    # ---- its own steps -----------------------------------------------------------------------

    @staticmethod
    def reading(res: InstanceResult) -> Reading:
        return Reading(res.calibrated, grains=res)

    def analyse_maps(self, maps: np.ndarray, mm_per_px: float, post: dict | None = None) -> InstanceResult:
        mask = postprocess(maps, post or self.post)
        return self.result(mask, mm_per_px, size_map_px(maps))

    def result(self, mask: np.ndarray, mm_per_px: float, size_px: np.ndarray | None = None) -> InstanceResult:
        m = measure_instances(mask, mm_per_px, volume_from=self.method, size_map_px=size_px)
        stats = instance_stats(m, self.method)
        psd = raw_psd(m, self.method)
        raw = np.array([psd[k] for k in TARGETS]) if psd else np.full(3, np.nan)
        cal = apply_readout(self.readout, stats)[0] if self.readout else raw.copy()
        outside = tuple(outside_domain(self.readout, stats[None])) if self.readout else ()
        return InstanceResult(mask, m, stats, raw, cal, sieve_size(m, self.method), psd, size_px, outside)

    def analyse(self, images_u8: torch.Tensor, mm_per_px: float | list[float]) -> list[InstanceResult]:
        """uint8 N×3×H×W → one result per image (mm per pixel: one for all, or one each)."""
        return [r.grains for r in self.predict(images_u8, mm_per_px)]

    def all_maps(self, images: torch.Tensor, batch: int = 4) -> np.ndarray:
        return np.concatenate([self.outputs(images[i : i + batch]) for i in range(0, len(images), batch)])


class SegmentationScorer(DatasetScorer):
    """Evaluation of the grains found in a dataset's scenes against their true masks: precision /
    recall / F1 at IoU 0.5, the raw (uncalibrated) PSD's R², and the size errors of the matched
    grains by every sieve method (on the predicted masks, on those fully visible, and on the true
    masks: the measurement alone)."""

    KINDS = ("matched", "matched_fully_visible", "true_mask_fully_visible")

    def __init__(self, est: InstanceEstimator, results_root: Path, dataset: str):
        from ...manifest import read_particles

        self.est, self.root, self.dataset = est, Path(results_root), dataset
        self.particles = read_particles(results_root, dataset)
        self.tp = self.n_pred = self.n_true = 0
        self.ious: list[float] = []
        self.f1s: list[float] = []
        self.raw: list[np.ndarray] = []
        self.y: list[list[float]] = []
        self.sizes = {k: {"est": {m: [] for m in SIEVE_METHODS}, "true": []} for k in self.KINDS}

    def add(self, row: dict, reading: Reading) -> dict:
        from ...io import read_png
        from .draw import resize_mask

        res: InstanceResult = reading.grains
        true = read_png(self.root / row["mask_path"]).astype(np.int64)
        true = resize_mask(true, res.mask.shape)
        match = match_instances(res.mask, true)
        self.tp, self.n_pred, self.n_true = self.tp + match.n_matched, self.n_pred + match.n_pred, \
            self.n_true + match.n_true
        self.ious += match.iou.tolist()
        self.f1s.append(match.f1)
        self.raw.append(res.raw)
        self.y.append([float(row[t]) for t in TARGETS])
        p = self.particles.get(row["scene_id"])
        if p is None:
            raise PsdError(f"the particle manifest of {self.dataset!r} has no rows for {row['scene_id']}")
        size_by_id = np.full(int(p["particle_id"].max()) + 2, np.nan)
        z_by_id = np.full(len(size_by_id), -np.inf)
        size_by_id[p["particle_id"] + 1] = p["size_mm"]  # mask id = particle_id + 1
        z_by_id[p["particle_id"] + 1] = p["z_mm"]
        visible = fully_visible(true, z_by_id)
        m = res.measurements
        k = np.searchsorted(m.ids, match.pred_ids)
        inner = ~m.touches_edge[k]
        tid = match.true_ids
        for key, sel in (("matched", inner), ("matched_fully_visible", inner & visible[tid])):
            self.sizes[key]["true"] += size_by_id[tid[sel]].tolist()
            for meth in m.methods():
                self.sizes[key]["est"][meth] += sieve_size(m, meth)[k[sel]].tolist()
        # the estimators on perfect masks (the size map: the network's, read on the true instances)
        tm = measure_instances(true, m.mm_per_px, size_map_px=res.size_map_px)
        vis = visible[tm.ids]
        self.sizes["true_mask_fully_visible"]["true"] += size_by_id[tm.ids[vis]].tolist()
        for meth in tm.methods():
            self.sizes["true_mask_fully_visible"]["est"][meth] += sieve_size(tm, meth)[vis].tolist()
        return {**{f"raw_{n}_mm": float(v) for n, v in zip(NAMES, res.raw, strict=True)},
                "n_pred": match.n_pred, "n_true": match.n_true, "n_matched": match.n_matched, "f1": match.f1}

    def metrics(self) -> dict:
        from ..metrics import regression_metrics

        raw_arr, y = np.stack(self.raw), np.array(self.y)
        raw = regression_metrics(y, np.where(np.isfinite(raw_arr), raw_arr, np.nanmean(raw_arr, axis=0)))
        raw["images_without_instances"] = int((~np.isfinite(raw_arr).all(axis=1)).sum())
        nan = float("nan")
        seg = {"iou": 0.5, "precision": self.tp / self.n_pred if self.n_pred else nan,
               "recall": self.tp / self.n_true if self.n_true else nan,
               "f1": f1_score(self.tp, self.n_pred, self.n_true), "mean_image_f1": float(np.nanmean(self.f1s)),
               "n_pred": self.n_pred, "n_true": self.n_true, "n_matched": self.tp,
               "mean_matched_iou": float(np.mean(self.ious)) if self.ious else nan}
        size = {"relative_to": "true sieve size", "method": self.est.method,
                **{key: {meth: size_errors(v["est"][meth], v["true"]) for meth in SIEVE_METHODS}
                   for key, v in self.sizes.items()}}
        return {"raw": raw, "segmentation": seg, "size_error": size}

    def summary(self, metrics: dict) -> str:
        se, seg = metrics["size_error"]["matched"][self.est.method], metrics["segmentation"]
        return (", raw " + " / ".join(f"{metrics['raw'][n]['r2']:.3f}" for n in NAMES)
                + f"; P/R/F1 {seg['precision']:.3f}/{seg['recall']:.3f}/{seg['f1']:.3f}; size error of matched "
                + "particles " + (f"median {100 * se['median']:.1f} %, p90 {100 * se['p90']:.1f} %" if se["n"]
                                  else "(none matched)"))


def readout_problems(meta: dict) -> list[str]:
    """What is wrong with an instance model's network shape, post-processing and read-out (plain
    data in model.pt's meta and an export's meta.json); empty when it is fine."""
    def num(v) -> bool:
        return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)

    def nums(v, n: int) -> bool:
        return isinstance(v, list) and len(v) == n and all(num(x) for x in v)

    problems = []
    if meta.get("trunk", TRUNK) != TRUNK:
        problems.append(f"trunk must be {TRUNK!r}")
    stages = meta.get("trunk_stages", TRUNK_STAGES)
    if isinstance(stages, bool) or stages not in RECEPTIVE_RADIUS_PX:
        problems.append(f"trunk_stages must be one of {', '.join(map(str, RECEPTIVE_RADIUS_PX))}")
        stages = TRUNK_STAGES
    n_dec = len(decoder_for(stages))
    dec = meta.get("decoder", list(decoder_for(stages)))
    if not (isinstance(dec, list) and len(dec) == n_dec
            and all(isinstance(c, int) and not isinstance(c, bool) and 1 <= c <= 1024 for c in dec)):
        problems.append(f"decoder must be {n_dec} channel counts")
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
    sizes = [meta.get(k) for k in GRAIN_SIZE_KEYS]
    if any(v is not None for v in sizes) and not (all(num(v) and v > 0 for v in sizes) and sizes[0] <= sizes[1]):
        problems.append(f"{', '.join(GRAIN_SIZE_KEYS)} must be positive numbers (px), grain_px <= grain_px_max")
    probe = meta.get(GRAIN_PROBE_KEY)
    if probe is not None and not (num(probe) and 0 < probe < 1):
        problems.append(f"{GRAIN_PROBE_KEY} must be a factor of the scale between 0 and 1")
    if meta.get("tta", "none") not in TTA_VIEWS:
        problems.append(f"tta must be one of {', '.join(TTA_VIEWS)}")
    if not isinstance(meta.get("auto_scale", False), bool):
        problems.append("auto_scale must be true or false (predict's default reading)")
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
    if not ok:
        return [f"{name} must hold impute/mean/scale ({nf} numbers each) and weights ({nf + 1} × 3)"]
    per_target = ro.get("target_features")
    if per_target is not None and not (isinstance(per_target, list) and len(per_target) == 3 and all(
            isinstance(t, list) and t and all(f in feats for f in t) for t in per_target)):
        return [f"{name}.target_features must be 3 lists of its features (one per target) or absent"]
    # optional (a read-out fitted before they were recorded has none): the fitted ranges and the ratios it is held to
    problems = [f"{name}.{k} must be {n} numbers or absent" for k, n in (("lo", nf), ("hi", nf), ("ratio_lo", 3),
                                                                         ("ratio_hi", 3))
                if ro.get(k) is not None and not nums(ro[k], n)]
    ratios = [ro.get("ratio_lo"), ro.get("ratio_hi")]
    if not problems and (ratios[0] is None) != (ratios[1] is None):
        problems.append(f"{name}.ratio_lo and ratio_hi go together")
    elif not problems and ratios[0] is not None and not all(v > 0 for v in (*ratios[0], *ratios[1])):
        problems.append(f"{name}.ratio_lo and ratio_hi must be > 0")
    return problems


