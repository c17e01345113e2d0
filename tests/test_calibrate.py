"""`psdfactory calibrate`: the correction's math (learn/calibration.py: fit, apply, leave-one-out,
the meta block's validation), the command's refusals (deploy/calibrate.py), and end to end on a
tiny trained model: calibrate, the written model, predict (.pt and an ONNX export) applying it."""

import csv
import json
import logging
import re
import shutil
import sys
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from psdfactory import PsdError
from psdfactory.learn import calibration as cal
from psdfactory.psd import FOOTPRINT_DEFINITIONS, SOLID_DEFINITIONS

from .test_training import dataset, param_slice  # noqa: F401  (the fixture and the parameter slice)

PLUGINS = Path(__file__).parent / "plugins"


def references(n: int, seed: int = 0) -> np.ndarray:
    """n plausible d10 <= d50 <= d90 (mm)."""
    rng = np.random.default_rng(seed)
    d50 = rng.uniform(2.0, 20.0, n)
    return np.stack([d50 * rng.uniform(0.3, 0.6, n), d50, d50 * rng.uniform(1.5, 2.5, n)], axis=1)


A, B = np.array([0.8, 1.25, 0.6]), np.array([0.3, -0.4, 1.5])  # the "model": predicted = A * true + B


def block_of(true: np.ndarray, pred: np.ndarray) -> dict:
    names = [f"s{i}.png" for i in range(len(true))]
    return cal.calibration_block(names, pred, true, "sieve", "number", None, "2025-01-01T00:00:00+00:00", "0.1.0")


# ---- the math ------------------------------------------------------------------------------


def test_an_exact_affine_model_is_corrected_exactly_in_fit_and_in_leave_one_out():
    true = references(6)
    pred = A * true + B
    params = cal.fit(pred, true)
    assert params["method"] == "affine"
    np.testing.assert_allclose(params["slope"], 1 / A, rtol=1e-9)
    np.testing.assert_allclose(params["intercept"], -B / A, rtol=1e-9)
    np.testing.assert_allclose(cal.apply(params, pred), true, rtol=1e-9)
    np.testing.assert_allclose(cal.leave_one_out(pred, true), true, rtol=1e-9)
    block = block_of(true, pred)
    for name in ("d10", "d50", "d90"):
        assert block["loo"][name]["mape_pct"] < 1e-6 and block["loo"][name]["mae_mm"] < 1e-6
        assert block["uncalibrated"][name]["mape_pct"] > 5  # the model alone is off
    assert cal.calibration_problems(block) == []
    json.dumps(block)  # plain data: a meta.json holds it as it is


def test_with_noise_leave_one_out_is_worse_than_the_in_fit_error_and_better_than_none():
    true = references(8, seed=1)
    pred = A * true + B + np.random.default_rng(2).normal(0, 0.4, true.shape)
    block = block_of(true, pred)
    for name in ("d10", "d50", "d90"):
        loo, fit, raw = (block[k][name]["mae_mm"] for k in ("loo", "fit", "uncalibrated"))
        assert fit < loo < raw, (name, fit, loo, raw)


def test_isotonic_from_ten_references_is_monotone_and_extrapolates_linearly():
    assert cal.method_for(9) == "affine" and cal.method_for(10) == "isotonic"
    true = references(12, seed=3)
    pred = A * true + B
    params = cal.fit(pred, true)
    assert params["method"] == "isotonic"
    np.testing.assert_allclose(cal.apply(params, pred), true, rtol=1e-9)  # exact on its knots
    np.testing.assert_allclose(params["slope_out"], 1 / A, rtol=1e-9)  # the chord of an exact line: 1/A
    beyond = np.array([[0.1, 0.5, 1.0], [40.0, 80.0, 160.0]])  # below and above every reference
    np.testing.assert_allclose(cal.apply(params, A * beyond + B), beyond, rtol=1e-9)
    # a monotone but curved model, and a noisy one: the correction never decreases
    curved = np.sqrt(true) * 2
    noisy = curved + np.random.default_rng(4).normal(0, 0.3, true.shape)
    for p in (curved, noisy):
        fitted = cal.fit(p, true)
        grid = np.linspace(p.min() - 1, p.max() + 1, 200)
        for k in range(3):
            x = np.asarray(fitted["x"][k])
            assert (np.diff(x) > 0).all() and (np.diff(fitted["y"][k]) >= 0).all()
            ys = cal._apply_isotonic(grid, fitted["x"][k], fitted["y"][k], fitted["slope_out"][k])
            assert (np.diff(ys) >= -1e-12).all()
    np.testing.assert_allclose(cal.apply(cal.fit(curved, true), curved), true, rtol=1e-9)
    loo = cal.leave_one_out(curved, true)
    assert np.isfinite(loo).all() and not np.allclose(loo, true)  # the left-out point is not in the fit


