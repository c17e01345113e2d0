"""The bench/ scripts' own logic: a dataset copy at the CNNs' input size (shrink_results.py), a
recipe changed for the runs of seed_spread.py (--set) written as a config that needs no Snakemake
(--write-config), the outline comparison of mask_fit.py, and the rest of the scripts' pure parts
(photo_scales.py's forced scale, test_time_bn.py's BatchNorm blend, ...)."""

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from .conftest import REPO


def bench_module(name: str):
    spec = importlib.util.spec_from_file_location(name, REPO / "bench" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_a_shrunk_mask_keeps_ids_and_places_them_by_pixel_centre():
    """shrink_results.py resizes masks with the instance code's own resize_mask."""
    from psdfactory.learn.instances.draw import resize_mask

    def shrink_mask(mask, size):
        return resize_mask(mask, (size, size))

    mask = np.zeros((8, 8), np.uint16)
    mask[:4, :4], mask[4:, 4:], mask[0, 7] = 3, 9, 5
    small = shrink_mask(mask, 4)
    assert small.shape == (4, 4) and small.dtype == np.uint16
    assert set(np.unique(small)) <= {0, 3, 5, 9}  # nearest neighbour: no id that was not there
    assert (small[:2, :2] == 3).all() and (small[2:, 2:] == 9).all() and (small[:2, 2:] == 0).all()
    assert (shrink_mask(mask, 8) == mask).all()
    up = shrink_mask(mask, 16)  # any size: each pixel takes the id under its centre
    assert up[0, 15] == 5 and up[0, 13] == 0 and (up[:8, :8] == 3).all()


def test_set_changes_the_recipe_only_and_write_config_gives_a_config_without_snakemake(tmp_path):
    from psdfactory import PsdError
    from psdfactory.config import apply_settings

    seed_spread = bench_module("seed_spread")
    raw = {"train": {"epochs": 8}, "seed": 1}
    out = apply_settings(raw, ["train.epochs=50", "train.instances.lr=0.01", "evaluate.precision=bf16",
                               "train.architectures=[resnet50, efficientnet_b0]"], seed_spread.SETTABLE)
    assert out["train"] == {"epochs": 50, "instances": {"lr": 0.01}, "architectures": ["resnet50", "efficientnet_b0"]}
    assert out["evaluate"] == {"precision": "bf16"}
    for bad in ("seed=3", "datasets.train.n_scenes=5", "train=1", "train.epochs", "train.epochs.x=1"):
        with pytest.raises(PsdError, match="--set"):
            apply_settings({"train": {"epochs": 8}}, [bad], seed_spread.SETTABLE)
    written = tmp_path / "cfg.json"
    import subprocess
    import sys

    r = subprocess.run([sys.executable, str(REPO / "bench" / "seed_spread.py"), "--config",
                        str(REPO / "config" / "paper-cpu.yaml"), "--set", "train.epochs=50",
                        "--set", "train.size_cells=0", "--write-config", str(written)],
                       capture_output=True, text=True, cwd=REPO)
    assert r.returncode == 0, r.stderr
    cfg = json.loads(written.read_text())
    assert cfg["train"]["epochs"] == 50 and cfg["train"]["size_cells"] == 0
    assert cfg["train"]["batch_size"] > 0 and cfg["datasets"]["train"]["n_scenes"] == 1000  # defaults filled in
    assert seed_spread.load_config(written, []) == cfg  # read back as it is, no validation needed
    r = subprocess.run([sys.executable, str(REPO / "bench" / "seed_spread.py"), "--config",
                        str(REPO / "config" / "paper-cpu.yaml"), "--set", "train.epochs=0", "--write-config",
                        str(tmp_path / "bad.json")], capture_output=True, text=True, cwd=REPO)
    assert r.returncode != 0 and "epochs" in r.stderr and not (tmp_path / "bad.json").exists()
    r = subprocess.run([sys.executable, str(REPO / "bench" / "seed_spread.py"), "--config",
                        str(REPO / "config" / "paper-cpu.yaml"), "--no-snakemake", "--results", str(tmp_path / "x"),
                        "--seed-list", "42"], capture_output=True, text=True, cwd=REPO)
    assert r.returncode != 0 and "no manifests for" in r.stderr and "point it there" in r.stderr  # a wrong --results


def test_seed_spread_knows_a_run_of_other_scenes_or_labels(tmp_path):
    """seed_spread.py keeps a finished run only if it was trained and scored on the same scenes and
    labels (data.json): relabelled scenes (e.g. after labels.particles changed) or another split
    give another identity, so the run is redone."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    seed_spread = bench_module("seed_spread")
    shards = tmp_path / "a" / "manifest" / "scenes"
    shards.mkdir(parents=True)
    rows = {"scene_id": ["a-0", "a-1"], "split": ["train", "val"], "d10_mm": [1.0, 2.0], "d50_mm": [3.0, 4.0],
            "d90_mm": [5.0, 6.0], "n_particles": [10, 12]}
    pq.write_table(pa.table(rows), shards / "shard-00000.parquet")
    first = seed_spread.data_identity(tmp_path, ["a", "a"])
    assert first == seed_spread.data_identity(tmp_path, ["a"])
    pq.write_table(pa.table({**rows, "n_particles": [11, 13]}), shards / "shard-00000.parquet")
    assert seed_spread.data_identity(tmp_path, ["a"]) == first  # what the runs do not read: the same data
    pq.write_table(pa.table({**rows, "d50_mm": [3.0, 4.1]}), shards / "shard-00000.parquet")
    assert seed_spread.data_identity(tmp_path, ["a"]) != first  # relabelled
    pq.write_table(pa.table({**rows, "split": ["train", "test"]}), shards / "shard-00000.parquet")
    assert seed_spread.data_identity(tmp_path, ["a"]) != first  # another split


@pytest.mark.parametrize("seconds", ["7m", "0", "00", "", "-5"])
def test_gpu_seed_spread_refuses_a_time_limit_that_is_not_whole_seconds(tmp_path, seconds):
    """bench/gpu_seed_spread.sh checks SECONDS itself (timeout would fail every run later, each with its own error)."""
    import subprocess

    script = str(REPO / "bench" / "gpu_seed_spread.sh")
    r = subprocess.run(["bash", script, "cfg.json", "results", str(tmp_path / "out"), seconds, "resnet50", "1"],
                       capture_output=True, text=True, timeout=30)
    assert r.returncode == 2 and "SECONDS must be a whole number of seconds" in r.stderr
    assert not (tmp_path / "out").exists()  # refused before anything ran


def test_instance_readout_refuses_to_write_a_refitted_model_over_the_model_it_reads(tmp_path):
    """bench/instance_readout.py --write-models DIR: a copy whose path is the --model file (or the --out
    file) is refused before any work, the model left as it was."""
    import subprocess
    import sys

    from psdfactory.learn.instances.net import net_from_meta
    from psdfactory.learn.instances.watershed import DEFAULT_POSTPROCESS
    from psdfactory.learn.runtime import save_model

    meta = {"arch": "instances", "mm_per_px": 0.5, "image_resolution": 64, "input_size": 64,
            "postprocess": dict(DEFAULT_POSTPROCESS), "sieve_method": "min_feret", "size_definition": "sieve",
            "weighting": "number", "maps": ["foreground", "boundary", "distance"], "readouts": {}}
    model = tmp_path / "none-footprints" / "model.pt"
    model.parent.mkdir()
    save_model(model, net_from_meta(meta), meta)
    before = model.read_bytes()
    r = subprocess.run([sys.executable, str(REPO / "bench" / "instance_readout.py"), "--model", str(model),
                        "--write-models", str(tmp_path)], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert r.returncode != 0 and f"would overwrite {model}" in r.stderr
    assert model.read_bytes() == before


def test_photo_maps_shows_the_photo_and_each_map_of_an_instance_model(tmp_path):
    """bench/photo_maps.py: the photo at the network's scale and its four maps, each tile the map's
    values as grey levels, named."""
    from PIL import Image

    from psdfactory.learn.instances.net import net_from_meta
    from psdfactory.learn.instances.watershed import DEFAULT_POSTPROCESS
    from psdfactory.learn.runtime import save_model

    photo_maps = bench_module("photo_maps")
    maps = np.stack([np.full((50, 60), v, np.float32) for v in (0.0, 0.25, 0.5, 1.0)])
    image = np.full((50, 60, 3), 7, np.uint8)
    out = photo_maps.panel(image, maps, window=40)
    assert out.shape == (2 * 40, 3 * 40, 3)  # 5 tiles of 40 x 40 px on a 3-wide grid
    tile = {k: out[40 * (k // 3) + 30, 40 * (k % 3) + 30] for k in range(5)}  # a pixel below each label
    assert [int(tile[k][0]) for k in range(5)] == [7, 0, 63, 127, 255]  # photo, then the maps 0, 0.25, 0.5, 1
    assert (out[60:, 80:] == 255).all()  # the sixth place stays blank
    label = out[1:15, 1:40].reshape(-1, 3)
    assert (label == 0).all(axis=1).any() and (label[:, 0] > 200).any()  # the tile's name, in yellow on black

    meta = {"arch": "instances", "mm_per_px": 0.5, "image_resolution": 64, "input_size": 64,
            "postprocess": dict(DEFAULT_POSTPROCESS), "sieve_method": "min_feret", "size_definition": "sieve",
            "weighting": "number", "maps": ["foreground", "boundary", "distance", "size"], "readouts": {}}
    model = tmp_path / "model.pt"
    save_model(model, net_from_meta(meta), meta)
    rng = np.random.default_rng(0)
    Image.fromarray(rng.integers(0, 255, (48, 80, 3), dtype=np.uint8)).save(tmp_path / "bed.png")
    assert photo_maps.main(["--model", str(model), "--mm-per-px", "1.0", str(tmp_path / "bed.png"),
                            "--out", str(tmp_path / "maps")]) == 0
    shown = np.asarray(Image.open(tmp_path / "maps" / "bed.png"))
    assert shown.shape == (2 * 96, 3 * 160, 3)  # read at the model's 0.5 mm/px: twice the size, 96 x 160 px
    assert photo_maps.main(["--model", str(model), str(tmp_path / "missing.png"), "--out", str(tmp_path / "m2")]) == 1
    assert not (tmp_path / "m2" / "missing.png").exists()  # a photo that cannot be read: said, skipped, exit 1
    for bad in ("0", "-1", "nan", "1e9"):  # a scale that is not a finite number in range: one line, nothing written
        with pytest.raises(SystemExit):
            photo_maps.main(["--model", str(model), f"--mm-per-px={bad}", str(tmp_path / "bed.png"),
                             "--out", str(tmp_path / "m3")])
    assert not (tmp_path / "m3").exists()
    before = (tmp_path / "bed.png").read_bytes()
    with pytest.raises(SystemExit):  # the panel of bed.png would overwrite bed.png: refused before any work
        photo_maps.main(["--model", str(model), "--mm-per-px", "1.0", str(tmp_path / "bed.png"),
                         "--out", str(tmp_path)])
    assert (tmp_path / "bed.png").read_bytes() == before


def test_mask_fit_measures_how_much_fatter_the_found_grains_are():
    """bench/mask_fit.py: found grains one px fatter on every side than the reference's squares
    read an area ratio of 12²/10², and the ring's pixels as lying on the reference's background."""
    fit = bench_module("mask_fit").fit
    ref = np.zeros((40, 40), np.int64)
    ref[5:15, 5:15], ref[20:30, 22:32] = 1, 2
    found = np.zeros_like(ref)
    found[4:16, 4:16], found[19:31, 21:33] = 7, 3
    r = fit(found, ref, 0.5)
    assert r["matched"] == 2
    assert r["area_ratio"] == pytest.approx(1.44)
    assert r["minor_ratio"] == pytest.approx(1.2, abs=0.02)
    assert r["on_ref_background"] == pytest.approx(44 / 144) and r["on_other_grain"] == 0
    assert r["ref_background"] == pytest.approx(1 - 200 / 1600)
    assert r["found_background"] == pytest.approx(1 - 288 / 1600)
    assert r["band_px"] == 0 and r["minor_ratio_restored"] == r["minor_ratio"]  # two grains far apart: no band
    assert sum(r["kinds"].fn.values()) == sum(r["kinds"].fp.values()) == 0  # both matched: nothing to sort
    # grain 2 found in three pieces (none with IoU 0.5) and a grain on the background: their kinds
    found[19:31, 21:33] = 0
    found[20:30, 22:25], found[20:30, 25:29], found[20:30, 29:32], found[34:38, 2:6] = 3, 4, 6, 5
    r = fit(found, ref, 0.5)
    assert r["kinds"].fn == {"cut": 1, "merged": 0, "missed": 0, "misfit": 0}
    assert r["kinds"].fp == {"merge": 0, "background": 1, "piece": 3, "misfit": 0}
    # a reference drawn with a 4 px outline band between its 12 px squares; the grains found meet at its middle
    ref = np.zeros((64, 64), np.int64)
    found = np.zeros_like(ref)
    for k, (i, j) in enumerate(np.ndindex(4, 4), start=1):
        ref[16 * i + 2 : 16 * i + 14, 16 * j + 2 : 16 * j + 14] = k
        found[16 * i : 16 * i + 16, 16 * j : 16 * j + 16] = k
    r = fit(found, ref, 0.5)
    assert r["band_px"] == pytest.approx(4.0) and r["area_ratio"] == pytest.approx(256 / 144)
    assert r["area_ratio_restored"] == pytest.approx(256 / 252)  # grown back by 2.5 px, but its corners' √8 px
    assert r["minor_ratio"] == pytest.approx(16 / 12, abs=0.01) and 1 < r["minor_ratio_restored"] < 1.05
    assert r["f1_ceiling"] == 1.0  # 12 px grains grown back by 2 px a side keep IoU (12/16)² > 0.5


def test_mask_fit_ceiling_is_what_the_outline_band_allows():
    """bench/mask_fit.py's f1_ceiling: a reference whose 4 px band is wide against its 3 px grains
    (IoU of one grown back (3/7)² < 0.5) lets no finder that draws grains meeting match them; its
    12 px grains stay matched. 4 matched, 27 small references missed, 24 grown grains found in excess
    (the 3 on the image's left edge are left out by the border rule): F1 = 8 / 59."""
    fit = bench_module("mask_fit").fit
    ref = np.zeros((60, 64), np.int64)
    for j in range(4):
        ref[2:14, 16 * j + 2 : 16 * j + 14] = j + 1
    for k, (i, j) in enumerate(np.ndindex(3, 9), start=5):
        ref[18 + 7 * i : 21 + 7 * i, 2 + 7 * j : 5 + 7 * j] = k
    r = fit(ref.copy(), ref, 0.5)
    assert r["band_px"] == pytest.approx(4.0)
    assert r["f1_ceiling"] == pytest.approx(8 / 59)
    assert r["matched"] == 31  # the found grains are the reference itself: every one matched as drawn


def test_seed_spread_gives_the_photo_figures_as_drawn_and_with_outlines_restored(tmp_path):
    """bench/seed_spread.py's photo table: F1 and the matched grains' size error over the seeds, as
    drawn → against the reference grains grown back by half their outline band."""
    seed_spread = bench_module("seed_spread")

    def photo_run(f1: float, err: float, f1_r: float, err_r: float) -> dict:
        ref = {"d10": 5.0, "d50": 10.0, "d90": 20.0}
        r = {"detection": {"f1": f1}, "size_error": {"size_definition": {"median": err}},
             "outlines_restored": {"detection": {"f1": f1_r}, "size_error": {"size_definition": {"median": err_r}}},
             "psd_rel_err": dict.fromkeys(ref, 0.1), "psd_mm": {k: v * 1.1 for k, v in ref.items()},
             "reference_mm": ref}
        return {"photos": {"real": {"finds_grains": True, "photos": {"a.jpg": r}}}, "datasets": {}}

    metrics = {"instances": {42: photo_run(0.70, 0.136, 0.68, 0.077), 7: photo_run(0.72, 0.120, 0.70, 0.061)}}
    md = seed_spread.write_summary(tmp_path, {"command": "x", "commit": "abc", "cpu": "cpu"}, ["instances"], [42, 7],
                                   [], {}, metrics, {"instances": [4.0, 5.0]}, True)
    row = next(line for line in md.splitlines() if "real/a.jpg" in line)
    assert "| 2 | 0.71 ± 0.01 → 0.69 ± 0.01 | 12.8 ± 0.8 % → 6.9 ± 0.8 % |" in row, row
    summary = json.loads((tmp_path / "spread.json").read_text())
    assert summary["photos"]["instances"]["real/a.jpg"]["size_err_restored"]["n"] == 2
    # a run that matched no grain (size error None) counts in the F1, not in the size error
    none = photo_run(0.02, 0.1, 0.02, 0.1)
    row = none["photos"]["real"]["photos"]["a.jpg"]
    for r in (row, row["outlines_restored"]):
        r["size_error"]["size_definition"]["median"] = None
    metrics["instances"][11] = none
    md = seed_spread.write_summary(tmp_path, {"command": "x", "commit": "abc", "cpu": "cpu"}, ["instances"],
                                   [42, 7, 11], [], {}, metrics, {"instances": [4.0, 5.0, 4.0]}, True)
    row = next(line for line in md.splitlines() if "real/a.jpg" in line)
    assert "| 3 | 0.48 ± 0.35 → 0.47 ± 0.34 | 12.8 ± 0.8 % → 6.9 ± 0.8 % |" in row, row


def test_the_scale_free_readout_scales_with_the_bed_and_fits_a_known_ratio():
    """bench/readout_transfer.py's `ratio` read-outs: labels a fixed multiple of the visible d50 are fitted
    back, and a bed whose every size is k times larger (the same image statistics otherwise) reads k times larger."""
    from psdfactory.learn.instances.stats import STAT_NAMES

    rt = bench_module("readout_transfer")
    rng = np.random.default_rng(0)
    n = 40
    x = np.ones((n, len(STAT_NAMES)))
    mm = [i for i, s in enumerate(STAT_NAMES) if s.endswith("_mm") or s == "mm_per_px"]
    x[:, STAT_NAMES.index("d50_mm")] = rng.uniform(3, 12, n)
    for s, f in (("d10_mm", 0.5), ("d90_mm", 1.8), ("d10_v_mm", 0.9), ("d50_v_mm", 1.5), ("d90_v_mm", 2.2),
                 ("mean_mm", 1.1), ("std_mm", 0.6), ("mm_per_px", 0.08)):
        x[:, STAT_NAMES.index(s)] = x[:, STAT_NAMES.index("d50_mm")] * f * rng.uniform(0.9, 1.1, n)
    for s in ("map_d10_mm", "map_d50_mm", "map_d90_mm", "map_d50_v_mm"):
        x[:, STAT_NAMES.index(s)] = x[:, STAT_NAMES.index("d50_mm")] * rng.uniform(0.8, 2.0, n)
    x[:, STAT_NAMES.index("covered_fraction")] = rng.uniform(0.6, 0.9, n)
    x[:, STAT_NAMES.index("log_density")] = x[:, STAT_NAMES.index("log_density_all")] = rng.uniform(0.5, 1.0, n)
    v50 = x[:, STAT_NAMES.index("d50_mm")]
    y = v50[:, None] * np.array([0.4, 0.9, 1.7])
    for with_map in (True, False):
        ro = rt.fit_ratio(x, y, with_map)
        np.testing.assert_allclose(rt.apply_ratio(ro, x), y, rtol=0.02)
        big = x.copy()
        big[:, mm] *= 3.0
        big[:, STAT_NAMES.index("log_density")] = np.log1p(np.expm1(x[:, STAT_NAMES.index("log_density")]) / 9)
        big[:, STAT_NAMES.index("log_density_all")] = big[:, STAT_NAMES.index("log_density")]
        np.testing.assert_allclose(rt.apply_ratio(ro, big), 3.0 * rt.apply_ratio(ro, x), rtol=1e-9)


def test_the_coverage_readout_fits_labels_whose_correction_changes_with_the_covered_fraction():
    """bench/readout_transfer.py's `ridge + coverage` read-out: labels whose ratio to the visible d50 grows with the
    covered fraction (hidden fines pull a dense bed's labels further) are fitted back, where the plain ridge read-out
    (one slope for every bed) cannot; the read-out applies through `apply_readout`'s names, per target as trained."""
    from psdfactory.learn.instances.stats import READOUT_FEATURES, SIZE_STATS, STAT_NAMES
    from psdfactory.learn.readout import VISIBLE, apply_readout, fit_readout

    rt = bench_module("readout_transfer")
    rng = np.random.default_rng(1)
    n = 80
    x = np.ones((n, len(STAT_NAMES)))
    v50 = rng.uniform(3, 12, n)
    cov = rng.uniform(0.3, 0.95, n)
    for s, f in (("d10_mm", 0.5), ("d50_mm", 1.0), ("d90_mm", 1.8), ("d10_v_mm", 0.9), ("d50_v_mm", 1.5),
                 ("d90_v_mm", 2.2), ("mean_mm", 1.1), ("std_mm", 0.6)):
        x[:, STAT_NAMES.index(s)] = v50 * f * rng.uniform(0.95, 1.05, n)
    x[:, STAT_NAMES.index("covered_fraction")] = cov
    x[:, STAT_NAMES.index("log_density")] = x[:, STAT_NAMES.index("log_density_all")] = rng.uniform(0.5, 1.0, n)
    y = v50[:, None] * np.array([0.4, 0.9, 1.7]) * (1.4 - 0.6 * cov)[:, None]
    feats = READOUT_FEATURES
    plain = apply_readout(fit_readout(x, y, features=feats), x)
    ro = rt.fit_coverage(x, y, feats, None)
    assert ro["extra"] == rt.coverage_names(feats) and "d50_mm*covered_fraction" in ro["extra"]
    fitted = rt.apply_coverage(ro, x)
    err = lambda p: np.abs(p / y - 1).mean()  # noqa: E731
    assert err(fitted) < 0.01 < err(plain), (err(fitted), err(plain))
    # per target: a target's interactions are those of the statistics it reads
    ro = rt.fit_coverage(x, y, feats, [feats, feats, feats[:3]])
    assert set(ro["target_features"][2]) == {*feats[:3], *(f"{s}*covered_fraction" for s in feats[:3])}
    np.testing.assert_allclose(rt.apply_coverage(ro, x), y, rtol=0.05)
    # held as any read-out, through the names: a bed of sizes far beyond the fitted ones reads within the ratios of
    # label to visible size it was fitted on
    big = x.copy()
    big[:, [STAT_NAMES.index(s) for s in SIZE_STATS]] *= 10
    seen = big[:, [STAT_NAMES.index(s) for s in VISIBLE]]
    p = rt.apply_coverage(ro, big)
    assert (p >= seen * np.array(ro["ratio_lo"]) - 1e-9).all() and (p <= seen * np.array(ro["ratio_hi"]) + 1e-9).all()


def test_readout_transfer_scores_a_set_it_cannot_calibrate_as_nan_not_an_abort():
    """bench/readout_transfer.py's `scores`: the leave-one-out calibrated error of a set is NaN where fewer than
    calibrate's minimum of references read a finite size (two images; an image without grains), not an exception
    that loses the run; with enough finite rows it is the error of those rows."""
    rt = bench_module("readout_transfer")
    rng = np.random.default_rng(2)
    y = np.sort(rng.uniform(1, 10, (8, 3)), axis=1)
    p = y * rng.uniform(0.9, 1.1, y.shape)
    assert np.isnan(rt.scores(p[:2], y[:2])["loo_abs_err_pct"]).all()
    q = p.copy()
    q[:6] = np.nan  # six images without a reading: two left
    assert np.isnan(rt.scores(q, y)["loo_abs_err_pct"]).all()
    q = p.copy()
    q[0] = np.nan
    loo = rt.scores(q, y)["loo_abs_err_pct"]
    assert np.isfinite(loo).all() and (np.array(loo) < 50).all()


def test_readout_transfer_refuses_a_fit_on_dataset_the_model_was_not_trained_on_before_any_image(tmp_path):
    """bench/readout_transfer.py --fit-on: a dataset outside the model's training datasets is refused in one line,
    naming them, before any scene is read (the results folder does not even exist)."""
    import subprocess
    import sys

    import torch

    model = tmp_path / "model.pt"
    torch.save({"meta": {"arch": "instances", "params": {"datasets": ["train", "train_sparse"]}}}, model)
    config = tmp_path / "config.yaml"
    config.write_text((REPO / "config" / "config.yaml").read_text().replace("results: results",
                                                                          f"results: {tmp_path / 'nowhere'}"))
    r = subprocess.run([sys.executable, str(REPO / "bench" / "readout_transfer.py"), "--model", str(model),
                        "--config", str(config), "--fit-on", "train", "gravel"],
                       capture_output=True, text=True, cwd=REPO, timeout=120)
    assert r.returncode != 0, r.stderr
    assert "--fit-on gravel: not among the datasets" in r.stderr and "(train, train_sparse)" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr


def test_the_cell_histogram_reads_percentiles_inside_the_bins_that_hold_them():
    """bench/cnn_cell_head.py: a bed of one size class reads every percentile inside that class; area shares
    turn into number shares (a bin of grains twice the size holds a quarter of the grains per pixel)."""
    from psdfactory.learn.size_cells import BIN_EDGES_LOG2_PX, N_CLASSES

    cc = bench_module("cnn_cell_head")
    k = 5  # the class between edges 3 and 4 of BIN_EDGES_LOG2_PX
    shares = np.zeros((1, N_CLASSES))
    shares[0, 0], shares[0, k] = 0.3, 0.7  # the table does not count
    p = np.log2(cc.histogram_percentiles(shares)[0])
    assert (p >= BIN_EDGES_LOG2_PX[k - 2] - 1e-9).all() and (p <= BIN_EDGES_LOG2_PX[k - 1] + 1e-9).all()
    assert p[0] < p[1] < p[2]
    # equal areas in classes one octave apart: 4 times as many of the smaller grains, so d50 lies in the smaller
    shares = np.zeros((1, N_CLASSES))
    shares[0, 3], shares[0, 5] = 0.5, 0.5
    d10, d50, d90 = np.log2(cc.histogram_percentiles(shares)[0])
    assert d50 <= BIN_EDGES_LOG2_PX[2] + 1e-9 and d90 >= BIN_EDGES_LOG2_PX[3] - 1e-9


@pytest.mark.parametrize("out", ["model", "config", "folder"])
def test_readout_transfer_refuses_an_out_file_that_is_an_input_before_any_work(tmp_path, out):
    """bench/readout_transfer.py --out: the model, the config or a folder is refused at once, the file as it was."""
    import subprocess
    import sys

    model, config = tmp_path / "model.pt", tmp_path / "config.yaml"
    model.write_bytes(b"not read")
    config.write_text("results: r\n")
    target = {"model": model, "config": config, "folder": tmp_path}[out]
    before = model.read_bytes(), config.read_text()
    r = subprocess.run([sys.executable, str(REPO / "bench" / "readout_transfer.py"), "--model", str(model),
                        "--config", str(config), "--out", str(target)],
                       capture_output=True, text=True, cwd=REPO, timeout=120)
    assert r.returncode != 0 and "is a folder or one of the inputs" in r.stderr, r.stderr
    assert (model.read_bytes(), config.read_text()) == before


def test_recalibrate_from_takes_a_run_of_the_same_network_only(tmp_path, capsys):
    """seed_spread.py --recalibrate-from: a finished run that differs only in the settings applied after training
    (tta, sieve_method, readout), on the same scenes and labels, lends its network; another network, other data or
    an unfinished run does not."""
    seed_spread = bench_module("seed_spread")
    mine = {"arch": "instances", "seed": 7, "lr": 0.001,
            "settings": {"tta": "d4", "lr": 0.003, "readout": "footprints", "auto_scale": True}}
    run = tmp_path / "7" / "instances"
    run.mkdir(parents=True)
    (run / "params.json").write_text(json.dumps({**mine, "settings": {**mine["settings"], "tta": "none"}}))
    (run / "data.json").write_text(json.dumps("abc"))
    source = seed_spread.recalibration_source
    assert source(str(tmp_path), 7, "instances", mine, "abc") is None  # no model.pt yet
    assert "not finished" in capsys.readouterr().out
    (run / "model.pt").write_bytes(b"x")
    assert source(str(tmp_path), 7, "instances", mine, "abc") == run / "model.pt"
    assert source(str(tmp_path), 7, "instances", mine, "other") is None
    assert "other scenes or labels" in capsys.readouterr().out
    assert source(str(tmp_path), 8, "instances", {**mine, "seed": 8}, "abc") is None
    (run / "params.json").write_text(json.dumps({**mine, "settings": {**mine["settings"], "lr": 0.01}}))
    assert source(str(tmp_path), 7, "instances", mine, "abc") is None
    assert "trained another network" in capsys.readouterr().out


def test_calibration_basis_reads_labels_and_scores_a_reading_by_its_leave_one_out_error(tmp_path):
    """calibration_basis.py: a scene's labels in a definition and weighting, and the leave-one-out error of a
    reading exactly affine in the references (0) against one that is noise (far from 0)."""
    cb = bench_module("calibration_basis")
    (tmp_path / "labels.json").write_text(json.dumps({"d10_b_axis_mm": 1.0, "d50_b_axis_mm": 2.0, "d90_b_axis_mm": 3.0,
                                                      "d10_sieve_v_mm": 4.0, "d50_sieve_v_mm": 5.0,
                                                      "d90_sieve_v_mm": 6.0}))
    assert cb.labels_of(tmp_path, "b-axis", "number").tolist() == [1.0, 2.0, 3.0]
    assert cb.labels_of(tmp_path, "sieve", "volume").tolist() == [4.0, 5.0, 6.0]
    rng = np.random.default_rng(0)
    d50 = rng.uniform(2, 20, 12)
    ref = np.stack([0.4 * d50, d50, 2 * d50], axis=1)
    assert np.allclose(cb.loo_mape(0.5 * ref + 1, ref), 0, atol=1e-9)
    assert np.allclose(cb.subset_mape(0.5 * ref + 1, ref, 5, 20, 0), 0, atol=1e-9)
    noise = np.sort(rng.uniform(1, 30, (12, 3)), axis=1)
    assert (cb.loo_mape(noise, ref) > 10).all()


def test_calibration_basis_measures_a_scenes_own_mask_as_a_perfect_grain_finder(tmp_path):
    """calibration_basis.py --true-masks: each scene's mask.png measured at its scale (render.json), the grains cut
    by the border left out, and resampled to a coarser scale first where asked."""
    from psdfactory.io import write_png
    from psdfactory.psd import weighted_percentiles

    cb = bench_module("calibration_basis")
    mask = np.zeros((120, 120), np.uint16)
    for k, (r, c, side) in enumerate([(10, 10, 10), (40, 40, 20), (80, 10, 30), (0, 100, 10)], 1):
        mask[r:r + side, c:c + side] = k  # squares; the last one touches the border
    scene = tmp_path / "s0"
    scene.mkdir()
    write_png(scene / "mask.png", mask)
    (scene / "render.json").write_text(json.dumps({"mm_per_px": 0.5}))
    got = cb.true_mask_readings([scene], None)
    widths_mm = 0.5 * np.array([10.0, 20.0, 30.0])  # the whole squares' sides
    assert np.allclose(got[("feret-min", "number")][0], weighted_percentiles(widths_mm, None), rtol=0.03)
    ecd_mm = widths_mm * np.sqrt(4 / np.pi)
    assert np.allclose(got[("ecd", "area")][0], weighted_percentiles(ecd_mm, widths_mm**2), rtol=0.03)
    coarse = cb.true_mask_readings([scene], 1.0)  # half the pixels a side: the same mm
    assert np.allclose(coarse[("feret-min", "number")][0], got[("feret-min", "number")][0], rtol=0.1)


def test_calibration_basis_saves_every_reading_and_the_references(tmp_path):
    """calibration_basis.py --save: the readings it scores (here a perfect grain finder's) and the scenes' labels,
    in the scenes' order, to an .npz an analysis the table does not make can load."""
    from psdfactory.io import write_png

    cb = bench_module("calibration_basis")
    root = tmp_path / "scenes"
    for i, side in enumerate([8, 12, 16, 20]):
        scene = root / f"s{i}"
        scene.mkdir(parents=True)
        mask = np.zeros((100, 100), np.uint16)
        for k in range(4):
            mask[5 + 24 * k:5 + 24 * k + side, 40:40 + side] = k + 1
        write_png(scene / "mask.png", mask)
        (scene / "image.png").write_bytes(b"")  # listed, not read, with --true-masks
        (scene / "render.json").write_text(json.dumps({"mm_per_px": 0.5}))
        (scene / "labels.json").write_text(json.dumps({f"d{q}_b_axis_mm": 0.5 * side for q in (10, 50, 90)}))
    for bad in (root, root / "s0" / "r.npz"):  # a folder, a file inside the scenes: refused before any work
        with pytest.raises(SystemExit):
            cb.main(["--true-masks", "--scenes", str(root), "--subset", "0", "--save", str(bad)])
    assert not (root / "s0" / "r.npz").exists()
    out = tmp_path / "readings.npz"
    assert cb.main(["--true-masks", "--scenes", str(root), "--subset", "0", "--save", str(out)]) == 0
    saved = np.load(out)
    assert saved["scenes"].tolist() == [str((root / f"s{i}").resolve()) for i in range(4)]
    assert (str(saved["definition"]), str(saved["weighting"])) == ("b-axis", "number")
    assert np.allclose(saved["reference"][:, 1], [4, 6, 8, 10])
    assert np.allclose(saved["feret-min|number"][:, 1], saved["reference"][:, 1], rtol=0.05)
    assert {"ecd|area", "feret-max|volume"} <= set(saved.files)


def test_calibration_choice_finds_the_reading_that_calibrates_and_scores_itself_without_the_held_out_one(
        tmp_path, capsys, monkeypatch):
    """calibration_choice.py: where one reading is exactly affine in the references and the fixed rule's is noise,
    the choice and the committee predict each held-out reference from the others to ~0 error while the fixed
    rule's leave-one-out stays large; no fit of the nested leave-one-out ever sees the reference it predicts; the
    corrected d-values come out sorted; a file that is not a --save .npz is refused in one line."""
    from psdfactory.learn import calibration as cal

    cc = bench_module("calibration_choice")
    rng = np.random.default_rng(1)
    d50 = rng.uniform(2, 20, 9)
    ref = np.stack([0.4 * d50, d50, 2 * d50], axis=1)
    reads = {"b-axis|number": np.sort(rng.uniform(1, 30, (9, 3)), axis=1), "ecd|volume": 0.7 * ref + 0.5}
    for how in ("choice", "committee"):
        assert np.allclose(cc.nested_loo(reads, ref, how), ref, rtol=1e-6), how

    seen, fit = [], cal.fit
    monkeypatch.setattr(cal, "fit", lambda p, r, method=None: seen.append(np.asarray(r)[:, 1]) or fit(p, r, method))
    for i in range(len(ref)):
        others = np.arange(len(ref)) != i
        seen.clear()
        cc.predict({k: v[others] for k, v in reads.items()}, ref[others], {k: v[i] for k, v in reads.items()},
                   "committee")
        assert seen and not any(np.isclose(r, d50[i]).any() for r in seen)  # held out of every fit
    monkeypatch.undo()
    calls, predict = [], cc.predict  # and nested_loo hands predict the others only, the held-out one as new
    monkeypatch.setattr(cc, "predict", lambda rd, r, new, how: calls.append((r[:, 1], new)) or predict(rd, r, new, how))
    cc.nested_loo(reads, ref, "choice")
    monkeypatch.undo()
    assert len(calls) == len(ref)
    for i, (r, new) in enumerate(calls):
        assert np.allclose(new["ecd|volume"], reads["ecd|volume"][i]) and not np.isclose(r, d50[i]).any()

    crossing = {"ecd|volume": reads["ecd|volume"][:, ::-1].copy()}  # d10 and d90 read swapped
    assert (np.diff(cc.predict(crossing, ref, {"ecd|volume": crossing["ecd|volume"][0]}, "choice")) >= 0).all()

    out = tmp_path / "r.npz"
    np.savez(out, reference=ref, definition="b-axis", weighting="number",
             scenes=np.array([str(tmp_path / f"s{i}") for i in range(9)]), **reads)
    assert cc.main([str(out)]) == 0
    row = capsys.readouterr().out.splitlines()[-1].split()
    fixed, choice, committee = (float(row[i]) for i in (5, 10, 15))  # d50 of each "d10 / d50 / d90" cell
    assert fixed > 10 and choice < 0.01 and committee < 0.01
    np.save(tmp_path / "one.npy", ref)
    with pytest.raises(SystemExit):
        cc.main([str(tmp_path / "one.npy")])
    assert "not the .npz of calibration_basis.py --save" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cc.main([str(out), "--also", "sieve"])  # its scenes have no labels.json
    assert "--also sieve" in capsys.readouterr().err


def test_relook_renders_the_same_scenes_in_another_look_and_leaves_the_sources_alone(tmp_path, tiny_results):
    """relook.py: each scene rendered again with a config's render block and --set render.* on top, at the
    settings asked (resolution, a bright table), its particles, poses and labels copied as they are."""
    import yaml

    from psdfactory.io import read_png

    relook = bench_module("relook")
    cfg, root = tiny_results
    scenes = root / "tiny" / "scenes"
    before = {p: p.read_bytes() for p in scenes.glob("*/image.png")}
    config = tmp_path / "tiny.yaml"
    config.write_text(yaml.safe_dump(json.loads(json.dumps(cfg))))
    assert relook.main(["--scenes", str(scenes), "--out", str(tmp_path / "out"), "--config", str(config),
                        "--set", "render.resolution=48", "--set", "render.table_palette=[[0.9, 0.9, 0.9]]"]) == 0
    assert {p: p.read_bytes() for p in scenes.glob("*/image.png")} == before
    for src in sorted(scenes.iterdir()):
        dst = tmp_path / "out" / src.name
        assert (dst / "labels.json").read_bytes() == (src / "labels.json").read_bytes()
        new, old = read_png(dst / "image.png"), read_png(src / "image.png")
        mask_new, mask_old = read_png(dst / "mask.png"), read_png(src / "mask.png")
        assert new.shape == (48, 48, 3) and mask_new.shape == (48, 48)
        assert new[mask_new == 0].mean() > old[mask_old == 0].mean() + 60  # the table is bright now
    with pytest.raises(SystemExit):
        relook.main(["--scenes", str(scenes), "--out", str(tmp_path / "x"), "--config", str(config),
                     "--set", "train.epochs=3"])  # not a render setting
    with pytest.raises(SystemExit):  # another part of the table: the source's labels would not be of it
        relook.main(["--scenes", str(scenes), "--out", str(tmp_path / "y"), "--config", str(config),
                     "--set", "render.view_fraction=[0.5, 0.5]"])
    assert not any((tmp_path / "y").glob("*/image.png"))
    for out in (scenes, next(scenes.iterdir()) / "new", config):  # the sources themselves, inside one, a file
        with pytest.raises(SystemExit):
            relook.main(["--scenes", str(scenes), "--out", str(out), "--config", str(config)])
    assert {p: p.read_bytes() for p in scenes.glob("*/image.png")} == before


def test_augment_cost_times_each_part_and_refuses_a_run_of_nothing(capsys):
    """bench/augment_cost.py: a row per part (the two augmentations and the training step), each a positive time,
    their shares summing to ~100 %; zero runs or batches are refused, not divided by."""
    augment_cost = bench_module("augment_cost")
    assert augment_cost.main(["--batch", "2", "--size", "32", "--repeats", "2", "--batches", "1",
                              "--threads", "1"]) == 0
    lines = capsys.readouterr().out.splitlines()
    table = lines[lines.index(next(line for line in lines if line.startswith("part"))) + 1:][:3]
    parts = [line[:18].strip() for line in table]
    assert parts == ["photometric", "surface_texture", "training step"]
    times = [float(line[18:].split()[0]) for line in table]
    shares = [float(line.split()[-1].rstrip("%")) for line in table]
    assert all(t > 0 for t in times)
    assert abs(sum(shares) - 100) <= 2
    assert "surface_texture adds" in lines[-1]
    for bad in (["--repeats", "0"], ["--batches", "0"]):
        with pytest.raises(SystemExit):
            augment_cost.main(bad)


def test_photo_scales_reads_a_photo_set_at_a_forced_factor_of_its_scale(tmp_path):
    """bench/photo_scales.py: each photo's mm per px times the factor, in a copy of its CSV (other
    columns and the set's own CSV untouched), or the set's one number times it; never the automatic scale."""
    at = bench_module("photo_scales").photo_set_at
    folder = tmp_path / "set"
    folder.mkdir()
    (folder / "labels.csv").write_text("image,mm_per_px,d50_mm\na.jpg,0.5,10\nb.jpg,2,30\n", encoding="utf-8")
    params = {"name": "s", "folder": str(folder), "mm_per_px": {"csv": "labels.csv", "column": "mm_per_px"},
              "reference": {"csv": "labels.csv"}, "masks": "{stem}_mask.png", "auto_scale": True}
    work = tmp_path / "work"
    work.mkdir()
    p = at(params, 0.25, work)
    assert p["auto_scale"] is False and params["auto_scale"] is True  # the set's params are left alone
    rows = (Path(p["mm_per_px"]["csv"]).read_text(encoding="utf-8")).split()
    assert rows[0] == "image,mm_per_px,d50_mm"
    assert [float(r.split(",")[1]) for r in rows[1:]] == [0.125, 0.5] and rows[2].endswith(",30")
    assert (folder / "labels.csv").read_text(encoding="utf-8").split()[1] == "a.jpg,0.5,10"
    assert p["reference"]["csv"] == str(folder / "labels.csv") and p["folder"] == str(folder)
    assert at(dict(params, mm_per_px=0.4), 2.0, work)["mm_per_px"] == pytest.approx(0.8)


def test_test_time_bn_blends_the_trained_statistics_with_the_images_own():
    """bench/test_time_bn.py: a = 0 leaves the network as trained, a = 1 gives each BatchNorm the
    statistics of the batch it adapts on, a = 0.5 their mean; the network stays in eval mode."""
    import torch

    adapt = bench_module("test_time_bn").adapt
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Conv2d(3, 4, 1, bias=False), torch.nn.BatchNorm2d(4)).eval()
    bn = net[1]
    bn.running_mean.fill_(1.0)
    bn.running_var.fill_(4.0)
    x = torch.randn(2, 3, 8, 8) * 3 + 2
    with torch.no_grad():
        y = net[0](x)
    mean, var = y.mean(dim=(0, 2, 3)), y.var(dim=(0, 2, 3), unbiased=True)
    adapt(net, x, 0.0)
    assert torch.equal(bn.running_mean, torch.ones(4)) and torch.equal(bn.running_var, torch.full((4,), 4.0))
    adapt(net, x, 1.0)
    assert torch.allclose(bn.running_mean, mean, atol=1e-5) and torch.allclose(bn.running_var, var, atol=1e-4)
    assert not bn.training
    adapt(net, x, 0.5)  # blended with the statistics it was trained with, not with the last adaptation
    assert torch.allclose(bn.running_mean, (mean + 1) / 2, atol=1e-5)
    assert torch.allclose(bn.running_var, (var + 4) / 2, atol=1e-4)


def test_photo_scales_refuses_a_run_it_cannot_do_before_any_work(tmp_path):
    """bench/photo_scales.py: a missing model, a factor that is not finite or not in (0, 4], and a --work
    in the photo set's folder are each named; readings are kept under a name of the model file as it is."""
    mod = bench_module("photo_scales")
    folder, model = tmp_path / "photos", tmp_path / "model.pt"
    folder.mkdir()
    assert len(mod.check_run(model, [0.5], None, folder)) == 1  # no model file
    model.write_bytes(b"x")
    assert mod.check_run(model, [0.5, 1.0], tmp_path / "work", folder) == []
    (problem,) = mod.check_run(model, [0.0, float("nan"), 5.0, 0.3], None, folder)
    assert "0.0 nan 5.0" in problem
    assert "photo set's folder" in mod.check_run(model, [0.5], folder / "w", folder)[0]
    assert "photo set's folder" in mod.check_run(model, [0.5], folder, folder)[0]
    assert "is the model" in mod.check_run(model, [0.5], model, folder)[0]
    key = mod.model_key(model)
    assert key == mod.model_key(model)
    model.write_bytes(b"another model")
    assert mod.model_key(model) != key


def test_finder_size_bias_recovers_a_rim_law_and_reads_a_scenes_truth(tmp_path):
    """bench/finder_size_bias.py: ratio = a + b / d50_px fitted back from exact points; a scene's
    particles in view, their size in px at the model's scale and its dark background read from its files."""
    import pandas as pd
    from PIL import Image

    mod = bench_module("finder_size_bias")
    d = np.array([10.0, 12.0, 16.0, 20.0, 30.0])
    assert mod.fit_rim(d, 0.7 + 7.0 / d) == pytest.approx((0.7, 7.0))
    scene = tmp_path / "s"
    scene.mkdir()
    particles = pd.DataFrame({"b_axis_mm": [2.0, 4.0, 6.0, 50.0], "feret_min_mm": [1.0, 3.0, 5.0, 40.0],
                              "visible_px": [5, 9, 20, 0], "settled": [True, True, True, True]})
    particles.to_parquet(scene / "particles.parquet")
    (scene / "labels.json").write_text(json.dumps({"mm_per_px": 0.5}), encoding="utf-8")
    mask = np.zeros((10, 10), np.uint16)
    mask[:5] = 1
    Image.fromarray(mask).save(scene / "mask.png")
    img = np.full((10, 10), 255, np.uint8)
    img[5:7] = 40  # 20 of the 50 background pixels dark
    Image.fromarray(img).save(scene / "image.png")
    s = mod.scene_stats(scene, 0.25)
    assert s["in_view_feret_min_d50_mm"] == 3.0 and s["d50_px"] == pytest.approx(16.0)  # the buried one left out
    assert s["covered"] == pytest.approx(0.5) and s["dark_background"] == pytest.approx(0.4)
    assert s["in_view_per_cm2"] == pytest.approx(3 / 0.25)  # 10 x 10 px at 0.5 mm: 0.25 cm²


def test_photo_robustness_makes_a_photo_set_again_as_another_camera_would(tmp_path):
    """bench/photo_robustness.py's variants: a smaller photo gets its mask shrunk alike and a scale multiplied to
    match (the same mm on the ground), a grey one equal channels, a JPEG one a .jpg in labels.csv; the masks' ids and
    the references stay."""
    from PIL import Image

    pr = bench_module("photo_robustness")
    src = tmp_path / "set"
    src.mkdir()
    rng = np.random.default_rng(0)
    Image.fromarray(rng.integers(0, 255, (60, 90, 3), dtype=np.uint8)).save(src / "a.jpg")
    mask = np.zeros((60, 90), np.uint16)
    mask[10:40, 10:50], mask[20:50, 60:85] = 1, 2
    Image.fromarray(mask).save(src / "a_mask.png")
    (src / "labels.csv").write_text("image,mm_per_px,d10_mm,d50_mm,d90_mm\na.jpg,0.5,1,2,3\n")

    pr.make_variant(src, tmp_path / "half", "half")
    rows = (tmp_path / "half" / "labels.csv").read_text().splitlines()
    assert rows[1].split(",")[:2] == ["a.png", "1"] and rows[1].endswith(",1,2,3")  # 90 px -> 45: twice the mm
    half = np.asarray(Image.open(tmp_path / "half" / "a.png"))
    half_mask = np.asarray(Image.open(tmp_path / "half" / "a_mask.png"))
    assert half.shape == (30, 45, 3) and half_mask.shape == (30, 45) and set(np.unique(half_mask)) == {0, 1, 2}

    pr.make_variant(src, tmp_path / "grey", "grey")
    grey = np.asarray(Image.open(tmp_path / "grey" / "a.png")).astype(int)
    assert grey.shape == (60, 90, 3) and (grey[..., 0] == grey[..., 1]).all() and (grey[..., 1] == grey[..., 2]).all()
    assert np.array_equal(np.asarray(Image.open(tmp_path / "grey" / "a_mask.png")), mask)

    pr.make_variant(src, tmp_path / "jpeg", "jpeg25")
    assert (tmp_path / "jpeg" / "labels.csv").read_text().splitlines()[1].startswith("a.jpg,0.5,")
    assert Image.open(tmp_path / "jpeg" / "a.jpg").format == "JPEG"


def test_photo_robustness_refuses_outputs_among_its_inputs(tmp_path):
    """--work inside the photo set or a model, --json a model, a photo-set file, inside --work or a folder: each
    refused before any work, in a line naming the flag; a work folder per photo set."""
    pr = bench_module("photo_robustness")
    photos, model, work = tmp_path / "set", tmp_path / "model.pt", tmp_path / "work"
    photos.mkdir()
    model.write_bytes(b"x")
    assert pr.output_problems(photos, [model], work, tmp_path / "out.json") == []
    for w, j, flag in ((photos / "w", None, "--work"), (model, None, "--work"), (None, model, "--json"),
                       (None, photos / "labels.csv", "--json"), (work, work / "all.json", "--json"),
                       (None, tmp_path, "--json")):
        found = pr.output_problems(photos, [model], w, j)
        assert len(found) == 1 and found[0].startswith(flag), (w, j, found)
    other = tmp_path / "other" / "set"
    assert pr.variant_folder(work, photos, "grey") != pr.variant_folder(work, other, "grey")
    assert pr.variant_folder(work, photos, "grey").name == "grey"


def test_relook_refuses_an_out_folder_inside_the_scenes_it_reads(tmp_path, capsys):
    """relook.py: --out the scenes' folder itself or inside one of its scenes is refused before anything is written."""
    rl = bench_module("relook")
    scene = tmp_path / "scenes" / "s0"
    scene.mkdir(parents=True)
    (scene / "poses.parquet").write_bytes(b"")
    (scene / "spec.json").write_text("{}")
    for bad in (tmp_path / "scenes", scene / "again"):
        with pytest.raises(SystemExit):
            rl.main(["--scenes", str(tmp_path / "scenes"), "--out", str(bad), "--config", str(tmp_path / "none.yaml")])
        assert "is --scenes or inside one of its scenes" in capsys.readouterr().err
    assert not (scene / "again").exists()
