"""The sky-view factor of a scene's surface and the lit grains the instance estimator can learn
(`train.instances.gap_sky_view`)."""

import numpy as np
import pytest

from psdfactory import PsdError
from psdfactory.config import train_params
from psdfactory.learn.instances.targets import training_mask
from psdfactory.learn.instances.training import InstanceSettings
from psdfactory.scene.exposure import gap_radius_mm, lit_mask, scene_sky_view, scene_surface, sky_view

from .conftest import split_dataset, tiny_config


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


def test_lit_mask_makes_the_shadowed_pixels_background():
    mask = np.array([[0, 1, 1], [2, 2, 1]], dtype=np.uint16)
    view = np.array([[0.1, 0.9, 0.3], [0.5, 0.49, 1.0]], dtype=np.float32)
    out = lit_mask(mask, view, 0.5)
    assert out.dtype == np.uint16
    np.testing.assert_array_equal(out, [[0, 1, 0], [2, 0, 1]])
    with pytest.raises(PsdError, match="differ in size"):
        lit_mask(mask, view[:1], 0.5)


def test_the_horizon_radius_is_the_median_b_axis():
    assert gap_radius_mm(np.array([[9.0, 4.0, 2.0], [12.0, 8.0, 3.0], [6.0, 5.0, 4.0]])) == 5.0
    with pytest.raises(PsdError, match="without particles"):
        gap_radius_mm(np.zeros((0, 3)))


def test_a_scenes_surface_is_its_renders_and_its_gaps_lie_on_particles(tmp_path):
    (scene,) = split_dataset(tmp_path, ["train"], resolution=48)
    height, px_mm, radius = scene_surface(scene)
    from psdfactory.io import read_json, read_png

    mask = read_png(scene / "mask.png")
    assert height.shape == mask.shape and px_mm == read_json(scene / "render.json")["mm_per_px"]
    # where the render shows a particle the surface stands above the table; where it shows the table it does not
    ground = read_json(scene / "render.json")["look"]["ground_level_mm"]
    assert np.median(height[mask > 0]) > ground + 0.5
    assert np.median(height[mask == 0]) == pytest.approx(ground, abs=0.3)
    assert radius > 0
    # the surface lines up with the mask: raised where a particle shows, at the ground where the table does
    assert ((height > ground + 0.05) == (mask > 0)).mean() > 0.9
    view = scene_sky_view(scene)
    assert ((view >= 0) & (view <= 1)).all()
    row = {"mask_path": str((scene / "mask.png").relative_to(tmp_path))}
    np.testing.assert_array_equal(training_mask(tmp_path, row), mask)
    lit = training_mask(tmp_path, row, 0.9)
    assert set(np.unique(lit)) <= set(np.unique(mask))
    assert (lit > 0).sum() < (mask > 0).sum()  # at 0.9 some particle pixels are gaps
    np.testing.assert_array_equal(lit[lit > 0], mask[lit > 0])  # and the rest keep their ids


def test_render_records_lack_of_a_camera_is_refused(tmp_path):
    (scene,) = split_dataset(tmp_path, ["train"], resolution=32)
    from psdfactory.io import read_json, write_json

    rec = read_json(scene / "render.json")
    del rec["look"]["view_fraction"]
    write_json(scene / "render.json", rec)
    with pytest.raises(PsdError, match="lacks the camera.*render it again"):
        scene_surface(scene)


def test_gap_sky_view_is_a_setting_in_the_slice_only_when_on():
    cfg = tiny_config()
    cfg["train"]["architectures"] = ["instances"]
    assert "gap_sky_view" not in train_params(cfg, "instances").get("settings", {})
    cfg["train"]["instances"]["gap_sky_view"] = 0.5
    assert train_params(cfg, "instances")["settings"]["gap_sky_view"] == 0.5
    base = train_params(tiny_config(), "instances")["settings"]
    assert InstanceSettings.from_dict(base).gap_sky_view == 0.0
    with pytest.raises(PsdError, match="gap_sky_view"):
        InstanceSettings.from_dict({**base, "gap_sky_view": 1.5})


