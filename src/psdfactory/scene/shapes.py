"""Particle shape families.

Every particle gets its own mesh (vertices in mm, centred on its centre of volume, and
outward-facing triangles). Its drawn size is its b-axis: the intermediate side of its
minimum-volume bounding box (the generator's size, as the seed paper's). Its volume is the exact
volume of the mesh; its sieve size and the other definitions are measured on it (``sizes``).

Families:
- ``crushed_rock``: convex hull of 20-40 random points on a perturbed ellipsoid (angular, unique).
- ``granule``: a slightly bumpy, near-spherical prill (fertiliser granules).
- ``ellipsoid``: a smooth ellipsoid with random axis ratios.
- ``mesh``: the user's own mesh files (OBJ/STL/PLY/GLB, loaded with trimesh).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from .. import PsdError
from ..config import MAX_MESH_FACES
from ..io import read_mesh

FAMILIES = ("crushed_rock", "granule", "ellipsoid", "mesh")


@dataclass(frozen=True)
class ShapeParams:
    """Knobs of a shape family (ranges are [lo, hi], drawn per particle)."""

    aspect_b: tuple[float, float] = (0.6, 1.0)  # intermediate / long axis
    aspect_c: tuple[float, float] = (0.4, 0.8)  # short / long axis
    n_points: tuple[int, int] = (20, 40)  # crushed_rock hull points
    roughness: float = 0.15  # relative radial noise
    mesh_files: tuple[str, ...] = ()

    @classmethod
    def for_family(cls, family: str, overrides: dict | None = None) -> ShapeParams:
        defaults = {
            "crushed_rock": {},
            "granule": {"aspect_b": (0.9, 1.0), "aspect_c": (0.85, 0.95), "roughness": 0.03},
            "ellipsoid": {"aspect_b": (0.5, 0.9), "aspect_c": (0.4, 0.8), "roughness": 0.0},
            "mesh": {},
        }
        if family not in defaults:
            raise PsdError(f"unknown particle shape {family!r}; choose one of {', '.join(FAMILIES)}")
        kw = dict(defaults[family])
        for k, v in (overrides or {}).items():
            kw[k] = tuple(v) if isinstance(v, list) else v
        return cls(**kw)


@dataclass
class Particle:
    vertices: np.ndarray  # (V, 3) float64, mm, centred on the centre of volume
    faces: np.ndarray  # (F, 3) int32, counter-clockwise seen from outside
    size_mm: float  # the drawn size: the b-axis (intermediate side of the minimum-volume bounding box)
    volume_mm3: float
    dims_mm: np.ndarray = field(default_factory=lambda: np.zeros(3))  # minimum box sides: a ≥ b ≥ c
    sieve_mm: float = float("nan")  # the side of the smallest square hole it passes


def fibonacci_sphere(n: int) -> np.ndarray:
    """n nearly evenly spread unit vectors."""
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    theta = np.pi * (1 + 5**0.5) * i
    return np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], axis=1)


def random_directions(rng: np.random.Generator, n: int) -> np.ndarray:
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def volume_and_centroid(vertices: np.ndarray, faces: np.ndarray) -> tuple[float, np.ndarray]:
    """Exact volume and centre of volume of a closed, outward-oriented triangle mesh."""
    a, b, c = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    six_v = np.einsum("ij,ij->i", a, np.cross(b, c))  # signed tetrahedra with the origin
    vol = six_v.sum() / 6.0
    if abs(vol) < 1e-12:
        raise PsdError("degenerate particle mesh (zero volume)")
    centroid = ((a + b + c) * six_v[:, None]).sum(axis=0) / (24.0 * vol)
    return float(vol), centroid


def convex_mesh(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Convex hull as (vertices, outward faces) with only the hull's own vertices."""
    return convex_meshes([points])[0]


