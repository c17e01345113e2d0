"""``psdfactory predict``: d10/d50/d90 in mm for new images, with a ``model.pt`` or an exported ``.onnx``."""

from __future__ import annotations

import csv
import datetime
import json
import logging
import math
import os
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F

from .. import PsdError
from ..config import AUTO_SCALE_MARGIN, LEGACY_AUTO_SCALE_PROBE, PREDICT_TILE_PX
from ..io import is_within, read_photo, same_file, write_json
from ..learn.calibration import apply_calibration, calibration_note, source_reading
from ..learn.data import to_input
from ..learn.estimator import GRAIN_PROBE_KEY, GRAIN_SIZE_KEYS, Estimator, Reading, reading_of
from ..learn.instances.net import GRID_PX
from ..photoset import IMAGE_SUFFIXES, Region
from ..psd import SOLID_DEFINITIONS, TARGETS

logger = logging.getLogger(__name__)


NOT_PHOTOS = {"mask.png"}  # the factory's instance masks, found beside its images in a results folder


def is_dir(p: Path) -> bool:
    """Path.is_dir, False (not an error) for a name too long or a path it cannot look at: the
    file's own row then says why."""
    try:
        return p.is_dir()
    except OSError:
        return False


def expand_inputs(paths: list[str]) -> list[Path]:
    """Files as given; folders → their image files, subfolders included (sorted by path),
    skipping the factory's ``mask.png`` files and hidden folders."""
    out: list[Path] = []
    for p in map(Path, paths):
        if is_dir(p):
            out += sorted(f for f in p.rglob("*") if f.suffix.lower() in IMAGE_SUFFIXES and f.name not in NOT_PHOTOS
                          and not any(part.startswith(".") for part in f.relative_to(p).parts) and f.is_file())
        else:
            out.append(p)
    return out


def image_files(inputs: list[str]) -> list[Path]:
    """``expand_inputs``, refusing none found in one line that names the inputs and the suffixes."""
    files = expand_inputs(inputs)
    if not files:
        raise PsdError(f"no image files in {', '.join(inputs)} (looked for {', '.join(sorted(IMAGE_SUFFIXES))} in "
                       "the folders and their subfolders, hidden folders and mask.png files left out)")
    return files


def check_outputs(model: Path, inputs: list[str], **outputs: Path | None) -> None:
    """``_check_outputs``; a path the checks cannot look at (a name too long, no permission) is
    one line too."""
    try:
        _check_outputs(model, inputs, **outputs)
    except OSError as e:
        raise PsdError(f"{e.filename or 'an output'}: {e.strerror}") from None


def _check_outputs(model: Path, inputs: list[str], out: Path | None = None, masks_dir: Path | None = None,
                   overlay_dir: Path | None = None, particles_out: Path | None = None,
                   log: Path | None = None, other_dirs: dict[str, Path] | None = None) -> None:
    """Refuse, before any work, an output that would overwrite or mix with an input: a file output
    that is the model, an input image or another output, a file output with the wrong suffix or
    that is a folder, and an output folder that is or lies inside an input folder, holds an input
    image, or is a file. `other_dirs`: more output folders of a file per image, by their flag."""
    model = Path(model)
    folders = [Path(p) for p in inputs if is_dir(Path(p))]
    images = [Path(p) for p in inputs if not is_dir(Path(p))]
    files = {"--out": out, "--particles": particles_out, "--log": log}
    files = {k: Path(v) for k, v in files.items() if v is not None}
    dirs = {k: Path(v) for k, v in {"--masks": masks_dir, "--overlay": overlay_dir, **(other_dirs or {})}.items()
            if v is not None}
    for flag, path, suffixes in (("--out", files.get("--out"), (".csv", ".json")),
                                 ("--particles", files.get("--particles"), (".csv",))):
        if path is not None and path.suffix.lower() not in suffixes:
            raise PsdError(f"{flag} {path}: must end in {' or '.join(suffixes)}")
    for flag, path in files.items():
        if path.is_dir():
            raise PsdError(f"{flag} {path} is a folder; give a file name")
        if same_file(path, model) or same_file(path, model.with_name("meta.json")):
            raise PsdError(f"{flag} {path} is the model: choose another file")
        hit = (next((i for i in images if same_file(path, i)), None)
               or next((f for f in folders if is_within(path, f)), None))
        if hit is not None:
            raise PsdError(f"{flag} {path} would overwrite or land among the input images ({hit}): choose a file "
                           "outside them")
    named = list(files.items()) + list(dirs.items())
    for flag, path in named:
        blocker = next((a for a in path.absolute().parents if a.exists() and not a.is_dir()), None)
        if blocker is not None:
            raise PsdError(f"{flag} {path}: {blocker} is a file, not a folder; choose another place")
    for i, (f1, p1) in enumerate(named):
        for f2, p2 in named[i + 1:]:
            if same_file(p1, p2) or (f2 in dirs and is_within(p1, p2)) or (f1 in dirs and is_within(p2, p1)):
                raise PsdError(f"{f1} {p1} and {f2} {p2} would write over each other: give each its own place")
    for flag, d in dirs.items():
        if d.exists() and not d.is_dir():
            raise PsdError(f"{flag} {d} is a file; give a folder")
        if is_within(model, d) and same_file(model.parent, d):
            raise PsdError(f"{flag} {d} is the model's folder: choose another folder")
        hit = next((f for f in folders if is_within(d, f) or same_file(d, f)), None)
        if hit is not None:
            raise PsdError(f"{flag} {d} is or lies inside the input folder {hit}: its files would be read as "
                           "photos next time; choose a folder outside it")
        hit = next((i for i in images if same_file(i.parent, d)), None)
        if hit is not None:
            raise PsdError(f"{flag} {d} holds the input image {hit}, which a file written there could overwrite; "
                           "choose another folder")


def network_scale(meta: dict) -> float:
    """mm per pixel of the network's input: training images are resized to the input size."""
    return meta["mm_per_px"] * meta["image_resolution"] / meta["input_size"]


MAX_NETWORK_PIXELS = 4096 * 4096  # the largest input a network is run on in one pass (memory grows with it)
# An estimator whose outputs are maps (Estimator.tile_margin_px) runs an image larger than a tile at the network's
# scale tile by tile; its stitched maps, watershed and measurement still grow with the image: ~150 B per network
# pixel above ~0.9 GB (bench/photo_speed.py: 7.1 GB peak for 48 MP), so up to 8192 x 8192 px there (~11 GB).
DEFAULT_TILE_PX = PREDICT_TILE_PX  # a tile's side at the network's scale (predict --tile)
MAX_TILED_PIXELS = 8192 * 8192

