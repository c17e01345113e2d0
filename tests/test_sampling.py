import numpy as np
import pytest
from scipy import stats

from psdfactory import PsdError
from psdfactory import config as psd_config
from psdfactory.scene.sampling import SampleParams, drop_positions, sample_scene, truncnormal_sizes

from .conftest import tiny_config


@pytest.mark.parametrize("mean,sigma,lo,hi", [(9.0, 7.0, 0.1, 20.0), (6.0, 8.0, 0.1, 20.0), (3.0, 1.0, 2.5, 4.0),
                                               (2.0, 3.0, 5.0, 15.0), (9.0, 0.5, 0.1, 8.0)])
def test_truncnormal_matches_scipy(mean, sigma, lo, hi):
    rng = np.random.default_rng(0)
    x = truncnormal_sizes(rng, 20000, mean, sigma, lo, hi)
    assert x.min() >= lo and x.max() <= hi
    ref = stats.truncnorm((lo - mean) / sigma, (hi - mean) / sigma, loc=mean, scale=sigma)
    assert stats.kstest(x, ref.cdf).pvalue > 1e-3
    assert abs(x.mean() - ref.mean()) < 4 * ref.std() / np.sqrt(len(x))
    # and not some other distribution: an untruncated normal must be rejected
    assert stats.kstest(x, stats.norm(mean, sigma).cdf).pvalue < 1e-6


def test_truncnormal_rejects_bad_bounds():
    with pytest.raises(PsdError, match="a < b"):
        truncnormal_sizes(np.random.default_rng(0), 10, 5, 1, 8, 2)
    with pytest.raises(PsdError, match="too far in the tail"):
        truncnormal_sizes(np.random.default_rng(0), 10, 0.0, 0.1, 50.0, 60.0)


def _params(cfg, index=0):
    return SampleParams.from_dict(psd_config.sample_params(cfg, "tiny", index))


def test_spec_has_paper_keys_and_respects_ranges():
    cfg = tiny_config()
    spec, geo = sample_scene(_params(cfg))
    for key in ("shape_type", "size_mean", "size_sigma", "table_size", "samplesize", "particles"):
        assert key in spec
    assert 30 <= spec["samplesize"] <= 40
    assert 5 <= spec["size_mean"] <= 8 and 2 <= spec["size_sigma"] <= 3
    sizes = np.array([p["size"] for p in spec["particles"]])
    assert sizes.min() >= 1 and sizes.max() <= 12
    xy = np.array([[p["x"], p["y"]] for p in spec["particles"]])
    half_long = geo["dims_mm"][:, 0] / 2
    assert (np.abs(xy).max(axis=1) <= 30 - half_long + 1e-3).all()
    np.testing.assert_allclose(geo["size_mm"], sizes, atol=1e-4)


def test_same_seed_same_scene_and_other_index_differs():
    cfg = tiny_config()
    a, ga = sample_scene(_params(cfg, 1))
    b, gb = sample_scene(_params(cfg, 1))
    c, _ = sample_scene(_params(cfg, 2))
    assert a == b
    for k in ga:
        np.testing.assert_array_equal(ga[k], gb[k])
    assert a["particles"] != c["particles"]


def test_adding_scenes_or_datasets_leaves_existing_scenes_alone():
    small = tiny_config(n_scenes=3)
    big = tiny_config(n_scenes=300, shard_size=7)
    big["datasets"]["other"] = dict(big["datasets"]["tiny"])
    assert psd_config.sample_params(small, "tiny", 2) == psd_config.sample_params(big, "tiny", 2)
    assert sample_scene(_params(small, 2))[0] == sample_scene(_params(big, 2))[0]


def test_other_global_seed_changes_scene():
    a = tiny_config()
    b = tiny_config()
    b["seed"] = 8
    assert sample_scene(_params(a))[0]["particles"] != sample_scene(_params(b))[0]["particles"]


def test_drop_positions_spread_out_better_than_uniform():
    rng = np.random.default_rng(3)
    r = np.full(400, 3.0)
    vol = np.full(400, 100.0)

    def crowding(xy):  # mean count of neighbours closer than 2r
        d = np.linalg.norm(xy[:, None] - xy[None], axis=-1)
        return ((d < 6.0).sum() - len(xy)) / len(xy)

    uniform = drop_positions(rng, r, vol, 100.0, candidates=1, cell_mm=2.0)
    spread = drop_positions(rng, r, vol, 100.0, candidates=6, cell_mm=2.0)
    assert crowding(spread) < 0.8 * crowding(uniform)


