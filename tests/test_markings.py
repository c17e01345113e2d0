"""Veins, speckle and patches on the particles of a render: only marked particles' pixels change,
the mask never, lines are as wide as asked, and switching them on changes no other draw."""


import numpy as np
import pytest

from psdfactory.io import read_json, read_png
from psdfactory.scene.render.markings import KINDS, MarkingParams, add_markings, draw_particles, vein_lines

from .render_helpers import rerender

DEFAULTS = {"veins": [0.5, 0.5], "vein_width_mm": [1.0, 1.0], "vein_spacing_mm": [10.0, 10.0],
            "speckle": [0.4, 0.4], "speckle_mm": [1.5, 1.5], "patches": [0.2, 0.2]}


def params(probability: float = 1.0, **kw) -> MarkingParams:
    return MarkingParams.from_dict({"probability": probability, **DEFAULTS, **kw})


def grid_mask(size: int = 240, cell: int = 40) -> np.ndarray:
    """Square particles of `cell` px (ids 1..n) with a 4 px table gap between them."""
    r, c = np.mgrid[0:size, 0:size]
    ids = (r // cell) * (size // cell) + c // cell + 1
    gap = (r % cell < 4) | (c % cell < 4)
    return np.where(gap, 0, ids).astype(np.uint16)


def test_only_marked_particles_change_and_the_table_never():
    mask = grid_mask()
    n = int(mask.max())
    rgb = np.full((*mask.shape, 3), 0.5, np.float32)
    out, drawn = add_markings(rgb, mask, n, 0.5, params(0.5), np.random.default_rng(1))
    changed = np.abs(out - rgb).max(axis=2) > 1e-4
    assert not changed[mask == 0].any()  # the table as it was
    touched = np.unique(mask[changed])
    assert 0 < len(touched) < n  # half the particles, roughly
    assert drawn["marked"] == len(touched)
    assert set(drawn) == {"marked", *KINDS} and all(0 <= drawn[k] <= drawn["marked"] for k in KINDS)
    assert out.dtype == np.float32 and out.min() >= 0 and out.max() <= 1


def test_off_returns_the_image_itself():
    mask = grid_mask()
    rgb = np.full((*mask.shape, 3), 0.5, np.float32)
    out, drawn = add_markings(rgb, mask, int(mask.max()), 0.5, params(0.0), np.random.default_rng(0))
    assert out is rgb and drawn["marked"] == 0


@pytest.mark.parametrize("width_px", [2.0, 6.0])
def test_vein_lines_are_as_wide_as_asked(width_px):
    # a field with straight zero lines 50 px apart and unit slope per ... : sin(2 pi x / 100)
    x = np.arange(400, dtype=np.float32)
    field = np.broadcast_to(np.sin(2 * np.pi * x / 100), (50, 400)).astype(np.float32)
    lines = vein_lines(field, np.zeros_like(field), width_px)
    # 8 zero crossings in 400 px; each line covers ~width_px at half strength or more
    covered = (lines >= 0.5).sum(axis=1).mean()
    assert 8 * width_px * 0.4 <= covered <= 8 * width_px * 0.8 + 8
    assert lines.max() == pytest.approx(1.0, abs=0.2)


def test_the_particles_draws_do_not_depend_on_the_contrasts():
    a = draw_particles(np.random.default_rng(5), params(0.4), 300)
    b = draw_particles(np.random.default_rng(5), params(0.4, veins=[0.1, 0.9], patches=[0.0, 0.0]), 300)
    np.testing.assert_array_equal(a["marked"], b["marked"])
    np.testing.assert_array_equal(a["offset"], b["offset"])
    assert (b["contrast"][:, 2] == 0).all() and (np.sign(a["contrast"][:, 0]) == np.sign(b["contrast"][:, 0])).all()
    assert 0.3 < a["marked"].mean() < 0.5


@pytest.mark.slow
def test_switching_them_on_changes_only_the_particles_pixels(tiny_results, tmp_path):
    _, root = tiny_results
    src = root / "tiny" / "scenes" / "tiny-000001"
    dirs = rerender(tiny_results, tmp_path, "markings")
    mask = read_png(src / "mask.png")
    for p in (0.0, 1.0):
        np.testing.assert_array_equal(read_png(dirs[p] / "mask.png"), mask)  # the particles are the same
    np.testing.assert_array_equal(read_png(dirs[0.0] / "image.png"), read_png(src / "image.png"))
    assert "markings" not in read_json(dirs[0.0] / "render.json")
    drawn = read_json(dirs[1.0] / "render.json")["markings"]
    assert drawn["marked"] == len(np.unique(mask[mask > 0]))
    img_off, img_on = (read_png(dirs[p] / "image.png").astype(int) for p in (0.0, 1.0))
    differs = np.abs(img_on - img_off).max(axis=2) > 2
    # the same light, colours and noise (its own random stream): what changes lies on the
    # particles, up to the camera's blur around their outlines
    from scipy import ndimage

    near_particles = ndimage.binary_dilation(mask > 0, iterations=3)
    assert differs.sum() > 100 and not differs[~near_particles].any()