def test_tied_predictions_are_pooled_and_the_corrected_d_values_stay_ordered():
    true = references(10, seed=5)
    true[1] = true[0] * 1.001
    pred = A * true + B
    pred[1] = pred[0]  # two samples the model cannot tell apart
    params = cal.fit(pred, true)
    assert len(params["x"][1]) == 9 and params["y"][1][np.searchsorted(params["x"][1], pred[0, 1])] == \
        pytest.approx((true[0, 1] + true[1, 1]) / 2)
    # corrections that would cross (d10's map raises, d90's lowers): sorted after the correction
    params = {"method": "affine", "slope": [3.0, 1.0, 0.2], "intercept": [0.0, 0.0, 0.0]}
    out = cal.apply(params, np.array([[2.0, 3.0, 4.0], [1.0, 1.5, 2.0]]))
    np.testing.assert_allclose(out, [[0.8, 3.0, 6.0], [0.4, 1.5, 3.0]])
    assert (np.diff(out, axis=1) >= 0).all()


def test_a_model_that_reads_the_same_for_every_reference_is_refused():
    true = references(5)
    pred = A * true + B
    pred[:, 1] = 4.2
    with pytest.raises(PsdError, match="same d50 .4.2 mm. for every reference"):
        cal.fit(pred, true)


@pytest.mark.parametrize("edit, says", [
    (lambda n, v: (n[:2], v[:2]), "2 reference sample.s.; calibration needs at least 3"),
    (lambda n, v: (n[:2] + [n[0]] + n[3:], v), "duplicate images .a.png."),
    (lambda n, v: (n, np.where(np.arange(12).reshape(4, 3) == 4, np.nan, v)), "not finite numbers: b.png .d50_mm=nan"),
    (lambda n, v: (n, np.where(np.arange(12).reshape(4, 3) == 8, np.inf, v)), "not finite.*c.png .d90_mm=inf"),
    (lambda n, v: (n, np.where(np.arange(12).reshape(4, 3) == 9, -1.0, v)), "must be positive.*d.png .d10_mm=-1"),
    (lambda n, v: (n, np.where(np.arange(12).reshape(4, 3) == 0, 0.0, v)), "must be positive.*a.png .d10_mm=0"),
    (lambda n, v: (n, v[:, ::-1]), "d10 <= d50 <= d90 violated.*a.png .3, 2, 1."),
])
def test_bad_references_are_refused_in_one_line_naming_them(edit, says):
    names = ["a.png", "b.png", "c.png", "d.png"]
    values = np.array([[1.0, 2, 3], [2, 3, 4], [3, 4, 5], [4, 5, 6]])
    with pytest.raises(PsdError, match=says) as e:
        cal.check_references(*edit(names, values))
    assert "\n" not in str(e.value)


def test_the_meta_block_is_validated_and_a_corrupt_one_is_refused():
    true = references(12, seed=6)
    good = block_of(true, A * true + B)
    assert cal.calibration_problems(good) == []
    for corrupt, says in [
        ({"method": "spline"}, "calibration.method"),
        ({"n": 2}, "calibration.n"),
        ({"size_definition": "weight"}, "calibration.size_definition"),
        ({"params": {**good["params"], "slope_out": [1.0, 2.0]}}, "slope_out"),
        ({"params": {**good["params"], "x": [good["params"]["x"][0][::-1]] + good["params"]["x"][1:]}},
         "x must increase"),
        ({"references": good["references"][:5]}, "calibration.references"),
        ({"loo": {"d10": {"mape_pct": "a lot"}}}, "calibration.loo"),
        ({"mm_per_px": -1}, "calibration.mm_per_px"),
    ]:
        problems = cal.calibration_problems({**good, **corrupt})
        assert problems and says in problems[0], (corrupt, problems)
    assert cal.calibration_problems([1, 2]) == ["calibration must be a dict"]


