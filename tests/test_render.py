import numpy as np
import pytest

from psdfactory import PsdError
from psdfactory.io import read_json, read_png
from psdfactory.scene.render.look import RenderParams
from psdfactory.scene.render.tiny import downsample, shade_from_height
from psdfactory.scene.stages import load_poses


@pytest.mark.slow
def test_image_and_mask_files(tiny_results):
    cfg, root = tiny_results
    d = root / "tiny" / "scenes" / "tiny-000000"
    img, mask = read_png(d / "image.png"), read_png(d / "mask.png")
    assert img.shape == (64, 64, 3) and img.dtype == np.uint8
    assert mask.shape == (64, 64) and mask.dtype == np.uint16
    meta = read_json(d / "render.json")
    assert meta["mm_per_px"] == pytest.approx(60 / 64)
    # the rendered image is not flat: particles differ from the table
    assert img[mask > 0].mean() != pytest.approx(img[mask == 0].mean(), abs=3)


@pytest.mark.slow
def test_mask_ids_are_particle_ids_at_their_positions(tiny_results):
    _, root = tiny_results
    d = root / "tiny" / "scenes" / "tiny-000001"
    spec = read_json(d / "spec.json")
    mask = read_png(d / "mask.png").astype(int)
    pos, _, _ = load_poses(d)
    n = spec["samplesize"]
    assert mask.max() <= n and mask.min() == 0
    px = read_json(d / "render.json")["mm_per_px"]
    rows, cols = np.indices(mask.shape)
    checked = 0
    for pid in range(n):
        sel = mask == pid + 1
        if sel.sum() < 12:
            continue
        x = (cols[sel].mean() + 0.5) * px - 30
        y = 30 - (rows[sel].mean() + 0.5) * px
        size = spec["particles"][pid]["size"]
        # the visible part of particle k lies around particle k's settled centre
        assert np.hypot(x - pos[pid, 0], y - pos[pid, 1]) < size + 2 * px, f"mask id {pid + 1} is not particle {pid}"
        checked += 1
    assert checked >= 5


@pytest.mark.slow
def test_render_is_deterministic(tiny_results, tmp_path):
    import shutil

    from psdfactory import config as psd_config
    from psdfactory.scene.stages import run_render

    cfg, root = tiny_results
    src = root / "tiny" / "scenes" / "tiny-000002"
    dst = tmp_path / "copy"
    shutil.copytree(src, dst)
    run_render(psd_config.render_params(cfg), dst)
    np.testing.assert_array_equal(read_png(src / "image.png"), read_png(dst / "image.png"))
    np.testing.assert_array_equal(read_png(src / "mask.png"), read_png(dst / "mask.png"))


def test_downsample_is_box_filter():
    a = np.arange(16, dtype=float).reshape(4, 4)
    np.testing.assert_allclose(downsample(a, 2), [[2.5, 4.5], [10.5, 12.5]])


def test_shadow_falls_away_from_light():
    h = np.zeros((21, 21))
    h[10, 10] = 10.0  # a 10 mm post in the middle
    light_from_plus_x = [np.cos(np.radians(45)), 0.0, np.sin(np.radians(45))]
    s = shade_from_height(h, 1.0, light_from_plus_x, 10.0)
    assert s[10, 5] == 1 and s[10, 15] == 0  # shadow on the -x side only
    assert s[5, 10] == 0


def test_unknown_or_missing_render_setting():
    with pytest.raises(PsdError, match="unknown render setting: resolutoin"):
        RenderParams.from_dict({"resolutoin": 64})
    with pytest.raises(PsdError, match="render lacks .*resolution"):  # no second set of defaults
        RenderParams.from_dict({"backend": "tiny"})


@pytest.mark.parametrize("rasteriser", ["numba", "pybullet"])
def test_every_particle_keeps_its_own_id_past_pybullets_127_links_a_body(rasteriser):
    """The TinyRenderer gets the particles as the links of a few multibodies (one call per 127
    particles): each pixel's id must still be its own particle's, for scenes of ~1,000 particles as
    for small ones. 20 × 20 cubes of 4 mm on a grid, each seen from above where it lies."""
    from psdfactory import config as psd_config
    from psdfactory.scene.geometry import Geometry
    from psdfactory.scene.render.look import draw_look
    from psdfactory.scene.render.tiny import LINKS_PER_BODY, tiny_raw

    side, pitch, table = 20, 6.0, 130.0
    n = side * side
    assert n > 3 * LINKS_PER_BODY
    from psdfactory.scene.shapes import convex_mesh

    corners, faces = convex_mesh(np.array([[x, y, z] for x in (-2, 2) for y in (-2, 2) for z in (-2, 2)], float))
    corners, faces = corners.astype(np.float32), faces.astype(np.int32)
    nv, nf = len(corners), len(faces)
    geo = Geometry(np.tile(corners, (n, 1)), np.tile(faces, (n, 1)), np.arange(n + 1) * nv, np.arange(n + 1) * nf,
                   np.full(n, 4.0), np.full(n, 64.0), np.full((n, 3), 4.0), np.full(n, 4.0))
    centres = (np.arange(side) - (side - 1) / 2) * pitch
    xy = np.array([[x, y] for x in centres for y in centres])
    pos = np.column_stack([xy, np.full(n, 2.0)])
    quats = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
    cfg = psd_config.validate({"datasets": {"train": {"n_scenes": 1, "table_size": table, "count": [1, 2]}},
                               "render": {"resolution": 260, "supersample": 1}})
    p = RenderParams.from_dict(psd_config.render_params(cfg))
    look = draw_look(np.random.default_rng(0), p, n, np.random.default_rng(1))
    _, ids, _ = tiny_raw({"table_size": table, "shape_type": "crushed_rock"}, geo, pos, quats, p, look, rasteriser)
    px = table / 260  # mm per pixel; rows grow towards -y, columns towards +x
    for k in range(n):
        r, c = np.nonzero(ids == k + 1)
        assert len(r) > 20, f"particle {k} not seen"
        x, y = (c.mean() + 0.5) * px - table / 2, table / 2 - (r.mean() + 0.5) * px  # its centre, mm
        assert abs(x - xy[k, 0]) < pitch / 3 and abs(y - xy[k, 1]) < pitch / 3, f"particle {k}'s pixels lie elsewhere"
    assert ids.max() == n


