"""Training of the instance estimator: random crops of the training split with flips / 90°
rotations on image and targets and photometric jitter on the image, the shared loop of
`learn.fit` (model selection by validation loss, resumable); then the post-processing picked on
the validation masks and the read-out fitted on the training and validation scenes' predicted
instances, all stored in the model file's meta."""

from __future__ import annotations

import itertools
import logging
import math
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch

from ... import PsdError, __version__
from ...config import AUTO_SCALE_PROBE, SETTINGS_OFF, config_fields, network_recipe, training_recipe
from ...manifest import PARTICLE_READ_COLUMNS
from ...psd import NAMES, SOLID_DEFINITIONS, TARGETS, definition_targets
from ..augment import TTA_VIEWS, grain_colour, photometric, surface_texture
from ..data import label_definition, normalise, particles_by_scene, training_rows
from ..data import targets as label_targets
from ..estimator import GRAIN_PROBE_KEY, GRAIN_SIZE_KEYS
from ..fit import FitTask, fingerprint, fit, write_history
from ..metrics import regression_metrics
from ..models import count_parameters
from ..readout import apply_readout, fit_readout
from ..runtime import (
    LrSchedule,
    autocast,
    loss_scaler,
    optimise_step,
    pick_device,
    save_model,
    torch_runner,
    training_precision,
)
from . import ARCH
from .measure import SIEVE_METHODS
from .net import FULL_RES, TRUNK, InstanceMaps, build_instance_net, decoder_for
from .scoring import f1_score, match_instances
from .stats import READOUT_TARGET_FEATURES, READOUTS
from .targets import MAPS, boundary_weight, instance_loss, load_scenes, random_crops, read_scene_mask
from .watershed import DEFAULT_POSTPROCESS, POSTPROCESS_GRID, postprocess

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class InstanceSettings:
    """`train.instances` in the config: what only the instance estimator's training uses
    (defaults: the schema's)."""

    crops_per_image: int  # random crops of each training image per epoch
    photometric: float  # strength of the camera/light augmentation of the image (0 = off)
    lr: float  # Adam learning rate
    sieve_method: str  # min_feret | ellipse_minor | size_map
    readout: str  # what the calibrated read-out reads, per target (READOUTS, READOUT_TARGET_FEATURES)
    tta: str  # none | flips | d4: the views of each image whose maps are averaged (TTA_VIEWS)
    auto_scale: bool  # the model's meta says predict reads photos at the grains' scale by default
    min_visible_share: float  # particles less of whose silhouette is in view are taught as background (grain_mask)
    surface_texture: float  # strength of the texture laid on the training crops' grains (augment.surface_texture)
    grain_colour: float  # strength of the colour of its own given to each training grain (augment.grain_colour)
    trunk_stages: int  # the ResNet-18 stages its trunk keeps: 2 (stride 8) or 3 (stride 16; net.InstanceNet)
    calibration_datasets: tuple[str, ...] | None  # those of its datasets the calibration is fitted on (None: all)

    @classmethod
    def from_dict(cls, d: dict) -> InstanceSettings:
        # SETTINGS_OFF are in a slice only when on (config.train_params): absent means off
        s = cls(**config_fields(cls, {**SETTINGS_OFF, **d}, "train.instances"))
        if s.calibration_datasets is not None:
            names = s.calibration_datasets
            if isinstance(names, str) or not all(isinstance(n, str) for n in names) or not names:
                raise PsdError(f"train.instances.calibration_datasets must be a list of dataset names, not {names!r}")
            s = replace(s, calibration_datasets=tuple(names))
        if s.sieve_method not in SIEVE_METHODS:
            raise PsdError(f"train.instances.sieve_method must be one of {', '.join(SIEVE_METHODS)}")
        if s.readout not in READOUTS:
            raise PsdError(f"train.instances.readout must be one of {', '.join(READOUTS)}")
        if s.tta not in TTA_VIEWS:
            raise PsdError(f"train.instances.tta must be one of {', '.join(TTA_VIEWS)}")
        return s



def val_loss(model, images, targets, device, precision, pw: float, batch: int = 4) -> float:
    model.eval()
    total = 0.0
    with torch.inference_mode():
        for i in range(0, len(images), batch):
            x = normalise(images[i : i + batch].to(device))
            with autocast(device, precision):
                out = model(x)
            total += float(instance_loss(out, targets[i : i + batch].to(device), pw)[0]) * len(x)
    return total / max(len(images), 1)


