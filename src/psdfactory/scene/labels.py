"""Stage 4: labels of a scene.

- d10/d50/d90 of every size definition (``psd.SIZE_DEFINITIONS``), number- and volume-weighted;
- the training targets ``d*_mm`` (the configured definition and weighting: by default the sieve
  size, number-weighted as the paper's labels) and ``d*_v_mm`` (the same definition,
  volume-weighted, as sieves report mass);
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
from ..psd import SIZE_DEFINITIONS, TARGETS, VOLUME_TARGETS, cumulative_curve, definition_targets, weighted_percentiles


@dataclass(frozen=True)
class LabelParams:
    """The config's `labels` section (defaults: the schema's, config.schema.yaml)."""

    visible_min_px: int  # a particle with at least this many mask pixels counts as visible
    psd_bins: int  # points of the cumulative curves, log-spaced over the size bounds
    size_definition: str  # what d*_mm are percentiles of (one of psd.SIZE_DEFINITIONS)
    weighting: str  # what d*_mm count: "number" (particles) or "volume"
    particles: str  # which particles they count: "in_view" (centre in the image) or "bed" (all)

    @classmethod
    def from_dict(cls, d: dict) -> LabelParams:
        # without `particles` (config.label_params: the camera sees the whole table) every particle is in view
        return cls(**config_fields(cls, {"particles": "bed", **d}, "labels"))


def in_view(x_mm: np.ndarray, y_mm: np.ndarray, view_mm: float) -> np.ndarray:
    """Which particle centres lie in the camera's square view of `view_mm` mm a side, centred on
    the table (render.json's view_mm and image_origin)."""
    half = float(view_mm) / 2
    return (np.abs(np.asarray(x_mm, float)) < half) & (np.abs(np.asarray(y_mm, float)) < half)


def visible_pixels(mask: np.ndarray, n_particles: int) -> np.ndarray:
    """Pixels of each particle (index = particle_id) in a mask where 0 = table, k = id + 1."""
    if mask.max(initial=0) > n_particles:
        raise PsdError(f"mask holds id {int(mask.max()) - 1} but the scene has only {n_particles} particles")
    return np.bincount(mask.ravel(), minlength=n_particles + 1)[1:]


def scene_labels(
    sizes_by_definition: dict[str, np.ndarray], volumes: np.ndarray, visible_px: np.ndarray, image_px: int,
    bounds: tuple[float, float], p: LabelParams, counted: np.ndarray | None = None,
) -> dict:
    """A scene's labels from its particles' sizes under every definition (name → array), of the
    particles `counted` (a boolean mask; None: all of them). The visible particles and the
    covered fraction are the image's, whatever the labels count."""
    n_bed = len(volumes)
    if counted is not None:
        if not counted.any():
            raise PsdError(f"none of the scene's {n_bed} particles has its centre in the camera's view: no labels "
                           "of the particles in view (labels.particles: bed counts the whole bed)")
        sizes_by_definition = {k: np.asarray(v)[counted] for k, v in sizes_by_definition.items()}
        volumes = np.asarray(volumes)[counted]
    per_definition = {}
    for name in SIZE_DEFINITIONS:
        for weighting, w in (("number", None), ("volume", volumes)):
            d = weighted_percentiles(sizes_by_definition[name], w)
            per_definition.update({t: float(v) for t, v in zip(definition_targets(name, weighting), d, strict=True)})
    sizes = sizes_by_definition[p.size_definition]
    d_main = [per_definition[t] for t in definition_targets(p.size_definition, p.weighting)]
    d_v = [per_definition[t] for t in definition_targets(p.size_definition, "volume")]
    lo, hi = max(bounds[0], 1e-3), bounds[1]
    grid = np.geomspace(lo, hi, p.psd_bins)
    return {
        "n_particles": int(len(sizes)),  # those the labels count
        "n_in_bed": int(n_bed),
        "particles_counted": p.particles,
        "n_visible": int((visible_px >= p.visible_min_px).sum()),
        "covered_fraction": float(visible_px.sum() / image_px),  # image pixels showing a particle
        "size_definition": p.size_definition,
        "weighting": p.weighting,
        **dict(zip(TARGETS, d_main, strict=True)),
        **dict(zip(VOLUME_TARGETS, d_v, strict=True)),
        **per_definition,
        "psd_size_mm": grid.tolist(),
        "psd_q0": cumulative_curve(sizes, np.ones_like(sizes), grid).tolist(),
        "psd_q3": cumulative_curve(sizes, volumes, grid).tolist(),
    }
