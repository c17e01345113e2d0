"""The size definitions on shapes with known answers, and the sieve search against an independent
brute-force search written here (a dense grid of passing directions × hole angles, refined by
Nelder–Mead: nothing of the production search)."""

import numpy as np
import pytest

from psdfactory.psd import (
    ALL_DEFINITION_TARGETS,
    SIZE_DEFINITIONS,
    WEIGHTINGS,
    definition_targets,
    size_column,
    weighted_percentiles,
)
from psdfactory.scene import sizes
from psdfactory.scene.shapes import ShapeParams, convex_mesh, fibonacci_sphere, make_particles, pack


def box_points(a: float, b: float, c: float) -> np.ndarray:
    return np.array([[x, y, z] for x in (-a / 2, a / 2) for y in (-b / 2, b / 2) for z in (-c / 2, c / 2)])


def ellipsoid_points(a: float, b: float, c: float, n: int = 3000) -> np.ndarray:
    return fibonacci_sphere(n) * np.array([a, b, c]) / 2


def one(points: np.ndarray) -> np.ndarray:
    return sizes.pad_vertices(points, np.array([0, len(points)]))


def brute_force_sieve(v: np.ndarray, n_dirs: int = 1500) -> float:
    """The smallest square hole side over a grid of passing directions and hole angles, the best
    few refined by Nelder–Mead over (direction, angle)."""
    from scipy.optimize import minimize

    def sides(d: np.ndarray, th: np.ndarray) -> np.ndarray:
        d = d / np.linalg.norm(d)
        e = np.cross(d, [1.0, 0, 0] if abs(d[0]) < 0.9 else [0, 1.0, 0])
        e /= np.linalg.norm(e)
        f = np.cross(d, e)
        u = np.cos(th)[:, None] * e + np.sin(th)[:, None] * f
        w = -np.sin(th)[:, None] * e + np.cos(th)[:, None] * f
        return np.maximum(np.ptp(v @ u.T, axis=0), np.ptp(v @ w.T, axis=0))

    dirs = fibonacci_sphere(2 * n_dirs)
    dirs = dirs[dirs[:, 2] >= 0]
    th = np.deg2rad(np.arange(0.0, 90.0, 2.0))
    coarse = sorted((sides(d, th).min(), i, th[sides(d, th).argmin()]) for i, d in enumerate(dirs))
    best = coarse[0][0]
    for _, i, t0 in coarse[:6]:
        r = minimize(lambda x: sides(x[:3], x[3:])[0], np.r_[dirs[i], t0], method="Nelder-Mead",
                     options={"xatol": 1e-8, "fatol": 1e-10, "maxiter": 3000})
        best = min(best, float(r.fun))
    return best


def test_cube_passes_a_hole_of_its_side():
    assert sizes.sieve_sizes(one(box_points(3.0, 3.0, 3.0)))[0] == pytest.approx(3.0, rel=1e-4)


def test_sphere_passes_a_hole_of_its_diameter():
    assert sizes.sieve_sizes(one(ellipsoid_points(8.0, 8.0, 8.0)))[0] == pytest.approx(8.0, rel=2e-3)


@pytest.mark.parametrize("c", [0.4, 0.2, 0.05, 0.01])
def test_thin_plate_passes_edge_on_along_the_diagonal(c):
    a, b = 10.0, 6.0
    s = sizes.sieve_sizes(one(box_points(a, b, c)))[0]
    assert s == pytest.approx((b + c) / np.sqrt(2), rel=1e-3)  # → b/√2 as the plate gets thinner
    assert s < b


def test_ellipsoid_sieve_is_the_sedimentologists_formula():
    # passing along the long axis the shadow is the b × c ellipse; its smallest square lies at 45°
    a, b, c = 12.0, 8.0, 3.0
    s = sizes.sieve_sizes(one(ellipsoid_points(a, b, c)))[0]
    assert s == pytest.approx(np.sqrt((b * b + c * c) / 2), rel=3e-3)


@pytest.mark.parametrize("shape", [(10.0, 6.0, 4.0), (5.0, 4.5, 1.0), (9.0, 3.0, 2.5), (7.0, 5.0, 5.0)])
def test_box_sieve_matches_brute_force(shape):
    v = box_points(*shape) @ np.linalg.qr(np.random.default_rng(1).normal(size=(3, 3)))[0]  # turned anyhow
    ours = sizes.sieve_sizes(one(v))[0]
    assert ours == pytest.approx(brute_force_sieve(v), rel=5e-3)
    assert ours <= brute_force_sieve(v) * (1 + 1e-3)


