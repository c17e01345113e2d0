"""The ceilings a model is judged against, on synthetic cases with known answers."""

import numpy as np
import pytest

from psdfactory import PsdError
from psdfactory.io import write_png
from psdfactory.learn.ceiling import (
    dataset_ceilings,
    footprint_features,
    sampling_features,
    scene_footprints,
    visible_features,
)
from psdfactory.learn.instances.stats import STAT_NAMES
from psdfactory.learn.metrics import cross_validated_r2
from psdfactory.psd import TARGETS, weighted_percentiles


def test_visible_features_use_only_the_visible_particles():
    f = visible_features(np.array([1.0, 2, 3, 4, 5]), np.array([0, 5, 5, 5, 0]), min_px=1)
    assert f[1] == pytest.approx(3.0) and f[3] == pytest.approx(3.0) and f[4] == pytest.approx(np.log(4))
    assert f[0] < f[1] < f[2]
    assert np.isnan(visible_features(np.array([1.0]), np.array([0]))).all()
    assert visible_features(np.array([1.0, 2]), np.array([3, 9]), min_px=5)[3] == 2.0  # 3 px < 5: not seen


def test_cross_validated_r2_known_answers():
    rng = np.random.default_rng(0)
    x = rng.standard_normal((3000, 2))
    exact = np.column_stack([2 * x[:, 0] + 1, x[:, 1] - x[:, 0]])
    assert cross_validated_r2(x, exact) == pytest.approx([1.0, 1.0], abs=1e-3)
    # y = x0 + noise of sd 0.5: R² = 1 / (1 + 0.25) = 0.8
    noisy = (x[:, 0] + 0.5 * rng.standard_normal(3000))[:, None]
    assert cross_validated_r2(x, noisy)[0] == pytest.approx(0.8, abs=0.02)
    # features that say nothing: out of fold, no better than the mean
    assert cross_validated_r2(rng.standard_normal((200, 3)), rng.standard_normal((200, 1)))[0] < 0.05
    with pytest.raises(PsdError, match="at least"):
        cross_validated_r2(x[:3], exact[:3])


def test_sampling_features_are_the_population_percentiles():
    f = sampling_features(np.array([10.0]), np.array([2.0]), bounds=(-1e6, 1e6))[0]
    assert f[:3] == pytest.approx([10 - 1.28155 * 2, 10, 10 + 1.28155 * 2], abs=1e-3)
    g = sampling_features(np.array([1.0]), np.array([5.0]), bounds=(0.1, 20))[0]
    assert 0.1 < g[0] < g[1] < g[2] < 20 and g[1] > 1.0  # truncation at 0.1 lifts the median


def _scenes(n, hide_small=0.0, seed=1):
    rng = np.random.default_rng(seed)
    scenes, particles = [], {}
    for i in range(n):
        mu, sd = rng.uniform(5, 10), rng.uniform(1, 3)
        sizes = np.clip(rng.normal(mu, sd, 300), 0.5, None)
        vis = np.where(sizes < hide_small, 0, 10)
        d = weighted_percentiles(sizes, None)
        scenes.append({"scene_id": f"s{i}", **dict(zip(TARGETS, d, strict=True)), "size_mean": mu, "size_sigma": sd})
        particles[f"s{i}"] = (sizes, vis)
    return scenes, particles


def test_every_particle_visible_gives_a_perfect_visible_ceiling():
    scenes, particles = _scenes(40)
    c = dataset_ceilings(scenes, particles, bounds=(0.5, 100))
    assert [c["visible"][t] for t in TARGETS] == pytest.approx([1.0, 1.0, 1.0], abs=1e-3)
    # μ, σ known but 300 particles scatter around them: below 1, well above 0
    assert all(0.5 < c["sampling"][t] < 0.999 for t in TARGETS)


def test_hidden_fines_lower_the_d10_ceiling_most():
    scenes, particles = _scenes(60, hide_small=6.0)
    c = dataset_ceilings(scenes, particles, bounds=(0.5, 100))["visible"]
    assert c["d10_mm"] < c["d90_mm"] and c["d90_mm"] > 0.9


def test_too_few_scenes_or_one_fixed_distribution():
    scenes, particles = _scenes(4)
    c = dataset_ceilings(scenes, particles, bounds=(0.5, 100))
    assert c["visible"] is None and "too few" in c["note"]
    scenes, particles = _scenes(20)
    for s in scenes:
        s["size_mean"], s["size_sigma"] = 7.0, 2.0
    assert dataset_ceilings(scenes, particles, bounds=(0.5, 100))["sampling"] is None


