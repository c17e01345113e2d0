"""The instance estimator (architecture `instances`): targets, network, read-out, and one tiny
training run through predict, evaluate, benchmark and export. Nothing trains to convergence:
the accuracy is a benchmark (README), not a test."""

import csv
import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import torch

from psdfactory import PsdError
from psdfactory import config as psd_config
from psdfactory.io import read_png
from psdfactory.learn.augment import TTA_VIEWS
from psdfactory.learn.instances.draw import resize_mask
from psdfactory.learn.instances.estimator import InstanceEstimator, averaged_maps
from psdfactory.learn.instances.measure import measure_instances
from psdfactory.learn.instances.net import InstanceNet
from psdfactory.learn.instances.scoring import fully_visible, match_instances
from psdfactory.learn.instances.stats import READOUT_FEATURES, READOUTS, STAT_NAMES
from psdfactory.learn.instances.targets import (
    MAPS,
    decode_size,
    encode_size,
    instance_loss,
    instance_targets,
    random_crops,
    target_stack,
    zoom,
)
from psdfactory.learn.instances.training import InstanceSettings
from psdfactory.learn.instances.watershed import DEFAULT_POSTPROCESS, postprocess
from psdfactory.learn.readout import apply_readout, fit_readout
from psdfactory.manifest import write_shard

from .conftest import make_scene, tiny_config

pytest.importorskip("skimage")


def discs(shape, centres, r):
    """Instance mask of discs painted in order (a later disc wins where they overlap)."""
    mask = np.zeros(shape, dtype=np.uint16)
    rr, cc = np.indices(shape)
    for k, (y, x) in enumerate(centres, start=1):
        mask[(rr - y) ** 2 + (cc - x) ** 2 <= r * r] = k
    return mask


def test_targets_of_two_touching_discs():
    mask = discs((40, 60), [(20, 20), (20, 36)], 9)  # overlapping by 2 px: they share a straight border
    fg, bd, dist = instance_targets(mask)
    assert fg.dtype == bool and np.array_equal(fg, mask > 0)
    # the border between them is boundary on both sides; the centres are not
    row = 20
    cols = np.flatnonzero((mask[row, :-1] == 1) & (mask[row, 1:] == 2))
    assert len(cols) == 1
    c = cols[0]
    assert bd[row, c] and bd[row, c + 1]
    assert not bd[20, 20] and not bd[20, 36] and not bd[mask == 0].any()
    # the distance is 1 at each disc's centre (its maximum) and small at the border between them
    assert dist.dtype == np.float32 and dist.max() == pytest.approx(1.0) and dist[mask == 0].max() == 0
    for k, centre in ((1, (20, 20)), (2, (20, 36))):
        d = np.where(mask == k, dist, -1)
        peak = np.unravel_index(np.argmax(d), d.shape)
        assert abs(peak[0] - centre[0]) <= 1 and abs(peak[1] - centre[1]) <= 1
        assert dist[centre] > 0.85
    assert dist[row, c] <= 0.2 and dist[row, c + 1] <= 0.2
    # one tensor per mask: foreground, boundary, distance (and the size map when sizes are known)
    t = target_stack(mask)
    assert t.shape == (3, 40, 60) and t.dtype == torch.float32
    sizes = np.array([np.nan, 14.0, 40.0])  # by mask id: disc 2 is a bigger grain, mostly hidden
    t4 = target_stack(mask, sizes)
    assert t4.shape == (len(MAPS), 40, 60) and torch.equal(t4[:3], t)
    assert decode_size(t4[3][mask == 1].numpy()) == pytest.approx(14.0, rel=1e-5)
    assert decode_size(t4[3][mask == 2].numpy()) == pytest.approx(40.0, rel=1e-5)
    assert (t4[3][mask == 0] == 0).all()
    with pytest.raises(PsdError, match="id 2"):
        target_stack(mask, sizes[:2])


def test_size_encoding_round_trips_and_clips():
    px = np.array([0.5, 1.0, 7.3, 100.0, 1024.0])
    assert decode_size(encode_size(px)) == pytest.approx(px, rel=1e-9)
    assert encode_size(np.array([0.01, 1e6])).tolist() == [0.0, 1.0]


def test_size_map_measures_partly_hidden_particles_whole():
    """With a perfect size map, the 'size_map' sieve size of a half-hidden disc is its true size,
    where its footprint's min Feret diameter reads the visible half."""
    mask = discs((64, 64), [(32, 20), (32, 44)], 14)
    mask[:, :20] = 0  # the left disc is cut in half (e.g. hidden under another particle)
    sizes = np.array([np.nan, 28.0, 28.0])
    maps = target_stack(mask, sizes).numpy()
    est = InstanceEstimator({"postprocess": DEFAULT_POSTPROCESS, "sieve_method": "size_map"}, lambda x: maps[None])
    got = est.analyse_maps(maps, 0.5)
    assert got.sizes_mm == pytest.approx([14.0, 14.0], rel=0.01)
    feret = measure_instances(got.mask, 0.5).min_feret_mm
    assert feret.min() < 0.6 * 14.0

def test_perfect_maps_give_back_the_true_instances():
    """The post-processing on the targets themselves (a perfect network) recovers the mask."""
    mask = discs((64, 80), [(16, 16), (16, 31), (44, 20), (40, 60), (58, 75)], 8)
    mask[5:8, 70:73] = 6  # a 9-px grain
    maps = np.stack([m.astype(np.float32) for m in instance_targets(mask)])
    pred = postprocess(maps, DEFAULT_POSTPROCESS)
    res = match_instances(pred, mask, iou=0.8)
    assert res.n_pred == res.n_true == 6 and res.n_matched == 6
    # and the estimator measures them like the true mask
    est = InstanceEstimator({"postprocess": DEFAULT_POSTPROCESS}, lambda x: maps[None])
    got = est.analyse_maps(maps, 0.5)
    ref = measure_instances(mask, 0.5)
    assert sorted(got.measurements.area_mm2) == pytest.approx(sorted(ref.area_mm2), rel=0.02)
    assert got.calibrated == pytest.approx(got.raw)  # no read-out: the raw percentiles
    assert got.sizes_mm.shape == (6,) and got.stats.shape == (len(STAT_NAMES),)


@pytest.mark.parametrize("tta", ["flips", "d4"])
def test_test_time_views_are_turned_back_into_the_image_frame(tta):
    """averaged_maps: maps that follow the image (here its own pixels) come back unchanged on a
    non-square image off the 32-px grid, every view run on the image padded to the grid; a map that
    marks its input's top-left pixel, whatever the view, comes back as a quarter on each of the
    image's four corners when the image is on the grid (each corner is one view in four), and on its
    top-left only when it is not (the other views' top-left is a corner of the padding, cut away)."""
    x = torch.arange(2 * 3 * 5 * 40, dtype=torch.float32).reshape(2, 3, 5, 40)
    seen = []

    def follows(v):
        seen.append(tuple(v.shape[-2:]))
        return v[:, :2].numpy()

    got = averaged_maps(follows, x, TTA_VIEWS[tta])
    assert got.shape == (2, 2, 5, 40) and np.allclose(got, x[:, :2].numpy())
    assert len(seen) == len(TTA_VIEWS[tta]) and (32, 64) in seen
    assert set(seen) <= {(32, 64), (64, 32)} and ((64, 32) in seen) == (tta == "d4")  # quarter turns swap H and W

    def top_left(v):
        m = np.zeros((v.shape[0], 1, *v.shape[-2:]), np.float32)
        m[:, :, 0, 0] = 1
        return m

    corners = np.zeros((32, 64))
    corners[[0, 0, -1, -1], [0, -1, 0, -1]] = 0.25
    assert np.allclose(averaged_maps(top_left, torch.zeros(1, 3, 32, 64), TTA_VIEWS[tta])[0, 0], corners)
    off_grid = np.zeros((5, 40))
    off_grid[0, 0] = 0.25
    assert np.allclose(averaged_maps(top_left, x, TTA_VIEWS[tta])[0, 0], off_grid)


def test_estimator_averages_the_model_views_and_checks_the_setting():
    from psdfactory.learn.instances.estimator import readout_problems

    calls = []
    maps, image = np.zeros((1, 4, 16, 16), np.float32), torch.zeros(1, 3, 16, 16, dtype=torch.uint8)
    for meta, n in (({"tta": "none"}, 1), ({"tta": "flips"}, 4), ({"tta": "d4"}, 8),
                    ({}, 1)):  # a model file from before test-time views: one view
        calls.clear()
        InstanceEstimator(meta, lambda x: calls.append(1) or maps).outputs(image)
        assert len(calls) == n
    defaults = psd_config.train_params(tiny_config(), "instances")["settings"]
    assert InstanceSettings.from_dict(defaults).tta == "none"  # the schema default
    assert InstanceSettings.from_dict({**defaults, "tta": "d4"}).tta == "d4"
    with pytest.raises(PsdError, match="train.instances.tta"):
        InstanceSettings.from_dict({**defaults, "tta": "d8"})
    assert any("tta" in p for p in readout_problems({"tta": "d8"}))


@pytest.mark.parametrize("stages", [2, 3])
@pytest.mark.parametrize("shape", [(1, 3, 33, 47), (2, 3, 64, 64), (1, 3, 9, 70)])
def test_network_maps_have_the_input_size(shape, stages):
    net = InstanceNet(stages=stages).eval()
    with torch.no_grad():
        out = net(torch.randn(*shape))
    assert out.shape == (shape[0], len(MAPS), *shape[2:]) and torch.isfinite(out).all()


