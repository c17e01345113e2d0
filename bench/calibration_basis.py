#!/usr/bin/env python
"""Which of a model's readings a calibration should correct: leave-one-out errors per reading.

`psdfactory calibrate` fits, per target, a correction from one of the model's readings of each
reference image to the reference's d10/d50/d90. An instance model has many readings of an image:
its read-outs of the solid definitions (sieve, b-axis, ...) and the footprint definitions measured
on the grains it found (feret-min, feret-max, ecd), each number-, area- or volume-weighted. This
script reads every image once, takes each of those readings, and prints for each the Spearman rank
correlation with the references and the leave-one-out error of the calibration fitted on it
(mean |error| / reference, %), with all the references and with random subsets of a few (the
affine fit a user with 5 sieve results gets: the median over draws of each subset's own
leave-one-out error).

References are synthetic scenes (folders with image.png and labels.json: the workflow's
`results/<dataset>/scenes/*`, or bench/paper_look.py's), labelled in --label-definition and
--label-weighting:

    .venv/bin/python bench/calibration_basis.py --model results/models/instances/model.pt \
        --scenes results/train_cycles/scenes --label-definition b-axis
    .venv/bin/python bench/calibration_basis.py --model M --scenes /tmp/psd-paper-look/scenes \
        --mm-per-px 0.3 --label-definition b-axis

With --true-masks instead of --model, the readings are those of a perfect grain finder: each scene's
own mask.png (every particle in view, as the renderer drew it) measured as an instance model measures
the grains it finds, in the footprint definitions; --at-mm-per-px first resamples the mask to a
coarser scale (a model's: 0.59 for the default), as a model sees the image. What a calibration on
footprints could reach with segmentation left out of the error:

    .venv/bin/python bench/calibration_basis.py --true-masks --scenes /tmp/psd-paper-look/scenes \
        --label-definition b-axis [--at-mm-per-px 0.59]

Synthetic scenes only: the development photos are for measuring, never for choosing (issue 24).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np


def labels_of(scene: Path, definition: str, weighting: str) -> np.ndarray:
    """A scene's d10/d50/d90 (mm) in a size definition and weighting, from its labels.json."""
    from psdfactory.psd import definition_targets

    lab = json.loads((scene / "labels.json").read_text())
    return np.array([lab[k] for k in definition_targets(definition, weighting)], dtype=float)


def scene_scale(scene: Path) -> float:
    """A scene's mm per pixel, from its render.json (the view jitters it where the config says so)."""
    from psdfactory import PsdError

    try:
        return float(json.loads((scene / "render.json").read_text())["mm_per_px"])
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise PsdError(f"{scene / 'render.json'}: no readable mm_per_px ({type(e).__name__}: {e})") from None


def readings(model: Path, images: list[Path],
             mm_per_px: float | list[float] | None) -> dict[tuple[str, str], np.ndarray]:
    """Every reading the model gives of each image (`mm_per_px`: one scale for all, one per image, or
    None: the model's): {(definition, weighting): N x 3}."""
    from psdfactory.deploy.predict import DEFAULT_TILE_PX, load_predictor, network_size, read_at_scale
    from psdfactory.io import read_photo
    from psdfactory.psd import SIZE_DEFINITIONS

    est = load_predictor(model, "cpu")
    if "calibration" in est.meta:  # its readings before any correction: what a calibration would be fitted on
        print(f"{model} is calibrated: its uncalibrated readings are compared", file=sys.stderr)
        est.meta = {k: v for k, v in est.meta.items() if k != "calibration"}
    kinds = [(d, w) for d in SIZE_DEFINITIONS if d in est.definitions(est.meta) for w in est.weightings(est.meta, d)]
    out: dict[tuple[str, str], list[np.ndarray]] = {k: [] for k in kinds}
    scales = mm_per_px if isinstance(mm_per_px, list) else [mm_per_px] * len(images)
    for i, (path, mm) in enumerate(zip(images, scales, strict=True), 1):
        image, size_hw = read_photo(path, need=lambda h, w, p=path, mm=mm: network_size(p, h, w, est.meta, mm))
        found, _ = read_at_scale(est, image, size_hw, mm, DEFAULT_TILE_PX, str(path))
        for d, w in kinds:
            out[(d, w)].append(np.asarray(est.in_definition(found, d, w, str(path)), dtype=float))
        print(f"read {i}/{len(images)} images", file=sys.stderr, end="\r")
    print(file=sys.stderr)
    return {k: np.array(v) for k, v in out.items()}