# Grains that look larger than those a model trained on are cut along their texture: the network sees a patch of a
# grain, not the grain. Like Cellpose reading an image at its cells' diameter, predict reads such a photo at a
# coarser scale (`choose_scale`): a probe at AUTO_SCALE_PROBE of the model's scale (the factor training recorded,
# meta grain_px_probe_scale) says how large the grains look (Estimator.apparent_grain_px); where that is more than
# AUTO_SCALE_MARGIN times the largest of the model's validation images seen the same way (meta grain_px_probe_max;
# a model without the factor: a quarter of the scale, no margin, as it was trained for), the photo is read where
# they look the validation images' median size (meta grain_px),
# checked there against the largest at the model's scale (grain_px_max). Never finer than the model's scale, never
# with the photo's shorter side under AUTO_SCALE_MIN_PX; a photo whose grains look as the validation images' do is
# read at the model's scale, as before.
AUTO_SCALE_MIN_PX = 64
AUTO_SCALE_REREAD = 1.1  # the check moves the scale by more than this factor: read the photo again there


def target_size(h: int, w: int, meta: dict, mm_per_px: float | None, scale: float = 1.0) -> tuple[int, int]:
    """(height, width) an image of h x w px is resized to before the network: the model's input
    size (an image of the training images' size, `check_field_of_view`), or with `mm_per_px` the
    model's scale times `scale` (< 1: coarser), the aspect ratio kept."""
    if mm_per_px is None:
        return meta["input_size"], meta["input_size"]
    k = scale * mm_per_px / network_scale(meta)
    return max(32, round(h * k)), max(32, round(w * k))


def network_size(path: Path | str, h: int, w: int, meta: dict, mm_per_px: float | None) -> tuple[int, int]:
    """The (height, width) a photo of h x w px is read at by the network (`target_size`); without
    `mm_per_px` only a photo of the training images' size is taken (`check_field_of_view`)."""
    if mm_per_px is None:
        check_field_of_view(path, (h, w), meta)
    return target_size(h, w, meta, mm_per_px)


def check_field_of_view(path: Path | str, size_hw: tuple[int, int], meta: dict) -> None:
    """Without --mm-per-px an image's scale is known only when it was made as the training images
    were: of their size (image_resolution px square, at the model's mm per px). Any other size is
    refused, saying how to find the scale, rather than taken to cover their field of view."""
    res, mm = meta["image_resolution"], meta["mm_per_px"]
    h, w = size_hw
    if (h, w) != (res, res):
        raise PsdError(f"{path}: {w} x {h} px is not the model's field of view ({res} x {res} px at {mm:.4g} mm/px, "
                       f"{res * mm:.0f} mm square), so its scale is unknown: give it with --mm-per-px (a ruler or "
                       "scale card lying in the shot, on the grains' level: mm per px = its length in mm / its "
                       "length in px)")


def network_mm_per_px(size_hw: tuple[int, int], net_hw: tuple[int, int], meta: dict,
                      mm_per_px: float | None) -> float:
    """mm per pixel of an image of `size_hw` px resized to `net_hw` for the network: the model's
    scale up to the rounding of the size (exact here)."""
    if mm_per_px is None:
        return network_scale(meta)
    return mm_per_px * math.sqrt(size_hw[0] * size_hw[1] / (net_hw[0] * net_hw[1]))


def prepare(image: np.ndarray, meta: dict, mm_per_px: float | None,
            size_hw: tuple[int, int] | None = None, max_pixels: int = MAX_NETWORK_PIXELS,
            scale: float = 1.0) -> torch.Tensor:
    """uint8 image → uint8 1x3xHxW tensor at the scale the network was trained on (times `scale`,
    with `mm_per_px`). `size_hw`: the image's full size when `image` was decoded reduced
    (read_photo), so the scale stays exact. `max_pixels`: the most the network takes (more for an
    estimator that tiles)."""
    size = target_size(*(size_hw or image.shape[:2]), meta, mm_per_px, scale)
    if size[0] * size[1] > max_pixels:
        raise PsdError(f"at the model's scale this image is {size[1]} x {size[0]} px, more than the "
                       f"{max_pixels:,} px the network is run on: crop it, or check --mm-per-px")
    if mm_per_px is None:
        return to_input(image, meta["input_size"])[None]  # an image made as the training images were
    t = torch.from_numpy(np.array(image, dtype=np.uint8, copy=True)).permute(2, 0, 1)[None]
    if tuple(image.shape[:2]) == size:
        return t  # already at the model's scale
    t = F.interpolate(t.float(), size=size, mode="bilinear", antialias=True, align_corners=False)
    return t.round().clamp(0, 255).to(torch.uint8)


# ---- large images: tiles at the network's scale ------------------------------------------------


def tile_spans(n: int, tile: int, margin: int) -> list[tuple[int, int, int, int]]:
    """(core start, core end, tile start, tile end) along an axis of `n` px cut into tiles of at
    most `tile` px: the cores (each tile's own part of the stitched maps) lie side by side and
    cover the axis; each tile reaches `margin` px beyond its core on both sides, except at the
    image's own edges. With `tile` and `margin` multiples of GRID_PX every tile starts on the
    network's stride grid, as in one pass; the last one ends at the image's edge."""
    if n <= tile:
        return [(0, n, 0, n)]
    out = []
    start = 0
    while True:
        t0 = max(0, start - margin)
        if n - t0 <= tile:
            out.append((start, n, t0, n))
            return out
        end = t0 + tile - margin
        out.append((start, end, t0, end + margin))
        start = end


def check_tile(tile: int, margin: int) -> None:
    """A tile must hold its two margins and a core of GRID_PX, and sit on the stride grid."""
    if tile % GRID_PX or tile < 2 * margin + GRID_PX:
        raise PsdError(f"--tile {tile}: give a multiple of {GRID_PX} of at least {2 * margin + GRID_PX} px "
                       f"(two margins of {margin} px, what this model's maps see around a pixel, and a core of "
                       f"{GRID_PX} px)")


def tiled_outputs(est: Estimator, x: torch.Tensor, tile: int, where: str = "") -> np.ndarray:
    """The estimator's output maps of uint8 1×3×H×W `x`, computed tile by tile (`tile_spans`,
    margin `est.tile_margin_px`) and stitched from each tile's core: what one pass gives, since
    a pixel's maps see only its margin, in the memory of one tile for the network. Progress
    lines (tile i/N) go to the log."""
    h, w = x.shape[-2:]
    margin = est.tile_margin_px
    rows, cols = tile_spans(h, tile, margin), tile_spans(w, tile, margin)
    n, maps = len(rows) * len(cols), None
    shown = time.monotonic()
    for i, ((r0, r1, a0, a1), (c0, c1, b0, b1)) in enumerate(((r, c) for r in rows for c in cols), start=1):
        out = est.outputs(x[:, :, a0:a1, b0:b1])
        if out.ndim != 4 or out.shape[-2:] != (a1 - a0, b1 - b0):
            raise PsdError(f"{est.arch}: its outputs {out.shape} are not maps of the input's size, as tiling needs")
        if maps is None:
            maps = np.empty((x.shape[0], out.shape[1], h, w), dtype=np.float32)
        maps[:, :, r0:r1, c0:c1] = out[:, :, r0 - a0:r1 - a0, c0 - b0:c1 - b0]
        if i == 1 or i == n or time.monotonic() - shown >= 5.0:
            shown = time.monotonic()
            logger.info(f"{where}: tile {i}/{n} ({w} x {h} px at the network's scale, tiles of {tile} px)")
    return maps


