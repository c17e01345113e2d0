from pathlib import Path

import numpy as np
import pytest

from psdfactory import PsdError
from psdfactory.scene.geometry import Geometry
from psdfactory.scene.shapes import (
    ShapeParams,
    convex_mesh,
    make_particles,
    pack,
    volume_and_centroid,
)


def test_volume_and_centroid_of_unit_cube():
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=float)
    v, f = convex_mesh(corners)
    vol, c = volume_and_centroid(v, f)
    assert vol == pytest.approx(1.0)
    np.testing.assert_allclose(c, [0.5, 0.5, 0.5], atol=1e-12)


@pytest.mark.parametrize("family", ["crushed_rock", "granule", "ellipsoid"])
def test_size_is_the_b_axis_and_volume_is_exact(family):
    rng = np.random.default_rng(1)
    sizes = np.array([2.0, 7.5, 15.0])
    parts = make_particles(family, sizes, rng, ShapeParams.for_family(family))
    for p, s in zip(parts, sizes, strict=True):
        dims = p.dims_mm  # the minimum-volume box (tests/test_sizes.py checks it)
        assert dims[1] == pytest.approx(s, rel=1e-9) and p.size_mm == s
        assert 0 < p.sieve_mm <= s * (1 + 1e-9)
        assert dims[0] >= dims[1] >= dims[2] > 0
        vol, centroid = volume_and_centroid(p.vertices, p.faces)
        assert vol == pytest.approx(p.volume_mm3) and vol > 0
        np.testing.assert_allclose(centroid, 0, atol=1e-9 * s)
        # a convex body lies inside its bounding box and fills a good part of it
        assert 0.3 * dims.prod() < vol < dims.prod()


def test_ellipsoid_volume_close_to_analytic():
    p = make_particles("ellipsoid", np.array([10.0]), np.random.default_rng(2), ShapeParams.for_family("ellipsoid"))[0]
    a, b, c = p.dims_mm / 2
    assert p.volume_mm3 == pytest.approx(4 / 3 * np.pi * a * b * c, rel=0.08)  # 92-point hull is a little smaller


def test_crushed_rocks_are_unique():
    parts = make_particles("crushed_rock", np.full(5, 8.0), np.random.default_rng(3),
                           ShapeParams.for_family("crushed_rock"))
    vols = [p.volume_mm3 for p in parts]
    assert len(set(np.round(vols, 6))) == 5


def test_user_mesh_family(tmp_path):
    trimesh = pytest.importorskip("trimesh")
    box = trimesh.creation.box(extents=[3.0, 2.0, 1.0])
    path = tmp_path / "rock.stl"
    box.export(path)
    params = ShapeParams.for_family("mesh", {"mesh_files": [str(path)]})
    p = make_particles("mesh", np.array([4.0]), np.random.default_rng(0), params)[0]
    np.testing.assert_allclose(p.dims_mm, [6.0, 4.0, 2.0], rtol=1e-9)
    assert p.volume_mm3 == pytest.approx(48.0)


def test_user_mesh_errors(tmp_path):
    bad = tmp_path / "bad.obj"
    bad.write_text("this is not a mesh\n")
    for files, msg in [([str(tmp_path / "nope.obj")], "not found"), ([str(bad)], "bad.obj")]:
        params = ShapeParams.for_family("mesh", {"mesh_files": files})
        with pytest.raises(PsdError, match=msg):
            make_particles("mesh", np.array([4.0]), np.random.default_rng(0), params)


