"""The randomised look: the render settings drawn per scene within their ranges, deterministic
per seed, recorded in render.json, and the same for both backends; and the river-gravel config."""

from __future__ import annotations

import copy
import shutil
from dataclasses import asdict

import numpy as np
import pytest
import yaml

from psdfactory import config as psd_config
from psdfactory.config import load_config
from psdfactory.io import read_json, read_png
from psdfactory.scene.render.cycles import CyclesParams, cycles_job, draw_cycles_look
from psdfactory.scene.render.look import LUMA, RenderParams, apply_sensor, draw_look, jpeg, mm_per_px, tint_rgb
from psdfactory.scene.stages import run_render
from psdfactory.seeding import rng_for

from .conftest import REPO, make_scene
from .test_cycles import cycles_config, needs_blender

WIDE = {
    "view_fraction": [0.7, 0.9],
    "table_palette": [[0.9, 0.9, 0.88], [0.5, 0.4, 0.3]],
    "table_hue_jitter": 0.1,
    "table_brightness": [0.9, 1.0],
    "table_texture": [0.1, 0.3],
    "table_grain_mm": [0.5, 2.0],
    "ground_level_mm": [1.0, 3.0],
    "surface_detail": [0.02, 0.2],
    "particle_grain_mm": [0.3, 1.2],
    "light_tint": [-0.5, 0.8],
    "jpeg_fraction": 1.0,
    "jpeg_quality": [50, 70],
}


def render_settings(**over) -> RenderParams:
    cfg = psd_config.validate({"datasets": {"a": {"n_scenes": 1}}, "train": {"datasets": ["a"]},
                               "render": {"resolution": 64, **copy.deepcopy(over)}})
    return RenderParams.from_dict(psd_config.render_params(cfg))


def looks(p: RenderParams, n: int = 50, scenes: int = 20):
    for i in range(scenes):
        entropy = [1, 2, i]
        yield draw_look(rng_for(entropy, "render"), p, n, rng_for(entropy, "look"))


def test_new_settings_are_drawn_within_their_ranges():
    p = render_settings(**WIDE)
    tables, views = set(), []
    for lk in looks(p):
        assert 0.7 <= lk.view_fraction <= 0.9
        views.append(lk.view_fraction)
        assert 0.1 <= lk.table_texture <= 0.3 and 0.5 <= lk.table_grain_mm <= 2.0
        assert 1.0 <= lk.ground_level_mm <= 3.0 and 0.3 <= lk.particle_grain_mm <= 1.2
        assert -0.5 <= lk.light_tint <= 0.8 and lk.light_rgb == pytest.approx(tint_rgb(lk.light_tint))
        assert 50 <= lk.jpeg_quality <= 70
        assert len(lk.surface_detail) == 50 and all(0.02 <= d <= 0.2 for d in lk.surface_detail)
        # a palette colour × brightness × hue jitter
        t = np.asarray(lk.table_rgb)
        ratio = [t / np.asarray(c) for c in p.table_palette]
        assert any(np.all((r >= 0.9 * 0.9 - 1e-9) & (r <= 1.0 * 1.1 + 1e-9)) for r in ratio)
        tables.add(int(t[0] > 0.7))
    assert tables == {0, 1}  # both table colours occur
    assert np.ptp(views) > 0.05


def test_defaults_keep_todays_fixed_look():
    p = render_settings()
    for lk in looks(p, scenes=5):
        assert lk.view_fraction == 1.0 and lk.ground_level_mm == 0.0 and lk.jpeg_quality is None
        assert lk.light_rgb == pytest.approx([1, 1, 1]) and set(lk.surface_detail) == {0.04}
        assert lk.table_texture == 0.06 and lk.table_grain_mm == 1.5 and lk.particle_grain_mm == 0.6
        brightness = np.asarray(lk.table_rgb) / np.asarray(p.table_rgb)  # table_rgb × brightness only
        assert np.ptp(brightness) < 1e-9 and 0.8 <= brightness[0] <= 1.2