def grain_particles(results_root: Path, rows: list[dict], settings: InstanceSettings) -> dict | None:
    """The particle rows `read_scene_mask` needs to keep the grains `settings` teaches, of the rows' datasets;
    None where every visible particle is a grain."""
    if settings.min_visible_share <= 0:
        return None
    return particles_by_scene(results_root, sorted({r["dataset"] for r in rows}), ("particle_id", "ecd_mm"))


def pick_postprocess(maps: np.ndarray, masks: list[np.ndarray], grid: dict = POSTPROCESS_GRID) -> tuple[dict, float]:
    """The post-processing settings (from `grid` over DEFAULT_POSTPROCESS) with the best pooled F1
    at IoU 0.5 against the true masks."""
    best, best_f1 = dict(DEFAULT_POSTPROCESS), -1.0
    keys = list(grid)
    for values in itertools.product(*(grid[k] for k in keys)):
        s = {**DEFAULT_POSTPROCESS, **dict(zip(keys, values, strict=True))}
        tp = n_pred = n_true = 0
        for mp, true in zip(maps, masks, strict=True):
            res = match_instances(postprocess(mp, s), true)
            tp, n_pred, n_true = tp + res.n_matched, n_pred + res.n_pred, n_true + res.n_true
        f1 = f1_score(tp, n_pred, n_true) if n_pred + n_true else 0.0
        if f1 > best_f1:
            best, best_f1 = s, f1
    logger.info(f"post-processing picked on the validation masks: {best} (F1 at IoU 0.5: {best_f1:.3f})")
    return best, best_f1


def readout_features(readout: str) -> dict:
    """fit_readout's `features` and `target_features` for the read-out `readout` (READOUTS)."""
    return {"features": READOUTS[readout], "target_features": READOUT_TARGET_FEATURES[readout]}


def other_readouts(stats: np.ndarray, rows: list[dict], readout: str) -> dict:
    """Read-outs of the scenes' labels in every other solid size definition (same weighting), from
    the same instance statistics (`readout`, a name of READOUTS): the estimator reads its own
    definition and estimates these."""
    own = label_definition(rows)
    out = {}
    for d in SOLID_DEFINITIONS:
        cols = definition_targets(d, own["weighting"])
        y = np.array([[r.get(c, np.nan) for c in cols] for r in rows], dtype=float)
        if d != own["size_definition"] and np.isfinite(y).all():
            out[d] = fit_readout(stats, y, **readout_features(readout))
    return out


def grain_sizes(est, x_val: torch.Tensor, val_maps: np.ndarray) -> dict:
    """How large the grains of the validation images look to the trained network (px at the model's
    scale, `apparent_grain_px`), for predict's automatic scale: `grain_px`, the median over the
    images, `grain_px_max`, the largest, and `grain_px_probe_max`, the largest as seen at
    AUTO_SCALE_PROBE of the scale (there a network's size map reads grains seen small larger than
    they are: predict compares a photo's look there with this one), and that factor
    (`grain_px_probe_scale`). Empty without a size map."""
    from torch.nn import functional as F

    seen = [g for g in map(est.apparent_grain_px, val_maps) if g is not None]
    small = F.interpolate(x_val.float(), scale_factor=AUTO_SCALE_PROBE, mode="bilinear", antialias=True,
                          align_corners=False).round().clamp(0, 255).to(torch.uint8)
    probed = [g / AUTO_SCALE_PROBE for g in map(est.apparent_grain_px, est.all_maps(small)) if g is not None]
    if not seen or not probed:
        return {}
    sizes = (np.median(seen), np.max(seen), np.max(probed))
    return {**{k: round(float(v), 3) for k, v in zip(GRAIN_SIZE_KEYS, sizes, strict=True)},
            GRAIN_PROBE_KEY: AUTO_SCALE_PROBE}


