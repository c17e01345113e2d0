"""The sizes people measure a particle by, computed on its mesh (the names: ``psd.SIZE_DEFINITIONS``).

Of the solid particle (pose-free; computed once per particle when it is made):
- ``sieve``: the side of the smallest square hole it passes. A convex particle passes a square
  hole when, for some passing direction, its shadow along that direction fits in the square: the
  side is ``min over frames (u, v, d) of max(width along u, width along v)``, a width being the
  extent of the particle's vertices along a direction (the shadow's width along u is the solid's).
- ``b-axis``, ``c-axis`` (and the long ``a-axis``): the sides of its minimum-volume bounding box,
  sorted long → short (not the PCA extents, which overstate them for angular particles).
- ``esd``: the equivalent-sphere diameter of its exact volume.

Of the resting particle seen from the camera (``footprints``, from its settled pose): the
orthographic silhouette on the table's plane, ``feret-min`` and ``feret-max`` (its narrowest and
widest caliper widths) and ``ecd`` (the diameter of the circle of the same area).

Both minimisations over orientations run batched over every particle of a scene at once: a
coarse set of starting frames, then a pattern search with random rotation axes and shrinking
steps, each particle's frame kept apart (NumPy only, no per-particle Python loop). A particle's
mesh is taken as convex (every built-in family is a convex hull); for a user's non-convex mesh
the sizes are those of its convex hull, the shape calipers and sieves see.
"""

from __future__ import annotations

import functools

import numpy as np

from .geometry import quat_to_matrix

SEARCH_SEED = 20240601  # fixed: the search's random axes never change a label between runs
MIN_STEP_RAD = 2e-4  # the search stops refining a frame below this rotation (~0.01 % of a width)


