"""The one training loop every estimator uses (after torchvision's references/classification
``train.py``): epochs of `task.train_epoch`, a validation after each, the learning-rate schedule,
the best checkpoint kept by validation loss, early stopping after `patience` epochs without a
better one (under a schedule that allows it: `LrSchedule.stops_early`), ``history.csv`` and
TensorBoard scalars, and a resumable ``checkpoints/last.pt`` (everything needed to go on exactly
where a killed job stopped, refused when the settings or the training data changed: `fingerprint`).
"""

from __future__ import annotations

import csv
import hashlib
import json
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import nn

from .. import PsdError
from ..io import atomic_path
from .distributed import Ranks, agree, barrier
from .runtime import LrSchedule, load_checkpoint, save_model, write_torch

logger = logging.getLogger(__name__)
HISTORY_COLUMNS = ("epoch", "train_loss", "val_loss", "val_mae_mm", "lr", "seconds")
SINGLE = Ranks()  # one process


def fingerprint(settings: dict, data: list) -> str:
    """What a resumable checkpoint must match: the settings and the exact training data."""
    blob = json.dumps({"params": settings, "data": data}, sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def write_history(rows: list[dict], path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=HISTORY_COLUMNS)
        w.writeheader()
        for r in rows:
            w.writerow({k: r.get(k, float("nan")) for k in HISTORY_COLUMNS})


@dataclass
class FitTask:
    """What one estimator's training brings to `fit`.

    `train_epoch(bar)` runs one epoch (updating the tqdm `bar` by `unit`s) and returns its mean
    training loss; `validate()` returns {"val_loss": ..., optionally "val_mae_mm": ...}. `model`
    is the network saved as the best checkpoint; `modules` (the model among them) and
    `generators` are saved in the resumable checkpoint with the optimiser, the schedule and the
    fp16 loss `scaler` (`runtime.loss_scaler`; None in bf16 and fp32) that `train_epoch` steps with.
    In a distributed training (`learn.distributed`) `model` is the module inside the
    DistributedDataParallel wrapper that `train_epoch` steps, and `validate` returns the same on
    every rank.
    """

    model: nn.Module
    optimizer: torch.optim.Optimizer
    schedule: LrSchedule
    train_epoch: Callable[[object], float]
    validate: Callable[[], dict]
    items_per_epoch: int
    unit: str = "img"
    modules: dict[str, nn.Module] = field(default_factory=dict)
    generators: dict[str, torch.Generator] = field(default_factory=dict)
    scaler: torch.amp.GradScaler | None = None
    before_epoch: Callable[[int], None] | None = None  # called with the epoch's index before it (a pack's set_epoch)


@dataclass
class FitResult:
    best_loss: float
    best_epoch: int
    history: list[dict]
    stop_reason: str
    seconds: float


def _state(task: FitTask, fp: str, epoch: int, history: list[dict], best: float, best_epoch: int, stale: int) -> dict:
    """checkpoints/last.pt: tensors and plain data only (state dicts, the generators' ByteTensor
    states), so that it loads with weights_only=True."""
    return {
        "fingerprint": fp, "epoch": epoch, "optimizer": task.optimizer.state_dict(),
        "scheduler": task.schedule.state_dict(), "torch_rng": torch.get_rng_state(), "history": history,
        "best": float(best), "best_epoch": int(best_epoch), "stale": int(stale),
        "modules": {k: m.state_dict() for k, m in {"model": task.model, **task.modules}.items()},
        "generators": {k: g.get_state() for k, g in task.generators.items()},
        "grad_scaler": task.scaler.state_dict() if task.scaler is not None else None,
    }


def _resume(task: FitTask, path: Path, fp: str, name: str, also: tuple[str, ...] = ()
            ) -> tuple[int, list[dict], float, int, int]:
    """(first epoch, history, best, best epoch, stale) from `path` when it matches `fp` (or one of
    `also`: the same training's fingerprints as older versions computed them)."""
    fresh = (0, [], math.inf, -1, 0)
    if not path.is_file():
        return fresh
    ck = load_checkpoint(path, "training checkpoint")
    if ck.get("fingerprint") not in (fp, *also) or "modules" not in ck:
        logger.info(f"ignoring {path}: it was made with other settings or data")
        return fresh
    for k, m in {"model": task.model, **task.modules}.items():
        m.load_state_dict(ck["modules"][k])
    task.optimizer.load_state_dict(ck["optimizer"])
    saved = ck.get("grad_scaler")
    if task.scaler is not None and saved:
        task.scaler.load_state_dict(saved.get("state", saved))  # checkpoints of before 2026-11-26 held {device, state}
    task.schedule.load_state_dict(ck["scheduler"])
    for k, g in task.generators.items():
        g.set_state(ck["generators"][k])
    torch.set_rng_state(ck["torch_rng"])
    logger.info(f"resuming {name} from epoch {ck['epoch'] + 2} (checkpoint {path})")
    return ck["epoch"] + 1, ck["history"], ck["best"], ck["best_epoch"], ck["stale"]


def fit(task: FitTask, name: str, epochs: int, patience: float, out_dir: Path, fp: str, meta: dict,
        ranks: Ranks = SINGLE, also_fp: tuple[str, ...] = ()) -> FitResult:
    """Train `task` for up to `epochs` epochs; the best weights (by validation loss) are in
    `task.model` at the end and in ``checkpoints/best.pt`` (with `meta`). Refuses a run that
    trained no epoch. Of several `ranks`, rank 0 alone writes files and logs; all decide alike."""
    from torch.utils.tensorboard import SummaryWriter
    from tqdm import tqdm

    ckpt_dir = out_dir / "checkpoints"
    last_path = ckpt_dir / "last.pt"
    start, history, best, best_epoch, stale = _resume(task, last_path, fp, name, also_fp)
    tb = SummaryWriter(str(out_dir / "tensorboard")) if ranks.main else None
    talk = ranks.main and logger.isEnabledFor(logging.INFO)
    stop_reason = "max epochs"
    if not task.schedule.stops_early:  # its length is part of the schedule: the best epoch's weights are kept
        patience = math.inf
        if talk:
            logger.info(f"{name}: the {task.schedule.name} schedule runs all {epochs} epochs (no early stopping)")
    t_start = time.perf_counter()
    try:
        for epoch in range(start, epochs):
            if stale >= patience:  # a resumed run that had already stopped early
                stop_reason = f"early stopping (no better val loss for {stale} epochs)"
                break
            t0 = time.perf_counter()
            if task.before_epoch is not None:
                task.before_epoch(epoch)
            with tqdm(total=task.items_per_epoch, desc=f"{name} epoch {epoch + 1}/{epochs}", unit=task.unit,
                      mininterval=2.0, disable=not talk) as bar:
                train_loss = task.train_epoch(bar)
            val = agree(task.validate(), ranks)  # rank 0's: BatchNorm statistics differ a little between ranks
            task.schedule.after_epoch(val["val_loss"])
            row = {"epoch": epoch + 1, "train_loss": train_loss, "val_loss": val["val_loss"],
                   "val_mae_mm": val.get("val_mae_mm", float("nan")), "lr": task.optimizer.param_groups[0]["lr"],
                   "seconds": time.perf_counter() - t0}
            history.append(row)
            improved = row["val_loss"] < best
            if improved:
                best, best_epoch, stale = row["val_loss"], epoch + 1, 0
            else:
                stale += 1
            if ranks.main:
                for k in ("train_loss", "val_loss", "val_mae_mm", "lr"):
                    if math.isfinite(row[k]):
                        tb.add_scalar(k, row[k], epoch + 1)
                if improved:
                    save_model(ckpt_dir / "best.pt", task.model, {**meta, "epoch": epoch + 1, "val_loss": best})
                mae = f", val MAE {row['val_mae_mm']:.3f} mm" if math.isfinite(row["val_mae_mm"]) else ""
                logger.info(f"epoch {epoch + 1}: train loss {train_loss:.4f}, val loss {row['val_loss']:.4f}{mae}, "
                            f"lr {row['lr']:.2e}, {row['seconds']:.0f} s{' (best)' if improved else ''}")
                write_torch(last_path, _state(task, fp, epoch, history, best, best_epoch, stale))
                write_history(history, out_dir / "history.csv")
            if stale >= patience:
                stop_reason = f"early stopping (no better val loss for {stale} epochs)"
                break
    finally:
        if tb is not None:
            tb.close()
    if best_epoch < 0:
        raise PsdError("no epoch was trained (train.epochs must be ≥ 1)")
    if stale >= patience:  # also a finished run resumed, which had stopped early at its last epoch
        stop_reason = f"early stopping (no better val loss for {stale} epochs)"
    barrier(ranks)  # best.pt is rank 0's: the others read it once it is written
    task.model.load_state_dict(load_checkpoint(ckpt_dir / "best.pt", "training checkpoint")["state_dict"])
    return FitResult(best, best_epoch, history, stop_reason, time.perf_counter() - t_start)
