"""The calibrated read-out of the instance estimator: a ridge regression from one image's instance
statistics (`instances.stats.instance_stats`) to its labels. The camera cannot see the hidden fines;
fitted on a training split's instances, the read-out learns what they add. NumPy only, so the
ceiling job (no torch) fits the same read-out to the true masks' footprints."""

from __future__ import annotations

import numpy as np

from .instances.stats import READOUT_FEATURES, STAT_NAMES
from .metrics import MIN_SCENES, cross_validated_r2, ridge_fit

READOUT_ALPHAS = (1e-3, 1e-2, 1e-1, 1.0)  # ridge strengths (× N scenes) tried by cross-validation


def _impute(x: np.ndarray, fill: np.ndarray) -> np.ndarray:
    x = np.array(x, dtype=float, ndmin=2)
    return np.where(np.isfinite(x), x, fill[None, :])


def readout_columns(x: np.ndarray, features: list[str] | tuple[str, ...]) -> np.ndarray:
    """The columns `features` (names of STAT_NAMES) of instance statistics (N×len(STAT_NAMES))."""
    x = np.array(x, dtype=float, ndmin=2)
    return x[:, [STAT_NAMES.index(f) for f in features]]


def fit_readout(x: np.ndarray, y: np.ndarray, alphas: tuple[float, ...] = READOUT_ALPHAS, folds: int = 5,
                features: tuple[str, ...] = READOUT_FEATURES) -> dict:
    """A ridge read-out of the labels (N×3) from instance statistics (N×len(STAT_NAMES); the
    columns `features` are used), as plain lists: NaN features imputed with the training means,
    features standardised, the ridge strength (× N) picked by k-fold cross-validated mean R²
    where there are enough scenes."""
    x, y = readout_columns(x, features), np.asarray(y, float)
    fill = np.nanmean(np.where(np.isfinite(x), x, np.nan), axis=0) if len(x) else np.zeros(x.shape[1])
    fill = np.where(np.isfinite(fill), fill, 0.0)
    x = _impute(x, fill)
    cv = {}
    if len(x) >= MIN_SCENES:
        for a in alphas:
            cv[a] = cross_validated_r2(x, y, folds, ridge=a).tolist()
        alpha = max(cv, key=lambda a: np.nanmean(cv[a]))
    else:
        alpha = 1.0
    mu, sd, w = ridge_fit(x, y, alpha)
    return {"features": list(features), "impute": fill.tolist(), "mean": mu.tolist(), "scale": sd.tolist(),
            "weights": w.tolist(), "alpha": float(alpha), "n_scenes": int(len(x)),
            "cv_r2": [float(v) for v in cv[alpha]] if cv else None}


def apply_readout(readout: dict, x: np.ndarray) -> np.ndarray:
    """Calibrated d10/d50/d90 (N×3, mm) from instance statistics (N×len(STAT_NAMES)), sorted so
    d10 ≤ d50 ≤ d90."""
    x = _impute(readout_columns(x, readout["features"]), np.asarray(readout["impute"], float))
    z = (x - np.asarray(readout["mean"], float)) / np.asarray(readout["scale"], float)
    p = np.column_stack([np.ones(len(z)), z]) @ np.asarray(readout["weights"], float)
    return np.sort(p, axis=1)
