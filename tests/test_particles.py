"""Known-answer tests of the per-particle measurement core (psdfactory.learn.instances: measure,
watershed, stats, scoring, draw)."""

from __future__ import annotations

import numpy as np
import pytest

from psdfactory import PsdError
from psdfactory.learn.instances.draw import draw_overlay, instance_outlines
from psdfactory.learn.instances.measure import (
    SIEVE_METHODS,
    THICKNESS_RATIO,
    feret_diameters_px,
    measure_instances,
    sieve_size,
)
from psdfactory.learn.instances.scoring import match_instances
from psdfactory.learn.instances.stats import STAT_NAMES, instance_stats, psd_from_instances
from psdfactory.learn.instances.watershed import split_instances
from psdfactory.psd import cumulative_curve, weighted_percentiles


def paint_ellipse(mask: np.ndarray, k: int, centre: tuple[float, float], a: float, b: float,
                  angle_deg: float = 0.0) -> None:
    """Set to k every pixel whose centre (r, c) lies in the ellipse (semi-axes a along the
    rotated x axis, b across it)."""
    r, c = np.indices(mask.shape)
    t = np.deg2rad(angle_deg)
    x, y = c - centre[1], r - centre[0]
    u, v = x * np.cos(t) + y * np.sin(t), -x * np.sin(t) + y * np.cos(t)
    mask[(u / a) ** 2 + (v / b) ** 2 <= 1] = k


def paint_rectangle(mask: np.ndarray, k: int, centre: tuple[float, float], length: float, width: float,
                    angle_deg: float) -> None:
    r, c = np.indices(mask.shape)
    t = np.deg2rad(angle_deg)
    x, y = c - centre[1], r - centre[0]
    u, v = x * np.cos(t) + y * np.sin(t), -x * np.sin(t) + y * np.cos(t)
    mask[(np.abs(u) <= length / 2) & (np.abs(v) <= width / 2)] = k


def brute_force_feret(mask: np.ndarray, k: int, n_angles: int = 7200) -> tuple[float, float]:
    """Caliper widths of the pixel centres of instance k over many angles, plus one pixel
    (independent check of the rotating calipers)."""
    r, c = np.nonzero(mask == k)
    t = np.linspace(0, np.pi, n_angles, endpoint=False)
    proj = np.column_stack([c, r]).astype(float) @ np.stack([np.cos(t), np.sin(t)])
    widths = proj.max(axis=0) - proj.min(axis=0) + 1
    return float(widths.min()), float(widths.max())


# (id, centre, semi-major a, semi-minor b, angle) in px, in general position (sub-pixel
# centres, non-integer radii); ids need not be consecutive
SHAPES = [
    (3, (50.3, 49.6), 15.2, 15.2, 0),
    (7, (50.7, 120.2), 8.4, 8.4, 0),
    (8, (130.2, 70.5), 30.3, 12.1, 30),
    (20, (140.4, 155.3), 20.2, 9.7, 0),
]
MM = 0.5


@pytest.fixture(scope="module")
def shapes_mask() -> np.ndarray:
    mask = np.zeros((200, 200), dtype=np.uint16)
    for k, centre, a, b, angle in SHAPES:
        paint_ellipse(mask, k, centre, a, b, angle)
    return mask


def test_discs_and_ellipses_measured_within_a_pixel(shapes_mask):
    m = measure_instances(shapes_mask, MM)
    assert m.ids.tolist() == [3, 7, 8, 20]
    assert len(m) == 4 and m.image_shape == (200, 200) and m.mm_per_px == MM
    for i, (k, centre, a, b, _) in enumerate(SHAPES):
        assert m.area_px[i] == (shapes_mask == k).sum()
        assert m.area_mm2[i] == pytest.approx(m.area_px[i] * MM**2)
        # digitisation: the area is within half a pixel of the outline's length
        assert abs(m.area_px[i] - np.pi * a * b) < 0.5 * 2 * np.pi * a
        assert abs(m.eq_diameter_mm[i] - 2 * np.sqrt(a * b) * MM) < MM
        assert abs(m.min_feret_mm[i] - 2 * b * MM) < MM
        assert abs(m.max_feret_mm[i] - 2 * a * MM) < MM
        assert abs(m.ellipse_minor_mm[i] - 2 * b * MM) < MM
        assert abs(m.ellipse_major_mm[i] - 2 * a * MM) < MM
        assert m.centroid_row_px[i] == pytest.approx(centre[0], abs=0.2)
        assert m.centroid_col_px[i] == pytest.approx(centre[1], abs=0.2)
    assert not m.touches_edge.any()
    assert set(m.as_dict()) >= {"ids", "area_mm2", "min_feret_mm", "volume_mm3", "touches_edge"}


