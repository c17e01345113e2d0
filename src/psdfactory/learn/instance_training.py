"""Training of the instance estimator (architecture ``instances``; `learn.instances` holds the
network, targets, loss, post-processing and read-out): random crops of the training split with
flips / 90° rotations on image and targets and photometric jitter on the image, model selection by
validation loss; then the post-processing picked on the validation masks and the read-out fitted
on the training and validation scenes' predicted instances, all stored in the model file's meta."""

from __future__ import annotations

import csv
import logging
import math
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from .. import PsdError, __version__
from ..io import atomic_path, read_png
from ..psd import NAMES, TARGETS
from .instances import (
    ARCH,
    DECODER,
    DEFAULT_POSTPROCESS,
    FULL_RES,
    MAPS,
    POSTPROCESS_GRID,
    READOUTS,
    TRUNK,
    InstanceEstimator,
    InstanceSettings,
    all_maps,
    boundary_weight,
    build_instance_net,
    instance_loss,
    load_scenes,
    postprocess,
    random_crops,
    read_particles,
    torch_maps_fn,
)
from .particles import match_instances
from .readout import apply_readout, fit_readout

logger = logging.getLogger(__name__)


def _scaled_rows(rows):
    return [float(r["mm_per_px"]) for r in rows]



def _val_loss(model, images, targets, device, precision, pw: float, batch: int = 4) -> float:
    from .data import normalise
    from .runtime import autocast

    model.eval()
    total = 0.0
    with torch.inference_mode():
        for i in range(0, len(images), batch):
            x = normalise(images[i : i + batch].to(device))
            with autocast(device, precision):
                out = model(x)
            total += float(instance_loss(out, targets[i : i + batch].to(device), pw)[0]) * len(x)
    return total / max(len(images), 1)


def pick_postprocess(maps: np.ndarray, masks: list[np.ndarray], grid: dict = POSTPROCESS_GRID) -> tuple[dict, float]:
    """The post-processing settings (from `grid` over DEFAULT_POSTPROCESS) with the best pooled F1
    at IoU 0.5 against the true masks."""
    import itertools

    best, best_f1 = dict(DEFAULT_POSTPROCESS), -1.0
    keys = list(grid)
    for values in itertools.product(*(grid[k] for k in keys)):
        s = {**DEFAULT_POSTPROCESS, **dict(zip(keys, values, strict=True))}
        tp = n = 0
        for mp, true in zip(maps, masks, strict=True):
            res = match_instances(postprocess(mp, s), true)
            tp += res.n_matched
            n += res.n_pred + res.n_true
        f1 = 2 * tp / n if n else 0.0
        if f1 > best_f1:
            best, best_f1 = s, f1
    logger.info(f"post-processing picked on the validation masks: {best} (F1 at IoU 0.5: {best_f1:.3f})")
    return best, best_f1


def other_readouts(stats: np.ndarray, rows: list[dict], features: tuple[str, ...]) -> dict:
    """Read-outs of the scenes' labels in every other solid size definition (same weighting), from
    the same instance statistics: the estimator reads its own definition and estimates these."""
    from ..psd import SOLID_DEFINITIONS, definition_targets
    from .data import label_definition

    own = label_definition(rows)
    out = {}
    for d in SOLID_DEFINITIONS:
        cols = definition_targets(d, own["weighting"])
        y = np.array([[r.get(c, np.nan) for c in cols] for r in rows], dtype=float)
        if d != own["size_definition"] and np.isfinite(y).all():
            out[d] = fit_readout(stats, y, features=features)
    return out


