"""Stage 1: draw a scene's particles (count, sizes, drop positions, shapes).

Writes the paper's metadata JSON (``shape_type``, ``size_mean``, ``size_sigma``,
``table_size``, ``samplesize``, ``particles: [{size, x, y}]``) plus provenance, and the
particle meshes. Sizes and coordinates are in mm with the table centred at 0.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass

import numpy as np
from scipy.special import ndtr, ndtri

from .. import PsdError, __version__
from ..seeding import STREAMS, name_key, rng_for, scene_entropy, scene_id
from .shapes import ShapeLibrary, ShapeParams, make_particles, pack, shape_library


@dataclass(frozen=True)
class SampleParams:
    """The slice of the config that a scene's sample stage depends on: a dataset's settings
    (defaults: the schema's, config.schema.yaml), flattened, with the seed and the scene's index."""

    seed: int
    dataset: str
    index: int
    shape: str
    table_size: float
    count: tuple[int, int]
    size_mean: tuple[float, float]
    size_sigma: tuple[float, float]
    size_bounds: tuple[float, float]
    shape_params: dict
    placement_candidates: int
    placement_cell_mm: float
    shape_library: int  # 0: every particle a shape of its own; K: one of K shapes made once (shapes.shape_library)

    @classmethod
    def from_dict(cls, d: dict) -> SampleParams:
        """From config.sample_params (one scene's: with its index)."""
        try:
            return cls._from_slice(d)
        except KeyError as e:
            raise PsdError(f"the sample params lack {e.args[0]!r}: pass the validated config's slice "
                           "(psdfactory.config.sample_params)") from None

    @classmethod
    def _from_slice(cls, d: dict) -> SampleParams:
        size, placement = d["size"], d["placement"]
        return cls(
            seed=int(d["seed"]),
            dataset=str(d["dataset"]),
            index=int(d["index"]),
            shape=str(d["shape"]),
            table_size=float(d["table_size"]),
            count=(int(d["count"][0]), int(d["count"][1])),
            size_mean=tuple(map(float, size["mean"])),
            size_sigma=tuple(map(float, size["sigma"])),
            size_bounds=tuple(map(float, size["bounds"])),
            shape_params=dict(d["shape_params"]),
            placement_candidates=int(placement["candidates"]),
            placement_cell_mm=float(placement["cell_mm"]),
            shape_library=int(d.get("shape_library", 0)),  # (config.sample_params leaves out 0, the off value)
        )


def config_hash(obj: dict) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True).encode()).hexdigest()[:16]


def truncnormal_sizes(rng: np.random.Generator, n: int, mean: float, sigma: float, lo: float, hi: float) -> np.ndarray:
    """n draws of TruncNormal(a=lo, b=hi, mu=mean, sigma) (bounds in the same units as mean)."""
    if not lo < hi:
        raise PsdError(f"size bounds must satisfy a < b, got [{lo}, {hi}]")
    if sigma <= 0:
        raise PsdError(f"size sigma must be > 0, got {sigma}")
    a, b = (lo - mean) / sigma, (hi - mean) / sigma
    # Inverse-CDF sampling, done in the lower tail where the normal CDF keeps its precision.
    # (scipy.stats.truncnorm gives the same distribution, tested, but costs 0.3 s to import
    # in every sample job.)
    flip = a > 0
    if flip:
        a, b = -b, -a
    pa, pb = ndtr(a), ndtr(b)
    if not pb > pa:
        raise PsdError(f"size bounds [{lo}, {hi}] lie too far in the tail of N({mean}, {sigma}²)")
    z = np.clip(ndtri(pa + rng.random(n) * (pb - pa)), a, b)
    return mean + sigma * (-z if flip else z)