def bad_meshes(folder: Path) -> dict[str, tuple[Path, str]]:
    """Mesh files that are no particle — {name: (file, what the refusal says)} — and a good box."""
    import trimesh

    box = trimesh.creation.box(extents=[3.0, 2.0, 1.0])
    tri = [[0, 0, 0], [1, 0, 0], [0, 1, 0]]
    found = {}
    for name, mesh, says in [
        ("triangle.stl", trimesh.Trimesh(tri, [[0, 1, 2]]), "not a closed solid (3 edges"),
        ("open_box.obj", trimesh.Trimesh(box.vertices, box.faces[:-2]), "not a closed solid (4 edges"),
        ("inside_out.obj", trimesh.Trimesh(box.vertices, box.faces[:, ::-1]), "inside out"),
        ("flat.obj", trimesh.Trimesh(tri, [[0, 1, 2], [0, 2, 1]], process=False), "has no volume"),
        ("box.stl", box, ""),
    ]:
        mesh.export(folder / name)
        found[name] = (folder / name, says)
    return found


def test_a_user_mesh_that_is_not_a_closed_solid_is_refused_naming_the_file(tmp_path):
    pytest.importorskip("trimesh")
    for name, (path, says) in bad_meshes(tmp_path).items():
        params = ShapeParams.for_family("mesh", {"mesh_files": [str(path)]})
        if not says:
            assert make_particles("mesh", np.array([4.0]), np.random.default_rng(0), params)[0].volume_mm3 > 0
            continue
        with pytest.raises(PsdError) as e:
            make_particles("mesh", np.array([4.0]), np.random.default_rng(0), params)
        assert str(e.value).startswith(f"particle mesh {path} ") and says in str(e.value), (name, str(e.value))


def test_pack_roundtrip():
    parts = make_particles("granule", np.array([3.0, 4.0]), np.random.default_rng(0), ShapeParams.for_family("granule"))
    g = Geometry.from_arrays(pack(parts))
    assert len(g) == 2
    v, f = g.mesh(1)
    np.testing.assert_allclose(v, parts[1].vertices, atol=1e-5)
    np.testing.assert_array_equal(f, parts[1].faces)


def test_unknown_family():
    with pytest.raises(PsdError, match="unknown particle shape"):
        ShapeParams.for_family("cube")


def _one_hull(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The hull of one point set, particle by particle (as convex_mesh was before it was batched)."""
    from scipy.spatial import ConvexHull

    hull = ConvexHull(points)
    remap = np.full(len(points), -1, dtype=np.int64)
    remap[hull.vertices] = np.arange(len(hull.vertices))
    verts, faces = points[hull.vertices], remap[hull.simplices]
    a, b, c = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    flip = np.einsum("ij,ij->i", np.cross(b - a, c - a), (a + b + c) / 3 - verts.mean(axis=0)) < 0
    faces[flip] = faces[flip][:, ::-1]
    return verts, faces.astype(np.int32)


def test_batched_hulls_and_finishing_equal_one_particle_at_a_time():
    from psdfactory.scene.shapes import convex_meshes, crushed_rock_points, finish_all

    rng = np.random.default_rng(11)
    p = ShapeParams.for_family("crushed_rock")
    points = [crushed_rock_points(rng, p) for _ in range(40)]
    meshes = convex_meshes(points)
    for pts, (v, f) in zip(points, meshes, strict=True):
        rv, rf = _one_hull(pts)
        np.testing.assert_array_equal(v, rv)
        np.testing.assert_array_equal(f, rf)
    sizes = rng.uniform(1, 20, size=len(meshes))
    dims = np.sort(rng.uniform(0.5, 2.0, size=(len(meshes), 3)), axis=1)[:, ::-1]
    sieve = rng.uniform(0.5, 1.0, size=len(meshes))
    for (v, f), s, d, q, part in zip(meshes, sizes, dims, sieve, finish_all(meshes, sizes, dims, sieve), strict=True):
        scale = s / d[1]
        vol, centroid = volume_and_centroid(v * scale, f)  # bit for bit the same numbers
        assert part.volume_mm3 == vol and part.sieve_mm == float(q * scale)
        np.testing.assert_array_equal(part.vertices, v * scale - centroid)
        np.testing.assert_array_equal(part.dims_mm, d * scale)
