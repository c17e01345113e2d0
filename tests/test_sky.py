"""The sky-view factor of a height map and the tiny backend's sky occlusion (`render.occlusion: sky`)."""

from types import SimpleNamespace

import numpy as np
import pytest

from psdfactory import PsdError
from psdfactory import config as psd_config
from psdfactory.scene.render.look import RenderParams
from psdfactory.scene.render.sky import horizon_radius_mm, sky_view
from psdfactory.scene.render.tiny import shade_tiny

from .conftest import tiny_config


def test_an_open_plane_sees_the_whole_sky():
    view = sky_view(np.full((20, 30), 4.0), px_mm=0.5, radius_mm=5.0)
    assert view.shape == (20, 30) and view.dtype == np.float32
    np.testing.assert_allclose(view, 1.0)


def test_the_bottom_of_a_deep_narrow_gap_sees_little_sky():
    # a 10 mm high surface with a 5 mm wide, 10 mm deep square pit at 1 mm/px
    h = np.full((41, 41), 10.0)
    h[18:23, 18:23] = 0.0
    view = sky_view(h, px_mm=1.0, radius_mm=10.0)
    # at the centre the horizon rises atan(10 / 2.5) ≈ 76° towards each side (farther on the diagonals)
    assert view[20, 20] < 0.1
    assert view[5, 5] == pytest.approx(1.0)  # the plane around it: nothing above it
    # half a sky: beside a tall wall the horizon is ~90° on one side, 0° on the other
    wall = np.zeros((41, 41))
    wall[:, 21:] = 100.0
    v = sky_view(wall, px_mm=1.0, radius_mm=10.0)
    assert 0.35 < v[20, 20] < 0.65
    assert v[20, 0] > v[20, 15] > v[20, 20]  # farther from the wall, more sky
    # a trench as deep as it is wide: ~0.3 at its floor
    trench = np.full((41, 41), 6.0)
    trench[:, 17:24] = 0.0
    assert 0.2 < sky_view(trench, 1.0, 20.0)[20, 20] < 0.4


def test_the_horizon_is_searched_no_farther_than_the_radius():
    h = np.zeros((1, 60))
    h[0, 40:] = 20.0  # a step 20 px away from column 20
    assert sky_view(h, 1.0, radius_mm=10.0)[0, 20] == pytest.approx(1.0)
    assert sky_view(h, 1.0, radius_mm=30.0)[0, 20] < 1.0


def test_sky_view_refuses_what_it_cannot_read():
    with pytest.raises(PsdError, match="2-D"):
        sky_view(np.zeros(5), 1.0, 1.0)
    with pytest.raises(PsdError, match="positive"):
        sky_view(np.zeros((3, 3)), 0.0, 1.0)


def test_the_horizon_radius_is_the_median_b_axis():
    assert horizon_radius_mm(np.array([[9.0, 4.0, 2.0], [12.0, 8.0, 3.0], [6.0, 5.0, 4.0]])) == 5.0
    with pytest.raises(PsdError, match="without particles"):
        horizon_radius_mm(np.zeros((0, 3)))


def _shade(occlusion: str, height: np.ndarray) -> np.ndarray:
    """shade_tiny on a flat grey image (no texture, no cast shadow) over `height`, supersample 1."""
    look = SimpleNamespace(table_texture=0.0, surface_detail=[0.0], table_grain_mm=1.0, particle_grain_mm=1.0,
                           light_dir=[0.0, 0.0, 1.0], shadow_strength=0.0, occlusion_strength=0.8)
    p = SimpleNamespace(supersample=1, occlusion=occlusion)
    rgb = np.full(height.shape + (3,), 0.5, dtype=np.float32)
    ids = np.ones(height.shape, dtype=np.int32)
    return shade_tiny(rgb, ids, height.astype(np.float32), look, p, 1.0, np.random.default_rng(0), 20.0)[..., 0]


def test_sky_occlusion_darkens_each_pixel_by_the_sky_it_does_not_see():
    h = np.full((61, 61), 12.0)
    h[:, 28:33] = 0.0  # a 5 mm wide, 12 mm deep gap between two pebbles' tops
    h[:, 45:] = 30.0  # and a tall neighbour: its shadowless foot sees half a sky, far beyond the crevice blur
    sky, crevice = _shade("sky", h), _shade("crevice", h)
    np.testing.assert_allclose(sky, 0.5 * (1 - 0.8 * (1 - sky_view(h, 1.0, 20.0))), atol=1e-5)
    np.testing.assert_allclose(sky[30, 5], 0.5, atol=1e-5)  # the open top: as lit either way
    assert sky[30, 30] < 0.5 * 0.5  # the gap's floor sees little sky: darker than half its colour
    assert sky[30, 40] < crevice[30, 40] - 0.05  # 5 px from the wall: the tall neighbour hides half the sky


def test_render_occlusion_is_in_a_slice_only_where_the_tiny_backend_renders_it_and_it_is_not_the_default():
    cfg = tiny_config()
    assert "occlusion" not in psd_config.render_params(cfg)  # the default renders' params are as before
    assert "occlusion" not in psd_config.compare_params(cfg)  # and the backend comparison's
    cfg["render"]["occlusion"] = "sky"
    params = psd_config.render_params(cfg)
    assert params["occlusion"] == "sky" and RenderParams.from_dict(params).occlusion == "sky"
    assert psd_config.compare_params(cfg)["occlusion"] == "sky"
    cfg["render"]["backend"] = "cycles"  # Cycles traces the light: the setting is not in its slice
    assert "occlusion" not in psd_config.render_params(cfg)
    with pytest.raises(PsdError, match="render.occlusion must be one of crevice, sky"):
        RenderParams.from_dict({**params, "occlusion": "ambient"})
    with pytest.raises(PsdError, match="occlusion"):
        psd_config.validate({**tiny_config(), "render": {"occlusion": "ambient"}})


def test_a_scene_rendered_with_sky_occlusion_is_darker_on_its_particles_and_keeps_its_mask(tmp_path):
    from psdfactory.io import read_png
    from psdfactory.scene.stages import run_render

    from .conftest import split_dataset

    (scene,) = split_dataset(tmp_path, ["train"], resolution=48)
    cfg = tiny_config(count=[15, 25])
    cfg["render"].update(resolution=48, occlusion_strength=[0.8, 0.8], jpeg_fraction=0.0)
    images = {}
    for occlusion in ("crevice", "sky"):
        cfg["render"]["occlusion"] = occlusion
        run_render(psd_config.render_params(cfg), scene)
        images[occlusion] = read_png(scene / "image.png").astype(float).mean(axis=2)
        mask = read_png(scene / "mask.png")
        images[occlusion + "_mask"] = mask
    np.testing.assert_array_equal(images["crevice_mask"], images["sky_mask"])  # the look changes, not the scene
    on = images["sky_mask"] > 0
    assert not np.array_equal(images["sky"], images["crevice"])
    assert images["sky"][on].mean() < images["crevice"][on].mean()  # a bed's particles see less than the whole sky