def true_mask_readings(scenes: list[Path], at_mm_per_px: float | None) -> dict[tuple[str, str], np.ndarray]:
    """The footprint readings of each scene's own instance mask (a perfect grain finder), measured at
    the scene's scale or resampled (nearest) to the coarser `at_mm_per_px`: {(definition, weighting): N x 3}."""
    from psdfactory.io import read_png
    from psdfactory.learn.instances.draw import resize_mask
    from psdfactory.learn.instances.estimator import footprint_percentiles
    from psdfactory.learn.instances.measure import measure_instances
    from psdfactory.psd import FOOTPRINT_DEFINITIONS, GRAIN_WEIGHTINGS

    out: dict[tuple[str, str], list[np.ndarray]] = {(d, w): [] for d in FOOTPRINT_DEFINITIONS for w in GRAIN_WEIGHTINGS}
    for i, scene in enumerate(scenes, 1):
        mask, mm = read_png(scene / "mask.png").astype(np.int64), scene_scale(scene)
        if at_mm_per_px is not None and at_mm_per_px > mm:
            shape = (max(1, round(mask.shape[0] * mm / at_mm_per_px)), max(1, round(mask.shape[1] * mm / at_mm_per_px)))
            mm *= mask.shape[1] / shape[1]
            mask = resize_mask(mask, shape)
        m = measure_instances(mask, mm)
        for d, w in out:
            out[(d, w)].append(np.asarray(footprint_percentiles(m, d, w, str(scene)), dtype=float))
        print(f"measured {i}/{len(scenes)} masks", file=sys.stderr, end="\r")
    print(file=sys.stderr)
    return {k: np.array(v) for k, v in out.items()}


def loo_mape(p: np.ndarray, r: np.ndarray, method: str | None = None) -> np.ndarray:
    """Leave-one-out mean |error| / reference (%) per target of the calibration fitted on `p`."""
    from psdfactory.learn import calibration as cal

    return 100 * np.mean(np.abs(cal.leave_one_out(p, r, method) - r) / r, axis=0)


