"""Things in a photo that are not grains (scale card, ruler), drawn over a render: the mask is 0
under them, and switching them on changes no other draw of the scene."""

import numpy as np
import pytest

from psdfactory import PsdError
from psdfactory.io import read_json, read_png
from psdfactory.scene.render.distractors import KINDS, DistractorParams, add_distractors

from .render_helpers import rerender


def params(probability: float = 1.0, kinds=KINDS) -> DistractorParams:
    return DistractorParams.from_dict({"probability": probability, "kinds": list(kinds), "brightness": [1.0, 1.0]})


@pytest.mark.parametrize("kind", KINDS)
def test_a_distractor_hides_what_is_under_it_and_prints_dark_marks(kind):
    rgb = np.full((200, 200, 3), 0.4, np.float32)
    mask = np.arange(1, 200 * 200 + 1, dtype=np.int64).reshape(200, 200) % 7  # grains everywhere (0: gaps)
    out, covered, drawn = add_distractors(rgb, mask, 0.5, params(kinds=[kind]), np.random.default_rng(3))
    assert len(drawn) == 1 and drawn[0]["kind"] == kind
    under = out != 0.4
    under = under.any(axis=2)
    assert drawn[0]["covered_px"] > 1000 and (covered[under] == 0).all()  # nothing counts as a grain under it
    assert (covered[~under] == mask[~under]).all()  # and nothing else changed
    assert (out[under].min(axis=1) < 0.1).sum() > 30  # its print / ticks / chequer: dark marks
    assert out[under].max() > 0.5


def test_no_distractor_at_probability_zero_and_refusals():
    rgb, mask = np.zeros((10, 10, 3), np.float32), np.ones((10, 10), np.uint16)
    out, covered, drawn = add_distractors(rgb, mask, 1.0, params(0.0), np.random.default_rng(0))
    assert drawn == [] and out is rgb and covered is mask
    with pytest.raises(PsdError, match="boot"):
        DistractorParams.from_dict({"probability": 1.0, "kinds": ["boot"], "brightness": [1, 1]})


@pytest.mark.slow
def test_switching_them_on_changes_nothing_but_where_they_lie(tiny_results, tmp_path):
    _, root = tiny_results
    src = root / "tiny" / "scenes" / "tiny-000001"
    dirs = rerender(tiny_results, tmp_path, "distractors")
    off, on = (read_png(dirs[p] / "mask.png") for p in (0.0, 1.0))
    np.testing.assert_array_equal(off, read_png(src / "mask.png"))  # probability 0: the scene as before
    drawn = read_json(dirs[1.0] / "render.json")["distractors"]
    assert len(drawn) == 1 and drawn[0]["covered_px"] > 0
    changed = on != off
    assert changed.any() and (on[changed] == 0).all()  # the mask only loses what the object covers
    img_off, img_on = (read_png(dirs[p] / "image.png").astype(int) for p in (0.0, 1.0))
    differs = np.abs(img_on - img_off).max(axis=2) > 1
    # the same light, colours and noise elsewhere (its own random stream): only the pixels it
    # covers change, and those its edge blurs (a few px around it)
    cov = drawn[0]["covered_px"]
    assert cov * 0.8 <= differs.sum() <= cov + 12 * np.sqrt(cov) + 50