@pytest.mark.parametrize("angle", [0.0, 25.0, 45.0, 70.0])
def test_rotated_rectangle_feret(angle):
    mask = np.zeros((80, 80), dtype=np.uint16)
    paint_rectangle(mask, 1, (40.3, 39.6), 44, 12, angle)
    _, fmin, fmax = feret_diameters_px(mask)
    # exact rotating calipers agree with a brute-force projection on 7200 angles (which can
    # only overestimate the minimum and underestimate the maximum)
    bmin, bmax = brute_force_feret(mask, 1)
    assert bmin - 0.01 <= fmin[0] <= bmin + 1e-9
    assert bmax - 1e-9 <= fmax[0] <= bmax + 0.01
    # and the geometry: the outermost pixel centres lie within a pixel inside each true edge
    assert 12 - 1 <= fmin[0] <= 12 + 1
    assert np.hypot(44, 12) - 1.5 <= fmax[0] <= np.hypot(44, 12) + 1


def test_feret_of_irregular_instances_matches_brute_force():
    # non-convex, holed and disconnected instances: smoothed noise cut into Voronoi cells
    from scipy import ndimage

    rng = np.random.default_rng(11)
    h, w = 90, 110
    noise = ndimage.gaussian_filter(rng.normal(size=(h, w)), 2.5)
    cells = np.zeros((h, w), dtype=np.uint16)
    cells.ravel()[rng.choice(h * w, 25, replace=False)] = np.arange(1, 26)
    _, (ir, ic) = ndimage.distance_transform_edt(cells == 0, return_indices=True)
    mask = np.where(noise > np.quantile(noise, 0.4), cells[ir, ic], 0).astype(np.uint16)
    mask[np.isin(mask, [3, 4])] = 3  # one instance in two separate cells
    ids, fmin, fmax = feret_diameters_px(mask)
    assert len(ids) >= 20
    for k, a, b in zip(ids, fmin, fmax, strict=True):
        bmin, bmax = brute_force_feret(mask, k, n_angles=3600)
        assert bmin - 0.05 <= a <= bmin + 1e-9, k
        assert bmax - 1e-9 <= b <= bmax + 0.05, k


def test_axis_aligned_rectangle_is_exact():
    mask = np.zeros((30, 60), dtype=np.uint16)
    mask[5:15, 10:50] = 4  # 10 rows x 40 columns
    m = measure_instances(mask, 1.0)
    assert m.min_feret_mm[0] == pytest.approx(10)
    assert m.max_feret_mm[0] == pytest.approx(np.hypot(9, 39) + 1)  # centres' hull + one pixel
    # second moments of unit squares: variance L^2 / 12 exactly, axes 4 sigma
    assert m.ellipse_minor_mm[0] == pytest.approx(4 * 10 / np.sqrt(12))
    assert m.ellipse_major_mm[0] == pytest.approx(4 * 40 / np.sqrt(12))
    # the second-moment minor axis overestimates a rectangle's width by 2/sqrt(3); min Feret does not
    assert sieve_size(m, "ellipse_minor")[0] / sieve_size(m, "min_feret")[0] == pytest.approx(2 / np.sqrt(3))


def test_tiny_instances():
    mask = np.zeros((10, 10), dtype=np.uint16)
    mask[2, 2] = 1  # one pixel
    mask[6, 2:7] = 2  # a one-pixel-thin line
    mask[[1, 2, 3, 4], [9, 8, 7, 6]] = 3  # a one-pixel-thin diagonal (collinear centres)
    mask[8:10, 8:10] = 4  # 2 x 2
    m = measure_instances(mask, 1.0)
    np.testing.assert_allclose(m.min_feret_mm, [1, 1, 1, 2])
    np.testing.assert_allclose(m.max_feret_mm, [1, 5, 3 * np.sqrt(2) + 1, np.sqrt(2) + 1])
    np.testing.assert_allclose(m.ellipse_minor_mm[:2], [4 / np.sqrt(12)] * 2)
    assert (m.volume_mm3 > 0).all()