@pytest.mark.slow
@pytest.mark.parametrize("family", ["crushed_rock", "ellipsoid", "granule"])
def test_family_sieve_matches_brute_force(family):
    parts = make_particles(family, np.full(4, 10.0), np.random.default_rng(5), ShapeParams.for_family(family))
    for p in parts:
        ref = brute_force_sieve(p.vertices)
        assert p.sieve_mm == pytest.approx(ref, rel=5e-3), family
        assert p.sieve_mm <= ref * 1.005


def test_minimum_box_of_a_turned_box_and_an_ellipsoid():
    turn = np.linalg.qr(np.random.default_rng(2).normal(size=(3, 3)))[0]
    dims, _ = sizes.minimum_box(one(box_points(4.0, 9.0, 2.0) @ turn))
    np.testing.assert_allclose(dims[0], [9.0, 4.0, 2.0], rtol=1e-3)
    # an ellipsoid's smallest box is the one along its axes (Hadamard's inequality)
    dims, _ = sizes.minimum_box(one(ellipsoid_points(12.0, 7.0, 3.0) @ turn))
    np.testing.assert_allclose(dims[0], [12.0, 7.0, 3.0], rtol=1e-2)


def test_minimum_box_is_no_larger_than_trimeshs():
    trimesh = pytest.importorskip("trimesh")
    parts = make_particles("crushed_rock", np.full(8, 10.0), np.random.default_rng(3),
                           ShapeParams.for_family("crushed_rock"))
    for p in parts:
        _, extents = trimesh.bounds.oriented_bounds(trimesh.Trimesh(p.vertices, p.faces))
        assert np.prod(p.dims_mm) <= np.prod(extents) * 1.003  # never worse than its one-face-flush heuristic
        assert p.dims_mm[1] == pytest.approx(10.0)  # the drawn size is the b-axis
        assert p.dims_mm[0] >= p.dims_mm[1] >= p.dims_mm[2] > 0


def test_esd_of_a_sphere_and_a_cube():
    assert sizes.equivalent_sphere_diameter(np.array([np.pi / 6 * 8.0**3]))[0] == pytest.approx(8.0)
    assert sizes.equivalent_sphere_diameter(np.array([27.0]))[0] == pytest.approx((6 * 27 / np.pi) ** (1 / 3))


def test_footprints_of_a_resting_and_a_turned_box():
    v, _ = convex_mesh(box_points(8.0, 6.0, 2.0))
    flat = np.array([0.0, 0.0, 0.0, 1.0])  # x, y, z, w
    on_edge = np.array([np.sin(np.pi / 4), 0.0, 0.0, np.cos(np.pi / 4)])  # 90° about x: shows 8 × 2
    quarter = np.array([0.0, 0.0, np.sin(np.pi / 8), np.cos(np.pi / 8)])  # 45° about z: the same 8 × 6
    f = sizes.footprints(np.concatenate([v, v, v]), np.array([0, 8, 16, 24]), np.stack([flat, on_edge, quarter]))
    np.testing.assert_allclose(f["feret_min_mm"], [6.0, 2.0, 6.0], rtol=1e-9)
    np.testing.assert_allclose(f["feret_max_mm"], [10.0, np.hypot(8, 2), 10.0], rtol=1e-9)
    np.testing.assert_allclose(f["ecd_mm"], np.sqrt(4 * np.array([48.0, 16.0, 48.0]) / np.pi), rtol=1e-9)


def test_the_search_is_deterministic_and_scale_equivariant():
    parts = make_particles("crushed_rock", np.array([4.0, 9.0]), np.random.default_rng(4),
                           ShapeParams.for_family("crushed_rock"))
    g = pack(parts)
    v = sizes.pad_vertices(g["vertices"].astype(float), g["vert_offsets"])
    a, b = sizes.sieve_sizes(v), sizes.sieve_sizes(v)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_allclose(sizes.sieve_sizes(v * 2.5), 2.5 * a, rtol=2e-3)