def image_outputs(est: Estimator, x: torch.Tensor, tile: int | None = DEFAULT_TILE_PX, where: str = "") -> np.ndarray:
    """The estimator's outputs for one uint8 1×3×H×W image at the network's scale: in one pass,
    or, for an estimator whose outputs are maps (`tile_margin_px`) and an image larger than
    `tile` px on a side, its maps computed tile by tile and stitched (`tiled_outputs`)."""
    h, w = x.shape[-2:]
    if est.tile_margin_px is None or tile is None or (h <= tile and w <= tile):
        return est.outputs(x)
    check_tile(tile, est.tile_margin_px)
    return tiled_outputs(est, x, tile, where)


def choose_scale(est: Estimator, shorter_side: int, outputs_at, where: str = "") -> float:
    """The factor of the model's scale to read a photo at: 1, or less where its grains look larger
    than the model's validation grains (see AUTO_SCALE_PROBE, AUTO_SCALE_MARGIN). `shorter_side`: the photo's shorter
    side in px at the model's scale; `outputs_at(scale)` → the estimator's outputs of the photo at
    that factor. 1 without the estimator's `auto_scale`, the meta's grain sizes or an apparent one."""
    trained, most, probe_most = (est.meta.get(k) for k in GRAIN_SIZE_KEYS)
    if not est.auto_scale or None in (trained, most, probe_most):
        return 1.0
    recorded = est.meta.get(GRAIN_PROBE_KEY)  # a model of before it: probed as it was trained for
    probe_scale, margin = ((LEGACY_AUTO_SCALE_PROBE, 1.0) if recorded is None
                           else (float(recorded), AUTO_SCALE_MARGIN))
    lowest = AUTO_SCALE_MIN_PX / shorter_side
    probe = max(probe_scale, lowest)
    if probe >= 1.0:
        return 1.0  # too few pixels to look coarser

    def looks(scale: float) -> float | None:  # the grains' apparent size at the model's scale (px)
        seen = est.apparent_grain_px(outputs_at(scale)[0])
        return None if seen is None else seen / scale

    def near(new: float, old: float) -> float:  # the scale looked at already, where the new one is close to it
        return old if abs(math.log(new / old)) <= math.log(AUTO_SCALE_REREAD) else new

    seen = looks(probe)
    # a photo too small for the probe's factor is looked at coarser than 1 but finer than it: its look is compared
    # with the validation grains' largest at the model's scale
    # (the margin is of the probe's reference, where it was measured; the model's-scale one is compared as it is)
    if seen is None or seen <= (margin * probe_most if probe == probe_scale else most):
        return 1.0
    scale = near(max(min(1.0, trained / seen), lowest), probe)
    again = looks(scale)  # seen nearer the training size, the grains are sized better: read where that says
    if again is not None:
        if again <= most:
            return 1.0  # the probe misjudged them: at the model's scale they look as its validation grains do
        scale = near(max(min(1.0, trained / again), lowest), scale)
    if scale == 1.0:
        return 1.0
    logger.info(f"{where}: its grains look {again or seen:.0f} px at the model's scale, larger than on any of the "
                f"model's validation images (at most {most:.0f} px): read at {scale:.3g} x the model's scale, where "
                f"they look {trained:.0f} px as those do at the median (with --no-auto-scale: at its scale)")
    return scale


def read_at_scale(est: Estimator, image: np.ndarray, size_hw: tuple[int, int], mm_per_px: float | None,
                  tile: int | None = DEFAULT_TILE_PX, where: str = "") -> tuple[object, tuple[int, int]]:
    """The estimator's reading of a decoded photo (`read_photo`: `image`, its full size `size_hw`)
    at the model's scale, or at the coarser one `choose_scale` picks (with `mm_per_px` only: the
    scale of an image given without it is the training images'), and the (height, width) the
    network read it at; the outputs of the last scale looked at are reused when it is the one picked."""
    meta = est.meta
    max_px = MAX_TILED_PIXELS if (est.tile_margin_px is not None and tile is not None) else MAX_NETWORK_PIXELS
    last: dict = {}

    def outputs_at(scale: float) -> np.ndarray:
        if last.get("scale") != scale:
            last.clear()  # one image's outputs in memory at a time
            x = prepare(image, meta, mm_per_px, size_hw, max_px, scale)
            last.update(scale=scale, hw=tuple(x.shape[-2:]), outputs=image_outputs(est, x, tile, where))
        return last["outputs"]

    scale = 1.0
    if mm_per_px is not None:
        scale = choose_scale(est, min(target_size(*size_hw, meta, mm_per_px)), outputs_at, where)
    outputs = outputs_at(scale)
    return est.read(outputs, [network_mm_per_px(size_hw, last["hw"], meta, mm_per_px)])[0], last["hw"]