def drop_positions(
    rng: np.random.Generator,
    footprint_r: np.ndarray,
    volumes: np.ndarray,
    table_size: float,
    candidates: int,
    cell_mm: float,
) -> np.ndarray:
    """x-y drop spots: for each particle the lowest of `candidates` random spots on a coarse
    height map of the particles placed so far (candidates=1 is plain uniform placement).

    Spreading the drops this way gives an even bed and a short fall in the simulation.
    """
    half = table_size / 2
    n_cells = max(1, int(np.ceil(table_size / cell_mm)))
    height = np.zeros((n_cells, n_cells))
    out = np.empty((len(footprint_r), 2))
    for i, (r, vol) in enumerate(zip(footprint_r, volumes, strict=True)):
        lim = half - r
        if lim <= 0:
            raise PsdError(f"a particle {2 * r:.1f} mm across does not fit on a {table_size} mm table")
        cand = rng.uniform(-lim, lim, size=(candidates, 2))
        k = max(1, int(r / cell_mm))
        cells = np.clip(((cand + half) / cell_mm).astype(int), 0, n_cells - 1)
        h = [height[max(cx - k, 0) : cx + k + 1, max(cy - k, 0) : cy + k + 1].mean() for cx, cy in cells]
        best = int(np.argmin(h))
        out[i] = cand[best]
        cx, cy = cells[best]
        sl = (slice(max(cx - k, 0), cx + k + 1), slice(max(cy - k, 0), cy + k + 1))
        height[sl] += vol / (np.pi * r * r)
    return out


def circumradii(vertices: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Each particle's largest vertex distance from its centre of volume: the radius it never
    reaches beyond in the x-y plane, however it lands."""
    r = np.linalg.norm(np.asarray(vertices, dtype=float), axis=1)
    return np.maximum.reduceat(r, offsets[:-1]) if len(offsets) > 1 else np.zeros(0)


def draw_sizes(p: SampleParams, rng: np.random.Generator | None = None) -> tuple[int, float, float, np.ndarray]:
    """(count, μ, σ, sizes in mm) of a scene: the first draws of its ``sample`` stream (`rng`; by
    default that stream from the start), so the sizes alone can be had without making a scene."""
    if rng is None:
        rng = rng_for(scene_entropy(p.seed, p.dataset, p.index), "sample")
    lo_n, hi_n = p.count
    n = int(rng.integers(lo_n, hi_n + 1))
    mean = float(rng.uniform(*p.size_mean))
    sigma = float(rng.uniform(*p.size_sigma))
    return n, mean, sigma, truncnormal_sizes(rng, n, mean, sigma, *p.size_bounds)


def dataset_library(p: SampleParams) -> ShapeLibrary | None:
    """The shapes the dataset's scenes draw from (None where each particle gets its own): one
    library per seed and dataset, so a test dataset's shapes are not a training dataset's."""
    if not p.shape_library:
        return None
    return shape_library(p.shape, ShapeParams.for_family(p.shape, p.shape_params), p.shape_library,
                         (p.seed, name_key(p.dataset), STREAMS["shape_library"]))


def sample_scene(p: SampleParams) -> tuple[dict, dict[str, np.ndarray]]:
    """The scene spec (paper metadata + provenance) and its packed particle meshes."""
    entropy = scene_entropy(p.seed, p.dataset, p.index)
    rng = rng_for(entropy, "sample")
    n, mean, sigma, sizes = draw_sizes(p, rng)

    shape_params = ShapeParams.for_family(p.shape, p.shape_params)
    particles = make_particles(p.shape, sizes, rng_for(entropy, "shape"), shape_params, dataset_library(p))
    geometry = pack(particles)
    xy = drop_positions(
        rng,
        footprint_r=circumradii(geometry["vertices"], geometry["vert_offsets"]),
        volumes=geometry["volume_mm3"],
        table_size=p.table_size,
        candidates=p.placement_candidates,
        cell_mm=p.placement_cell_mm,
    )
    # (shape_library 0 left out: the hash of a scene made before the library existed stays the same)
    params_dict = {k: (list(v) if isinstance(v, tuple) else v) for k, v in p.__dict__.items()
                   if k != "shape_library" or v}
    spec = {
        # the paper's metadata keys
        "shape_type": p.shape,
        "size_mean": round(mean, 4),
        "size_sigma": round(sigma, 4),
        "table_size": p.table_size,
        "samplesize": n,
        "particles": [
            {"size": round(float(s), 4), "x": round(float(x), 3), "y": round(float(y), 3)}
            for s, (x, y) in zip(sizes, xy, strict=True)
        ],
        # provenance
        "scene_id": scene_id(p.dataset, p.index),
        "dataset": p.dataset,
        "index": p.index,
        "seed": p.seed,
        "entropy": entropy,
        "size_bounds": list(p.size_bounds),
        "units": "mm",
        "config_hash": config_hash(params_dict),
        "psdfactory_version": __version__,
    }
    return spec, geometry