def test_empty_mask_and_bad_input():
    m = measure_instances(np.zeros((8, 8), dtype=np.uint16), 0.5)
    assert len(m) == 0 and m.min_feret_mm.shape == (0,)
    with pytest.raises(PsdError):
        measure_instances(np.zeros((8, 8), dtype=float), 0.5)
    with pytest.raises(PsdError):
        measure_instances(np.zeros((2, 8, 8), dtype=np.uint16), 0.5)
    with pytest.raises(PsdError):
        measure_instances(np.zeros((8, 8), dtype=np.uint16), 0.0)


def test_touches_edge():
    mask = np.zeros((20, 30), dtype=np.uint16)
    mask[0, 5:8] = 1  # top row
    mask[8:12, 29] = 2  # right column
    mask[18:20, 0:2] = 3  # bottom-left corner
    mask[5:10, 5:10] = 4  # interior
    mask[1:4, 20:24] = 5  # one pixel off the border
    m = measure_instances(mask, 1.0)
    edge = dict(zip(m.ids.tolist(), m.touches_edge.tolist(), strict=True))
    assert edge == {1: True, 2: True, 3: True, 4: False, 5: False}


def test_volume_is_an_ellipsoid_on_the_footprint():
    mask = np.zeros((100, 100), dtype=np.uint16)
    paint_ellipse(mask, 1, (50, 50), 30, 15, 10)
    m = measure_instances(mask, 0.2)
    a, b = 30 * 0.2, 15 * 0.2
    expected = np.pi / 6 * (2 * a) * (2 * b) * (THICKNESS_RATIO * 2 * b)
    assert m.volume_mm3[0] == pytest.approx(expected, rel=0.06)
    m2 = measure_instances(mask, 0.2, thickness_ratio=2 * THICKNESS_RATIO)
    assert m2.volume_mm3[0] == pytest.approx(2 * m.volume_mm3[0])
    m3 = measure_instances(mask, 0.2, volume_from="ellipse_minor")
    assert m3.volume_mm3[0] == pytest.approx(m.volume_mm3[0] * m.ellipse_minor_mm[0] / m.min_feret_mm[0])


def test_sieve_size_methods(shapes_mask):
    m = measure_instances(shapes_mask, MM)
    np.testing.assert_array_equal(sieve_size(m), m.min_feret_mm)
    np.testing.assert_array_equal(sieve_size(m, "ellipse_minor"), m.ellipse_minor_mm)
    with pytest.raises(PsdError, match="min_feret"):
        sieve_size(m, "feret")


def test_psd_from_instances_equals_the_labels_estimators():
    rng = np.random.default_rng(3)
    sizes = rng.gamma(4.0, 2.0, size=60)
    volumes = sizes**3 * rng.uniform(0.3, 0.6, size=60)
    include = rng.random(60) > 0.2
    grid = np.geomspace(0.5, 40, 16)
    psd = psd_from_instances(sizes, volumes, include, grid)
    s, v = sizes[include], volumes[include]
    assert psd["n_instances"] == include.sum()
    np.testing.assert_allclose([psd["d10_mm"], psd["d50_mm"], psd["d90_mm"]], weighted_percentiles(s, None))
    np.testing.assert_allclose([psd["d10_v_mm"], psd["d50_v_mm"], psd["d90_v_mm"]], weighted_percentiles(s, v))
    np.testing.assert_allclose(psd["psd_q0"], cumulative_curve(s, np.ones_like(s), grid))
    np.testing.assert_allclose(psd["psd_q3"], cumulative_curve(s, v, grid))
    np.testing.assert_array_equal(psd["psd_size_mm"], grid)
    default = psd_from_instances(sizes, volumes)
    assert default["n_instances"] == 60 and len(default["psd_size_mm"]) == 32 and default["psd_q0"][-1] == 1.0


def test_psd_from_a_perfect_mask_matches_the_true_sizes():
    # discs of known diameter (the sieve size of a sphere) on a mask, measured back
    rng = np.random.default_rng(5)
    mask = np.zeros((240, 240), dtype=np.uint16)
    diameters = []
    k = 0
    for row in range(20, 240, 40):
        for col in range(20, 240, 40):
            k += 1
            d = rng.uniform(6, 30)
            paint_ellipse(mask, k, (row + rng.uniform(-1, 1), col + rng.uniform(-1, 1)), d / 2, d / 2)
            diameters.append(d)
    mm = 0.25
    m = measure_instances(mask, mm)
    true = np.array(diameters) * mm
    psd = psd_from_instances(sieve_size(m), m.volume_mm3, ~m.touches_edge)
    np.testing.assert_allclose([psd["d10_mm"], psd["d50_mm"], psd["d90_mm"]], weighted_percentiles(true, None), atol=mm)
    np.testing.assert_allclose(
        [psd["d10_v_mm"], psd["d50_v_mm"], psd["d90_v_mm"]], weighted_percentiles(true, true**3), atol=mm
    )