def test_the_hook_applies_only_in_the_calibrations_definition_and_refuses_a_far_off_reading():
    true = references(5, seed=7)
    block = block_of(true, A * true + B)
    meta = {"calibration": block}
    sieve = {"size_definition": "sieve", "weighting": "number"}
    d = A * np.array([1.0, 2.0, 4.0]) + B
    np.testing.assert_allclose(cal.apply_calibration(meta, sieve, d), [1.0, 2.0, 4.0])
    assert cal.apply_calibration({}, sieve, d) is d  # an uncalibrated model: as read
    note = cal.calibration_note(meta, sieve)
    assert note.startswith("calibrated on 5 references (affine, sieve size, number-weighted") and "LOO error" in note
    for other in ({"size_definition": "esd", "weighting": "number"},
                  {"size_definition": "sieve", "weighting": "volume"}):
        with pytest.raises(PsdError, match="calibrated for the sieve size, number-weighted; its correction does not "
                                           "apply"):
            cal.apply_calibration(meta, other, d)
        with pytest.raises(PsdError, match="--size-definition sieve"):
            cal.calibration_note(meta, other)
    with pytest.raises(PsdError, match="calibrated d-values are not positive"):
        cal.apply_calibration(meta, sieve, np.array([0.01, 0.02, 0.03]) - 5)


def test_the_basis_is_the_references_reading_else_the_grains_in_their_weighting_else_the_models_own():
    grains = {("sieve", "number"), *((d, w) for d in ("feret-min", "ecd") for w in ("number", "area", "volume"))}
    finder = (lambda d, w: (d, w) in grains), (lambda d: "number")
    cnn = (lambda d, w: (d, w) == ("sieve", "number")), (lambda d: "number")

    def basis(wanted, model):
        return cal.basis_for(dict(zip(("size_definition", "weighting"), wanted, strict=True)), *model)

    assert basis(("sieve", "number"), finder) == {"size_definition": "sieve", "weighting": "number"}
    assert basis(("sieve", "volume"), finder) == {"size_definition": "feret-min", "weighting": "volume"}
    assert basis(("b-axis", "area"), finder) == {"size_definition": "feret-min", "weighting": "area"}
    assert basis(("esd", "volume"), finder) == {"size_definition": "ecd", "weighting": "volume"}
    assert basis(("ecd", "volume"), finder) == {"size_definition": "ecd", "weighting": "volume"}
    assert basis(("sieve", "volume"), cnn) == {"size_definition": "sieve", "weighting": "number"}  # maps weightings


def test_a_block_records_its_basis_and_the_hook_corrects_that_reading():
    true = references(5, seed=8)
    names = [f"s{i}.png" for i in range(5)]
    grains = {"size_definition": "feret-min", "weighting": "volume"}
    block = cal.calibration_block(names, A * true + B, true, "sieve", "volume", None, "2025-01-01T00:00:00+00:00",
                                  "0.1.0", basis=grains)
    assert block["basis"] == grains and cal.calibration_problems(block) == []
    same = cal.calibration_block(names, A * true + B, true, "sieve", "volume", None, "2025-01-01T00:00:00+00:00",
                                 "0.1.0", basis={"size_definition": "sieve", "weighting": "volume"})
    assert "basis" not in same  # a block without one corrects the reading it gives
    assert cal.basis_of(same) == {"size_definition": "sieve", "weighting": "volume"}
    for bad in ({"size_definition": "weight", "weighting": "volume"}, {"size_definition": "ecd"}, "ecd", None):
        problems = cal.calibration_problems({**block, "basis": bad})
        assert problems and "calibration.basis" in problems[0]
    problems = cal.calibration_problems({**block, "weighting": "mass"})  # what the rows would be labelled: refused
    assert problems and "calibration.weighting one of number, area, volume" in problems[0]
    assert set(cal.FOOTPRINT_FOR) == set(SOLID_DEFINITIONS) and set(cal.FOOTPRINT_FOR.values()) <= set(
        FOOTPRINT_DEFINITIONS)
    meta, sieve_v = {"calibration": block}, {"size_definition": "sieve", "weighting": "volume"}
    assert cal.source_reading(meta, sieve_v) == grains and cal.source_reading({}, sieve_v) == sieve_v
    with pytest.raises(PsdError, match="calibrated for the sieve size, volume-weighted"):
        cal.source_reading(meta, {"size_definition": "sieve", "weighting": "number"})
    note = cal.calibration_note(meta, sieve_v)
    assert "sieve size, volume-weighted, corrected from its feret-min reading, volume-weighted" in note
    with pytest.raises(PsdError, match="predict without --size-definition and --weighting \\(or with --size-definition "
                                       "sieve --weighting volume\\)"):
        cal.apply_calibration(meta, {"size_definition": "sieve", "weighting": "number"}, np.ones(3))
    # a calibrated model reads in its calibration's definition and weighting unless told otherwise
    from psdfactory.learn.estimator import Estimator, reading_of

    model = {"arch": "x", "size_definition": "sieve", "weighting": "number"}
    assert reading_of(Estimator, model, None) == {"size_definition": "sieve", "weighting": "number"}
    assert reading_of(Estimator, {**model, "calibration": block}, None) == sieve_v
    assert reading_of(Estimator, {**model, "calibration": block}, "sieve", "volume") == sieve_v
    with pytest.raises(PsdError, match="--weighting volume of sieve"):
        reading_of(Estimator, model, "sieve", "volume")  # uncalibrated, it reads number-weighted sieve sizes only