def test_a_deeper_trunk_is_described_by_its_meta_and_refused_when_it_is_not_one():
    """trunk_stages 3: layer3 kept, a decoder stage more, the model file's meta rebuilds the same network (its
    weights load), and a meta naming another trunk depth or a decoder of the wrong length is refused."""
    from psdfactory.learn.instances.estimator import readout_problems
    from psdfactory.learn.instances.net import decoder_for, net_from_meta

    deep, flat = InstanceNet(stages=3), InstanceNet()
    assert deep.layer3 is not None and flat.layer3 is None and len(deep.up) == len(flat.up) + 1
    assert sum(p.numel() for p in deep.parameters()) > 3 * sum(p.numel() for p in flat.parameters())
    meta = {"maps": list(MAPS), "trunk_stages": 3, "decoder": list(decoder_for(3))}
    net_from_meta(meta).load_state_dict(deep.state_dict())  # strict: every weight, no more, no fewer
    with pytest.raises(RuntimeError):
        net_from_meta({"maps": list(MAPS)}).load_state_dict(deep.state_dict())
    assert not [p for p in readout_problems(meta) if "trunk" in p or "decoder" in p]
    assert any("trunk_stages" in p for p in readout_problems({**meta, "trunk_stages": 4}))
    assert any("decoder" in p for p in readout_problems({**meta, "decoder": list(decoder_for(2))}))
    with pytest.raises(PsdError, match="stages"):
        InstanceNet(stages=5)


def test_glimpsed_particles_are_taught_as_background():
    from psdfactory.learn.instances.targets import grain_mask

    mask = np.zeros((40, 40), np.uint16)
    yy, xx = np.mgrid[:40, :40]
    mask[(yy - 15) ** 2 + (xx - 15) ** 2 <= 36] = 1  # a whole particle on top: 113 px of a 12-px disc
    mask[30:32, 20:22] = 2  # 4 px of a particle 12 px across, deep in the bed: a glimpse
    mask[0:2, 30:32] = 3  # 4 px of another, cut by the image's border
    mask[25:28, 5:8] = 4  # 9 px with no particle row: kept as it is
    ecd = np.array([np.nan, 12.0, 12.0, 12.0])  # per mask id
    out = grain_mask(mask, ecd, 0.5)
    assert set(np.unique(out)) == {0, 1, 3, 4}  # the glimpse is background, the rest unchanged
    assert (out[mask != 2] == mask[mask != 2]).all() and out.dtype == mask.dtype
    assert (grain_mask(mask, ecd, 0.0) == mask).all()  # 0: every visible particle is a grain
    assert set(np.unique(grain_mask(mask, ecd, 1.0))) == {0, 3, 4}  # the disc shows 113 px of its 113.1


def test_min_visible_share_is_in_the_training_slice_only_when_set():
    """Off (the schema default, 0) it leaves every slice as it was, so no model trained before it retrains."""
    import copy

    from psdfactory.config import load_config, train_params
    from psdfactory.learn.instances.training import InstanceSettings

    cfg = load_config("config/config.yaml")
    off = train_params(cfg, "instances")["settings"]
    assert "min_visible_share" not in off and InstanceSettings.from_dict(off).min_visible_share == 0.0
    # nor the fingerprint of a training that leaves it off: a checkpoint written before it still resumes
    from dataclasses import asdict

    from psdfactory.config import network_recipe, training_recipe

    full = {**train_params(cfg, "instances"), "settings": asdict(InstanceSettings.from_dict(off))}
    assert full["settings"]["min_visible_share"] == 0.0
    before = {**full, "settings": {k: v for k, v in full["settings"].items() if k != "min_visible_share"}}
    assert training_recipe(full) == training_recipe(before) and network_recipe(full) == network_recipe(before)
    cfg = copy.deepcopy(cfg)
    cfg["train"]["instances"]["min_visible_share"] = 0.5
    on = train_params(cfg, "instances")["settings"]
    assert on["min_visible_share"] == 0.5 and InstanceSettings.from_dict(on).min_visible_share == 0.5
    set_on = {**full, "settings": asdict(InstanceSettings.from_dict(on))}
    assert network_recipe(set_on) != network_recipe(full)  # set, it is another network


@pytest.mark.parametrize(("key", "off_value", "on_value", "refused"),
                         [("surface_texture", 0.0, 1.0, 5.0), ("grain_colour", 0.0, 1.0, 5.0),
                          ("trunk_stages", 2, 3, 4)])
def test_a_network_setting_is_in_the_training_slice_only_when_set(key, off_value, on_value, refused):
    """train.instances.surface_texture / grain_colour off (0) and trunk_stages at 2 change no slice; set, it is
    another network; a value the schema does not allow is refused naming the key."""
    import copy
    from dataclasses import asdict

    from psdfactory.config import load_config, network_recipe, train_params
    from psdfactory.learn.instances.training import InstanceSettings

    cfg = load_config("config/config.yaml")
    off = train_params(cfg, "instances")["settings"]
    assert key not in off and getattr(InstanceSettings.from_dict(off), key) == off_value
    cfg = copy.deepcopy(cfg)
    cfg["train"]["instances"][key] = on_value
    on = train_params(cfg, "instances")["settings"]
    assert on[key] == on_value
    full = {**train_params(cfg, "instances"), "settings": asdict(InstanceSettings.from_dict(off))}
    assert network_recipe({**full, "settings": asdict(InstanceSettings.from_dict(on))}) != network_recipe(full)

    def too_strong(raw: dict) -> dict:
        raw["train"]["instances"][key] = refused
        return raw

    with pytest.raises(PsdError, match=key):
        load_config("config/config.yaml", edit=too_strong)


def test_calibration_datasets_choose_the_scenes_the_calibration_is_fitted_on():
    """train.instances.calibration_datasets: absent, no slice and no network changes; set, the calibration after
    training takes the scenes of those datasets only (rows and images alike), the network is the same one, and a
    dataset it does not train on is refused naming the key."""
    import copy
    from dataclasses import asdict

    from psdfactory.config import load_config, network_recipe, train_params
    from psdfactory.learn.instances.training import calibration_scenes

    cfg = load_config("config/config.yaml")
    off = train_params(cfg, "instances")["settings"]
    assert "calibration_datasets" not in off and InstanceSettings.from_dict(off).calibration_datasets is None
    on_cfg = copy.deepcopy(cfg)
    on_cfg["train"]["instances"]["calibration_datasets"] = ["train"]
    on = train_params(on_cfg, "instances")["settings"]
    assert InstanceSettings.from_dict(on).calibration_datasets == ("train",)
    full = {**train_params(cfg, "instances"), "settings": asdict(InstanceSettings.from_dict(off))}
    assert network_recipe({**full, "settings": asdict(InstanceSettings.from_dict(on))}) == network_recipe(full)

    rows = [{"dataset": d, "scene_id": f"{d}-{i}"} for i, d in enumerate(["a", "b", "a", "b", "b"])]
    x = torch.arange(5, dtype=torch.uint8).reshape(5, 1, 1, 1).expand(5, 3, 2, 2)
    settings = InstanceSettings.from_dict({**off, "calibration_datasets": ["b"]})
    tr, va, xt, xv = calibration_scenes(settings, rows, rows[:2], x, x[:2])
    assert [r["scene_id"] for r in tr] == ["b-1", "b-3", "b-4"] and [r["scene_id"] for r in va] == ["b-1"]
    assert xt[:, 0, 0, 0].tolist() == [1, 3, 4] and xv[:, 0, 0, 0].tolist() == [1]
    everything = calibration_scenes(InstanceSettings.from_dict(off), rows, rows[:2], x, x[:2])
    assert everything[0] is rows and everything[2] is x
    with pytest.raises(PsdError, match="calibration_datasets b: 3 train and 0 val"):
        calibration_scenes(settings, rows, rows[:1], x, x[:1])
    assert calibration_scenes(settings, rows, rows[:2])[2:] == (None, None)  # rows alone: checked before training
    with pytest.raises(PsdError, match="must be a list of dataset names"):
        InstanceSettings.from_dict({**off, "calibration_datasets": "train"})
    # a checkpoint of before 2026-11-28 resumes with it set as without it (the legacy fingerprints ignore it)
    from psdfactory.learn.instances.training import legacy_fingerprints
    from psdfactory.learn.train import TrainParams

    params = TrainParams.from_dict({k: v for k, v in full.items() if k != "settings"})
    ids = [("s-0", "train", 1.0, 2.0, 3.0)]
    assert legacy_fingerprints(params, InstanceSettings.from_dict(on), ids) == \
        legacy_fingerprints(params, InstanceSettings.from_dict(off), ids)

    def elsewhere(raw: dict) -> dict:
        raw["train"]["instances"]["calibration_datasets"] = ["ood_test"]
        return raw

    with pytest.raises(PsdError, match="train.instances.calibration_datasets: 'ood_test' is not one of the datasets"):
        load_config("config/config.yaml", edit=elsewhere)

    def twice(raw: dict) -> dict:
        raw["train"]["instances"]["calibration_datasets"] = ["train", "train"]
        return raw

    with pytest.raises(PsdError, match="train.instances.calibration_datasets: lists a dataset twice"):
        load_config("config/config.yaml", edit=twice)


