"""Which estimator trains and runs each `train.architectures` name, torch-free until one is
used: the instance estimator (``instances``), estimators that installed packages declare in the
``psdfactory.estimators`` entry-point group, and every torchvision classification model as a
CNN regressor (`learn.cnn.CnnRegressor`). See `learn.estimator` for the interface.
"""

from __future__ import annotations

import importlib
import logging
from collections.abc import Callable

from .. import PsdError

logger = logging.getLogger(__name__)
ENTRY_POINTS = "psdfactory.estimators"
BUILTIN = {"instances": "psdfactory.learn.instances.estimator:InstanceEstimator"}
CNN = "psdfactory.learn.cnn:CnnRegressor"


def plugins() -> dict[str, object]:
    """name → entry point of the installed estimator plug-ins (not loaded)."""
    from importlib.metadata import entry_points

    return {ep.name: ep for ep in entry_points(group=ENTRY_POINTS)}


def torchvision_names() -> set[str]:
    """torchvision's classification models (imported only here: the scene jobs never pay for it)."""
    import torchvision

    return set(torchvision.models.list_models(module=torchvision.models))


def _load(arch: str, target: str):
    from .estimator import Estimator

    module, _, name = target.partition(":")
    try:
        cls = getattr(importlib.import_module(module), name)
    except Exception as e:  # a broken plug-in names itself
        raise PsdError(f"estimator {arch!r} ({target}) could not be loaded: {type(e).__name__}: {e}") from None
    if not (isinstance(cls, type) and issubclass(cls, Estimator)):
        raise PsdError(f"estimator {arch!r} ({target}) is not a psdfactory.learn.estimator.Estimator")
    return cls


def estimator_class(arch: str):
    """The Estimator subclass that trains and runs `arch`."""
    if arch in BUILTIN:
        return _load(arch, BUILTIN[arch])
    found = plugins()
    if arch in found:
        return _load(arch, found[arch].value)
    if arch in torchvision_names():
        return _load(arch, CNN)
    raise PsdError(f"unknown architecture {arch!r}: not {', '.join(BUILTIN)}, not an installed estimator plug-in "
                   f"({', '.join(found) or 'none installed'}), not a torchvision classification model")


def check_architectures(archs: list[str], known: Callable[[], set[str]] | None = None) -> None:
    """Every `train.architectures` entry is an estimator this install can train: a built-in or
    plug-in estimator, or a torchvision classification model. `known()` → the torchvision names
    (by default torchvision's own registry; asked only when some name is none of the others)."""
    others = [a for a in archs if a not in BUILTIN and a not in plugins()]
    if not others:
        return
    if known is None:
        def known() -> set[str]:
            try:
                return torchvision_names()
            except ImportError:
                return set(others)  # a scenes-only install: the training jobs will say what is missing
    names = known()
    bad = [a for a in others if a not in names]
    if bad:
        close = {b: sorted(n for n in names if n.startswith(b[:4]))[:4] for b in bad}
        hint = "; ".join(f"{b}: e.g. {', '.join(c)}" for b, c in close.items() if c)
        extra = ", ".join([*BUILTIN, *plugins()])
        raise PsdError(f"train.architectures: {', '.join(map(repr, bad))} not an estimator psdfactory can train "
                       f"({extra}, or a torchvision classification model{'; ' + hint if hint else ''})")
