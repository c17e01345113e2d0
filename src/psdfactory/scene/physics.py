"""Stage 2: drop the particles on the table with pybullet and let them settle.

Internally Bullet works in centimetres (gravity -981 cm/s²): measured to behave best for
millimetre-to-centimetre particles. Everything that leaves this module is in mm.

Two settles (``physics.settle``), both freezing each particle once it is still and stopping when
``stop_frozen_fraction`` of them are:
- ``fast`` (default): each particle starts near where it will rest. From its random orientation
  it is tipped, quasi-statically, onto the face it would come to rest on if dropped on the bare
  floor (``resting_rotations``), then lowered onto a height field of the particles placed before
  it, at the lowest spot within ``SPAWN_SHIFT_MM`` of its drop spot (``resting_spawn``): falls of
  ~1 mm instead of tens of mm, ~30 % fewer steps. A particle freezes once every point of it moves
  slower than ``freeze_speed_mm_s`` (``|v| + |ω|·r``, r its circumradius) at ``freeze_checks``
  checks in a row; the floor and walls are rigid bodies like the particles (one solver for every
  contact; penetration corrected by contact_erp alone, no split impulse); the walls collide only
  with particles near them; it does not stop while a moving particle is half the quality
  tolerance into the floor (caught landing).
- ``legacy``: the settle before it, kept so that old datasets can be made again pose for pose and
  compared: random orientations stacked in columns over the drop spots (``spawn_heights``), a
  particle frozen when its speed and spin are both below ``freeze_speed_mm_s`` and
  ``freeze_spin_rad_s``.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import numpy as np

from .. import PsdError
from ..config import config_fields
from ..seeding import rng_for
from .geometry import CM, Geometry, gc_paused, quat_to_matrix

logger = logging.getLogger(__name__)
GROUP_ACTIVE, GROUP_FROZEN, GROUP_WALLS, GROUP_INNER, GROUP_FLOOR = 1, 2, 4, 8, 16
GROUP_ALL = GROUP_ACTIVE | GROUP_FROZEN | GROUP_WALLS | GROUP_INNER | GROUP_FLOOR
SETTLES = ("fast", "legacy")
SPAWN_CELL_MM = 1.0  # the fast settle's height field
SPAWN_SHIFT_MM = 3.0  # how far from its drop spot a particle may start, looking for a low spot
WALL_MARGIN_MM = 30.0  # particles farther than this (plus their radius) from every wall skip the walls


# The config's `physics` section (defaults: the schema's, config.schema.yaml).


@dataclass(frozen=True)
class QualityBounds:
    min_settled_fraction: float
    max_penetration_mm: float
    max_below_floor: int  # particles whose lowest point is under the floor (beyond tolerance)
    max_off_table: int  # particles with a point outside the walls (beyond tolerance)
    tolerance_mm: float


@dataclass(frozen=True)
class PhysicsParams:
    settle: str  # "fast" or "legacy" (module docstring)
    timestep_s: float
    solver_iterations: int
    max_time_s: float
    check_every_steps: int
    freeze_speed_mm_s: float
    freeze_spin_rad_s: float
    freeze_checks: int
    stop_frozen_fraction: float
    density_g_cm3: float
    max_mass_ratio: float  # lighter particles are given mass_max / ratio (see particle_masses)
    friction: float
    rolling_friction: float
    restitution: float
    collision_margin_mm: float
    contact_breaking_mm: float
    spawn_gap_mm: float
    contact_erp: float  # measured: 0.2 leaves ~1 mm of penetration under load, 0.8 ~0.2 mm
    retries: int
    quality: QualityBounds

    @classmethod
    def from_dict(cls, d: dict) -> PhysicsParams:
        """From the validated `physics` slice (config.simulate_params)."""
        kw = config_fields(cls, d, "physics")
        kw["quality"] = QualityBounds(**config_fields(QualityBounds, kw["quality"], "physics.quality"))
        if kw["settle"] not in SETTLES:
            raise PsdError(f"physics.settle: {kw['settle']!r} unknown; one of {', '.join(SETTLES)}")
        return cls(**kw)


@dataclass
class SimResult:
    positions_mm: np.ndarray  # (N, 3) centre of volume
    quaternions: np.ndarray  # (N, 4) x, y, z, w
    settled: np.ndarray  # (N,) bool
    quality: dict
    attempt: int


def random_quaternions(rng: np.random.Generator, n: int) -> np.ndarray:
    """Uniform random rotations (x, y, z, w)."""
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def posed_vertices(geometry: Geometry, i: int, pos: np.ndarray, rot: np.ndarray) -> np.ndarray:
    v, _ = geometry.mesh(i)
    return v @ rot.T + pos


def spawn_heights(
    geometry: Geometry, xy: np.ndarray, rots: np.ndarray, table_size: float, gap: float, cell: float = 2.0
) -> np.ndarray:
    """Start heights (mm) that stack the particles without overlap over their drop spots.

    Each particle's rotated extent is treated as a cylinder; columns of a coarse grid record
    the top of what is already there. Low starts mean short falls and few wasted steps.
    """
    n_cells = int(math.ceil(table_size / cell)) + 1
    col = np.zeros((n_cells, n_cells))
    half = table_size / 2
    z = np.empty(len(xy))
    for i, (x, y) in enumerate(xy):
        v = geometry.mesh(i)[0] @ rots[i].T
        r = float(np.hypot(v[:, 0], v[:, 1]).max())
        lo, hi = float(v[:, 2].min()), float(v[:, 2].max())
        i0, i1 = int((x - r + half) / cell), int((x + r + half) / cell) + 1
        j0, j1 = int((y - r + half) / cell), int((y + r + half) / cell) + 1
        sl = (slice(max(i0, 0), max(i1, 1)), slice(max(j0, 0), max(j1, 1)))
        z[i] = col[sl].max() - lo + gap
        col[sl] = z[i] + hi
    return z


def matrix_to_quaternions(r: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotation matrices → (N, 4) unit quaternions x, y, z, w (the inverse of
    ``quat_to_matrix``; each from its largest component, so that none divides by a small one)."""
    m00, m11, m22 = r[:, 0, 0], r[:, 1, 1], r[:, 2, 2]
    cands = np.stack([
        np.stack([1 + m00 - m11 - m22, r[:, 0, 1] + r[:, 1, 0], r[:, 0, 2] + r[:, 2, 0], r[:, 2, 1] - r[:, 1, 2]], -1),
        np.stack([r[:, 0, 1] + r[:, 1, 0], 1 - m00 + m11 - m22, r[:, 1, 2] + r[:, 2, 1], r[:, 0, 2] - r[:, 2, 0]], -1),
        np.stack([r[:, 0, 2] + r[:, 2, 0], r[:, 1, 2] + r[:, 2, 1], 1 - m00 - m11 + m22, r[:, 1, 0] - r[:, 0, 1]], -1),
        np.stack([r[:, 2, 1] - r[:, 1, 2], r[:, 0, 2] - r[:, 2, 0], r[:, 1, 0] - r[:, 0, 1], 1 + m00 + m11 + m22], -1),
    ], 1)  # (N, 4 candidates, 4): candidate k is 4·q_k·q
    diag = np.stack([1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22, 1 + m00 + m11 + m22], -1)
    q = cands[np.arange(len(r)), diag.argmax(axis=-1)]
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _faces(geometry: Geometry) -> tuple:
    """Every particle's faces at once: vertices (V, 3), faces as global vertex indices (F, 3),
    outward unit normals (F, 3), distances of the face planes from the particle's centre (F,),
    the face across each edge (F, 3; edge k is the one opposite corner k) and each face's particle."""
    v = geometry.vertices.astype(np.float64)
    nf = np.diff(geometry.face_offsets)
    pid = np.repeat(np.arange(len(nf)), nf)
    f = geometry.faces.astype(np.int64) + geometry.vert_offsets[:-1][pid, None]
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    normal = np.cross(b - a, c - a)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
    dist = np.einsum("ij,ij->i", normal, a)
    edges = np.sort(np.stack([f[:, [1, 2]], f[:, [2, 0]], f[:, [0, 1]]], axis=1), axis=2).reshape(-1, 2)
    order = np.lexsort((edges[:, 1], edges[:, 0]))
    e = edges[order]
    pair = np.flatnonzero((e[1:] == e[:-1]).all(axis=1))  # a closed mesh: every edge twice
    across = np.full(len(edges), -1)
    across[order[pair]], across[order[pair + 1]] = order[pair + 1] // 3, order[pair] // 3
    return v, f, normal, dist, across.reshape(-1, 3), pid