def _disc_mask(diameters_px, size=160, gap=3):
    """Discs of the given diameters side by side in rows, none touching another or the edge."""
    mask = np.zeros((size, size), np.uint16)
    yy, xx = np.mgrid[:size, :size]
    x = y = gap + 1
    row_h = 0
    for k, d in enumerate(diameters_px, 1):
        if x + d + gap >= size:
            x, y, row_h = gap + 1, y + row_h + gap, 0
        assert y + d + gap < size, "too many discs for the mask"
        mask[(yy - (y + d / 2)) ** 2 + (xx - (x + d / 2)) ** 2 <= (d / 2) ** 2] = k
        x, row_h = x + d + gap, max(row_h, d)
    return mask


def test_footprint_features_measure_the_true_masks_discs():
    f = footprint_features(_disc_mask([10, 20, 30, 20]), mm_per_px=0.5)
    stat = dict(zip(STAT_NAMES, f, strict=True))
    assert stat["d50_mm"] == pytest.approx(10.0, abs=0.6)  # 20 px discs at 0.5 mm/px, to within a pixel
    assert stat["d10_mm"] < stat["d50_mm"] < stat["d90_mm"]
    assert stat["edge_fraction"] == 0.0


def test_footprint_ceiling_is_perfect_when_every_grain_shows_its_whole_footprint(tmp_path):
    """Labels = percentiles of the discs drawn in each mask: a perfect segmentation measures them
    all, so the footprint ceiling is near 1; hiding the small discs (not drawn) lowers d10's most."""
    rng = np.random.default_rng(3)
    scenes, particles, hidden = [], {}, {}
    for i in range(30):
        d_px = np.clip(rng.normal(rng.uniform(8, 18), rng.uniform(2, 5), 16), 4, 30).round()
        labels = weighted_percentiles(d_px * 0.5, None)
        path = tmp_path / f"s{i}" / "mask.png"
        path.parent.mkdir()
        write_png(path, _disc_mask(d_px, size=200))
        (tmp_path / f"s{i}" / "hidden.png").parent.mkdir(exist_ok=True)
        write_png(tmp_path / f"s{i}" / "hidden.png", _disc_mask(d_px[d_px >= 12], size=200))
        scenes.append({"scene_id": f"s{i}", **dict(zip(TARGETS, labels, strict=True)), "size_mean": 1.0,
                       "size_sigma": 1.0, "mask_path": f"s{i}/mask.png", "mm_per_px": 0.5})
        particles[f"s{i}"] = (d_px * 0.5, np.full(len(d_px), 10))
    fp = scene_footprints(tmp_path, scenes)
    c = dataset_ceilings(scenes, particles, bounds=(0.5, 100), footprints=fp)
    assert all(c["footprints"][t] > 0.9 for t in TARGETS)  # pixel rounding of 4-30 px discs and 16 per scene
    hidden = scene_footprints(tmp_path, [{**s, "mask_path": s["mask_path"].replace("mask", "hidden")} for s in scenes])
    h = dataset_ceilings(scenes, particles, bounds=(0.5, 100), footprints=hidden)["footprints"]
    assert h["d10_mm"] < 0.9 and h["d10_mm"] < h["d90_mm"]
    assert dataset_ceilings(scenes, particles, bounds=(0.5, 100))["footprints"] is None  # no masks, no figure


def test_a_re_renders_few_scenes_are_scored_by_a_read_out_fitted_on_its_sources_other_scenes():
    from psdfactory.learn.ceiling import SceneSet
    from psdfactory.learn.metrics import fitted_r2

    rng = np.random.default_rng(3)
    x = rng.standard_normal((500, 2))
    y = np.column_stack([3 * x[:, 0] - 1, x[:, 1] + 0.5 * rng.standard_normal(500)])
    r2 = fitted_r2(x[:400], y[:400], x[400:], y[400:])
    assert r2[0] == pytest.approx(1.0, abs=1e-3) and r2[1] == pytest.approx(0.8, abs=0.06)  # 1 / (1 + 0.25)

    # 4 scenes alone cannot be cross-validated; fitted on 60 others of the same distribution they
    # are scored, and with every particle visible the visible-particle read-out is exact
    few, few_particles = _scenes(4, seed=5)
    many, many_particles = _scenes(60, seed=6)
    assert dataset_ceilings(few, few_particles, bounds=(0.5, 100))["visible"] is None
    c = dataset_ceilings(few, few_particles, bounds=(0.5, 100),
                         reference=SceneSet(many, many_particles, name="train (train, val)"))
    assert [c["visible"][t] for t in TARGETS] == pytest.approx([1.0, 1.0, 1.0], abs=1e-2)
    assert c["fitted_on"] == {"dataset": "train (train, val)", "n_scenes": 60} and c["footprints"] is None