def test_loss_is_lower_for_the_true_maps_and_crops_keep_targets_aligned():
    mask = discs((32, 32), [(10, 10), (10, 22), (24, 16)], 6)
    t = target_stack(mask, np.array([np.nan, 12.0, 12.0, 30.0]))[None]
    good = torch.stack([(t[:, 0] * 2 - 1) * 8, (t[:, 1] * 2 - 1) * 8, torch.logit(t[:, 2].clamp(0.01, 0.99)),
                        torch.logit(t[:, 3].clamp(0.01, 0.99))], dim=1)
    assert instance_loss(good, t, 3.0)[0] < 0.5 * instance_loss(torch.zeros_like(good), t, 3.0)[0]
    # the size term: in octaves of size on the particles' pixels
    wrong = good.clone()
    wrong[:, 3] = torch.logit(torch.from_numpy(encode_size(np.full((32, 32), 24.0))).float())  # 12 → 24 px: 1 octave
    parts = instance_loss(wrong, t, 3.0)[1]
    share = float(((mask > 0) & (mask < 3)).sum() / (mask > 0).sum())
    assert parts["size"] == pytest.approx(share * 1.0 + (1 - share) * np.log2(30 / 24), rel=0.02)
    # crops turned by flips / rotations: the image and its targets turn together
    img = (t[:, :1].repeat(1, 3, 1, 1) * 255).to(torch.uint8)  # the image is the foreground itself
    gen = torch.Generator().manual_seed(0)
    x, tt = random_crops(img, t, torch.zeros(8, dtype=torch.long), 20, gen)
    assert x.shape == (8, 3, 20, 20) and tt.shape == (8, len(MAPS), 20, 20)
    assert torch.equal(x[:, 0] > 0, tt[:, 0] > 0)
    assert len({tuple(c[0].flatten().tolist()) for c in x}) > 1  # not all the same crop


@pytest.mark.parametrize("s", [2.0, 0.5])
def test_a_zoomed_crop_keeps_its_targets_true_to_the_image(s):
    """Magnified by s: the grains' area grows by s², the size map says s times larger, the
    distance map stays in [0, 1] on the grains, and the boundary stays a line around each grain."""
    mask = discs((64, 64), [(16, 16), (16, 46), (46, 30)], 10)
    sizes = np.array([np.nan, 20.0, 20.0, 20.0])
    t = target_stack(mask, sizes)
    img = torch.from_numpy(np.where(mask > 0, 200, 30).astype(np.uint8))[None].repeat(3, 1, 1)
    size = int(64 * s)
    x, tz = zoom(img, t, size)
    assert x.shape == (3, size, size) and tz.shape == (len(MAPS), size, size) and x.dtype == torch.uint8
    fg = tz[0] > 0
    assert float(fg.sum()) == pytest.approx(float((mask > 0).sum()) * s * s, rel=0.08)
    assert torch.equal(fg, x[0] > 115)  # the image and the foreground agree
    np.testing.assert_allclose(decode_size(tz[3][fg].numpy()), 20.0 * s, rtol=1e-5)
    assert float(tz[2][fg].max()) <= 1.0 and float(tz[2][~fg].abs().max()) == 0.0
    # the boundary: a closed line on each grain (each grain's interior stays apart from the others)
    from scipy import ndimage

    inside = fg.numpy() & (tz[1].numpy() == 0)
    assert ndimage.label(inside)[1] == 3
    assert 0 < float(tz[1].sum()) < 0.5 * float(fg.sum())


def test_zoomed_crops_draw_their_scale_and_unzoomed_ones_are_as_before():
    mask = discs((64, 64), [(16, 16), (16, 46), (46, 30)], 10)
    t = target_stack(mask, np.array([np.nan, 20.0, 20.0, 20.0]))[None]
    img = (t[:, :1].repeat(1, 3, 1, 1) * 255).to(torch.uint8)
    idx = torch.zeros(16, dtype=torch.long)
    a = random_crops(img, t, idx, 32, torch.Generator().manual_seed(3))
    b = random_crops(img, t, idx, 32, torch.Generator().manual_seed(3), scale=(1.0, 1.0))
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])  # off: the same draws as without it
    x, tt = random_crops(img, t, idx, 32, torch.Generator().manual_seed(3), scale=(0.6, 1.8))
    fg = tt[:, 0] > 0
    sizes = [float(np.median(decode_size(tt[i, 3][fg[i]].numpy()))) for i in range(16) if fg[i].any()]
    assert min(sizes) < 20.0 * 0.9 and max(sizes) > 20.0 * 1.1  # grains drawn smaller and larger
    assert all(20.0 * 0.6 * 0.99 <= v <= 20.0 * 1.8 * 1.01 for v in sizes)


def test_readout_recovers_a_linear_map_and_orders_the_targets():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(40, len(STAT_NAMES)))
    w = rng.normal(size=(len(STAT_NAMES), 3))
    used = np.isin(STAT_NAMES, READOUT_FEATURES)
    w[~used] = 0.0  # the labels depend on the read-out's features only
    y = x @ w * 0.05 + np.array([3.0, 8.0, 14.0])  # small slopes: already ordered
    ro = fit_readout(x, y, alphas=(1e-6,))
    assert json.loads(json.dumps(ro)) == ro  # plain types only
    assert ro["features"] == list(READOUT_FEATURES)
    assert apply_readout(ro, x) == pytest.approx(y, abs=1e-3)
    x2 = x.copy()
    x2[:, ~used] *= 100  # the field of view's statistics (edge fraction, mm/px) change nothing
    assert apply_readout(ro, x2) == pytest.approx(apply_readout(ro, x))
    xn = x.copy()
    xn[0, 2] = np.nan  # imputed, not propagated
    assert np.isfinite(apply_readout(ro, xn)).all()
    p = apply_readout(ro, rng.normal(size=(50, len(STAT_NAMES))) * 30)
    assert (np.diff(p, axis=1) >= 0).all()



def test_a_readout_reads_the_size_map_for_the_targets_it_names_only():
    from psdfactory.learn.instances.estimator import readout_problems
    from psdfactory.learn.instances.stats import MAP_READOUT_FEATURES, READOUT_TARGET_FEATURES

    rng = np.random.default_rng(3)
    x = rng.normal(size=(60, len(STAT_NAMES)))
    y = x[:, :3] * 0.3 + x[:, [STAT_NAMES.index("map_d90_mm")] * 3] * 0.5 + [3.0, 8.0, 14.0]
    name = "footprints+size_map_d10_d50"
    features, per_target = READOUTS[name], READOUT_TARGET_FEATURES[name]
    assert features == MAP_READOUT_FEATURES and per_target[2] == READOUT_FEATURES
    ro = fit_readout(x, y, alphas=(1e-3,), features=features, target_features=per_target)
    assert json.loads(json.dumps(ro)) == ro
    assert ro["target_features"] == [list(t) for t in per_target] and ro["features"] == list(features)
    w = np.asarray(ro["weights"])
    on_map = [1 + features.index(f) for f in features if f.startswith("map_")]
    assert np.abs(w[on_map, :2]).max() > 0.1 and (w[on_map, 2] == 0).all()  # d10, d50 read the map; d90 not
    # each group is the read-out of its own statistics: d90 as the footprints alone read it, d10/d50 as the map
    foot = fit_readout(x, y, alphas=(1e-3,), features=READOUT_FEATURES)
    both = fit_readout(x, y, alphas=(1e-3,), features=features)
    kept = [0, *(1 + features.index(f) for f in READOUT_FEATURES)]
    assert w[kept, 2] == pytest.approx(np.asarray(foot["weights"])[:, 2])
    assert w[:, :2] == pytest.approx(np.asarray(both["weights"])[:, :2])
    assert ro["cv_r2"][2] == pytest.approx(foot["cv_r2"][2]) and ro["cv_r2"][:2] == pytest.approx(both["cv_r2"][:2])
    assert readout_problems({"postprocess": {"threshold": 0.5, "h": 0.1, "min_distance": 3, "min_area_px": 4},
                             "maps": list(MAPS), "sieve_method": "min_feret", "readout": ro}) == []
    bad = {**ro, "target_features": [["d10_mm"], ["not_a_stat"], ["d90_mm"]]}
    assert any("target_features" in p for p in readout_problems({"maps": list(MAPS), "readout": bad}))
    with pytest.raises(ValueError, match="not among its features"):
        fit_readout(x, y, features=READOUT_FEATURES, target_features=per_target)
    with pytest.raises(ValueError, match="2 targets"):
        fit_readout(x, y, features=features, target_features=per_target[:2])
    with pytest.raises(ValueError, match="twice"):
        fit_readout(x, y, features=features, target_features=(*per_target[:2], ("d90_mm", "d90_mm")))
    # each group picks its own ridge strength: a list, one per target, where they differ
    picked = fit_readout(x, y, features=features, target_features=per_target)["alpha"]
    assert isinstance(picked, list) and len(picked) == 3 and picked[0] == picked[1]


