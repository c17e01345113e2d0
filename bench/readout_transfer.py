#!/usr/bin/env python
"""The instance estimator's read-out on images of another distribution: variants measured, not adopted
(docs/experiments.md, 2026-11-27 and 2026-11-29).

The read-out (`learn.readout`) is a ridge regression from an image's instance statistics to its
labels, fitted on the training scenes: it learns how much the hidden fines pull the labels below the
grains in view. On scenes of another size distribution (the paper's renders: narrower, smaller and
denser) it extrapolates; on a model trained on dense and sparse beds together it must read both. The
variants, each measured against it:

- **scale-free** (`ratio`, `ratio-nomap`): predict log(label / the visible grains' d50) from
  dimensionless statistics only (the visible grains' d10, d90, volume-weighted d-values and mean over
  their d50, their coefficient of variation, the covered fraction, grains per grain area, the pixel
  over the grain size; `ratio` adds the size map's d-values over the visible d50). Scale the bed and
  the reading scales with it.
- **a wider family to fit on** (`--wider CONFIG`): the read-outs fitted on the training scenes *and*
  the train/val scenes of the first dataset of another config (e.g. bench/configs/wider_sizes.yaml:
  the default's rock and table with sizes mean 3-14 mm, sd 2-8 mm, 150-400 particles), made first
  with `snakemake -j2 scenes --configfile CONFIG`.
- **coverage interactions** (`ridge + coverage`): the read-out as trained, plus each size statistic it
  reads times the covered fraction, so that how much the hidden grains pull the labels below the
  grains in view may change with how densely the bed covers the table (a model trained on dense and
  sparse beds together).
- **a part of the training families to fit on** (`--fit-on DATASET ...`): the read-outs fitted on the
  train/val scenes of only these of the model's training datasets (e.g. the dense beds of a model
  trained on dense and sparse ones).

Each model's statistics are read as `psdfactory predict` reads an image (`predict.read_at_scale`),
the read-outs refitted on the model's training scenes (train + val, as training fits them: those of
its calibration_datasets where its meta names them; with --fit-on, those of the datasets it names),
and scored per target on the test split of the training dataset, the other evaluated datasets, and
scenes in the paper's look (`bench/paper_look.py`'s --work folder, 0.3 mm/px), in the sieve and
b-axis definitions: R², Spearman ρ, mean and mean absolute relative error, and the mean absolute
relative error after a leave-one-out calibration on the set's other images (as `psdfactory
calibrate` fits one; NaN where fewer than its minimum of references read a finite size):

    .venv/bin/python bench/readout_transfer.py --model results/models/instances/model.pt \
        --datasets train train_cycles ood_test --paper-look /tmp/psd-paper-look [--wider CONFIG] [--fit-on train]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

RIDGES = (1e-3, 1e-2, 1e-1, 1.0, 10.0)
RATIO_SIZES = ("d10_mm", "d90_mm", "d10_v_mm", "d50_v_mm", "d90_v_mm", "mean_mm")
RATIO_MAP_SIZES = ("map_d10_mm", "map_d50_mm", "map_d90_mm", "map_d50_v_mm")


def image_stats(est, items: list[tuple[Path, float]]) -> np.ndarray:
    """Instance statistics of each (image, mm per px), read as predict reads it."""
    from psdfactory.deploy.predict import DEFAULT_TILE_PX, read_at_scale
    from psdfactory.io import read_photo

    out = []
    for path, mm_per_px in items:
        image, hw = read_photo(path)
        found, _ = read_at_scale(est, image, hw, mm_per_px, DEFAULT_TILE_PX, str(path))
        out.append(found.grains.stats)
    return np.array(out)


def ratio_features(x: np.ndarray, with_map: bool) -> tuple[np.ndarray, np.ndarray]:
    """Dimensionless features of instance statistics (N×len(STAT_NAMES)) and the visible d50 (mm)."""
    from psdfactory.learn.instances.stats import STAT_NAMES

    def c(name: str) -> np.ndarray:
        return x[:, STAT_NAMES.index(name)]

    v50 = c("d50_mm")
    f = [np.log(c(n) / v50) for n in RATIO_SIZES]
    f += [c("std_mm") / c("mean_mm"), c("covered_fraction"),
          np.log(np.expm1(c("log_density")) * v50**2 / 100), np.log(np.expm1(c("log_density_all")) * v50**2 / 100),
          np.log(c("mm_per_px") / v50)]
    if with_map:
        f += [np.log(c(n) / v50) for n in RATIO_MAP_SIZES]
    return np.column_stack(f), v50


def fit_ratio(x: np.ndarray, y: np.ndarray, with_map: bool) -> dict:
    from psdfactory.learn.metrics import cross_validated_r2, ridge_fit

    f, v50 = ratio_features(x, with_map)
    t = np.log(y / v50[:, None])
    cv = {a: float(np.nanmean(cross_validated_r2(f, t, 5, ridge=a))) for a in RIDGES}
    alpha = max(cv, key=cv.get)
    mu, sd, w = ridge_fit(f, t, alpha)
    return {"mean": mu, "scale": sd, "weights": w, "with_map": with_map}


def apply_ratio(ro: dict, x: np.ndarray) -> np.ndarray:
    f, v50 = ratio_features(x, ro["with_map"])
    z = (f - ro["mean"]) / ro["scale"]
    return np.sort(v50[:, None] * np.exp(np.column_stack([np.ones(len(z)), z]) @ ro["weights"]), axis=1)


def coverage_names(features: tuple[str, ...]) -> tuple[str, ...]:
    """The interaction statistics `ridge + coverage` adds: each size statistic among `features` × covered_fraction."""
    from psdfactory.learn.instances.stats import MAP_SIZE_STATS, SIZE_STATS

    return tuple(f"{s}*covered_fraction" for s in (*SIZE_STATS, *MAP_SIZE_STATS) if s in features)


def with_coverage(x: np.ndarray, extra: tuple[str, ...]) -> tuple[np.ndarray, tuple[str, ...]]:
    """Instance statistics (N×len(STAT_NAMES)) with the columns `extra` (coverage_names) appended, and all names."""
    from psdfactory.learn.instances.stats import STAT_NAMES

    x = np.array(x, dtype=float, ndmin=2)
    cov = x[:, STAT_NAMES.index("covered_fraction")][:, None]
    cols = [STAT_NAMES.index(n.split("*")[0]) for n in extra]
    return np.column_stack([x, x[:, cols] * cov]), (*STAT_NAMES, *extra)


def fit_coverage(x: np.ndarray, y: np.ndarray, features: tuple[str, ...], per_target: list | None) -> dict:
    """The ridge read-out as trained (`features`, `per_target`), each target also reading its size statistics ×
    covered_fraction (coverage_names); apply it with apply_coverage, which appends the same columns."""
    from psdfactory.learn.readout import fit_readout

    extra = coverage_names(features)
    xx, names = with_coverage(x, extra)
    targets = None if per_target is None else [
        (*t, *(e for e in extra if e.split("*")[0] in t)) for t in per_target]
    return {**fit_readout(xx, y, features=(*features, *extra), target_features=targets, names=names), "extra": extra}


def apply_coverage(ro: dict, x: np.ndarray) -> np.ndarray:
    from psdfactory.learn.readout import apply_readout

    xx, names = with_coverage(x, tuple(ro["extra"]))
    return apply_readout(ro, xx, names)


def scores(p: np.ndarray, y: np.ndarray) -> dict:
    from scipy.stats import spearmanr

    from psdfactory import PsdError
    from psdfactory.learn import calibration
    from psdfactory.learn.metrics import r2_scores

    e = (p - y) / y
    loo = np.full_like(y, np.nan)
    ok = np.isfinite(p).all(axis=1) & np.isfinite(y).all(axis=1)
    if ok.sum() >= calibration.MIN_REFERENCES:  # a reading it cannot fit (all alike, say) scores NaN, not an abort
        try:
            loo[ok] = (calibration.leave_one_out(p[ok], y[ok]) - y[ok]) / y[ok]
        except PsdError:
            pass
    return {"r2": r2_scores(y, p).tolist(), "rho": [float(spearmanr(p[:, j], y[:, j])[0]) for j in range(3)],
            "err_pct": (100 * e.mean(0)).tolist(), "abs_err_pct": (100 * np.abs(e).mean(0)).tolist(),
            "loo_abs_err_pct": [100 * float(np.abs(c[np.isfinite(c)]).mean()) if np.isfinite(c).any() else np.nan
                                for c in loo.T]}  # over the images it could calibrate


def main() -> None:
    from psdfactory import PsdError
    from psdfactory.cli import configure_logging
    from psdfactory.config import load_config
    from psdfactory.learn.data import training_rows
    from psdfactory.learn.evaluate import eval_rows
    from psdfactory.learn.readout import apply_readout, fit_readout
    from psdfactory.learn.runtime import load_checkpoint, load_estimator
    from psdfactory.psd import definition_targets

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default="config/config.yaml")
    ap.add_argument("--model", nargs="+", required=True, help="instance estimators' model.pt")
    ap.add_argument("--datasets", nargs="+", default=["train", "train_cycles", "ood_test"],
                    help="datasets scored (their test split)")
    ap.add_argument("--paper-look", type=Path, help="bench/paper_look.py's --work folder (its scenes/)")
    ap.add_argument("--wider", type=Path, help="a config whose first dataset's train/val scenes the read-outs are "
                                               "also fitted on (made first: snakemake scenes --configfile)")
    ap.add_argument("--fit-on", nargs="+", metavar="DATASET",
                    help="fit the read-outs on the train/val scenes of only these of each model's training datasets")
    ap.add_argument("--definitions", nargs="+", default=["sieve", "b-axis"])
    ap.add_argument("--out", type=Path, help="write the figures as JSON")
    a = ap.parse_args()
    if a.out is not None:  # refused before any work: it must not overwrite what it reads
        inputs = [Path(m) for m in a.model] + [Path(a.config)] + ([a.wider] if a.wider else [])
        if a.out.is_dir() or any(a.out.resolve() == p.resolve() for p in inputs):
            raise SystemExit(f"--out {a.out} is a folder or one of the inputs (a model or config): give a new file")
    configure_logging()
    try:
        root = Path(load_config(Path(a.config))["results"])
    except PsdError as e:
        raise SystemExit(str(e)) from None
    fit_on = list(dict.fromkeys(a.fit_on or []))
    own = f"train ({', '.join(fit_on)})" if fit_on else "train"  # how the rows name the fit on the model's scenes
    labels_of = {"train": own, "train + wider": f"{own} + wider"}
    trained_on, calibrated_on = {}, {}
    for model in a.model:  # every --fit-on checked before any image is read
        try:
            meta = load_checkpoint(Path(model)).get("meta") or {}
        except PsdError as e:
            raise SystemExit(str(e)) from None
        trained_on[model] = list((meta.get("params") or {}).get("datasets") or [])
        calibrated_on[model] = list(meta.get("calibration_datasets") or trained_on[model])  # as training fits it
        if unknown := [d for d in fit_on if d not in trained_on[model]]:
            raise SystemExit(f"--fit-on {' '.join(unknown)}: not among the datasets {model} was trained on "
                             f"({', '.join(trained_on[model])})")

    def labels(rows: list[dict], d: str) -> np.ndarray:
        return np.array([[r[c] for c in definition_targets(d, "number")] for r in rows], float)

    sets = {d: (root, eval_rows(root, d)) for d in a.datasets}
    if a.paper_look:
        scenes = sorted((a.paper_look / "scenes").iterdir())
        sets["paper look"] = (a.paper_look / "scenes", [
            {"image_path": f"{s.name}/image.png", "mm_per_px": 0.3, **json.loads((s / "labels.json").read_text())}
            for s in scenes if (s / "labels.json").exists()])
    wider = None
    if a.wider:
        wcfg = load_config(a.wider)
        wroot, wds = Path(wcfg["results"]), next(iter(wcfg["datasets"]))
        tr, va, _ = training_rows(wroot, [wds])
        wider = (wroot, tr + va)
    fits = ["train"] + (["train + wider"] if wider else [])
    out = []
    for model in a.model:
        est = load_estimator(Path(model))
        tr, va, _ = training_rows(root, fit_on or calibrated_on[model])
        fit_rows = {"train": tr + va}

        def stats_of(base: Path, rows: list[dict], est=est) -> np.ndarray:
            return image_stats(est, [(base / r["image_path"], float(r["mm_per_px"])) for r in rows])

        fit_x = {"train": stats_of(root, tr + va)}
        if wider:
            fit_x["train + wider"] = np.concatenate([fit_x["train"], stats_of(*wider)])
            fit_rows["train + wider"] = tr + va + wider[1]
        scored = {k: stats_of(base, rows) for k, (base, rows) in sets.items()}
        features = tuple(est.meta["readout"]["features"])
        per_target = est.meta["readout"].get("target_features")  # a read-out per target reads as it was trained
        for fit in fits:
            for d in a.definitions:
                y = labels(fit_rows[fit], d)
                readouts = {"ridge (as trained)": (fit_readout(fit_x[fit], y, features=features,
                                                                     target_features=per_target), apply_readout),
                            "ratio": (fit_ratio(fit_x[fit], y, True), apply_ratio),
                            "ridge + coverage": (fit_coverage(fit_x[fit], y, features, per_target), apply_coverage),
                            "ratio-nomap": (fit_ratio(fit_x[fit], y, False), apply_ratio)}
                for name, (ro, apply) in readouts.items():
                    for k, (_, rows) in sets.items():
                        out.append({"model": model, "fitted_on": labels_of[fit], "definition": d,
                                    "readout": name, "images": k, "n": len(rows),
                                    **scores(apply(ro, scored[k]), labels(rows, d))})

    def f(v: list[float], digits: int = 2) -> str:
        return " / ".join(f"{x:.{digits}f}" for x in v)

    print("| model | fitted on | definition | read-out | images | R² | ρ | mean error % | mean abs error % | "
          "calibrated, leave-one-out: mean abs error % |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in out:
        print(f"| {r['model']} | {r['fitted_on']} | {r['definition']} | {r['readout']} | {r['images']} ({r['n']}) | "
              f"{f(r['r2'])} | {f(r['rho'])} | {f(r['err_pct'], 1)} | {f(r['abs_err_pct'], 1)} | "
              f"{f(r['loo_abs_err_pct'], 1)} |")
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
