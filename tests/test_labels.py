import numpy as np
import pytest

from psdfactory import PsdError
from psdfactory.psd import SIZE_DEFINITIONS, cumulative_curve, weighted_percentiles
from psdfactory.scene.labels import LabelParams, in_view, scene_labels, visible_pixels


def test_number_percentiles_hand_computed():
    # midpoints of 4 equal weights sit at 0.125, 0.375, 0.625, 0.875
    d = weighted_percentiles(np.array([4.0, 1.0, 3.0, 2.0]), None)
    np.testing.assert_allclose(d, [1.0, 2.5, 4.0])
    d = weighted_percentiles(np.array([1.0, 2.0, 3.0, 4.0]), None, q=(25.0, 75.0))
    np.testing.assert_allclose(d, [1.5, 3.5])


def test_equal_weights_match_numpy_hazen():
    x = np.random.default_rng(0).gamma(2.0, 3.0, size=101)
    np.testing.assert_allclose(weighted_percentiles(x, None), np.percentile(x, [10, 50, 90], method="hazen"))


def test_volume_percentiles_hand_computed():
    # sizes 1 and 2 with volumes 1 and 3: midpoints at 0.5/4 = 0.125 and (4 - 1.5)/4 = 0.625
    d50 = weighted_percentiles(np.array([1.0, 2.0]), np.array([1.0, 3.0]), q=(50.0,))
    assert d50[0] == pytest.approx(1.0 + (0.5 - 0.125) / 0.5)


def test_volume_weighting_shifts_up():
    rng = np.random.default_rng(1)
    sizes = rng.uniform(1, 20, 500)
    d_n = weighted_percentiles(sizes, None)
    d_v = weighted_percentiles(sizes, sizes**3)
    assert (d_v > d_n).all()


def test_percentile_errors():
    with pytest.raises(PsdError):
        weighted_percentiles(np.array([]), None)
    with pytest.raises(PsdError):
        weighted_percentiles(np.array([1.0, 2.0]), np.array([-1.0, 1.0]))


def test_cumulative_curve():
    q = cumulative_curve(np.array([1.0, 2.0, 3.0]), np.array([1.0, 1.0, 2.0]), np.array([0.5, 1.0, 2.5, 3.0]))
    np.testing.assert_allclose(q, [0.0, 0.25, 0.5, 1.0])


def test_visible_pixels_and_bad_mask():
    mask = np.array([[0, 1, 1], [3, 3, 3]], dtype=np.uint16)
    np.testing.assert_array_equal(visible_pixels(mask, 3), [2, 0, 3])
    with pytest.raises(PsdError, match="only 2 particles"):
        visible_pixels(mask, 2)


def test_scene_labels():
    sizes = np.array([1.0, 2.0, 3.0, 4.0])
    by_definition = {d: sizes * (k + 1) for k, d in enumerate(SIZE_DEFINITIONS)}
    by_definition["sieve"] = sizes
    lab = scene_labels(by_definition, sizes**3, np.array([0, 5, 1, 9]), 100, (0.5, 5.0),
                       LabelParams(visible_min_px=2, psd_bins=32, size_definition="sieve", weighting="number",
                                   particles="bed"))
    assert lab["size_definition"] == "sieve" and lab["weighting"] == "number"
    assert lab["d50_b_axis_mm"] == pytest.approx(5.0) and lab["d50_sieve_mm"] == lab["d50_mm"]
    vol = scene_labels(by_definition, sizes**3, np.array([0, 5, 1, 9]), 100, (0.5, 5.0),
                       LabelParams(visible_min_px=2, psd_bins=32, size_definition="b-axis", weighting="volume",
                                   particles="bed"))
    assert vol["d50_mm"] == vol["d50_b_axis_v_mm"] == vol["d50_v_mm"] > vol["d50_b_axis_mm"]
    assert lab["n_visible"] == 2
    assert lab["covered_fraction"] == pytest.approx(0.15)
    assert lab["d10_mm"] <= lab["d50_mm"] <= lab["d90_mm"]
    assert lab["d50_mm"] == pytest.approx(2.5)
    assert lab["psd_q0"][-1] == 1.0 and lab["psd_q3"][0] == 0.0
    assert lab["n_particles"] == lab["n_in_bed"] == 4 and lab["particles_counted"] == "bed"


def test_labels_count_the_particles_in_view():
    """labels.particles: in_view — only the particles whose centre the camera sees; the visible
    particles and the covered fraction stay the image's."""
    x = np.array([0.0, 10.0, -49.0, 60.0, 0.0])
    y = np.array([0.0, -30.0, 49.0, 0.0, -50.5])
    np.testing.assert_array_equal(in_view(x, y, 100.0), [True, True, True, False, False])
    sizes = np.array([1.0, 2.0, 3.0, 9.0, 9.0])  # the two out of view: the large ones
    by_definition = {d: sizes for d in SIZE_DEFINITIONS}
    p = LabelParams(visible_min_px=1, psd_bins=8, size_definition="sieve", weighting="number", particles="in_view")
    vis = np.array([4, 4, 4, 2, 0])
    lab = scene_labels(by_definition, sizes**3, vis, 100, (0.5, 10.0), p, in_view(x, y, 100.0))
    assert lab["d50_mm"] == pytest.approx(2.0) and lab["d90_mm"] <= 3.0  # of 1, 2, 3 mm alone
    assert lab["n_particles"] == 3 and lab["n_in_bed"] == 5 and lab["particles_counted"] == "in_view"
    assert lab["n_visible"] == 4 and lab["covered_fraction"] == pytest.approx(0.14)  # the image's
    bed = scene_labels(by_definition, sizes**3, vis, 100, (0.5, 10.0), p)
    assert bed["d50_mm"] == pytest.approx(3.0)
    with pytest.raises(PsdError, match="none of the scene's 5 particles has its centre in the camera's view"):
        scene_labels(by_definition, sizes**3, vis, 100, (0.5, 10.0), p, np.zeros(5, bool))


def test_label_params_leave_the_setting_out_where_the_camera_sees_the_whole_table():
    """Where the camera sees the whole table every particle is in view: labels.particles is left out of
    that dataset's label jobs (so theirs are not rerun), and a slice without it counts every particle."""
    from psdfactory import config as psd_config

    from .conftest import tiny_config

    cfg = tiny_config()
    assert "particles" not in psd_config.label_params(cfg, "tiny")
    assert psd_config.label_params(cfg)["particles"] == "in_view"  # the schema's default
    assert LabelParams.from_dict(psd_config.label_params(cfg, "tiny")).particles == "bed"
    cfg["render"]["view_fraction"] = [0.7, 0.9]
    assert psd_config.label_params(psd_config.validate(cfg), "tiny")["particles"] == "in_view"
