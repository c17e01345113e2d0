"""Photos as people take them (docs/photos.md): large ones run in tiles and stitched, the particle
table in mm at the photo's scale, the PSD's weighting, EXIF orientation and non-square photos,
and the refusals (no scale, a reading the model cannot give). No training: the instance
estimator runs on a synthetic "network" whose maps depend on the image within a few pixels
(`local_maps`), as a trained one's do within its receptive field, or on an untrained network
where only the maps' arithmetic matters."""

from __future__ import annotations

import csv
import json
import logging
import math
import os
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from psdfactory import PsdError
from psdfactory.deploy import predict
from psdfactory.deploy.predict import (
    PARTICLE_COLUMNS,
    image_outputs,
    prepare,
    tile_spans,
    tiled_outputs,
)
from psdfactory.learn.data import IMAGENET_MEAN, IMAGENET_STD
from psdfactory.learn.estimator import Reading
from psdfactory.learn.instances.estimator import InstanceEstimator, grid_shape
from psdfactory.learn.instances.measure import measure_instances
from psdfactory.learn.instances.scoring import match_instances
from psdfactory.learn.instances.watershed import DEFAULT_POSTPROCESS
from psdfactory.psd import weighted_percentiles

pytest.importorskip("skimage")

NET_MM = 0.5  # mm per px at the synthetic model's network scale
META = {"arch": "instances", "mm_per_px": NET_MM, "image_resolution": 256, "input_size": 256,
        "postprocess": dict(DEFAULT_POSTPROCESS), "sieve_method": "min_feret", "size_definition": "sieve",
        "weighting": "number", "maps": ["foreground", "boundary", "distance"], "readouts": {}}
REACH = 12  # px: how far the synthetic maps see


def normalised_grey(v: float) -> float:
    """What a grey pixel of value v becomes after learn.data.normalise, averaged over the channels."""
    return float(np.mean([(v / 255 - m) / s for m, s in zip(IMAGENET_MEAN, IMAGENET_STD, strict=True)]))


def local_maps(x: torch.Tensor, grey_threshold: float = 100.0) -> np.ndarray:
    """A stand-in network: normalised N×3×H×W → foreground (brighter than `grey_threshold`),
    boundary (a foreground pixel whose 4-neighbour has another grey) and distance (to the nearest
    background or boundary pixel, clipped at REACH px and scaled to 0..1). A pixel's maps depend
    on the image within REACH + 1 px only."""
    from scipy import ndimage

    out = []
    for img in x.mean(1).numpy():
        fg = img > normalised_grey(grey_threshold)
        p = np.pad(img, 1, mode="edge")
        c = p[1:-1, 1:-1]
        diff = ((np.abs(c - p[:-2, 1:-1]) > 0.02) | (np.abs(c - p[2:, 1:-1]) > 0.02)
                | (np.abs(c - p[1:-1, :-2]) > 0.02) | (np.abs(c - p[1:-1, 2:]) > 0.02))
        bd = fg & diff
        dist = np.minimum(ndimage.distance_transform_edt(fg & ~bd), REACH) / REACH
        out.append(np.stack([fg, bd, dist]).astype(np.float32))
    return np.stack(out)


def synthetic_estimator(calls: list | None = None) -> InstanceEstimator:
    def run(x):
        if calls is not None:
            calls.append(tuple(x.shape[-2:]))
        return local_maps(x)

    return InstanceEstimator(dict(META), run)