def load_predictor(model_path: Path, device: str = "cpu", runtime: str = "torch") -> Estimator:
    """A model file as its estimator (`learn.estimator.Estimator`): a `model.pt` runs in PyTorch,
    or with `runtime` "onnx" or "auto" in ONNX Runtime where that is faster here
    (`fastpath.choose`); an exported `.onnx` (fp32 or int8, with the export's meta.json beside
    it) runs in ONNX Runtime on the CPU."""
    model_path = Path(model_path)
    if model_path.suffix != ".onnx":
        from ..learn.runtime import load_estimator, pick_device
        from .fastpath import choose

        dev = pick_device(device)
        return choose(load_estimator(model_path, dev), model_path, runtime, dev)
    from ..learn.registry import estimator_class
    from ..learn.runtime import meta_problems
    from .quantize import OrtModel, require_onnxruntime

    require_onnxruntime(f"the ONNX model {model_path}")
    meta_path = model_path.with_name("meta.json")
    if not model_path.is_file():
        raise PsdError(f"model file not found: {model_path}")
    if not meta_path.is_file():
        raise PsdError(f"{meta_path} is missing: an ONNX model needs the meta.json that `psdfactory export` writes "
                       "beside it")
    if meta_path.stat().st_size > 1_000_000:
        raise PsdError(f"{meta_path} refused: {meta_path.stat().st_size} bytes is far more than an export's meta.json "
                       "holds")
    try:
        meta = json.loads(meta_path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise PsdError(f"{meta_path} is not readable JSON ({e})") from None
    problems = meta_problems(meta)
    if problems:
        raise PsdError(f"{meta_path} refused: " + "; ".join(problems))
    if model_path.stat().st_size == 0:
        raise PsdError(f"{model_path} is empty (0 bytes), not an ONNX model; export the model again")
    try:
        ort = OrtModel(model_path, torch.get_num_threads())
    except Exception as e:  # onnxruntime's own errors (InvalidProtobuf, Fail, ...)
        first = (str(e).strip().splitlines() or [type(e).__name__])[0][:200]
        raise PsdError(f"{model_path} is not an ONNX model ONNX Runtime can load ({first}); export the model "
                       "again") from None
    return estimator_class(meta["arch"])(meta, lambda x: ort(x.numpy()))


# `warning`: what makes a reading doubtful though it was made (not a size distribution, few whole grains, a read-out
# extrapolating), in words, as the log says it; empty for a plain reading and a failed one (its `error` says why)
COLUMNS = ["image", *TARGETS, "size_definition", "weighting", "error", "warning"]
# the column sets --resume reads back: a file of before the warning column has none
READABLE_COLUMNS = (frozenset(COLUMNS), frozenset(COLUMNS) - {"warning"})


def reading(meta: dict, requested: str | None, weighting: str | None = None) -> dict:
    """What predict's d-values will be of: {"size_definition", "weighting"}. A model reads the
    definition and weighting it was trained on, and what else its estimator can
    (`Estimator.definitions`, `Estimator.weightings`: an instance model also estimates the other
    solid definitions it has a read-out for, and measures the footprint ones on the grains it
    finds, weighted by number, area or volume). Anything else is refused, naming what it can read."""
    from ..learn.registry import estimator_class

    return reading_of(estimator_class(meta["arch"]), meta, requested, weighting)


def describe_model(meta: dict, model_path: Path, mm_per_px: float | None, margin: int | None = None,
                   tile: int | None = None) -> list[str]:
    lines = [f"model {meta['arch']} ({model_path}): expects images at {meta['mm_per_px']:.4f} mm/px "
             f"({meta['image_resolution']} px over {meta['mm_per_px'] * meta['image_resolution']:.0f} mm); "
             f"network input {meta['input_size']} px = {network_scale(meta):.4f} mm/px"]
    if mm_per_px is None:
        lines.append(f"no --mm-per-px given: only images of the training images' size ({meta['image_resolution']} px "
                     "square) are taken, at their scale; give --mm-per-px for any other")
    if margin is not None and tile is not None:
        lines.append(f"images larger than {tile} px at {network_scale(meta):.4f} mm/px are run in tiles of {tile} px "
                     f"overlapping by {2 * margin} px, their maps stitched and post-processed as one")
    return lines


def not_a_psd(d_mm: np.ndarray) -> str | None:
    """What makes a reading no size distribution (a size <= 0 or not finite, d10 <= d50 <= d90
    broken), in words; None for a plausible one. A regressor's head can give either far from its
    training images."""
    d = np.asarray(d_mm, float)
    text = " / ".join(f"{v:.3g}" for v in d) + " mm"
    if not np.all(np.isfinite(d)):
        return f"d10/d50/d90 {text}, not a number"
    if np.any(d <= 0):
        return f"d10/d50/d90 {text}, a size <= 0"
    if np.any(np.diff(d) < 0):
        return f"d10/d50/d90 {text}, out of order"
    return None


def not_a_psd_warning(where: str, arch: str, d_mm: np.ndarray) -> str | None:
    """The warning, naming the image (`where`), for a model's reading that is no size distribution
    (`not_a_psd`); None for a plausible one."""
    problem = not_a_psd(d_mm)
    if problem:
        return (f"{where}: {arch} read {problem}: not a size distribution. The image is unlike those the model "
                "learnt (material, look, scale): its d-values are no measurement")
    return None


def say_warnings(where: str, warnings: list[str | None], log: logging.Logger = logger) -> str:
    """Each warning about one image's reading (None: none) to the log as it is, and all of them as the
    `warning` cell of its row: without the leading `where` the row's image names already, joined by " | "."""
    said = [w for w in warnings if w]
    for w in said:
        log.warning(w)
    return " | ".join(w.removeprefix(f"{where}: ") for w in said)


# A percentile of n grains rests on about n / 10 of them at d10 and at d90: under this many whole grains, on fewer
# than 3 each
MIN_WHOLE_GRAINS = 30


def grain_count_problem(where: str, grains: object) -> tuple[str | None, str | None]:
    """(error, warning) about how many whole grains a grain finder's reading (`grains`: an InstanceResult, or None
    for a regressor) rests on: an error where it found none, or only grains cut by the image's edge (a read-out from
    no grain is the training scenes' prior, not a measurement); a warning under MIN_WHOLE_GRAINS."""
    m = getattr(grains, "measurements", None)
    if m is None:
        return None, None
    n_all, n_whole = len(m), int((~np.asarray(m.touches_edge, bool)).sum())
    look = "--overlay shows what the model took for grains"
    if n_all == 0:
        return (f"{where}: no grain found, nothing to measure: is it a photo of a grain bed, at the scale given "
                f"(--mm-per-px)? ({look})"), None
    if n_whole == 0:
        return (f"{where}: every grain found ({n_all}) touches the image's edge: none is whole, so no size can be "
                "read. Grains as large as the field of view, a wrong --mm-per-px, or no grains at all "
                f"({look})"), None
    if n_whole < MIN_WHOLE_GRAINS:
        return None, (f"{where}: {n_whole} whole grain{'s' if n_whole > 1 else ''} found: its d10 and d90 each rest "
                      f"on fewer than 3 of them (at least {MIN_WHOLE_GRAINS} for percentiles to mean much): "
                      "photograph a larger area, or check the overlay")
    return None, None


def corrected_reading(est: Estimator, found: Reading, what: dict, where: str) -> tuple[np.ndarray, dict]:
    """(d10/d50/d90 of `found` as `what` asks, the reading they were taken from): a calibrated
    model's basis reading (`learn.calibration.source_reading`) with its correction applied, else the
    reading `what` names as it is."""
    source = source_reading(est.meta, what)
    d = est.in_definition(found, source["size_definition"], source["weighting"], where)
    return apply_calibration(est.meta, what, d), source


def predict_one(est: Estimator, path: Path, mm_per_px: float | None, grains: GrainOutputs | None = None,
                what: dict | None = None, tile: int | None = DEFAULT_TILE_PX, roi: Region | None = None) -> dict:
    """One image → its row; a bad image gives a row whose `error` names the file and the reason.
    Without `mm_per_px` only an image of the training images' size is taken (at their scale);
    any other is refused before it is decoded. An image larger than `tile` px at the network's
    scale is run tile by tile (`image_outputs`), at a coarser scale where its grains look larger than
    the training grains (`read_at_scale`). With `grains` (an estimator that finds grains),
    its overlay, mask and particle rows are written. `what`: the reading (``reading``). `roi`: the
    part of the photo to read (`Region`), as if the photo were cropped to it."""
    meta = est.meta
    what = what or reading(meta, None)
    try:
        def network_hw(h: int, w: int) -> tuple[int, int]:
            return network_size(path if roi is None else f"{path} (its box --roi {roi})", h, w, meta, mm_per_px)

        image, size_hw = read_photo(path, need=network_hw if roi is None else roi.need(path, network_hw))
        frame = (0.0, 0.0, *map(float, size_hw))  # where the image read lies in the photo (particle_rows)
        if roi is not None:
            (image, frame), size_hw = roi.crop(image, size_hw), roi.size_hw
        found, _ = read_at_scale(est, image, size_hw, mm_per_px, tile, str(path))
        if grains is not None:
            grains.write(path, image, size_hw, found.grains, frame)
        error, few = grain_count_problem(str(path), found.grains)
        if error:
            raise PsdError(error)
        d, source = corrected_reading(est, found, what, str(path))
        outside = getattr(found.grains, "readout_outside", ())
        extrapolates = None
        if outside and source["size_definition"] in SOLID_DEFINITIONS:
            held = (", held to the correction of the visible grains' sizes it learnt"
                    if getattr(est, "readout_held", False) else "")
            extrapolates = (f"{path}: its grains lie outside what {meta['arch']}'s read-out was fitted on "
                            f"({'; '.join(outside[:3])}{'; ...' if len(outside) > 3 else ''}): the read-out "
                            f"extrapolates{held}; check the d-values against the grains' own (--size-definition "
                            "feret-min)")
        warning = say_warnings(str(path), [few, extrapolates, not_a_psd_warning(str(path), meta["arch"], d)])
        return {"image": str(path), **{t: float(v) for t, v in zip(TARGETS, d, strict=True)}, **what, "error": "",
                "warning": warning}
    except PsdError as e:
        error = str(e)
    except MemoryError:
        error = f"{path}: out of memory while predicting"
    except Exception as e:  # one image must not stop the others: its row says what went wrong
        error = f"{path}: {type(e).__name__}: {e}"
    return {"image": str(path), **dict.fromkeys(TARGETS), **what, "error": error, "warning": ""}


def predict_rows(est: Estimator, files: list[Path], mm_per_px: float | None = None,
                 done: dict[str, dict] | None = None, grains: GrainOutputs | None = None,
                 what: dict | None = None, tile: int | None = DEFAULT_TILE_PX,
                 roi: Region | None = None) -> Iterator[tuple[dict, bool]]:
    """(row, predicted now) per file, in order, one image in memory at a time; the rows of
    `done` (keyed by image_key; of the same reading) are given back as they are, not predicted again."""
    done = done or {}
    if grains is not None:
        grains.name_outputs(files)
    for f in files:
        old = done.get(image_key(f))
        yield ({**old, "image": str(f)}, False) if old else (predict_one(est, f, mm_per_px, grains, what, tile, roi),
                                                                 True)


def open_inputs(model_path: Path, inputs: list[str], mm_per_px: float | None, device: str, outputs: dict | None = None,
                size_definition: str | None = None, weighting: str | None = None,
                tile: int | None = DEFAULT_TILE_PX, runtime: str = "torch", auto_scale: bool | None = None,
                roi: Region | None = None):
    """The model (its runner and meta, described in the log), the image files to predict and what
    the d-values will be of (``reading``). `outputs`: an instance model's --overlay / --masks /
    --particles (refused for the others); `tile`: checked against the model's margin; `runtime`:
    the engine for a model.pt (`fastpath.RUNTIMES`); `auto_scale`: photos whose grains look larger
    than the training grains read at a coarser scale (`choose_scale`), or not; None: as the model's
    recipe says (`Estimator.auto_scale`, from its meta); `roi`: the box of each photo read, checked
    against the one a calibrated model's references were read in."""
    est = load_predictor(model_path, device, runtime)
    asked = auto_scale is not None
    if asked:
        est.auto_scale = bool(auto_scale)
    meta = est.meta
    if not est.finds_grains and any((outputs or {}).values()):
        raise PsdError(f"--overlay, --masks and --particles need a model that finds grains (e.g. the instance "
                       f"estimator, arch 'instances'); {meta['arch']} reads d10/d50/d90 straight off the image and "
                       "measures no particle")
    what = reading(meta, size_definition, weighting)
    if est.tile_margin_px is not None and tile is not None:
        check_tile(tile, est.tile_margin_px)
    files = image_files(inputs)
    for line in describe_model(meta, model_path, mm_per_px, est.tile_margin_px, tile):
        logger.info(line)
    logger.info(f"d10/d50/d90 of the particles' {what['size_definition']} size, {what['weighting']}-weighted")
    if asked and est.auto_scale and not est.finds_grains:
        logger.warning(f"--auto-scale has no effect here: {meta['arch']} reads d10/d50/d90 straight off the image at "
                       "its training scale; the automatic scale is for models that find grains (arch 'instances')")
    elif asked and est.auto_scale and mm_per_px is None:
        logger.warning("--auto-scale has no effect without --mm-per-px: the photos are taken to be at the training "
                       "images' scale; give their mm per pixel for the automatic scale")
    elif est.auto_scale and est.finds_grains and not all(k in meta for k in GRAIN_SIZE_KEYS):
        logger.info("this model does not record how large its training grains look (trained by an older "
                    "psdfactory): photos are read at its scale only; train it again for the automatic scale")
    elif not asked and est.auto_scale and est.finds_grains and mm_per_px is not None:
        logger.info("this model reads a photo whose grains look larger than its training grains at a coarser scale "
                    "(its recipe's train.instances.auto_scale, as --auto-scale); --no-auto-scale reads every photo "
                    "at its own scale")
    if (note := calibration_note(meta, what)) is not None:  # refuses a reading the calibration is not of
        logger.info(note)
        fitted = meta["calibration"].get("auto_scale")
        if fitted is not None and est.finds_grains and fitted != est.auto_scale:
            logger.warning(f"this model was calibrated on photos read {'with' if fitted else 'without'} the automatic "
                           f"scale, and reads them {'with' if est.auto_scale else 'without'} it now: where that moves "
                           f"a photo's scale the correction does not fit its reading; predict with "
                           f"{'--auto-scale' if fitted else '--no-auto-scale'}, as it was calibrated")
        boxed = meta["calibration"].get("roi")  # checked by calibration_problems when the model was loaded
        if (None if boxed is None else Region.parse(boxed)) != roi:
            then = f"the box {boxed} of its photos" if boxed else "whole photos"
            now = f"the box {roi}" if roi is not None else "whole photos"
            logger.warning(f"this model was calibrated on {then} and reads {now} now: where that changes what is in "
                           "view the correction may not fit; predict as it was calibrated "
                           f"({f'--roi {boxed}' if boxed else 'without --roi'}) where the photos are framed alike")
    return est, files, what


def predict_files(model_path: Path, inputs: list[str], mm_per_px: float | None = None, device: str = "cpu",
                  overlay_dir: Path | None = None, masks_dir: Path | None = None,
                  particles_out: Path | None = None, size_definition: str | None = None,
                  weighting: str | None = None, tile: int | None = DEFAULT_TILE_PX,
                  runtime: str = "torch", auto_scale: bool | None = None, roi: Region | None = None) -> list[dict]:
    """One row per image. An instance model can also write each image's overlay and instance
    mask and a table of every measured particle (`GrainOutputs`). `roi`: the part of every image
    to read (`Region`)."""
    outputs = {"overlay_dir": overlay_dir, "masks_dir": masks_dir, "particles_out": particles_out}
    est, files, what = open_inputs(model_path, inputs, mm_per_px, device, outputs, size_definition, weighting, tile,
                                   runtime, auto_scale, roi)
    grains = GrainOutputs(est.meta, **outputs) if est.finds_grains else None
    rows = [row for row, _ in predict_rows(est, files, mm_per_px, grains=grains, what=what, tile=tile, roi=roi)]
    if grains is not None:
        grains.finish()
    return rows


# ---- streaming to --out: rows written as they come, the final file complete or absent ---------


def image_key(path: str | Path) -> str:
    """What identifies an image across runs (--resume): its absolute path."""
    return os.path.abspath(path)


def partial_path(out: Path) -> Path:
    """Where rows go while a run is under way: <out>.partial.csv (CSV whatever --out's format).
    It is renamed (CSV) or converted (JSON) to --out when every image is done; an interrupted
    run leaves it behind with every row it finished, and --resume picks them up."""
    return out.with_name(out.name + ".partial.csv")


def _row_from_text(r: dict) -> dict | None:
    """A CSV row read back (strings) → a row; None for a malformed one (e.g. the half-written
    last line of a killed run)."""
    try:
        if not r.get("image") or None in r.values() or set(r) not in READABLE_COLUMNS:
            return None
        nums = {k: (float(r[k]) if r[k] not in ("", None) else None) for k in COLUMNS[1:4]}
    except (TypeError, ValueError):
        return None
    if not r["error"] and None in nums.values():
        return None
    return {"image": r["image"], **nums, "size_definition": r["size_definition"], "weighting": r["weighting"],
            "error": r["error"] or "", "warning": r.get("warning") or ""}


def read_rows(path: Path) -> list[dict]:
    """The rows of a predictions file (.csv / .json) or a partial file; [] if there is none."""
    if not path.is_file():
        return []
    try:
        if path.suffix.lower() == ".json":
            data = json.loads(path.read_text())
            rows = data if isinstance(data, list) else []
            return [{"warning": "", **r} for r in rows if isinstance(r, dict) and set(r) in READABLE_COLUMNS]
        with open(path, newline="") as f:
            return [r for r in map(_row_from_text, csv.DictReader(f)) if r is not None]
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, csv.Error) as e:
        raise PsdError(f"--resume: cannot read {path} ({e}); move it away or run without --resume") from None