def test_a_readout_names_the_statistics_it_would_extrapolate_from():
    from psdfactory.learn.readout import DOMAIN_MARGIN, outside_domain

    rng = np.random.default_rng(1)
    x = rng.uniform(0, 1, size=(30, len(STAT_NAMES)))
    ro = fit_readout(x, x[:, :3] + [1.0, 2.0, 3.0])
    lo, hi = np.asarray(ro["lo"]), np.asarray(ro["hi"])
    assert outside_domain(ro, x[:1]) == []
    j, k = STAT_NAMES.index("d50_mm"), ro["features"].index("d50_mm")
    near, beyond, far = x[:1].copy(), x[:1].copy(), x[:1].copy()
    near[0, j] = hi[k] + 0.9 * DOMAIN_MARGIN * (hi[k] - lo[k])  # within the margin: still inside
    beyond[0, j] = hi[k] + 1.1 * DOMAIN_MARGIN * (hi[k] - lo[k])
    far[0, j] = 5.0
    assert outside_domain(ro, near) == []
    assert [n.split()[0] for n in outside_domain(ro, beyond)] == ["d50_mm"]
    (named,) = outside_domain(ro, far)
    assert named.startswith("d50_mm 5 (fitted ") and f"to {hi[ro['features'].index('d50_mm')]:.3g})" in named
    low = x[:1].copy()
    low[0, STAT_NAMES.index("log_density")] = lo[ro["features"].index("log_density")] - 2
    assert [n.split()[0] for n in outside_domain(ro, low)] == ["log_density"]
    unused = x[:1].copy()
    unused[0, STAT_NAMES.index("mm_per_px")] = 50.0  # not a read-out feature
    assert outside_domain(ro, unused) == []
    old = {k: v for k, v in ro.items() if k not in ("lo", "hi")}  # fitted before ranges were recorded
    assert outside_domain(old, far) == []
    flat = {**ro, "hi": list(ro["lo"])}  # a feature constant where it was fitted: no range to judge by
    assert outside_domain(flat, far) == []
    # a model's meta: the new keys are optional, and checked where present
    from psdfactory.learn.instances.estimator import _one_readout_problems

    def nums(v, n):
        return isinstance(v, list) and len(v) == n and all(isinstance(e, (int, float)) for e in v)

    assert _one_readout_problems("readout", ro, ["size"], nums) == []
    assert _one_readout_problems("readout", old, ["size"], nums) == []
    assert _one_readout_problems("readout", {**ro, "lo": [1.0]}, ["size"], nums) == [
        f"readout.lo must be {len(ro['features'])} numbers or absent"]
    assert _one_readout_problems("readout", {**ro, "ratio_lo": [0.5, -1.0, 0.9]}, ["size"], nums) == [
        "readout.ratio_lo and ratio_hi must be > 0"]
    assert _one_readout_problems("readout", {**ro, "ratio_hi": None}, ["size"], nums) == [
        "readout.ratio_lo and ratio_hi go together"]


def test_a_readout_corrects_the_visible_grains_no_more_than_it_learnt(tmp_path):
    """A read-out fitted on 3-6 px grains extrapolates on 40 px grains: its linear fit alone reads a
    d10 below zero there. Each target is held within the label / visible-size ratios of the scenes
    it was fitted on, and the statistics it extrapolates from are named."""
    from psdfactory.learn.instances.estimator import InstanceEstimator

    def grid(side: int, n: int) -> np.ndarray:
        m = np.zeros((n * (side + 2), n * (side + 2)), np.uint16)
        for k, (i, j) in enumerate(np.ndindex(n, n), start=1):
            m[i * (side + 2) + 1 : i * (side + 2) + 1 + side, j * (side + 2) + 1 : j * (side + 2) + 1 + side] = k
        return m

    base = {"postprocess": DEFAULT_POSTPROCESS, "size_definition": "sieve", "weighting": "number"}
    x = np.stack([InstanceEstimator(base).result(grid(side, 8), 1.0).stats for side in (3, 4, 5, 6, 7, 8)])
    seen = x[:, [STAT_NAMES.index(c) for c in ("d10_mm", "d50_mm", "d90_mm")]]
    # labels that fall behind the grains as they grow: a linear fit crosses zero on larger grains
    y = seen * np.array([0.8, 1.0, 1.3]) - np.array([0.3, 0.2, 0.1]) * seen**2 / seen.mean(axis=0)
    ro = fit_readout(x, y, alphas=(1e-6,))
    ratio = y / seen
    assert ro["ratio_lo"] == pytest.approx(ratio.min(axis=0).tolist())
    assert ro["ratio_hi"] == pytest.approx(ratio.max(axis=0).tolist())
    unheld = {k: v for k, v in ro.items() if k not in ("ratio_lo", "ratio_hi")}  # as fitted before the ratios
    inside = apply_readout(unheld, x)
    held = np.clip(inside, seen * ratio.min(axis=0), seen * ratio.max(axis=0))
    assert apply_readout(ro, x) == pytest.approx(np.sort(held, axis=1))  # where it was fitted: within a hair
    assert np.abs(held - inside).max() < 0.05 * np.abs(inside).max()
    est = InstanceEstimator({**base, "readout": ro, "readouts": {"c-axis": ro}})
    inside = est.result(grid(5, 8), 1.0)
    assert inside.readout_outside == ()
    big = est.result(grid(40, 3), 1.0)
    assert apply_readout(unheld, big.stats[None])[0][0] < 0  # the linear fit alone: a d10 below zero
    assert any(n.startswith("d50_mm") for n in big.readout_outside)
    assert big.calibrated == pytest.approx(np.sort(big.raw * np.asarray(ro["ratio_lo"])))  # held at the least
    assert np.all(big.calibrated > 0)
    assert est.in_definition(est.reading(big), "c-axis", "number", "big.png") == pytest.approx(big.calibrated)

def test_fully_visible_excludes_edge_and_lower_particles():
    mask = np.zeros((20, 30), dtype=np.uint16)
    mask[5:10, 5:10] = 1  # alone
    mask[5:10, 15:20] = 2  # touches 3, which lies higher
    mask[5:10, 20:25] = 3
    mask[15:20, 10:14] = 4  # touches the edge
    z = np.array([-np.inf, 1.0, 1.0, 2.0, 1.0])
    assert fully_visible(mask, z).tolist() == [False, True, False, True, False]


def test_resize_mask_keeps_ids():
    mask = discs((16, 16), [(5, 5), (10, 11)], 3)
    big = resize_mask(mask, (32, 48))
    assert big.shape == (32, 48) and set(np.unique(big)) == set(np.unique(mask))
    maps = np.stack([mask, mask * 2]).astype(np.float32)  # a stack of maps: each resized alike
    assert np.array_equal(resize_mask(maps, (32, 48)), np.stack([big, big * 2]))


def test_train_params_slice_has_the_instance_settings_only_for_instances():
    cfg = tiny_config()
    assert "settings" not in psd_config.train_params(cfg, "resnet50")
    p = psd_config.train_params(cfg, "instances")
    assert p["settings"]["crops_per_image"] >= 1 and p["input_size"] == 128
    assert p["epochs"] == cfg["train"]["epochs"] and "epochs" not in p["settings"]  # null: train.epochs
    cfg["train"]["instances"]["epochs"] = cfg["train"]["epochs"] + 7  # its own length, the CNNs' unchanged
    assert psd_config.train_params(cfg, "instances")["epochs"] == cfg["train"]["epochs"] + 7
    assert psd_config.train_params(cfg, "resnet50")["epochs"] == cfg["train"]["epochs"]


def test_the_instance_estimator_can_train_on_more_datasets_than_the_cnns():
    """train.instances.datasets: the grain finder's own training data (more scene families), the
    CNNs' unchanged; null keeps train.datasets; the training rule's inputs follow it."""
    cfg = tiny_config()
    assert psd_config.train_params(cfg, "instances")["datasets"] == cfg["train"]["datasets"]
    raw = {"seed": 1, "datasets": {"tiny": {"n_scenes": 4}, "beds": {"n_scenes": 4, "shape": "granule"}},
           "train": {"datasets": ["tiny"], "architectures": ["resnet50", "instances"],
                     "instances": {"datasets": ["tiny", "beds"]}}}
    cfg = psd_config.validate(raw)
    assert psd_config.train_params(cfg, "instances")["datasets"] == ["tiny", "beds"]
    assert "datasets" not in psd_config.train_params(cfg, "instances")["settings"]
    assert psd_config.train_params(cfg, "resnet50")["datasets"] == ["tiny"]
    assert psd_config.trained_datasets(cfg) == ["tiny", "beds"]  # what the report counts as trained on
    raw["train"]["architectures"] = ["resnet50"]
    assert psd_config.trained_datasets(psd_config.validate(raw)) == ["tiny"]
    raw["train"]["instances"]["datasets"] = ["tiny", "nope"]  # checked whether it is trained now or not
    with pytest.raises(PsdError, match="train.instances.datasets: 'nope' is not one of the configured datasets"):
        psd_config.validate(raw)


# ---------------------------------------------------------------------------------------------
# one tiny training run, then everything downstream of it


def tiny_instance_params(cfg: dict) -> dict:
    """The instance estimator's training slice of `cfg` (the schema's defaults), one tiny epoch."""
    params = psd_config.train_params(cfg, "instances")
    params.update(pretrained="none", epochs=1, batch_size=2, input_size=32, precision="fp32", seed=1)
    params["settings"].update(crops_per_image=2)
    return params


