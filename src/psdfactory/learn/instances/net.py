"""The instance network: a ResNet-18 trunk cut at stride 8 (or, with `train.instances.trunk_stages: 3`, at
stride 16) and a light U-Net decoder predicting the maps of `targets.MAPS` at the input's resolution, any size."""

from __future__ import annotations

import logging

import torch
from torch import nn
from torch.nn import functional as F

from ... import PsdError
from . import ARCH
from .targets import MAPS, MASK_MAPS

logger = logging.getLogger(__name__)
TRUNK = "resnet18"
TRUNK_STAGES = 2  # the ResNet-18 stages after the stem the trunk keeps: layer1, layer2 (stride 8)
STAGE_CHANNELS = (64, 128, 256)  # of layer1, layer2, layer3
DECODER = (64, 32, 16)  # channels of the decoder stages at strides 4, 2, 1
FULL_RES = 8  # channels of the full-resolution skip
# How far (px) an output pixel's maps see, per trunk: 70 px at most on any side with two stages (measured by the
# gradient of one output pixel for every position modulo the trunk's stride: the stem's 7x7/2 conv and 3x3/2 pool,
# layer1's four 3x3 convs at stride 4, layer2's four at stride 8, then the decoder's bilinear upsampling and 3x3
# convs at strides 4, 2 and 1); 150 px with layer3's four at stride 16 and a decoder stage at stride 8. Nothing
# farther changes them: tests/test_photos.py measures it again.
RECEPTIVE_RADIUS_PX = {2: 70, 3: 150}
# The grid (px) every trunk's strides divide: an input padded at its bottom and right to a multiple of it is sampled
# at the same pixels of the image whichever way it is turned or mirrored; tiles that start on it see what one pass sees.
GRID_PX = 32


def decoder_for(stages: int) -> tuple[int, ...]:
    """The decoder's channels for a trunk of `stages` stages: DECODER, led by a stage at stride 8 with layer2's
    channels when the trunk goes on to layer3."""
    if stages not in RECEPTIVE_RADIUS_PX:
        raise PsdError(f"the {ARCH} trunk keeps {' or '.join(map(str, RECEPTIVE_RADIUS_PX))} stages, not {stages!r}")
    return STAGE_CHANNELS[1:stages - 1] + DECODER


# ---------------------------------------------------------------------------------------------
# the network


def _cbr(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


class InstanceNet(nn.Module):
    """ResNet-18 trunk (stem, layer1, layer2: stride 8; with `stages` 3 layer3 too: stride 16) + U-Net decoder
    → N×C×H×W logits (the first `n_maps` of MAPS) at the input's size, for any H, W ≥ 1."""

    def __init__(self, trunk: nn.Module | None = None, decoder: tuple[int, ...] | None = None, full: int = FULL_RES,
                 n_maps: int = len(MAPS), stages: int = TRUNK_STAGES):
        super().__init__()
        decoder = decoder_for(stages) if decoder is None else tuple(decoder)
        if len(decoder) != stages + 1:
            raise PsdError(f"a {stages}-stage trunk needs {stages + 1} decoder stages, got {len(decoder)}")
        if trunk is None:
            import torchvision

            trunk = torchvision.models.resnet18(weights=None)
        self.stem = nn.Sequential(trunk.conv1, trunk.bn1, trunk.relu)  # stride 2, 64
        self.pool = trunk.maxpool
        self.layer1 = trunk.layer1  # stride 4, 64
        self.layer2 = trunk.layer2  # stride 8, 128
        self.layer3 = trunk.layer3 if stages >= 3 else None  # stride 16, 256
        self.full = _cbr(3, full)
        skips = (*STAGE_CHANNELS[1:stages - 1][::-1], 64, 64, full)  # layer2 (with layer3), layer1, stem, full
        ups, prev = [], STAGE_CHANNELS[stages - 1]
        for c, s in zip(decoder, skips, strict=True):
            ups.append(_cbr(prev + s, c))
            prev = c
        self.up = nn.ModuleList(ups)
        self.head = nn.Conv2d(prev, n_maps, 1)
        with torch.no_grad():  # start near the class balance: a dense bed is mostly foreground, rarely boundary
            self.head.bias.copy_(torch.tensor([1.0, -1.0, 0.0, 0.0][:n_maps]))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        f0 = self.full(x)
        f1 = self.stem(x)
        f2 = self.layer1(self.pool(f1))
        y = self.layer2(f2)
        skips = (f2, f1, f0)
        if self.layer3 is not None:
            skips = (y, *skips)
            y = self.layer3(y)
        for up, skip in zip(self.up, skips, strict=True):
            y = F.interpolate(y, size=skip.shape[-2:], mode="bilinear", align_corners=False)
            y = up(torch.cat([y, skip], dim=1))
        return self.head(y)


class InstanceMaps(nn.Module):
    """The network with its logits turned into maps in [0, 1] (what inference and ONNX use)."""

    def __init__(self, net: nn.Module):
        super().__init__()
        self.net = net

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(self.net(images).float())


def build_instance_net(pretrained: str = "none", stages: int = TRUNK_STAGES) -> tuple[InstanceNet, str]:
    """The instance network; its trunk with ImageNet weights as `train.pretrained` says (auto:
    when they can be had, else from scratch with a warning). Returns (net, weights used)."""
    import warnings

    import torchvision

    from ..models import load_imagenet_weights

    trunk = torchvision.models.resnet18(weights=None)
    used = "none (trained from scratch)"
    if pretrained in ("imagenet", "auto"):
        try:
            trunk.load_state_dict(load_imagenet_weights(TRUNK))
            used = f"imagenet ({TRUNK} trunk)"
        except PsdError as e:
            if pretrained == "imagenet":
                raise
            msg = (f"train.pretrained: auto — no ImageNet weights for the {TRUNK} trunk of {ARCH}; "
                   f"training from scratch. ({e})")
            warnings.warn(msg, stacklevel=2)
            logger.warning(msg)
            used = "none (auto: ImageNet weights unavailable, trained from scratch)"
    elif pretrained != "none":
        raise PsdError(f"train.pretrained must be auto, imagenet or none, got {pretrained!r}")
    return InstanceNet(trunk, n_maps=len(MAPS), stages=stages), used



# ---------------------------------------------------------------------------------------------
# model files


def net_from_meta(meta: dict) -> InstanceNet:
    """An untrained InstanceNet of the shape a model file's meta describes."""
    if meta.get("trunk", TRUNK) != TRUNK:
        raise PsdError(f"unknown trunk {meta.get('trunk')!r} for {ARCH}")
    stages = int(meta.get("trunk_stages", TRUNK_STAGES))
    return InstanceNet(decoder=tuple(meta.get("decoder", decoder_for(stages))),
                       full=int(meta.get("full_res_channels", FULL_RES)), n_maps=len(meta.get("maps", MASK_MAPS)),
                       stages=stages)