def test_psd_errors():
    with pytest.raises(PsdError, match="no particle instance left"):
        psd_from_instances(np.array([1.0, 2.0]), np.array([1.0, 8.0]), np.array([False, False]))
    with pytest.raises(PsdError, match="no particle instance left"):
        psd_from_instances(np.array([]), np.array([]))
    with pytest.raises(PsdError):
        psd_from_instances(np.array([1.0, 2.0]), np.array([1.0]))


def test_instance_stats(shapes_mask):
    m = measure_instances(shapes_mask, MM)
    st = instance_stats(m)
    assert st.shape == (len(STAT_NAMES),)
    got = dict(zip(STAT_NAMES, st, strict=True))
    # a mask alone has no size map: its statistics are NaN, every other one is finite
    assert all(np.isnan(got[k]) == k.startswith("map_") for k in STAT_NAMES)
    np.testing.assert_allclose([got["d10_mm"], got["d50_mm"], got["d90_mm"]],
                               weighted_percentiles(m.min_feret_mm, None))

    # with a size map (px of the particle each pixel belongs to): the same statistics of its
    # median per instance, beside the footprints' (which it does not change)
    size_px = np.where(shapes_mask > 0, 3.0 * shapes_mask, 0.0)
    mm = measure_instances(shapes_mask, MM, size_map_px=size_px)
    got_map = dict(zip(STAT_NAMES, instance_stats(mm), strict=True))
    assert np.isfinite(list(got_map.values())).all()
    np.testing.assert_allclose([got_map["map_d10_mm"], got_map["map_d50_mm"], got_map["map_d90_mm"]],
                               weighted_percentiles(3.0 * m.ids * MM, None))
    assert got_map["map_mean_mm"] == pytest.approx(3.0 * m.ids.mean() * MM)
    assert all(got_map[k] == got[k] for k in STAT_NAMES if not k.startswith("map_"))
    cm2 = shapes_mask.size * MM**2 / 100  # densities per cm² of image: a larger view of the same bed reads the same
    assert got["log_density"] == pytest.approx(np.log1p(4 / cm2))
    assert got["covered_fraction"] == pytest.approx((shapes_mask > 0).mean())
    assert got["edge_fraction"] == 0.0 and got["mm_per_px"] == MM

    # edge instances: excluded from the sizes, counted in the edge fraction
    mask = shapes_mask.copy()
    mask[0:40, 160:200] = 99
    got = dict(zip(STAT_NAMES, instance_stats(measure_instances(mask, MM)), strict=True))
    assert got["edge_fraction"] == pytest.approx(1 / 5)
    assert got["log_density"] == pytest.approx(np.log1p(4 / cm2))
    assert got["log_density_all"] == pytest.approx(np.log1p(5 / cm2))
    assert got["d90_mm"] < 36 * MM  # the 40 px edge square is not in the sizes

    # nothing to measure: NaN sizes (or the fill value), never an exception
    empty = measure_instances(np.zeros((16, 16), dtype=np.uint16), MM)
    st = dict(zip(STAT_NAMES, instance_stats(empty), strict=True))
    assert np.isnan(st["d50_mm"]) and st["log_density"] == 0.0
    assert st["covered_fraction"] == 0.0 and st["edge_fraction"] == 0.0
    assert np.isfinite(instance_stats(empty, fill_value=0.0)).all()
    # everything touches the edge: sizes fall back to all instances
    edge_only = np.zeros((16, 16), dtype=np.uint16)
    edge_only[0:4, 0:4] = 1
    st = dict(zip(STAT_NAMES, instance_stats(measure_instances(edge_only, 1.0)), strict=True))
    assert st["d50_mm"] == pytest.approx(4.0) and st["edge_fraction"] == 1.0


