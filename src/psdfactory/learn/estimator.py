"""One interface for every estimator: what training, evaluation, prediction, export and the
benchmark call, so that none of them asks which kind of model it holds.

An estimator is a network (`net`, a torch module, or an ONNX Runtime session behind `run`) and
what turns its outputs into d10/d50/d90 (`read`). Two are built in — `learn.cnn.CnnRegressor`
(the paper's regressors: the network's output *is* the PSD) and
`learn.instances.estimator.InstanceEstimator` (maps → grains → PSD) — and more plug in through the
``psdfactory.estimators`` entry-point group: a package that declares
``[project.entry-points."psdfactory.estimators"] myarch = "mypkg.module:MyEstimator"`` trains,
evaluates, predicts, exports and benchmarks as ``train.architectures: [myarch]`` without a line
changed here.

What a subclass gives:

- `train(params, results_root, out_dir, settings)` (classmethod): train on a dataset's
  train/val splits, write ``model.pt`` (`learn.runtime.save_model`: its meta names the
  architecture) and return the summary meta; `learn.fit.fit` is the loop to use;
- `build_net(meta)` (classmethod): an untrained network of the shape a meta describes;
- `read(outputs, mm_per_px)`: the network's outputs for a batch → one `Reading` per image.

What it may override: `meta_problems` (its meta's own keys), `inference_module` (the module
exported and timed: normalised images in, the outputs `read` takes out), `outputs` (e.g. test-time
augmentation), `definitions` / `weightings` / `in_definition` (size definitions and weightings it
can read beyond its own), `scorer` (evaluation beyond the d-values: segmentation, size errors),
and the class attributes `any_size`, `finds_grains`, `tile_margin_px` (which a model may set for itself, from
its meta), `torchscript`, `int8`, `output_doc`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np
import torch
from torch import nn

from .. import PsdError
from ..psd import GRAIN_WEIGHTINGS, SIZE_DEFINITIONS, TARGETS, WEIGHTINGS, check_grain_weighting

logger = logging.getLogger(__name__)
LEGACY_DEFINITION = "b-axis"  # a model trained before sizes had names learnt the drawn size, the b-axis


@dataclass
class Reading:
    """What an estimator read off one image: d10/d50/d90 in mm in the model's own size definition
    and weighting, and whatever else it found (`grains`: an estimator that finds grains gives its
    per-image result here; predict writes its masks, overlays and particle rows from it)."""

    d_mm: np.ndarray
    grains: object | None = None
    extra: dict = field(default_factory=dict)


class DatasetScorer:
    """Evaluation beyond the d-values, one dataset at a time: `add` per scene, then `metrics`
    (merged into the dataset's metrics) — the base adds nothing. `columns` gives a scene's extra
    columns in predictions.csv."""

    def add(self, row: dict, reading: Reading) -> dict:
        return {}

    def metrics(self) -> dict:
        return {}

    def summary(self, metrics: dict) -> str:
        return ""


# the meta keys of how large a grain finder's validation grains look (px at the model's scale): their median, their
# largest, and their largest as seen at config.AUTO_SCALE_PROBE of the scale (instances.training.grain_sizes);
# predict --auto-scale reads a photo at a coarser scale only with all three (deploy.predict.choose_scale)
GRAIN_SIZE_KEYS = ("grain_px", "grain_px_max", "grain_px_probe_max")
GRAIN_PROBE_KEY = "grain_px_probe_scale"  # the factor grain_px_probe_max was seen at (absent: LEGACY_AUTO_SCALE_PROBE)


def default_auto_scale(meta: dict) -> bool:
    """Whether predict reads photos with this model at the grains' scale unless told otherwise: its recipe's
    choice (`train.instances.auto_scale`, the meta's ``auto_scale``); False for a model without one."""
    return bool(meta.get("auto_scale", False))


class Estimator:
    """A trained model that reads d10/d50/d90 (mm) off images; see the module docstring."""

    any_size: ClassVar[bool] = False  # the network takes images of any H×W at its scale (else square)
    finds_grains: ClassVar[bool] = False  # predict can write masks, overlays and particle rows
    # `outputs` are per-pixel maps at the input's size, each pixel's depending on the input within this many
    # px only (its receptive field), and `read` takes maps of any size: predict may cut an image too large for
    # one pass into tiles that overlap by this margin, stitch their maps and read them once. None: never tiled.
    # A class's value, or a model's own where its network's receptive field depends on its meta
    tile_margin_px: int | None = None
    torchscript: ClassVar[bool] = True  # export writes a TorchScript copy
    int8: ClassVar[bool] = True  # export and the benchmark may quantise it to int8
    output_doc: ClassVar[str] = "float32 Nx3: d10, d50, d90 in mm"
    output_name: ClassVar[str] = "d_mm"  # the ONNX output's name
    def __init__(self, meta: dict, run: Callable[[torch.Tensor], np.ndarray], net: nn.Module | None = None):
        self.meta = meta
        self.run = run  # normalised float N×3×H×W → the network's outputs (numpy)
        self.net = net
        # True (predict --auto-scale): predict reads a photo whose grains look larger than the validation grains
        # (apparent_grain_px) at a coarser scale; False: always at the model's scale. The model's own default is
        # its recipe's (train.instances.auto_scale, in its meta); predict's --auto-scale/--no-auto-scale override it
        self.auto_scale: bool = default_auto_scale(meta)

    # ---- what a subclass gives ---------------------------------------------------------------

    @classmethod
    def train(cls, params, results_root: Path, out_dir: Path, settings: dict | None = None) -> dict:
        """Train on `params.datasets` of `results_root` into `out_dir`; the model's meta. An
        estimator that can also read a pack (`psdfactory pack`) takes ``pack`` and
        ``loader_workers`` keywords too (the CNNs do)."""
        raise NotImplementedError

    @classmethod
    def build_net(cls, meta: dict) -> nn.Module:
        raise NotImplementedError

    def read(self, outputs: np.ndarray, mm_per_px: list[float]) -> list[Reading]:
        raise NotImplementedError

    # ---- what a subclass may override --------------------------------------------------------

    @classmethod
    def meta_problems(cls, meta: dict) -> list[str]:
        """What is wrong with this estimator's own keys of a meta (the common ones are checked
        by `learn.runtime.meta_problems`); empty when fine."""
        return []

    @classmethod
    def needs_target_stats(cls) -> bool:
        return True

    def inference_module(self) -> nn.Module:
        """The torch module that maps normalised images to the outputs `read` takes."""
        if self.net is None:
            raise PsdError("this model was loaded without its PyTorch network (an ONNX file)")
        return self.net

    def outputs(self, images_u8: torch.Tensor) -> np.ndarray:
        """The network's outputs for uint8 N×3×H×W images."""
        from .data import normalise

        return np.asarray(self.run(normalise(images_u8)))

    @classmethod
    def definitions(cls, meta: dict) -> tuple[str, ...]:
        """The size definitions a model of this meta can give d-values in (its own first)."""
        return (model_definition(meta),)

    @classmethod
    def weightings(cls, meta: dict, definition: str) -> tuple[str, ...]:
        """What d-values of `definition` (one of `definitions`) can count, of `psd.GRAIN_WEIGHTINGS`
        (its training labels' weighting first): by default only that one."""
        return (meta.get("weighting", "number"),)

    @classmethod
    def reads(cls, meta: dict, definition: str, weighting: str) -> bool:
        """Whether a model of this meta gives d-values of `definition`, weighted by `weighting`."""
        return definition in cls.definitions(meta) and weighting in cls.weightings(meta, definition)

    def in_definition(self, reading: Reading, definition: str, weighting: str, where: str) -> np.ndarray:
        """d10/d50/d90 of `reading` in `definition` (one of `definitions()`), `weighting` (one of
        `weightings(definition)`)."""
        return reading.d_mm

    def scorer(self, results_root: Path, dataset: str) -> DatasetScorer:
        return DatasetScorer()

    def apparent_grain_px(self, outputs: np.ndarray) -> float | None:
        """How large, in px, the grains look in one image's `outputs` (its area-weighted median
        size), or None where the estimator cannot say (it finds no grain, or it is not one that
        sizes grains). With the meta's `grain_px` and `grain_px_max` (the median and the largest of
        the same figure on its validation images), predict reads a photo whose grains look larger
        than the largest at the coarser scale where they look the median's size."""
        return None

    # ---- shared ------------------------------------------------------------------------------

    @property
    def arch(self) -> str:
        return self.meta["arch"]

    def predict(self, images_u8: torch.Tensor, mm_per_px: float | list[float]) -> list[Reading]:
        """uint8 N×3×H×W images at the network's scale → one reading per image (mm per pixel:
        one for all, or one each)."""
        scales = list(mm_per_px) if isinstance(mm_per_px, (list, tuple)) else [float(mm_per_px)] * len(images_u8)
        return self.read(self.outputs(images_u8), scales)

    def with_runner(self, run: Callable[[torch.Tensor], np.ndarray]) -> Estimator:
        """The same estimator with another way to run its network (a faster path, ONNX Runtime)."""
        return type(self)(self.meta, run, self.net)


def model_definition(meta: dict) -> str:
    """The size definition a model's training labels were of."""
    return meta.get("size_definition", LEGACY_DEFINITION)


def reading_of(est_cls: type[Estimator], meta: dict, requested: str | None, weighting: str | None = None) -> dict:
    """What a model's d-values will be of: {"size_definition", "weighting"} — its own definition
    and weighting, or those asked for when its estimator can read them (`Estimator.definitions`,
    `Estimator.weightings`); anything else is refused in one line naming what it can read. A
    calibrated model gives the d-values its calibration was fitted to by default (`psdfactory
    calibrate`: `learn.calibration.source_reading` says which reading they are corrected from)."""
    block = meta.get("calibration")
    if isinstance(block, dict) and requested in (None, block.get("size_definition")) and (
            weighting in (None, block.get("weighting"))):
        return {"size_definition": block["size_definition"], "weighting": block["weighting"]}
    definitions = est_cls.definitions(meta)
    own, own_weighting = model_definition(meta), meta.get("weighting", "number")
    definition = requested or own
    if definition not in SIZE_DEFINITIONS:
        raise PsdError(f"--size-definition {definition!r}: not a size definition; one of {', '.join(SIZE_DEFINITIONS)}")
    if definition not in definitions:
        raise PsdError(f"--size-definition {definition}: this {meta.get('arch')} model reads "
                       f"{', '.join(d for d in SIZE_DEFINITIONS if d in definitions)} (trained on {own} labels); train "
                       f"one with labels.size_definition: {definition} to read {definition}")
    if weighting is not None:
        check_grain_weighting(weighting)
    allowed = est_cls.weightings(meta, definition)
    weighting = weighting or (own_weighting if own_weighting in allowed else allowed[0])
    if weighting not in allowed:
        can = {}  # weightings → the definitions read in them
        for d in (d for d in SIZE_DEFINITIONS if d in definitions):
            can.setdefault(tuple(w for w in GRAIN_WEIGHTINGS if w in est_cls.weightings(meta, d)), []).append(d)
        said = "; ".join(f"{', '.join(ds)} {'-, '.join(ws)}-weighted" for ws, ds in can.items())
        given = [d for ws, ds in can.items() if weighting in ws for d in ds]
        if given:
            how = f"ask for it with --size-definition {' or '.join(given)}"
        elif weighting in WEIGHTINGS:
            how = f"train one with labels.weighting: {weighting}"
        else:
            how = "a model that finds grains (arch 'instances') measures it with --size-definition feret-min"
        raise PsdError(f"--weighting {weighting} of {definition}: this {meta.get('arch')} model reads {said} "
                       f"(trained on {own_weighting}-weighted {own} labels); {how}")
    return {"size_definition": definition, "weighting": weighting}


def rows_readings(est: Estimator, results_root: Path, rows: list[dict], batch: int = 8):
    """(readings, true targets N×3) of manifest rows, `batch` images at a time at the model's input."""
    from .data import SceneImages

    ds = SceneImages(results_root, rows, est.meta["input_size"], cache=False)
    readings = []
    for i in range(0, len(ds), batch):
        x = torch.stack([ds[j][0] for j in range(i, min(i + batch, len(ds)))])
        readings += est.predict(x, [network_scale(r, x.shape[-1]) for r in rows[i : i + batch]])
    return readings, ds.y.numpy()


def network_scale(row: dict, size: int) -> float:
    """mm per pixel of a manifest row's image at the network's input size."""
    return float(row["mm_per_px"]) * int(row["resolution"]) / size


def predictions(readings: list[Reading]) -> np.ndarray:
    return np.stack([r.d_mm for r in readings]) if readings else np.zeros((0, len(TARGETS)))
