"""Regression metrics in the layout of the paper's table 2 (numpy only)."""

from __future__ import annotations

import numpy as np

from ..psd import NAMES


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
