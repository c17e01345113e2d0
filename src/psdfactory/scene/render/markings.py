"""Surface markings of natural stones: veins, speckle and patches, drawn on the particles of a
rendered image (either backend) before the sensor.

A grain finder trained on evenly mottled particles cuts a real pebble into pieces along its own
markings: a quartz vein across it, a dark band, a granite's coarse crystals, a lighter half. Here
a share of the particles carries such markings, so that a model learns that an edge inside a
particle's outline is not a grain's boundary. The mask and the labels do not change: the
particles are the same, only their albedo is.

- ``veins``: thin lines (``vein_width_mm``) of another brightness, lighter (quartz, calcite) or
  darker, meandering across the particle: the zero lines of a smooth random field whose scale is
  ``vein_spacing_mm``, shifted per particle so that a vein does not run on into its neighbour;
- ``speckle``: coarse spots (``speckle_mm``) lighter or darker than the stone, as a granite's
  crystals or a conglomerate's clasts;
- ``patches``: a broad change of brightness across the particle (weathering, a wet half, a
  lighter band), on the scale of the veins' spacing.

Every marked particle carries each kind with probability 1/2 (at least one), at a contrast drawn
from the kind's range: the relative change of brightness at the marking's centre. Each scene's
markings come from its own ``markings`` random stream: switching them on or changing their
settings changes no other draw of the scene.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ...config import config_fields

KINDS = ("veins", "speckle", "patches")
Range = tuple[float, float]


@dataclass(frozen=True)
class MarkingParams:
    """The config's `render.markings` section (defaults: the schema's, config.schema.yaml)."""

    probability: float  # share of the particles that carry markings (0 = none)
    veins: Range  # contrast, per marked particle
    vein_width_mm: Range  # per scene
    vein_spacing_mm: Range  # per scene
    speckle: Range
    speckle_mm: Range
    patches: Range

    @classmethod
    def from_dict(cls, d: dict) -> MarkingParams:
        kw = config_fields(cls, d, "render.markings")
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in kw.items()})


def smooth_field(rng: np.random.Generator, shape: tuple[int, int], sigma_px: float) -> np.ndarray:
    """White noise smoothed by a Gaussian of `sigma_px`, scaled to zero mean and unit sd."""
    f = ndimage.gaussian_filter(rng.standard_normal(shape).astype(np.float32), max(sigma_px, 0.5), mode="wrap")
    return (f - f.mean()) / (f.std() + 1e-6)


def vein_lines(field: np.ndarray, offset: np.ndarray, width_px: float) -> np.ndarray:
    """Lines `width_px` wide along the zero lines of `field + offset` (offset per pixel): 1 on
    the line, falling linearly to 0 at half the width, by the distance |f| / |∇f| to the line."""
    f = field + offset
    gy, gx = np.gradient(field)
    dist = np.abs(f) / (np.hypot(gx, gy) + 1e-6)
    return np.clip(1 - dist / max(width_px / 2, 0.5), 0, 1)


def draw_particles(rng: np.random.Generator, p: MarkingParams, n: int) -> dict[str, np.ndarray]:
    """Per-particle draws (n particles, index 0 = particle id 1), every one made whatever the
    settings, so that one setting changes no other draw: which particles are marked, which kinds
    each carries, each kind's signed contrast, and the veins' offsets."""
    marked = rng.random(n) < p.probability
    kinds = rng.random((n, len(KINDS))) < 0.5
    kinds[np.arange(n), rng.integers(0, len(KINDS), n)] = True  # at least one kind
    sign = np.where(rng.random((n, len(KINDS))) < 0.5, -1.0, 1.0)
    contrast = np.stack([rng.uniform(*getattr(p, k), n) for k in KINDS], axis=1) * sign * kinds * marked[:, None]
    offset = rng.uniform(-1.5, 1.5, n)
    return {"marked": marked, "contrast": contrast.astype(np.float32), "offset": offset.astype(np.float32)}


def add_markings(rgb: np.ndarray, mask: np.ndarray, n: int, px_mm: float, p: MarkingParams,
                 rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    """The rendered image (float H×W×3 in [0, 1]) with markings on a share of the particles of
    `mask` (ids 1..n; 0 is the table) → (image, what was drawn: the count of marked particles and
    of each kind among the visible ones)."""
    width_mm, spacing_mm, speckle_mm = (float(rng.uniform(*r)) for r in (p.vein_width_mm, p.vein_spacing_mm,
                                                                        p.speckle_mm))
    per = draw_particles(rng, p, n)
    visible = np.unique(mask[mask > 0])
    visible = visible[visible <= n]
    drawn = {"marked": int(per["marked"][visible - 1].sum()),
             **{k: int((per["contrast"][visible - 1, i] != 0).sum()) for i, k in enumerate(KINDS)}}
    if not drawn["marked"]:
        return rgb, drawn
    shape = mask.shape
    # the zero lines of a Gaussian field lie ~2.2 sigma apart on average along a line
    veins_f = smooth_field(rng, shape, spacing_mm / px_mm / 2.2)
    speck_f = smooth_field(rng, shape, speckle_mm / px_mm / 2)
    patch_f = smooth_field(rng, shape, spacing_mm / px_mm)
    ids = np.clip(mask.astype(np.int64), 0, n)
    table = np.zeros((1, len(KINDS)), np.float32)
    contrast = np.concatenate([table, per["contrast"]])[ids]  # H×W×3: each pixel's particle's contrasts
    offset = np.concatenate([[0.0], per["offset"]]).astype(np.float32)[ids]
    factor = np.ones(shape, np.float32)
    factor *= 1 + contrast[..., 0] * vein_lines(veins_f, offset, width_mm / px_mm)
    factor *= 1 + contrast[..., 1] * np.clip((speck_f - 1.1) / 0.5, 0, 1)  # ~15 % of the surface
    factor *= 1 + contrast[..., 2] * np.clip(patch_f, -1.5, 1.5) / 1.5
    return np.clip(rgb * factor[..., None], 0, 1).astype(np.float32), drawn