# ---- the command's inputs ------------------------------------------------------------------


def write_csv(path: Path, rows: list[list], header=("image", "d10_mm", "d50_mm", "d90_mm")) -> Path:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        w.writerows(rows)
    return path


def test_the_reference_table_is_read_and_its_problems_named(tmp_path):
    from psdfactory.deploy.calibrate import read_references

    rows = [["a.png", 1, 2, 3], ["b.png", 2, 3, 4], ["c.png", 3, 4, 5]]
    names, values = read_references(write_csv(tmp_path / "ok.csv", rows + [["", "", "", ""]],
                                              header=("image", "d10_mm", "d50_mm", "d90_mm", "note")))
    assert names == ["a.png", "b.png", "c.png"] and values.shape == (3, 3) and values[2, 2] == 5
    bad = [
        (write_csv(tmp_path / "col.csv", rows, header=("image", "d10_mm", "d50", "d90_mm")),
         r"missing column\(s\) d50_mm \(found: image, d10_mm, d50, d90_mm\)"),
        (write_csv(tmp_path / "num.csv", rows[:2] + [["c.png", 3, "four", 5]]),
         r"line 4 \(c.png\): d50_mm is 'four', not a number"),
        (write_csv(tmp_path / "empty.csv", rows[:2] + [["c.png", 3, "", 5]]), r"line 4 \(c.png\): d50_mm is empty"),
        (write_csv(tmp_path / "two.csv", rows[:2]), "2 reference sample"),
        (write_csv(tmp_path / "dup.csv", rows + [["b.png", 2, 3, 4]]), r"duplicate images \(b.png\)"),
        (write_csv(tmp_path / "nan.csv", rows + [["d.png", 2, "nan", 4]]), r"not finite numbers: d.png"),
        (tmp_path / "absent.csv", "file not found"),
    ]
    for path, says in bad:
        with pytest.raises(PsdError, match=says):
            read_references(path)


def test_references_match_images_by_path_then_name_then_stem_one_to_one(tmp_path):
    from psdfactory.deploy.calibrate import match_images

    (tmp_path / "x").mkdir()
    (tmp_path / "y").mkdir()
    files = [tmp_path / "x" / "a.png", tmp_path / "x" / "b.jpg", tmp_path / "y" / "c.png", tmp_path / "y" / "a.png"]
    for f in files:
        f.write_bytes(b"")
    ref = tmp_path / "ref.csv"
    got = match_images([str(files[0]), "y/a.png", "b.jpg", "c"], files, ref)  # path; relative to ref.csv; name; stem
    assert got == [files[0], files[3], files[1], files[2]]
    with pytest.raises(PsdError) as e:
        match_images([str(files[0]), "b.png", "c.tif", "zzz", "qqq"], files, ref)
    msg = str(e.value)  # b.png matches b.jpg by stem, c.tif c.png by stem
    assert "references with no image: zzz, qqq" in msg and f"images with no reference: {files[3]}" in msg
    with pytest.raises(PsdError, match=r"references matching several images \(give their paths\): a.png \(2 images"):
        match_images(["a.png", "b.jpg", "c.png"], files, ref)
    with pytest.raises(PsdError, match=r"matched by more than one reference: .*b.jpg \(b.jpg, b\)"):
        match_images([str(files[0]), "b.jpg", "b", "c.png", str(files[3])], files, ref)
    with pytest.raises(PsdError, match="images given more than once"):
        match_images(["a", "b"], [files[1], tmp_path / "x" / ".." / "x" / "b.jpg"], ref)


