"""The paper's estimator: a CNN regressor (any torchvision classification model with the ordered
head of `learn.models`) whose output is d10/d50/d90 in mm.

Training follows the paper's recipe by default: MSE on standardised targets, Adam,
ReduceLROnPlateau on the validation loss (or a one-cycle schedule, `train.lr_schedule`), random
90° rotations and flips, early stopping, the best checkpoint kept (`learn.fit`); beside it the
scale, crop and photometric augmentations and the dense size task (`train.size_cells`).
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from .. import PsdError, __version__
from ..psd import TARGETS
from .augment import augment_d4, photometric, rescale
from .data import SceneImages, label_definition, normalise, particles_by_scene, split_summary, training_rows
from .estimator import Estimator, Reading
from .fit import FitTask, fingerprint, fit, write_history
from .models import (
    TargetStats,
    build_model,
    count_parameters,
    crop_size,
    inception_aux_fits,
    input_size,
    main_output,
)
from .runtime import (
    LrSchedule,
    is_target_stats,
    loss_fn,
    loss_scaler,
    optimise_step,
    pick_device,
    predict_batches,
    save_model,
    training_precision,
)

logger = logging.getLogger(__name__)


class OutputOnly(nn.Module):
    """A plain tensor out (d10, d50, d90 in mm), also for InceptionV3's tuple output."""

    def __init__(self, model: nn.Module):
        super().__init__()
        self.m = model

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return main_output(self.m(images))


@dataclass
class SizeCells:
    """The dense size-histogram task of `learn.size_cells` while training: the tap on the
    backbone's last feature map, the head that reads it (as it trains: DistributedDataParallel on
    several ranks), the loss weight, and the head itself (what is saved)."""

    tap: object
    head: nn.Module
    weight: float
    module: nn.Module

    def loss(self, codes: torch.Tensor) -> torch.Tensor:
        from .size_cells import cell_loss, cell_targets

        f = self.tap.features.float()  # in fp32 whatever the backbone's autocast precision
        return self.weight * cell_loss(self.head(f), cell_targets(codes.to(f.device), tuple(f.shape[-2:])))


def run_epoch(model, loader, stats, opt, sched, device, precision, aux_weight, gen, params,
              bar=None, cells: SizeCells | None = None, scaler=None) -> float:
    """One pass over the training images (or their windows, `windows.SceneWindows`); with `cells`
    the loader's images carry size codes as a fourth channel (augmented with the image) and the
    size-histogram loss is added; `scaler`: fp16's loss scaler (`runtime.loss_scaler`)."""
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

        loss = optimise_step(model, opt, x, loss_of, device, precision, "train.lr", scaler)
        sched.after_step()
        total += loss * len(x)
        n += len(x)
        if bar is not None:
            bar.update(len(x))
            bar.set_postfix(loss=f"{total / n:.4f}")
    return total / max(n, 1)