def resting_rotations(geometry: Geometry, rots: np.ndarray, faces: tuple | None = None) -> np.ndarray:
    """Each particle turned from its orientation `rots` onto the face it comes to rest on when
    dropped on a flat floor, quasi-statically: the face its centre's downward ray leaves through,
    then over the edge its centre's projection lies beyond while that lowers the centre (a face
    is stable when the projection lies on it). Turned the shortest way, so its heading stays."""
    v, f, normal, dist, across, pid = _faces(geometry) if faces is None else faces
    n = len(rots)
    if n == 0:
        return rots
    down = -rots[:, 2, :]  # the world's -z in each particle's own frame
    score = np.einsum("ij,ij->i", normal, down[pid]) / np.maximum(dist, 1e-12)
    order = np.lexsort((-score, pid))
    face = order[np.searchsorted(pid[order], np.arange(n))]  # the exit face of the downward ray
    # barycentric coordinates of the centre's projection on each face's plane
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    e0, e1, e2 = b - a, c - a, dist[:, None] * normal - a
    d00, d01, d11 = (e0 * e0).sum(1), (e0 * e1).sum(1), (e1 * e1).sum(1)
    d20, d21 = (e2 * e0).sum(1), (e2 * e1).sum(1)
    den = np.maximum(d00 * d11 - d01 * d01, 1e-300)
    lb, lc = (d11 * d20 - d01 * d21) / den, (d00 * d21 - d01 * d20) / den
    bary = np.stack([1 - lb - lc, lb, lc], axis=1)
    k = bary.argmin(axis=1)
    nxt = across[np.arange(len(f)), k]
    stays = (bary.min(axis=1) >= 0) | (nxt < 0) | (dist[np.maximum(nxt, 0)] >= dist * (1 - 1e-9))
    nxt = np.where(stays, np.arange(len(f)), nxt)
    for _ in range(len(f)):  # each tip lowers the centre: it ends
        new = nxt[face]
        if np.array_equal(new, face):
            break
        face = new
    w = np.einsum("nij,nj->ni", rots, normal[face])  # the resting face's normal, in the world
    return _shortest_turns(w, np.array([0.0, 0.0, -1.0])) @ rots