# ---- end to end on a tiny trained model ----------------------------------------------------


@pytest.fixture(scope="module")
def model(dataset, tmp_path_factory):  # noqa: F811
    """A meancolour model (tests/plugins: the cheapest there is) trained on the tiny dataset, its 10
    images copied under their scene names, and the references: the scenes' labels."""
    from psdfactory.learn.train import train_from_params

    out = tmp_path_factory.mktemp("cal")
    with pytest.MonkeyPatch.context() as mp:
        mp.syspath_prepend(str(PLUGINS))
        train_from_params(param_slice(arch="meancolour", epochs=3), dataset, out / "m")
        sys.modules.pop("psd_meancolour", None)
    rows = pq.read_table(next((dataset / "tiny" / "manifest" / "scenes").glob("*.parquet"))).to_pylist()
    photos = out / "photos"
    photos.mkdir()
    for r in rows:
        shutil.copy(dataset / r["image_path"], photos / f"{r['scene_id']}.png")
    labels = {r["scene_id"]: [r["d10_mm"], r["d50_mm"], r["d90_mm"]] for r in rows}
    return out / "m" / "model.pt", photos, labels, rows[0]["size_definition"]


@pytest.fixture
def plugin(monkeypatch):
    monkeypatch.syspath_prepend(str(PLUGINS))
    yield
    sys.modules.pop("psd_meancolour", None)


def test_calibrate_writes_the_model_with_its_calibration_and_predict_applies_it(model, plugin, tmp_path, capsys,
                                                                               caplog):
    from psdfactory.cli import main
    from psdfactory.deploy.export import export
    from psdfactory.deploy.predict import predict_files
    from psdfactory.learn.runtime import load_checkpoint

    model_pt, photos, labels, definition = model
    ref = write_csv(tmp_path / "ref.csv", [[k, *v] for k, v in labels.items()])  # by stem: scene ids
    out = tmp_path / "calibrated.pt"
    assert main(["calibrate", "--model", str(model_pt), "--reference", str(ref), "--out", str(out), str(photos)]) == 0
    table = capsys.readouterr().out
    assert "calibration on 10 references: isotonic" in table and "leave-one-out" in table
    lines = table.splitlines()
    assert [ln.split()[0] for ln in lines[-3:]] == ["d10", "d50", "d90"]

    before, after = load_checkpoint(model_pt), load_checkpoint(out)
    assert before["state_dict"].keys() == after["state_dict"].keys()
    assert all((before["state_dict"][k] == after["state_dict"][k]).all() for k in before["state_dict"])
    c = after["meta"]["calibration"]
    assert {k: v for k, v in after["meta"].items() if k != "calibration"} == before["meta"]
    assert c["method"] == "isotonic" and c["n"] == 10 and c["size_definition"] == definition
    assert c["weighting"] == "number" and c["mm_per_px"] is None and c["version"] and c["date"][:2] == "20"
    assert sorted(r["image"] for r in c["references"]) == sorted(labels)
    assert all(r["file"] == str(photos / f"{r['image']}.png") for r in c["references"])
    assert all(isinstance(v, float) for xs in c["params"]["x"] for v in xs)
    assert cal.calibration_problems(c) == []
    # the table is the block's numbers
    d50 = next(ln for ln in lines if ln.startswith("d50")).split()
    assert float(d50[1]) == pytest.approx(c["uncalibrated"]["d50"]["mape_pct"], abs=0.05)
    assert float(d50[3]) == pytest.approx(c["loo"]["d50"]["mape_pct"], abs=0.05)

    images = sorted(str(p) for p in photos.glob("*.png"))
    raw = predict_files(model_pt, images)
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="psdfactory"):
        corrected = predict_files(out, images)
    notes = [r.message for r in caplog.records if r.message.startswith("calibrated on 10 references (isotonic")]
    assert len(notes) == 1 and "LOO error" in notes[0]
    raw_d = np.array([[r[t] for t in ("d10_mm", "d50_mm", "d90_mm")] for r in raw])
    got = np.array([[r[t] for t in ("d10_mm", "d50_mm", "d90_mm")] for r in corrected])
    np.testing.assert_allclose(got, cal.apply(c["params"], raw_d), rtol=1e-6)
    by_ref = {r["file"]: [r["d10_mm"], r["d50_mm"], r["d90_mm"]] for r in c["references"]}
    want = np.array([by_ref[i] for i in images])
    for k, name in enumerate(("d10", "d50", "d90")):  # on its own references: the in-fit error it recorded
        assert np.abs(got[:, k] - want[:, k]).mean() == pytest.approx(c["fit"][name]["mae_mm"], rel=1e-6)
        assert np.abs(raw_d[:, k] - want[:, k]).mean() == pytest.approx(c["uncalibrated"][name]["mae_mm"], rel=1e-6)

    export(out, tmp_path / "exp")
    assert json.loads((tmp_path / "exp" / "meta.json").read_text())["calibration"] == c
    from_onnx = predict_files(tmp_path / "exp" / "model.onnx", images)
    np.testing.assert_allclose([r["d50_mm"] for r in from_onnx], got[:, 1], rtol=1e-4)


