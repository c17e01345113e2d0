"""Stage 4: labels of a scene.

- number-weighted d10/d50/d90 (the paper's labels: percentiles of the particle count);
- volume-weighted d10/d50/d90 (what sieves and laser diffraction report);
- the cumulative PSD curves Q0 (number) and Q3 (volume) on fixed size bins;
- per-particle visible pixels from the instance mask and the count of visible particles.

The percentile convention and the curves are ``psdfactory.psd``'s (shared with the estimators
that measure particles in images).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import PsdError
from ..config import config_fields
from ..psd import TARGETS, VOLUME_TARGETS, cumulative_curve, weighted_percentiles


@dataclass(frozen=True)
class LabelParams:
    """The config's `labels` section (defaults: the schema's, config.schema.yaml)."""

    visible_min_px: int  # a particle with at least this many mask pixels counts as visible
    psd_bins: int  # points of the cumulative curves, log-spaced over the size bounds

    @classmethod
    def from_dict(cls, d: dict) -> LabelParams:
        return cls(**config_fields(cls, d, "labels"))


def visible_pixels(mask: np.ndarray, n_particles: int) -> np.ndarray:
    """Pixels of each particle (index = particle_id) in a mask where 0 = table, k = id + 1."""
    if mask.max(initial=0) > n_particles:
        raise PsdError(f"mask holds id {int(mask.max()) - 1} but the scene has only {n_particles} particles")
    return np.bincount(mask.ravel(), minlength=n_particles + 1)[1:]


def scene_labels(
    sizes: np.ndarray, volumes: np.ndarray, visible_px: np.ndarray, image_px: int, bounds: tuple[float, float],
    p: LabelParams,
) -> dict:
    d_n = weighted_percentiles(sizes, None)
    d_v = weighted_percentiles(sizes, volumes)
    lo, hi = max(bounds[0], 1e-3), bounds[1]
    grid = np.geomspace(lo, hi, p.psd_bins)
    return {
        "n_particles": int(len(sizes)),
        "n_visible": int((visible_px >= p.visible_min_px).sum()),
        "covered_fraction": float(visible_px.sum() / image_px),  # image pixels showing a particle
        **{t: float(d) for t, d in zip(TARGETS, d_n, strict=True)},
        **{t: float(d) for t, d in zip(VOLUME_TARGETS, d_v, strict=True)},
        "psd_size_mm": grid.tolist(),
        "psd_q0": cumulative_curve(sizes, np.ones_like(sizes), grid).tolist(),
        "psd_q3": cumulative_curve(sizes, volumes, grid).tolist(),
        "weighting": "d*_mm: number-weighted (the paper's labels); d*_v_mm: volume-weighted",
    }
