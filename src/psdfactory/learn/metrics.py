"""Regression metrics in the layout of the paper's table 2 (numpy only)."""

from __future__ import annotations

import numpy as np

from .. import PsdError
from ..psd import NAMES

MIN_SCENES = 6  # fewer scenes than this give no meaningful cross-validated figure


def r2(y: np.ndarray, p: np.ndarray) -> float:
    """Coefficient of determination 1 - SS_res / SS_tot (nan when y is constant)."""
    ss_tot = float(((y - y.mean()) ** 2).sum())
    if ss_tot == 0:
        return float("nan")
    return 1.0 - float(((y - p) ** 2).sum()) / ss_tot


def regression_metrics(y_true: np.ndarray, y_pred: np.ndarray) -> dict:
    """R², MSE, MAE overall and per target, the relative error per target, and the fraction
    of predictions that break d10 ≤ d50 ≤ d90.

    'Overall' pools the three targets (as the paper's table 2 does: its overall R² exceeds every
    per-target R², which only pooling gives); 'mean_r2' is the plain average of the per-target R².
    """
    y = np.asarray(y_true, dtype=float).reshape(-1, 3)
    p = np.asarray(y_pred, dtype=float).reshape(-1, 3)
    if len(y) == 0:
        return {"n": 0}
    out: dict = {"n": int(len(y))}
    err = p - y
    out["overall"] = {"r2": r2(y.ravel(), p.ravel()), "mse": float((err**2).mean()), "mae": float(np.abs(err).mean())}
    for j, name in enumerate(NAMES):
        out[name] = {
            "r2": r2(y[:, j], p[:, j]),
            "mse": float((err[:, j] ** 2).mean()),
            "mae": float(np.abs(err[:, j]).mean()),
            "rel_err": float(np.mean(np.abs(err[:, j]) / np.abs(y[:, j]))),
        }
    out["mean_r2"] = float(np.mean([out[n]["r2"] for n in NAMES]))
    out["order_violations"] = float(np.mean((p[:, 0] > p[:, 1]) | (p[:, 1] > p[:, 2])))
    return out


def r2_scores(y: np.ndarray, pred: np.ndarray) -> np.ndarray:
    """R² per column."""
    ss_res = ((y - pred) ** 2).sum(axis=0)
    ss_tot = ((y - y.mean(axis=0)) ** 2).sum(axis=0)
    return 1.0 - ss_res / np.where(ss_tot > 0, ss_tot, np.nan)


def standardisation(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(mean, scale) per column of `x` that a ridge fit standardises it by (a constant column: scale 1)."""
    sd = x.std(axis=0)
    return x.mean(axis=0), np.where(sd > 0, sd, 1.0)


def ridge_fit(x: np.ndarray, y: np.ndarray, ridge: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(mean, scale, weights) of a ridge regression of `y` on standardised `x` (the penalty
    `ridge` × N on the slopes, none on the intercept; weights[0] the intercept)."""
    mu, sd = standardisation(x)
    a = np.column_stack([np.ones(len(x)), (x - mu) / sd])
    reg = ridge * len(x) * np.eye(a.shape[1])
    reg[0, 0] = 0.0
    return mu, sd, np.linalg.solve(a.T @ a + reg, a.T @ y)


def ridge_predict(x_fit: np.ndarray, y_fit: np.ndarray, x: np.ndarray, ridge: float = 1e-3) -> np.ndarray:
    """A ridge-regularised linear read-out of `y_fit` from `x_fit` (features standardised on
    `x_fit`, the intercept unpenalised), applied to `x`."""
    mu, sd, w = ridge_fit(x_fit, y_fit, ridge)
    return np.column_stack([np.ones(len(x)), (x - mu) / sd]) @ w


def _finite_rows(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rows of (x, y) without a NaN or infinite value."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    ok = np.isfinite(x).all(axis=1) & np.isfinite(y).all(axis=1)
    return x[ok], y[ok]


def _usable(x: np.ndarray, y: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray]:
    x, y = _finite_rows(x, y)
    if len(y) < MIN_SCENES:
        raise PsdError(f"{len(y)} usable scenes: {what} needs at least {MIN_SCENES}")
    return x, y


def cross_validated_r2(x: np.ndarray, y: np.ndarray, folds: int = 5, ridge: float = 1e-3, seed: int = 0) -> np.ndarray:
    """Out-of-fold R² per target of a ridge-regularised linear read-out of `y` (N×T) from `x`
    (N×F); features standardised on each training fold. Rows with a NaN feature are dropped."""
    x, y = _usable(x, y, "a cross-validated ceiling")
    n = len(y)
    order = np.random.default_rng(seed).permutation(n)
    pred = np.empty_like(y)
    for k in range(min(folds, n)):
        test = order[k::min(folds, n)]
        train = np.setdiff1d(order, test)
        pred[test] = ridge_predict(x[train], y[train], x[test], ridge)
    return r2_scores(y, pred)


def fitted_r2(x_fit: np.ndarray, y_fit: np.ndarray, x: np.ndarray, y: np.ndarray, ridge: float = 1e-3) -> np.ndarray:
    """R² per target on (x, y) of the read-out fitted on (x_fit, y_fit) — other scenes, as a model
    is fitted on its training scenes. Rows with a NaN feature are dropped on either side."""
    x_fit, y_fit = _usable(x_fit, y_fit, "fitting a ceiling's read-out")
    x, y = _finite_rows(x, y)
    return r2_scores(y, ridge_predict(x_fit, y_fit, x, ridge))
