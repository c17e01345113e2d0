"""Training of one architecture on a dataset's train/val splits (the paper's recipe by default).

MSE on standardised targets, Adam, ReduceLROnPlateau on the validation loss (or a one-cycle
schedule, `train.lr_schedule`), random 90°
rotations and flips, early stopping; best checkpoint kept, resumable from the last one.
"""

from __future__ import annotations

import csv
import hashlib
import json
import logging
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import nn

from .. import PsdError, __version__
from ..config import config_fields
from ..io import atomic_path
from ..psd import TARGETS
from .augment import augment_d4, photometric, rescale
from .data import SceneImages, label_definition, normalise, training_rows
from .models import TargetStats, build_model, count_parameters, inception_aux_fits, input_size
from .runtime import (
    LrSchedule,
    load_checkpoint,
    loss_fn,
    optimise_step,
    pick_device,
    predict_batches,
    save_model,
    training_precision,
    write_torch,
)

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrainParams:
    """One architecture's training settings: the config's `train` section (defaults: the
    schema's, config.schema.yaml) with the architecture, its input size and the seed
    (config.train_params)."""

    arch: str  # one of train.architectures
    datasets: tuple[str, ...]  # trained on together
    pretrained: str
    epochs: int
    batch_size: int
    lr: float
    weight_decay: float
    lr_factor: float
    lr_patience: int
    lr_schedule: str  # plateau | onecycle (runtime.LrSchedule)
    early_stopping_patience: int
    input_size: int  # train.input_size[arch], else config.default_input_size(arch)
    precision: str  # auto | fp32 | bf16 | fp16
    device: str
    aux_loss_weight: float
    augment: bool
    scale_augment: tuple[float, float]
    photometric: float
    size_cells: float  # weight of the dense size-histogram loss (learn.size_cells); 0 = off
    seed: int  # the config's seed

    @classmethod
    def from_dict(cls, d: dict) -> TrainParams:
        return cls(**config_fields(cls, d, "train"))


def train_from_params(params: dict, results_root: Path, out_dir: Path) -> dict:
    """`train` from a `config.train_params` slice: the instance estimator's slice carries its own
    `instances` settings beside the `train` ones (the CNNs' slices do not: editing them retrains
    no CNN)."""
    params = dict(params)
    instances = params.pop("instances", None)
    return train(TrainParams.from_dict(params), results_root, out_dir, instances)


