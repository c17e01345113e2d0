"""CNN regressors for (d10, d50, d90) in mm, built on torchvision classification models.

The head guarantees d10 ≤ d50 ≤ d90 by construction: it predicts d10 and two non-negative
gaps (softplus). Targets are standardised inside the model: the head works in units of the
training targets' spread, and ``forward`` returns millimetres.
"""

from __future__ import annotations

import logging
import math
import warnings
from dataclasses import dataclass

import torch
from torch import nn

from .. import PsdError
from ..config import crop_problem, default_input_size, inception_aux_fits, input_size_problem

logger = logging.getLogger(__name__)


@dataclass
class TargetStats:
    """Statistics of the training targets.

    ``mean``/``std``: of d10, d50, d90 — the loss compares z-scores (standardised targets).
    ``part_mean``/``part_std``: of d10 and the gaps d50-d10, d90-d50 — the head's units.
    """

    mean: list[float]
    std: list[float]
    part_mean: list[float]
    part_std: list[float]

    @classmethod
    def from_targets(cls, y: torch.Tensor) -> TargetStats:
        y = y.double()
        parts = torch.stack([y[:, 0], y[:, 1] - y[:, 0], y[:, 2] - y[:, 1]], dim=1)

        def spread(t: torch.Tensor) -> list[float]:
            return (t.std(dim=0).clamp_min(1e-3) if len(t) > 1 else torch.ones(3, dtype=t.dtype)).tolist()

        return cls(y.mean(dim=0).tolist(), spread(y), parts.mean(dim=0).tolist(), spread(parts))

    def standardise(self, y_mm: torch.Tensor) -> torch.Tensor:
        mean = torch.tensor(self.mean, dtype=y_mm.dtype, device=y_mm.device)
        std = torch.tensor(self.std, dtype=y_mm.dtype, device=y_mm.device)
        return (y_mm - mean) / std


class OrderedHead(nn.Module):
    """features → (d10, d50, d90) in mm with d10 ≤ d50 ≤ d90 always."""

    def __init__(self, in_features: int, stats: TargetStats, dropout: float = 0.2):
        super().__init__()
        self.drop = nn.Dropout(dropout)
        self.fc = nn.Linear(in_features, 3)
        self.register_buffer("mean", torch.tensor(stats.part_mean, dtype=torch.float32))
        self.register_buffer("std", torch.tensor(stats.part_std, dtype=torch.float32))
        nn.init.normal_(self.fc.weight, std=1e-3)
        with torch.no_grad():
            # start at the training means: std * softplus(bias) = mean gap
            m, s = stats.part_mean, stats.part_std
            self.fc.bias.copy_(torch.tensor([0.0, _softplus_inv(m[1] / s[1]), _softplus_inv(m[2] / s[2])]))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        r = self.fc(self.drop(x)).float()
        d10 = self.mean[0] + self.std[0] * r[:, 0]
        gap1 = self.std[1] * nn.functional.softplus(r[:, 1])
        gap2 = self.std[2] * nn.functional.softplus(r[:, 2])
        return torch.stack([d10, d10 + gap1, d10 + gap1 + gap2], dim=1)


def _softplus_inv(y: float) -> float:
    y = max(y, 1e-3)
    return y + math.log(-math.expm1(-y))


def input_size(arch: str, configured: dict | None = None) -> int:
    size = int((configured or {}).get(arch, default_input_size(arch)))
    problem = input_size_problem(arch, size)
    if problem:
        raise PsdError(problem)
    return size


def crop_size(arch: str, crop: int, size: int) -> int:
    """The training window (`train.crop`) of `arch` at input `size`: 0 = the whole image."""
    problem = crop_problem(arch, crop, size)
    if problem:
        raise PsdError(problem)
    return crop if 0 < crop < size else 0


def _weights_enum(arch: str):
    import torchvision

    try:
        return torchvision.models.get_model_weights(arch).DEFAULT
    except (ValueError, KeyError):
        return None


