import numpy as np
import pytest

from psdfactory import PsdError
from psdfactory.psd import SIZE_DEFINITIONS, cumulative_curve, weighted_percentiles
from psdfactory.scene.labels import LabelParams, scene_labels, visible_pixels


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
                       LabelParams(visible_min_px=2, psd_bins=32, size_definition="sieve", weighting="number"))
    assert lab["size_definition"] == "sieve" and lab["weighting"] == "number"
    assert lab["d50_b_axis_mm"] == pytest.approx(5.0) and lab["d50_sieve_mm"] == lab["d50_mm"]
    vol = scene_labels(by_definition, sizes**3, np.array([0, 5, 1, 9]), 100, (0.5, 5.0),
                       LabelParams(visible_min_px=2, psd_bins=32, size_definition="b-axis", weighting="volume"))
    assert vol["d50_mm"] == vol["d50_b_axis_v_mm"] == vol["d50_v_mm"] > vol["d50_b_axis_mm"]
    assert lab["n_visible"] == 2
    assert lab["covered_fraction"] == pytest.approx(0.15)
    assert lab["d10_mm"] <= lab["d50_mm"] <= lab["d90_mm"]
    assert lab["d50_mm"] == pytest.approx(2.5)
    assert lab["psd_q0"][-1] == 1.0 and lab["psd_q3"][0] == 0.0
