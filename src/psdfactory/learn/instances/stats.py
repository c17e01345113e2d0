"""From measured grains to the PSD, and the fixed-length per-image statistics a read-out fits
(torch-free)."""

from __future__ import annotations

import numpy as np

from ... import PsdError
from ...psd import cumulative_curve, weighted_percentiles
from .measure import DEFAULT_SIEVE_METHOD, InstanceMeasurements, sieve_size

PSD_GRID_POINTS = 32


# ---------------------------------------------------------------------------------------------
# from instances to the PSD


def psd_from_instances(
    sizes_mm: np.ndarray,
    volumes_mm3: np.ndarray,
    include: np.ndarray | None = None,
    grid_mm: np.ndarray | None = None,
) -> dict:
    """Number- and volume-weighted d10/d50/d90 (mm) and the Q0/Q3 curves of the included instances.

    Same estimators and key names as the scene labels (`psdfactory.scene.labels.scene_labels`):
    `d*_mm` number-weighted, `d*_v_mm` volume-weighted, `psd_q0`/`psd_q3` the cumulative
    fractions at `psd_size_mm`. `include` is a boolean mask over instances (e.g.
    `~m.touches_edge`; default all). `grid_mm` defaults to 32 log-spaced sizes over the included
    sizes. Raises PsdError when no instance is left.
    """
    sizes = np.asarray(sizes_mm, dtype=float).ravel()
    volumes = np.asarray(volumes_mm3, dtype=float).ravel()
    if volumes.shape != sizes.shape:
        raise PsdError(f"{len(sizes)} sizes but {len(volumes)} volumes")
    keep = np.ones(len(sizes), dtype=bool) if include is None else np.asarray(include, dtype=bool).ravel()
    if keep.shape != sizes.shape:
        raise PsdError(f"include has {len(keep)} entries for {len(sizes)} instances")
    keep = keep & np.isfinite(sizes) & np.isfinite(volumes)
    s, v = sizes[keep], volumes[keep]
    if s.size == 0:
        raise PsdError("no particle instance left to measure a PSD from (none found, or all excluded, e.g. touching "
                       "the image edge)")
    d_n = weighted_percentiles(s, None)
    d_v = weighted_percentiles(s, v)
    if grid_mm is None:
        lo = max(float(s.min()), 1e-3)
        grid = np.geomspace(lo, max(float(s.max()), lo), PSD_GRID_POINTS)
    else:
        grid = np.asarray(grid_mm, dtype=float)
    return {
        "n_instances": int(s.size),
        "d10_mm": float(d_n[0]),
        "d50_mm": float(d_n[1]),
        "d90_mm": float(d_n[2]),
        "d10_v_mm": float(d_v[0]),
        "d50_v_mm": float(d_v[1]),
        "d90_v_mm": float(d_v[2]),
        "psd_size_mm": grid,
        "psd_q0": cumulative_curve(s, np.ones_like(s), grid),
        "psd_q3": cumulative_curve(s, v, grid),
    }


SIZE_STATS = ("d10_mm", "d50_mm", "d90_mm", "d10_v_mm", "d50_v_mm", "d90_v_mm", "mean_mm", "std_mm")
# the same size statistics of the size map's estimate per instance (NaN for a mask alone)
MAP_SIZE_STATS = tuple(f"map_{k}" for k in SIZE_STATS)
STAT_NAMES = (
    *SIZE_STATS,
    "log_density",
    "log_density_all",
    "covered_fraction",
    "edge_fraction",
    "mm_per_px",
    *MAP_SIZE_STATS,
)
# The statistics a read-out may use: those that do not change with the field of view (a larger
# image of the same bed has more instances and fewer of them on its edge) or with the camera.
# READOUT_FEATURES need a mask only (footprints); with the network's size map, a read-out may
# add the size map's statistics (MAP_READOUT_FEATURES).
READOUT_FEATURES = (*SIZE_STATS, "log_density", "log_density_all", "covered_fraction")
MAP_READOUT_FEATURES = (*READOUT_FEATURES, *MAP_SIZE_STATS)