def grain_bed(h: int, w: int, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(uint8 H×W×3 image, its instance mask): n discs of radius 4-20 px, each its own grey
    (110-250), painted in turn on a black ground (a later one hides part of an earlier one)."""
    rng = np.random.default_rng(seed)
    mask = np.zeros((h, w), np.int32)
    rr, cc = np.indices((h, w))
    for k in range(1, n + 1):
        y, x, r = rng.uniform(0, h), rng.uniform(0, w), rng.uniform(4, 20)
        mask[(rr - y) ** 2 + (cc - x) ** 2 <= r * r] = k
    greys = np.concatenate([[0], rng.permutation(np.linspace(110, 250, n)).round()])
    return np.repeat(greys[mask][:, :, None], 3, axis=2).astype(np.uint8), mask


def predict_image(est, x: torch.Tensor, mm_per_px: float, tile: int, where: str = ""):
    """The estimator's reading of one image at the network's scale, tiled as predict tiles it."""
    return est.read(image_outputs(est, x, tile, where), [mm_per_px])[0]


def as_input(image: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)[None]


@pytest.fixture()
def synthetic_model(monkeypatch):
    """predict's model loader gives the synthetic instance estimator; the calls to its network
    are counted (their input sizes)."""
    calls: list = []
    monkeypatch.setattr(predict, "load_predictor", lambda path, device="cpu", runtime="torch":
                        synthetic_estimator(calls))
    return calls


def read_csv(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


# ---- tiles ------------------------------------------------------------------------------------


def test_tile_spans_cover_the_axis_with_cores_and_keep_tiles_on_the_stride_grid():
    for n, tile, margin in ((1000, 256, 96), (257, 256, 96), (5000, 1024, 96), (300, 224, 96), (256, 256, 96)):
        spans = tile_spans(n, tile, margin)
        cores = [(a, b) for a, b, _, _ in spans]
        assert cores[0][0] == 0 and cores[-1][1] == n
        assert all(b == a2 for (_, b), (a2, _) in zip(cores[:-1], cores[1:], strict=True))  # side by side
        for a, b, t0, t1 in spans:
            assert t1 - t0 <= tile and t0 % 32 == 0 and t0 <= a < b <= t1
            assert a - t0 >= margin or t0 == 0  # a core sees `margin` px beyond it, or the image's edge
            assert t1 - b >= margin or t1 == n
    assert tile_spans(200, 256, 96) == [(0, 200, 0, 200)]
    assert len(tile_spans(4000, 1024, 96)) == 1 + math.ceil((4000 - 1024) / (1024 - 2 * 96))


@pytest.mark.parametrize(("stages", "tta"), [(2, "none"), (3, "none"), (2, "d4"), (3, "d4")])
def test_tiled_maps_of_the_network_equal_one_pass(stages, tta):
    """The instance network's maps, tile by tile with the estimator's margin, are those of one
    pass (its receptive field, for either trunk, is within the margin), on an image whose sides are
    off the stride grid, averaged over the eight turned and mirrored views too (each view's strides
    fall on the same pixels in a tile as in the whole image); with a margin too small (one view) they are not."""
    from psdfactory.learn.instances.net import RECEPTIVE_RADIUS_PX, net_from_meta
    from psdfactory.learn.runtime import torch_runner

    torch.manual_seed(0)
    meta = dict(META, maps=["foreground", "boundary", "distance", "size"], trunk_stages=stages, tta=tta)
    net = net_from_meta(meta).eval()
    for m in net.modules():  # an untrained network with batch-norm statistics that are not the identity
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.uniform_(-0.2, 0.2)
            m.running_var.uniform_(0.5, 2.0)
    est = InstanceEstimator(meta, torch_runner(InstanceEstimator(meta, None, net).inference_module()))
    assert est.tile_margin_px >= RECEPTIVE_RADIUS_PX[stages] and est.tile_margin_px % 32 == 0
    size = 2 * est.tile_margin_px + 96  # tiles of `size` px: two along each side of the image
    x = as_input(np.random.default_rng(1).integers(0, 256, (size + 40, size + 70, 3), dtype=np.uint8))
    one = est.outputs(x)
    tiled = tiled_outputs(est, x, size)
    margin = est.tile_margin_px
    assert len(est.views) == (8 if tta == "d4" else 1)
    assert len(tile_spans(size + 40, size, margin)) == len(tile_spans(size + 70, size, margin)) == 2
    exact = np.abs(tiled - one).max()
    assert tiled.shape == one.shape and exact < 1e-5, exact
    if tta == "none":  # one view: a margin inside the receptive field shows (eight views average it down)
        est.tile_margin_px = (RECEPTIVE_RADIUS_PX[stages] // 32 - 1) * 32
        short = np.abs(tiled_outputs(est, x, size - 64) - one).max()
        assert short > 100 * max(exact, 1e-7), (exact, short)


def test_forced_tiles_find_the_grains_of_one_pass(caplog):
    """A 540 × 480 px bed in tiles of 256 px (cores of 64 px: most grains cross a seam) finds
    the grains one pass finds, none cut at a seam or found twice."""
    image, truth = grain_bed(480, 540, 260)
    calls: list = []
    est = synthetic_estimator(calls)
    one = predict_image(est, as_input(image), NET_MM, tile=1024).grains
    assert calls == [grid_shape(480, 540)]  # one pass, on the stride grid
    calls.clear()
    with caplog.at_level(logging.INFO, logger="psdfactory.deploy.predict"):
        tiled = predict_image(est, as_input(image), NET_MM, tile=256, where="bed.png").grains
    n_tiles = len(tile_spans(480, 256, 96)) * len(tile_spans(540, 256, 96))
    assert len(calls) == n_tiles >= 30 and max(h * w for h, w in calls) <= 256 * 256
    assert f"bed.png: tile {n_tiles}/{n_tiles}" in caplog.text and "bed.png: tile 1/" in caplog.text
    match = match_instances(tiled.mask, one.mask)
    assert match.n_pred > 150 and match.f1 >= 0.98, (match.n_pred, match.n_true, match.f1)
    assert match_instances(one.mask, truth).f1 > 0.9  # and they are the grains drawn
    row_seams, col_seams = ([a for a, *_ in tile_spans(n, 256, 96)[1:]] for n in (480, 540))
    cell = np.searchsorted(row_seams, np.arange(480), side="right")[:, None] * 100 + np.searchsorted(
        col_seams, np.arange(540), side="right")[None, :]  # the tile whose core holds each pixel
    crossing = [k for k in np.unique(tiled.mask[tiled.mask > 0]) if len(np.unique(cell[tiled.mask == k])) > 1]
    assert len(crossing) > 60  # a third of them: grains spanning tiles are whole: one instance each
    np.testing.assert_allclose(sorted(tiled.sizes_mm), sorted(one.sizes_mm), rtol=0.02)
    np.testing.assert_allclose(tiled.calibrated, one.calibrated, rtol=0.02)


def test_a_tile_too_small_for_the_model_is_refused(synthetic_model, tmp_path, capsys):
    from psdfactory.cli import main

    Image.fromarray(grain_bed(64, 64, 5)[0]).save(tmp_path / "a.png")
    args = ["predict", "--model", "m.pt", "--mm-per-px", str(NET_MM), "--tile", "200", str(tmp_path / "a.png")]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "--tile 200: give a multiple of 32 of at least 224 px" in err and len(err.strip().splitlines()) == 1


# ---- the particle table -----------------------------------------------------------------------


def test_particle_table_measures_known_shapes_in_mm_at_the_photo_scale(synthetic_model, tmp_path):
    """A photo at 0.25 mm/px (twice the model's resolution) with a 20 × 8 mm rectangle, an
    ellipse of axes 24 × 10 mm and a disc cut by the border: the table gives their sizes in mm
    and their centroids in the photo's pixels, measured on the network's mask (0.5 mm/px)."""
    from psdfactory.cli import main

    photo_mm = 0.25
    h, w = 400, 480
    img = np.zeros((h, w, 3), np.uint8)
    img[100:132, 60:140] = 200  # 32 × 80 px = 8 × 20 mm, centroid (115.5, 99.5)
    rr, cc = np.indices((h, w))
    img[((rr - 250.5) / 20) ** 2 + ((cc - 300.5) / 48) ** 2 <= 1] = 200  # axes 96 × 40 px = 24 × 10 mm
    img[((rr - 380) ** 2 + (cc - 420) ** 2) <= 40**2] = 200  # cut by the bottom edge
    Image.fromarray(img).save(tmp_path / "shapes.png")
    out = tmp_path / "grains.csv"
    args = ["predict", "--model", "m.pt", "--mm-per-px", str(photo_mm), "--particles", str(out),
            "--masks", str(tmp_path / "masks"), str(tmp_path / "shapes.png")]
    assert main(args) == 0
    assert synthetic_model == [grid_shape(200, 240)]  # the network saw the photo at its own scale (on the grid)
    rows = read_csv(out)
    assert list(rows[0]) == PARTICLE_COLUMNS and len(rows) == 3
    assert all(c.endswith(("_mm", "_mm2", "_mm3", "_px")) for c in PARTICLE_COLUMNS if c not in
               ("image", "id", "touches_edge"))
    by_place = {(round(float(r["centroid_row_px"]) / 50), round(float(r["centroid_col_px"]) / 50)): r for r in rows}
    rect, ell = by_place[(2, 2)], by_place[(5, 6)]
    f = {k: float(v) for k, v in rect.items() if k not in ("image", "touches_edge")}
    assert f["centroid_row_px"] == pytest.approx(115.5, abs=1.0) and f["centroid_col_px"] == pytest.approx(99.5, abs=1)
    assert f["area_mm2"] == pytest.approx(160, rel=0.05)
    assert f["feret_min_mm"] == pytest.approx(8, abs=0.6) and f["feret_max_mm"] == pytest.approx(math.hypot(20, 8),
                                                                                                   abs=0.8)
    assert f["ellipse_minor_mm"] == pytest.approx(8 * 2 / math.sqrt(3), rel=0.05)  # a rectangle's second moments
    assert f["ecd_mm"] == pytest.approx(math.sqrt(4 * f["area_mm2"] / math.pi), rel=1e-3)
    assert f["sieve_size_mm"] == f["feret_min_mm"] and f["mask_mm_per_px"] == NET_MM  # the model's: min Feret
    assert f["volume_mm3"] == pytest.approx(2 / 3 * f["area_mm2"] * 0.65 * f["sieve_size_mm"], rel=1e-3)
    e = {k: float(v) for k, v in ell.items() if k not in ("image", "touches_edge")}
    assert e["ellipse_major_mm"] == pytest.approx(24, rel=0.03) and e["ellipse_minor_mm"] == pytest.approx(10, rel=0.05)
    assert e["area_mm2"] == pytest.approx(math.pi * 12 * 5, rel=0.05)
    assert e["feret_min_mm"] == pytest.approx(10, abs=0.6) and e["feret_max_mm"] == pytest.approx(24, abs=0.8)
    assert [r["touches_edge"] for r in (rect, ell)] == ["False", "False"]
    assert [r["touches_edge"] for r in rows if r not in (rect, ell)] == ["True"]
    with Image.open(tmp_path / "masks" / "shapes.png") as m:  # the mask at the photo's size
        assert m.size == (w, h)


def shapes_photo(h: int = 400, w: int = 480) -> np.ndarray:
    """A photo at 0.25 mm/px: an 8 × 20 mm rectangle (rows 100-131, columns 60-139), an ellipse of
    axes 24 × 10 mm centred at (250.5, 300.5) and a disc cut by the bottom edge."""
    img = np.zeros((h, w, 3), np.uint8)
    img[100:132, 60:140] = 200
    rr, cc = np.indices((h, w))
    img[((rr - 250.5) / 20) ** 2 + ((cc - 300.5) / 48) ** 2 <= 1] = 200
    img[((rr - 380) ** 2 + (cc - 420) ** 2) <= 40**2] = 200
    return img


def test_a_box_of_the_photo_reads_as_the_photo_cropped_to_it(synthetic_model, tmp_path, capsys):
    """predict --roi reads the box as a photo cropped to it would read (the same d-values and
    grains; the network sees the box alone, at the model's scale); the particle table keeps the
    photo's pixels, the mask is the box's; a grain cut by the box's side touches the edge; a box
    beyond the photo fails that photo's row, naming the box and the photo's size."""
    from psdfactory.cli import main

    img = shapes_photo()
    Image.fromarray(img).save(tmp_path / "shapes.png")
    left, top, right, bottom = 40, 80, 400, 320  # the rectangle and the ellipse, not the disc
    Image.fromarray(img[top:bottom, left:right]).save(tmp_path / "cropped.png")

    def run(name, *extra):
        out, table = tmp_path / f"{name}.csv", tmp_path / f"{name}_grains.csv"
        code = main(["predict", "--model", "m.pt", "--mm-per-px", "0.25", "--size-definition", "feret-min",
                     "--out", str(out), "--particles", str(table), "--masks", str(tmp_path / name), *extra])
        return code, read_csv(out), read_csv(table)

    code, boxed, boxed_grains = run("boxed", "--roi", f"{left},{top},{right},{bottom}", str(tmp_path / "shapes.png"))
    assert code == 0 and synthetic_model == [grid_shape(120, 180)]  # the box alone, at 0.5 mm/px
    code, cropped, cropped_grains = run("cropped", str(tmp_path / "cropped.png"))
    assert code == 0
    assert [boxed[0][t] for t in ("d10_mm", "d50_mm", "d90_mm")] == [cropped[0][t] for t in ("d10_mm", "d50_mm",
                                                                                              "d90_mm")]
    assert len(boxed_grains) == len(cropped_grains) == 2
    assert all(g["touches_edge"] == "False" for g in boxed_grains)
    for b, c in zip(sorted(boxed_grains, key=lambda g: g["id"]), sorted(cropped_grains, key=lambda g: g["id"]),
                    strict=True):
        assert float(b["centroid_row_px"]) == pytest.approx(float(c["centroid_row_px"]) + top, abs=0.05)
        assert float(b["centroid_col_px"]) == pytest.approx(float(c["centroid_col_px"]) + left, abs=0.05)
        assert b["feret_min_mm"] == c["feret_min_mm"]
    rect = min(boxed_grains, key=lambda g: float(g["area_mm2"]))
    assert float(rect["centroid_row_px"]) == pytest.approx(115.5, abs=1) and float(rect["centroid_col_px"]) == \
        pytest.approx(99.5, abs=1)  # in the photo's pixels
    with Image.open(tmp_path / "boxed" / "shapes.png") as m:
        assert m.size == (right - left, bottom - top)

    code, cut, cut_grains = run("cut", "--roi", "40,80,400,250", str(tmp_path / "shapes.png"))  # through the ellipse
    assert code == 0 and sorted(g["touches_edge"] for g in cut_grains) == ["False", "True"]

    code, beyond, _ = run("beyond", "--roi", "0,0,481,400", str(tmp_path / "shapes.png"))
    assert code == 1 and beyond[0]["d50_mm"] == ""
    assert "--roi 0,0,481,400 is not inside the photo (480 x 400 px" in beyond[0]["error"]
    assert "is not inside the photo" in capsys.readouterr().out


@pytest.mark.parametrize(("text", "says"), [("10,10,5,20", "RIGHT above LEFT"), ("0,0,100", "four whole numbers"),
                                            ("-1,0,10,10", "0 or more"), ("a,b,c,d", "four whole numbers"),
                                            ("0,0,1.5,10", "four whole numbers"), ("0,20,10,20", "BOTTOM above"),
                                            ("1_0,0,20,20", "four whole numbers")])
def test_a_box_that_is_not_one_is_refused_in_one_line(text, says, tmp_path, capsys):
    from psdfactory.cli import main
    from psdfactory.photoset import Region

    with pytest.raises(PsdError, match=says):
        Region.parse(text)
    if says != "four whole numbers":  # a box made in code is checked as one parsed
        with pytest.raises(PsdError, match=says):
            Region(*(int(p) for p in text.split(",")))
    (tmp_path / "a.png").write_bytes(b"not read")
    for command in (["predict"], ["calibrate", "--reference", "ref.csv", "--out", "c.pt"]):
        with pytest.raises(SystemExit) as e:
            main([*command, "--model", "m.pt", f"--roi={text}", str(tmp_path / "a.png")])
        assert e.value.code == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].count("--roi") == 1 and says in err[0], (command, err)  # named once


def test_a_box_is_cut_from_a_photo_decoded_reduced():
    """`Region.crop` takes the box's share of a photo decoded at a fraction of its size."""
    from psdfactory.photoset import Region

    full = np.arange(400 * 600).reshape(400, 600)
    box = Region(60, 100, 300, 260)
    part, frame = box.crop(full, (400, 600))
    assert (part == full[100:260, 60:300]).all() and frame == (100, 60, 160, 240)
    half = full[::2, ::2]
    part, frame = box.crop(half, (400, 600))
    assert (part == half[50:130, 30:150]).all() and frame == (100, 60, 160, 240)
    # a box off the decoded grid: the part is the box rounded to decoded pixels, and says where it lies
    fifth = full[::5, ::5]
    part, frame = Region(3, 2, 203, 183).crop(fifth, (400, 600))
    assert (part == fifth[0:37, 1:41]).all() and frame == (0, 5, 185, 200)
    assert box.size_hw == (160, 240)
    with pytest.raises(PsdError, match="not inside the photo"):
        box.need("p.jpg", lambda h, w: (h, w))(200, 600)
    assert box.need("p.jpg", lambda h, w: (h // 2, w // 2))(400, 600) == (200, 300)


# ---- weighting --------------------------------------------------------------------------------


def test_weighting_changes_the_percentiles_as_it_should():
    """Ten small discs and one large one (and one on the edge, left out): by number the large
    one is a tenth of the grains, by area most of the bed, by volume more still."""
    mask = np.zeros((200, 200), np.int32)
    rr, cc = np.indices(mask.shape)
    for k in range(10):
        mask[(rr - 20 - 16 * k) ** 2 + (cc - 20) ** 2 <= 5**2] = k + 1
    mask[(rr - 100) ** 2 + (cc - 120) ** 2 <= 40**2] = 11
    mask[(rr - 190) ** 2 + (cc - 190) ** 2 <= 30**2] = 12  # touches the edge
    m = measure_instances(mask, NET_MM)
    est = synthetic_estimator()
    reading = Reading(np.zeros(3), grains=type("R", (), {"measurements": m})())
    got = {w: est.in_definition(reading, "ecd", w, "known") for w in ("number", "area", "volume")}
    whole = ~m.touches_edge
    assert whole.sum() == 11
    for w, weights in (("number", None), ("area", m.area_mm2), ("volume", m.volume_mm3)):
        np.testing.assert_allclose(got[w], weighted_percentiles(m.eq_diameter_mm[whole],
                                                                None if weights is None else weights[whole]))
    small, large = m.eq_diameter_mm[0], m.eq_diameter_mm[10]
    assert got["number"][1] == pytest.approx(small, rel=1e-6)  # the median grain is a small one
    # by area the large grain holds 6/7 of the weight, by volume more: its midpoint comes nearer the median
    assert got["volume"][1] > got["area"][1] > 3 * small
    assert got["volume"][0] > got["area"][0] == pytest.approx(small, rel=1e-6)  # by volume the small are < 10 %
    assert got["number"][2] < large and got["area"][2] == got["volume"][2] == pytest.approx(large, rel=1e-6)


def test_predict_weighting_flag_and_resume(synthetic_model, tmp_path, capsys):
    """--weighting reaches the CSV (values and columns); a --resume of another weighting predicts
    every image again."""
    from psdfactory.cli import main

    for i in range(2):
        Image.fromarray(grain_bed(256, 256, 60, seed=i)[0]).save(tmp_path / f"bed{i}.png")
    out = tmp_path / "psd.csv"
    base = ["predict", "--model", "m.pt", "--size-definition", "feret-min", "--out", str(out)]
    assert main([*base, "--weighting", "number", str(tmp_path / "bed0.png"), str(tmp_path / "bed1.png")]) == 0
    number = read_csv(out)
    assert {(r["size_definition"], r["weighting"]) for r in number} == {("feret-min", "number")}
    assert len(synthetic_model) == 2
    assert main([*base, "--weighting", "area", "--resume", str(tmp_path / "bed0.png"), str(tmp_path / "bed1.png")]) == 0
    area = read_csv(out)
    assert len(synthetic_model) == 4  # rows of another reading are predicted again
    assert {r["weighting"] for r in area} == {"area"}
    for n, a in zip(number, area, strict=True):
        assert float(a["d50_mm"]) > float(n["d50_mm"])  # larger grains count more by area
    assert main([*base, "--weighting", "area", "--resume", str(tmp_path / "bed0.png"), str(tmp_path / "bed1.png")]) == 0
    assert len(synthetic_model) == 4  # the same reading: nothing predicted again
    assert "(feret-min, area-weighted)" in capsys.readouterr().out


def test_resume_predicts_again_when_the_particle_table_is_of_an_older_version(synthetic_model, tmp_path, caplog):
    """The skipped photos' grain rows are carried over from the previous table; a table with
    other columns (an older psdfactory's) cannot give them, so every photo is predicted again."""
    from psdfactory.cli import main

    for i in range(2):
        Image.fromarray(grain_bed(256, 256, 30, seed=i)[0]).save(tmp_path / f"bed{i}.png")
    grains, out = tmp_path / "grains.csv", tmp_path / "psd.csv"
    args = ["predict", "--model", "m.pt", "--out", str(out), "--particles", str(grains),
            str(tmp_path / "bed0.png"), str(tmp_path / "bed1.png")]
    assert main(args) == 0 and len(synthetic_model) == 2
    rows = read_csv(grains)
    assert main([*args, "--resume"]) == 0 and len(synthetic_model) == 2  # nothing predicted, rows kept
    assert read_csv(grains) == rows
    with open(grains, "w") as f:  # the table as an older predict wrote it
        f.write("image,id,area_mm2,sieve_size_mm,volume_mm3,touches_edge\n")
    with caplog.at_level(logging.INFO, logger="psdfactory"):
        assert main([*args, "--resume"]) == 0
    assert len(synthetic_model) == 4 and "every image is predicted again" in caplog.text
    assert read_csv(grains) == rows


def test_resume_keeps_no_row_read_at_another_scale_or_by_another_model(synthetic_model, tmp_path, caplog):
    """A --resume after the photos' scale, the model file, the automatic scale or the box changed predicts
    every image again (the rows do not say how they were read; `.<out>.reading.json` does), and
    keeps the rows of the same reading."""
    from psdfactory.cli import main
    from psdfactory.deploy.predict import reading_path

    for i in range(2):
        Image.fromarray(grain_bed(256, 256, 30, seed=i)[0]).save(tmp_path / f"bed{i}.png")
    out = tmp_path / "psd.csv"
    (tmp_path / "m.pt").write_bytes(b"a model")  # the fixture loads no file: this one is only looked at
    images = [str(tmp_path / "bed0.png"), str(tmp_path / "bed1.png")]

    def run(*extra: str) -> int:
        before = len(synthetic_model)
        caplog.clear()
        with caplog.at_level(logging.INFO, logger="psdfactory"):
            assert main(["predict", "--model", str(tmp_path / "m.pt"), "--out", str(out), *extra, *images]) == 0
        return len(synthetic_model) - before  # the network's calls: none where every row is kept

    assert run("--mm-per-px", "0.5") > 0
    stamp = json.loads(reading_path(out).read_text())
    assert stamp["mm_per_px"] == 0.5 and stamp["model"] == str(tmp_path / "m.pt")
    assert run("--mm-per-px", "0.5", "--resume") == 0  # the same reading: kept
    assert run("--mm-per-px", "0.4", "--resume") > 0  # another scale
    assert "mm_per_px 0.5 → 0.4" in caplog.text and "every image is predicted again" in caplog.text
    assert run("--mm-per-px", "0.4", "--no-auto-scale", "--resume") == 0  # the fixture's model has no auto scale
    assert run("--mm-per-px", "0.4", "--auto-scale", "--resume") > 0
    assert "auto_scale False → True" in caplog.text
    assert run("--mm-per-px", "0.4", "--auto-scale", "--roi", "0,0,200,256", "--resume") > 0  # a box of each
    assert "roi None → '0,0,200,256'" in caplog.text
    assert run("--mm-per-px", "0.4", "--auto-scale", "--roi", "0,0,200,256", "--resume") == 0
    assert run("--mm-per-px", "0.4", "--auto-scale", "--resume") > 0  # the box left out again
    os.utime(tmp_path / "m.pt", ns=(1, 1))  # the model file replaced (trained again in place)
    assert run("--mm-per-px", "0.4", "--auto-scale", "--resume") > 0 and "model_mtime_ns" in caplog.text
    reading_path(out).unlink()  # an older psdfactory's rows: how they were read is unknown
    assert run("--mm-per-px", "0.4", "--auto-scale", "--resume") > 0 and "missing or unreadable" in caplog.text
    assert len(read_csv(out)) == 2


def test_readings_the_model_cannot_give_are_refused_in_one_line(synthetic_model, tmp_path, capsys):
    from psdfactory.cli import main
    from psdfactory.deploy.predict import reading

    inst = dict(META, readouts={"esd": {}})
    assert reading(inst, "ecd", "volume") == {"size_definition": "ecd", "weighting": "volume"}
    assert reading(inst, "feret-max", None) == {"size_definition": "feret-max", "weighting": "number"}
    with pytest.raises(PsdError, match=r"--weighting area of sieve: this instances model reads sieve, esd number-"
                                       r"weighted; feret-min, feret-max, ecd number-, area-, volume-weighted"):
        reading(inst, "sieve", "area")
    cnn = {"arch": "resnet50", "size_definition": "sieve", "weighting": "number"}
    with pytest.raises(PsdError, match="reads sieve number-weighted .*train one with labels.weighting: volume"):
        reading(cnn, None, "volume")
    with pytest.raises(PsdError, match="a model that finds grains .* measures it"):
        reading(cnn, None, "area")
    Image.fromarray(grain_bed(64, 64, 5)[0]).save(tmp_path / "a.png")
    assert main(["predict", "--model", "m.pt", "--weighting", "volume", str(tmp_path / "a.png")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--weighting volume of sieve" in err[0] and "feret-min" in err[0]
    with pytest.raises(SystemExit):
        main(["predict", "--model", "m.pt", "--weighting", "mass", str(tmp_path / "a.png")])
    assert "invalid choice: 'mass'" in capsys.readouterr().err


# ---- photos as people take them ----------------------------------------------------------------


def test_a_photo_without_a_scale_is_refused_unless_it_is_the_training_images_size(synthetic_model, tmp_path,
                                                                                  monkeypatch):
    from psdfactory.cli import main

    photos = tmp_path / "photos"
    photos.mkdir()
    Image.fromarray(grain_bed(300, 400, 40)[0]).save(photos / "phone.jpg", quality=95)
    Image.fromarray(grain_bed(256, 256, 40)[0]).save(photos / "factory.png")  # the training images' size
    decoded = []
    real = Image.Image.load
    monkeypatch.setattr(Image.Image, "load", lambda self, *a: decoded.append(self.size) or real(self, *a))
    out = tmp_path / "p.csv"
    assert main(["predict", "--model", "m.pt", "--out", str(out), str(photos)]) == 1
    rows = {Path(r["image"]).name: r for r in read_csv(out)}
    assert rows["factory.png"]["error"] == "" and float(rows["factory.png"]["d50_mm"]) > 0
    err = rows["phone.jpg"]["error"]
    assert "400 x 300 px is not the model's field of view (256 x 256 px at 0.5 mm/px, 128 mm square)" in err
    assert "--mm-per-px" in err and "mm per px = its length in mm / its length in px" in err
    assert (400, 300) not in decoded  # refused from its header, before decoding
    assert main(["predict", "--model", "m.pt", "--mm-per-px", "0.5", str(photos / "phone.jpg")]) == 0


def test_a_non_square_photo_keeps_its_aspect_ratio():
    img = np.zeros((300, 400, 3), np.uint8)
    assert prepare(img, META, 0.25).shape == (1, 3, 150, 200)
    assert prepare(img, META, 1.0).shape == (1, 3, 600, 800)
    assert prepare(img, META, 0.5).shape == (1, 3, 300, 400)  # at the model's scale: as it is


def test_exif_orientation_is_honoured(synthetic_model, tmp_path):
    """A JPEG stored 240 wide × 160 high with EXIF orientation 6 (shown turned 90° clockwise):
    its mask is 160 wide × 240 high, and the grain stored at the top left lies at the top right
    of the upright photo, where the particle table puts it."""
    from psdfactory.cli import main

    stored = np.zeros((160, 240, 3), np.uint8)
    stored[20:60, 30:90] = 200  # 40 × 60 px, centre (39.5, 59.5) as stored
    exif = Image.Exif()
    exif[0x0112] = 6
    Image.fromarray(stored).save(tmp_path / "phone.jpg", exif=exif.tobytes(), quality=95)
    assert main(["predict", "--model", "m.pt", "--mm-per-px", str(NET_MM), "--masks", str(tmp_path / "m"),
                 "--particles", str(tmp_path / "g.csv"), str(tmp_path / "phone.jpg")]) == 0
    assert synthetic_model == [grid_shape(240, 160)]
    with Image.open(tmp_path / "m" / "phone.png") as im:
        assert im.size == (160, 240)
        mask = np.asarray(im)
    (row,) = read_csv(tmp_path / "g.csv")
    # turned 90° clockwise: stored (r, c) → upright (c, 159 - r)
    assert float(row["centroid_row_px"]) == pytest.approx(59.5, abs=1) and float(row["centroid_col_px"]) == \
        pytest.approx(159 - 39.5, abs=1)
    assert mask[60, 120] > 0 and mask[60, 40] == 0
    assert float(row["feret_min_mm"]) == pytest.approx(40 * NET_MM, abs=1) and float(row["feret_max_mm"]) > 60 * NET_MM
    # a box is in px of the upright photo: its right half holds the grain, at the same place in the table
    assert main(["predict", "--model", "m.pt", "--mm-per-px", str(NET_MM), "--roi", "80,0,160,240", "--masks",
                 str(tmp_path / "boxed"), "--particles", str(tmp_path / "b.csv"), str(tmp_path / "phone.jpg")]) == 0
    assert synthetic_model[-1] == grid_shape(240, 80)
    with Image.open(tmp_path / "boxed" / "phone.png") as im:
        assert im.size == (80, 240)
    (boxed,) = read_csv(tmp_path / "b.csv")
    assert float(boxed["centroid_row_px"]) == pytest.approx(float(row["centroid_row_px"]), abs=0.5)
    assert float(boxed["centroid_col_px"]) == pytest.approx(float(row["centroid_col_px"]), abs=0.5)


def test_a_large_photo_runs_in_tiles_through_predict(synthetic_model, tmp_path, caplog):
    from psdfactory.cli import main

    image, _ = grain_bed(480, 640, 200)
    Image.fromarray(image).save(tmp_path / "big.png")
    out = tmp_path / "grains.csv"
    with caplog.at_level(logging.INFO, logger="psdfactory"):
        assert main(["predict", "--model", "m.pt", "--mm-per-px", str(NET_MM), "--tile", "320", "--particles",
                     str(out), "--masks", str(tmp_path / "m"), str(tmp_path / "big.png")]) == 0
    n = len(tile_spans(480, 320, 96)) * len(tile_spans(640, 320, 96))
    assert len(synthetic_model) == n > 1 and f"tile {n}/{n}" in caplog.text
    rows = read_csv(out)
    with Image.open(tmp_path / "m" / "big.png") as im:
        mask = np.asarray(im)
    assert sorted(int(r["id"]) for r in rows) == sorted(set(np.unique(mask)) - {0})
    est = synthetic_estimator()
    one = predict_image(est, as_input(image), NET_MM, tile=1024).grains
    assert match_instances(mask, one.mask).f1 >= 0.98