def load_imagenet_weights(arch: str) -> dict:
    """ImageNet weights from the local torch cache, or downloaded. Raises PsdError if neither."""
    w = _weights_enum(arch)
    if w is None:
        raise PsdError(f"torchvision has no ImageNet weights for {arch!r}")
    try:
        return w.get_state_dict(progress=False, check_hash=True)
    except Exception as e:
        raise PsdError(
            f"ImageNet weights for {arch} could not be had ({type(e).__name__}: {e}). Put "
            f"{w.url.rsplit('/', 1)[-1]} in the torch hub cache (torch.hub.get_dir()/checkpoints) "
            "or set train.pretrained: none"
        ) from None


def build_model(arch: str, stats: TargetStats, pretrained: str = "none",
                size: int | None = None) -> tuple[nn.Module, str]:
    """A torchvision model with the ordered regression head; returns (model, weights used).

    InceptionV3 keeps its auxiliary head (trained with its own loss term) when the input is
    large enough for it (≥ 299 px); below that the head is dropped (training logs a note).
    """
    import torchvision

    if arch not in torchvision.models.list_models(module=torchvision.models):
        raise PsdError(f"unknown architecture {arch!r}: not a torchvision classification model")
    kwargs = {"aux_logits": True, "init_weights": True} if arch == "inception_v3" else {}
    model = torchvision.models.get_model(arch, weights=None, **kwargs)
    used = "none (trained from scratch)"
    if pretrained in ("imagenet", "auto"):
        try:
            state = load_imagenet_weights(arch)
            model.load_state_dict(state)
            used = f"imagenet ({_weights_enum(arch)})"
        except PsdError as e:
            if pretrained == "imagenet":
                raise
            msg = f"train.pretrained: auto — no ImageNet weights for {arch}; training from scratch. ({e})"
            warnings.warn(msg, stacklevel=2)
            logger.warning(msg)
            used = "none (auto: ImageNet weights unavailable, trained from scratch)"
    elif pretrained != "none":
        raise PsdError(f"train.pretrained must be auto, imagenet or none, got {pretrained!r}")
    replace_head(model, arch, stats)
    if arch == "inception_v3" and size is not None and not inception_aux_fits(size):
        model.aux_logits = False
        model.AuxLogits = None
    return model, used


def replace_head(model: nn.Module, arch: str, stats: TargetStats) -> None:
    """Swap the last Linear layer of the classifier (and of InceptionV3's auxiliary classifier)
    for the ordered regression head; the layers before it (pooling, norms, dropout) stay."""
    for attr in ("fc", "classifier", "heads", "head"):
        if isinstance(getattr(model, attr, None), nn.Module):
            _swap_last_linear(model, attr, stats)
            break
    else:
        raise PsdError(f"don't know where the classifier of {arch} is")
    aux = getattr(model, "AuxLogits", None)
    if aux is not None:
        _swap_last_linear(aux, "fc", stats)


def _swap_last_linear(parent: nn.Module, attr: str, stats: TargetStats) -> None:
    module = getattr(parent, attr)
    if isinstance(module, nn.Linear):
        setattr(parent, attr, OrderedHead(module.in_features, stats))
        return
    names = [n for n, m in module.named_modules() if isinstance(m, nn.Linear)]
    if not names:
        raise PsdError(f"no Linear layer in {type(parent).__name__}.{attr} to replace")
    *path, last = names[-1].split(".")
    owner = module
    for p in path:
        owner = getattr(owner, p)
    setattr(owner, last, OrderedHead(getattr(owner, last).in_features, stats))


def main_output(out) -> torch.Tensor:
    """The main prediction of a model's output (InceptionV3 returns (logits, aux) in training)."""
    return out.logits if hasattr(out, "logits") else out


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for n, p in model.named_parameters() if "AuxLogits" not in n)