def fingerprint(params: TrainParams, rows: list[dict]) -> str:
    """What a resumable checkpoint must match: the settings and the exact training scenes."""
    ids = [(r["scene_id"], r["split"], *(r[t] for t in TARGETS)) for r in rows]
    blob = json.dumps({"params": asdict(params), "scenes": ids}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


@dataclass
class History:
    rows: list[dict] = field(default_factory=list)

    def write_csv(self, path: Path) -> None:
        with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
            keys = ["epoch", "train_loss", "val_loss", "val_mae_mm", "lr", "seconds"]
            w = csv.DictWriter(f, fieldnames=keys)
            w.writeheader()
            for r in self.rows:
                w.writerow({k: r[k] for k in keys})


@dataclass
class SizeCells:
    """The dense size-histogram task of `learn.size_cells` while training: the tap on the
    backbone's last feature map, the head that reads it, and the loss weight."""

    tap: object
    head: nn.Module
    weight: float

    def loss(self, codes: torch.Tensor) -> torch.Tensor:
        from .size_cells import cell_loss, cell_targets

        f = self.tap.features.float()  # in fp32 whatever the backbone's autocast precision
        return self.weight * cell_loss(self.head(f), cell_targets(codes.to(f.device), tuple(f.shape[-2:])))


def run_epoch(model, loader, stats, opt, sched, device, precision, aux_weight, gen, params: TrainParams,
              bar=None, cells: SizeCells | None = None) -> float:
    """One pass over the training images; with `cells` the loader's images carry size codes as a
    fourth channel (augmented with the image) and the size-histogram loss is added."""
    model.train()
    total, n = 0.0, 0
    for x, y in loader:
        if params.augment:
            x = augment_d4(x, gen)
        if tuple(params.scale_augment) != (1.0, 1.0):
            x, y = rescale(x, y, tuple(params.scale_augment), gen)
        codes = x[:, 3] if cells is not None else None
        x = x[:, :3]
        if params.photometric > 0:
            x = photometric(x, gen, params.photometric)
        x = normalise(x.to(device)).contiguous(memory_format=torch.channels_last)
        y = stats.standardise(y.to(device))

        def loss_of(out, y=y, codes=codes):
            loss = loss_fn(out, y, stats, aux_weight)
            return loss if cells is None else loss + cells.loss(codes)

        loss = optimise_step(model, opt, x, loss_of, device, precision, "train.lr")
        sched.after_step()
        total += loss * len(x)
        n += len(x)
        if bar is not None:
            bar.update(len(x))
            bar.set_postfix(loss=f"{total / n:.4f}")
    return total / max(n, 1)


def resume_state(fp: str, epoch: int, model, opt, sched, gen: torch.Generator, loader_gen: torch.Generator,
                 history: History, best: float, best_epoch: int, stale: int, cells: SizeCells | None = None) -> dict:
    """What checkpoints/last.pt holds to resume training exactly: tensors and plain data only
    (state dicts, the generators' ByteTensor states), so that it loads with weights_only=True."""
    return {
        "fingerprint": fp, "epoch": epoch, "model": model.state_dict(), "optimizer": opt.state_dict(),
        "scheduler": sched.state_dict(), "gen": gen.get_state(), "loader_gen": loader_gen.get_state(),
        "torch_rng": torch.get_rng_state(), "history": history.rows, "best": float(best),
        "best_epoch": int(best_epoch), "stale": int(stale),
        "cell_head": cells.head.state_dict() if cells is not None else None,
    }


def train(params: TrainParams, results_root: Path, out_dir: Path, instances: dict | None = None) -> dict:
    """Train `params.arch`; for the instance estimator (arch 'instances') `instances` is the
    config's `train.instances` slice (see `train_from_params`)."""
    if params.arch == "instances":  # segmentation network + measurement + read-out
        from .instance_training import train_instances
        from .instances import InstanceSettings

        if instances is None:
            raise PsdError("arch 'instances' needs the train.instances settings (config.train_params gives them)")
        return train_instances(params, InstanceSettings.from_dict(instances), results_root, out_dir)
    from tqdm import tqdm

    torch.manual_seed(params.seed)
    np.random.seed(params.seed % 2**32)
    device = pick_device(params.device)
    size = input_size(params.arch, {params.arch: params.input_size})

    train_rows, val_rows, rows = training_rows(results_root, params.datasets)
    train_ds = SceneImages(results_root, train_rows, size)
    val_ds = SceneImages(results_root, val_rows, size)
    stats = TargetStats.from_targets(train_ds.y)
    model, weights_used = build_model(params.arch, stats, params.pretrained, size=size)
    if params.arch == "inception_v3" and not inception_aux_fits(size):
        logger.info(f"inception_v3 at {size} px: auxiliary head dropped (it needs ≥ 299 px)")
    model = model.to(device).to(memory_format=torch.channels_last)
    batch = min(params.batch_size, len(train_ds))
    precision = training_precision(params.precision, device, model, size, batch,
                                   lambda out: loss_fn(out, torch.zeros(batch, 3), stats, params.aux_loss_weight))
    cells, fed = None, train_ds
    if params.size_cells > 0:  # the dense size-histogram task: a head on the last feature map, training only
        from .instances import read_particles
        from .size_cells import CellHead, FeatureTap, ScenesWithSizeCodes, feature_channels

        tap = FeatureTap(model, params.arch)
        cells = SizeCells(tap, CellHead(feature_channels(model, tap, size)).to(device), params.size_cells)
        particles = {k: v for ds in params.datasets for k, v in read_particles(results_root, ds).items()}
        fed = ScenesWithSizeCodes(train_ds, particles)
    trained = list(model.parameters()) + (list(cells.head.parameters()) if cells is not None else [])
    opt = torch.optim.Adam(trained, lr=params.lr, weight_decay=params.weight_decay)
    gen = torch.Generator().manual_seed(params.seed)
    loader_gen = torch.Generator().manual_seed(params.seed + 1)
    train_loader = torch.utils.data.DataLoader(fed, batch_size=params.batch_size, shuffle=True, generator=loader_gen)
    sched = LrSchedule(opt, params.lr_schedule, params.epochs, len(train_loader), params.lr_factor,
                       params.lr_patience)
    val_loader = torch.utils.data.DataLoader(val_ds, batch_size=params.batch_size)

    ckpt_dir = out_dir / "checkpoints"
    last_path = ckpt_dir / "last.pt"
    fp = fingerprint(params, rows)
    history = History()
    start_epoch, best, best_epoch, stale = 0, math.inf, -1, 0
    if last_path.is_file():
        ck = load_checkpoint(last_path, "training checkpoint")
        if ck.get("fingerprint") == fp:
            model.load_state_dict(ck["model"])
            if cells is not None:
                cells.head.load_state_dict(ck["cell_head"])
            opt.load_state_dict(ck["optimizer"])
            sched.load_state_dict(ck["scheduler"])
            gen.set_state(ck["gen"])
            loader_gen.set_state(ck["loader_gen"])
            torch.set_rng_state(ck["torch_rng"])
            history.rows = ck["history"]
            start_epoch, best, best_epoch, stale = ck["epoch"] + 1, ck["best"], ck["best_epoch"], ck["stale"]
            logger.info(f"resuming {params.arch} from epoch {start_epoch + 1} (checkpoint {last_path})")
        else:
            logger.info(f"ignoring {last_path}: it was made with other settings or data")

    from torch.utils.tensorboard import SummaryWriter

    tb = SummaryWriter(str(out_dir / "tensorboard"))
    n_params = count_parameters(model)
    logger.info(f"training {params.arch} ({n_params / 1e6:.1f} M parameters, weights: {weights_used}) on "
        f"{len(train_ds)} train / {len(val_ds)} val scenes of {', '.join(params.datasets)}, input {size} px, "
        f"{device} {precision}, up to {params.epochs} epochs")
    meta = {
        "arch": params.arch,
        "input_size": size,
        "target_stats": asdict(stats),
        "targets": list(TARGETS),
        **label_definition(train_rows + val_rows),
        "mm_per_px": float(np.median([r["mm_per_px"] for r in train_rows])),
        "image_resolution": int(np.median([r["resolution"] for r in train_rows])),
        "weights": weights_used,
        "params": asdict(params),
        "n_parameters": n_params,
        "psdfactory_version": __version__,
    }
    stop_reason = "max epochs"
    for epoch in range(start_epoch, params.epochs):
        t0 = time.perf_counter()
        with tqdm(total=len(train_ds), desc=f"{params.arch} epoch {epoch + 1}/{params.epochs}", unit="img",
                  mininterval=2.0, leave=True, disable=not logger.isEnabledFor(logging.INFO)) as bar:
            train_loss = run_epoch(model, train_loader, stats, opt, sched, device, precision,
                                   params.aux_loss_weight, gen, params, bar, cells)
        pred, y = predict_batches(model, val_loader, device, precision)
        val_loss = float(nn.functional.mse_loss(stats.standardise(pred), stats.standardise(y)))
        val_mae = float((pred - y).abs().mean())
        sched.after_epoch(val_loss)
        lr = opt.param_groups[0]["lr"]
        row = {"epoch": epoch + 1, "train_loss": train_loss, "val_loss": val_loss, "val_mae_mm": val_mae, "lr": lr,
               "seconds": time.perf_counter() - t0}
        history.rows.append(row)
        for k in ("train_loss", "val_loss", "val_mae_mm", "lr"):
            tb.add_scalar(k, row[k], epoch + 1)
        improved = val_loss < best
        if improved:
            best, best_epoch, stale = val_loss, epoch + 1, 0
            save_model(ckpt_dir / "best.pt", model, {**meta, "epoch": epoch + 1, "val_loss": val_loss})
        else:
            stale += 1
        logger.info(f"epoch {epoch + 1}: train loss {train_loss:.4f}, val loss {val_loss:.4f}, "
                    f"val MAE {val_mae:.3f} mm, lr {lr:.2e}, {row['seconds']:.0f} s{' (best)' if improved else ''}")
        write_torch(last_path, resume_state(fp, epoch, model, opt, sched, gen, loader_gen, history, best, best_epoch,
                                            stale, cells))
        history.write_csv(out_dir / "history.csv")
        if stale >= params.early_stopping_patience:
            stop_reason = f"early stopping (no better val loss for {stale} epochs)"
            break
    tb.close()
    if cells is not None:
        cells.tap.remove()
    if best_epoch < 0:
        raise PsdError("no epoch was trained (train.epochs must be ≥ 1)")
    best_ckpt = load_checkpoint(ckpt_dir / "best.pt", "training checkpoint")
    summary = {**best_ckpt["meta"], "best_epoch": best_epoch, "epochs_run": len(history.rows),
               "stop_reason": stop_reason, "precision": precision, "device": str(device)}
    write_torch(out_dir / "model.pt", {"meta": summary, "state_dict": best_ckpt["state_dict"]})
    history.write_csv(out_dir / "history.csv")
    logger.info(f"done: best val loss {best:.4f} at epoch {best_epoch} ({stop_reason}); wrote {out_dir / 'model.pt'}")
    return summary