def test_stats_of_a_tiled_bed_do_not_change_with_the_field_of_view(shapes_mask):
    """The read-out's counts and coverage are the same for a view of four times the area of the
    same bed (its percentiles too, up to the interpolation between fewer samples)."""
    from psdfactory.learn.instances.stats import READOUT_FEATURES

    one = measure_instances(shapes_mask, MM)
    tiled = shapes_mask.astype(np.int64).copy()
    big = np.block([[tiled, tiled + 100], [tiled + 200, tiled + 300]])
    big[big % 100 == 0] = 0
    four = measure_instances(big.astype(np.uint16), MM)
    a = dict(zip(STAT_NAMES, instance_stats(one), strict=True))
    b = dict(zip(STAT_NAMES, instance_stats(four), strict=True))
    assert {"log_density", "log_density_all", "covered_fraction"} <= set(READOUT_FEATURES)
    assert not {"edge_fraction", "mm_per_px"} & set(READOUT_FEATURES)
    for k in ("mean_mm", "std_mm", "log_density", "log_density_all", "covered_fraction"):
        assert b[k] == pytest.approx(a[k], rel=1e-6, abs=1e-9), k


def test_size_map_median_per_instance(shapes_mask):
    """The 'size_map' sieve size is the median of the map over each instance, in mm."""
    rng = np.random.default_rng(0)
    size_px = rng.uniform(5, 50, size=shapes_mask.shape)
    m = measure_instances(shapes_mask, MM, volume_from="size_map", size_map_px=size_px)
    assert m.methods() == SIEVE_METHODS
    for i, k in enumerate(m.ids):
        assert sieve_size(m, "size_map")[i] == pytest.approx(np.median(size_px[shapes_mask == k]) * MM)
    assert np.allclose(m.volume_mm3, 2 / 3 * m.area_mm2 * m.thickness_ratio * m.size_map_mm)
    plain = measure_instances(shapes_mask, MM)
    assert "size_map" not in plain.methods()
    with pytest.raises(PsdError, match="size map"):
        sieve_size(plain, "size_map")
    with pytest.raises(PsdError, match="size map"):
        measure_instances(shapes_mask, MM, volume_from="size_map")
    with pytest.raises(PsdError, match="differ in size"):
        measure_instances(shapes_mask, MM, size_map_px=size_px[:10])


def two_touching_discs(r: float = 12, gap: float = 20) -> np.ndarray:
    mask = np.zeros((64, 80), dtype=np.uint16)
    paint_ellipse(mask, 1, (32, 40 - gap / 2), r, r)
    paint_ellipse(mask, 2, (32, 40 + gap / 2), r, r)
    return mask


def test_split_separates_two_touching_discs():
    pytest.importorskip("skimage")
    true = two_touching_discs()
    assert (true > 0).sum() > 0 and len(np.unique(true)) == 3
    pred = split_instances((true > 0).astype(float))
    assert pred.dtype == np.uint16 and pred.max() == 2
    res = match_instances(pred, true, iou=0.9)
    assert res.n_matched == 2


def test_split_keeps_one_disc_and_one_ellipse_whole():
    pytest.importorskip("skimage")
    mask = np.zeros((80, 120), dtype=np.uint16)
    paint_ellipse(mask, 1, (40, 30), 14, 14)
    paint_ellipse(mask, 2, (40, 85), 28, 9, 20)  # elongated: a long ridge in the distance map
    mask[2:4, 2:4] = 3  # 4 px: kept at the default min_area_px
    mask[76, 116] = 4  # 1 px: dropped
    pred = split_instances(mask > 0)
    assert pred.max() == 3
    assert match_instances(pred, mask, iou=0.95).n_matched == 3


def test_split_with_boundary_or_distance_maps():
    pytest.importorskip("skimage")
    true = two_touching_discs(r=12, gap=10)  # heavily overlapping: one round-ish blob
    fg = (true > 0).astype(float)
    # the foreground alone cannot tell them apart at a large h
    assert split_instances(fg, h=5.0).max() == 1
    # a predicted boundary between them can
    shifted = np.roll(true, 1, axis=1)
    boundary = (instance_outlines(true) & (shifted != true) & (shifted > 0)).astype(float)
    boundary = np.maximum(boundary, np.roll(boundary, -1, axis=1))
    pred = split_instances(fg, boundary_prob=boundary, h=2.0)
    assert pred.max() == 2 and match_instances(pred, true, iou=0.8).n_matched == 2
    # so can a given distance map (here: the true per-instance distance transform)
    from scipy import ndimage

    dist = sum(ndimage.distance_transform_edt(true == k) for k in (1, 2))
    pred = split_instances(fg, distance=dist, h=2.0)
    assert pred.max() == 2
    # nothing above threshold: an empty mask
    assert split_instances(np.zeros((8, 8))).max() == 0


