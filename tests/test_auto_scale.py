"""predict's automatic scale (deploy.predict.choose_scale / read_at_scale): a photo whose grains
look larger than the model's training grains is read at the coarser scale that shows them at
that size, and measured in mm at the scale it was read at. No training: a stand-in estimator
whose apparent grain size is known, and the instance estimator on a synthetic "network" whose
size map gives each blob's diameter."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest
from PIL import Image
from scipy import ndimage

from psdfactory.config import AUTO_SCALE_MARGIN, AUTO_SCALE_PROBE, LEGACY_AUTO_SCALE_PROBE
from psdfactory.deploy import calibrate as calibrate_mod  # imported before any test patches predict.load_predictor
from psdfactory.deploy import predict
from psdfactory.deploy.predict import AUTO_SCALE_MIN_PX, choose_scale
from psdfactory.learn.instances.estimator import InstanceEstimator, grid_shape, readout_problems
from psdfactory.learn.instances.targets import encode_size

from .test_photos import META, NET_MM, local_maps, read_csv

pytest.importorskip("skimage")

GRAIN_PX, GRAIN_PX_MAX = 16.0, 24.0  # how large the stand-in models' validation grains look: median, largest
SIZES = {"grain_px": GRAIN_PX, "grain_px_max": GRAIN_PX_MAX, "grain_px_probe_max": GRAIN_PX_MAX,
         "grain_px_probe_scale": AUTO_SCALE_PROBE}


class Looks:
    """A stand-in estimator: at a factor s of the model's scale its grains look `true_px * s`, up
    to `most_px` (a network sees no grain larger than its receptive field); `outputs_at` records
    the factors asked."""

    def __init__(self, true_px: float | None, meta: dict | None = None, most_px: float = math.inf):
        self.true_px, self.most_px = true_px, most_px
        self.meta = dict(SIZES) if meta is None else meta
        self.auto_scale = True
        self.asked: list[float] = []

    def apparent_grain_px(self, outputs):
        return None if outputs is None else float(outputs)

    def outputs_at(self, scale: float):
        self.asked.append(scale)
        return [None if self.true_px is None else min(self.true_px * scale, self.most_px)]

    def choose(self, shorter_side: int = 1024) -> float:
        return choose_scale(self, shorter_side, self.outputs_at, "photo.jpg")


def test_grains_as_large_as_the_validation_grains_are_read_at_the_model_scale():
    for true_px in (GRAIN_PX, GRAIN_PX / 3, GRAIN_PX_MAX):
        looks = Looks(true_px)
        assert looks.choose() == 1.0
        assert looks.asked == [AUTO_SCALE_PROBE]  # one look at half the scale, no second


def test_larger_grains_are_read_where_they_look_as_large_as_the_median_validation_grain(caplog):
    with caplog.at_level(logging.INFO, logger="psdfactory.deploy.predict"):
        for true_px in (1.5 * GRAIN_PX_MAX, 4 * GRAIN_PX, 6 * GRAIN_PX):
            looks = Looks(true_px)
            assert looks.choose() == pytest.approx(GRAIN_PX / true_px)
            assert looks.asked[0] == AUTO_SCALE_PROBE and looks.asked[-1] == pytest.approx(GRAIN_PX / true_px)
    assert "photo.jpg: its grains look 96 px at the model's scale, larger than on any of the model's validation " \
           "images (at most 24 px): read at 0.167 x the model's scale, where they look 16 px" in caplog.text


def test_a_photo_too_small_for_the_probe_is_compared_at_the_model_scale_without_the_margin():
    """A shorter side under AUTO_SCALE_MIN_PX / AUTO_SCALE_PROBE: the first look is as coarse as the side allows and
    is compared with the validation grains' largest at the model's scale, as it is (the margin is the probe's)."""
    side = int(AUTO_SCALE_MIN_PX / AUTO_SCALE_PROBE) - 28  # 100 px: the look at 0.64
    looks = Looks(1.15 * GRAIN_PX_MAX)
    assert looks.choose(shorter_side=side) < 1.0
    assert looks.asked[0] == pytest.approx(AUTO_SCALE_MIN_PX / side)


def test_never_coarser_than_the_smallest_side_allows():
    looks = Looks(100 * GRAIN_PX)
    assert looks.choose(shorter_side=512) == pytest.approx(AUTO_SCALE_MIN_PX / 512)
    looks = Looks(100 * GRAIN_PX)  # a photo this small cannot be looked at coarser at all
    assert looks.choose(shorter_side=AUTO_SCALE_MIN_PX) == 1.0 and looks.asked == []


def test_the_second_look_corrects_the_probe():
    """Grains of 256 px under a network that sees none larger than 24 px: the probe (at 0.5) says
    they look 48 px, so 1/3; the look there says 72 px: read again at 2/9, nearer their size."""
    looks = Looks(16 * GRAIN_PX, most_px=24)
    assert looks.choose() == pytest.approx(GRAIN_PX / 72)
    assert looks.asked == [AUTO_SCALE_PROBE, pytest.approx(GRAIN_PX / 48)]
    # a scale within 10 % of one looked at already keeps that one (read_at_scale reads its outputs again)
    looks = Looks(66.0, most_px=16.5)  # the probe says 33 px: 0.485, the probe's 0.5
    assert looks.choose() == AUTO_SCALE_PROBE and looks.asked == [AUTO_SCALE_PROBE, AUTO_SCALE_PROBE]


def test_grains_a_little_larger_than_the_validation_grains_are_read_at_the_model_scale():
    """Under AUTO_SCALE_MARGIN times the validation grains' largest look at the probe: the model's scale."""
    looks = Looks(0.98 * AUTO_SCALE_MARGIN * GRAIN_PX_MAX)
    assert looks.choose() == 1.0 and looks.asked == [AUTO_SCALE_PROBE]
    looks = Looks(1.05 * AUTO_SCALE_MARGIN * GRAIN_PX_MAX)
    assert looks.choose() < 1.0


def test_a_model_of_before_the_probe_factor_probes_at_a_quarter_without_the_margin():
    """A model whose meta does not say at which factor its validation grains were probed was
    probed at a quarter of the scale, and is read as it was then."""
    legacy = {k: v for k, v in SIZES.items() if k != "grain_px_probe_scale"}
    looks = Looks(1.1 * GRAIN_PX_MAX, meta=legacy)
    assert looks.choose() == pytest.approx(GRAIN_PX / (1.1 * GRAIN_PX_MAX))
    assert looks.asked[0] == LEGACY_AUTO_SCALE_PROBE


def test_grains_the_probe_oversizes_but_the_second_look_finds_in_range_are_read_at_the_model_scale():
    class Oversized(Looks):  # the probe sees them twice as large as they are
        def outputs_at(self, scale):
            self.asked.append(scale)
            return [self.true_px * scale * (2.0 if scale == AUTO_SCALE_PROBE else 1.0)]

    looks = Oversized(20.0)
    assert looks.choose() == 1.0 and looks.asked == [AUTO_SCALE_PROBE, pytest.approx(GRAIN_PX / 40)]


def test_the_probe_is_compared_with_the_validation_grains_as_the_probe_saw_them():
    """A network that reads grains seen small as larger (here: all by 2x at the probe's scale):
    the validation grains' largest look at the probe (48 px) keeps a photo of 40 px grains,
    oversized to 80 by the probe, at the model's scale in one look; one of 120 px is read coarser."""
    class Oversized(Looks):
        def outputs_at(self, scale):
            self.asked.append(scale)
            return [self.true_px * scale * (2.0 if scale == AUTO_SCALE_PROBE else 1.0)]

    sizes = dict(SIZES, grain_px_probe_max=2 * 1.8 * GRAIN_PX_MAX)
    looks = Oversized(1.8 * GRAIN_PX_MAX, meta=sizes)
    assert looks.choose() == 1.0 and looks.asked == [AUTO_SCALE_PROBE]
    looks = Oversized(120.0, meta=sizes)
    assert looks.choose() == pytest.approx(GRAIN_PX / 120.0)


def test_no_look_without_the_setting_the_training_size_or_a_grain():
    looks = Looks(8 * GRAIN_PX, meta={})  # a model from before the grain sizes
    assert looks.choose() == 1.0 and looks.asked == []
    looks = Looks(8 * GRAIN_PX)
    looks.auto_scale = False  # predict without --auto-scale
    assert looks.choose() == 1.0 and looks.asked == []
    looks = Looks(None)  # no grain found at the probe's scale
    assert looks.choose() == 1.0 and looks.asked == [AUTO_SCALE_PROBE]


def test_apparent_grain_size_is_the_size_maps_median_over_grain_pixels():
    meta = dict(META, maps=["foreground", "boundary", "distance", "size"])
    est = InstanceEstimator(meta, None)
    maps = np.zeros((4, 64, 64), np.float32)
    maps[0, :20, :20] = 1.0  # 400 grain pixels: 300 of a 10 px grain, 100 of a 40 px one
    maps[3, :15, :20], maps[3, 15:20, :20] = encode_size(np.float64(10.0)), encode_size(np.float64(40.0))
    maps[3, 30:, 30:] = encode_size(np.float64(200.0))  # not grain pixels: not counted
    assert est.apparent_grain_px(maps) == pytest.approx(10.0, rel=1e-4)
    few = np.zeros_like(maps)
    few[0, :5, :5] = 1.0
    assert est.apparent_grain_px(few) is None  # too few grain pixels to say
    assert InstanceEstimator(dict(META), None).apparent_grain_px(maps[:3]) is None  # no size map


def test_a_model_meta_with_bad_grain_sizes_is_refused():
    meta = dict(META, maps=["foreground", "boundary", "distance", "size"], readout=None, tta="none")
    message = "grain_px, grain_px_max, grain_px_probe_max must be positive numbers (px), grain_px <= grain_px_max"
    assert message not in readout_problems(meta)  # a model from before them
    assert message not in readout_problems(dict(meta, **SIZES))
    for bad in (-1, 0, float("nan"), "12", True, None, GRAIN_PX_MAX + 1):
        assert message in readout_problems(dict(meta, **dict(SIZES, grain_px=bad))), bad
    assert message in readout_problems(dict(meta, grain_px=12.5, grain_px_max=30.0))  # one missing
    assert "auto_scale must be true or false (predict's default reading)" in readout_problems(
        dict(meta, **SIZES, auto_scale="yes"))
    assert not any("auto_scale" in p for p in readout_problems(dict(meta, **SIZES, auto_scale=True)))
    probe = "grain_px_probe_scale must be a factor of the scale between 0 and 1"
    assert probe not in readout_problems(dict(meta, **SIZES))
    for bad in (0, 1.0, 2, "0.5", float("nan")):
        assert probe in readout_problems(dict(meta, **dict(SIZES, grain_px_probe_scale=bad))), bad


# ---- through predict, on the instance estimator -------------------------------------------------


def blob_maps(x) -> np.ndarray:
    """`local_maps` and a size map: each blob's equivalent-circle diameter (px) on its pixels."""
    maps = local_maps(x)
    out = []
    for m in maps:
        fg = m[0] > 0.5
        labels, n = ndimage.label(fg)
        area = np.bincount(labels.ravel(), minlength=n + 1).astype(float)
        size = np.where(fg, encode_size(np.sqrt(4 * area / math.pi))[labels], 0.0)
        out.append(np.concatenate([m, size[None].astype(np.float32)]))
    return np.stack(out)


def discs(side: int, diameter: float) -> np.ndarray:
    """A grey bed of `side` px with discs of `diameter` px on a grid, apart from each other."""
    rr, cc = np.indices((side, side))
    pitch = int(diameter * 1.6)
    image = np.zeros((side, side), np.uint8)
    for y in range(pitch // 2, side - pitch // 2, pitch):
        for x in range(pitch // 2, side - pitch // 2, pitch):
            image[(rr - y) ** 2 + (cc - x) ** 2 <= (diameter / 2) ** 2] = 200
    return np.repeat(image[:, :, None], 3, axis=2)


@pytest.fixture()
def sized_model(monkeypatch):
    calls: list = []

    def run(x):
        calls.append(tuple(x.shape[-2:]))
        return blob_maps(x)

    meta = dict(META, maps=["foreground", "boundary", "distance", "size"], **SIZES)
    monkeypatch.setattr(predict, "load_predictor", lambda path, device="cpu", runtime="torch":
                        InstanceEstimator(dict(meta), run))
    return calls


@pytest.mark.parametrize("auto", [True, False])
def test_large_grains_are_read_coarser_and_measured_in_mm_all_the_same(sized_model, tmp_path, caplog, auto):
    """Discs of 64 px (32 mm) under a model whose validation grains look 16 px (24 at most): read at a quarter of
    the model's scale (2 mm/px) with the automatic scale, at it without; the same grains, the
    same sizes in mm."""
    Image.fromarray(discs(512, 64)).save(tmp_path / "bed.png")
    with caplog.at_level(logging.INFO, logger="psdfactory.deploy.predict"):
        rows = predict.predict_files(tmp_path / "m.pt", [str(tmp_path / "bed.png")], mm_per_px=NET_MM,
                                     particles_out=tmp_path / "p.csv", auto_scale=auto)
    assert rows[0]["error"] == ""
    grains = [r for r in read_csv(tmp_path / "p.csv") if r["touches_edge"] == "False"]
    assert len(grains) == 25
    np.testing.assert_allclose([float(r["ecd_mm"]) for r in grains], 32.0, rtol=0.06)
    scale = float(grains[0]["mask_mm_per_px"])
    if auto:
        assert scale == pytest.approx(4 * NET_MM, rel=0.02)
        assert sized_model == [(256, 256), grid_shape(129, 129)]  # the probe, then ~a quarter: never the model's 512 px
        assert "bed.png: its grains look 6" in caplog.text
        assert "px at the model's scale, larger than on any of the model's validation images (at most 24 px): read " \
               "at 0.25" in caplog.text
    else:
        assert scale == pytest.approx(NET_MM) and sized_model == [(512, 512)]
        assert "x the model's scale" not in caplog.text


def test_grains_of_the_training_size_cost_one_small_look(sized_model, tmp_path):
    Image.fromarray(discs(512, 16)).save(tmp_path / "bed.png")
    rows = predict.predict_files(tmp_path / "m.pt", [str(tmp_path / "bed.png")], mm_per_px=NET_MM,
                                 particles_out=tmp_path / "p.csv", auto_scale=True)
    assert rows[0]["error"] == "" and sized_model == [(256, 256), (512, 512)]
    assert {float(r["mask_mm_per_px"]) for r in read_csv(tmp_path / "p.csv")} == {NET_MM}


def test_predict_auto_scale_flag(sized_model, tmp_path):
    """Off by default (the model's scale, one pass); --auto-scale reads the photo of large grains coarser."""
    from psdfactory.cli import main

    Image.fromarray(discs(256, 64)).save(tmp_path / "bed.png")
    args = ["predict", "--model", "m.pt", "--mm-per-px", str(NET_MM), "--particles", str(tmp_path / "p.csv")]
    assert main([*args, str(tmp_path / "bed.png")]) == 0
    assert sized_model == [(256, 256)]
    sized_model.clear()
    assert main([*args, "--auto-scale", str(tmp_path / "bed.png")]) == 0
    assert sized_model[0] == (128, 128) and (256, 256) not in sized_model


@pytest.mark.parametrize("recipe", [True, False])
def test_the_models_recipe_sets_predicts_default_and_the_flags_override_it(sized_model, monkeypatch, tmp_path,
                                                                          caplog, recipe):
    """A model whose recipe says so (train.instances.auto_scale → its meta) is read at the grains' scale
    without --auto-scale, and at its own with --no-auto-scale; a model without it the other way round."""
    from psdfactory.cli import main

    meta = dict(META, maps=["foreground", "boundary", "distance", "size"], **SIZES, auto_scale=recipe)
    monkeypatch.setattr(predict, "load_predictor", lambda path, device="cpu", runtime="torch":
                        InstanceEstimator(dict(meta), lambda x: (sized_model.append(tuple(x.shape[-2:])),
                                                                 blob_maps(x))[1]))
    Image.fromarray(discs(256, 64)).save(tmp_path / "bed.png")
    args = ["predict", "--model", "m.pt", "--mm-per-px", str(NET_MM), "--particles", str(tmp_path / "p.csv")]
    coarser = (128, 128)
    for flag, auto in ((None, recipe), ("--auto-scale", True), ("--no-auto-scale", False)):
        sized_model.clear()
        caplog.clear()
        with caplog.at_level(logging.INFO, logger="psdfactory.deploy.predict"):
            assert main([*args, *([flag] if flag else []), str(tmp_path / "bed.png")]) == 0
        assert (sized_model[0] == coarser) is auto and ((256, 256) in sized_model) is not auto
        assert ("its recipe's train.instances.auto_scale" in caplog.text) is (flag is None and recipe)


def test_calibrate_reads_as_predict_will_and_predict_says_when_it_reads_otherwise(sized_model, monkeypatch,
                                                                                 tmp_path, caplog):
    """calibrate reads the references as predict does with the model (its recipe's default, or the flag given),
    records which, and predict warns where it reads a calibrated model's photos the other way."""
    from psdfactory.cli import main
    from psdfactory.learn import calibration, runtime

    meta = dict(META, maps=["foreground", "boundary", "distance", "size"], **SIZES, auto_scale=True)
    saved: dict = {}

    def stand_in(path, device="cpu", runtime="torch"):
        return InstanceEstimator(dict(saved.get("meta", meta)),
                                 lambda x: (sized_model.append(tuple(x.shape[-2:])), blob_maps(x))[1])

    monkeypatch.setattr(calibrate_mod, "load_predictor", stand_in)
    monkeypatch.setattr(runtime, "load_checkpoint", lambda path: {"meta": dict(meta), "state_dict": {}})
    monkeypatch.setattr(runtime, "meta_problems", lambda m: calibration.calibration_problems(m["calibration"]))
    monkeypatch.setattr(runtime, "write_torch", lambda path, obj: saved.update(obj))
    rows = ["image,d10_mm,d50_mm,d90_mm"]
    for k, d in enumerate((40, 52, 64)):
        Image.fromarray(discs(256, d)).save(tmp_path / f"bed{k}.png")
        rows.append(f"bed{k}.png,{d * NET_MM * 0.9},{d * NET_MM},{d * NET_MM * 1.1}")
    (tmp_path / "ref.csv").write_text("\n".join(rows) + "\n")
    args = ["calibrate", "--model", "m.pt", "--reference", str(tmp_path / "ref.csv"), "--mm-per-px", str(NET_MM),
            "--out", str(tmp_path / "cal.pt")]
    for flag, auto in ((None, True), ("--no-auto-scale", False)):
        saved.clear()
        sized_model.clear()
        assert main([*args, *([flag] if flag else []), str(tmp_path)]) == 0
        assert saved["meta"]["calibration"]["auto_scale"] is auto
        assert ((256, 256) in sized_model) is not auto  # read at the model's scale only without it
    monkeypatch.setattr(predict, "load_predictor", stand_in)
    assert saved["meta"]["auto_scale"] is False  # the calibrated model reads as its references were read
    for flag, warned in (("--auto-scale", True), ("--no-auto-scale", False), (None, False)):
        caplog.clear()
        with caplog.at_level(logging.INFO, logger="psdfactory.deploy.predict"):
            main(["predict", "--model", "cal.pt", "--mm-per-px", str(NET_MM), *([flag] if flag else []),
                  str(tmp_path / "bed0.png")])
        assert ("calibrated on photos read without the automatic scale" in caplog.text) is warned
    assert calibration.calibration_problems(dict(saved["meta"]["calibration"], auto_scale="yes")) == [
        "calibration.auto_scale must be true or false (how its photos were read)"]
    # without a scale the automatic one does nothing: nothing recorded, the model's default kept
    saved.clear()
    assert main([a for a in args if a not in ("--mm-per-px", str(NET_MM))] + [str(tmp_path)]) == 0
    assert "auto_scale" not in saved["meta"]["calibration"] and saved["meta"]["auto_scale"] is True


def test_train_instances_auto_scale_is_in_the_training_slice_only_when_on(tmp_path):
    """Off (the schema default) it leaves the slice as it was, so no model trained before it retrains;
    on, the instance settings carry it (into the meta). Runs that differ in it alone are one recipe."""
    from psdfactory.config import load_config, train_params, training_recipe
    from psdfactory.report import same_recipe

    gravel = load_config("config/gravel.yaml")
    before = train_params(gravel, "instances")
    before["settings"] = {k: v for k, v in before["settings"].items() if k != "auto_scale"}  # a run of before it
    assert training_recipe(before) == training_recipe(train_params(gravel, "instances"))
    assert same_recipe(dict(before, seed=7), gravel, "instances")
    assert not same_recipe(dict(before, settings=dict(before["settings"], lr=1.0)), gravel, "instances")
    from psdfactory.learn.instances.training import InstanceSettings

    assert "auto_scale" not in train_params(load_config("config/config.yaml"), "instances")["settings"]
    on = train_params(load_config("config/gravel.yaml"), "instances")["settings"]
    assert on["auto_scale"] is True and InstanceSettings.from_dict(on).auto_scale is True
    off = train_params(load_config("config/config.yaml"), "instances")["settings"]
    assert InstanceSettings.from_dict(off).auto_scale is False


def test_a_photo_set_reads_as_predict_auto_scale_where_it_says_so(tmp_path):
    from psdfactory.photoset import resolve

    Image.fromarray(discs(64, 16)).save(tmp_path / "a.png")
    spec = {"folder": str(tmp_path), "mm_per_px": 0.5}
    assert resolve("s", spec).auto_scale is None  # as predict reads with each model by default
    assert resolve("s", dict(spec, auto_scale=True)).auto_scale is True
    assert resolve("s", dict(spec, auto_scale=False)).auto_scale is False


def test_training_records_the_validation_grains_sizes_at_both_scales():
    """grain_sizes: the median and largest apparent size of the validation maps, and the largest
    of the same images looked at AUTO_SCALE_PROBE of the scale (here a network reading every image's
    grains as half its side), in px at the model's scale, with that factor; nothing where no grain is
    seen."""
    import torch

    from psdfactory.learn.instances.training import grain_sizes

    class Stand:
        seen: list = []

        def apparent_grain_px(self, maps):
            return maps

        def all_maps(self, x):
            self.seen.append(tuple(x.shape[-2:]))
            return [x.shape[-1] / 2] * len(x)

    x = torch.zeros((3, 3, 64, 64), dtype=torch.uint8)
    assert grain_sizes(Stand(), x, [10.0, 20.0, 30.0]) == {"grain_px": 20.0, "grain_px_max": 30.0,
                                                            "grain_px_probe_max": 64 * AUTO_SCALE_PROBE / 2
                                                            / AUTO_SCALE_PROBE,
                                                            "grain_px_probe_scale": AUTO_SCALE_PROBE}
    assert Stand.seen == [(64 * AUTO_SCALE_PROBE,) * 2]  # the images shrunk by the factor the meta records
    assert grain_sizes(Stand(), x, [None, None, None]) == {}


def test_auto_scale_says_when_it_cannot_apply(sized_model, tmp_path, caplog, monkeypatch):
    """Without --mm-per-px, or with a model that finds no grains, --auto-scale changes nothing:
    predict says so instead of ignoring it in silence."""
    Image.fromarray(discs(128, 16)).save(tmp_path / "bed.png")
    with caplog.at_level(logging.INFO, logger="psdfactory.deploy.predict"):
        predict.predict_files(tmp_path / "m.pt", [str(tmp_path / "bed.png")], auto_scale=True)
    assert "--auto-scale has no effect without --mm-per-px" in caplog.text
    caplog.clear()
    monkeypatch.setattr(InstanceEstimator, "finds_grains", False)
    with caplog.at_level(logging.INFO, logger="psdfactory.deploy.predict"):
        predict.predict_files(tmp_path / "m.pt", [str(tmp_path / "bed.png")], mm_per_px=NET_MM, auto_scale=True)
    assert "--auto-scale has no effect here" in caplog.text and "without --mm-per-px" not in caplog.text
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="psdfactory.deploy.predict"):
        predict.predict_files(tmp_path / "m.pt", [str(tmp_path / "bed.png")], mm_per_px=NET_MM)
    assert "--auto-scale" not in caplog.text
