import logging

import numpy as np
import pytest

from psdfactory import PsdError
from psdfactory import config as psd_config
from psdfactory.scene.geometry import Geometry
from psdfactory.scene.physics import (
    PhysicsParams,
    QualityBounds,
    quality_figures,
    quality_problems,
    quat_to_matrix,
    random_quaternions,
    simulate,
    spawn_heights,
)
from psdfactory.scene.sampling import SampleParams, sample_scene

from .conftest import tiny_config


def _scene(index=0, **over):
    cfg = tiny_config(**over)
    spec, geo = sample_scene(SampleParams.from_dict(psd_config.sample_params(cfg, "tiny", index)))
    xy = np.array([[p["x"], p["y"]] for p in spec["particles"]])
    return cfg, spec, Geometry.from_arrays(geo), xy


def test_quaternions_are_rotations():
    q = random_quaternions(np.random.default_rng(0), 50)
    r = quat_to_matrix(q)
    np.testing.assert_allclose(r @ np.transpose(r, (0, 2, 1)), np.broadcast_to(np.eye(3), r.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(r), 1.0)


def test_spawn_heights_do_not_overlap_in_columns():
    _, spec, geo, xy = _scene()
    rots = quat_to_matrix(random_quaternions(np.random.default_rng(0), len(geo)))
    z = spawn_heights(geo, xy, rots, 60.0, gap=0.5)
    lows = np.array([(geo.mesh(i)[0] @ rots[i].T)[:, 2].min() for i in range(len(geo))])
    assert (z + lows >= 0.5 - 1e-9).all()  # every particle starts above the floor


@pytest.mark.slow
def test_settled_bed_is_physical_and_deterministic():
    cfg, spec, geo, xy = _scene()
    p = PhysicsParams.from_dict(psd_config.simulate_params(cfg))
    a = simulate(geo, xy, 60.0, spec["entropy"], p)
    b = simulate(geo, xy, 60.0, spec["entropy"], p)
    np.testing.assert_array_equal(a.positions_mm, b.positions_mm)
    np.testing.assert_array_equal(a.quaternions, b.quaternions)
    rots = quat_to_matrix(a.quaternions)
    for i in range(len(geo)):
        v = geo.mesh(i)[0] @ rots[i].T + a.positions_mm[i]
        assert v[:, 2].min() > -p.quality.tolerance_mm, f"particle {i} sank through the floor"
        assert np.abs(v[:, :2]).max() < 30 + p.quality.tolerance_mm, f"particle {i} left the table"
    # they came to rest on the table, not in the air: the bed is a few particles thick at most
    assert a.positions_mm[:, 2].max() < 3 * geo.dims_mm[:, 0].max()
    assert a.quality["settled_fraction"] >= 0.95
    assert a.quality["worst_penetration_mm"] < 1.0


def test_quality_figures_flag_bad_poses():
    _, spec, geo, xy = _scene()
    n = len(geo)
    pos = np.column_stack([xy, np.full(n, 20.0)])
    quat = np.tile([0, 0, 0, 1.0], (n, 1))
    pos[0, 2] = -5.0  # sunk through the floor
    pos[1, 0] = 40.0  # beyond the wall at x = 30
    q = quality_figures(geo, pos, quat, np.ones(n, bool), min_contact_mm=-2.0, table_size=60.0, tol=0.5)
    assert q["below_floor"] == 1 and q["off_table"] == 1 and q["worst_penetration_mm"] == 2.0
    bounds = PhysicsParams.from_dict(psd_config.simulate_params(tiny_config())).quality  # the schema's defaults
    assert isinstance(bounds, QualityBounds)
    problems = quality_problems(q, bounds)
    assert len(problems) == 3
    pos[2, 2] = np.nan
    q = quality_figures(geo, pos, quat, np.ones(n, bool), 0.0, 60.0, 0.5)
    assert any("blew up" in s for s in quality_problems(q, bounds))


@pytest.mark.slow
def test_scene_failing_quality_is_retried_then_fails_loudly(caplog):
    cfg, spec, geo, xy = _scene(count=[30, 30])
    phys = psd_config.simulate_params(cfg)
    phys.update(max_time_s=0.05, retries=1)  # far too short to settle
    phys["quality"]["min_settled_fraction"] = 0.99
    with pytest.raises(PsdError, match="after 2 attempts") as e:
        simulate(geo, xy, 60.0, spec["entropy"], PhysicsParams.from_dict(phys))
    assert "settled fraction" in str(e.value)
    retried = [r for r in caplog.records if r.levelno == logging.WARNING and "quality check failed" in r.getMessage()]
    assert [r.getMessage().split(":")[0] for r in retried] == ["attempt 0", "attempt 1"]


def test_mass_ratio_is_capped():
    from psdfactory.scene.physics import particle_masses

    m = particle_masses(np.array([1.0, 1000.0, 8000.0]), 2.0, max_ratio=100.0)
    np.testing.assert_allclose(m, [0.16, 2.0, 16.0])  # 8000 mm³ × 2 g/cm³ = 16 g; floor 0.16 g


def test_matrix_to_quaternions_inverts_quat_to_matrix():
    from psdfactory.scene.physics import matrix_to_quaternions

    q = random_quaternions(np.random.default_rng(3), 200)
    back = matrix_to_quaternions(quat_to_matrix(q))
    np.testing.assert_allclose(np.abs((back * q).sum(axis=1)), 1.0, atol=1e-12)  # q and -q: one rotation


def test_resting_rotations_lie_on_a_face_their_centre_stands_over():
    from scipy.spatial import Delaunay

    from psdfactory.scene.physics import resting_rotations

    _, _, geo, _ = _scene(count=[60, 60])
    turned = resting_rotations(geo, quat_to_matrix(random_quaternions(np.random.default_rng(0), len(geo))))
    for i in range(len(geo)):
        v = geo.mesh(i)[0] @ turned[i].T
        foot = v[v[:, 2] < v[:, 2].min() + 1e-9 * np.abs(v).max()][:, :2]
        assert len(foot) >= 3, f"particle {i} does not lie on a face"
        assert Delaunay(foot).find_simplex([0.0, 0.0]) >= 0, f"particle {i} would tip over"  # its centre is at 0


def test_resting_spawn_starts_near_the_drop_spots_and_above_what_is_below():
    from psdfactory.scene.physics import SPAWN_SHIFT_MM, resting_rotations, resting_spawn

    _, _, geo, xy = _scene(count=[80, 80])
    rots = resting_rotations(geo, quat_to_matrix(random_quaternions(np.random.default_rng(1), len(geo))))
    start, z = resting_spawn(geo, xy, rots, 60.0, gap=0.5)
    assert np.abs(start - xy).max() <= SPAWN_SHIFT_MM + 1e-9
    posed = [geo.mesh(i)[0] @ rots[i].T + [*start[i], z[i]] for i in range(len(geo))]
    assert min(v[:, 2].min() for v in posed) >= 0.5 - 1e-9  # above the floor by the gap
    assert max(np.abs(v[:, :2]).max() for v in posed) <= 30 + 1e-9  # on the table
    # no particle starts inside another (checked with the hulls' face planes at the other's vertices)
    from psdfactory.scene.shapes import convex_mesh

    planes = []
    for v in posed:
        hv, hf = convex_mesh(v)
        n = np.cross(hv[hf[:, 1]] - hv[hf[:, 0]], hv[hf[:, 2]] - hv[hf[:, 0]])
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        planes.append((n, np.einsum("ij,ij->i", n, hv[hf[:, 0]])))
    for i, (n, d) in enumerate(planes):
        for j, v in enumerate(posed):
            if i != j:
                depth = (d[None, :] - v @ n.T).min(axis=1)  # > 0: the vertex lies inside hull i
                assert depth.max() < 0.05, f"particle {j} starts {depth.max():.2f} mm inside particle {i}"


@pytest.mark.slow
def test_the_legacy_settle_is_still_there_and_deterministic():
    cfg, spec, geo, xy = _scene()
    params = psd_config.simulate_params(cfg)
    assert params["settle"] == "fast"  # the default
    params["settle"] = "legacy"
    p = PhysicsParams.from_dict(params)
    a = simulate(geo, xy, 60.0, spec["entropy"], p)
    b = simulate(geo, xy, 60.0, spec["entropy"], p)
    np.testing.assert_array_equal(a.positions_mm, b.positions_mm)
    assert a.quality["settled_fraction"] >= 0.95 and a.quality["worst_penetration_mm"] < 1.0
    params["settle"] = "fastest"
    with pytest.raises(PsdError, match="physics.settle"):
        PhysicsParams.from_dict(params)
