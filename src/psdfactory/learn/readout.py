"""The calibrated read-out of the instance estimator: a ridge regression from one image's instance
statistics (`instances.stats.instance_stats`) to its labels. The camera cannot see the hidden fines;
fitted on a training split's instances, the read-out learns what they add. NumPy only, so the
ceiling job (no torch) fits the same read-out to the true masks' footprints."""

from __future__ import annotations

import numpy as np

from .instances.stats import READOUT_FEATURES, SIZE_STATS, STAT_NAMES
from .metrics import MIN_SCENES, cross_validated_r2, ridge_fit, standardisation

READOUT_ALPHAS = (1e-3, 1e-2, 1e-1, 1.0)  # ridge strengths (× N scenes) tried by cross-validation
# how far beyond the range of a feature it was fitted on (× that range) a read-out reads without a word: farther,
# its linear fit extrapolates (grains many times the training grains' size: a photo of cobbles under a model of
# fine rock read a d10 below zero) and `outside_domain` names the features
DOMAIN_MARGIN = 0.5
# the visible grains' number-weighted d10/d50/d90 (instance statistics): what the read-out corrects, and what it is
# held to: each target within the range of label / visible ratios of the scenes it was fitted on (`apply_readout`)
VISIBLE = SIZE_STATS[:3]  # d10_mm, d50_mm, d90_mm


def _impute(x: np.ndarray, fill: np.ndarray) -> np.ndarray:
    x = np.array(x, dtype=float, ndmin=2)
    return np.where(np.isfinite(x), x, fill[None, :])


def readout_columns(x: np.ndarray, features: list[str] | tuple[str, ...],
                    names: tuple[str, ...] = STAT_NAMES) -> np.ndarray:
    """The columns `features` of instance statistics (N×len(names); `names` the columns' names:
    STAT_NAMES, or those and derived statistics appended by a caller that reads those too)."""
    x = np.array(x, dtype=float, ndmin=2)
    return x[:, [names.index(f) for f in features]]