def test_particle_too_big_for_table():
    with pytest.raises(PsdError, match="does not fit"):
        drop_positions(np.random.default_rng(0), np.array([40.0]), np.array([1.0]), 50.0, 1, 2.0)


# ---- shape_library: a dataset's scenes draw their particles from K shapes made once -----------

def test_shape_library_scenes_draw_scaled_library_shapes_with_their_exact_sizes():
    from psdfactory.scene.sizes import box_and_sieve

    cfg = tiny_config(shape_library=16)
    spec, geo = sample_scene(_params(cfg, 0))
    n = spec["samplesize"]
    v, off = geo["vertices"].astype(float), geo["vert_offsets"]
    meshes = [v[off[i]:off[i + 1]] for i in range(n)]
    # at most 16 shapes: a particle's shape up to its scale is one of a few
    shapes = {(len(m), round(float(np.linalg.norm(m, axis=1).max() / geo["size_mm"][i]), 5))
              for i, m in enumerate(meshes)}
    assert len(shapes) <= 16 < n
    # the sizes are each particle's own, as the unique shapes' are: the drawn size is its b-axis
    # and the sieve size and volume are those measured on the particle as stored
    np.testing.assert_allclose(geo["size_mm"], [p["size"] for p in spec["particles"]], atol=1e-4)
    dims, sieve = box_and_sieve(meshes)
    np.testing.assert_allclose(sieve, geo["sieve_mm"], rtol=2e-3)
    np.testing.assert_allclose(np.median(dims[:, 1] / geo["size_mm"]), 1.0, atol=1e-3)
    from psdfactory.scene.shapes import volume_and_centroid
    for i in range(0, n, 7):
        f = geo["faces"][geo["face_offsets"][i]:geo["face_offsets"][i + 1]]
        vol, centre = volume_and_centroid(meshes[i], f)
        assert vol == pytest.approx(geo["volume_mm3"][i], rel=1e-4)
        np.testing.assert_allclose(centre, 0, atol=1e-3)  # centred on its centre of volume


def test_shape_library_is_reproducible_and_the_datasets_own():
    cfg = tiny_config(shape_library=16)
    cfg["datasets"]["other"] = dict(cfg["datasets"]["tiny"])
    a, ga = sample_scene(_params(cfg, 1))
    b, gb = sample_scene(_params(cfg, 1))
    assert a == b and all(np.array_equal(ga[k], gb[k]) for k in ga)
    other = sample_scene(SampleParams.from_dict(psd_config.sample_params(cfg, "other", 1)))[1]
    # another dataset (a test set beside a training set) draws from shapes of its own
    assert not set(np.round(ga["sieve_mm"] / ga["size_mm"], 6)) & set(np.round(other["sieve_mm"] / other["size_mm"], 6))


def test_shape_library_zero_is_the_scene_of_before():
    """The default (0) adds nothing to a scene's params or its hash: scenes made before the
    library existed are still up to date, and the same as before."""
    cfg = tiny_config()
    params = psd_config.sample_params(cfg, "tiny", 0)
    assert "shape_library" not in params
    p = SampleParams.from_dict(params)
    spec, _ = sample_scene(p)
    from psdfactory.scene.sampling import config_hash
    legacy = {k: (list(v) if isinstance(v, tuple) else v) for k, v in p.__dict__.items() if k != "shape_library"}
    assert spec["config_hash"] == config_hash(legacy)
    lib = tiny_config(shape_library=8)
    assert psd_config.sample_params(lib, "tiny", 0)["shape_library"] == 8
    assert sample_scene(SampleParams.from_dict(psd_config.sample_params(lib, "tiny", 0)))[0]["config_hash"] != \
        spec["config_hash"]


def test_shape_library_is_refused_for_user_meshes_and_inherited_by_a_rerender(tmp_path):
    import trimesh

    mesh = tmp_path / "rock.stl"
    trimesh.creation.icosphere(subdivisions=1, radius=3.0).export(mesh)
    with pytest.raises(PsdError, match=r"tiny\.shape_library: shape 'mesh' draws from its mesh files"):
        tiny_config(shape="mesh", shape_params={"mesh_files": [str(mesh)]}, shape_library=4)
    with pytest.raises(PsdError, match="shape_library"):
        tiny_config(shape_library=-1)
    cfg = dict(tiny_config(shape_library=8))
    again = {"rerender_of": {"dataset": "tiny", "split": ["train", "val", "test"]}}
    cfg["datasets"] = {**cfg["datasets"], "again": again}
    cfg = psd_config.validate(cfg)
    assert cfg["datasets"]["again"]["shape_library"] == 8