def done_rows(out: Path) -> dict[str, dict]:
    """Images that already have a prediction in --out or its partial file (--resume); failed
    ones are not counted as done, so they are tried again."""
    rows = read_rows(out) + read_rows(partial_path(out))
    return {image_key(r["image"]): r for r in rows if not r["error"]}


def reading_path(out: Path) -> Path:
    """Where a run with --out records how it read the images (`read_settings`): a --resume keeps
    the rows of a run that read them the same way only."""
    return out.with_name(f".{out.name}.reading.json")


def read_settings(model_path: Path, est: Estimator, mm_per_px: float | None, tile: int | None,
                  runtime: str, roi: Region | None = None) -> dict:
    """What a row's d-values depend on beyond the image and its size definition and weighting
    (those are in the row): the model file (path, size and modification time: a model trained
    again in place is another), the photos' scale, the automatic scale as it applies, the tile,
    the runtime and the part of the photos read."""
    try:
        st = os.stat(model_path)
        size, mtime = st.st_size, st.st_mtime_ns
    except OSError:  # gone since it was loaded: known by its path alone
        size = mtime = None
    return {"model": os.path.abspath(model_path), "model_bytes": size, "model_mtime_ns": mtime,
            "mm_per_px": mm_per_px, "auto_scale": bool(est.auto_scale and est.finds_grains and mm_per_px is not None),
            "tile": tile, "runtime": runtime, "roi": None if roi is None else str(roi)}


