"""How much of the labels an image can possibly tell: the ceilings a model is judged against.

- **visible-particle ceiling**: the labels read out, by a cross-validated linear model, from the
  TRUE sieve sizes of the particles the camera sees (at least ``visible_min_px`` pixels in
  ``mask.png``): their d10/d50/d90, mean and count. A perfect measurement of every visible
  particle gives this much; hidden fines and the particles under the top layer cost the rest.
- **footprint ceiling** (perfect segmentation): the instance estimator's own read-out
  (`readout.fit_readout` of `instances.stats.instance_stats`, min Feret) fitted to the footprints of
  the TRUE masks. What measuring each visible footprint gives with no segmentation error: a
  partly hidden grain shows a smaller footprint than its sieve size, which the visible-particle
  ceiling (true sizes) does not pay for. The gap between the two is the cost of measuring
  footprints; the gap between it and the instance estimator is the cost of its segmentation.
- **sampling ceiling** (where the generator's μ and σ vary between scenes): the labels read out
  from the generator's own population percentiles (the truncated normal's d10/d50/d90) and μ, σ.
  It measures how much a scene's ~N particles scatter around the distribution they were drawn
  from; a model that beats it reads the actual particles, not the recipe.

All are R² per target (d10, d50, d90), out-of-fold over k folds of a dataset's scenes — or, for
a re-render of another dataset's scenes (too few, e.g. 14 test scenes, for a stable
cross-validation), with the read-outs fitted on the source dataset's other scenes (its training
split: the same distribution, the same particles' sizes) and scored on the re-render's, as a model
is. Pure numpy/scipy: no torch.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import PsdError
from ..io import read_png
from ..manifest import group_by_scene
from ..psd import PERCENTILES, TARGETS, weighted_percentiles
from .instances.measure import measure_instances
from .instances.stats import instance_stats
from .metrics import MIN_SCENES, cross_validated_r2, fitted_r2, r2_scores
from .readout import apply_readout, fit_readout

logger = logging.getLogger(__name__)

def visible_features(sizes: np.ndarray, visible_px: np.ndarray, min_px: int = 1) -> np.ndarray:
    """[d10, d50, d90, mean, log(1 + count)] of the true sizes of the visible particles
    (number-weighted, the labels' percentile convention); NaNs where none is visible."""
    seen = np.asarray(sizes, float)[np.asarray(visible_px) >= min_px]
    if seen.size == 0:
        return np.full(5, np.nan)
    return np.array([*weighted_percentiles(seen, None), seen.mean(), np.log1p(seen.size)])


def footprint_features(mask: np.ndarray, mm_per_px: float) -> np.ndarray:
    """The instance estimator's statistics (`instance_stats`, min Feret) of a true instance mask:
    what it would measure of this image with a perfect segmentation."""
    return instance_stats(measure_instances(mask, mm_per_px))


def sampling_features(mean: np.ndarray, sigma: np.ndarray, bounds: tuple[float, float]) -> np.ndarray:
    """Per scene: the generator's population d10/d50/d90 (truncated normal on `bounds`), μ and σ."""
    from scipy.stats import truncnorm

    mean, sigma = np.asarray(mean, float), np.asarray(sigma, float)
    a, b = (bounds[0] - mean) / sigma, (bounds[1] - mean) / sigma
    pop = np.stack([truncnorm.ppf(q / 100, a, b, loc=mean, scale=sigma) for q in PERCENTILES], axis=1)
    return np.column_stack([pop, mean, sigma])


@dataclass
class SceneSet:
    """Scenes with what the ceilings read of them: manifest rows (scene_id, labels, size_mean,
    size_sigma), scene_id → (true sizes, visible pixels), and scene_id → `footprint_features` of
    its mask (None: no footprint ceiling)."""

    scenes: list[dict]
    particles: dict[str, tuple[np.ndarray, np.ndarray]]
    footprints: dict[str, np.ndarray] | None = None
    name: str = ""

    def labels(self) -> np.ndarray:
        return np.array([[s[t] for t in TARGETS] for s in self.scenes], float).reshape(-1, len(TARGETS))

    def visible(self, min_px: int) -> np.ndarray:
        return np.stack([visible_features(*self.particles[s["scene_id"]], min_px=min_px) for s in self.scenes])

    def footprint(self) -> np.ndarray:
        return np.stack([self.footprints[s["scene_id"]] for s in self.scenes])

    def sampling(self, bounds: tuple[float, float]) -> np.ndarray:
        mean, sigma = (np.array([s[k] for s in self.scenes], float) for k in ("size_mean", "size_sigma"))
        return sampling_features(mean, sigma, bounds)

    def generator_varies(self) -> bool:
        return any(np.ptp([s[k] for s in self.scenes]) > 0 for k in ("size_mean", "size_sigma"))


def dataset_ceilings(scenes: list[dict], particles: dict[str, tuple[np.ndarray, np.ndarray]],
                     bounds: tuple[float, float], visible_min_px: int = 1, folds: int = 5,
                     footprints: dict[str, np.ndarray] | None = None, reference: SceneSet | None = None) -> dict:
    """The ceilings of one dataset. `scenes`: manifest rows (scene_id, labels, size_mean,
    size_sigma); `particles`: scene_id → (true sizes, visible pixels); `footprints`: scene_id →
    `footprint_features` of its mask (no footprint ceiling without). With `reference` (other
    scenes of the same distribution, footprints where these have them) the read-outs are fitted
    on those and scored on these scenes instead of cross-validated."""
    here = SceneSet(scenes, particles, footprints)
    y = here.labels()
    out: dict = {"n_scenes": len(scenes), "targets": list(TARGETS), "folds": folds,
                 "label_sd_mm": dict(zip(TARGETS, y.std(axis=0).round(4).tolist(), strict=True))}
    fit_on = reference if reference is not None and len(reference.scenes) >= MIN_SCENES else None
    if fit_on is None and len(scenes) < MIN_SCENES:
        out["note"] = f"{len(scenes)} scenes: too few for a cross-validated ceiling (needs {MIN_SCENES})"
        out["visible"] = out["sampling"] = out["footprints"] = None
        return out
    if fit_on is not None:
        out["fitted_on"] = {"dataset": fit_on.name, "n_scenes": len(fit_on.scenes)}
        y_fit = fit_on.labels()

        def r2_of(x_fit: np.ndarray, x: np.ndarray) -> list[float]:
            return fitted_r2(x_fit, y_fit, x, y).tolist()
    else:
        def r2_of(x_fit: np.ndarray, x: np.ndarray) -> list[float]:
            return cross_validated_r2(x, y, folds).tolist()

    src = fit_on or here
    out["visible"] = dict(zip(TARGETS, r2_of(src.visible(visible_min_px), here.visible(visible_min_px)), strict=True))
    out["footprints"] = None
    if footprints is not None and src.footprints is not None:
        if fit_on is not None:
            pred = apply_readout(fit_readout(fit_on.footprint(), y_fit, folds=folds), here.footprint())
            r2f = r2_scores(y, pred).tolist()
        else:
            r2f = fit_readout(here.footprint(), y, folds=folds)["cv_r2"]
        out["footprints"] = dict(zip(TARGETS, r2f, strict=True))
    if src.generator_varies():
        out["sampling"] = dict(zip(TARGETS, r2_of(src.sampling(bounds), here.sampling(bounds)), strict=True))
    else:
        out["sampling"] = None  # one fixed distribution: the labels differ by sampling noise alone
    return out


def scene_footprints(results_root: Path, scenes: list[dict], every_s: float = 30.0) -> dict[str, np.ndarray]:
    """`footprint_features` of each scene's mask.png (paths in the manifest rows, relative to the
    results root), with a progress line every `every_s` seconds."""
    out, t0, last = {}, time.monotonic(), time.monotonic()
    for i, s in enumerate(scenes, 1):
        out[s["scene_id"]] = footprint_features(read_png(Path(results_root) / s["mask_path"]), float(s["mm_per_px"]))
        if time.monotonic() - last > every_s and i < len(scenes):
            last, rate = time.monotonic(), i / (time.monotonic() - t0)
            eta = (len(scenes) - i) / rate
            logger.info(f"footprints: {i}/{len(scenes)} masks measured, {rate:.1f}/s, ETA {eta:.0f} s")
    return out


def read_scene_set(scene_shards: list, particle_shards: list, splits: list[str] | None = None,
                   name: str = "") -> SceneSet:
    """The scenes of these manifest shards (those in `splits` only, if given) with their particles'
    true sizes and visible pixels."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    scenes = pa.concat_tables([pq.read_table(f) for f in scene_shards]).to_pylist()
    if splits is not None:
        scenes = [s for s in scenes if s["split"] in splits]
    parts = pa.concat_tables([pq.read_table(f, columns=["scene_id", "size_mm", "visible_px"]) for f in particle_shards])
    grouped = group_by_scene(parts, ("size_mm", "visible_px"))
    particles = {k: (v["size_mm"], v["visible_px"]) for k, v in grouped.items()}
    missing = [s["scene_id"] for s in scenes if s["scene_id"] not in particles]
    if missing:
        raise PsdError(f"the particle manifest has no rows for {len(missing)} scenes (e.g. {missing[0]}); "
                       "rerun the manifest jobs")
    return SceneSet(scenes, particles, name=name)


def ceilings_from_manifests(scene_shards: list, particle_shards: list, bounds: tuple[float, float],
                            visible_min_px: int = 1, folds: int = 5, results_root: Path | None = None,
                            reference: dict | None = None) -> dict:
    """`dataset_ceilings` of the scenes in these manifest shards (Parquet files); with
    `results_root` also the footprint ceiling, from the scenes' masks. `reference`
    ({"dataset", "splits", "scenes": shards, "particles": shards}): fit the read-outs on those
    scenes (a re-render's source dataset, the splits it does not take) and score on these."""
    here = read_scene_set(scene_shards, particle_shards)
    ref = None
    if reference is not None:
        ref = read_scene_set(reference["scenes"], reference["particles"], reference["splits"],
                             f"{reference['dataset']} ({', '.join(reference['splits'])})")
    if results_root is not None:
        here.footprints = scene_footprints(results_root, here.scenes)
        if ref is not None:
            ref.footprints = scene_footprints(results_root, ref.scenes)
    return dataset_ceilings(here.scenes, here.particles, bounds, visible_min_px, folds, here.footprints, ref)


def dataset_ceilings_from_config(config: dict, results_root: Path, dataset: str, footprints: bool = False) -> dict:
    """`ceilings_from_manifests` of a dataset of a validated config, from its manifests under
    `results_root` (a re-render's fitted on its source's other splits, as the DAG's ceiling job
    does); with `footprints` the footprint ceiling too."""
    from ..config import ceiling_params

    def shards(d: str, table: str) -> list[Path]:
        found = sorted((Path(results_root) / d / "manifest" / table).glob("*.parquet"))
        if not found:
            raise PsdError(f"no {table} manifest of {d} under {results_root}: make the dataset first")
        return found

    p = ceiling_params(config, dataset)
    ref = p["reference"]
    if ref:
        ref = {**ref, **{t: shards(ref["dataset"], t) for t in ("scenes", "particles")}}
    return ceilings_from_manifests(shards(dataset, "scenes"), shards(dataset, "particles"), tuple(p["bounds"]),
                                   p["visible_min_px"], results_root=results_root if footprints else None,
                                   reference=ref)