def _shortest_turns(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N, 3, 3): the smallest rotation taking each unit vector a to b."""
    vx = np.zeros((len(a), 3, 3))
    cr = np.cross(a, b)
    vx[:, 0, 1], vx[:, 0, 2], vx[:, 1, 2] = -cr[:, 2], cr[:, 1], -cr[:, 0]
    vx[:, 1, 0], vx[:, 2, 0], vx[:, 2, 1] = cr[:, 2], -cr[:, 1], cr[:, 0]
    cos = a @ b
    turn = np.eye(3) + vx + vx @ vx / np.maximum(1 + cos, 1e-12)[:, None, None]
    turn[cos < -1 + 1e-9] = np.diag([1.0, -1.0, -1.0])  # upside down: half a turn about x
    return turn


def resting_spawn(geometry: Geometry, xy: np.ndarray, rots: np.ndarray, table_size: float, gap: float,
                  cell: float = SPAWN_CELL_MM, shift: float = SPAWN_SHIFT_MM,
                  faces: tuple | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Start spots (N, 2) and heights (N,) in mm: each particle in turn, as turned by `rots`,
    lowered onto a height field (cells of `cell` mm) of those placed before it, at the lowest
    spot within `shift` mm of its drop spot, `gap` above what it would touch.

    Each particle's underside and top over the cells (``_surfaces``) are widened by a cell, so that
    what a cell holds is about never lower (top) or higher (underside) than the particle there."""
    v, f, normal, dist, _, pid = _faces(geometry) if faces is None else faces
    n = len(rots)
    vo = geometry.vert_offsets
    nv = np.diff(vo)
    vr = np.einsum("vij,vj->vi", rots[np.repeat(np.arange(n), nv)], v)  # turned, about each centre
    nr = np.einsum("fij,fj->fi", rots[pid], normal)
    half = table_size / 2
    lo = np.minimum.reduceat(vr[:, :2], vo[:-1]) + xy
    hi = np.maximum.reduceat(vr[:, :2], vo[:-1]) + xy
    c0 = np.floor((lo + half) / cell).astype(int) - 1  # first cell (x, y) of each particle's window
    ext = np.floor((hi + half) / cell).astype(int) + 2 - c0  # window size in cells
    zlow = np.minimum.reduceat(vr[:, 2], vo[:-1])
    radius = np.sqrt(np.maximum.reduceat((vr[:, :2] ** 2).sum(axis=1), vo[:-1]))
    tops, bottoms = _surfaces(vr, f, nr, dist, pid, np.repeat(np.arange(n), nv), xy, c0, ext, cell, half)
    k = int(round(shift / cell))
    w = 2 * k + 1
    pad = k + 2
    size = int(math.ceil(table_size / cell)) + 2 + 2 * pad
    height = np.zeros((size, size))
    moves = np.arange(-k, k + 1) * cell
    room = (half - radius)[:, None]  # a start keeps the particle on the table
    ok_x = np.abs(xy[:, 0, None] + moves) <= room
    ok_y = np.abs(xy[:, 1, None] + moves) <= room
    ok_x[:, k] |= ~ok_x.any(axis=1)  # (the drop spot itself, should no move keep it on)
    ok_y[:, k] |= ~ok_y.any(axis=1)
    # what a move costs beside the height: nothing (1e-9 mm² per mm² moved: ties go to the
    # nearer spot), or everything where it would leave the table
    nearer = 1e-9 * (moves[:, None] ** 2 + moves[None, :] ** 2)
    penalty = np.where(ok_x[:, :, None] & ok_y[:, None, :], nearer, np.inf)
    z, move = np.empty(n), np.empty((n, 2), dtype=int)
    item = height.itemsize
    for i in range(n):
        a0, b0 = c0[i] + pad - k
        ex, ey = ext[i]
        windows = np.ndarray((w, w, ex, ey), height.dtype, height, (a0 * size + b0) * item,
                             (size * item, item, size * item, item))  # every start within reach
        lift = (windows - bottoms[i]).max(axis=(2, 3))  # how high it starts at each
        ja, jb = divmod(int((lift + penalty[i]).argmin()), w)
        move[i] = ja, jb
        z[i] = max(float(lift[ja, jb]), -zlow[i]) + gap
        under = height[a0 + ja:a0 + ja + ex, b0 + jb:b0 + jb + ey]
        np.maximum(under, z[i] + tops[i], out=under)
    start = xy + moves[move]
    return start, z