@pytest.mark.parametrize("shape_type", ["crushed_rock", "granule"])  # flat facets; smooth vertex normals
def test_the_compiled_rasteriser_draws_what_tinyrenderer_draws(tiny_results, shape_type):
    """raster.py draws TinyRenderer's triangles by its rules: on a scene of the tiny dataset, under
    four looks (light from anywhere, dim to saturating, tinted), the same particle at every pixel,
    the same heights, and TinyRenderer's colour bytes (bar a rare pixel on a float32 rounding step)."""
    from psdfactory import config as psd_config
    from psdfactory.io import read_json
    from psdfactory.scene.render.look import draw_look
    from psdfactory.scene.render.tiny import tiny_raw
    from psdfactory.scene.stages import load_geometry

    cfg, root = tiny_results
    d = root / "tiny" / "scenes" / "tiny-000001"
    spec = {**read_json(d / "spec.json"), "shape_type": shape_type}
    geo = load_geometry(d)
    pos, quats, _ = load_poses(d)
    c = psd_config.validate({**cfg, "render": {**cfg["render"], "light_intensity": [0.6, 1.4], "light_tint": [-1, 1]}})
    p = RenderParams.from_dict(psd_config.render_params(c))
    for seed in range(4):
        look = draw_look(np.random.default_rng(seed), p, len(geo), np.random.default_rng(seed + 10))
        a_rgb, a_ids, a_h = tiny_raw(spec, geo, pos, quats, p, look, "numba")
        b_rgb, b_ids, b_h = tiny_raw(spec, geo, pos, quats, p, look, "pybullet")
        assert a_rgb.shape == b_rgb.shape and a_rgb.dtype == b_rgb.dtype == np.float32
        np.testing.assert_array_equal(a_ids, b_ids)
        np.testing.assert_allclose(a_h, b_h, atol=0.01)  # mm
        same = (np.abs(a_rgb - b_rgb) * 255 < 0.5).all(axis=-1)
        assert same.mean() > 0.999, (seed, same.mean())


def test_the_rasteriser_is_chosen_by_the_environment(monkeypatch):
    from psdfactory.scene.render import raster

    monkeypatch.delenv(raster.ENV, raising=False)
    assert raster.rasteriser() == "numba"
    monkeypatch.setenv(raster.ENV, "pybullet")
    assert raster.rasteriser() == "pybullet"
    monkeypatch.setenv(raster.ENV, "opengl")
    with pytest.raises(PsdError, match="PSDFACTORY_RASTERISER='opengl' is no rasteriser"):
        raster.rasteriser()


def test_a_smooth_texture_octave_made_on_the_downsampling_blocks_survives_it_unchanged():
    """fractal_noise(block=2) makes its octaves of sigma >= COARSE_OCTAVE_SIGMA_PX on 2 x 2 blocks:
    what the image's 2 x 2 downsampling keeps of the texture is the same field, bar a box blur far
    below the octave's sigma (its block means correlate > 0.99 with the full-resolution texture's,
    with the same spread and the same grain size); the finer octave is made as before."""
    from psdfactory.scene.render.tiny import COARSE_OCTAVE_SIGMA_PX, fractal_noise, white_layers

    layers = white_layers(np.random.default_rng(0), (512, 512))
    for sigmas in [(0.8, 3.3), (2.0, 8.2)]:
        assert max(sigmas) >= COARSE_OCTAVE_SIGMA_PX
        full, coarse = fractal_noise(layers, sigmas), fractal_noise(layers, sigmas, block=2)
        assert coarse.shape == full.shape and coarse.dtype == np.float32
        a, b = downsample(full, 2), downsample(coarse, 2)
        assert np.corrcoef(a.ravel(), b.ravel())[0, 1] > 0.99
        assert abs(b.std() / a.std() - 1) < 0.02
        lag = [np.corrcoef(x[:, :-3].ravel(), x[:, 3:].ravel())[0, 1] for x in (a, b)]
        assert abs(lag[0] - lag[1]) < 0.02
    fine = fractal_noise(layers, (0.8, 1.2), block=2)  # no octave smooth enough: as without blocks
    np.testing.assert_array_equal(fine, fractal_noise(layers, (0.8, 1.2)))


def test_without_numba_the_tiny_backend_falls_back_to_tinyrenderer(monkeypatch, caplog):
    import builtins

    from psdfactory.scene.render import raster

    real_import = builtins.__import__

    def no_numba(name, *a, **k):
        if name == "numba":
            raise ImportError("No module named 'numba'")
        return real_import(name, *a, **k)

    monkeypatch.delenv(raster.ENV, raising=False)
    monkeypatch.setattr(raster, "_kernel", None)
    monkeypatch.setattr(builtins, "__import__", no_numba)
    with caplog.at_level("WARNING", logger="psdfactory.scene.render.raster"):
        assert raster.rasteriser() == "pybullet"
    assert any("numba is not installed" in r.message for r in caplog.records)
