"""How much of the sky each pixel of a rendered scene sees: the grain outline a person draws on a
photo of a bed is the lit top of each pebble, not the shadowed gap beside it where a lower pebble
shows. The render's height map (the surface the camera sees, in mm above the table) gives each
pixel's sky-view factor; pixels of a particle that see less than a set fraction of the sky are
the gaps between the pebbles on top (`lit_mask`), taught as background by the instance
estimator's training with `train.instances.gap_sky_view`.

Pure functions of arrays, and `scene_surface`, which recomputes a scene's height map from its
particles, poses and render record (no new render and no new file: a Cycles re-render shares its
source's geometry and camera, so its gaps are the same).
"""

from __future__ import annotations

import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from .. import PsdError
from ..io import read_json

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


def lit_mask(mask: np.ndarray, view: np.ndarray, threshold: float) -> np.ndarray:
    """The instance mask with each particle pixel whose sky-view factor is below `threshold` set
    to 0 (background): the particles' lit tops, the gaps between them background."""
    m = np.asarray(mask)
    if m.shape != np.shape(view):
        raise PsdError(f"the mask {m.shape} and its sky-view map {np.shape(view)} differ in size")
    return np.where(np.asarray(view) >= threshold, m, 0).astype(m.dtype)


def gap_radius_mm(dims_mm: np.ndarray) -> float:
    """How far the horizon is searched: the median particle's intermediate (b) axis — far enough to
    see a gap's neighbours' crests, not the bed's far side."""
    d = np.asarray(dims_mm, dtype=float)
    if not len(d):
        raise PsdError("a scene without particles has no gaps to find")
    return float(np.median(d[:, 1]))


def scene_surface(scene_dir: Path) -> tuple[np.ndarray, float, float]:
    """(height map in mm, mm per px, the horizon radius in mm) of a rendered scene at its render's
    resolution, recomputed with the tiny backend's rasteriser from the scene's particles, poses and
    render.json (the camera and the ground level the render used)."""
    from .render.tiny import downsample, tiny_raw
    from .stages import load_geometry, load_poses

    scene_dir = Path(scene_dir)
    rend = read_json(scene_dir / "render.json")
    spec = read_json(scene_dir / "spec.json")
    look = rend.get("look") or {}
    missing = [k for k in ("view_fraction", "ground_level_mm", "light_dir") if k not in look]
    if missing or "camera_height_mm" not in rend:
        raise PsdError(f"{scene_dir / 'render.json'} lacks the camera ({', '.join(missing) or 'camera_height_mm'}): "
                       "it was not written by this version's render stage; delete the scene's render outputs (or run "
                       "snakemake --forcerun render_batch) to render it again")
    geometry = load_geometry(scene_dir)
    pos, quat, _ = load_poses(scene_dir)
    res = int(rend["resolution"])
    s = int(rend.get("supersample", 2))  # as the tiny backend renders it, each pixel the mean of its block
    p = SimpleNamespace(resolution=res, supersample=s, camera_height_mm=float(rend["camera_height_mm"]))
    shading = dict(light_rgb=[1.0, 1.0, 1.0], ambient=1.0, light_intensity=1.0, table_rgb=[0.5, 0.5, 0.5],
                   particle_rgb=np.full((len(geometry), 3), 0.5))
    look_ns = SimpleNamespace(**{**look, **shading})
    _, _, height = tiny_raw(spec, geometry, pos, quat, p, look_ns)
    return downsample(height, s), float(rend["mm_per_px"]), gap_radius_mm(geometry.dims_mm)


def scene_sky_view(scene_dir: Path) -> np.ndarray:
    """The sky-view factor of each pixel of a rendered scene (`sky_view` of `scene_surface`)."""
    height, px_mm, radius = scene_surface(scene_dir)
    return sky_view(height, px_mm, radius)