def resumable(out: Path, settings: dict) -> str | None:
    """Why the rows already in --out (or its partial file) cannot be kept for a run that reads with
    `settings`; None when they can."""
    try:
        before = json.loads(reading_path(out).read_text())
    except (OSError, ValueError):
        return f"{reading_path(out).name} is missing or unreadable, so how they were read is unknown"
    if not isinstance(before, dict):
        return f"{reading_path(out).name} is not a record of a run"
    changed = [f"{k} {before.get(k)!r} → {v!r}" for k, v in settings.items() if before.get(k) != v]
    return f"they were read otherwise ({'; '.join(changed)})" if changed else None


def lock_path(out: Path) -> Path:
    return out.with_name(f".{out.name}.lock")


class OutLock:
    """One predict run per --out at a time: an exclusive flock on `.<out>.lock` beside it, held
    for the run and released by the kernel when the process ends, however it ends (kill -9 too).
    A second run on the same --out is refused at once, in one line."""

    def __init__(self, out: Path):
        import fcntl

        self.path = lock_path(out)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self.fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
        except OSError as e:
            raise PsdError(f"--out {out}: cannot write in {self.path.parent} ({e.strerror})") from None
        try:
            fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            holder = os.read(self.fd, 32).decode(errors="replace").strip() or "?"
            os.close(self.fd)
            raise PsdError(f"--out {out}: another predict (pid {holder}) is writing it now; wait for it to end "
                           "or choose another --out") from None
        os.ftruncate(self.fd, 0)
        os.write(self.fd, str(os.getpid()).encode())

    def release(self) -> None:
        if self.fd is not None:
            self.path.unlink(missing_ok=True)
            os.close(self.fd)
            self.fd = None


class RowWriter:
    """Rows appended to the partial file as they come: flushed at once (a killed run keeps
    every finished row), fsync'ed at most every `sync_s` seconds and at the end."""

    def __init__(self, out: Path, sync_s: float = 1.0):
        self.out, self.partial, self.sync_s = out, partial_path(out), sync_s
        self.partial.parent.mkdir(parents=True, exist_ok=True)
        self.f = open(self.partial, "w", newline="")
        self.w = csv.DictWriter(self.f, fieldnames=COLUMNS)
        self.w.writeheader()
        self.synced = time.monotonic()

    def write(self, row: dict) -> None:
        self.w.writerow(row)
        self.f.flush()
        if time.monotonic() - self.synced >= self.sync_s:
            os.fsync(self.f.fileno())
            self.synced = time.monotonic()

    def close(self) -> None:
        if not self.f.closed:
            self.f.flush()
            os.fsync(self.f.fileno())
            self.f.close()

    def finish(self) -> None:
        """Every image done: the partial file becomes --out (whole, in one rename)."""
        self.close()
        if self.out.suffix.lower() == ".json":
            write_json(self.out, read_rows(self.partial))
            self.partial.unlink()
        else:
            os.replace(self.partial, self.out)