class CnnRegressor(Estimator):
    """A torchvision CNN with the ordered regression head: image in, d10/d50/d90 (mm) out."""

    @classmethod
    def build_net(cls, meta: dict) -> nn.Module:
        model, _ = build_model(meta["arch"], TargetStats(**meta["target_stats"]), "none", size=meta["input_size"])
        return model

    @classmethod
    def meta_problems(cls, meta: dict) -> list[str]:
        ok = is_target_stats(meta.get("target_stats"))
        return [] if ok else [f"target_stats is missing or not valid (got {str(meta.get('target_stats'))[:80]!r})"]

    def inference_module(self) -> nn.Module:
        return OutputOnly(super().inference_module()).eval()

    def read(self, outputs: np.ndarray, mm_per_px: list[float]) -> list[Reading]:
        return [Reading(np.asarray(o, dtype=float)) for o in np.asarray(outputs).reshape(-1, len(TARGETS))]

    @classmethod
    def train(cls, params, results_root: Path, out_dir: Path, settings: dict | None = None,
              pack: Path | None = None, loader_workers: int = 0) -> dict:
        """Train on the datasets' scene folders, or on a pack's shards (`pack`, read by
        `loader_workers` DataLoader workers); under ``torchrun`` on several processes (a pack
        only: each rank its own shards, `learn.distributed`)."""
        from .distributed import agree, barrier, ranks_from_env, start, stop, wrap

        ranks = ranks_from_env()
        if ranks.distributed and pack is None:
            raise PsdError(f"training on {ranks.world} processes reads a pack, each rank its own shards: pack the "
                           "training datasets (psdfactory pack) and give it with --pack")
        torch.manual_seed(params.seed)
        np.random.seed(params.seed % 2**32)
        device = start(ranks, pick_device(params.device))
        size = input_size(params.arch, {params.arch: params.input_size})
        crop = crop_size(params.arch, params.crop, size)
        cells_on = params.size_cells > 0
        loader_gen = torch.Generator().manual_seed(params.seed + 1)
        window_gen = torch.Generator().manual_seed(params.seed + 2)  # train.crop's windows
        if pack is None:
            data = folder_data(params, results_root, size, cells_on, loader_gen, crop, window_gen)
        else:
            data = pack_data(params, Path(pack), size, cells_on, loader_workers, ranks, crop)
        stats = data.stats
        model, weights_used = build_model(params.arch, stats, params.pretrained, size=size)
        if params.arch == "inception_v3" and not inception_aux_fits(size):
            logger.info(f"inception_v3 at {size} px: auxiliary head dropped (it needs ≥ 299 px)")
        model = model.to(device).to(memory_format=torch.channels_last)
        batch = min(params.batch_size, data.n_train)
        precision = agree(training_precision(params.precision, device, model, crop or size, batch,
                                             lambda out: loss_fn(out, torch.zeros(batch, 3), stats,
                                                                 params.aux_loss_weight)), ranks)
        cells = None
        if cells_on:  # the dense size-histogram task: a head on the last feature map, training only
            from .size_cells import CellHead, FeatureTap, feature_channels

            tap = FeatureTap(model, params.arch)
            head = CellHead(feature_channels(model, tap, size)).to(device)
            cells = SizeCells(tap, wrap(head, ranks, device), params.size_cells, head)
        # what steps; `model` inside it is what is saved. InceptionV3's auxiliary head at aux_loss_weight 0 gets
        # no gradient, which DDP must be told of
        net = wrap(model, ranks, device, unused=getattr(model, "aux_logits", False) and not params.aux_loss_weight)
        trained = list(model.parameters()) + (list(cells.module.parameters()) if cells is not None else [])
        opt = torch.optim.Adam(trained, lr=params.lr, weight_decay=params.weight_decay)
        gen = torch.Generator().manual_seed(params.seed + ranks.rank)  # each rank augments its images its own way
        sched = LrSchedule(opt, params.lr_schedule, params.epochs, data.steps_per_epoch, params.lr_factor,
                           params.lr_patience)

        def validate() -> dict:
            pred, y = predict_batches(model, data.val_loader, device, precision)
            return {"val_loss": float(nn.functional.mse_loss(stats.standardise(pred), stats.standardise(y))),
                    "val_mae_mm": float((pred - y).abs().mean())}

        scaler = loss_scaler(device, precision)
        task = FitTask(model, opt, sched, lambda bar: run_epoch(net, data.train_loader, stats, opt, sched, device,
                                                               precision, params.aux_loss_weight, gen, params, bar,
                                                               cells, scaler),
                       validate, data.n_train, "img", modules={"cell_head": cells.module} if cells else {},
                       generators={"gen": gen, "loader_gen": loader_gen, "window_gen": window_gen}, scaler=scaler,
                       before_epoch=data.before_epoch)
        n_params = count_parameters(model)
        windows = f" (trained on random {crop}-px windows, each labelled by its particles)" if crop else ""
        logger.info(f"training {params.arch} ({n_params / 1e6:.1f} M parameters, weights: {weights_used}) on "
                    f"{data.describe}, input {size} px{windows}, "
                    f"{device} {precision}, up to {params.epochs} epochs")
        meta = {
            "arch": params.arch,
            "input_size": size,
            "target_stats": asdict(stats),
            "targets": list(TARGETS),
            **data.definition,
            "mm_per_px": data.mm_per_px,
            "image_resolution": data.resolution,
            "weights": weights_used,
            "params": asdict(params),
            "n_parameters": n_params,
            "psdfactory_version": __version__,
        }
        if pack is not None:
            meta["pack"] = {"path": str(pack), "datasets": data.datasets, "ranks": ranks.world}
        res = fit(task, params.arch, params.epochs, params.early_stopping_patience, out_dir,
                  fingerprint(asdict(params), data.fingerprint), meta, ranks)
        if cells is not None:
            cells.tap.remove()
        summary = {**meta, "epoch": res.best_epoch, "val_loss": res.best_loss, "best_epoch": res.best_epoch,
                   "epochs_run": len(res.history), "stop_reason": res.stop_reason, "precision": precision,
                   "device": str(device)}
        if ranks.main:
            save_model(out_dir / "model.pt", model, summary)
            write_history(res.history, out_dir / "history.csv")
            logger.info(f"done: best val loss {res.best_loss:.4f} at epoch {res.best_epoch} ({res.stop_reason}); "
                        f"wrote {out_dir / 'model.pt'}")
        barrier(ranks)
        stop(ranks)
        return summary