@pytest.fixture()
def few_grains_read(monkeypatch):
    """The tiny fixture's one-epoch model finds no whole grain on a 48 px scene (one frame-filling "grain"), and
    predict refuses such a reading (``predict.grain_count_problem``, tested in test_predict_inputs.py): the tests
    of predict's machinery below read it all the same."""
    from psdfactory.deploy import predict

    monkeypatch.setattr(predict, "grain_count_problem", lambda *a: (None, None))


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """Two tiny 48-px scenes (train, val), their manifests, and one epoch of training."""
    from psdfactory.learn.train import train_from_params

    cfg = tiny_config(n_scenes=2, count=[15, 25])
    cfg["render"]["resolution"] = 48
    root = tmp_path_factory.mktemp("res")
    dirs = [make_scene(cfg, root / "tiny" / "scenes" / f"tiny-{i:06d}", index=i) for i in range(2)]
    m = root / "tiny" / "manifest"
    out = m / "scenes" / "shard-00000.parquet"
    write_shard(dirs, root, {"train": 1.0}, out, m / "particles" / "shard-00000.parquet")
    t = pq.read_table(out)
    pq.write_table(t.set_column(t.schema.get_field_index("split"), "split", pa.array(["train", "val"])), out)
    params = tiny_instance_params(cfg)
    model_dir = root / "models" / "instances"
    summary = train_from_params(params, root, model_dir)
    return root, model_dir / "model.pt", summary


