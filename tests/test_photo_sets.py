"""Photo sets (config `photos`): labelled photographs as a dataset kind — declared, validated and
their files checked before any job; the border-aware detection scorer and the size / PSD figures
against hand-computed cases; the report's photo figures."""

from __future__ import annotations

import copy
import csv
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml

from psdfactory import PsdError, photoset
from psdfactory.config import SCHEMA, photo_params, validate
from psdfactory.learn.instances.scoring import border_ids, match_instances, match_off_border

# ---- a tiny photo set, made in the test ------------------------------------------------------------


def rect_mask(shape: tuple[int, int], rects: dict[int, tuple[int, int, int, int]]) -> np.ndarray:
    """An instance mask: id → (row0, row1, col0, col1), inclusive."""
    m = np.zeros(shape, np.uint16)
    for k, (r0, r1, c0, c1) in rects.items():
        m[r0 : r1 + 1, c0 : c1 + 1] = k
    return m


# the reference grains of photo "a" (40 x 40 px at 0.5 mm/px): A and B inside, C cut by the border
REF_A = {1: (4, 11, 4, 19), 2: (20, 35, 24, 35), 3: (36, 39, 0, 9)}


def make_photo_set(folder: Path, n: int = 2, size: tuple[int, int] = (40, 40), scale: float = 0.5) -> Path:
    """`n` small photos (a.png, b.png, ...) with 16-bit masks (<stem>_mask.png) and labels.csv
    (image, mm_per_px, d10/d50/d90 in mm): a photo set as the default config's, in miniature."""
    from PIL import Image

    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(3)
    f = size[0] / 40  # REF_A's grains, scaled to the photo
    grains = {k: (round(r0 * f), round((r1 + 1) * f) - 1, round(c0 * f), round((c1 + 1) * f) - 1)
              for k, (r0, r1, c0, c1) in REF_A.items()}
    rows = []
    for i in range(n):
        stem = chr(ord("a") + i)
        mask = rect_mask(size, grains)
        img = rng.integers(40, 90, (*size, 3), dtype=np.uint8)
        img[mask > 0] = rng.integers(150, 230, (int((mask > 0).sum()), 3), dtype=np.uint8)
        Image.fromarray(img).save(folder / f"{stem}.png")
        Image.fromarray(mask).save(folder / f"{stem}_mask.png")
        rows.append({"image": f"{stem}.png", "mm_per_px": scale, "d10_mm": 4.0, "d50_mm": 6.0, "d90_mm": 8.0})
    with open(folder / "labels.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    return folder


def photo_spec(folder: Path) -> dict:
    return {"folder": str(folder), "mm_per_px": {"csv": "labels.csv", "column": "mm_per_px"},
            "masks": "{stem}_mask.png", "reference": {"csv": "labels.csv"}}


def photo_config(folder: Path, over: dict | None = None) -> dict:
    return {"datasets": {"train": {"n_scenes": 2}}, "photos": {"field": {**photo_spec(folder), **(over or {})}}}


# ---- the dataset kind ---------------------------------------------------------------------------------


def test_a_photo_set_validates_and_resolves_to_its_files(tmp_path):
    folder = make_photo_set(tmp_path / "ph")
    cfg = validate(photo_config(folder))
    assert cfg["photos"]["field"]["size_definition"] == "ellipse-minor" and cfg["photos"]["field"]["images"] == "*"
    sets = photoset.check(cfg)
    s = sets["field"]
    assert [p.name for p in s.photos] == ["a.png", "b.png"]  # the masks are not photos
    a = s.photos[0]
    assert a.mm_per_px == 0.5 and a.size_hw == (40, 40) and a.mask == folder / "a_mask.png"
    assert a.reference_mm == (4.0, 6.0, 8.0)
    assert set(s.files()) == {folder / f for f in ("a.png", "b.png", "a_mask.png", "b_mask.png", "labels.csv")}
    # one number for every photo, no masks, no reference: fine too
    cfg = validate({"datasets": {"train": {"n_scenes": 2}}, "photos": {"x": {"folder": str(folder), "mm_per_px": 0.3,
                                                                            "images": "*.png"}}})
    s = photoset.check(cfg)["x"]
    assert [p.mm_per_px for p in s.photos] == [0.3] * 4 and not s.has_masks  # without a pattern the masks are photos
    assert photo_params(cfg, "x")["name"] == "x"
    # the default config evaluates every model on the real photos
    from .conftest import REPO

    default = validate(yaml.safe_load((REPO / "config" / "config.yaml").read_text()))
    assert default["photos"]["real"]["folder"] == "data/photos/real"
    real = photoset.resolve("real", {**default["photos"]["real"], "folder": str(REPO / "data/photos/real")})
    assert [(p.name, p.mm_per_px, p.size_hw) for p in real.photos] == [("barton_creek.jpg", 0.288, (1500, 2000)),
                                                                        ("torrey_pines_beach.jpg", 1.108, (960, 1280))]
    assert real.photos[0].reference_mm == (5.69, 15.18, 36.14)


def _broken(folder: Path, what: str) -> dict:
    """A photo set's config after one thing about it or its files went wrong."""
    from PIL import Image

    cfg = photo_config(folder)
    spec = cfg["photos"]["field"]
    if what == "no folder":
        spec["folder"] = str(folder / "nowhere")
    elif what == "no mask":
        (folder / "b_mask.png").unlink()
    elif what == "mask of another size":
        Image.fromarray(np.zeros((40, 39), np.uint16)).save(folder / "b_mask.png")
    elif what == "colour mask":
        Image.fromarray(np.zeros((40, 40, 3), np.uint8)).save(folder / "b_mask.png")
    elif what == "no scale row":
        text = (folder / "labels.csv").read_text().splitlines()
        (folder / "labels.csv").write_text("\n".join(line for line in text if not line.startswith("b.png")) + "\n")
    elif what == "scale not a number":
        (folder / "labels.csv").write_text((folder / "labels.csv").read_text().replace("b.png,0.5", "b.png,half"))
    elif what == "no scale column":
        spec["mm_per_px"]["column"] = "scale"
    elif what == "no csv":
        spec["reference"]["csv"] = "gone.csv"
    elif what == "unordered reference":
        (folder / "labels.csv").write_text((folder / "labels.csv").read_text().replace("4.0,6.0,8.0", "9.0,6.0,8.0"))
    elif what == "two photos, one stem":
        Image.fromarray(np.zeros((40, 40, 3), np.uint8)).save(folder / "a.jpg")
    elif what == "not an image":
        (folder / "b.png").write_bytes(b"not a png")
    elif what == "no photos":
        spec["images"] = "*.tif"
    return cfg


@pytest.mark.parametrize("what,says", [
    ("no folder", "photos.field.folder: "),
    ("no mask", "photos.field.masks: the photo b.png has no mask b_mask.png"),
    ("mask of another size", "b_mask.png is 39 x 40 px, its photo b.png 40 x 40 px"),
    ("colour mask", "is a RGB image, not an instance mask"),
    ("no scale row", "photos.field.mm_per_px: " + "{labels} has no row for the photo b.png"),
    ("scale not a number", "image b.png: mm_per_px is 'half', not a number > 0"),
    ("no scale column", "has no column scale"),
    ("no csv", "photos.field.reference.csv: {folder}/gone.csv: no such file"),
    ("unordered reference", "d10 <= d50 <= d90 does not hold (9, 6, 8)"),
    ("two photos, one stem", "the photos a.jpg and a.png share the name 'a'"),
    ("not an image", "b.png is not a readable image"),
    ("no photos", "photos.field: no photos in"),
])
def test_a_broken_photo_set_is_refused_in_one_line_naming_the_key_and_file(tmp_path, what, says):
    folder = make_photo_set(tmp_path / "ph")
    cfg = validate(_broken(folder, what))  # the schema cannot see files: the check does
    with pytest.raises(PsdError) as e:
        photoset.check(cfg)
    msg = str(e.value)
    assert says.format(labels=folder / "labels.csv", folder=folder) in msg, msg
    assert msg.count("\n") == 1  # "invalid photo sets:" and the one problem


@pytest.mark.parametrize("change,says", [
    ({"masks": "mask.png"}, "photos.field.masks: 'mask.png' must hold {stem}"),
    ({"masks": "masks/{stem}.png"}, "give a file name pattern, not a path"),
    ({"masks": "{stem}_mask.txt"}, "must end in an image suffix"),
    ({"mm_per_px": 0}, "photos.field.mm_per_px: 0 is less than or equal to the minimum of 0"),
    ({"mm_per_px": {"csv": "labels.csv"}}, "'column' is a required property"),
    ({"size_definition": "sieve"}, "photos.field.size_definition: 'sieve' is not one of"),
    ({"reference": {"csv": "labels.csv", "definition": "x"}}, "Additional properties are not allowed"),
    ({"folder": ""}, "photos.field.folder"),
])
def test_a_bad_photo_set_is_refused_by_the_schema_or_the_config_check(tmp_path, change, says):
    with pytest.raises(PsdError, match="invalid config") as e:
        validate(photo_config(tmp_path, change))
    assert says in str(e.value), str(e.value)


def test_photo_sets_keep_apart_from_the_datasets(tmp_path):
    cfg = photo_config(tmp_path)
    cfg["photos"]["train"] = cfg["photos"].pop("field")
    with pytest.raises(PsdError, match="photos.train: a dataset has this name too"):
        validate(cfg)
    with pytest.raises(PsdError, match="photos: 'bad-name' does not match"):
        validate({"datasets": {"train": {"n_scenes": 2}}, "photos": {"bad-name": photo_spec(tmp_path)}})
    assert validate({"datasets": {"train": {"n_scenes": 2}}})["photos"] == {}  # none by default


def test_check_config_checks_the_photo_files(tmp_path, capsys):
    from psdfactory.cli import main

    folder = make_photo_set(tmp_path / "ph")
    path = tmp_path / "c.yaml"
    path.write_text(yaml.safe_dump(photo_config(folder)))
    assert main(["check-config", str(path)]) == 0
    assert "1 photo set of 2 photos" in capsys.readouterr().out
    (folder / "b_mask.png").unlink()
    assert main(["check-config", str(path)]) == 2
    assert "photos.field.masks: the photo b.png has no mask b_mask.png" in capsys.readouterr().err


def test_the_reference_definitions_are_the_ones_a_grain_is_measured_in():
    from psdfactory.deploy.photos import MEASURE_OF

    schema = yaml.safe_load(SCHEMA.read_text())
    assert schema["definitions"]["photo_set"]["properties"]["size_definition"]["enum"] == list(MEASURE_OF)


# ---- the scorer: the border rule, by hand ----------------------------------------------------------------

# 10 x 10 px. Reference: 1 and 2 inside, 3 cut by the top border, 4 inside.
TRUE = {1: (2, 4, 2, 4), 2: (6, 8, 6, 8), 3: (0, 1, 6, 9), 4: (3, 5, 7, 8)}
# Found: 10 = reference 1 (TP); 11 inside, matching nothing (FP); 12 on the bottom border matching
# nothing (left out, not an FP); 13 = reference 3 (left out with it); 14 = reference 4 grown to the
# right border (IoU 6 / 9: a TP though on the border). Reference 2 is missed (FN).
PRED = {10: (2, 4, 2, 4), 11: (6, 7, 2, 3), 12: (9, 9, 0, 3), 13: (0, 1, 6, 9), 14: (3, 5, 7, 9)}


def test_the_border_rule_by_hand():
    true, pred = rect_mask((10, 10), TRUE), rect_mask((10, 10), PRED)
    assert border_ids(true).tolist() == [3] and border_ids(pred).tolist() == [12, 13, 14]
    m = match_off_border(pred, true)
    assert (m.tp, m.fp, m.fn, m.left_out_pred, m.left_out_true) == (2, 1, 1, 2, 1)
    assert sorted(zip(m.pred_ids.tolist(), m.true_ids.tolist(), strict=True)) == [(10, 1), (14, 4)]
    assert m.iou.tolist() == pytest.approx(sorted([1.0, 6 / 9], reverse=True))
    assert (m.precision, m.recall, m.f1) == pytest.approx((2 / 3, 2 / 3, 2 / 3))
    # without the rule, 12 would be a false positive and 3 a true grain (13 its match): P 3/5, R 3/4
    plain = match_instances(pred, true)
    assert (plain.precision, plain.recall) == pytest.approx((3 / 5, 3 / 4))
    # the border as another copy of the mask decided it: grain 12 not on it → a false positive after all
    m = match_off_border(pred, true, pred_on_border=np.array([13, 14]))
    assert (m.tp, m.fp, m.fn, m.left_out_pred) == (2, 2, 1, 1)
    # a reference border grain is left out whatever is found there: nothing found, it is no miss
    m = match_off_border(np.zeros((10, 10), np.uint16), true)
    assert (m.tp, m.fp, m.fn, m.left_out_true) == (0, 0, 3, 1) and m.recall == 0 and np.isnan(m.precision)


# 40 x 40 px. Reference 1 found in three pieces; 2 and 3, side by side, found as one grain (IoU 24 / 54
# each); 4 not found; 5 found shifted (IoU 36 / 92); 6 found exactly. Found 15 lies on the background,
# 16 on the border matching nothing (left out, of no kind).
KIND_TRUE = {1: (2, 9, 2, 11), 2: (2, 5, 20, 25), 3: (6, 9, 20, 25), 4: (14, 19, 2, 7), 5: (14, 21, 14, 21),
             6: (30, 37, 30, 37)}
KIND_PRED = {10: (2, 9, 2, 4), 11: (2, 9, 5, 7), 17: (2, 9, 8, 11), 12: (2, 10, 20, 25), 13: (16, 23, 16, 23),
             14: (30, 37, 30, 37), 15: (30, 35, 2, 7), 16: (0, 1, 30, 35)}


def test_error_kinds_by_hand():
    from psdfactory.learn.instances.scoring import error_kinds

    true, pred = rect_mask((40, 40), KIND_TRUE), rect_mask((40, 40), KIND_PRED)
    m = match_off_border(pred, true)
    assert (m.tp, m.fp, m.fn, m.left_out_pred) == (1, 6, 5, 1)
    assert sorted(m.fn_ids.tolist()) == [1, 2, 3, 4, 5] and sorted(m.fp_ids.tolist()) == [10, 11, 12, 13, 15, 17]
    k = error_kinds(pred, true, m)
    assert k.fn == {"cut": 1, "merged": 2, "missed": 1, "misfit": 1}
    assert k.fp == {"merge": 1, "background": 1, "piece": 3, "misfit": 1}
    # found 13 lies more than half inside reference 5 but is as large: a misfit, not a piece; and where the
    # two grains of the merge are found alone, the merge is gone and the other kinds stay
    alone = pred.copy()
    alone[2:11, 20:26] = 0
    alone[2:6, 20:26], alone[6:10, 20:26] = 18, 19
    k = error_kinds(alone, true, match_off_border(alone, true))
    assert k.fn == {"cut": 1, "merged": 0, "missed": 1, "misfit": 1}
    assert k.fp == {"merge": 0, "background": 1, "piece": 3, "misfit": 1}
    # nothing found: every reference grain is missed
    empty = np.zeros((40, 40), np.uint16)
    k = error_kinds(empty, true, match_off_border(empty, true))
    assert k.fn["missed"] == 6 and sum(k.fp.values()) == 0


# ---- size errors and the PSD, by hand ----------------------------------------------------------------------

# Found at the network's scale (20 x 20 px at 1.0 mm/px, half the photo's 0.5 mm/px): A' = reference A
# (4 x 8 px, ellipse minor 4 px · 2/√3 = 4.6188 mm, as A's 8 px · 0.5 mm); B' one column wider than B
# (7 instead of 6 px: 8.0829 mm vs 6.9282 mm, +1/6); D' on the border, matching nothing.
FOUND = {1: (2, 5, 2, 9), 2: (10, 17, 12, 18), 3: (0, 1, 15, 19)}
W = 2 / np.sqrt(3)  # a w-px-wide axis-aligned rectangle's ellipse minor axis is w · 2/√3 px


def _fake_reading(mask: np.ndarray, mm_per_px: float):
    from psdfactory.learn.instances.measure import measure_instances

    m = measure_instances(mask, mm_per_px)
    grains = SimpleNamespace(mask=mask, measurements=m, sizes_mm=m.min_feret_mm)
    return SimpleNamespace(d_mm=np.array([5.0, 6.5, 9.0]), grains=grains)


def test_size_errors_and_psd_by_hand(tmp_path):
    from psdfactory.deploy.photos import TABLE_COLUMNS, PhotoScorer, read_mask, table_row
    from psdfactory.learn.instances.scoring import FN_KINDS, FP_KINDS

    folder = make_photo_set(tmp_path / "ph", n=1)
    s = photoset.check(validate(photo_config(folder)))["field"]
    photo = s.photos[0]
    ref = read_mask(photo.mask, photo.size_hw)
    scorer = PhotoScorer(SimpleNamespace(finds_grains=True), s)
    r = scorer.add(photo, _fake_reading(rect_mask((20, 20), FOUND), 1.0), ref)
    d = r["detection"]
    assert (d["tp"], d["fp"], d["fn"], d["left_out_found"], d["left_out_reference"]) == (2, 0, 0, 1, 1)
    assert r["n_found"] == 3 and r["n_found_off_border"] == 2 and r["n_reference"] == 2
    a, b, b_ref = 4 * W, 7 * W, 6 * W  # mm
    se = r["size_error"]["size_definition"]
    assert se["n"] == 2 and se["median"] == pytest.approx((b - b_ref) / b_ref / 2)  # of 0 and 1/6
    assert se["p90"] == pytest.approx(0.9 * (b - b_ref) / b_ref)
    # the sieve estimate (min Feret: 4 and 7 px) against the reference's ellipse minor axis
    sieve = r["size_error"]["sieve"]
    assert sorted([sieve["median"], sieve["p90"]]) == pytest.approx(sorted(
        [np.median([abs(4 - a) / a, abs(7 - b_ref) / b_ref]),
         np.percentile([abs(4 - a) / a, abs(7 - b_ref) / b_ref], 90)]))
    # d10/d50/d90 of the two grains found off the border, 'hazen': a, (a + b) / 2, b
    assert [r["psd_mm"][n] for n in ("d10", "d50", "d90")] == pytest.approx([a, (a + b) / 2, b])
    assert [r["psd_rel_err"][n] for n in ("d10", "d50", "d90")] == pytest.approx(
        [(a - 4) / 4, ((a + b) / 2 - 6) / 6, (b - 8) / 8])
    assert r["error_kinds"] == {"fn": dict.fromkeys(FN_KINDS, 0), "fp": dict.fromkeys(FP_KINDS, 0)}
    pooled = scorer.pooled()
    assert pooled["detection"]["f1"] == 1.0 and pooled["size_error"]["size_definition"]["n"] == 2
    # B not found: a miss, in the photo's row, its photos.csv columns and the set's sum
    r2 = scorer.add(photo, _fake_reading(rect_mask((20, 20), {1: FOUND[1], 3: FOUND[3]}), 1.0), ref)
    assert r2["detection"]["fn"] == 1 and r2["error_kinds"]["fn"] == {**dict.fromkeys(FN_KINDS, 0), "missed": 1}
    row = table_row(photo, {**r2, "network_hw": (20, 20), "overlay": "a.png"}, "ellipse-minor",
                    {"size_definition": "sieve", "weighting": "number"})
    assert (row["fn_missed"], row["fn_cut"], row["fp_background"]) == (1, 0, 0)
    assert set(row) <= set(TABLE_COLUMNS) and {"fn_merged", "fp_piece"} <= set(row)
    assert scorer.pooled()["error_kinds"]["fn"]["missed"] == 1
    from psdfactory.report import misses_line

    assert misses_line(r2["error_kinds"]).startswith(
        "not matched: 1 reference grains (0 cut, 0 merged, 1 missed, 0 misfit), 0 grains found (0 merge, ")
    assert pooled["psd_abs_rel_err"]["d90"] == pytest.approx(abs(b - 8) / 8)
    # a model that finds no grains: its own reading against the reference, nothing else
    cnn = PhotoScorer(SimpleNamespace(finds_grains=False), s).add(photo, SimpleNamespace(d_mm=np.array([5, 6, 10.0])),
                                                                  ref)
    assert "detection" not in cnn and cnn["psd_rel_err"]["d90"] == pytest.approx(0.25)
    # no reference CSV: the reference d-values are the same percentiles of its masks' grains
    s2 = photoset.resolve("field", {**photo_spec(folder), "reference": None, "size_definition": "ellipse-minor"})
    r2 = PhotoScorer(SimpleNamespace(finds_grains=True), s2).add(s2.photos[0], _fake_reading(rect_mask(
        (20, 20), FOUND), 1.0), ref)
    assert r2["reference_from"] == "mask" and r2["reference_mm"]["d90"] == pytest.approx(b_ref)



# ---- reference masks with an outline band (photoset outline_band_px) ---------------------------------------


def test_neighbour_gaps_and_the_outline_band_by_hand():
    from psdfactory.learn.instances.scoring import neighbour_gaps, outline_band_px

    # 1 and 2 touch; 2 and 3 leave 3 px between them (cols 10-12); 4 lies 5 px below 1 (rows 9-13)
    m = rect_mask((30, 30), {1: (0, 8, 0, 4), 2: (0, 8, 5, 9), 3: (0, 8, 13, 20), 4: (14, 20, 0, 4)})
    pairs, gaps = neighbour_gaps(m)
    got = dict(zip(map(tuple, pairs.tolist()), gaps.tolist(), strict=True))
    assert sorted(got) == [(1, 2), (1, 4), (2, 3), (2, 4), (3, 4)]
    assert (got[(1, 2)], got[(2, 3)], got[(1, 4)]) == (0.0, 3.0, 5.0)
    assert 26 ** 0.5 <= got[(2, 4)] < 5.5 and got[(3, 4)] > 10  # a slanted gap, √(5² + 1²), reads a little over
    # a grid of 12 px squares 4 px apart, as an outline class drawn in 0s leaves them: the band is 4 px
    grid = rect_mask((64, 64), {1 + i * 4 + j: (16 * i, 16 * i + 11, 16 * j, 16 * j + 11)
                                for i in range(4) for j in range(4)})
    assert outline_band_px(grid) == pytest.approx(4.0)
    assert outline_band_px(rect_mask((10, 10), {1: (2, 5, 2, 5)})) == 0.0  # no neighbour
    assert outline_band_px(np.zeros((8, 8), np.uint16)) == 0.0
    # sparse grains, far apart for their size, say nothing of a band
    sparse = rect_mask((60, 60), {1 + i * 3 + j: (20 * i, 20 * i + 5, 20 * j, 20 * j + 5)  # 14 px apart
                                  for i in range(3) for j in range(3)})
    assert outline_band_px(sparse) == 0.0
    touching = rect_mask((20, 20), {k + 1: (0, 19, 5 * k, 5 * k + 4) for k in range(4)})
    assert outline_band_px(touching) == 0.0


def test_restoring_outlines_grows_grains_to_meet_at_the_bands_middle():
    from psdfactory.learn.instances.scoring import outline_band_px, restore_outlines

    full = rect_mask((64, 64), {1 + i * 4 + j: (16 * i, 16 * i + 15, 16 * j, 16 * j + 15)
                                for i in range(4) for j in range(4)})  # touching 16 px squares
    drawn = rect_mask((64, 64), {1 + i * 4 + j: (16 * i + 2, 16 * i + 13, 16 * j + 2, 16 * j + 13)
                                 for i in range(4) for j in range(4)})  # each eroded 2 px: 4 px bands
    band = outline_band_px(drawn)
    assert band == pytest.approx(4.0)
    back = restore_outlines(drawn, band)
    assert np.array_equal(back[back > 0], full[back > 0])  # no grain grows into another's place
    # grown by (4 + 1) / 2 px: whole again, but at each square's 4 corners the pixel √8 px from it
    assert (back != full).sum() == 16 * 4
    assert np.array_equal(back[24], full[24]) and np.array_equal(back[:, 40], full[:, 40])
    assert np.array_equal(restore_outlines(drawn, 0), drawn)
    # an odd band (5 px): its middle pixel goes to one of the two grains, none is left between them
    odd = rect_mask((64, 64), {1 + i * 4 + j: (16 * i + 2, 16 * i + 12, 16 * j + 2, 16 * j + 12)
                               for i in range(4) for j in range(4)})
    assert outline_band_px(odd) == pytest.approx(5.0)
    grown = restore_outlines(odd, 5.0)
    assert (grown[7] > 0).all() and (grown[:, 39] > 0).all()  # rows and columns through the grains: no gap
    with pytest.raises(PsdError, match="outline band"):
        restore_outlines(drawn, -1)


def test_the_scorer_gives_the_figures_again_against_restored_outlines(tmp_path):
    from psdfactory.deploy.photos import PhotoScorer, read_mask

    folder = make_photo_set(tmp_path / "ph", n=1)
    # the reference drawn 1 px inside each grain: the grains "found" are the full ones
    # grain 3 is drawn 1 px from the top border: grown back it reaches it, and is still a reference grain
    ref_full = rect_mask((40, 40), {1: (4, 11, 4, 19), 2: (20, 35, 24, 35), 3: (0, 3, 24, 36)})
    drawn = rect_mask((40, 40), {1: (5, 10, 5, 18), 2: (21, 34, 25, 34), 3: (1, 2, 25, 35)})
    from PIL import Image

    Image.fromarray(drawn).save(folder / "a_mask.png")
    s = photoset.check(validate(photo_config(folder, {"outline_band_px": 2})))["field"]
    assert s.outline_band_px == 2
    photo = s.photos[0]
    ref = read_mask(photo.mask, photo.size_hw)
    reading = _fake_reading(ref_full, photo.mm_per_px)
    as_drawn = PhotoScorer(SimpleNamespace(finds_grains=True), s).add(photo, reading, ref)
    assert as_drawn["size_error"]["size_definition"]["median_bias"] > 0.1  # found grains look too large
    rest = PhotoScorer(SimpleNamespace(finds_grains=True), s, outlines_restored=True).add(photo, reading, ref)
    assert as_drawn["n_reference"] == 3
    assert rest["band_px"] == 2 and rest["detection"]["f1"] == 1.0 and rest["n_reference"] == 3
    # grown by (2 + 1) / 2 px, corners included (√2): the reference is the found grains
    assert rest["size_error"]["size_definition"]["median"] == pytest.approx(0.0)
    assert rest["reference_from"] == "mask"  # the CSV's d-values are of the grains as drawn
    # ... of all three grains, 3 too: the border rule is the mask's as drawn (its grown copy touches the border)
    from psdfactory.deploy.photos import percentiles
    from psdfactory.learn.instances.measure import measure_instances

    full = measure_instances(ref_full.astype(np.int64), photo.mm_per_px)
    assert list(rest["reference_mm"].values()) == pytest.approx(percentiles(full.ellipse_minor_mm).tolist())
    assert rest["detection"]["tp"] == 3 and rest["detection"]["left_out_reference"] == 0
    auto = photoset.check(validate(photo_config(folder, {"outline_band_px": "auto"})))["field"]
    rest = PhotoScorer(SimpleNamespace(finds_grains=True), auto, outlines_restored=True).add(photo, reading, ref)
    assert rest["band_px"] == 0.0  # the mask's two grains are far apart: no band to read off it
    # a band without masks describes nothing: refused, naming the key
    with pytest.raises(PsdError, match="photos.field.outline_band_px: 'auto' describes reference masks"):
        photoset.check(validate(photo_config(folder, {"outline_band_px": "auto", "masks": None})))
    with pytest.raises(PsdError, match="photos.field.outline_band_px"):
        validate(photo_config(folder, {"outline_band_px": -2}))

# ---- the report's photo figures ------------------------------------------------------------------------------

def photo_metrics(arch: str, name: str, finds_grains: bool, f1: float = 0.62) -> dict:
    """A model's metrics.json on a photo set, as deploy.photos writes it (two photos)."""
    det = {"iou": 0.5, "tp": 200, "fp": 50, "fn": 100, "left_out_found": 12, "left_out_reference": 0,
           "precision": 0.8, "recall": 0.667, "f1": f1}
    err = {"n": 190, "median": 0.081, "p90": 0.32, "median_bias": -0.02}
    photos = {}
    for i, photo in enumerate(("barton_creek.jpg", "torrey_pines_beach.jpg")):
        ref = {"d10": 5.69, "d50": 15.18, "d90": 36.14}
        psd = {k: v * (1.1 + 0.1 * i) for k, v in ref.items()}
        r = {"reference_mm": ref, "reference_from": "csv", "psd_mm": psd,
             "psd_rel_err": {k: 0.1 + 0.1 * i for k in ref}, "reading_mm": psd,
             "reading_rel_err": {k: 0.1 for k in ref},
             "network_hw": [737, 983], "mm_per_px": 0.288, "overlay": f"{Path(photo).stem}.png"}
        if finds_grains:
            r.update(n_found=320, n_found_off_border=300, n_reference=347, detection=det,
                     size_error={"size_definition": err, "sieve": err})
        photos[photo] = r
    pooled = {"psd_abs_rel_err": {"d10": 0.15, "d50": 0.15, "d90": 0.15}}
    if finds_grains:
        pooled.update(detection={**det, "tp": 400}, size_error={"size_definition": err, "sieve": err})
    return {"arch": arch, "photoset": name, "finds_grains": finds_grains, "size_definition": "ellipse-minor",
            "psd_size_definition": "ellipse-minor" if finds_grains else "sieve",
            "reading": {"size_definition": "sieve", "weighting": "number"}, "iou": 0.5,
            "compared_at": "the photo's resolution", "photos": photos, "pooled": pooled}


def write_photo_results(root: Path, arch: str, name: str, finds_grains: bool) -> Path:
    """eval/<arch>/photos/<name>/metrics.json and its overlays (800 x 625 px, as deploy.photos draws them)."""
    from PIL import Image

    d = root / "eval" / arch / "photos" / name
    (d / "overlays").mkdir(parents=True)
    m = photo_metrics(arch, name, finds_grains)
    (d / "metrics.json").write_text(json.dumps(m))
    for r in m["photos"].values():
        Image.new("RGB", (800, 625), (120, 130, 140)).save(d / "overlays" / r["overlay"])
    return d / "metrics.json"


def test_the_summary_card_gets_a_column_group_per_photo_set_never_ranked_on():
    from psdfactory.report import photo_table, summarize, summary_table

    from .test_report import SPEED, _bench, _summary_config, _tables

    cfg, metrics = _summary_config(photos=False)
    bench = {a: _bench(a, v) for a, v in SPEED.items()}
    photos = {a: {"real": photo_metrics(a, "real", a == "instances", f1=0.62)} for a in metrics}
    plain = summarize(cfg, metrics, bench, _tables())
    s = summarize(cfg, metrics, bench, _tables(), photos)
    assert [c.name for c in s.photo_sets] == ["real"]
    assert s.photo_sets[0].about == "2 photos vs reference (ellipse-minor)"
    assert s.photo_cells["instances"]["real"] == ["0.62", "15 % / 15 %"]
    assert s.photo_cells["resnet18"]["real"] == ["—", "15 % / 15 %"]  # a CNN: no F1, its own reading's error
    assert s.use == plain.use  # the photos are measured, not ranked on
    assert "never ranked on" in s.note
    head, rows = summary_table(s)
    assert "F1 on real (photos)" in head and rows[0][head.index("F1 on real (photos)")] in ("—", "0.62")
    head, rows = photo_table(photos["instances"]["real"])
    assert rows[0][:5] == ["barton_creek.jpg", "300 / 347", "0.800", "0.667", "0.620"]
    assert rows[0][5] == "8.1 % / 32.0 %" and rows[0][-1] == "+10 % / +10 % / +10 %"
    assert rows[-1][0] == "all 2 (pooled)" and rows[-1][1] == "600 / 694" and rows[-1][-1].startswith("mean |error|")
    head, rows = photo_table(photos["resnet18"]["real"])
    assert head == ["photo", "d10 / d50 / d90 (mm)", "reference (mm)", "error d10 / d50 / d90"]  # no grains
    assert rows[0] == ["barton_creek.jpg", "6.26 / 16.7 / 39.8", "5.69 / 15.2 / 36.1", "+10 % / +10 % / +10 %"]
    # a set that restores its references' outlines: the same rows again against those
    m = copy.deepcopy(photos["instances"]["real"])
    for r in m["photos"].values():
        r["outlines_restored"] = {"band_px": 5.0, "reference_mm": {"d10": 6.0, "d50": 16.0, "d90": 40.0},
                                  "reference_from": "mask", "psd_rel_err": {"d10": 0.02, "d50": -0.01, "d90": 0.0},
                                  "n_reference": 340, "detection": {**r["detection"], "f1": 0.7},
                                  "size_error": r["size_error"]}
    m["pooled_outlines_restored"] = {**m["pooled"], "detection": {**m["pooled"]["detection"], "f1": 0.71}}
    head, rows = photo_table(m)
    assert len(rows) == 6 and rows[2][0] == "all 2 (pooled)"
    assert rows[3][:5] == ["barton_creek.jpg, outlines restored (band 5.0 px)", "300 / 340", "0.800", "0.667", "0.700"]
    assert rows[3][-2:] == ["6.00 / 16.0 / 40.0", "+2 % / -1 % / +0 %"]  # the restored reference's d-values
    assert rows[5][0] == "all 2 (pooled), outlines restored" and rows[5][1] == "600 / 680" and rows[5][4] == "0.710"


def test_report_inputs_key_photo_metrics_by_their_folders(tmp_path):
    from psdfactory.report import photo_inputs

    files = [f"r/eval/{a}/photos/{s}/metrics.json" for a in ("x", "y") for s in ("real", "lab")]
    got = photo_inputs(["x", "y"], ["real", "lab"], files)
    assert got["y"]["lab"] == Path("r/eval/y/photos/lab/metrics.json")
    with pytest.raises(PsdError, match="4 metrics files for 2 models x 3 photo sets"):
        photo_inputs(["x", "y"], ["real", "lab", "more"], files)
    with pytest.raises(PsdError, match="is not eval/<arch>/photos/<set>/metrics.json"):
        photo_inputs(["x", "y"], ["real", "lab"], files[:3] + ["r/eval/z/photos/lab/metrics.json"])
    with pytest.raises(PsdError, match="once each"):
        photo_inputs(["x", "y"], ["real", "lab"], files[:3] + files[:1])
    assert copy.deepcopy(got) == got


# ---- the command, with a model that finds no grains ------------------------------------------------------------

CNN_META = {"arch": "resnet18", "input_size": 64, "image_resolution": 64, "mm_per_px": 0.5,
            "target_stats": {"mean": [4.0, 6.0, 8.0], "std": [0.5, 0.5, 0.5], "part_mean": [1.0, 1.0, 1.0],
                             "part_std": [0.2, 0.2, 0.2]}}


@pytest.fixture(scope="module")
def cnn_model(tmp_path_factory) -> Path:
    """An untrained resnet18 reading 64 px at 0.5 mm/px, saved as training saves it."""
    import torch

    from psdfactory.learn.models import TargetStats, build_model
    from psdfactory.learn.runtime import save_model

    torch.manual_seed(0)
    model, _ = build_model("resnet18", TargetStats(**CNN_META["target_stats"]), "none", size=64)
    path = tmp_path_factory.mktemp("cnn") / "model.pt"
    save_model(path, model, CNN_META)
    return path


def test_evaluate_photos_writes_metrics_a_row_and_an_overlay_per_photo(tmp_path, cnn_model, capsys):
    from psdfactory.cli import main

    folder = make_photo_set(tmp_path / "ph", size=(80, 80))  # 80 px at 0.5 mm/px: 80 px at the model's scale
    cfg = validate(photo_config(folder, {"outline_band_px": 2}))
    params = json.dumps({"photoset": photo_params(cfg, "field"), "precision": "fp32"})
    out = tmp_path / "eval" / "resnet18" / "photos" / "field"
    assert main(["evaluate-photos", "--params", params, "--model", str(cnn_model), "--out-dir", str(out)]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert (m["arch"], m["photoset"], m["finds_grains"], m["psd_size_definition"]) == ("resnet18", "field", False,
                                                                                      "b-axis")
    a = m["photos"]["a.png"]
    assert a["network_hw"] == [80, 80] and a["reference_mm"] == {"d10": 4.0, "d50": 6.0, "d90": 8.0}
    assert a["psd_rel_err"]["d50"] == pytest.approx((a["psd_mm"]["d50"] - 6.0) / 6.0)
    assert "detection" not in m["pooled"] and m["pooled"]["psd_abs_rel_err"]["d50"] == pytest.approx(
        np.mean([abs(r["psd_rel_err"]["d50"]) for r in m["photos"].values()]))
    rows = list(csv.DictReader(open(out / "photos.csv")))
    assert [r["image"] for r in rows] == ["a.png", "b.png"] and rows[0]["f1"] == "" and rows[0]["overlay"] == "a.png"
    # the reading again against the reference masks' grains grown by 1 px (the CSV's d-values are of those drawn)
    rest = a["outlines_restored"]
    assert rest["band_px"] == 2 and rest["reference_from"] == "mask" and "detection" not in rest
    assert rest["reference_mm"]["d50"] > 6.0 and m["pooled_outlines_restored"]["psd_abs_rel_err"]["d50"] is not None
    assert float(rows[0]["outline_band_px"]) == 2 and float(rows[0]["restored_reference_d50_mm"]) == pytest.approx(
        rest["reference_mm"]["d50"]) and rows[0]["restored_f1"] == ""
    from PIL import Image

    with Image.open(out / "overlays" / "b.png") as img:  # the photo under a caption band
        assert img.size[0] == 80 and img.size[1] > 80
    # a photo smaller than the model reads, at its scale: one line naming it and the size it needs
    small = validate(photo_config(folder, {"mm_per_px": 0.25}))
    params = json.dumps({"photoset": photo_params(small, "field"), "precision": "fp32"})
    capsys.readouterr()
    args = ["evaluate-photos", "--params", params, "--model", str(cnn_model), "--out-dir", str(tmp_path / "x")]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "at least 32 mm a side" in err[0], err
    assert "a.png: at resnet18's scale (0.500 mm/px) this photo is 40 x 40 px, smaller than the 64 px" in err[0]


def test_evaluate_photos_reads_a_calibrated_model_as_predict_does_and_names_its_weighting(tmp_path, cnn_model,
                                                                                        caplog):
    """A CNN calibrated to references by mass: its photo readings are its own corrected, labelled volume-weighted
    in photos.csv, with a warning that the set's references count grains."""
    import logging

    import torch

    from psdfactory.cli import main
    from psdfactory.learn import calibration as cal
    from psdfactory.learn.estimator import model_definition
    from psdfactory.learn.runtime import write_torch

    folder = make_photo_set(tmp_path / "ph", size=(80, 80))
    params = json.dumps({"photoset": photo_params(validate(photo_config(folder, {})), "field"), "precision": "fp32"})
    raw_out, cal_out = tmp_path / "raw", tmp_path / "cal"
    assert main(["evaluate-photos", "--params", params, "--model", str(cnn_model), "--out-dir", str(raw_out)]) == 0
    ckpt = torch.load(cnn_model, map_location="cpu", weights_only=True)
    own = {"size_definition": model_definition(ckpt["meta"]), "weighting": ckpt["meta"].get("weighting", "number")}
    pred = np.array([[1.0, 2.0, 3.0], [2.0, 3.0, 5.0], [3.0, 5.0, 8.0]])
    block = cal.calibration_block(["x", "y", "z"], pred, 2 * pred + 1, own["size_definition"], "volume", 0.5,
                                  "2025-01-01T00:00:00+00:00", "0.1.0", basis=own)
    assert block["basis"] == own
    write_torch(tmp_path / "calibrated.pt", {**ckpt, "meta": {**ckpt["meta"], "calibration": block}})
    with caplog.at_level(logging.WARNING, logger="psdfactory"):
        assert main(["evaluate-photos", "--params", params, "--model", str(tmp_path / "calibrated.pt"),
                     "--out-dir", str(cal_out)]) == 0
    assert any("reads volume-weighted d-values (its calibration's)" in r.message for r in caplog.records)
    raw, got = (json.loads((o / "metrics.json").read_text()) for o in (raw_out, cal_out))
    assert got["reading"] == {"size_definition": own["size_definition"], "weighting": "volume"}
    for name in ("a.png", "b.png"):
        r = np.array(list(raw["photos"][name]["reading_mm"].values()))
        np.testing.assert_allclose(list(got["photos"][name]["reading_mm"].values()), np.sort(2 * r + 1), rtol=1e-5)
    rows = list(csv.DictReader(open(cal_out / "photos.csv")))
    assert {(r["reading_size_definition"], r["reading_weighting"]) for r in rows} == {(own["size_definition"],
                                                                                        "volume")}


def test_the_workflow_plans_a_job_per_model_and_photo_set_and_refuses_a_broken_one_before_any(tmp_path):
    from PIL import Image

    from .workflow_helpers import planned_jobs, snakemake, write_config

    folder = make_photo_set(tmp_path / "ph")
    cfg = {"results": "results", "datasets": {"train": {"n_scenes": 2, "shard_size": 2}},
           "train": {"architectures": ["resnet18", "instances"]}, "show": {"compare_backends": 0},
           "photos": {"field": photo_spec(folder)}}
    path = write_config(tmp_path / "c.yaml", cfg)
    r = snakemake("-n", "--configfile", str(path), workdir=tmp_path)
    assert r.returncode == 0, (r.stdout + r.stderr)[-2000:]
    assert planned_jobs(r)["evaluate_photos"] == 2 and planned_jobs(r)["report"] == 1
    Image.fromarray(np.zeros((40, 39), np.uint16)).save(folder / "b_mask.png")  # a mask of another size
    r = snakemake("-n", "--configfile", str(path), workdir=tmp_path)
    out = r.stdout + r.stderr
    assert r.returncode != 0 and "photos.field.masks: " in out and "b_mask.png is 39 x 40 px" in out, out[-2000:]
    assert not (tmp_path / "results").exists()


def test_a_reading_that_is_no_size_distribution_is_said_beside_its_figures(tmp_path):
    """A regressor far from its training images (here one whose head starts at d10 = -5 mm) reads a size
    below zero: evaluate-photos scores the photo all the same and says why its d-values are no measurement in
    the log, metrics.json, photos.csv and the report's photo table (marked, the warning under it)."""
    import torch

    from psdfactory.cli import main
    from psdfactory.learn.models import TargetStats, build_model
    from psdfactory.learn.runtime import save_model
    from psdfactory.report import photo_sections

    stats = dict(CNN_META["target_stats"], part_mean=[-5.0, 1.0, 1.0])
    torch.manual_seed(0)
    model, _ = build_model("resnet18", TargetStats(**stats), "none", size=64)
    save_model(tmp_path / "model.pt", model, dict(CNN_META, target_stats=stats))
    folder = make_photo_set(tmp_path / "ph", size=(80, 80))
    params = json.dumps({"photoset": photo_params(validate(photo_config(folder)), "field"), "precision": "fp32"})
    out = tmp_path / "eval"
    assert main(["evaluate-photos", "--params", params, "--model", str(tmp_path / "model.pt"), "--out-dir",
                 str(out)]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert all("a size <= 0: not a size distribution" in r["warning"] for r in m["photos"].values())
    assert all(not r["warning"].startswith("field/") for r in m["photos"].values())  # the photo is its row's
    rows = list(csv.DictReader(open(out / "photos.csv")))
    assert [r["warning"] for r in rows] == [m["photos"][r["image"]]["warning"] for r in rows]
    head, table, _, warned, misses = photo_sections({"resnet18": {"field": m}})["field"]["tables"]["resnet18"]
    assert misses == []  # a CNN finds no grains: no misses to sort
    d_col = head.index("d10 / d50 / d90 (mm)")
    assert all(row[d_col].startswith("⚠ ") for row in table[:2]) and not table[2][d_col].startswith("⚠")
    assert [w.split(":")[0] for w in warned] == ["⚠ a.png", "⚠ b.png"]