def _surfaces(vr: np.ndarray, f: np.ndarray, nr: np.ndarray, dist: np.ndarray, pid: np.ndarray, vpid: np.ndarray,
              xy: np.ndarray, c0: np.ndarray, ext: np.ndarray, cell: float, half: float) -> tuple[list, list]:
    """Each particle's top and underside over its window of cells (``resting_spawn``), relative to
    its centre: at each cell centre the height of the face above (below) it, a face's plane
    evaluated only over the cells its shadow covers, so the work grows with the area, not with
    area × faces; each vertex also raises (lowers) its own cell; -inf / inf off the particle;
    then each cell takes the extreme of its 3 × 3 neighbourhood."""
    n = len(xy)
    size = ext[:, 0] * ext[:, 1]
    off = np.concatenate([[0], np.cumsum(size)])
    top, bot = np.full(off[-1], -np.inf), np.full(off[-1], np.inf)
    wx = (c0[:, 0] + 0.5) * cell - half - xy[:, 0]  # centre of each window's first cell, particle frame
    wy = (c0[:, 1] + 0.5) * cell - half - xy[:, 1]
    a, b, c = vr[f[:, 0]], vr[f[:, 1]], vr[f[:, 2]]
    for sign, out, pick in ((1.0, top, np.maximum), (-1.0, bot, np.minimum)):
        fs = np.flatnonzero(sign * nr[:, 2] > 1e-9)  # faces turned up (down)
        p = pid[fs]
        tri = np.stack([a[fs, :2], b[fs, :2], c[fs, :2]], axis=1)  # (k, 3, 2)
        i0 = np.ceil((tri[..., 0].min(1) - wx[p]) / cell).astype(int)  # the cells whose centres its shadow may hold
        i1 = np.floor((tri[..., 0].max(1) - wx[p]) / cell).astype(int)
        j0 = np.ceil((tri[..., 1].min(1) - wy[p]) / cell).astype(int)
        j1 = np.floor((tri[..., 1].max(1) - wy[p]) / cell).astype(int)
        ni, nj = np.maximum(i1 - i0 + 1, 0), np.maximum(j1 - j0 + 1, 0)
        cnt = ni * nj
        e = np.repeat(np.arange(len(fs)), cnt)  # one row per (face, cell)
        k = np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        ci, cj = i0[e] + k // nj[e], j0[e] + k % nj[e]
        pe = p[e]
        x, y = wx[pe] + ci * cell, wy[pe] + cj * cell
        t = tri[e]
        d1 = (t[:, 1, 0] - t[:, 0, 0]) * (y - t[:, 0, 1]) - (t[:, 1, 1] - t[:, 0, 1]) * (x - t[:, 0, 0])
        d2 = (t[:, 2, 0] - t[:, 1, 0]) * (y - t[:, 1, 1]) - (t[:, 2, 1] - t[:, 1, 1]) * (x - t[:, 1, 0])
        d3 = (t[:, 0, 0] - t[:, 2, 0]) * (y - t[:, 2, 1]) - (t[:, 0, 1] - t[:, 2, 1]) * (x - t[:, 2, 0])
        eps = 1e-9 * cell * cell
        inside = ((d1 >= -eps) & (d2 >= -eps) & (d3 >= -eps)) | ((d1 <= eps) & (d2 <= eps) & (d3 <= eps))
        g = fs[e[inside]]
        z = (dist[g] - nr[g, 0] * x[inside] - nr[g, 1] * y[inside]) / nr[g, 2]
        pick.at(out, off[pe[inside]] + ci[inside] * ext[pe[inside], 1] + cj[inside], z)
    # every vertex in its own cell (a peak between cell centres)
    vi = np.floor((vr[:, 0] - wx[vpid]) / cell + 0.5).astype(int)
    vj = np.floor((vr[:, 1] - wy[vpid]) / cell + 0.5).astype(int)
    at = off[vpid] + vi * ext[vpid, 1] + vj
    np.maximum.at(top, at, vr[:, 2])
    np.minimum.at(bot, at, vr[:, 2])
    # each cell takes the extreme of its 3 × 3 neighbourhood within its particle's window
    cp = np.repeat(np.arange(n), size)
    local = np.arange(off[-1]) - off[cp]
    ci, cj, ex, ey = local // ext[cp, 1], local % ext[cp, 1], ext[cp, 0], ext[cp, 1]
    wide_top, wide_bot = top.copy(), bot.copy()
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            ok = (ci + di >= 0) & (ci + di < ex) & (cj + dj >= 0) & (cj + dj < ey)
            src = np.where(ok, np.arange(off[-1]) + di * ey + dj, 0)
            np.maximum(wide_top, np.where(ok, top[src], -np.inf), out=wide_top)
            np.minimum(wide_bot, np.where(ok, bot[src], np.inf), out=wide_bot)
    tops = [wide_top[off[i]:off[i + 1]].reshape(ext[i]) for i in range(n)]
    bottoms = [wide_bot[off[i]:off[i + 1]].reshape(ext[i]) for i in range(n)]
    return tops, bottoms