def test_definition_names_and_columns():
    assert size_column("b-axis") == "b_axis_mm" and size_column("feret-min") == "feret_min_mm"
    assert definition_targets("sieve", "number") == ("d10_sieve_mm", "d50_sieve_mm", "d90_sieve_mm")
    assert definition_targets("esd", "volume") == ("d10_esd_v_mm", "d50_esd_v_mm", "d90_esd_v_mm")
    assert len(set(ALL_DEFINITION_TARGETS)) == 3 * len(SIZE_DEFINITIONS) * len(WEIGHTINGS)
    with pytest.raises(Exception, match="unknown size definition"):
        size_column("diameter")


def test_schema_names_the_same_definitions():
    import yaml

    from psdfactory.config import SCHEMA

    labels = yaml.safe_load(SCHEMA.read_text())["properties"]["labels"]["properties"]
    assert tuple(labels["size_definition"]["enum"]) == SIZE_DEFINITIONS
    assert tuple(labels["weighting"]["enum"]) == WEIGHTINGS


@pytest.mark.slow
@pytest.mark.parametrize("definition,weighting", [("sieve", "number"), ("b-axis", "volume")])
def test_labels_recomputed_from_the_particle_table(tmp_path, definition, weighting):
    import pyarrow.parquet as pq

    from psdfactory.io import read_json
    from psdfactory.scene.stages import load_geometry
    from tests.conftest import make_scene, tiny_config

    cfg = tiny_config()
    cfg["labels"].update(size_definition=definition, weighting=weighting)
    d = make_scene(cfg, tmp_path / "tiny" / "scenes" / "tiny-000000")
    labels, parts = read_json(d / "labels.json"), pq.read_table(d / "particles.parquet").to_pydict()
    assert labels["size_definition"] == definition and labels["weighting"] == weighting
    vol = np.array(parts["volume_mm3"])
    for name in SIZE_DEFINITIONS:
        x = np.array(parts[size_column(name)])
        assert np.isfinite(x).all() and (x > 0).all(), name
        for w, wts in (("number", None), ("volume", vol)):
            np.testing.assert_allclose([labels[t] for t in definition_targets(name, w)], weighted_percentiles(x, wts))
    np.testing.assert_array_equal(parts["size_mm"], parts[size_column(definition)])
    main = weighted_percentiles(np.array(parts["size_mm"]), vol if weighting == "volume" else None)
    np.testing.assert_allclose([labels["d10_mm"], labels["d50_mm"], labels["d90_mm"]], main)
    # the sieve size recomputed from the scene's own geometry.npz
    g = load_geometry(d)
    again = sizes.sieve_sizes(sizes.pad_vertices(g.vertices, g.vert_offsets))
    np.testing.assert_allclose(parts["sieve_mm"], again, rtol=5e-3)
    b = np.array(parts["b_axis_mm"])
    np.testing.assert_allclose(b, g.size_mm, rtol=1e-3)  # the drawn size is the b-axis
    assert (np.array(parts["sieve_mm"]) <= b * 1.001).all() and (np.array(parts["c_axis_mm"]) <= b).all()


@pytest.mark.parametrize("family", ["crushed_rock", "granule"])
def test_all_silhouettes_at_once_match_one_hull_each(family):
    rng = np.random.default_rng(8)
    g = pack(make_particles(family, rng.uniform(2, 20, 60), rng, ShapeParams.for_family(family)))
    q = rng.normal(size=(60, 4))
    hulls = sizes.footprints(g["vertices"], g["vert_offsets"], q)
    batched = sizes.footprints(g["vertices"], g["vert_offsets"], q, g["faces"], g["face_offsets"], chunk=16)
    for k in ("feret_min_mm", "feret_max_mm", "ecd_mm"):
        np.testing.assert_allclose(batched[k], hulls[k], rtol=1e-9, err_msg=k)


def test_the_grid_through_a_kd_tree_is_the_grid_of_every_cosine():
    frames, dirs, axes = sizes._grid()
    every = np.stack([sizes._nearest_direction(frames[:, k], dirs) for k in range(3)], axis=1)
    np.testing.assert_array_equal(axes, every)


def test_grid_widths_in_blocks_equal_one_product():
    rock = ShapeParams.for_family("crushed_rock")
    parts = make_particles("crushed_rock", np.full(40, 5.0), np.random.default_rng(6), rock)
    g = pack(parts)
    v = sizes.pad_vertices(g["vertices"].astype(float), g["vert_offsets"])
    p = v.astype(np.float32) @ sizes._grid()[1].T.astype(np.float32)
    np.testing.assert_array_equal(sizes.grid_widths(v), p.max(axis=1) - p.min(axis=1))