def fit_readout(x: np.ndarray, y: np.ndarray, alphas: tuple[float, ...] = READOUT_ALPHAS, folds: int = 5,
                features: tuple[str, ...] = READOUT_FEATURES,
                target_features: tuple[tuple[str, ...], ...] | None = None,
                names: tuple[str, ...] = STAT_NAMES) -> dict:
    """A ridge read-out of the labels (N×3) from instance statistics (N×len(names); the
    columns `features` are used), as plain lists: NaN features imputed with the training means,
    features standardised, the ridge strength (× N) picked by k-fold cross-validated mean R²
    where there are enough scenes. It records the range of each feature (`lo`, `hi`:
    `outside_domain`) and of each label's ratio to the visible grains' size (`ratio_lo`,
    `ratio_hi`: `apply_readout` holds a reading within it) over these scenes; the cross-validated
    R² that picks the ridge strength is of the linear fit alone (a held reading differs from it
    only where a scene's residual crosses the extreme ratios, at most a hair where it was fitted).
    The ratios are to the number-weighted visible sizes whatever the labels' weighting: for
    volume-weighted labels they are wider, the hold looser.

    `target_features` (one tuple of names per target, each within `features`; default: all of
    them for every target): what each target reads. Targets that read the same statistics are
    fitted together, each such group with its own ridge strength; a target's weights on the
    statistics it does not read are zero, so the read-out applies as any other. Such a read-out
    records `target_features`, and `alpha` per target. `names`: the names of `x`'s columns
    (`readout_columns`); a read-out fitted with other names than STAT_NAMES is applied with the same."""
    y = np.asarray(y, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = y / readout_columns(x, VISIBLE, names)  # how much the labels exceed the visible grains' sizes
    ratio = np.where(np.isfinite(ratio) & (ratio > 0), ratio, np.nan)
    bounded = np.isfinite(ratio).any(axis=0).all()
    x = readout_columns(x, features, names)
    fill = np.nanmean(np.where(np.isfinite(x), x, np.nan), axis=0) if len(x) else np.zeros(x.shape[1])
    fill = np.where(np.isfinite(fill), fill, 0.0)
    x = _impute(x, fill)
    features = list(features)
    if target_features is not None and len(target_features) != y.shape[1]:
        raise ValueError(f"target_features names the statistics of {len(target_features)} targets, the labels have "
                         f"{y.shape[1]}")
    groups: dict[tuple[str, ...], list[int]] = {}  # the statistics read -> the targets that read them
    for t, fs in enumerate(target_features or [tuple(features)] * y.shape[1]):
        if unknown := [f for f in fs if f not in features]:
            raise ValueError(f"target {t} of the read-out reads {unknown}, which are not among its features")
        if len(set(fs)) != len(fs):
            raise ValueError(f"target {t} of the read-out names a statistic twice: {list(fs)}")
        groups.setdefault(tuple(fs), []).append(t)
    mu, sd = standardisation(x)  # per feature: each group's ridge_fit standardises its columns alike
    weights = np.zeros((len(features) + 1, y.shape[1]))
    alpha_t, cv_t = np.ones(y.shape[1]), np.full(y.shape[1], np.nan)
    for fs, ts in groups.items():
        cols = [features.index(f) for f in fs]
        alpha, cv = _ridge_strength(x[:, cols], y[:, ts], alphas, folds)
        weights[np.ix_([0, *(c + 1 for c in cols)], ts)] = ridge_fit(x[:, cols], y[:, ts], alpha)[2]
        alpha_t[ts] = alpha
        if cv is not None:
            cv_t[ts] = cv
    uniform = len(groups) == 1
    out = {"features": features, "impute": fill.tolist(), "mean": mu.tolist(), "scale": sd.tolist(),
           "weights": weights.tolist(), "alpha": float(alpha_t[0]) if uniform else alpha_t.tolist(),
           "n_scenes": int(len(x)),
           "lo": x.min(axis=0).tolist() if len(x) else None, "hi": x.max(axis=0).tolist() if len(x) else None,
           "ratio_lo": np.nanmin(ratio, axis=0).tolist() if bounded else None,
           "ratio_hi": np.nanmax(ratio, axis=0).tolist() if bounded else None,
           "cv_r2": [float(v) for v in cv_t] if len(x) >= MIN_SCENES else None}
    if not uniform:
        out["target_features"] = [list(fs) for fs in target_features]
    return out


def _ridge_strength(x: np.ndarray, y: np.ndarray, alphas: tuple[float, ...],
                    folds: int) -> tuple[float, np.ndarray | None]:
    """The ridge strength (of `alphas`) of best k-fold cross-validated mean R² over the targets `y`,
    and its R² per target; (1.0, None) with fewer than MIN_SCENES scenes."""
    if len(x) < MIN_SCENES:
        return 1.0, None
    cv = {a: cross_validated_r2(x, y, folds, ridge=a) for a in alphas}
    best = max(cv, key=lambda a: np.nanmean(cv[a]))
    return best, cv[best]


def apply_readout(readout: dict, x: np.ndarray, names: tuple[str, ...] = STAT_NAMES) -> np.ndarray:
    """Calibrated d10/d50/d90 (N×3, mm) from instance statistics (N×len(names)), sorted so
    d10 ≤ d50 ≤ d90. Each target is held within the ratios to the visible grains' size (VISIBLE)
    the labels had on the scenes it was fitted on: it corrects a reading as much as it did there
    and no more, so that where the linear fit extrapolates (`outside_domain`) it neither reads a
    size below zero nor departs from the grains in view by more than it ever learnt. A read-out
    fitted before the ratios were recorded is not held. `names`: as `fit_readout` was given them."""
    x = np.array(x, dtype=float, ndmin=2)
    f = _impute(readout_columns(x, readout["features"], names), np.asarray(readout["impute"], float))
    z = (f - np.asarray(readout["mean"], float)) / np.asarray(readout["scale"], float)
    p = np.column_stack([np.ones(len(z)), z]) @ np.asarray(readout["weights"], float)
    if readout.get("ratio_lo") is not None:
        seen = readout_columns(x, VISIBLE, names)
        ok = np.isfinite(seen) & (seen > 0)
        lo, hi = seen * np.asarray(readout["ratio_lo"], float), seen * np.asarray(readout["ratio_hi"], float)
        p = np.where(ok, np.clip(p, lo, hi), p)
    return np.sort(p, axis=1)


def outside_domain(readout: dict, x: np.ndarray, names: tuple[str, ...] = STAT_NAMES) -> list[str]:
    """The features of one image's statistics (1 x len(names); `names` as `fit_readout` was given them)
    that lie farther than DOMAIN_MARGIN x the range the read-out was fitted on beyond that range, each as
    "name value (fitted lo to hi)": where the read-out extrapolates. Empty inside it, and for a
    read-out fitted before ranges were recorded. A feature that was constant where it was
    fitted has no range to judge by, and a missing one (NaN: no grain) is imputed as the read-out
    imputes it: neither is named."""
    if readout.get("lo") is None or readout.get("hi") is None:
        return []
    v = _impute(readout_columns(x, readout["features"], names), np.asarray(readout["impute"], float))[0]
    lo, hi = np.asarray(readout["lo"], float), np.asarray(readout["hi"], float)
    pad = DOMAIN_MARGIN * (hi - lo)
    out = ((v < lo - pad) | (v > hi + pad)) & (hi > lo)
    return [f"{f} {v[j]:.3g} (fitted {lo[j]:.3g} to {hi[j]:.3g})" for j, f in enumerate(readout["features"]) if out[j]]