def test_tiny_training_writes_a_plain_model_file(tiny):
    from psdfactory.learn.runtime import load_model

    root, model_path, summary = tiny
    ckpt = torch.load(model_path, map_location="cpu", weights_only=True)  # tensors and plain types only
    meta = ckpt["meta"]
    assert meta["arch"] == "instances" and meta["input_size"] == 48 and meta["crop_size"] == 32
    assert meta["mm_per_px"] == pytest.approx(60 / 48)
    assert len(meta["readout"]["weights"]) == len(meta["readout"]["features"]) + 1
    assert set(meta["postprocess"]) >= {"threshold", "h"} and meta["maps"] == list(MAPS)
    assert meta["sieve_method"] == "min_feret"  # the schema default: the size map is measured, not (yet) better
    assert meta["tta"] == "none"  # the schema default: calibrated on the maps of the image alone, as it is run
    assert meta["auto_scale"] is False  # the schema default: predict reads photos at the model's scale
    # the read-out reads what train.instances.readout names, fitted on the train and the val scene
    assert meta["readout"]["features"] == list(READOUTS[meta["readout_features"]])
    assert meta["readout"]["n_scenes"] == 2
    model, meta2 = load_model(model_path)
    assert isinstance(model, InstanceNet)
    assert meta2["readout"] == meta["readout"] and meta2["postprocess"] == meta["postprocess"]
    with open(model_path.parent / "history.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 1 and float(rows[0]["train_loss"]) > 0


def test_training_on_the_grains_in_view_teaches_glimpses_as_background(tiny, tmp_path):
    """train.instances.min_visible_share: the targets (and the validation masks the post-processing is picked on)
    hold the particles enough of which is in view; the training runs on them end to end."""
    from psdfactory.learn.data import particles_by_scene, training_rows
    from psdfactory.learn.instances.targets import load_scenes
    from psdfactory.learn.train import train_from_params
    from psdfactory.manifest import PARTICLE_READ_COLUMNS

    root, _, summary = tiny
    train_rows, _, _ = training_rows(root, ["tiny"])
    particles = particles_by_scene(root, ["tiny"], PARTICLE_READ_COLUMNS + ("ecd_mm",))
    fg = {share: float(load_scenes(root, train_rows, particles, share)[1][:, 0].sum()) for share in (0.0, 0.5, 1.0)}
    assert fg[0.0] >= fg[0.5] >= fg[1.0] and fg[0.0] > fg[1.0]  # fewer grains taught the more must be in view
    assert fg[0.0] == float(load_scenes(root, train_rows, particles)[1][:, 0].sum())
    with pytest.raises(PsdError, match="min_visible_share"):
        load_scenes(root, train_rows, None, 0.5)
    cfg = tiny_config(n_scenes=2, count=[15, 25])
    cfg["render"]["resolution"] = 48
    params = tiny_instance_params(cfg)
    params["settings"]["min_visible_share"] = 0.5
    params["settings"]["surface_texture"] = 1.0  # and texture on the grains it learns (augment.surface_texture)
    train_from_params(params, root, tmp_path / "instances")
    meta = torch.load(tmp_path / "instances" / "model.pt", map_location="cpu", weights_only=True)["meta"]
    assert meta["readout"]["n_scenes"] == 2 and set(meta["postprocess"]) >= {"threshold", "h"}
    assert meta["min_visible_share"] == 0.5 and meta["surface_texture"] == 1.0
    # calibrated again, it keeps the grains it learnt: another share is another network
    from psdfactory.learn.instances.training import recalibrate

    settings = {k: v for k, v in params["settings"].items() if k not in ("epochs", "datasets")}
    other = InstanceSettings.from_dict({**settings, "min_visible_share": 0})
    with pytest.raises(PsdError, match="min_visible_share 0.5, not 0"):
        recalibrate(tmp_path / "instances" / "model.pt", other, root, tmp_path / "again.pt", InstanceEstimator, "cpu")
    with pytest.raises(PsdError, match="ecd_mm"):
        load_scenes(root, train_rows, particles_by_scene(root, ["tiny"]), 0.5)


def test_a_trained_network_calibrated_again_under_other_views_keeps_its_weights(tiny, tmp_path):
    """recalibrate: the same network, the post-processing and read-out made again from its maps averaged over the
    views train.instances.tta names (bench/seed_spread.py --recalibrate-from); the network recipe is blind to those
    settings and to nothing else."""
    from psdfactory.learn.instances.training import recalibrate
    from psdfactory.learn.runtime import load_model

    root, model_path, summary = tiny
    params = summary["params"]
    cfg = tiny_config(n_scenes=2, count=[15, 25])
    settings = {**psd_config.train_params(cfg, "instances")["settings"], "tta": "d4"}
    settings.pop("epochs", None), settings.pop("datasets", None)
    settings["auto_scale"] = True
    meta, val_mae = recalibrate(model_path, InstanceSettings.from_dict(settings), root, tmp_path / "model.pt",
                                InstanceEstimator, "cpu")
    assert meta["tta"] == "d4" and meta["recalibrated_from"] == str(model_path) and val_mae >= 0
    assert meta["auto_scale"] is True  # predict's default reading is the new settings', not the source's
    assert meta["calibration_datasets"] == ["tiny"]  # all it trained on, where the settings name none
    assert meta["mm_per_px"] == summary["mm_per_px"]  # the scale of the scenes it is calibrated on: the same ones
    with pytest.raises(PsdError, match="calibration_datasets other: .* was not trained on it"):
        recalibrate(model_path, InstanceSettings.from_dict({**settings, "calibration_datasets": ["other"]}), root,
                    tmp_path / "other.pt", InstanceEstimator, "cpu")
    assert meta["readout"]["n_scenes"] == 2 and set(meta["postprocess"]) >= {"threshold", "h"}
    before = torch.load(model_path, map_location="cpu", weights_only=True)["state_dict"]
    after = torch.load(tmp_path / "model.pt", map_location="cpu", weights_only=True)["state_dict"]
    assert before.keys() == after.keys() and all(torch.equal(before[k], after[k]) for k in before)
    model, meta2 = load_model(tmp_path / "model.pt")
    assert InstanceEstimator(meta2).views == TTA_VIEWS["d4"]
    # a seed_spread run that differs in a calibration setting shares its network; one that differs in what the
    # network learns does not
    mine = {**params, "settings": dict(settings)}
    assert psd_config.network_recipe({**mine, "settings": {**settings, "tta": "none", "readout": "footprints"}}) \
        == psd_config.network_recipe(mine)
    assert psd_config.network_recipe({**mine, "settings": {**settings, "lr": 0.5}}) != psd_config.network_recipe(mine)
    assert psd_config.network_recipe({**mine, "seed": 2}) != psd_config.network_recipe(mine)


def test_training_again_with_other_views_calibrates_the_finished_network_without_training_it(tiny, caplog):
    """train.instances.tta edited in the config: the train rule reruns, finds the finished training of the same
    network in its checkpoints and only calibrates it again (its history has no new epoch)."""
    import logging
    import shutil

    from psdfactory.learn.train import train_from_params

    root, model_path, summary = tiny
    out = root / "models" / "instances_views"
    shutil.copytree(model_path.parent, out)
    cfg = tiny_config(n_scenes=2, count=[15, 25])
    params = tiny_instance_params(cfg)
    params["settings"]["tta"] = "flips"
    with caplog.at_level(logging.INFO):
        meta = train_from_params(params, root, out)
    assert meta["tta"] == "flips" and meta["epochs_run"] == 1 == summary["epochs_run"]
    assert "resuming" in caplog.text and "ignoring" not in caplog.text
    before = torch.load(model_path, map_location="cpu", weights_only=True)["state_dict"]
    after = torch.load(out / "model.pt", map_location="cpu", weights_only=True)["state_dict"]
    assert all(torch.equal(before[k], after[k]) for k in before)
    # a checkpoint written before 2026-11-28, whose fingerprint held the calibration settings, resumes as well
    from dataclasses import asdict

    from psdfactory.learn.data import training_rows
    from psdfactory.learn.fit import fingerprint
    from psdfactory.learn.runtime import load_checkpoint, write_torch
    from psdfactory.learn.train import TrainParams
    from psdfactory.psd import TARGETS

    p = dict(params)
    old_settings = {**asdict(InstanceSettings.from_dict(p.pop("settings"))), "tta": "none"}
    ck = load_checkpoint(out / "checkpoints" / "last.pt", "training checkpoint")
    rows = [(r["scene_id"], r["split"], *(r[t] for t in TARGETS)) for r in training_rows(root, params["datasets"])[2]]
    ck["fingerprint"] = fingerprint(psd_config.training_recipe({**asdict(TrainParams.from_dict(p)),
                                                                "settings": old_settings}), rows)
    write_torch(out / "checkpoints" / "last.pt", ck)
    caplog.clear()
    with caplog.at_level(logging.INFO):
        assert train_from_params(params, root, out)["epochs_run"] == 1
    assert "resuming" in caplog.text and "ignoring" not in caplog.text
    params["settings"]["lr"] = 0.01  # what the network learns: trained anew
    caplog.clear()
    with caplog.at_level(logging.INFO):
        train_from_params(params, root, out)
    assert "ignoring" in caplog.text


def test_readout_of_footprints_and_size_map(tiny, tmp_path, few_grains_read):
    """train.instances.readout picks the read-out's statistics: the size map's too, for every target or for d10
    and d50 only, or not."""
    from psdfactory.learn.capability import detect
    from psdfactory.learn.instances.estimator import readout_problems
    from psdfactory.learn.instances.stats import READOUT_TARGET_FEATURES
    from psdfactory.learn.train import train_from_params

    root, model_path, _ = tiny
    meta = torch.load(model_path, map_location="cpu", weights_only=True)["meta"]
    assert meta["readout_features"] == "footprints"
    cfg = tiny_config(n_scenes=2, count=[15, 25])
    cfg["render"]["resolution"] = 48
    params = tiny_instance_params(cfg)
    with pytest.raises(PsdError, match="train.instances.readout"):
        InstanceSettings.from_dict({**params["settings"], "readout": "pixels"})
    assert not any(f.startswith("map_") for f in meta["readout"]["features"])
    for other in ("footprints+size_map", "footprints+size_map_d10_d50"):
        params["settings"] = {**params["settings"], "readout": other}
        out = tmp_path / other.replace("+", "-")
        summary = train_from_params(params, root, out)
        ro = summary["readout"]
        assert summary["readout_features"] == other and ro["features"] == list(READOUTS[other])
        assert any(f.startswith("map_") for f in ro["features"])
        per_target = READOUT_TARGET_FEATURES[other]
        assert ro.get("target_features", [list(per_target[0])] * 3) == [list(t) for t in per_target]
        map_rows = [1 + ro["features"].index(f) for f in ro["features"] if f.startswith("map_")]
        reads_map = [any(f.startswith("map_") for f in t) for t in per_target]
        assert [bool(np.any(np.asarray(ro["weights"])[map_rows, t])) for t in range(3)] == reads_map
        assert all(summary["readouts"][d].get("target_features") == ro.get("target_features")
                   for d in summary["readouts"])  # the other size definitions read as their own

        # the size map's read-out in deployment: predict reads it the same through PyTorch and ONNX;
        # a network without a size map cannot carry it
        assert readout_problems(summary) == []
        assert any("size map" in p for p in readout_problems({**summary, "maps": ["foreground", "boundary",
                                                                                  "distance"]}))
        if detect().onnxruntime:
            from psdfactory.deploy.export import export
            from psdfactory.deploy.predict import predict_files

            export(out / "model.pt", out / "onnx")
            img = str(root / "tiny" / "scenes" / "tiny-000001" / "image.png")
            ref = predict_files(out / "model.pt", [img])[0]
            got = predict_files(out / "onnx" / "model.onnx", [img])[0]
            keys = ("d10_mm", "d50_mm", "d90_mm")
            assert not got["error"] and [got[k] for k in keys] == pytest.approx([ref[k] for k in keys], abs=1e-3)


def test_precision_auto_times_bf16_against_fp32_and_trains_in_the_faster(tiny, tmp_path, monkeypatch):
    """On a CPU with native bf16, `precision: auto` times one batch of the instance network in
    each (as for the CNNs) and trains in the faster; calibration maps stay fp32."""
    from psdfactory.learn import runtime
    from psdfactory.learn.train import train_from_params

    root, _, _ = tiny
    calls = []

    def timed(model, size, batch, loss_of):
        out = model(torch.zeros(batch, 3, size, size))
        loss = loss_of(out)  # the instance loss of the network's maps: a finite scalar
        calls.append((size, batch, float(loss)))
        return "bf16"

    monkeypatch.setattr(runtime, "cpu_has_fast_bf16", lambda: True)
    monkeypatch.setattr(runtime, "faster_cpu_precision", timed)
    from psdfactory.learn.instances import training as instance_training

    maps_precision = []
    real_runner = instance_training.torch_runner
    monkeypatch.setattr(instance_training, "torch_runner",
                        lambda module, device, precision="fp32": maps_precision.append(precision)
                        or real_runner(module, device, precision))
    cfg = tiny_config(n_scenes=2, count=[15, 25])
    cfg["render"]["resolution"] = 48
    params = {**tiny_instance_params(cfg), "precision": "auto"}
    summary = train_from_params(params, root, tmp_path / "auto")
    assert len(calls) == 1 and calls[0][:2] == (32, 2) and np.isfinite(calls[0][2])
    assert summary["precision"] == "bf16"  # trained under bf16 autocast, to a finite loss
    assert maps_precision == ["fp32"]  # the calibration's maps, as evaluate and predict make them
    with open(tmp_path / "auto" / "history.csv") as f:
        assert np.isfinite(float(next(csv.DictReader(f))["train_loss"]))


def test_predict_writes_overlays_masks_and_particles(tiny, tmp_path, capsys, few_grains_read):
    from PIL import Image

    from psdfactory.cli import main
    from psdfactory.deploy.predict import PARTICLE_COLUMNS

    root, model_path, _ = tiny
    scenes = root / "tiny" / "scenes"
    args = ["predict", "--model", str(model_path), "--out", str(tmp_path / "p.csv"), "--overlay", str(tmp_path / "ov"),
            "--masks", str(tmp_path / "masks"), "--particles", str(tmp_path / "particles.csv"), str(scenes)]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "d10_mm" in out and out.count("image.png") == 2
    with open(tmp_path / "p.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["image"].split("/")[-2] for r in rows] == ["tiny-000000", "tiny-000001"]
    assert list(rows[0]) == ["image", "d10_mm", "d50_mm", "d90_mm", "size_definition", "weighting", "error",
                            "warning"]
    assert {(r["size_definition"], r["weighting"]) for r in rows} == {("sieve", "number")}  # the labels' definition
    assert all(float(r["d10_mm"]) <= float(r["d50_mm"]) <= float(r["d90_mm"]) for r in rows)
    with open(tmp_path / "particles.csv") as f:
        parts = list(csv.DictReader(f))
    assert not (tmp_path / "particles.csv.partial.csv").exists()
    for scene in ("tiny-000000", "tiny-000001"):  # both images are called image.png: the folder names them
        with Image.open(tmp_path / "masks" / f"{scene}_image.png") as im:
            assert im.mode in ("I;16", "I;16B", "I;16L") and im.size == (48, 48)
            mask = np.asarray(im)
        with Image.open(tmp_path / "ov" / f"{scene}_image.png") as im:
            assert im.mode == "RGB" and im.size == (48, 48)
        ids = sorted(int(p["id"]) for p in parts if f"/{scene}/" in p["image"])
        assert ids == sorted(set(np.unique(mask)) - {0})
    for folder in ("masks", "ov"):  # each output folder says which image each file belongs to
        with open(tmp_path / folder / "index.csv") as f:
            index = {Path(r["image"]).parent.name: r["file"] for r in csv.DictReader(f)}
        assert index == {"tiny-000000": "tiny-000000_image.png", "tiny-000001": "tiny-000001_image.png"}
    assert parts == [] or list(parts[0]) == PARTICLE_COLUMNS
    # --resume skips both images, and the particle table keeps their rows
    assert main([*args[:-1], "--resume", str(scenes)]) == 0
    with open(tmp_path / "particles.csv") as f:
        assert sorted(map(str, csv.DictReader(f))) == sorted(map(str, parts))
    # an image at another scale is resized to the model's, and its mask written at the image's own size
    img = np.asarray(Image.open(scenes / "tiny-000000" / "image.png"))
    big = tmp_path / "big.png"
    Image.fromarray(np.repeat(np.repeat(img, 2, axis=0), 2, axis=1)).save(big)
    assert main(["predict", "--model", str(model_path), "--mm-per-px", str(60 / 96), "--masks", str(tmp_path / "m2"),
                 str(big)]) == 0
    with Image.open(tmp_path / "m2" / "big.png") as im:
        assert im.size == (96, 96)


def test_predict_reads_every_size_definition(tiny, tmp_path, few_grains_read):
    """The model reads its own definition (sieve), estimates the other solid ones with their own
    read-outs, and measures the footprint ones on the whole grains it finds."""
    from psdfactory import PsdError
    from psdfactory.deploy.predict import predict_files
    from psdfactory.psd import SIZE_DEFINITIONS, SOLID_DEFINITIONS, TARGETS, weighted_percentiles

    root, model_path, _ = tiny
    meta = torch.load(model_path, map_location="cpu", weights_only=True)["meta"]
    assert meta["size_definition"] == "sieve" and meta["weighting"] == "number"
    assert set(meta["readouts"]) == set(SOLID_DEFINITIONS) - {"sieve"}
    img = root / "tiny" / "scenes" / "tiny-000000" / "image.png"
    rows = {d: predict_files(model_path, [img], size_definition=d)[0] for d in SOLID_DEFINITIONS}
    for d, r in rows.items():
        assert r["error"] == "" and r["size_definition"] == d, (d, r)
        assert r["d10_mm"] <= r["d50_mm"] <= r["d90_mm"], d
    # another definition's read-out differs from the model's own: it is fitted to other labels
    assert [rows["esd"][t] for t in TARGETS] != [rows["sieve"][t] for t in TARGETS]
    # the footprint definitions are measured on the whole grains found (this one-epoch network
    # finds few, so on a mask made here): a 6 × 2 px and a 4 × 4 px grain, and one on the edge
    from types import SimpleNamespace

    from psdfactory.learn.estimator import Reading

    mask = np.zeros((12, 12), np.int32)
    mask[2:4, 2:8], mask[6:10, 6:10], mask[0:3, 10:12] = 1, 2, 3
    res = SimpleNamespace(measurements=measure_instances(mask, 0.5), calibrated=np.array([1.0, 2.0, 3.0]))
    out = InstanceEstimator(meta)
    got = {d: out.in_definition(Reading(res.calibrated, res), d, "number", str(img)) for d in SIZE_DEFINITIONS
           if d in ("feret-min", "feret-max", "ecd", "sieve")}
    np.testing.assert_array_equal(got["sieve"], [1.0, 2.0, 3.0])  # the model's own: its calibrated read-out
    m = res.measurements  # grain 3 touches the edge: left out
    for d, col in (("feret-min", m.min_feret_mm), ("feret-max", m.max_feret_mm), ("ecd", m.eq_diameter_mm)):
        np.testing.assert_allclose(got[d], weighted_percentiles(col[:2], None))
    assert got["feret-min"][1] < got["ecd"][1] < got["feret-max"][1]
    mask[mask != 3] = 0
    with pytest.raises(PsdError, match="no whole grain found"):
        out.in_definition(Reading(np.zeros(3), SimpleNamespace(measurements=measure_instances(mask, 0.5))),
                          "ecd", "number", str(img))


def test_a_grain_finder_calibrated_to_mass_weighted_references_corrects_its_grains_measured_by_volume(
        tiny, tmp_path, monkeypatch, few_grains_read):
    """calibrate --weighting volume (a sieve analysis): a model that reads its solid definitions number-weighted only
    takes the grains it found, measured by volume (min Feret width; ecd for esd), and predict with the calibrated
    model corrects that reading, labelled as the references are."""
    from types import SimpleNamespace

    from psdfactory.deploy.calibrate import references_reading
    from psdfactory.deploy.predict import predict_files
    from psdfactory.learn import calibration as cal
    from psdfactory.learn.runtime import write_torch

    root, model_path, _ = tiny
    ckpt = torch.load(model_path, map_location="cpu", weights_only=True)
    est = SimpleNamespace(meta=ckpt["meta"], reads=InstanceEstimator.reads)
    for asked, want in [(("sieve", None), ("sieve", "number")), (("sieve", "volume"), ("feret-min", "volume")),
                        (("esd", "area"), ("ecd", "area")), (("ecd", "volume"), ("ecd", "volume"))]:
        what, basis = references_reading(est, *asked)
        assert (what["size_definition"], what["weighting"]) == (asked[0], asked[1] or "number")
        assert (basis["size_definition"], basis["weighting"]) == want, asked

    readings = {("feret-min", "volume"): np.array([2.0, 4.0, 8.0]), ("sieve", "number"): np.array([1.0, 1.5, 2.0])}
    monkeypatch.setattr(InstanceEstimator, "in_definition", lambda self, found, d, w, where: readings[(d, w)])
    refs = np.array([[3.0, 5.0, 9.0], [4.0, 6.0, 10.0], [6.0, 9.0, 15.0]])
    block = cal.calibration_block(["a", "b", "c"], refs / 2 - 0.5, refs, "sieve", "volume", None,
                                  "2025-01-01T00:00:00+00:00", "0.1.0",
                                  basis={"size_definition": "feret-min", "weighting": "volume"})
    write_torch(tmp_path / "cal.pt", {**ckpt, "meta": {**ckpt["meta"], "calibration": block}})
    img = root / "tiny" / "scenes" / "tiny-000000" / "image.png"
    row = predict_files(tmp_path / "cal.pt", [img])[0]
    assert row["error"] == "" and (row["size_definition"], row["weighting"]) == ("sieve", "volume")
    np.testing.assert_allclose([row["d10_mm"], row["d50_mm"], row["d90_mm"]], 2 * (readings[("feret-min", "volume")]
                                                                                   + 0.5), rtol=1e-9)
    assert predict_files(model_path, [img])[0]["d50_mm"] == pytest.approx(1.5)  # uncalibrated: its own reading


def test_evaluate_writes_segmentation_and_size_figures(tiny, tmp_path):
    from psdfactory.learn.evaluate import evaluate

    root, model_path, _ = tiny
    res = evaluate(model_path, root, ["tiny"], tmp_path / "ev")
    m = json.loads((tmp_path / "ev" / "metrics.json").read_text())["datasets"]["tiny"]
    assert res["arch"] == "instances" and m["n"] == 2 and m["split"] == "all"
    assert {"d10", "d50", "d90", "overall", "raw", "segmentation", "size_error"} <= set(m)
    seg = m["segmentation"]
    assert seg["n_true"] > 0 and seg["iou"] == 0.5
    assert seg["recall"] == pytest.approx(seg["n_matched"] / seg["n_true"])
    assert seg["n_pred"] == 0 or 0 <= seg["precision"] <= 1
    se = m["size_error"]
    assert set(se["matched"]) == {"min_feret", "ellipse_minor", "size_map"}
    # the size map read on the true masks is scored like the footprint methods
    assert se["true_mask_fully_visible"]["size_map"]["n"] == se["true_mask_fully_visible"]["min_feret"]["n"]
    # measured on the true masks: both estimators within a few tens of % of the true sieve size
    assert se["true_mask_fully_visible"]["min_feret"]["n"] > 0
    assert se["true_mask_fully_visible"]["min_feret"]["median"] < 0.5
    header = (tmp_path / "ev" / "predictions.csv").read_text().splitlines()[0]
    assert "pred_d50_mm" in header and "raw_d50_mm" in header and "f1" in header
    assert (tmp_path / "ev" / "scatter.png").is_file()


def test_evaluate_photos_says_when_a_photo_rests_on_few_grains_and_scores_it_all_the_same(tiny, tmp_path, caplog):
    """Unlike predict (which refuses a reading from no whole grain), evaluate-photos scores every photo of its set,
    and says in the log what predict would have refused or warned of (`predict.grain_count_problem`)."""
    import logging

    from psdfactory.cli import main
    from psdfactory.config import validate
    from psdfactory.deploy.predict import MIN_WHOLE_GRAINS

    from .test_photo_sets import make_photo_set, photo_config, photo_params

    _, model_path, _ = tiny
    # two 80-px photos at 0.5 mm/px: 32 px at the tiny model's 1.25 mm/px, room for a handful of grains at most
    folder = make_photo_set(tmp_path / "ph", size=(80, 80))
    params = json.dumps({"photoset": photo_params(validate(photo_config(folder)), "field"), "precision": "fp32"})
    out = tmp_path / "eval"
    with caplog.at_level(logging.WARNING, logger="psdfactory"):
        assert main(["evaluate-photos", "--params", params, "--model", str(model_path), "--out-dir", str(out)]) == 0
    said = [r.getMessage() for r in caplog.records if "field/" in r.getMessage()]
    for photo in ("a.png", "b.png"):
        line = next((s for s in said if f"field/{photo}:" in s), "")
        assert ("no grain found" in line or "touches the image's edge" in line
                or f"fewer than 3 of them (at least {MIN_WHOLE_GRAINS}" in line), said
    m = json.loads((out / "metrics.json").read_text())
    assert set(m["photos"]) == {"a.png", "b.png"}  # scored all the same
    assert all("detection" in r for r in m["photos"].values())


def test_benchmark_times_network_and_watershed(tiny):
    from psdfactory.deploy.benchmark import benchmark

    root, model_path, _ = tiny
    b = benchmark(model_path, root, "tiny", batch=2, seconds=0.02, repeats=1)
    r = b["results"][0]
    # the instance estimator's paths are timed end to end (network + watershed + read-out) like a
    # CNN's, and its fast path is chosen by measurement within the accuracy budget; no int8
    assert b["arch"] == "instances" and r["fast_key"] in r["paths"] and "int8" not in r["paths"]
    assert "int8" in r["skipped"]
    assert r["paths"]["fast"]["batched"]["images_per_s"] > 0 and r["paths"]["fp32"]["batch1"]["batch"] == 1
    assert abs(r["paths"]["fast"]["r2_change"]) <= r["max_r2_change"]
    assert r["stages"]["network_ms_per_image"] > 0 and r["stages"]["read_ms_per_image"] > 0
    # the split between network and reading is timed once, for the path chosen (the one reported)
    assert [k for k, p in r["paths"].items() if "stages" in p and k != "fast"] == [r["fast_key"]]
    assert r["paths"]["fp32"]["accuracy"]["n"] == 2


def test_export_onnx_maps_and_predict_with_them(tiny, tmp_path, few_grains_read):
    from psdfactory.learn.capability import detect

    if not detect().onnxruntime:
        pytest.skip("onnxruntime is not installed")
    from psdfactory import PsdError
    from psdfactory.deploy.export import export
    from psdfactory.deploy.predict import predict_files

    root, model_path, _ = tiny
    rep = export(model_path, tmp_path / "exp")
    assert rep["onnx"]["max_abs_diff"] < 1e-3 and (tmp_path / "exp" / "meta.json").is_file()
    img = str(root / "tiny" / "scenes" / "tiny-000001" / "image.png")
    ref = predict_files(model_path, [img], particles_out=tmp_path / "ref.csv")[0]
    got = predict_files(tmp_path / "exp" / "model.onnx", [img], particles_out=tmp_path / "got.csv")[0]
    assert not got["error"]
    assert len((tmp_path / "got.csv").read_text().splitlines()) == len((tmp_path / "ref.csv").read_text().splitlines())
    keys = ("d10_mm", "d50_mm", "d90_mm")
    assert [got[k] for k in keys] == pytest.approx([ref[k] for k in keys], abs=1e-3)
    with pytest.raises(PsdError, match="int8"):
        export(model_path, tmp_path / "exp8", int8_results=root, dataset="tiny")
    # with test-time views (train.instances.tta) the ONNX export reads the image as PyTorch does
    from psdfactory.learn.runtime import load_model, save_model

    model, meta = load_model(model_path)
    save_model(tmp_path / "d4" / "model.pt", model, {**meta, "tta": "d4"})
    export(tmp_path / "d4" / "model.pt", tmp_path / "exp_d4")
    assert json.loads((tmp_path / "exp_d4" / "meta.json").read_text())["tta"] == "d4"
    ref = predict_files(tmp_path / "d4" / "model.pt", [img])[0]
    got = predict_files(tmp_path / "exp_d4" / "model.onnx", [img])[0]
    assert not got["error"] and [got[k] for k in keys] == pytest.approx([ref[k] for k in keys], abs=1e-3)
    # a meta.json with a broken read-out is refused before anything runs
    meta = json.loads((tmp_path / "exp" / "meta.json").read_text())
    meta["readout"]["weights"] = [[1.0]]
    (tmp_path / "exp" / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(PsdError, match="readout"):
        predict_files(tmp_path / "exp" / "model.onnx", [img])


def test_the_fast_paths_find_the_same_grains_as_fp32(tiny, tmp_path):
    """Every inference path the benchmark may pick for the instance estimator here (channels-last,
    bf16 where the CPU has it natively, ONNX Runtime fp32) finds the grains fp32 eager finds:
    F1 ≥ 0.99 between the two instance masks, image by image, on the scenes; a path that does
    not (bf16's rounding moves marginal grain edges of this barely trained network on some CPUs)
    is never picked, however fast."""
    from psdfactory.deploy.benchmark import candidates, choose_fast, grain_agreement, onnx_runners
    from psdfactory.deploy.quantize import MIN_GRAIN_F1
    from psdfactory.learn import capability
    from psdfactory.learn.evaluate import eval_rows
    from psdfactory.learn.runtime import load_estimator, torch_runner

    root, model_path, _ = tiny
    est = load_estimator(model_path)
    rows = eval_rows(root, "tiny")
    x = torch.stack([torch.from_numpy(np.array(read_png(root / r["image_path"]), copy=True)).permute(2, 0, 1)
                     for r in rows])
    scale = float(rows[0]["mm_per_px"])
    # a one-epoch network finds few grains at its own threshold: cut its foreground map at the
    # median, so that there are grains to compare, whose edges are as marginal as any
    maps = est.outputs(x)
    est.post = {**est.post, "threshold": float(np.median(maps[:, 0])), "h": 0.02}
    base = [r.grains.mask for r in est.predict(x, scale)]
    paths, _ = candidates(torch.device("cpu"), capability.detect(), est.int8)
    ort = onnx_runners(est, est.meta["input_size"], [k for k, c in paths.items() if c.engine == "onnxruntime"],
                       np.zeros((1, 3, 8, 8), np.float32), tmp_path)
    checked = []
    for key, path in paths.items():
        run = ort[key] if path.engine == "onnxruntime" else torch_runner(est.inference_module(), "cpu", path.precision,
                                                                         path.channels_last)
        fast = est.with_runner(run)
        fast.post = est.post
        masks = [r.grains.mask for r in fast.predict(x, scale)]
        f1s = [m.f1 for m in (match_instances(a, b) for a, b in zip(masks, base, strict=True)) if m.n_true]
        agreement = grain_agreement(masks, base)
        assert agreement == min(f1s, default=1.0)
        if agreement < MIN_GRAIN_F1:  # the fastest path of all, and still passed over
            assert key not in ("fp32", "channels_last", "ort_fp32"), (key, agreement)
            paths = {"fp32": {"batched": {"images_per_s": 1.0}, "grain_f1_vs_fp32": 1.0},
                     key: {"batched": {"images_per_s": 100.0}, "r2_change": 0.0, "grain_f1_vs_fp32": agreement}}
            assert choose_fast(paths) == "fp32"
        checked.append(key)
    assert {"fp32", "channels_last"} <= set(checked)
    assert sum(int(b.max()) for b in base) >= 3  # grains were found to compare (not a vacuous pass)


def test_predict_runs_a_model_pt_in_onnx_runtime_from_a_cached_copy(tiny, tmp_path, monkeypatch, few_grains_read):
    """predict --runtime onnx / auto: the model.pt's network exported once into the cache (keyed by
    the file's hash), reloaded from there later, made again when the cached file is damaged; the
    readings and the grains the same as PyTorch's; auto follows the timing measured on this
    machine (kept per CPU, threads and versions) and measures again on another."""
    from psdfactory.deploy import fastpath, quantize
    from psdfactory.deploy.predict import load_predictor, predict_files

    root, model_path, _ = tiny
    cache = tmp_path / "cache"
    monkeypatch.setenv("PSDFACTORY_CACHE", str(cache))
    img = str(root / "tiny" / "scenes" / "tiny-000001" / "image.png")
    keys = ("d10_mm", "d50_mm", "d90_mm")
    ref = predict_files(model_path, [img], particles_out=tmp_path / "ref.csv", runtime="torch")[0]
    got = predict_files(model_path, [img], particles_out=tmp_path / "got.csv", runtime="onnx")[0]
    assert not got["error"] and [got[k] for k in keys] == pytest.approx([ref[k] for k in keys], abs=1e-3)
    assert (tmp_path / "got.csv").read_text().count("\n") == (tmp_path / "ref.csv").read_text().count("\n")
    copies = list(cache.glob("*.onnx"))
    assert len(copies) == 1 and copies[0].stem == fastpath.file_digest(model_path)
    assert load_predictor(model_path, runtime="torch").engine == "torch"

    real_export = quantize.export_onnx
    monkeypatch.setattr(quantize, "export_onnx", lambda *a, **k: pytest.fail("exported again"))
    assert load_predictor(model_path, runtime="onnx").engine == "onnx"  # from the cache
    copies[0].write_bytes(b"not an onnx model")  # damaged: made again
    monkeypatch.setattr(quantize, "export_onnx", real_export)
    assert load_predictor(model_path, runtime="onnx").engine == "onnx"
    assert copies[0].stat().st_size > 1000

    # auto: timed once on this machine, the faster kept; the timing reused; another machine measures again
    timings = cache / f"{copies[0].stem}.timings.json"
    assert load_predictor(model_path, runtime="auto").engine in ("torch", "onnx") and timings.is_file()
    key = fastpath.machine_key(torch.get_num_threads())
    for faster, slower in (("torch", "onnx"), ("onnx", "torch")):
        timings.write_text(json.dumps({key: {"size_hw": [48, 48], faster: 0.01, slower: 0.02}}))
        monkeypatch.setattr(fastpath, "time_engines", lambda *a, **k: pytest.fail("measured again"))
        assert load_predictor(model_path, runtime="auto").engine == faster
    timings.write_text(json.dumps({"another CPU": {"size_hw": [48, 48], "torch": 0.01, "onnx": 0.02}}))
    monkeypatch.setattr(fastpath, "time_engines", lambda runners, size_hw: {"torch": 2.0, "onnx": 1.0})
    assert load_predictor(model_path, runtime="auto").engine == "onnx"
    assert set(json.loads(timings.read_text())) == {"another CPU", key}

    # ONNX Runtime runs on the CPU only: on a GPU auto keeps PyTorch, onnx is refused
    est = load_predictor(model_path, runtime="torch")
    assert fastpath.choose(est, model_path, "auto", torch.device("cuda")).engine == "torch"
    with pytest.raises(PsdError, match="ONNX Runtime runs models on the CPU"):
        fastpath.choose(est, model_path, "onnx", torch.device("cuda"))
    with pytest.raises(PsdError, match="runtime 'fast'"):
        fastpath.choose(est, model_path, "fast", torch.device("cpu"))