@dataclass
class TrainingData:
    """Where a CNN's training reads its images: the loaders and what the model's meta and the
    resumable checkpoint's fingerprint need of them."""

    train_loader: torch.utils.data.DataLoader
    val_loader: torch.utils.data.DataLoader
    stats: TargetStats
    n_train: int  # training images an epoch (on this rank)
    steps_per_epoch: int  # its batches (a one-cycle schedule's steps)
    definition: dict  # size_definition, weighting
    mm_per_px: float  # the training images' median scale, at their render size
    resolution: int  # their median render size (px)
    fingerprint: list  # what identifies the training data
    describe: str  # for the log
    datasets: list[str]
    before_epoch: object = None  # called with the epoch's index before it


def folder_data(params, results_root: Path, size: int, cells: bool, loader_gen: torch.Generator, crop: int,
                window_gen: torch.Generator) -> TrainingData:
    """The datasets' train and val scenes from their folders (decoded once, cached in memory);
    with `crop` > 0 each training image is cut to a random window of that many px (drawn by
    `window_gen`) labelled by its own particles (`windows.SceneWindows`)."""
    from ..manifest import PARTICLE_READ_COLUMNS
    from .windows import PARTICLE_COLUMNS, SceneWindows

    train_rows, val_rows, rows = training_rows(results_root, params.datasets)
    train_ds = SceneImages(results_root, train_rows, size)
    val_ds = SceneImages(results_root, val_rows, size)
    fed = train_ds
    particles = None
    if cells or crop:  # the particle manifest read once, with the columns of both
        columns = (*PARTICLE_READ_COLUMNS, *(c for c in PARTICLE_COLUMNS if crop and c not in PARTICLE_READ_COLUMNS))
        particles = particles_by_scene(results_root, params.datasets, columns)
    if cells:
        from .size_cells import ScenesWithSizeCodes

        fed = ScenesWithSizeCodes(train_ds, particles)
    if crop:
        fed = SceneWindows(fed, train_rows, particles, crop, label_definition(train_rows)["weighting"], window_gen)
    train = split_summary(train_ds.y.numpy(), np.array([r["mm_per_px"] for r in train_rows]),
                          np.array([r["resolution"] for r in train_rows]))
    loader = torch.utils.data.DataLoader(fed, batch_size=params.batch_size, shuffle=True, generator=loader_gen)
    return TrainingData(
        loader, torch.utils.data.DataLoader(val_ds, batch_size=params.batch_size),
        TargetStats(**train["target_stats"]), len(train_ds), len(loader), label_definition(train_rows + val_rows),
        train["mm_per_px"], train["resolution"], [(r["scene_id"], r["split"], *(r[t] for t in TARGETS)) for r in rows],
        f"{len(train_ds)} train / {len(val_ds)} val scenes of {', '.join(params.datasets)}", list(params.datasets))


def pack_data(params, pack: Path, size: int, cells: bool, workers: int, ranks, crop: int = 0) -> TrainingData:
    """A pack's train split, each rank its own shards, and its whole val split on every rank."""
    from ..packs import read_index
    from .shards import ShardScenes, stack_codes

    if crop:
        raise PsdError(f"train.crop = {crop}: each window is labelled by the particles inside it, and a pack holds "
                       "no particle positions; train from the scene folders (without --pack), or set train.crop: 0")
    index = read_index(pack)
    if index["size"] != size:
        raise PsdError(f"--pack {pack} holds {index['size']} px images, {params.arch} trains at {size} px: pack "
                       f"with --size {size} (or set train.input_size.{params.arch})")
    for split in ("train", "val"):
        if split not in index["splits"]:
            raise PsdError(f"--pack {pack} has no {split} split; training needs train and val scenes")
    if cells and not index["masks"]:
        raise PsdError(f"--pack {pack} was packed with --no-masks: train.size_cells needs its size codes; pack "
                       "with masks, or set train.size_cells: 0")
    train_ds = ShardScenes(pack, "train", ("image", "codes", "targets") if cells else ("image", "targets"),
                           seed=params.seed, num_workers=workers, transform=stack_codes if cells else None)
    val_ds = ShardScenes(pack, "val", ("image", "targets"), shuffle_buffer=0, world=(0, 1))  # all of it, each rank
    train = index["splits"]["train"]
    n_val = index["splits"]["val"]["scenes"]
    return TrainingData(
        torch.utils.data.DataLoader(train_ds, batch_size=params.batch_size, num_workers=workers),
        torch.utils.data.DataLoader(val_ds, batch_size=params.batch_size),
        TargetStats(**train["target_stats"]), len(train_ds), train_ds.batches(params.batch_size),
        {"size_definition": index["size_definition"], "weighting": index["weighting"]},
        float(train["mm_per_px"]), int(train["resolution"]),
        [s["sha256"] for split in ("train", "val") for s in index["splits"][split]["shards"]],
        f"the pack {pack} ({', '.join(index['datasets'])}: {train['scenes']} train / {n_val} val scenes; "
        f"{len(train_ds)} a rank on {ranks.world} rank{'s' * (ranks.world > 1)}, {workers} loader workers each)",
        list(index["datasets"]), train_ds.set_epoch)