def convex_meshes(point_sets: list[np.ndarray]) -> list[tuple[np.ndarray, np.ndarray]]:
    """``convex_mesh`` of each point set: one Qhull call each, the rest (keeping the hull's own
    vertices, facing every face outwards) for all at once (the same meshes, ~10× less Python)."""
    from scipy.spatial import ConvexHull, QhullError  # imported here: the other stages never need it

    hulls = []
    for points in point_sets:
        try:
            hull = ConvexHull(points)
        except QhullError as e:
            raise PsdError(f"could not build a convex particle from {len(points)} points: {e}") from None
        hulls.append((hull.vertices, hull.simplices))  # vertices: the hull's points, sorted
    if not hulls:
        return []
    n = len(hulls)
    p_off = np.concatenate([[0], np.cumsum([len(p) for p in point_sets])])
    nv = np.array([len(u) for u, _ in hulls])
    nf = np.array([len(f) for _, f in hulls])
    v_off, f_off = np.concatenate([[0], np.cumsum(nv)]), np.concatenate([[0], np.cumsum(nf)])
    points = np.concatenate(point_sets)
    used = np.concatenate([u + p_off[i] for i, (u, _) in enumerate(hulls)])
    remap = np.full(len(points), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    verts = points[used]
    faces = remap[np.concatenate([f + p_off[i] for i, (_, f) in enumerate(hulls)])]
    # Qhull does not orient simplices; make them face away from the hull's interior.
    pid = np.repeat(np.arange(n), nf)
    inner = np.add.reduceat(verts, v_off[:-1], axis=0) / nv[:, None]
    a, b, c = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    normal = np.cross(b - a, c - a)
    flip = np.einsum("ij,ij->i", normal, (a + b + c) / 3 - inner[pid]) < 0
    faces[flip] = faces[flip][:, ::-1]
    faces = (faces - v_off[:-1][pid, None]).astype(np.int32)
    return [(verts[v_off[i]:v_off[i + 1]], faces[f_off[i]:f_off[i + 1]]) for i in range(n)]


def finish(vertices: np.ndarray, faces: np.ndarray, size_mm: float, dims: np.ndarray, sieve: float) -> Particle:
    """Scale a unit shape (its minimum box `dims`, sieve size `sieve`) so that its b-axis is
    `size_mm`; centre it on its centre of volume."""
    return finish_all([(vertices, faces)], np.array([size_mm], dtype=float), dims[None], np.array([sieve]))[0]


def finish_all(meshes: list[tuple[np.ndarray, np.ndarray]], sizes_mm: np.ndarray, dims: np.ndarray,
               sieve: np.ndarray) -> list[Particle]:
    """``finish`` of every shape, the arithmetic done for all at once; each particle's volume and
    centre are its own sums (the same numbers as ``volume_and_centroid`` of each)."""
    n = len(meshes)
    if n == 0:
        return []
    nv = np.array([len(v) for v, _ in meshes])
    nf = np.array([len(f) for _, f in meshes])
    v_off, f_off = np.concatenate([[0], np.cumsum(nv)]), np.concatenate([[0], np.cumsum(nf)])
    sizes_mm = np.asarray(sizes_mm, dtype=float)
    scale = sizes_mm / dims[:, 1]
    v = np.concatenate([m[0] for m in meshes]) * np.repeat(scale, nv)[:, None]
    local = np.concatenate([m[1] for m in meshes])
    f = local + v_off[:-1][np.repeat(np.arange(n), nf), None]
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    six_v = np.einsum("ij,ij->i", a, np.cross(b, c))  # signed tetrahedra with the origin
    moment = (a + b + c) * six_v[:, None]
    out = []
    for i in range(n):
        fs = slice(f_off[i], f_off[i + 1])
        vol = six_v[fs].sum() / 6.0
        if abs(vol) < 1e-12:
            raise PsdError("degenerate particle mesh (zero volume)")
        centroid = moment[fs].sum(axis=0) / (24.0 * vol)
        out.append(Particle(v[v_off[i]:v_off[i + 1]] - centroid, local[fs].astype(np.int32), float(sizes_mm[i]),
                            float(vol), dims[i] * scale[i], float(sieve[i] * scale[i])))
    return out


def _axes(rng: np.random.Generator, p: ShapeParams) -> np.ndarray:
    return np.array([1.0, rng.uniform(*p.aspect_b), rng.uniform(*p.aspect_c)])


Mesh = tuple[np.ndarray, np.ndarray]  # (vertices, faces) of a shape before it is sized


def crushed_rock_points(rng: np.random.Generator, p: ShapeParams) -> np.ndarray:
    n = int(rng.integers(p.n_points[0], p.n_points[1] + 1))
    dirs = random_directions(rng, n)
    return dirs * _axes(rng, p) * (1 + rng.uniform(-p.roughness, p.roughness, size=(n, 1)))


_SPHERE = fibonacci_sphere(92)


def granule_points(rng: np.random.Generator, p: ShapeParams) -> np.ndarray:
    bumps = 1 + rng.uniform(-p.roughness, p.roughness, size=(len(_SPHERE), 1))
    return _SPHERE * _axes(rng, p) * bumps


def ellipsoid_points(rng: np.random.Generator, p: ShapeParams) -> np.ndarray:
    return _SPHERE * _axes(rng, p)


def make_crushed_rock(rng: np.random.Generator, p: ShapeParams) -> Mesh:
    return convex_mesh(crushed_rock_points(rng, p))


def make_granule(rng: np.random.Generator, p: ShapeParams) -> Mesh:
    return convex_mesh(granule_points(rng, p))


def make_ellipsoid(rng: np.random.Generator, p: ShapeParams) -> Mesh:
    return convex_mesh(ellipsoid_points(rng, p))


@lru_cache(maxsize=64)
def load_mesh(path: str) -> tuple[np.ndarray, np.ndarray]:
    """A user's mesh file as (vertices, faces): a closed, outward-facing solid (io.read_mesh
    refuses any other, naming the file; the config check runs it before any scene is made)."""
    mesh = read_mesh(path, MAX_MESH_FACES)
    return np.asarray(mesh.vertices, dtype=float), np.asarray(mesh.faces, dtype=np.int32)


def make_from_mesh(rng: np.random.Generator, p: ShapeParams) -> Mesh:
    if not p.mesh_files:
        raise PsdError("shape 'mesh' needs shape_params.mesh_files: a list of OBJ/STL/PLY/GLB files")
    return load_mesh(p.mesh_files[int(rng.integers(len(p.mesh_files)))])


MAKERS: dict[str, Callable[[np.random.Generator, ShapeParams], Mesh]] = {
    "crushed_rock": make_crushed_rock,
    "granule": make_granule,
    "ellipsoid": make_ellipsoid,
    "mesh": make_from_mesh,
}
HULL_POINTS: dict[str, Callable[[np.random.Generator, ShapeParams], np.ndarray]] = {
    "crushed_rock": crushed_rock_points,
    "granule": granule_points,
    "ellipsoid": ellipsoid_points,
}


def make_particles(family: str, sizes_mm: np.ndarray, rng: np.random.Generator, params: ShapeParams,
                   library: ShapeLibrary | None = None) -> list[Particle]:
    """One particle per drawn size (its b-axis, mm) with its minimum box and sieve size, measured
    on all the scene's shapes at once (``sizes``). With a `library` (``shape_library``), each
    particle is one of its shapes instead, picked at random: no shape is made or measured per
    scene (the library's sizes, scaled: the same numbers as measuring the scaled shape, as every
    size scales with its shape; not mirrored, which the box search would measure afresh)."""
    if library is not None:
        pick = rng.integers(len(library.shapes), size=len(sizes_mm))
        shapes = [library.shapes[k] for k in pick]
        return finish_all(shapes, np.asarray(sizes_mm, dtype=float), library.dims[pick], library.sieve[pick])
    shapes, dims, sieve = made_and_measured(family, len(sizes_mm), rng, params)
    return finish_all(shapes, np.asarray(sizes_mm, dtype=float), dims, sieve)


def made_and_measured(family: str, n: int, rng: np.random.Generator,
                      params: ShapeParams) -> tuple[list[Mesh], np.ndarray, np.ndarray]:
    """`n` unit shapes of `family` and their minimum box sides (n, 3) and sieve sizes (n,),
    measured in one batch (``sizes``)."""
    from .sizes import box_and_sieve

    if family in HULL_POINTS:  # the same draws as MAKERS', the hulls' bookkeeping done for all at once
        shapes = convex_meshes([HULL_POINTS[family](rng, params) for _ in range(n)])
    else:
        shapes = [MAKERS[family](rng, params) for _ in range(n)]
    dims, sieve = box_and_sieve([v for v, _ in shapes])
    return shapes, dims, sieve


@dataclass(frozen=True)
class ShapeLibrary:
    """Shapes of one family made and measured once, for every scene of a dataset to draw from."""

    shapes: tuple[Mesh, ...]  # unit shapes as made (not yet scaled or centred)
    dims: np.ndarray  # (K, 3) their minimum box sides, long → short
    sieve: np.ndarray  # (K,) their sieve sizes


@lru_cache(maxsize=4)
def shape_library(family: str, params: ShapeParams, size: int, entropy: tuple[int, ...]) -> ShapeLibrary:
    """`size` shapes of a generated family, drawn from the random stream `entropy` and measured in
    one batch (~0.5 s per 1,000 crushed-rock shapes); kept for the process, so that a job making
    many scenes (``scenes_per_job``) makes them once."""
    if family not in HULL_POINTS:
        raise PsdError(f"shape_library: the {family!r} family's shapes are its mesh files; "
                       f"a library is for {', '.join(HULL_POINTS)}")
    shapes, dims, sieve = made_and_measured(family, size, np.random.default_rng(list(entropy)), params)
    for arr in (dims, sieve, *(x for shape in shapes for x in shape)):
        arr.flags.writeable = False  # shared by every scene of the process
    return ShapeLibrary(tuple(shapes), dims, sieve)


def pack(particles: list[Particle]) -> dict[str, np.ndarray]:
    """Concatenate per-particle meshes into flat arrays with offsets (for one .npz per scene)."""
    nv = np.array([len(p.vertices) for p in particles])
    nf = np.array([len(p.faces) for p in particles])
    return {
        "vertices": np.concatenate([p.vertices for p in particles]).astype(np.float32),
        "faces": np.concatenate([p.faces for p in particles]).astype(np.int32),
        "vert_offsets": np.concatenate([[0], np.cumsum(nv)]).astype(np.int64),
        "face_offsets": np.concatenate([[0], np.cumsum(nf)]).astype(np.int64),
        "size_mm": np.array([p.size_mm for p in particles]),
        "volume_mm3": np.array([p.volume_mm3 for p in particles]),
        "dims_mm": np.array([p.dims_mm for p in particles]).reshape(-1, 3),
        "sieve_mm": np.array([p.sieve_mm for p in particles]),
    }