def calibration_scenes(settings: InstanceSettings, train_rows: list[dict], val_rows: list[dict],
                       x_train: torch.Tensor | None = None, x_val: torch.Tensor | None = None
                       ) -> tuple[list[dict], list[dict], torch.Tensor | None, torch.Tensor | None]:
    """Of the training and validation scenes (rows, and their images where given), those the calibration is
    fitted on: the scenes of ``settings.calibration_datasets``, or all of them (the same objects). Refuses a
    choice that leaves no training or no validation scene, before anything is trained on it."""
    if settings.calibration_datasets is None:
        return train_rows, val_rows, x_train, x_val
    keep = set(settings.calibration_datasets)
    ti = [i for i, r in enumerate(train_rows) if r["dataset"] in keep]
    vi = [i for i, r in enumerate(val_rows) if r["dataset"] in keep]
    if not ti or not vi:
        trained = sorted({r["dataset"] for r in train_rows + val_rows})
        raise PsdError(f"train.instances.calibration_datasets {', '.join(sorted(keep))}: {len(ti)} train and "
                       f"{len(vi)} val scenes among those of the datasets it trains on ({', '.join(trained)}); "
                       "the calibration needs both")
    return ([train_rows[i] for i in ti], [val_rows[i] for i in vi],
            None if x_train is None else x_train[ti], None if x_val is None else x_val[vi])


def scale_meta(rows: list[dict]) -> dict:
    """The scale a model reads at, from the training scenes its calibration was fitted on: predict brings a photo
    to it, and the grain sizes and read-out were measured there."""
    res_px = int(np.median([r["resolution"] for r in rows]))
    return {"input_size": res_px,  # inference runs on whole images at the training images' scale
            "image_resolution": res_px, "mm_per_px": float(np.median([r["mm_per_px"] for r in rows]))}


def calibrate(model, device, settings: InstanceSettings, weights_used: str, results_root: Path, train_rows: list[dict],
              val_rows: list[dict], x_train: torch.Tensor, x_val: torch.Tensor, estimator: type) -> dict:
    """What a trained network's model file holds beside its weights, from its maps as evaluate and
    predict make them (averaged over the views ``settings.tta`` names): the post-processing picked on
    the validation masks, how large the validation grains look (predict's automatic scale), and the
    read-outs fitted on the training and validation scenes' predicted instances. Returns those meta
    entries and ``val_mae_mm`` (the calibrated validation error, in the read-out's fit)."""
    t0 = time.perf_counter()
    meta = {"arch": ARCH, "weights": weights_used, "sieve_method": settings.sieve_method, "readout": None,
            "postprocess": dict(DEFAULT_POSTPROCESS), "tta": settings.tta}
    est = estimator(meta, torch_runner(InstanceMaps(model), device), model)  # as evaluate and predict run it
    val_maps = est.all_maps(x_val)
    # the grains it was taught (train.instances.min_visible_share): what its post-processing is picked to find
    grains = grain_particles(results_root, val_rows, settings)
    val_masks = [read_scene_mask(results_root, r, grains, settings.min_visible_share) for r in val_rows]
    post, val_f1 = pick_postprocess(val_maps, val_masks)
    est.post = post
    grain_px = grain_sizes(est, x_val, val_maps)  # how large its grains look: predict's automatic scale
    train_maps = est.all_maps(x_train)
    train_res = [est.analyse_maps(mp, float(r["mm_per_px"])) for mp, r in zip(train_maps, train_rows, strict=True)]
    val_res = [est.analyse_maps(mp, float(r["mm_per_px"])) for mp, r in zip(val_maps, val_rows, strict=True)]
    y_train, y_val = label_targets(train_rows).numpy(), label_targets(val_rows).numpy()
    # the read-out is fitted on the training and the validation scenes: the network has learnt
    # the training images, so its instances there are better than on new images; the validation
    # images show the read-out what the network makes of images it has not seen
    stats = np.stack([r.stats for r in train_res + val_res])
    readout = fit_readout(stats, np.concatenate([y_train, y_val]), **readout_features(settings.readout))
    readouts = other_readouts(stats, train_rows + val_rows, settings.readout)
    val_cal = regression_metrics(y_val, apply_readout(readout, np.stack([r.stats for r in val_res])))
    val_raw = regression_metrics(y_val, np.nan_to_num(np.stack([r.raw for r in val_res])))
    r2s = {k: " / ".join(f"{m[n]['r2']:.3f}" for n in NAMES) for k, m in (("cal", val_cal), ("raw", val_raw))}
    cv = " / ".join(f"{v:.3f}" for v in readout["cv_r2"]) if readout["cv_r2"] else "n/a (too few scenes)"
    ridge = np.round(readout["alpha"], 6)  # per target where the targets read different statistics
    logger.info(f"read-out ({settings.readout}) fitted on {len(train_rows)} training + {len(val_rows)} validation "
                f"scenes (ridge {ridge}): cross-validated R² {cv}; validation R² calibrated (in the "
                f"fit) {r2s['cal']}, raw {r2s['raw']} ({time.perf_counter() - t0:.0f} s)")
    if grain_px:
        logger.info(f"the validation images' grains look {grain_px['grain_px']:.1f} px (median over the images of the "
                    f"size map's area-weighted median), at most {grain_px['grain_px_max']:.1f} px, and at most "
                    f"{grain_px['grain_px_probe_max']:.1f} px as seen at {AUTO_SCALE_PROBE} x the scale: predict reads "
                    "a photo whose grains look larger than that where they look the median's size")
    return {
        "postprocess": post,
        **grain_px,
        "sieve_method": settings.sieve_method,
        "readout_features": settings.readout,
        "tta": settings.tta,
        "readout": readout,
        "readouts": readouts,  # the other solid size definitions (predict --size-definition)
        # the validation scenes are in the read-out's fit: its out-of-fold R² is the honest figure
        "val": {"f1": val_f1, "r2_readout_cv": readout["cv_r2"],
                "r2_calibrated_in_fit": [val_cal[n]["r2"] for n in NAMES],
                "r2_raw": [val_raw[n]["r2"] for n in NAMES]},
        "val_mae_mm": val_cal["overall"]["mae"],
    }


