"""Deterministic random streams.

Every random draw of a scene comes from (global seed, dataset name, scene index, stream),
so adding scenes never changes existing ones and each use (a stage, the particle shapes, the
split) has its own stream. (The stage runners are ``scene.stages.STAGES``.)
"""

from __future__ import annotations

import hashlib

import numpy as np

# The random streams of a scene, independent of each other. The numbers are part of every seed:
# changing one changes every scene. "look" holds the render settings added after the first
# ones (scale, table/particle texture, light colour, JPEG), drawn apart so that the "render"
# stream's draws (light, colours, texture noise, sensor noise) stay what they were.
STREAMS = {"sample": 1, "shape": 2, "simulate": 3, "render": 4, "split": 5, "look": 6, "distractors": 7, "markings": 8,
           "shape_library": 9}  # a dataset's (seed, dataset, 9): the shapes its scenes draw from


def name_key(name: str) -> int:
    """A stable 32-bit integer for a string (Python's hash() is salted per process)."""
    return int.from_bytes(hashlib.sha256(name.encode()).digest()[:4], "little")


def scene_entropy(seed: int, dataset: str, index: int) -> list[int]:
    return [int(seed), name_key(dataset), int(index)]


def rng_for(entropy: list[int], stream: str, attempt: int = 0) -> np.random.Generator:
    """The generator of one stream of one scene (attempt > 0 for retries)."""
    return np.random.default_rng([*entropy, STREAMS[stream], int(attempt)])


def scene_id(dataset: str, index: int) -> str:
    return f"{dataset}-{index:06d}"


def scene_index(scene: str) -> int:
    try:
        return int(scene.rsplit("-", 1)[1])
    except (IndexError, ValueError):
        raise ValueError(f"not a scene id: {scene!r} (expected '<dataset>-<6-digit index>')") from None


SPLIT_ORDER = ("train", "val", "test")


def assign_split(entropy: list[int], fractions: dict[str, float]) -> str:
    """A scene's split from its own random stream: stable when scenes are added, and known
    before the scene exists (a re-render dataset picks its source's test scenes by it)."""
    from . import PsdError

    names = [s for s in SPLIT_ORDER if s in fractions] + sorted(s for s in fractions if s not in SPLIT_ORDER)
    total = sum(fractions[s] for s in names)
    if total <= 0:
        raise PsdError("split fractions must add up to more than 0")
    u = rng_for(entropy, "split").random() * total
    acc = 0.0
    for s in names:
        acc += fractions[s]
        if u < acc:
            return s
    return names[-1]