def test_an_affine_calibration_below_ten_and_the_commands_refusals(model, plugin, tmp_path, capsys, caplog):
    from psdfactory.cli import main
    from psdfactory.deploy.calibrate import calibrate
    from psdfactory.deploy.predict import predict_files
    from psdfactory.learn.runtime import load_checkpoint, write_torch

    model_pt, photos, labels, _ = model
    some = dict(list(labels.items())[:5])
    ref = write_csv(tmp_path / "ref.csv", [[f"{k}.png", *v] for k, v in some.items()])  # by file name
    images = [str(photos / f"{k}.png") for k in some]
    out = tmp_path / "affine.pt"
    block = calibrate(model_pt, ref, images, out, mm_per_px=None)
    assert block["method"] == "affine" and block["n"] == 5 and len(block["params"]["slope"]) == 3
    raw = predict_files(model_pt, images)
    got = predict_files(out, images)
    raw_d = np.array([[r["d10_mm"], r["d50_mm"], r["d90_mm"]] for r in raw])
    np.testing.assert_allclose([[r["d10_mm"], r["d50_mm"], r["d90_mm"]] for r in got],
                               cal.apply(block["params"], raw_d), rtol=1e-6)

    # a box of every photo (--roi): the whole of these images reads as without one, and the block records it; a
    # smaller box without a scale is not the model's field of view
    from PIL import Image

    from psdfactory.photoset import Region

    with Image.open(images[0]) as im:
        w, h = im.size
    boxed = calibrate(model_pt, ref, images, tmp_path / "boxed.pt", mm_per_px=None, roi=Region(0, 0, w, h))
    assert boxed["roi"] == f"0,0,{w},{h}" and "roi" not in block
    np.testing.assert_allclose(boxed["params"]["slope"], block["params"]["slope"])
    reading_of_block = {"size_definition": boxed["size_definition"], "weighting": boxed["weighting"]}
    assert f"the box 0,0,{w},{h} of each photo" in cal.calibration_note({"calibration": boxed}, reading_of_block)
    assert any("calibration.roi" in p for p in cal.calibration_problems({**boxed, "roi": "0,0,-1,5"}))
    with caplog.at_level(logging.WARNING, logger="psdfactory"):
        predict_files(tmp_path / "boxed.pt", images, roi=Region(0, 0, w, h))
        assert not [r for r in caplog.records if "calibrated on" in r.message]
        predict_files(tmp_path / "boxed.pt", images)  # whole photos: told that it was calibrated on a box
        predict_files(out, images, roi=Region(0, 0, w, h))  # and the other way round
    said = [r.message for r in caplog.records if "calibrated on the box" in r.message]
    assert len(said) == 1 and "reads whole photos now" in said[0] and f"--roi 0,0,{w},{h}" in said[0]
    said = [r.message for r in caplog.records if "calibrated on whole photos" in r.message]
    assert len(said) == 1 and f"reads the box 0,0,{w},{h} now" in said[0] and "without --roi" in said[0]
    with pytest.raises(PsdError, match=rf"\(its box --roi 0,0,{w - 1},{h}\): {w - 1} x {h} px is not the model's "
                                       "field of view"):
        calibrate(model_pt, ref, images, tmp_path / "small.pt", mm_per_px=None, roi=Region(0, 0, w - 1, h))

    # references of another weighting than the model reads (a sieve analysis counts mass): its reading corrected to
    # them, the calibrated model's d-values labelled as the references are
    vol = calibrate(model_pt, ref, images, tmp_path / "volume.pt", mm_per_px=None, weighting="volume")
    assert (vol["weighting"], vol["basis"]) == ("volume", {"size_definition": block["size_definition"],
                                                          "weighting": "number"})
    np.testing.assert_allclose(vol["params"]["slope"], block["params"]["slope"])  # the same readings and references
    got_v = predict_files(tmp_path / "volume.pt", images)
    assert {(r["size_definition"], r["weighting"]) for r in got_v} == {(block["size_definition"], "volume")}
    np.testing.assert_allclose([r["d50_mm"] for r in got_v], [r["d50_mm"] for r in got], rtol=1e-6)
    with pytest.raises(PsdError, match="calibrated for the .* size, volume-weighted"):
        predict_files(tmp_path / "volume.pt", images, weighting="number")
    # a basis this model does not give (a block edited, or moved onto another model) is refused when the model is
    # loaded, not read as another reading
    ckpt = load_checkpoint(tmp_path / "volume.pt")
    ckpt["meta"]["calibration"]["basis"] = {"size_definition": "feret-min", "weighting": "volume"}
    write_torch(tmp_path / "moved.pt", ckpt)
    with pytest.raises(PsdError, match="calibration.basis: the correction takes the feret-min reading, "
                                       "volume-weighted, which this meancolour model does not give"):
        predict_files(tmp_path / "moved.pt", images)

    capsys.readouterr()

    def refused(*args) -> str:
        assert main(["calibrate", "--model", str(model_pt), "--reference", str(ref), *args]) == 2
        captured = capsys.readouterr()
        verdict = [ln for ln in captured.err.splitlines() if not re.match(r"\d{4}-\d\d-\d\d ", ln)]  # log lines aside
        assert captured.out == "" and len(verdict) == 1 and verdict[0].startswith("psdfactory calibrate: error: ")
        return verdict[0]

    assert "is the model" in refused("--out", str(model_pt), *images)
    assert "is the input image" in refused("--out", images[0], *images)
    assert "is the reference table" in refused("--out", str(ref), *images)
    assert "must end in .pt" in refused("--out", str(tmp_path / "c.onnx"), *images)
    err = refused("--out", str(tmp_path / "c.pt"), *images[:4], str(photos / f"{list(labels)[7]}.png"))
    assert f"references with no image: {list(some)[4]}.png" in err and f"images with no reference: {photos}" in err
    broken = tmp_path / "broken" / f"{list(some)[0]}.png"
    broken.parent.mkdir()
    broken.write_text("not an image")
    err = refused("--out", str(tmp_path / "c.pt"), str(broken), *images[1:])
    assert "1 of 5 reference images failed to predict" in err and str(broken) in err
    assert not (tmp_path / "c.pt").exists()

    # a corrupt calibration block is refused in one line, in a model.pt and in an export's meta.json
    ckpt = load_checkpoint(out)
    ckpt["meta"]["calibration"]["params"]["slope"] = [1.0, 2.0]
    write_torch(tmp_path / "corrupt.pt", ckpt)
    with pytest.raises(PsdError, match="meta is refused: calibration.params: slope and intercept must be lists of 3"):
        predict_files(tmp_path / "corrupt.pt", images)
    assert main(["predict", "--model", str(tmp_path / "corrupt.pt"), images[0]]) == 2
    assert "calibration.params" in capsys.readouterr().err