# the read-outs there were before 2026-11-28 (legacy_fingerprints): fixed, whatever READOUTS holds now
LEGACY_READOUTS = ("footprints", "footprints+size_map")


def legacy_fingerprints(params, settings: InstanceSettings, ids: list) -> tuple[str, ...]:
    """The fingerprints the same training had before 2026-11-28, when they held the calibration settings too
    (config.CALIBRATION_SETTINGS, under any of their values): a checkpoint written then still resumes."""
    out = []
    for tta, sieve, readout in itertools.product(TTA_VIEWS, SIEVE_METHODS, LEGACY_READOUTS):
        old = {**asdict(settings), "tta": tta, "sieve_method": sieve, "readout": readout, "calibration_datasets": None}
        out.append(fingerprint(training_recipe({**asdict(params), "settings": old}), ids))
    return tuple(out)


def train_instances(params, settings: InstanceSettings, results_root: Path, out_dir: Path, estimator: type) -> dict:
    """Train the instance estimator (`params`: learn.train.TrainParams with arch 'instances') on
    a dataset's train split, select by validation loss, pick the post-processing on the
    validation masks, fit the read-out on the training + validation scenes; write model.pt and
    history.csv (its last row's val_mae_mm: the calibrated validation error, in the read-out's fit).
    `estimator`: the InstanceEstimator class, which the calibration runs as evaluate and predict do."""
    torch.manual_seed(params.seed)
    np.random.seed(params.seed % 2**32)
    device = pick_device(params.device)
    train_rows, val_rows, rows = training_rows(results_root, params.datasets)
    calibration_scenes(settings, train_rows, val_rows)  # a calibration without scenes is refused before training
    t_load = time.perf_counter()
    particles = particles_by_scene(results_root, params.datasets, PARTICLE_READ_COLUMNS + ("ecd_mm",)
                                   if settings.min_visible_share > 0 else None)  # the size map's targets
    x_train, t_train = load_scenes(results_root, train_rows, particles, settings.min_visible_share)
    x_val, t_val = load_scenes(results_root, val_rows, particles, settings.min_visible_share)
    crop = min(int(params.input_size), *x_train.shape[-2:])
    pw = boundary_weight(t_train)
    model, weights_used = build_instance_net(params.pretrained, settings.trunk_stages)
    model = model.to(device).to(memory_format=torch.channels_last)
    batch = min(params.batch_size, len(x_train) * settings.crops_per_image)
    dummy = torch.zeros(batch, len(MAPS), crop, crop)
    precision = training_precision(params.precision, device, model, crop, batch,
                                   lambda out: instance_loss(out, dummy, pw)[0])
    n_params = count_parameters(model)
    logger.info(f"training {ARCH} ({TRUNK} trunk + U-Net decoder, {n_params / 1e6:.2f} M parameters, weights: "
                f"{weights_used}) on {len(train_rows)} train / {len(val_rows)} val scenes of "
                f"{', '.join(params.datasets)}: {settings.crops_per_image} random {crop}-px crops per image and "
                f"epoch, {device} {precision}, {params.epochs} epochs, lr {settings.lr} ({params.lr_schedule}), "
                f"boundary weight {pw:.1f} (targets made in {time.perf_counter() - t_load:.1f} s)")
    opt = torch.optim.Adam(model.parameters(), lr=settings.lr, weight_decay=params.weight_decay)
    steps_per_epoch = math.ceil(len(x_train) * settings.crops_per_image / params.batch_size)
    sched = LrSchedule(opt, params.lr_schedule, params.epochs, steps_per_epoch, params.lr_factor, params.lr_patience)
    gen = torch.Generator().manual_seed(params.seed)
    scaler = loss_scaler(device, precision)

    def train_epoch(bar) -> float:
        model.train()
        order = torch.cat([torch.randperm(len(x_train), generator=gen) for _ in range(settings.crops_per_image)])
        total, n = 0.0, 0
        for b in range(0, len(order), params.batch_size):
            x, t = random_crops(x_train, t_train, order[b : b + params.batch_size], crop, gen, params.augment,
                                tuple(params.scale_augment))
            if settings.surface_texture > 0:  # before the camera: the stones' own texture
                x = surface_texture(x, t[:, 0], gen, settings.surface_texture)
            if settings.grain_colour > 0:  # before the camera too: the stones' own colours
                x = grain_colour(x, t[:, 0], t[:, 1], gen, settings.grain_colour)
            if settings.photometric > 0:
                x = photometric(x, gen, settings.photometric)
            x, t = normalise(x.to(device)), t.to(device)
            loss = optimise_step(model, opt, x, lambda out, t=t: instance_loss(out, t, pw)[0], device, precision,
                                 "train.instances.lr", scaler)
            sched.after_step()
            total += loss * len(x)
            n += len(x)
            bar.update(len(x))
            bar.set_postfix(loss=f"{total / n:.4f}")
        return total / max(n, 1)

    task = FitTask(model, opt, sched, train_epoch,
                   lambda: {"val_loss": val_loss(model, x_val, t_val, device, precision, pw)},
                   len(x_train) * settings.crops_per_image, "crop", generators={"gen": gen}, scaler=scaler)
    ids = [(r["scene_id"], r["split"], *(r[t] for t in TARGETS)) for r in rows]
    # without the settings that change the meta only (predict's default reading) or the calibration after training
    # (config.network_recipe): a run that differs in them resumes the same network's finished training
    fp = fingerprint(network_recipe({**asdict(params), "settings": asdict(settings)}), ids)
    res = fit(task, ARCH, params.epochs, params.early_stopping_patience, out_dir, fp,
              {"arch": ARCH, "maps": list(MAPS)}, also_fp=legacy_fingerprints(params, settings, ids))
    model.eval()

    c_train, c_val, cx_train, cx_val = calibration_scenes(settings, train_rows, val_rows, x_train, x_val)
    calib = calibrate(model, device, settings, weights_used, results_root, c_train, c_val, cx_train, cx_val, estimator)
    history = res.history
    history[-1]["val_mae_mm"] = calib.pop("val_mae_mm")
    write_history(history, out_dir / "history.csv")

    summary = {
        "arch": ARCH,
        "trunk": TRUNK,
        "trunk_stages": settings.trunk_stages,
        "decoder": list(decoder_for(settings.trunk_stages)),
        "full_res_channels": FULL_RES,
        **scale_meta(c_train),
        "crop_size": crop,
        "targets": list(TARGETS),
        **label_definition(train_rows + val_rows),
        "weights": weights_used,
        "maps": list(MAPS),
        **calib,
        "calibration_datasets": list(settings.calibration_datasets or params.datasets),  # what calib is fitted on
        "auto_scale": settings.auto_scale,  # predict's default reading (--auto-scale / --no-auto-scale)
        "min_visible_share": settings.min_visible_share,  # the grains it learnt (train.instances)
        "surface_texture": settings.surface_texture,  # the texture laid on them in training (train.instances)
        "grain_colour": settings.grain_colour,  # the colours given to them in training (train.instances)
        "boundary_pos_weight": pw,
        "params": asdict(params),
        "n_parameters": n_params,
        "psdfactory_version": __version__,
        "best_epoch": res.best_epoch,
        "epochs_run": len(history),
        "stop_reason": res.stop_reason,
        "train_seconds": sum(r["seconds"] for r in history),  # a resumed run's epochs before too
        "precision": precision,
        "device": str(device),
    }
    save_model(out_dir / "model.pt", model, summary)
    logger.info(f"done: best val loss {res.best_loss:.4f} at epoch {res.best_epoch} ({res.stop_reason}), "
                f"{summary['train_seconds']:.0f} s of training ({res.seconds:.0f} s in this run); wrote "
                f"{out_dir / 'model.pt'}")
    return summary