def progress_line(done: int, total: int, failed: int, seconds: float, predicted: int) -> str:
    """'predict: 120/300 images (1 failed), 35.2 images/s, ETA 0:00:05' — the rate counts the
    images predicted in this run (not those a --resume skipped)."""
    rate = predicted / seconds if seconds > 0 else 0.0
    left = total - done
    eta = "?" if rate <= 0 else str(datetime.timedelta(seconds=round(left / rate)))
    fail = f" ({failed} failed)" if failed else ""
    return f"predict: {done}/{total} images{fail}, {rate:.1f} images/s, ETA {eta}"


class Progress:
    """A progress line on a stream: rewritten in place on a terminal, a new line every
    `interval` seconds otherwise (log files)."""

    def __init__(self, total: int, stream=None, interval: float | None = None, enabled: bool = True):
        self.total, self.stream, self.enabled = total, stream or sys.stderr, enabled
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.interval = interval if interval is not None else (0.5 if self.tty else 10.0)
        self.t0 = self.shown = time.monotonic()
        self.done = self.failed = self.predicted = 0

    def update(self, failed: bool, predicted: bool) -> None:
        self.done += 1
        self.failed += failed
        self.predicted += predicted
        now = time.monotonic()
        if now - self.shown >= self.interval or self.done == self.total:
            self.shown = now
            self.show(end="\n" if self.done == self.total or not self.tty else "")

    def show(self, end: str) -> None:
        if not self.enabled:
            return
        line = progress_line(self.done, self.total, self.failed, time.monotonic() - self.t0, self.predicted)
        self.stream.write(("\r" + line if self.tty else line) + end)
        self.stream.flush()


def stream_predictions(model_path: Path, inputs: list[str], out: Path | None = None, mm_per_px: float | None = None,
                       device: str = "cpu", resume: bool = False, emit=None, progress_stream=None,
                       overlay_dir: Path | None = None, masks_dir: Path | None = None,
                       particles_out: Path | None = None, size_definition: str | None = None,
                       weighting: str | None = None, tile: int | None = DEFAULT_TILE_PX,
                       runtime: str = "torch", auto_scale: bool | None = None,
                       roi: Region | None = None) -> tuple[int, int]:
    """`psdfactory predict`: each image read, predicted and written (to `emit` and to `out`'s
    partial file) before the next is read, so memory stays flat and an interrupted run keeps
    what it did; `out` appears only when every image is done. → (images, failed). An instance
    model can also write overlays, masks and the particle table (`GrainOutputs`). `roi`: the part
    of every image to read (`Region`)."""
    outputs = {"overlay_dir": overlay_dir, "masks_dir": masks_dir, "particles_out": particles_out}
    lock = OutLock(out) if out is not None else None
    try:
        return _stream(model_path, inputs, out, mm_per_px, device, resume, emit, progress_stream, outputs,
                       size_definition, weighting, tile, runtime, auto_scale, roi)
    finally:
        if lock is not None:
            lock.release()


def _stream(model_path, inputs, out, mm_per_px, device, resume, emit, progress_stream, outputs,
            size_definition, weighting, tile, runtime, auto_scale, roi) -> tuple[int, int]:
    est, files, what = open_inputs(model_path, inputs, mm_per_px, device, outputs, size_definition, weighting, tile,
                                   runtime, auto_scale, roi)
    done = done_rows(out) if (resume and out is not None) else {}
    done = {k: r for k, r in done.items() if all(r.get(c) == what[c] for c in what)}  # rows of another reading: again
    if out is not None:
        settings = read_settings(Path(model_path), est, mm_per_px, tile, runtime, roi)
        if done and (why := resumable(Path(out), settings)) is not None:
            logger.warning(f"--resume: the rows already in {out} are not kept: {why}; every image is predicted again")
            done = {}
        write_json(reading_path(Path(out)), settings)
    particles = outputs.get("particles_out")
    if done and particles is not None and not particle_table_current(Path(particles)):
        logger.info(f"--resume: {particles} is missing or has other columns (an older psdfactory's): every image is "
                    "predicted again")
        done = {}
    grains = GrainOutputs(est.meta, **outputs, keep=done) if est.finds_grains else None
    if resume and out is None:
        logger.warning("--resume needs --out: nothing to resume from")
    elif resume:
        n = sum(image_key(f) in done for f in files)
        logger.info(f"--resume: {n} of {len(files)} images already have a prediction in {out} or {partial_path(out)}")
    writer = RowWriter(out) if out is not None else None
    progress = Progress(len(files), progress_stream, enabled=logger.isEnabledFor(logging.INFO))  # not with -q
    failed = 0
    try:
        if roi is not None:
            logger.info(f"reading the box {roi} (left, top, right, bottom in px of each photo as taken) of every "
                        "image: grains cut by its sides are left out of the visible-grain definitions, as at a "
                        "photo's border")
        for row, predicted in predict_rows(est, files, mm_per_px, done, grains, what, tile, roi):
            failed += bool(row["error"])
            if writer is not None:
                writer.write(row)
            if emit is not None:
                emit(row)
            progress.update(bool(row["error"]), predicted)
    finally:
        if writer is not None:
            writer.close()
    if writer is not None:
        writer.finish()
    if grains is not None:
        grains.finish()
    return len(files), failed


# ---- the files of a model that finds grains -------------------------------------------------

# The particle table (--particles): one row per grain found, lengths in mm, areas in mm², volumes in mm³, positions
# in px of the photo (upright, full size), each grain measured on the mask as the network found it (at
# mask_mm_per_px: the network's scale) and converted with that scale. docs/photos.md says what each column is
# in other tools' tables.
PARTICLE_COLUMNS = ["image", "id", "centroid_row_px", "centroid_col_px", "area_mm2", "ecd_mm", "ellipse_major_mm",
                    "ellipse_minor_mm", "feret_min_mm", "feret_max_mm", "sieve_size_mm", "volume_mm3", "touches_edge",
                    "mask_mm_per_px"]