def particle_masses(volume_mm3: np.ndarray, density_g_cm3: float, max_ratio: float) -> np.ndarray:
    """Masses in g, with the lightest raised to 1/max_ratio of the heaviest.

    Bullet's iterative solver cannot hold a 1 mm grain under a 20 mm stone (mass ratio ~8000):
    the grain is pressed through the floor. Capping the ratio keeps contacts stiff; it changes
    how the bed packs only for particles too small to matter for the image.
    """
    m = density_g_cm3 * np.asarray(volume_mm3, dtype=float) * CM**3
    if len(m) == 0:
        return m
    return np.maximum(m, m.max() / max_ratio)


def quality_figures(
    geometry: Geometry, pos_mm: np.ndarray, quats: np.ndarray, settled: np.ndarray, min_contact_mm: float,
    table_size: float, tol: float,
) -> dict:
    rots = quat_to_matrix(quats)
    half = table_size / 2
    below = off = 0
    lowest = np.inf
    for i in range(len(pos_mm)):
        v = posed_vertices(geometry, i, pos_mm[i], rots[i])
        zmin = float(v[:, 2].min())
        lowest = min(lowest, zmin)
        below += zmin < -tol
        off += bool(np.abs(v[:, :2]).max() > half + tol)
    finite = bool(np.isfinite(pos_mm).all() and np.isfinite(quats).all())
    return {
        "n_particles": int(len(pos_mm)),
        "settled_fraction": float(settled.mean()) if len(settled) else 1.0,
        "below_floor": int(below),
        "off_table": int(off),
        "lowest_point_mm": float(lowest) if finite else float("nan"),
        "worst_penetration_mm": float(max(0.0, -min_contact_mm)),
        "finite": finite,
    }