def test_split_min_distance_merges_close_seeds():
    pytest.importorskip("skimage")
    true = two_touching_discs(r=10, gap=18)
    fg = true > 0
    assert split_instances(fg).max() == 2
    assert split_instances(fg, min_distance=25).max() == 1


def test_match_instances_known_case():
    true = np.zeros((40, 40), dtype=np.uint16)
    true[2:12, 2:12] = 2  # A: matched by a shifted copy
    true[20:30, 20:30] = 40  # B: missed
    pred = np.zeros_like(true)
    pred[4:14, 2:12] = 5  # A shifted 2 rows: 80 px in common, 120 in the union
    pred[30:36, 2:8] = 9  # a false instance on the background
    res = match_instances(pred, true)
    assert (res.n_pred, res.n_true, res.n_matched) == (2, 2, 1)
    assert res.pred_ids.tolist() == [5] and res.true_ids.tolist() == [2]
    assert res.iou[0] == pytest.approx(80 / 120)
    assert res.precision == pytest.approx(0.5) and res.recall == pytest.approx(0.5) and res.f1 == pytest.approx(0.5)
    # stricter threshold: nothing matches
    res = match_instances(pred, true, iou=0.7)
    assert res.n_matched == 0 and res.f1 == 0.0


def test_match_is_one_to_one_and_handles_empty_masks():
    true = np.zeros((20, 20), dtype=np.uint16)
    true[0:10, 0:10] = 1
    true[0:10, 10:12] = 2
    pred = np.zeros_like(true)
    pred[0:10, 0:12] = 1  # covers both: IoU 100/120 with one, 20/120 with the other
    res = match_instances(pred, true)
    assert res.n_matched == 1 and res.true_ids.tolist() == [1]
    assert res.precision == 1.0 and res.recall == 0.5 and res.f1 == pytest.approx(2 / 3)
    empty = np.zeros_like(true)
    res = match_instances(empty, true)
    assert res.n_pred == 0 and np.isnan(res.precision) and res.recall == 0.0 and res.f1 == 0.0
    assert np.isnan(match_instances(empty, empty).f1)
    with pytest.raises(PsdError):
        match_instances(pred, true[:10])


def test_overlay(shapes_mask):
    rng = np.random.default_rng(0)
    image = rng.integers(0, 100, size=(*shapes_mask.shape, 3), dtype=np.uint8)
    m = measure_instances(shapes_mask, MM)
    out = draw_overlay(image, shapes_mask, sieve_size(m))
    assert out.shape == image.shape and out.dtype == np.uint8
    outline = instance_outlines(shapes_mask)
    assert outline.sum() > 100
    # no text where the sizes are not finite: exactly the outline pixels change
    no_text = draw_overlay(image, shapes_mask, np.full(len(m), np.nan))
    assert (no_text[outline] == [255, 255, 0]).all()
    np.testing.assert_array_equal(no_text[~outline], image[~outline])
    # with sizes: text inside the instances, the outlines (bar where text crosses them) kept
    inside = (shapes_mask == 8) & ~outline
    assert (out[inside] != image[inside]).any()
    assert (out[outline] == [255, 255, 0]).all(axis=1).mean() > 0.9
    far = np.zeros_like(outline)
    far[:, 185:] = True  # no instance there, and no text
    np.testing.assert_array_equal(out[far], image[far])
    # grey float images are accepted
    grey = draw_overlay(image[:, :, 0] / 255.0, shapes_mask, sieve_size(m))
    assert grey.shape == image.shape
    with pytest.raises(PsdError):
        draw_overlay(image, shapes_mask, sieve_size(m)[:2])


def test_instance_outlines_are_scikit_images_inner_boundaries():
    from skimage.segmentation import find_boundaries

    rng = np.random.default_rng(0)
    for _ in range(50):
        m = np.kron(rng.integers(0, 6, (rng.integers(1, 20), rng.integers(1, 20))), np.ones((2, 2), int))
        m = m[: rng.integers(1, 40), : rng.integers(1, 40)]
        want = find_boundaries(m, connectivity=1, mode="inner", background=0) & (m > 0)
        np.testing.assert_array_equal(instance_outlines(m), want)
