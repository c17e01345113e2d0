"""The pack format: a dataset's scenes as WebDataset tar shards for training (written by
``psdfactory pack``, `learn.shards`), shared by the packer and its readers. Light to import (the
command line builds its options from it).

A pack is a folder:

- ``<split>-NNNNNN.tar``: WebDataset shards of at most ``shard_scenes`` scenes, within one scene of
  each other in size, the scenes of every packed dataset mixed in a seeded order (`pack_order`:
  manifest shard by manifest shard, and the scenes of each in an order of their own). A
  scene is the files ``<scene_id>.jpg`` (or ``.png``: the image at ``size`` x ``size`` px, the
  networks' input size), ``<scene_id>.json`` (its manifest row: the targets, the size definition and
  weighting, and ``packed_mm_per_px``, the scale at the packed size), and with masks
  ``<scene_id>.mask.png`` (the 16-bit instance mask at the packed size, nearest neighbour: mask id k
  is particle k - 1), ``<scene_id>.codes.png`` (the dense size task's code map, `learn.size_cells`)
  and ``<scene_id>.particles.npy`` (`manifest.PARTICLE_READ_COLUMNS` per particle, float64;
  the JSON's ``particle_columns`` names them).
- ``index.json``: what was packed and how, and per split its scene count, target statistics,
  median scale and render size, and its shards with their scene counts, bytes and SHA-256. Written
  last: the pack is complete when it is there (the whole folder is written beside the old one and
  swapped in at the end).
"""

from __future__ import annotations

import random
import re
from dataclasses import dataclass
from pathlib import Path

from . import PsdError
from .config import DESIGN_INPUT_SIZE

FORMAT = "psdfactory-shards"
FORMAT_VERSION = 1
INDEX = "index.json"
IMAGE_FORMATS = ("jpg", "png")
SPLIT_NAME = re.compile(r"^[A-Za-z0-9_]+$")  # a split's shards are named after it
ORDER_STREAM = 0x5EED  # the packing order's random stream, beside the pack's seed


@dataclass(frozen=True)
class PackSpec:
    """How a pack is written (recorded in its index)."""

    size: int = DESIGN_INPUT_SIZE  # images (and masks) resized to size x size px
    image_format: str = "jpg"  # jpg | png (lossless)
    quality: int = 95  # JPEG quality
    masks: bool = True  # also the instance masks, size codes and particle tables (the dense size task)
    shard_scenes: int = 10_000  # scenes per shard at most
    seed: int = 0  # the order scenes are mixed in

    def problems(self) -> list[str]:
        out = []
        if not 32 <= self.size <= 4096:
            out.append(f"--size {self.size}: give the networks' input size in px, 32 to 4096")
        if self.image_format not in IMAGE_FORMATS:
            out.append(f"--format {self.image_format!r}: one of {', '.join(IMAGE_FORMATS)}")
        if not 1 <= self.quality <= 100:
            out.append(f"--quality {self.quality}: JPEG quality, 1 to 100")
        if self.shard_scenes < 1:
            out.append(f"--shard-scenes {self.shard_scenes}: at least 1")
        return out


def shard_name(split: str, k: int) -> str:
    return f"{split}-{k:06d}.tar"


def shard_sizes(n: int, most: int) -> list[int]:
    """Scenes per shard for `n` scenes, at most `most` a shard: as few shards as that allows, their
    sizes within one of each other (a small last shard would make every rank's loader worker that
    reads it stop early: `shard_plan`)."""
    k = -(-n // most)
    return [n // k + (i < n % k) for i in range(k)] if n else []


def pack_order(n_blocks: int, seed: int) -> list[int]:
    """The order a split's manifest shards (blocks) are packed in: a seeded permutation, so that a
    pack shard holds blocks of every packed dataset and of the whole dataset. The packer reads one
    block at a time (a million scenes' rows and particle tables do not fit in memory at once)."""
    import numpy as np

    return np.random.default_rng([int(seed), ORDER_STREAM]).permutation(n_blocks).tolist()


def block_rows_order(n_rows: int, seed: int, block: int) -> list[int]:
    """The order the scenes of one block (`block`: its place among all the packed blocks) are packed in."""
    import numpy as np

    return np.random.default_rng([int(seed), ORDER_STREAM, int(block)]).permutation(n_rows).tolist()


def read_index(path: Path) -> dict:
    """A pack's index.json (`path`: the file or the pack's folder), checked."""
    from .io import read_json

    path = Path(path)
    if path.is_dir():
        path = path / INDEX
    if not path.is_file():
        raise PsdError(f"no pack at {path.parent}: {INDEX} is missing (an interrupted pack leaves none; run "
                       "psdfactory pack again)")
    index = read_json(path)
    if not isinstance(index, dict) or index.get("format") != FORMAT:
        raise PsdError(f"{path} is not the index of a psdfactory pack")
    if index.get("version") != FORMAT_VERSION:
        raise PsdError(f"{path}: pack format version {index.get('version')}, this psdfactory reads {FORMAT_VERSION}; "
                       "pack the dataset again")
    return index


def sha256_of(path: Path) -> str:
    """A shard's SHA-256 (hex), read in chunks: what the index records and `verify` checks."""
    import hashlib

    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def verify(pack_dir: Path) -> tuple[int, list[str]]:
    """Every shard of a pack checked against its index (size and SHA-256): (shards checked, what is
    wrong, a line per damaged or missing shard). For a pack copied to another filesystem."""
    pack_dir = Path(pack_dir)
    index = read_index(pack_dir)
    problems, n = [], 0
    for split, part in index["splits"].items():
        for shard in part["shards"]:
            n += 1
            path = pack_dir / shard["name"]
            if not path.is_file():
                problems.append(f"{path}: missing ({split}, {shard['scenes']} scenes)")
                continue
            if sha256_of(path) != shard["sha256"]:
                problems.append(f"{path}: {path.stat().st_size} bytes whose SHA-256 is not the index's "
                                f"({shard['bytes']} bytes): damaged or incomplete")
    return n, problems


def epoch_order(shards: list[dict], seed: int, epoch: int) -> list[dict]:
    """An epoch's order of a split's shards: the same on every rank and worker (drawn from the
    seed and the epoch alone), another each epoch."""
    order = list(shards)
    random.Random(f"{int(seed)}:{int(epoch)}").shuffle(order)
    return order


def shard_plan(counts: list[int], rank: int, world: int, worker: int, workers: int) -> tuple[list[int], int]:
    """Which of an epoch's shards (their scene `counts`, in the epoch's order) one loader worker of
    one rank reads, and how many of their scenes it yields.

    One rank (`world` 1): all of its shards' scenes. Several: as many shards as any rank's same
    worker is dealt at least, times the smallest shard's count, so that every rank yields the same
    number of samples (DDP's ranks step in lockstep), none twice, and the same number every epoch
    whatever the order (a one-cycle schedule counts its steps in advance). What that leaves out of
    an epoch: up to one scene a shard (the packer's shards are within one scene of each other in
    size) and, where the shards are not a multiple of ranks x workers, the shards beyond the last
    full round (`left_out`)."""
    positions = list(range(len(counts)))
    mine = positions[rank::world][worker::workers]
    if world == 1:
        return mine, sum(counts[i] for i in mine)
    least = min(len(positions[r::world][worker::workers]) for r in range(world))
    return mine, least * min(counts, default=0)


def left_out(counts: list[int], world: int, workers: int) -> int:
    """Scenes of a split that no rank reads in an epoch (`shard_plan`), at most."""
    taken = sum(shard_plan(counts, r, world, w, workers)[1] for r in range(world) for w in range(workers))
    return sum(counts) - taken