def test_the_look_is_deterministic_and_the_render_streams_draws_stay_as_they_were():
    wide, plain = render_settings(**WIDE), render_settings()
    for a, b, c in zip(looks(wide), looks(wide), looks(plain), strict=True):
        da, db, dc = asdict(a), asdict(b), asdict(c)
        np.testing.assert_array_equal(da.pop("particle_rgb"), db.pop("particle_rgb"))
        assert da == db  # same seed, same look
        # the new settings come from their own stream: the first ones' draws do not move
        np.testing.assert_array_equal(a.particle_rgb, c.particle_rgb)
        for k in ("light_dir", "light_intensity", "ambient", "shadow_strength", "occlusion_strength",
                  "exposure", "white_balance", "vignetting", "blur_px", "noise_sigma", "shot_noise"):
            assert da[k] == dc[k], k


def test_tint_changes_the_colour_not_the_brightness():
    for t in (-1, -0.3, 0, 0.5, 1):
        assert float(LUMA @ np.asarray(tint_rgb(t))) == pytest.approx(1.0)
    warm, cool = tint_rgb(1.0), tint_rgb(-1.0)
    assert warm[0] > warm[2] and cool[2] > cool[0]
    assert tint_rgb(0.0) == pytest.approx([1, 1, 1])


def test_scale_follows_the_view():
    assert mm_per_px(150, 256, 0.8) == pytest.approx(150 * 0.8 / 256)
    assert mm_per_px(150, 256) == pytest.approx(150 / 256)


def test_jpeg_is_applied_in_the_sensor_at_the_drawn_quality():
    p = render_settings(**WIDE)
    lk = next(looks(p, n=1, scenes=1))
    img = np.random.default_rng(0).uniform(0.2, 0.8, (64, 64, 3)).astype(np.float32)
    out = apply_sensor(img, lk, p, np.random.default_rng(1))
    lk.jpeg_quality = None
    raw = apply_sensor(img, lk, p, np.random.default_rng(1))
    assert out.dtype == np.uint8 and not np.array_equal(out, raw)
    np.testing.assert_array_equal(out, jpeg(raw, next(looks(p, n=1, scenes=1)).jpeg_quality))


def test_cycles_gets_the_shared_look():
    p = render_settings(**WIDE, backend="cycles")
    lk = next(looks(p, n=3, scenes=1))
    extra = draw_cycles_look(np.random.default_rng(0), CyclesParams.from_dict(asdict(p.cycles)), 3)
    geometry = type("G", (), {"dims_mm": np.full((3, 3), 5.0), "__len__": lambda self: 3})()
    spec = {"table_size": 60.0, "shape_type": "granule"}
    job = cycles_job(spec, geometry, np.zeros((3, 3)), p, lk, extra)
    assert job["table_rgb"] == lk.table_rgb and job["table_texture"] == lk.table_texture
    assert job["grain_mm"] == lk.table_grain_mm and job["bump_mm"] == lk.particle_grain_mm
    assert job["ground_mm"] == lk.ground_level_mm and job["light_rgb"] == lk.light_rgb
    half_view = 30.0 * lk.view_fraction
    assert np.tan(np.radians(job["fov_deg"] / 2)) * p.camera_height_mm == pytest.approx(half_view)


@pytest.fixture(scope="module")
def wide_render(tiny_results, tmp_path_factory):
    """A tiny scene rendered by the fast backend with every new setting on."""
    cfg, root = tiny_results
    cfg = copy.deepcopy(cfg)
    cfg["render"].update(copy.deepcopy(WIDE))
    cfg = psd_config.validate(cfg)
    dst = tmp_path_factory.mktemp("wide") / "tiny-000001"
    shutil.copytree(root / "tiny" / "scenes" / "tiny-000001", dst)
    run_render(psd_config.render_params(cfg), dst)
    return cfg, root / "tiny" / "scenes" / "tiny-000001", dst