def subset_mape(p: np.ndarray, r: np.ndarray, k: int, draws: int, seed: int) -> np.ndarray:
    """The median over `draws` random subsets of `k` references of each subset's own LOO error."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(draws):
        idx = rng.choice(len(p), size=k, replace=False)
        try:
            out.append(loo_mape(p[idx], r[idx]))
        except Exception:  # a subset whose readings are all alike: nothing to fit
            continue
    return np.median(out, axis=0) if out else np.full(3, np.nan)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--model", type=Path)
    src.add_argument("--true-masks", action="store_true", help="read the scenes' own masks (a perfect grain finder) "
                     "instead of a model's grains")
    ap.add_argument("--at-mm-per-px", type=float, default=None, help="with --true-masks: resample each mask to this "
                    "coarser scale first (a model's), as the model sees the image")
    ap.add_argument("--scenes", type=Path, nargs="+", required=True, help="folders of scene folders")
    ap.add_argument("--label-definition", default="b-axis")
    ap.add_argument("--label-weighting", default="number", help="number or volume (psd.WEIGHTINGS)")
    ap.add_argument("--mm-per-px", default=None, help="the images' scale: a number, or 'scene' (each scene's own, "
                    "from its render.json); default: the model's")
    ap.add_argument("--subset", type=int, default=5, help="references in the small subsets (0: none)")
    ap.add_argument("--draws", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--save", type=Path, default=None, help="also write every reading (N x 3 per definition and "
                    "weighting, keys 'definition|weighting'), the references, their definition and weighting and "
                    "the scenes' folders to this .npz (bench/calibration_choice.py reads it)")
    args = ap.parse_args(argv)

    from scipy.stats import spearmanr

    from psdfactory import PsdError
    from psdfactory.io import is_within, same_file

    if args.save is not None and (args.save.is_dir() or (args.model and same_file(args.save, args.model))
                                  or any(is_within(args.save, d) for d in args.scenes)):
        ap.error(f"--save {args.save}: a folder, the model or inside a --scenes folder; give a new .npz file")
    scenes = sorted(s.parent for d in args.scenes for s in d.glob("*/labels.json") if (s.parent / "image.png").exists())
    if len(scenes) < 4:
        ap.error(f"{len(scenes)} scenes with image.png and labels.json under {args.scenes}: at least 4 needed")
    ref = np.array([labels_of(s, args.label_definition, args.label_weighting) for s in scenes])
    if args.at_mm_per_px is not None and not (args.true_masks and math.isfinite(args.at_mm_per_px)
                                              and args.at_mm_per_px > 0):
        ap.error("--at-mm-per-px: a positive number of mm per pixel, with --true-masks")
    if args.mm_per_px not in (None, "scene"):
        try:
            scale = float(args.mm_per_px)
        except ValueError:
            scale = float("nan")
        if not (math.isfinite(scale) and scale > 0):
            ap.error(f"--mm-per-px {args.mm_per_px!r}: a positive number of mm per pixel, or 'scene'")
    try:  # a missing or corrupt render.json, mask, image or model: its own message, no traceback
        if args.true_masks:
            reads = true_mask_readings(scenes, args.at_mm_per_px)
            source = "the scenes' own masks" + (f" at {args.at_mm_per_px} mm/px" if args.at_mm_per_px else "")
        else:
            if args.mm_per_px in (None, "scene"):
                scale = None if args.mm_per_px is None else [scene_scale(s) for s in scenes]
            reads = readings(args.model, [s / "image.png" for s in scenes], scale)
            source = f"model {args.model}"
    except PsdError as e:
        ap.exit(1, f"calibration_basis.py: {e}\n")
    if args.save:  # every reading and the references, for an analysis this table does not make
        from psdfactory.io import write_npz

        arrays = {f"{d}|{w}": p for (d, w), p in reads.items()}
        write_npz(args.save, reference=ref, definition=np.array(args.label_definition),
                  weighting=np.array(args.label_weighting), scenes=np.array([str(s.resolve()) for s in scenes]),
                  **arrays)
    print(f"{len(scenes)} scenes; references: {args.label_definition}, {args.label_weighting}-weighted; {source}")
    head = f"{'reading':<22}{'rho d10/d50/d90':>18}{'uncal %':>20}{f'LOO all {len(scenes)} %':>20}"
    head += f"{'LOO affine %':>20}" + (f"{f'LOO of {args.subset} %':>20}" if args.subset else "")
    print(head)
    for (d, w), p in reads.items():
        rho = [spearmanr(p[:, k], ref[:, k])[0] for k in range(3)]
        unc = 100 * np.mean(np.abs(p - ref) / ref, axis=0)
        cells = [" ".join(f"{v:5.2f}" for v in rho), " / ".join(f"{v:4.1f}" for v in unc)]
        scores = [(loo_mape, ()), (loo_mape, ("affine",))]
        if args.subset:
            scores.append((subset_mape, (args.subset, args.draws, args.seed)))
        for fn, extra in scores:
            try:
                cells.append(" / ".join(f"{v:4.1f}" for v in fn(p, ref, *extra)))
            except Exception as e:  # a reading that cannot be calibrated (all alike) says so
                cells.append(f"({type(e).__name__})")
        print(f"{d + ' ' + w:<22}{cells[0]:>18}" + "".join(f"{c:>20}" for c in cells[1:]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
