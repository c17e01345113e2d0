"""train.crop's windows: each labelled by the particles whose centre lies inside it."""

import numpy as np
import pytest
import torch

from psdfactory import PsdError
from psdfactory.learn.windows import SceneWindows, inside, particle_pixels, window_targets
from psdfactory.psd import weighted_percentiles


def test_particle_centres_map_to_the_image_frame_row_0_at_plus_y_column_0_at_minus_x():
    col, row = particle_pixels(np.array([-50.0, 0.0, 49.0]), np.array([50.0, 0.0, -49.0]), 100.0, 200)
    np.testing.assert_allclose(col, [0.0, 100.0, 198.0])
    np.testing.assert_allclose(row, [0.0, 100.0, 198.0])


def test_a_window_holds_the_centres_inside_it_and_their_percentiles_number_or_volume_weighted():
    col, row = np.array([1.0, 5.0, 9.9, 10.0, 3.0]), np.array([1.0, 5.0, 9.9, 2.0, 10.0])
    keep = inside(col, row, 0, 0, 10)
    assert keep.tolist() == [True, True, True, False, False]  # [r0, r0 + window) x [c0, c0 + window)
    sizes, volumes = np.array([2.0, 4.0, 8.0, 100.0, 100.0]), np.array([1.0, 1.0, 6.0, 1.0, 1.0])
    # three sizes, number-weighted (midpoint convention): d50 = the middle one, d10 and d90 clamp to the ends
    np.testing.assert_allclose(window_targets(sizes, volumes, keep, "number"), [2.0, 4.0, 8.0])
    # by volume (1, 1, 6 of 8) the midpoints sit at 1/16, 3/16 and 10/16: d50 between 4 and 8 mm
    d_v = window_targets(sizes, volumes, keep, "volume")
    np.testing.assert_allclose(d_v[1], 4 + 4 * (0.5 - 3 / 16) / (10 / 16 - 3 / 16))
    np.testing.assert_allclose(d_v, weighted_percentiles(sizes[:3], volumes[:3]))


class _Scenes:
    """Two 3×20×20 images whose pixel (r, c) holds 20·r + c, and scene targets of 99."""

    rows = [{"scene_id": "s0", "mm_per_px": 1.0, "resolution": 20}, {"scene_id": "s1", "mm_per_px": 1.0,
                                                                      "resolution": 20}]

    def __len__(self):
        return 2

    def __getitem__(self, i):
        x = torch.arange(400, dtype=torch.int32).reshape(1, 20, 20).repeat(3, 1, 1)
        return x, torch.full((3,), 99.0)


def _particles(rng, n=200):
    xy = rng.uniform(-10, 10, (n, 2))
    return {"particle_id": np.arange(n), "size_mm": rng.uniform(1, 5, n), "volume_mm3": rng.uniform(1, 9, n),
            "x_mm": xy[:, 0], "y_mm": xy[:, 1]}


def test_scene_windows_cut_each_image_and_label_the_window_by_its_particles_reproducibly():
    rng = np.random.default_rng(0)
    parts = {"s0": _particles(rng), "s1": _particles(rng)}
    ds = SceneWindows(_Scenes(), _Scenes.rows, parts, 8, "number", torch.Generator().manual_seed(3))
    for i in (0, 1, 0):
        x, y = ds[i]
        assert x.shape == (3, 8, 8)
        r0, c0 = divmod(int(x[0, 0, 0]), 20)
        assert torch.equal(x, _Scenes()[i][0][:, r0 : r0 + 8, c0 : c0 + 8])  # one window, every channel
        p = parts[_Scenes.rows[i]["scene_id"]]
        col, row = p["x_mm"] + 10, 10 - p["y_mm"]  # 1 mm per px, 20 mm view centred on the table
        keep = (col >= c0) & (col < c0 + 8) & (row >= r0) & (row < r0 + 8)
        assert keep.sum() >= 10
        np.testing.assert_allclose(y.numpy(), weighted_percentiles(p["size_mm"][keep], None), rtol=1e-6)
    again = SceneWindows(_Scenes(), _Scenes.rows, parts, 8, "number", torch.Generator().manual_seed(3))
    assert torch.equal(again[0][0], SceneWindows(_Scenes(), _Scenes.rows, parts, 8, "number",
                                                 torch.Generator().manual_seed(3))[0][0])


def test_scene_windows_refuse_missing_particles_and_windows_that_never_hold_one():
    rng = np.random.default_rng(1)
    with pytest.raises(PsdError, match=r"particle manifest has no rows for s1; rerun their label jobs"):
        SceneWindows(_Scenes(), _Scenes.rows, {"s0": _particles(rng)}, 8, "number", torch.Generator())
    far = {k: {**_particles(rng, 3), "x_mm": np.full(3, 500.0)} for k in ("s0", "s1")}  # all outside the view
    ds = SceneWindows(_Scenes(), _Scenes.rows, far, 8, "number", torch.Generator())
    with pytest.raises(PsdError, match=r"scene s0: no particle in any of 8 random 8-px windows; train.crop must be"):
        ds[0]