def test_a_model_taught_the_lit_tops_records_it_and_is_scored_against_them_too(tmp_path):
    import json

    from psdfactory.learn.evaluate import evaluate
    from psdfactory.learn.instances.targets import load_scenes
    from psdfactory.learn.train import train_from_params
    from psdfactory.manifest import read_scenes

    from .test_instances import tiny_instance_params

    dirs = split_dataset(tmp_path, ["train", "val"], resolution=48)
    cfg = tiny_config(n_scenes=2, count=[15, 25])
    cfg["render"]["resolution"] = 48
    cfg["train"]["instances"]["gap_sky_view"] = 0.8
    params = tiny_instance_params(cfg)
    assert params["settings"]["gap_sky_view"] == 0.8
    # the foreground target is the lit tops: fewer grain pixels than the masks hold
    rows = read_scenes(tmp_path, "tiny").to_pylist()
    _, full = load_scenes(tmp_path, rows)
    _, lit = load_scenes(tmp_path, rows, gap_sky_view=0.8)
    assert 0 < lit[:, 0].sum() < full[:, 0].sum()
    summary = train_from_params(params, tmp_path, tmp_path / "model")
    assert summary["gap_sky_view"] == 0.8
    evaluate(tmp_path / "model" / "model.pt", tmp_path, ["tiny"], tmp_path / "ev")
    m = json.loads((tmp_path / "ev" / "metrics.json").read_text())["datasets"]["tiny"]
    lit_seg, seg = m["segmentation_lit"], m["segmentation"]
    assert lit_seg["gap_sky_view"] == 0.8 and lit_seg["n_pred"] == seg["n_pred"]
    assert 0 < lit_seg["n_true"] <= seg["n_true"] and 0 <= lit_seg["n_matched"] <= lit_seg["n_pred"]
    assert len(dirs) == 2


def test_sky_occlusion_darkens_what_sees_little_sky_and_is_out_of_the_default_slice(tmp_path):
    from psdfactory import config as psd_config
    from psdfactory.io import read_png
    from psdfactory.scene.render.look import RenderParams
    from psdfactory.scene.stages import run_render

    (scene,) = split_dataset(tmp_path, ["train"], resolution=48)
    cfg = tiny_config(count=[15, 25])
    cfg["render"]["resolution"] = 48
    assert "occlusion" not in psd_config.render_params(cfg)  # the default renders' params are as before
    cfg["render"].update(occlusion="sky", occlusion_strength=[0.9, 0.9], jpeg_fraction=0.0)
    params = psd_config.render_params(cfg)
    assert params["occlusion"] == "sky"
    cfg["render"]["backend"] = "cycles"  # Cycles traces the light: the setting is not in its slice
    assert "occlusion" not in psd_config.render_params(cfg)
    cfg["render"]["backend"] = "tiny"
    run_render(params, scene)
    after = read_png(scene / "image.png").astype(float).mean(axis=2)
    cfg["render"].update(occlusion="crevice")
    run_render(psd_config.render_params(cfg), scene)
    crevice = read_png(scene / "image.png").astype(float).mean(axis=2)
    view = scene_sky_view(scene)
    low, high = view < np.quantile(view, 0.2), view >= np.quantile(view, 0.8)
    # darker where the sky is hidden, relative to where it is open
    assert (after[low].mean() / after[high].mean()) < (crevice[low].mean() / crevice[high].mean())
    with pytest.raises(PsdError, match="render.occlusion must be one of crevice, sky"):
        RenderParams.from_dict({**params, "occlusion": "ambient"})
    cfg["render"]["occlusion"] = "crevice"  # the backend comparison's settings, too, leave out the default
    assert "occlusion" not in psd_config.compare_params(cfg)
    cfg["render"]["occlusion"] = "sky"
    assert psd_config.compare_params(cfg)["occlusion"] == "sky"


def test_a_scene_without_a_visible_particle_keeps_its_empty_mask(tmp_path):
    from psdfactory.io import write_png

    (scene,) = split_dataset(tmp_path, ["train"], resolution=32)
    empty = np.zeros((32, 32), dtype=np.uint16)
    write_png(scene / "mask.png", empty)
    row = {"mask_path": str((scene / "mask.png").relative_to(tmp_path))}
    np.testing.assert_array_equal(training_mask(tmp_path, row, 0.5), empty)
