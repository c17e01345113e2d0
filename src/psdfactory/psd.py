"""What a particle size distribution's numbers mean, for the labels and for every estimator.

Percentile convention (number- or volume-weighted alike): each particle sits at the midpoint of
its own weight in the cumulative distribution, c_i = (W_i - w_i/2) / W, and the percentile is
interpolated linearly between those points (clamped at the ends). With equal weights this is
the 'hazen' method of numpy.percentile.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from . import PsdError

if TYPE_CHECKING:  # numpy is imported where it is used: the CLI reads the names here without it
    import numpy as np

PERCENTILES = (10.0, 50.0, 90.0)
NAMES = tuple(f"d{q:g}" for q in PERCENTILES)  # "d10", "d50", "d90": the per-target keys of metrics and reports
TARGETS = tuple(f"{n}_mm" for n in NAMES)  # the number-weighted labels (the paper's): what the models predict
VOLUME_TARGETS = tuple(f"{n}_v_mm" for n in NAMES)  # the volume-weighted labels

# What a particle's size is: the definitions people measure, one name each (scene/sizes.py measures
# them). Of the solid particle: `sieve` (the side of the smallest square hole it passes), `b-axis`
# and `c-axis` (the intermediate and short sides of its minimum-volume bounding box; the b-axis
# is the size a scene's sampler draws), `esd` (equivalent-sphere diameter). Of the resting
# particle seen from above: `feret-min`, `feret-max` (caliper widths of its silhouette) and `ecd`
# (equivalent-circle diameter of the silhouette's area).
SOLID_DEFINITIONS = ("sieve", "b-axis", "c-axis", "esd")
FOOTPRINT_DEFINITIONS = ("feret-min", "feret-max", "ecd")
SIZE_DEFINITIONS = SOLID_DEFINITIONS + FOOTPRINT_DEFINITIONS
WEIGHTINGS = ("number", "volume")  # what a percentile counts: particles, or their volume (mass)
# what the percentiles of grains measured in a photo may count (predict --weighting): also their footprint
# area, the weight that turns a photo's grains into a grid (Wolman) count, whose points land on a grain
# with a chance proportional to its exposed area
GRAIN_WEIGHTINGS = ("number", "area", "volume")


def check_grain_weighting(weighting: str) -> None:
    """Refuse, naming it, a weighting that is none of GRAIN_WEIGHTINGS (--weighting)."""
    if weighting not in GRAIN_WEIGHTINGS:
        raise PsdError(f"--weighting {weighting!r}: not a weighting; one of {', '.join(GRAIN_WEIGHTINGS)}")


def size_column(definition: str) -> str:
    """The particle table's column of a size definition: 'b-axis' → 'b_axis_mm'."""
    if definition not in SIZE_DEFINITIONS:
        raise PsdError(f"unknown size definition {definition!r}; one of {', '.join(SIZE_DEFINITIONS)}")
    return definition.replace("-", "_") + "_mm"


def definition_targets(definition: str, weighting: str) -> tuple[str, ...]:
    """The scene table's d10/d50/d90 columns of one definition and weighting, e.g. 'd50_sieve_mm'
    (number) or 'd50_sieve_v_mm' (volume)."""
    if weighting not in WEIGHTINGS:
        raise PsdError(f"unknown weighting {weighting!r}; one of {', '.join(WEIGHTINGS)}")
    key = size_column(definition)[:-3]
    return tuple(f"{n}_{key}{'_v' if weighting == 'volume' else ''}_mm" for n in NAMES)


ALL_DEFINITION_TARGETS = tuple(t for d in SIZE_DEFINITIONS for w in WEIGHTINGS for t in definition_targets(d, w))


def weighted_percentiles(values: np.ndarray, weights: np.ndarray | None,
                         q: tuple[float, ...] = PERCENTILES) -> np.ndarray:
    """Percentiles (q in 0..100) of `values` weighted by `weights` (midpoint convention)."""
    import numpy as np

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
    import numpy as np

    order = np.argsort(values)
    v, w = values[order], np.cumsum(weights[order])
    idx = np.searchsorted(v, sizes, side="right")
    return np.where(idx > 0, w[np.maximum(idx - 1, 0)], 0.0) / w[-1]