def particle_rows(path: Path | str, res, frame: tuple[float, float, float, float]) -> list[dict]:
    """The particle table's rows of one image from what the estimator found in it (`res`, as
    `learn.instances.estimator.InstanceResult`): every grain of its mask, measured at the
    network's scale (`res.measurements`), its centroid given in the pixels of the photo (upright,
    full size), where the image read covers `frame` = (top, left, height, width) (the whole photo:
    (0, 0, its height, its width); a part of it: `Region.crop`'s); `sieve_size_mm` is the model's
    own per-grain estimate."""
    m = res.measurements
    (h, w), (top, left, H, W) = res.mask.shape, frame
    rows = (m.centroid_row_px + 0.5) * (H / h) - 0.5 + top
    cols = (m.centroid_col_px + 0.5) * (W / w) - 0.5 + left
    mm = float(m.mm_per_px)

    def r(v: float, digits: int = 4) -> float:
        return round(float(v), digits)

    return [{"image": str(path), "id": int(m.ids[i]), "centroid_row_px": r(rows[i], 1),
             "centroid_col_px": r(cols[i], 1),
             "area_mm2": r(m.area_mm2[i]), "ecd_mm": r(m.eq_diameter_mm[i]),
             "ellipse_major_mm": r(m.ellipse_major_mm[i]), "ellipse_minor_mm": r(m.ellipse_minor_mm[i]),
             "feret_min_mm": r(m.min_feret_mm[i]), "feret_max_mm": r(m.max_feret_mm[i]),
             "sieve_size_mm": r(res.sizes_mm[i]), "volume_mm3": r(m.volume_mm3[i]),
             "touches_edge": bool(m.touches_edge[i]), "mask_mm_per_px": r(mm, 6)} for i in range(len(m))]


def particle_table_current(path: Path) -> bool:
    """Whether a particle table (or its partial file) is there with this version's columns."""
    found = False
    for p in (path, partial_path(path)):
        if p.is_file():
            try:
                with open(p, newline="") as f:
                    header = next(csv.reader(f), [])
            except (OSError, UnicodeDecodeError, csv.Error):
                return False
            if header != PARTICLE_COLUMNS:
                return False
            found = True
    return found


class GrainOutputs:
    """The files predict writes for a model that finds grains (`Estimator.finds_grains`), per
    image: the overlay (`<stem>.png`: outlines and sieve sizes in mm drawn on the image), the
    instance mask (`<stem>.png`, 16-bit, 0 = background, k = one particle, at the image's own
    size) and the rows of the particle table (written to `<particles>.partial.csv` as they come,
    renamed when every image is done; with --resume the rows of the images skipped are carried
    over from the previous table). Stems shared by several inputs (e.g. a results folder's
    `image.png`s) get their folder's name in front: `<folder>_<stem>`."""

    def __init__(self, meta: dict, overlay_dir: Path | None = None, masks_dir: Path | None = None,
                 particles_out: Path | None = None, keep: dict[str, dict] | None = None):
        self.meta = meta
        self.overlay_dir = Path(overlay_dir) if overlay_dir else None
        self.masks_dir = Path(masks_dir) if masks_dir else None
        self.particles_out = Path(particles_out) if particles_out else None
        self.names: dict[Path, str] = {}
        self.written = {"overlays": 0, "instance masks": 0}
        self.writer = None
        if self.particles_out is not None:
            old = self._old_particles(set(keep or {}))
            self.partial = partial_path(self.particles_out)
            self.partial.parent.mkdir(parents=True, exist_ok=True)
            self.file = open(self.partial, "w", newline="")
            self.writer = csv.DictWriter(self.file, fieldnames=PARTICLE_COLUMNS)
            self.writer.writeheader()
            self.writer.writerows(old)
            self.n_particles = len(old)

    def _old_particles(self, keys: set[str]) -> list[dict]:
        """The particle rows of the images a --resume skips, from the previous table or its partial file."""
        rows: list[dict] = []
        for path in (self.particles_out, partial_path(self.particles_out)):
            if keys and path.is_file():
                with open(path, newline="") as f:
                    rows += [r for r in csv.DictReader(f) if set(r) == set(PARTICLE_COLUMNS)
                             and image_key(r["image"]) in keys]
        return list({(image_key(r["image"]), r["id"]): r for r in rows}.values())

    def name_outputs(self, files: list[Path]) -> None:
        from collections import Counter

        stems = Counter(f.stem for f in files)
        taken: set[str] = set()
        for f in files:
            name = f.stem if stems[f.stem] == 1 else f"{f.parent.name}_{f.stem}"
            base, k = name, 2
            while name in taken:
                name, k = f"{base}-{k}", k + 1
            taken.add(name)
            self.names[f] = name

    def write(self, path: Path, image: np.ndarray, size_hw: tuple[int, int], res,
              frame: tuple[float, float, float, float]) -> None:
        """The files of one image from what the estimator found in it (`res`: mask, measurements,
        sizes_mm and raw d-values, as `learn.instances.estimator.InstanceResult`). A part of a photo
        (`predict --roi`): `image` and `size_hw` are the part's, its overlay and mask are of the part,
        the particle table's positions in the photo's pixels (`frame`: where the image lies in the photo,
        as `particle_rows` takes it)."""
        from ..io import write_png
        from ..learn.instances.draw import draw_overlay, resize_mask

        m = res.measurements
        if self.masks_dir:  # at the size of the image file
            name = self.names.get(path, path.stem)
            write_png(self.masks_dir / f"{name}.png", resize_mask(res.mask, size_hw).astype(np.uint16))
            self.written["instance masks"] += 1
        if self.overlay_dir:  # on the image as decoded
            over = draw_overlay(image, resize_mask(res.mask, image.shape[:2]), res.sizes_mm, m.ids,
                                min_text_area_px=40)
            write_png(self.overlay_dir / f"{self.names.get(path, path.stem)}.png", over, compress_level=1)
            self.written["overlays"] += 1
        if self.writer is not None:
            self.writer.writerows(particle_rows(path, res, frame))
            self.file.flush()
            self.n_particles += len(m)
        raw = ", ".join(f"{v:.3f}" for v in res.raw)
        logger.debug(f"{path}: {len(m)} particles ({int((~m.touches_edge).sum())} off the edge), raw d10/d50/d90 "
                     f"{raw} mm")

    def finish(self) -> None:
        if self.writer is not None and not self.file.closed:
            self.file.close()
            os.replace(self.partial, self.particles_out)
            logger.info(f"wrote {self.particles_out}: {self.n_particles} particles")
        for what, d in (("overlays", self.overlay_dir), ("instance masks", self.masks_dir)):
            if d is not None:
                self._write_index(d)
                logger.info(f"wrote {self.written[what]} {what} to {d}/ (index.csv: which image each belongs to)")

    def _write_index(self, folder: Path) -> None:
        """`index.csv` in an output folder: image path → its file, for every file there of this
        run's images (a --resume keeps those made before)."""
        from ..io import atomic_path

        rows = [(str(image), f"{name}.png") for image, name in self.names.items() if (folder / f"{name}.png").is_file()]
        with atomic_path(folder / "index.csv") as tmp, open(tmp, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["image", "file"])
            w.writerows(rows)