def pad_vertices(vertices: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Packed vertices (see ``shapes.pack``) → (N, Vmax, 3) float64, each particle centred on its
    vertices' mean and padded with its own first vertex (which changes no width)."""
    v = _padded(np.asarray(vertices, dtype=np.float64), np.asarray(offsets), 0, len(offsets) - 1)
    return v - v.mean(axis=1, keepdims=True) if len(v) else v


def _rodrigues(axes: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """Rotation matrices (…, 3, 3) about unit `axes` (…, 3) by `angles` (…)."""
    x, y, z = axes[..., 0], axes[..., 1], axes[..., 2]
    c, s = np.cos(angles), np.sin(angles)
    t = 1 - c
    return np.stack([
        np.stack([t * x * x + c, t * x * y - s * z, t * x * z + s * y], -1),
        np.stack([t * x * y + s * z, t * y * y + c, t * y * z - s * x], -1),
        np.stack([t * x * z - s * y, t * y * z + s * x, t * z * z + c], -1),
    ], -2)


def _widths(verts: np.ndarray, frames: np.ndarray, rows: int) -> np.ndarray:
    """Widths of each particle along the first `rows` axes of each of its frames.
    verts (N, V, 3), frames (N, F, 3, 3) (rows = axes) → (N, F, rows)."""
    n, f = frames.shape[:2]
    dirs = frames[:, :, :rows, :].reshape(n, f * rows, 3)
    p = verts @ dirs.transpose(0, 2, 1)  # (N, V, F*rows)
    return (p.max(axis=1) - p.min(axis=1)).reshape(n, f, rows)


def _box_objective(verts: np.ndarray, frames: np.ndarray) -> np.ndarray:
    return _widths(verts, frames, 3).prod(axis=-1)


def _sieve_objective(verts: np.ndarray, frames: np.ndarray) -> np.ndarray:
    return _widths(verts, frames, 2).max(axis=-1)


_CUBE = np.array([(x, y, z) for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1) if x or y or z], dtype=float)
CUBE_AXES = _CUBE / np.linalg.norm(_CUBE, axis=1, keepdims=True)  # 26 rotation axes: a cube's faces, edges, corners
FACE_AXES = np.concatenate([np.eye(3), -np.eye(3)])


def _search(verts: np.ndarray, frames: np.ndarray, objective, step0: float, keep: int = 2, prune_after: int = 4,
            max_iter: int = 100, n_random: int = 8, min_step: float = MIN_STEP_RAD, seed: int = 0,
            fixed: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Minimise `objective` over each particle's frame by a pattern search from S starting frames
    (N, S, 3, 3): each round tries turning every frame by its step about the `fixed` axes and
    `n_random` random ones, keeps the best if it is better and halves the step if not; after
    `prune_after` rounds only the `keep` best starts of each particle go on. The search runs in
    float32 (twice as fast); the best frame is made orthonormal and measured again in float64.
    → (best value (N,), best frame (N, 3, 3))."""
    rng = np.random.default_rng([SEARCH_SEED, seed])
    n = len(verts)
    exact = verts
    verts, frames = verts.astype(np.float32), frames.astype(np.float32)
    val = objective(verts, frames)
    step = np.full(val.shape, step0)
    fixed = FACE_AXES if fixed is None else fixed
    active = np.arange(n)
    for it in range(max_iter):
        if it == prune_after and frames.shape[1] > keep:
            order = np.argsort(val, axis=1)[:, :keep]
            frames = np.take_along_axis(frames, order[:, :, None, None], axis=1)
            val = np.take_along_axis(val, order, axis=1)
            step = np.take_along_axis(step, order, axis=1)
        live = (step[active] >= min_step).any(axis=1)
        active = active[live]
        if not len(active):
            break
        fr, st = frames[active], step[active]
        rand = rng.normal(size=(n_random, 3))
        axes = np.concatenate([fixed, rand / np.linalg.norm(rand, axis=1, keepdims=True)]).astype(np.float32)
        c = len(axes)
        a, s_ = st.shape
        # the steps are step0 / 2^k: the turns are made once per distinct step, then looked up
        steps, which = np.unique(st, return_inverse=True)
        rot = _rodrigues(np.broadcast_to(axes, (len(steps), c, 3)), steps[:, None].astype(np.float32))  # (U, C, 3, 3)
        # the frame's rows mixed: a turn about an axis in the frame's own coordinates; the C turns
        # of a frame stacked as one (3C × 3) matrix, one product per frame
        cand = (rot[which.reshape(a, s_)].reshape(a, s_, c * 3, 3) @ fr).reshape(a, s_, c, 3, 3)
        cv = objective(verts[active], cand.reshape(a, s_ * c, 3, 3)).reshape(a, s_, c)
        best = cv.argmin(axis=2)
        bv = np.take_along_axis(cv, best[..., None], axis=2)[..., 0]
        better = bv < val[active] * (1 - 1e-12)
        bf = np.take_along_axis(cand, best[..., None, None, None], axis=2)[:, :, 0]
        frames[active] = np.where(better[..., None, None], bf, fr)
        val[active] = np.where(better, bv, val[active])
        step[active] = np.where(better, st, st * 0.5)
    best = frames[np.arange(n), val.argmin(axis=1)].astype(np.float64)
    u, _, vt = np.linalg.svd(best)  # the nearest rotation: float32 steps drift a little from orthonormal
    best = u @ vt
    return objective(exact, best[:, None])[:, 0], best


def _pca_frames(verts: np.ndarray) -> np.ndarray:
    """(N, 3, 3) principal axes as rows (long first)."""
    _, _, vt = np.linalg.svd(verts, full_matrices=False)
    return vt


def minimum_box(verts: np.ndarray, widths: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Sides of each particle's minimum-volume bounding box, sorted long → short (N, 3), and the
    box's axes (N, 3, 3; rows in the same order). verts: (N, V, 3) as ``pad_vertices`` gives;
    `widths`: ``grid_widths(verts)`` if already computed. The search starts from the
    principal axes and the three best frames of the grid."""
    n = len(verts)
    if n == 0:
        return np.zeros((0, 3)), np.zeros((0, 3, 3))
    w = grid_widths(verts) if widths is None else widths
    frames = np.concatenate([_pca_frames(verts)[:, None], _grid_starts(w, "box", 3)], axis=1)
    _, best = _search(verts, frames, _box_objective, step0=0.25, min_step=2e-3)
    w = _widths(verts, best[:, None], 3)[:, 0]
    order = np.argsort(-w, axis=1)
    return np.take_along_axis(w, order, axis=1), np.take_along_axis(best, order[..., None], axis=1)


def sieve_sizes(verts: np.ndarray, box_axes: np.ndarray | None = None,
                widths: np.ndarray | None = None) -> np.ndarray:
    """Side of the smallest square hole each particle passes (N,). verts: (N, V, 3);
    `box_axes`: the minimum boxes' axes (rows long → short; computed when not given); `widths`:
    ``grid_widths(verts)`` if already computed. The search
    starts from passing along the long axis (hole at 0, 22.5 and 45°) and the six best frames of
    the grid."""
    n = len(verts)
    if n == 0:
        return np.zeros(0)
    w = grid_widths(verts) if widths is None else widths
    if box_axes is None:
        box_axes = minimum_box(verts, w)[1]
    frames = np.concatenate([_box_starts(box_axes)[:, :3], _grid_starts(w, "sieve", 6)], axis=1)
    val, best = _search(verts, frames, _sieve_objective, step0=0.08, keep=2, prune_after=3, min_step=2e-3)
    # a second search from each particle's best frame, with other random axes and a smaller first
    # step: a pattern search can stop early on the ridge where the two widths are equal
    val2, _ = _search(verts, best[:, None], _sieve_objective, step0=0.01, keep=1, seed=1, fixed=CUBE_AXES, n_random=8)
    return np.minimum(val, val2)


def _box_starts(box_axes: np.ndarray) -> np.ndarray:
    """(N, 12, 3, 3): passing along each box axis, the hole turned 0, 22.5, 45 and 67.5° about it."""
    starts = []
    for d in range(3):
        rolled = np.roll(box_axes, -(d + 1), axis=1)  # rows (u, v, d): the passing direction last
        for ang in np.deg2rad([0.0, 22.5, 45.0, 67.5]):
            starts.append(_rodrigues(np.array([0.0, 0.0, 1.0]), np.array(ang)) @ rolled)
    return np.stack(starts, axis=1)


def _frame_grid(n_dirs: int, n_angles: int) -> np.ndarray:
    """(n_dirs * n_angles, 3, 3) frames (rows u, v, d): passing directions d spread over a
    hemisphere, the hole's side turned over a quarter turn about each."""
    d = _hemisphere(n_dirs)
    ref = np.where(np.abs(d[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    a = np.cross(d, ref)
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = np.cross(d, a)
    ang = np.arange(n_angles) * (np.pi / 2 / n_angles)
    c, s = np.cos(ang)[None, :, None], np.sin(ang)[None, :, None]
    u = c * a[:, None] + s * b[:, None]
    v = -s * a[:, None] + c * b[:, None]
    return np.stack([u, v, np.broadcast_to(d[:, None], u.shape)], axis=2).reshape(-1, 3, 3)


def _hemisphere(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - i / n)  # a Fibonacci hemisphere (z ≥ 0)
    theta = np.pi * (1 + 5**0.5) * i
    return np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], axis=1)


def _nearest_direction(dirs: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Index of the grid direction nearest each of `dirs` (a width is the same along ±u)."""
    return np.abs(dirs @ grid.T).argmax(axis=1)


def _nearest_directions(dirs: np.ndarray, grid: np.ndarray, candidates: int = 4) -> np.ndarray:
    """``_nearest_direction`` through a k-d tree of ±grid: the `candidates` nearest by distance,
    then the largest |cos| among them (the same pick: for unit vectors the nearest is the one of
    largest cosine), in ~1 % of the time of every cosine."""
    from scipy.spatial import cKDTree

    _, idx = cKDTree(np.concatenate([grid, -grid])).query(dirs, k=candidates)
    idx = idx % len(grid)
    cos = np.abs(np.einsum("nk,nck->nc", dirs, grid[idx]))
    return np.take_along_axis(idx, cos.argmax(axis=1)[:, None], axis=1)[:, 0]


@functools.lru_cache(maxsize=1)
def _grid() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(frames, directions, axes): 10,800 frames that every particle's searches start from the
    best few of, the 2,400 directions their widths are looked up on, and each frame's three axes
    as indices into those. Built on first use (~0.05 s), not at import: the label stage never needs it."""
    frames = _frame_grid(600, 18)
    dirs = _hemisphere(2400)
    axes = np.stack([_nearest_directions(frames[:, k], dirs) for k in range(3)], axis=1)
    return frames, dirs, axes


def grid_widths(verts: np.ndarray, chunk: int = 16, dir_chunk: int = 600) -> np.ndarray:
    """(N, 2400) float32: each particle's widths along the grid's directions. In blocks of 16
    particles × 600 directions: each product fits the cache and stays under OpenBLAS's threshold
    for threads (idle threads spinning took a core from the other worker); every width is the
    same as in one product."""
    dirs = _grid()[1].T.astype(np.float32)
    out = np.empty((len(verts), dirs.shape[1]), np.float32)
    v32 = verts.astype(np.float32)
    for lo in range(0, len(verts), chunk):
        for d0 in range(0, dirs.shape[1], dir_chunk):
            p = v32[lo:lo + chunk] @ dirs[:, d0:d0 + dir_chunk]  # (n, V, K)
            out[lo:lo + chunk, d0:d0 + dir_chunk] = p.max(axis=1) - p.min(axis=1)
    return out


def _grid_starts(widths: np.ndarray, kind: str, keep: int, chunk: int = 32) -> np.ndarray:
    """(N, keep, 3, 3): the `keep` frames of the grid with the smallest box volume (`kind`
    'box') or sieve objective ('sieve'), their widths looked up in `widths`, per particle."""
    frames, _, axes = _grid()
    out = np.empty((len(widths), keep, 3, 3))
    for lo in range(0, len(widths), chunk):
        w = widths[lo:lo + chunk]
        u, v = w[:, axes[:, 0]], w[:, axes[:, 1]]
        obj = u * v * w[:, axes[:, 2]] if kind == "box" else np.maximum(u, v)
        best = np.argpartition(obj, keep, axis=1)[:, :keep]
        out[lo:lo + chunk] = frames[best]
    return out


def equivalent_sphere_diameter(volume_mm3: np.ndarray) -> np.ndarray:
    return np.cbrt(6.0 * np.asarray(volume_mm3, dtype=float) / np.pi)


def box_and_sieve(meshes: list[np.ndarray], chunk: int = 512) -> tuple[np.ndarray, np.ndarray]:
    """Minimum-box sides (N, 3; a ≥ b ≥ c) and sieve sizes (N,) of particles given as vertex
    arrays. Particles are measured in chunks of similar vertex counts, so that little of the work
    goes to padding."""
    n = len(meshes)
    dims, sieve = np.zeros((n, 3)), np.zeros(n)
    counts = np.array([len(m) for m in meshes])
    order = np.argsort(counts, kind="stable")
    for lo in range(0, n, chunk):
        idx = order[lo:lo + chunk]
        offsets = np.concatenate([[0], np.cumsum(counts[idx])])
        verts = pad_vertices(np.concatenate([meshes[i] for i in idx]), offsets)
        w = grid_widths(verts)
        dims[idx], axes = minimum_box(verts, w)
        sieve[idx] = sieve_sizes(verts, axes, w)
    return dims, sieve


# ---- footprints: the resting particle seen from above -----------------------------------------

def _convex_footprints(vertices: np.ndarray, vert_offsets: np.ndarray, faces: np.ndarray, face_offsets: np.ndarray,
                       rot: np.ndarray, chunk: int) -> dict[str, np.ndarray]:
    n = len(rot)
    nv, nf = np.diff(vert_offsets), np.diff(face_offsets)
    pid_v, pid_f = np.repeat(np.arange(n), nv), np.repeat(np.arange(n), nf)
    xy = np.einsum("vij,vj->vi", rot[pid_v], vertices)[:, :2]
    tri = faces.astype(np.int64) + vert_offsets[:-1][pid_f, None]  # global vertex indices
    a, b, c = xy[tri[:, 0]], xy[tri[:, 1]], xy[tri[:, 2]]
    cross = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    area = 0.25 * np.bincount(pid_f, weights=np.abs(cross), minlength=n)  # ½ Σ |shadow of a face|
    edges = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    pid_e = np.concatenate([pid_f] * 3)
    once = edges[:, 0] < edges[:, 1]  # each edge of a closed mesh, once
    order = np.argsort(pid_e[once], kind="stable")  # grouped by particle
    edges, pid_e = edges[once][order], pid_e[once][order]
    d = xy[edges[:, 1]] - xy[edges[:, 0]]
    length = np.hypot(d[:, 0], d[:, 1])
    ok = length > 1e-12 * (1 + np.abs(xy).max(initial=0))  # an edge seen end-on casts no edge
    normals = np.where(ok[:, None], np.stack([-d[:, 1], d[:, 0]], axis=1) / np.where(ok, length, 1)[:, None], np.nan)
    fmin, fmax = np.zeros(n), np.zeros(n)
    ne = np.bincount(pid_e, minlength=n)
    e_off = np.concatenate([[0], np.cumsum(ne)])
    for lo in range(0, n, chunk):
        hi = min(n, lo + chunk)
        v = _padded(xy, vert_offsets, lo, hi)  # (k, V, 2)
        nrm = _padded(normals, e_off, lo, hi)  # (k, E, 2)
        proj = v @ nrm.transpose(0, 2, 1)  # (k, V, E)
        width = proj.max(axis=1) - proj.min(axis=1)
        fmin[lo:hi] = np.nanmin(np.where(np.isnan(width), np.inf, width), axis=1)
        sq = (v**2).sum(-1)
        d2 = sq[:, :, None] + sq[:, None, :] - 2 * (v @ v.transpose(0, 2, 1))  # squared vertex distances
        fmax[lo:hi] = np.sqrt(np.maximum(d2.max(axis=(1, 2)), 0.0))
    fmin = np.where(np.isfinite(fmin), fmin, 0.0)
    return {"feret_min_mm": fmin, "feret_max_mm": fmax, "ecd_mm": np.sqrt(4.0 * area / np.pi)}


def _padded(rows: np.ndarray, offsets: np.ndarray, lo: int, hi: int) -> np.ndarray:
    """Rows of groups lo..hi-1 (group k = rows[offsets[k]:offsets[k+1]]) as (hi-lo, max count, …),
    each group padded with its own first row (which changes no extreme)."""
    counts = np.diff(offsets[lo:hi + 1])
    idx = offsets[lo:hi, None] + np.minimum(np.arange(max(int(counts.max(initial=1)), 1))[None, :],
                                            np.maximum(counts[:, None] - 1, 0))
    return rows[idx]


def polygon_measures(points: np.ndarray) -> tuple[float, float, float]:
    """(feret_min, feret_max, area) of the convex hull of 2-D points (M, 2)."""
    from scipy.spatial import ConvexHull, QhullError

    try:
        hull = ConvexHull(points)
    except (QhullError, ValueError):  # a degenerate (flat or single-point) shadow
        span = np.ptp(points, axis=0) if len(points) else np.zeros(2)
        return 0.0, float(np.hypot(*span)), 0.0
    h = points[hull.vertices]
    edges = np.roll(h, -1, axis=0) - h
    normals = np.stack([-edges[:, 1], edges[:, 0]], axis=1)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    proj = h @ normals.T  # the narrowest caliper lies flush with an edge
    feret_min = float((proj.max(axis=0) - proj.min(axis=0)).min())
    d = h[:, None, :] - h[None, :, :]
    feret_max = float(np.sqrt((d**2).sum(-1)).max())
    return feret_min, feret_max, float(hull.volume)  # a 2-D hull's "volume" is its area


def footprints(vertices: np.ndarray, vert_offsets: np.ndarray, quat_xyzw: np.ndarray, faces: np.ndarray | None = None,
               face_offsets: np.ndarray | None = None, chunk: int = 128) -> dict[str, np.ndarray]:
    """Min and max Feret diameter and equivalent-circle diameter of each particle's silhouette on
    the table (seen straight down, orthographic), from its vertices and settled orientation.

    With the meshes' `faces` (local indices, as ``shapes.pack`` stores them) and the particles
    convex, all particles at once: the shadow's area is half the summed shadows of its faces
    (every point of it lies under one face turned up and one turned down), its narrowest caliper
    lies flush with a shadow edge, which is the shadow of a mesh edge, and its widest joins two
    vertices. Without faces, one convex hull per particle (any mesh: its hull's shadow)."""
    q = np.asarray(quat_xyzw, dtype=float)
    rot = quat_to_matrix(q / np.linalg.norm(q, axis=1, keepdims=True))
    if faces is not None:
        return _convex_footprints(np.asarray(vertices, float), np.asarray(vert_offsets), np.asarray(faces),
                                  np.asarray(face_offsets), rot, chunk)
    n = len(rot)
    out = {k: np.zeros(n) for k in ("feret_min_mm", "feret_max_mm", "ecd_mm")}
    for i in range(n):
        v = np.asarray(vertices[vert_offsets[i]:vert_offsets[i + 1]], dtype=float)
        xy = (v @ rot[i].T)[:, :2]
        fmin, fmax, area = polygon_measures(xy)
        out["feret_min_mm"][i], out["feret_max_mm"][i] = fmin, fmax
        out["ecd_mm"][i] = np.sqrt(4.0 * area / np.pi)
    return out