def quality_problems(q: dict, b: QualityBounds) -> list[str]:
    problems = []
    if not q["finite"]:
        problems.append("the simulation blew up (non-finite poses)")
    if q["settled_fraction"] < b.min_settled_fraction:
        problems.append(f"settled fraction {q['settled_fraction']:.3f} < {b.min_settled_fraction}")
    if q["below_floor"] > b.max_below_floor:
        problems.append(f"{q['below_floor']} particles below the floor (> {b.max_below_floor})")
    if q["off_table"] > b.max_off_table:
        problems.append(f"{q['off_table']} particles outside the walls (> {b.max_off_table})")
    if q["worst_penetration_mm"] > b.max_penetration_mm:
        problems.append(f"worst penetration {q['worst_penetration_mm']:.2f} mm > {b.max_penetration_mm} mm")
    return problems


def _run_once(geometry: Geometry, xy: np.ndarray, table_size: float, p: PhysicsParams,
              rng: np.random.Generator) -> tuple:
    import pybullet as pb

    with gc_paused():  # ~10^4 small lists handed to pybullet; collecting them found nothing
        return _settle(pb, geometry, xy, table_size, p, rng)


def _settle(pb, geometry: Geometry, xy: np.ndarray, table_size: float, p: PhysicsParams,
            rng: np.random.Generator) -> tuple:
    n = len(geometry)
    fast = p.settle == "fast"
    quats = random_quaternions(rng, n)
    rots = quat_to_matrix(quats)
    if fast:
        faces = _faces(geometry)
        rots = resting_rotations(geometry, rots, faces)
        quats = matrix_to_quaternions(rots)
        xy, z0 = resting_spawn(geometry, xy, rots, table_size, p.spawn_gap_mm, faces=faces)
    else:
        z0 = spawn_heights(geometry, xy, rots, table_size, p.spawn_gap_mm)
    radius = circumradii_cm(geometry)
    half_mm = table_size / 2
    # the fast settle: particles far from every wall skip the walls (a plane pairs with every
    # particle in the broadphase, ~15 % of a step), until they come near one
    near_wall_mm = half_mm - WALL_MARGIN_MM - radius / CM
    inner = (np.abs(xy).max(axis=1) < near_wall_mm) if fast else np.zeros(n, dtype=bool)

    cid = pb.connect(pb.DIRECT)
    try:
        pb.setGravity(0, 0, -981.0, physicsClientId=cid)
        pb.setTimeStep(p.timestep_s, physicsClientId=cid)
        pb.setPhysicsEngineParameter(
            numSolverIterations=p.solver_iterations,
            contactBreakingThreshold=p.contact_breaking_mm * CM,
            deterministicOverlappingPairs=1,
            contactERP=p.contact_erp,
            erp=p.contact_erp,
            **({"useSplitImpulse": 0} if fast else {}),
            physicsClientId=cid,
        )
        half = table_size / 2 * CM
        # floor and four walls: half-spaces, nothing escapes them
        for normal, origin in [
            ((0, 0, 1), (0, 0, 0)),
            ((1, 0, 0), (-half, 0, 0)),
            ((-1, 0, 0), (half, 0, 0)),
            ((0, 1, 0), (0, -half, 0)),
            ((0, -1, 0), (0, half, 0)),
        ]:
            shape = pb.createCollisionShape(pb.GEOM_PLANE, planeNormal=normal, physicsClientId=cid)
            # fast: static rigid bodies, as the particles are (legacy's are multibodies: their
            # contacts went through the multibody solver, ~30 % of a step)
            body = pb.createMultiBody(0, shape, basePosition=origin, useMaximalCoordinates=fast, physicsClientId=cid)
            pb.changeDynamics(body, -1, lateralFriction=p.friction, restitution=p.restitution, physicsClientId=cid)
            if fast and normal[2]:
                pb.setCollisionFilterGroupMask(body, -1, GROUP_FLOOR, GROUP_ACTIVE | GROUP_INNER, physicsClientId=cid)
            else:
                pb.setCollisionFilterGroupMask(body, -1, GROUP_WALLS, GROUP_ACTIVE, physicsClientId=cid)

        masses = particle_masses(geometry.volume_mm3, p.density_g_cm3, p.max_mass_ratio)
        bodies = []
        for i in range(n):
            v, _ = geometry.mesh(i)
            shape = pb.createCollisionShape(pb.GEOM_MESH, vertices=(v * CM).tolist(), physicsClientId=cid)
            body = pb.createMultiBody(
                masses[i],
                shape,
                basePosition=[xy[i, 0] * CM, xy[i, 1] * CM, z0[i] * CM],
                baseOrientation=quats[i].tolist(),
                useMaximalCoordinates=True,
                physicsClientId=cid,
            )
            pb.changeDynamics(
                body,
                -1,
                lateralFriction=p.friction,
                rollingFriction=p.rolling_friction * CM,
                restitution=p.restitution,
                collisionMargin=p.collision_margin_mm * CM,
                physicsClientId=cid,
            )
            if inner[i]:
                pb.setCollisionFilterGroupMask(body, -1, GROUP_INNER, GROUP_ALL & ~GROUP_WALLS, physicsClientId=cid)
            else:
                pb.setCollisionFilterGroupMask(body, -1, GROUP_ACTIVE, GROUP_ALL, physicsClientId=cid)
            bodies.append(body)

        slow_count = np.zeros(n, dtype=int)
        frozen = np.zeros(n, dtype=bool)
        max_steps = int(round(p.max_time_s / p.timestep_s))
        v_thr = p.freeze_speed_mm_s * CM
        reach = (near_wall_mm * CM).tolist()
        step = 0
        t0 = time.perf_counter()
        while step < max_steps:
            for _ in range(p.check_every_steps):
                pb.stepSimulation(physicsClientId=cid)
            step += p.check_every_steps
            for i in np.flatnonzero(~frozen):
                lin, ang = pb.getBaseVelocity(bodies[i], physicsClientId=cid)
                if fast:  # every point of the particle slower than freeze_speed
                    slow = math.hypot(*lin) + math.hypot(*ang) * radius[i] < v_thr
                    if inner[i]:
                        at, _ = pb.getBasePositionAndOrientation(bodies[i], physicsClientId=cid)
                        if max(abs(at[0]), abs(at[1])) >= reach[i]:  # come near a wall: the walls again
                            inner[i] = False
                            pb.setCollisionFilterGroupMask(bodies[i], -1, GROUP_ACTIVE, GROUP_ALL, physicsClientId=cid)
                else:
                    slow = math.hypot(*lin) < v_thr and math.hypot(*ang) < p.freeze_spin_rad_s
                slow_count[i] = slow_count[i] + 1 if slow else 0
                if slow_count[i] >= p.freeze_checks:
                    # freeze: a static body costs nothing in the solver and stops jitter
                    pb.resetBaseVelocity(bodies[i], [0, 0, 0], [0, 0, 0], physicsClientId=cid)
                    pb.changeDynamics(bodies[i], -1, mass=0, physicsClientId=cid)
                    # frozen particles still collide with moving ones, but no longer with each
                    # other or the walls: the broadphase drops those pairs (measured: step cost
                    # falls with the number of moving particles instead of staying high)
                    pb.setCollisionFilterGroupMask(bodies[i], -1, GROUP_FROZEN, GROUP_ACTIVE | GROUP_INNER,
                                                   physicsClientId=cid)
                    frozen[i] = True
            if frozen.mean() >= p.stop_frozen_fraction:
                if not fast or not _landing(pb, cid, bodies, np.flatnonzero(~frozen), geometry,
                                            p.quality.tolerance_mm / 2):
                    break
        sim_time = step * p.timestep_s
        logger.info(f"settled {frozen.sum()}/{n} particles in {step} steps ({sim_time:.2f} s simulated, "
            f"{time.perf_counter() - t0:.1f} s wall)")

        pos = np.empty((n, 3))
        quat = np.empty((n, 4))
        for i, b in enumerate(bodies):
            ps, qs = pb.getBasePositionAndOrientation(b, physicsClientId=cid)
            pos[i], quat[i] = ps, qs
        pb.performCollisionDetection(physicsClientId=cid)
        contacts = pb.getContactPoints(physicsClientId=cid)
        min_contact = min((c[8] for c in contacts), default=0.0) / CM
        return pos / CM, quat, frozen, min_contact, step, sim_time
    finally:
        pb.disconnect(physicsClientId=cid)


