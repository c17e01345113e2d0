"""Stage 2: drop the particles on the table with pybullet and let them settle.

Internally Bullet works in centimetres (gravity -981 cm/s²): measured to behave best for
millimetre-to-centimetre particles. Everything that leaves this module is in mm.
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
from .geometry import CM, Geometry, quat_to_matrix

logger = logging.getLogger(__name__)
GROUP_ACTIVE, GROUP_FROZEN, GROUP_WALLS = 1, 2, 4
GROUP_ALL = GROUP_ACTIVE | GROUP_FROZEN | GROUP_WALLS


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

    n = len(geometry)
    quats = random_quaternions(rng, n)
    rots = quat_to_matrix(quats)
    z0 = spawn_heights(geometry, xy, rots, table_size, p.spawn_gap_mm)

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
            body = pb.createMultiBody(0, shape, basePosition=origin, physicsClientId=cid)
            pb.changeDynamics(body, -1, lateralFriction=p.friction, restitution=p.restitution, physicsClientId=cid)
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
            pb.setCollisionFilterGroupMask(body, -1, GROUP_ACTIVE, GROUP_ALL, physicsClientId=cid)
            bodies.append(body)

        slow_count = np.zeros(n, dtype=int)
        frozen = np.zeros(n, dtype=bool)
        max_steps = int(round(p.max_time_s / p.timestep_s))
        v_thr = p.freeze_speed_mm_s * CM
        step = 0
        t0 = time.perf_counter()
        while step < max_steps:
            for _ in range(p.check_every_steps):
                pb.stepSimulation(physicsClientId=cid)
            step += p.check_every_steps
            for i in np.flatnonzero(~frozen):
                lin, ang = pb.getBaseVelocity(bodies[i], physicsClientId=cid)
                slow = math.hypot(*lin) < v_thr and math.hypot(*ang) < p.freeze_spin_rad_s
                slow_count[i] = slow_count[i] + 1 if slow else 0
                if slow_count[i] >= p.freeze_checks:
                    # freeze: a static body costs nothing in the solver and stops jitter
                    pb.resetBaseVelocity(bodies[i], [0, 0, 0], [0, 0, 0], physicsClientId=cid)
                    pb.changeDynamics(bodies[i], -1, mass=0, physicsClientId=cid)
                    # frozen particles still collide with moving ones, but no longer with each
                    # other or the walls: the broadphase drops those pairs (measured: step cost
                    # falls with the number of moving particles instead of staying high)
                    pb.setCollisionFilterGroupMask(bodies[i], -1, GROUP_FROZEN, GROUP_ACTIVE, physicsClientId=cid)
                    frozen[i] = True
            if frozen.mean() >= p.stop_frozen_fraction:
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
