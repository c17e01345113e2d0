"""How much of the sky each pixel of a rendered scene sees. In daylight the gaps between the
pebbles of a deep bed are dark: the sky lights them from a narrow cone only. The tiny backend
darkens each pixel by the share of the sky it does not see with `render.occlusion: sky`
(`tiny.py`), from the sky-view factor of its height map.
"""

from __future__ import annotations

import math

import numpy as np

from ... import PsdError

DIRECTIONS = 16  # azimuths over which the horizon is searched
RADIUS_STEPS = 24  # distances (geometrically spaced from 1 px to the radius) sampled along each


def sky_view(height_mm: np.ndarray, px_mm: float, radius_mm: float, directions: int = DIRECTIONS) -> np.ndarray:
    """The sky-view factor of each pixel of a height map (float32 H×W in [0, 1]; Zakšek et al. 2011):
    1 − the mean over `directions` azimuths of the sine of the horizon's elevation, the horizon
    searched out to `radius_mm` (beyond the image the surface continues as its edge). 1 on an open
    plane; ~0.3 at the bottom of a gap as deep as it is wide."""
    h = np.asarray(height_mm, dtype=np.float32)
    if h.ndim != 2 or not h.size:
        raise PsdError(f"a height map must be a non-empty 2-D array, got shape {h.shape}")
    if not (px_mm > 0 and radius_mm > 0):
        raise PsdError(f"sky_view needs a positive scale and radius, got {px_mm} mm/px, {radius_mm} mm")
    r_px = max(radius_mm / px_mm, 1.0)
    steps = np.unique(np.round(np.geomspace(1.0, r_px, RADIUS_STEPS)).astype(int))
    pad = int(steps.max()) + 1
    padded = np.pad(h, pad, mode="edge")
    rows, cols = h.shape
    sines = np.zeros(h.shape, dtype=np.float32)
    for k in range(directions):
        a = 2 * math.pi * k / directions
        best = np.zeros(h.shape, dtype=np.float32)  # the steepest tangent towards the horizon, ≥ 0
        for r in steps:
            dr, dc = int(round(r * math.sin(a))), int(round(r * math.cos(a)))
            dist = math.hypot(dr, dc) * px_mm
            if dist == 0:
                continue
            ahead = padded[pad + dr : pad + dr + rows, pad + dc : pad + dc + cols]
            np.maximum(best, (ahead - h) / np.float32(dist), out=best)
        sines += best / np.sqrt(1 + best * best)
    return (1 - sines / directions).astype(np.float32)


def horizon_radius_mm(dims_mm: np.ndarray) -> float:
    """How far the horizon is searched: the median particle's intermediate (b) axis — far enough to
    see a gap's neighbours' crests, not the bed's far side."""
    d = np.asarray(dims_mm, dtype=float)
    if not len(d):
        raise PsdError("a scene without particles has no horizon radius")
    return float(np.median(d[:, 1]))