def test_the_config_fits_a_re_renders_ceilings_on_its_sources_other_splits():
    from psdfactory import config as psd_config
    from tests.conftest import tiny_config

    cfg = tiny_config(n_scenes=40)  # the default split: train, val and test scenes
    cfg["datasets"]["again"] = {"rerender_of": {"dataset": "tiny", "split": "test"}, "render": {}}
    cfg["datasets"]["every"] = {"rerender_of": {"dataset": "tiny", "split": ["train", "val", "test"]}, "render": {}}
    psd_config.validate(cfg)
    assert psd_config.ceiling_params(cfg, "again")["reference"] == {"dataset": "tiny", "splits": ["train", "val"]}
    assert psd_config.ceiling_params(cfg, "every")["reference"] is None  # nothing else to fit on: cross-validated
    assert psd_config.ceiling_params(cfg, "tiny")["reference"] is None


def test_ceilings_from_manifests_fit_on_the_reference_splits_only(tmp_path):
    import pyarrow as pa
    import pyarrow.parquet as pq

    from psdfactory.learn.ceiling import ceilings_from_manifests

    def shards(name, scenes, particles, splits):
        rows = [dict(s, split=sp) for s, sp in zip(scenes, splits, strict=True)]
        pq.write_table(pa.Table.from_pylist(rows), tmp_path / f"{name}-scenes.parquet")
        parts = [{"scene_id": k, "size_mm": float(z), "visible_px": int(v)}
                 for k, (sz, vis) in particles.items() for z, v in zip(sz, vis, strict=True)]
        pq.write_table(pa.Table.from_pylist(parts), tmp_path / f"{name}-particles.parquet")
        return [tmp_path / f"{name}-scenes.parquet"], [tmp_path / f"{name}-particles.parquet"]

    src, src_particles = _scenes(50, seed=8)
    src_s, src_p = shards("src", src, src_particles, ["train"] * 40 + ["test"] * 10)
    test = src[40:]
    here_s, here_p = shards("here", test, {s["scene_id"]: src_particles[s["scene_id"]] for s in test}, ["test"] * 10)
    c = ceilings_from_manifests(here_s, here_p, (0.5, 100),
                                reference={"dataset": "src", "splits": ["train"], "scenes": src_s, "particles": src_p})
    assert c["n_scenes"] == 10 and c["fitted_on"] == {"dataset": "src (train)", "n_scenes": 40}
    assert [c["visible"][t] for t in TARGETS] == pytest.approx([1.0, 1.0, 1.0], abs=1e-2)


def test_a_datasets_ceilings_from_the_config_find_its_manifests_and_its_reference(tmp_path):
    """`dataset_ceilings_from_config` (the benchmarks' entry): the shards under the results root, a
    re-render fitted on its source's other splits as the DAG's ceiling job does."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from psdfactory import config as psd_config
    from psdfactory.learn.ceiling import dataset_ceilings_from_config
    from tests.conftest import tiny_config

    def write(dataset, scenes, particles, splits):
        m = tmp_path / dataset / "manifest"
        for table in ("scenes", "particles"):
            (m / table).mkdir(parents=True)
        pq.write_table(pa.Table.from_pylist([dict(s, split=sp) for s, sp in zip(scenes, splits, strict=True)]),
                       m / "scenes" / "shard-00000.parquet")
        parts = [{"scene_id": k, "size_mm": float(z), "visible_px": int(v)}
                 for k, (sz, vis) in particles.items() for z, v in zip(sz, vis, strict=True)]
        pq.write_table(pa.Table.from_pylist(parts), m / "particles" / "shard-00000.parquet")

    cfg = tiny_config(n_scenes=50, table_size=300, size={"mean": [5, 8], "sigma": [2, 3], "bounds": [0.5, 100]})
    cfg["datasets"]["again"] = {"rerender_of": {"dataset": "tiny", "split": "test"}, "render": {}}
    psd_config.validate(cfg)
    src, particles = _scenes(50, seed=8)
    write("tiny", src, particles, ["train"] * 40 + ["test"] * 10)
    with pytest.raises(PsdError, match="no scenes manifest of again"):
        dataset_ceilings_from_config(cfg, tmp_path, "again")
    write("again", src[40:], {s["scene_id"]: particles[s["scene_id"]] for s in src[40:]}, ["test"] * 10)
    c = dataset_ceilings_from_config(cfg, tmp_path, "again")
    assert c["n_scenes"] == 10 and c["fitted_on"] == {"dataset": "tiny (train, val)", "n_scenes": 40}
    assert [c["visible"][t] for t in TARGETS] == pytest.approx([1.0, 1.0, 1.0], abs=1e-2)
    own = dataset_ceilings_from_config(cfg, tmp_path, "tiny")  # not a re-render: cross-validated on its own
    assert own["n_scenes"] == 50 and "fitted_on" not in own
