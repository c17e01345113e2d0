"""Training of one architecture on its datasets' train/val splits: the `train` section of the
config as `TrainParams`, handed to the architecture's estimator (`learn.registry`), which trains
with the shared loop of `learn.fit`."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from .. import PsdError
from ..config import config_fields


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
    crop: int  # train on random windows of this many px of each input image (labels kept); 0 = off
    size_cells: float  # weight of the dense size-histogram loss (learn.size_cells); 0 = off
    seed: int  # the config's seed

    @classmethod
    def from_dict(cls, d: dict) -> TrainParams:
        # train.crop is in a slice only when on (config.train_params): absent means off
        return cls(**config_fields(cls, {"crop": 0, **d}, "train"))


def train_from_params(params: dict, results_root: Path, out_dir: Path, pack: Path | None = None,
                      loader_workers: int = 0) -> dict:
    """`train` from a `config.train_params` slice: an estimator with settings of its own
    (`train.<arch>`, e.g. train.instances) gets them as `settings` (the others' slices do not
    carry them: editing them retrains nothing else)."""
    params = dict(params)
    settings = params.pop("settings", None)
    return train(TrainParams.from_dict(params), results_root, out_dir, settings, pack, loader_workers)


def train(params: TrainParams, results_root: Path, out_dir: Path, settings: dict | None = None,
          pack: Path | None = None, loader_workers: int = 0) -> dict:
    """Train `params.arch` with its estimator; returns the model's meta (also in model.pt). With
    `pack` (`psdfactory pack`) a CNN reads its images from the pack's shards instead of the scene
    folders, `loader_workers` DataLoader workers each, on every rank of a ``torchrun`` job."""
    import inspect

    from .registry import estimator_class

    estimator = estimator_class(params.arch)
    if pack is None:  # the interface every estimator has (plugins' included)
        return estimator.train(params, Path(results_root), Path(out_dir), settings)
    if loader_workers < 0:
        raise PsdError(f"--loader-workers {loader_workers}: 0 (load in the training process) or more")
    if "pack" not in inspect.signature(estimator.train).parameters:
        raise PsdError(f"{params.arch!r} does not train from a pack: leave out --pack")
    return estimator.train(params, Path(results_root), Path(out_dir), settings, pack=Path(pack),
                           loader_workers=loader_workers)
