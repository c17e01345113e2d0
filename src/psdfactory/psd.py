"""What a particle size distribution's numbers mean, for the labels and for every estimator.

Percentile convention (number- or volume-weighted alike): each particle sits at the midpoint of
its own weight in the cumulative distribution, c_i = (W_i - w_i/2) / W, and the percentile is
interpolated linearly between those points (clamped at the ends). With equal weights this is
the 'hazen' method of numpy.percentile.
"""

from __future__ import annotations

import numpy as np

from . import PsdError

PERCENTILES = (10.0, 50.0, 90.0)
NAMES = tuple(f"d{q:g}" for q in PERCENTILES)  # "d10", "d50", "d90": the per-target keys of metrics and reports
TARGETS = tuple(f"{n}_mm" for n in NAMES)  # the number-weighted labels (the paper's): what the models predict
VOLUME_TARGETS = tuple(f"{n}_v_mm" for n in NAMES)  # the volume-weighted labels


def weighted_percentiles(values: np.ndarray, weights: np.ndarray | None,
                         q: tuple[float, ...] = PERCENTILES) -> np.ndarray:
    """Percentiles (q in 0..100) of `values` weighted by `weights` (midpoint convention)."""
    values = np.asarray(values, dtype=float)
    if values.size == 0:
        raise PsdError("no particles to compute percentiles of")
    w = np.ones_like(values) if weights is None else np.asarray(weights, dtype=float)
    if w.shape != values.shape or (w < 0).any() or w.sum() <= 0:
        raise PsdError("percentile weights must be non-negative, one per value, and not all zero")
    order = np.argsort(values, kind="stable")
    v, w = values[order], w[order]
    cum = (np.cumsum(w) - w / 2) / w.sum()
    return np.interp(np.asarray(q) / 100.0, cum, v)


def cumulative_curve(values: np.ndarray, weights: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """Fraction of the total weight in particles not larger than each size (Q(x))."""
    order = np.argsort(values)
    v, w = values[order], np.cumsum(weights[order])
    idx = np.searchsorted(v, sizes, side="right")
    return np.where(idx > 0, w[np.maximum(idx - 1, 0)], 0.0) / w[-1]