@pytest.mark.slow
def test_fast_backend_records_the_look_and_crops_to_the_view(wide_render):
    cfg, full, cropped = wide_render
    meta = read_json(cropped / "render.json")
    look = meta["look"]
    for k in ("view_fraction", "table_texture", "table_grain_mm", "ground_level_mm", "particle_grain_mm",
              "light_tint", "light_rgb", "jpeg_quality", "surface_detail"):
        assert k in look, k
    assert meta["mm_per_px"] == pytest.approx(60 * look["view_fraction"] / 64)
    assert meta["view_mm"] == pytest.approx(60 * look["view_fraction"])
    # the same particles, seen magnified: the centre of the crop is the centre of the full view
    a, b = read_png(full / "mask.png").astype(int), read_png(cropped / "mask.png").astype(int)
    v = look["view_fraction"]
    rows = np.clip(((np.arange(64) + 0.5 - 32) * v + 32).astype(int), 0, 63)
    resampled = a[np.ix_(rows, rows)]
    visible = (b > 0) & (resampled > 0)
    assert (resampled == b)[visible].mean() > 0.8
    np.testing.assert_array_equal(read_png(cropped / "image.png").shape, (64, 64, 3))


@pytest.mark.slow
@needs_blender
def test_cycles_renders_the_same_look_and_view(wide_render, tmp_path):
    cfg, _, tiny = wide_render
    dst = tmp_path / tiny.name
    shutil.copytree(tiny, dst)
    run_render(psd_config.render_params(cycles_config(cfg)), dst)
    mt, mc = read_json(tiny / "render.json"), read_json(dst / "render.json")
    assert mc["backend"] == "cycles" and mc["mm_per_px"] == mt["mm_per_px"]
    assert mc["look"] == mt["look"]  # the one look, drawn before the backend
    a, b = read_png(tiny / "mask.png").astype(int), read_png(dst / "mask.png").astype(int)
    assert (a == b).mean() > 0.9  # the same camera: view and ground level


def test_gravel_config_is_valid():
    cfg = load_config(REPO / "config" / "gravel.yaml")
    r = cfg["render"]
    ds = cfg["datasets"]["gravel"]
    assert ds["shape"] == "granule"
    assert ds["table_size"] * np.mean(r["view_fraction"]) / r["resolution"] == pytest.approx(0.4)
    assert cfg["datasets"]["gravel_cycles"]["render"]["backend"] == "cycles"
    sparse = cfg["datasets"]["gravel_sparse"]  # the same pebbles, fewer: the sand shows between them
    assert sparse["shape"] == ds["shape"] and sparse["size"] == ds["size"] and max(sparse["count"]) < min(ds["count"])
    both = cfg["datasets"]["gravel_cycles_train"]  # the beds' train/val scenes by Cycles: the finder learns both
    assert both["rerender_of"] == {"dataset": "gravel", "split": ["train", "val"]}
    assert both["render"]["backend"] == "cycles"
    assert cfg["train"]["instances"]["datasets"] == ["gravel", "gravel_sparse", "gravel_cycles_train"]
    assert psd_config.train_params(cfg, "instances")["settings"]["auto_scale"] is True


@pytest.mark.slow
def test_a_gravel_scene_fills_the_field(tmp_path):
    cfg = yaml.safe_load((REPO / "config" / "gravel.yaml").read_text())
    cfg["render"]["resolution"] = 96  # the same view at a quarter of the pixels
    d = make_scene(psd_config.validate(cfg), tmp_path / "gravel-000000", dataset="gravel", index=0)
    image, mask = read_png(d / "image.png"), read_png(d / "mask.png")
    assert image.shape == (96, 96, 3) and mask.shape == (96, 96)
    assert (mask > 0).mean() >= 0.9  # the bed covers the field: no table edge, sand only between pebbles
    assert read_json(d / "render.json")["mm_per_px"] == pytest.approx(0.4 * 4, rel=0.03)