def train_instances(params, settings: InstanceSettings, results_root: Path, out_dir: Path) -> dict:
    """Train the instance estimator (`params`: learn.train.TrainParams with arch 'instances') on
    a dataset's train split, select by validation loss, pick the post-processing on the
    validation masks, fit the read-out on the training + validation scenes; write model.pt and
    history.csv (its last row's val_mae_mm: the calibrated validation error, in the read-out's fit)."""
    from tqdm import tqdm

    from .augment import photometric
    from .data import label_definition, normalise, training_rows
    from .data import targets as label_targets
    from .models import count_parameters
    from .runtime import LrSchedule, optimise_step, pick_device, save_model, training_precision

    torch.manual_seed(params.seed)
    np.random.seed(params.seed % 2**32)
    device = pick_device(params.device)
    train_rows, val_rows, rows = training_rows(results_root, params.datasets)
    t_load = time.perf_counter()
    # the size map's targets
    particles = {k: v for ds in params.datasets for k, v in read_particles(results_root, ds).items()}
    x_train, t_train = load_scenes(results_root, train_rows, particles)
    x_val, t_val = load_scenes(results_root, val_rows, particles)
    crop = min(int(params.input_size), *x_train.shape[-2:])
    pw = boundary_weight(t_train)
    model, weights_used = build_instance_net(params.pretrained)
    model = model.to(device).to(memory_format=torch.channels_last)
    batch = min(params.batch_size, len(x_train) * settings.crops_per_image)
    dummy = torch.zeros(batch, len(MAPS), crop, crop)
    precision = training_precision(params.precision, device, model, crop, batch,
                                   lambda out: instance_loss(out, dummy, pw)[0])
    n_params = count_parameters(model)
    logger.info(f"training {ARCH} ({TRUNK} trunk + U-Net decoder, {n_params / 1e6:.2f} M parameters, weights: "
        f"{weights_used}) on {len(train_rows)} train / {len(val_rows)} val scenes of {', '.join(params.datasets)}: "
        f"{settings.crops_per_image} random "
        f"{crop}-px crops per image and epoch, {device} {precision}, {params.epochs} epochs, lr {settings.lr} "
        f"({params.lr_schedule}), "
        f"boundary weight {pw:.1f} (targets made in {time.perf_counter() - t_load:.1f} s)")
    opt = torch.optim.Adam(model.parameters(), lr=settings.lr, weight_decay=params.weight_decay)
    steps_per_epoch = math.ceil(len(x_train) * settings.crops_per_image / params.batch_size)
    sched = LrSchedule(opt, params.lr_schedule, params.epochs, steps_per_epoch, params.lr_factor, params.lr_patience)
    gen = torch.Generator().manual_seed(params.seed)
    history: list[dict] = []
    best, best_epoch, best_state, stale = math.inf, -1, None, 0
    stop_reason = "max epochs"
    t_train0 = time.perf_counter()
    for epoch in range(params.epochs):
        t0 = time.perf_counter()
        model.train()
        order = torch.cat([torch.randperm(len(x_train), generator=gen) for _ in range(settings.crops_per_image)])
        total, n = 0.0, 0
        with tqdm(total=len(order), desc=f"{ARCH} epoch {epoch + 1}/{params.epochs}", unit="crop", mininterval=2.0,
                  disable=not logger.isEnabledFor(logging.INFO)) as bar:
            for b in range(0, len(order), params.batch_size):
                x, t = random_crops(x_train, t_train, order[b : b + params.batch_size], crop, gen, params.augment)
                if settings.photometric > 0:
                    x = photometric(x, gen, settings.photometric)
                x, t = normalise(x.to(device)), t.to(device)
                loss = optimise_step(model, opt, x, lambda out, t=t: instance_loss(out, t, pw)[0], device, precision,
                                     "train.instances.lr")
                sched.after_step()
                total += loss * len(x)
                n += len(x)
                bar.update(len(x))
                bar.set_postfix(loss=f"{total / n:.4f}")
        train_loss = total / max(n, 1)
        val_loss = _val_loss(model, x_val, t_val, device, precision, pw)
        sched.after_epoch(val_loss)
        lr = opt.param_groups[0]["lr"]
        row = {"epoch": epoch + 1, "train_loss": train_loss, "val_loss": val_loss, "val_mae_mm": float("nan"), "lr": lr,
               "seconds": time.perf_counter() - t0}
        history.append(row)
        improved = val_loss < best
        if improved:
            best, best_epoch, stale = val_loss, epoch + 1, 0
            best_state = {k: v.detach().cpu().clone() for k, v in model.state_dict().items()}
        else:
            stale += 1
        logger.info(f"epoch {epoch + 1}: train loss {train_loss:.4f}, val loss {val_loss:.4f}, lr {lr:.2e}, "
            f"{row['seconds']:.0f} s{' (best)' if improved else ''}")
        write_history(history, out_dir / "history.csv")
        if stale >= params.early_stopping_patience:
            stop_reason = f"early stopping (no better val loss for {stale} epochs)"
            break
    train_seconds = time.perf_counter() - t_train0
    if best_state is None:
        raise PsdError("no epoch was trained (train.epochs must be ≥ 1)")
    model.load_state_dict(best_state)
    model.eval()

    # calibration: post-processing on the validation masks, the read-out on the training split
    t0 = time.perf_counter()
    meta = {"arch": ARCH, "weights": weights_used, "sieve_method": settings.sieve_method, "readout": None,
            "postprocess": dict(DEFAULT_POSTPROCESS), "tta": settings.tta}
    est = InstanceEstimator(torch_maps_fn(model, device, "fp32"), meta)  # as evaluate and predict run it
    val_maps = all_maps(est, x_val)
    val_masks = [read_png(Path(results_root) / r["mask_path"]) for r in val_rows]
    post, val_f1 = pick_postprocess(val_maps, val_masks)
    est.post = post
    train_maps = all_maps(est, x_train)
    train_res = [est.analyse_maps(mp, s) for mp, s in zip(train_maps, _scaled_rows(train_rows), strict=True)]
    val_res = [est.analyse_maps(mp, s) for mp, s in zip(val_maps, _scaled_rows(val_rows), strict=True)]
    y_train, y_val = label_targets(train_rows).numpy(), label_targets(val_rows).numpy()
    # the read-out is fitted on the training and the validation scenes: the network has learnt
    # the training images, so its instances there are better than on new images; the validation
    # images show the read-out what the network makes of images it has not seen
    readout = fit_readout(np.stack([r.stats for r in train_res + val_res]), np.concatenate([y_train, y_val]),
                          features=READOUTS[settings.readout])
    from .metrics import regression_metrics

    readouts = other_readouts(np.stack([r.stats for r in train_res + val_res]), train_rows + val_rows,
                              READOUTS[settings.readout])
    val_cal = regression_metrics(y_val, apply_readout(readout, np.stack([r.stats for r in val_res])))
    val_raw = regression_metrics(y_val, np.nan_to_num(np.stack([r.raw for r in val_res])))
    history[-1]["val_mae_mm"] = val_cal["overall"]["mae"]
    write_history(history, out_dir / "history.csv")
    r2s = {k: " / ".join(f"{m[n]['r2']:.3f}" for n in NAMES) for k, m in (("cal", val_cal), ("raw", val_raw))}
    cv = " / ".join(f"{v:.3f}" for v in readout["cv_r2"]) if readout["cv_r2"] else "n/a (too few scenes)"
    logger.info(f"read-out ({settings.readout}) fitted on {len(train_rows)} training + {len(val_rows)} validation "
        f"scenes (ridge {readout['alpha']:g}): cross-validated R² {cv}; validation R² calibrated (in the fit) "
        f"{r2s['cal']}, raw {r2s['raw']} ({time.perf_counter() - t0:.0f} s)")

    mm = float(np.median([r["mm_per_px"] for r in train_rows]))
    res = int(np.median([r["resolution"] for r in train_rows]))
    summary = {
        "arch": ARCH,
        "trunk": TRUNK,
        "decoder": list(DECODER),
        "full_res_channels": FULL_RES,
        "input_size": res,  # inference runs on whole images at the training images' scale
        "crop_size": crop,
        "image_resolution": res,
        "mm_per_px": mm,
        "targets": list(TARGETS),
        **label_definition(train_rows + val_rows),
        "weights": weights_used,
        "maps": list(MAPS),
        "postprocess": post,
        "sieve_method": settings.sieve_method,
        "readout_features": settings.readout,
        "tta": settings.tta,
        "readout": readout,
        "readouts": readouts,  # the other solid size definitions (predict --size-definition)
        "boundary_pos_weight": pw,
        # the validation scenes are in the read-out's fit: its out-of-fold R² is the honest figure
        "val": {"f1": val_f1, "r2_readout_cv": readout["cv_r2"],
                "r2_calibrated_in_fit": [val_cal[n]["r2"] for n in NAMES],
                "r2_raw": [val_raw[n]["r2"] for n in NAMES]},
        "params": asdict(params),
        "n_parameters": n_params,
        "psdfactory_version": __version__,
        "best_epoch": best_epoch,
        "epochs_run": len(history),
        "stop_reason": stop_reason,
        "train_seconds": train_seconds,
        "precision": precision,
        "device": str(device),
    }
    save_model(out_dir / "model.pt", model, summary)
    logger.info(f"done: best val loss {best:.4f} at epoch {best_epoch} ({stop_reason}), {train_seconds:.0f} s of "
        f"training; wrote {out_dir / 'model.pt'}")
    return summary


def write_history(rows: list[dict], path: Path) -> None:
    keys = ["epoch", "train_loss", "val_loss", "val_mae_mm", "lr", "seconds"]
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        for r in rows:
            w.writerow({k: r[k] for k in keys})