def _size_stats(s: np.ndarray, v: np.ndarray, fill_value: float) -> list[float]:
    """Number- and volume-weighted d10/d50/d90, mean and sd of sizes `s` (volumes `v`), in the
    order of SIZE_STATS; `fill_value` without any size."""
    if not s.size:
        return [float(fill_value)] * len(SIZE_STATS)
    d_n = weighted_percentiles(s, None)
    d_v = weighted_percentiles(s, v) if (v > 0).any() else np.full(3, fill_value)
    return [*map(float, d_n), *map(float, d_v), float(s.mean()), float(s.std())]


def instance_stats(
    measurements: InstanceMeasurements,
    method: str = DEFAULT_SIEVE_METHOD,
    include_edge: bool = False,
    fill_value: float = np.nan,
) -> np.ndarray:
    """Fixed-length feature vector of one image's instances, in the order of STAT_NAMES.

    Size statistics (SIZE_STATS: number- and volume-weighted d10/d50/d90, mean and sd of the
    sieve-size estimate `method`) use the instances not touching the image edge (all with
    `include_edge`); when every instance touches the edge they fall back to all instances, and
    with no instance at all they are `fill_value` (NaN by default: impute before fitting). The
    same statistics of the size map's estimate per instance (MAP_SIZE_STATS; volumes as for
    the others) where the measurements carry one, else `fill_value`. Densities are log(1 + n
    per cm² of image) of the included and of all instances; `covered_fraction` is the share of image pixels in
    an instance, `edge_fraction` the share of instances touching the edge (0 with none), and
    `mm_per_px` the scale (it sets the size of the smallest visible particle).
    """
    sizes = sieve_size(measurements, method)
    n_all = len(sizes)
    keep = np.ones(n_all, dtype=bool) if include_edge else ~measurements.touches_edge
    if not keep.any():
        keep = np.ones(n_all, dtype=bool)
    v = measurements.volume_mm3[keep]
    out = dict.fromkeys(STAT_NAMES, float(fill_value))
    out.update(zip(SIZE_STATS, _size_stats(sizes[keep], v, fill_value), strict=True))
    if measurements.size_map_mm is not None:
        out.update(zip(MAP_SIZE_STATS, _size_stats(measurements.size_map_mm[keep], v, fill_value), strict=True))
    h, w = measurements.image_shape
    n_inc = int((~measurements.touches_edge).sum()) if not include_edge else n_all
    cm2 = max(h * w, 1) * measurements.mm_per_px**2 / 100.0
    out["log_density"] = float(np.log1p(n_inc / cm2))
    out["log_density_all"] = float(np.log1p(n_all / cm2))
    out["covered_fraction"] = float(measurements.area_px.sum() / max(h * w, 1))
    out["edge_fraction"] = float(measurements.touches_edge.mean()) if n_all else 0.0
    out["mm_per_px"] = float(measurements.mm_per_px)
    return np.array([out[k] for k in STAT_NAMES], dtype=float)



def raw_psd(m: InstanceMeasurements, method: str) -> dict | None:
    """Number- and volume-weighted PSD of the instances not touching the edge (all of them when
    every one does); None without any instance."""
    if not len(m):
        return None
    include = ~m.touches_edge if (~m.touches_edge).any() else None
    return psd_from_instances(sieve_size(m, method), m.volume_mm3, include=include)


# what the calibrated read-out may read (train.instances.readout), per target (d10, d50, d90): the
# instances' footprint statistics, or those and the same statistics of the size map — for every target, or for
# d10 and d50 only. The size map estimates each whole particle, hidden part included: what the fines, mostly hidden
# in a bed, lack in view. The coarse grains lie on top, seen whole: their footprints measure d90 directly, and
# there the map's estimate, only as good as the look the network trained on, is a liability on another look
# (docs/experiments.md, 2026-11-29: the fp32 entry and the read-out per target).
READOUT_TARGET_FEATURES = {
    "footprints": (READOUT_FEATURES,) * 3,
    "footprints+size_map": (MAP_READOUT_FEATURES,) * 3,
    "footprints+size_map_d10_d50": (MAP_READOUT_FEATURES, MAP_READOUT_FEATURES, READOUT_FEATURES),
}
# every statistic a read-out reads, in the order of its weights
READOUTS = {k: tuple(dict.fromkeys(f for t in v for f in t)) for k, v in READOUT_TARGET_FEATURES.items()}