def _landing(pb, cid: int, bodies: list[int], moving: np.ndarray, geometry: Geometry, depth_mm: float) -> bool:
    """Whether a moving particle is deeper than `depth_mm` in the floor: caught mid-impact (a small
    grain falling into a gap as the last ones settle), which the fast settle steps on through
    rather than stop on (a snapshot of it would fail the quality bounds and cost a whole retry)."""
    for i in moving:
        at, turn = pb.getBasePositionAndOrientation(bodies[i], physicsClientId=cid)
        v, _ = geometry.mesh(i)
        if float((v @ quat_to_matrix(np.asarray([turn]))[0].T)[:, 2].min()) + at[2] / CM < -depth_mm:
            return True
    return False


def circumradii_cm(geometry: Geometry) -> np.ndarray:
    """Each particle's largest vertex distance from its centre, in pybullet's unit."""
    r = np.linalg.norm(geometry.vertices.astype(np.float64), axis=1)
    return np.maximum.reduceat(r, geometry.vert_offsets[:-1]) * CM if len(geometry) else np.zeros(0)


def simulate(geometry: Geometry, xy: np.ndarray, table_size: float, entropy: list[int], p: PhysicsParams) -> SimResult:
    """Settle the scene; retry with derived seeds when quality bounds fail, then fail loudly."""
    failures = []
    for attempt in range(p.retries + 1):
        rng = rng_for(entropy, "simulate", attempt)
        t0 = time.perf_counter()
        pos, quat, settled, min_contact, steps, sim_time = _run_once(geometry, xy, table_size, p, rng)
        q = quality_figures(geometry, pos, quat, settled, min_contact, table_size, p.quality.tolerance_mm)
        q.update(steps=steps, simulated_s=sim_time, wall_s=time.perf_counter() - t0, attempt=attempt)
        problems = quality_problems(q, p.quality)
        if not problems:
            return SimResult(pos, quat, settled, q, attempt)
        logger.warning(f"attempt {attempt}: quality check failed: {'; '.join(problems)}")
        failures.append(f"attempt {attempt}: {'; '.join(problems)}")
    raise PsdError(
        f"simulation failed its quality bounds after {p.retries + 1} attempts:\n  " + "\n  ".join(failures)
        + "\nRelax config physics.quality, lengthen physics.max_time_s, or check the particle sizes."
    )