def recalibrate(model_path: Path, settings: InstanceSettings, results_root: Path, out_path: Path,
                estimator: type, device: str = "auto") -> tuple[dict, float]:
    """A trained instance model calibrated again under other calibration settings (``tta``, ``sieve_method``,
    ``readout``, ``calibration_datasets``: what the trained network's maps are made into and on which scenes,
    not what it learnt; and predict's default reading, ``auto_scale``), on the training and validation scenes it
    was trained on (those of ``calibration_datasets`` where set); writes the model to `out_path` with its
    network unchanged and returns its meta and the calibrated validation error (mm). A correction `psdfactory
    calibrate` had fitted to the old readings is dropped (it corrected readings this model no longer makes). For
    measuring those settings on trained networks without training them again (bench/seed_spread.py
    --recalibrate-from)."""
    from ..runtime import load_model, meta_problems

    dev = pick_device(device)
    model, meta = load_model(model_path, dev)
    if meta.get("arch") != ARCH or not isinstance(meta.get("params"), dict) or "datasets" not in meta["params"]:
        raise PsdError(f"{model_path} is not an instance estimator trained by this version (arch "
                       f"{meta.get('arch')!r}, no params.datasets in its meta): train it again")
    trained = float(meta.get("min_visible_share", 0.0))  # absent: trained before the setting, on every particle
    if trained != settings.min_visible_share:
        raise PsdError(f"{model_path} was trained on the particles with min_visible_share {trained:g}, not "
                       f"{settings.min_visible_share:g}: that changes what the network learns, so train it again")
    model.eval()
    outside = sorted(set(settings.calibration_datasets or ()) - set(meta["params"]["datasets"]))
    if outside:
        trained_on = ", ".join(meta["params"]["datasets"])
        raise PsdError(f"calibration_datasets {', '.join(outside)}: {model_path} was not trained on "
                       f"{'it' if len(outside) == 1 else 'them'} (its datasets: {trained_on})")
    train_rows, val_rows, _ = training_rows(results_root, meta["params"]["datasets"])
    train_rows, val_rows, *_ = calibration_scenes(settings, train_rows, val_rows)
    x_train, _ = load_scenes(results_root, train_rows)
    x_val, _ = load_scenes(results_root, val_rows)
    calib = calibrate(model, dev, settings, meta.get("weights", "unknown"), results_root, train_rows, val_rows,
                      x_train, x_val, estimator)
    val_mae = calib.pop("val_mae_mm")
    if "calibration" in meta:
        logger.warning(f"{model_path} carries a correction fitted by psdfactory calibrate: it is left out of "
                       f"{out_path} (calibrate the new model again)")
    new = {**{k: v for k, v in meta.items() if k != "calibration"}, **calib, **scale_meta(train_rows),
           "auto_scale": settings.auto_scale,
           "calibration_datasets": list(settings.calibration_datasets or meta["params"]["datasets"]),
           "recalibrated_from": str(model_path)}
    problems = meta_problems(new)
    if problems:
        raise PsdError(f"{model_path} calibrated with {settings}: " + "; ".join(problems))
    save_model(out_path, model, new)
    return new, val_mae
