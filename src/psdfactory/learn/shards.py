"""Training data as WebDataset tar shards (the format: `psdfactory.packs`): the packer from a
results root's manifests, and the dataset that reads the shards back (each rank and loader worker
its own shards, reshuffled each epoch).

Any WebDataset reader takes the shards (``webdataset.WebDataset("train-{000000..000009}.tar")``);
`ShardScenes` is the one training needs: exactly as many samples on every rank of a DDP job
(`torch.distributed` or the ``RANK``/``WORLD_SIZE`` variables ``torchrun`` sets), no sample twice in
an epoch, another shard order and shuffle each epoch (`set_epoch`), and shards read from a local
folder or any URL WebDataset opens (``pipe:aws s3 cp s3://bucket/pack/{name} -``).
"""

from __future__ import annotations

import io
import json
import logging
import random
from dataclasses import asdict, dataclass
from itertools import islice
from pathlib import Path

import numpy as np
import torch

from .. import PsdError, __version__
from ..io import atomic_dir, is_within, read_parquet, read_png, write_json
from ..manifest import PARTICLE_READ_COLUMNS
from ..packs import (
    FORMAT,
    FORMAT_VERSION,
    INDEX,
    SPLIT_NAME,
    PackSpec,
    block_rows_order,
    epoch_order,
    left_out,
    pack_order,
    read_index,
    sha256_of,
    shard_name,
    shard_plan,
    shard_sizes,
)
from ..psd import TARGETS
from ..seeding import SPLIT_ORDER
from .data import label_definition, split_summary, to_input

logger = logging.getLogger(__name__)

FIELDS = ("image", "targets", "mask", "codes", "particles", "meta")  # what ShardScenes can yield per scene


def _encode_image(array: np.ndarray, fmt: str, quality: int) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    if fmt == "jpg":
        Image.fromarray(array).save(buf, format="JPEG", quality=quality)
    else:
        Image.fromarray(array).save(buf, format="PNG", compress_level=6)
    return buf.getvalue()


def _png(array: np.ndarray) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(array).save(buf, format="PNG")
    return buf.getvalue()


def scene_sample(results_root: Path, row: dict, particles: dict | None, spec: PackSpec) -> dict:
    """One scene as a WebDataset sample: {"__key__": scene id, extension: bytes}."""
    from .instances.draw import resize_mask
    from .size_cells import scene_codes

    image = to_input(read_png(results_root / row["image_path"]), spec.size).permute(1, 2, 0).numpy()
    meta = {k: v for k, v in row.items() if not k.endswith("_path")}
    meta["packed_size"] = spec.size
    meta["packed_mm_per_px"] = float(row["mm_per_px"]) * float(row["resolution"]) / spec.size
    sample = {"__key__": row["scene_id"], spec.image_format: _encode_image(image, spec.image_format, spec.quality)}
    if spec.masks:
        if particles is None:
            raise PsdError(f"the particle manifest has no rows for {row['scene_id']}; rerun its manifest job")
        mask = read_png(results_root / row["mask_path"])
        sample["mask.png"] = _png(resize_mask(mask, (spec.size, spec.size)).astype(np.uint16))
        # the dense size task's targets, made as training makes them from the full-size mask
        sample["codes.png"] = _png(scene_codes(mask, particles, float(row["mm_per_px"]), spec.size).numpy())
        table = np.stack([np.asarray(particles[c], dtype=np.float64) for c in PARTICLE_READ_COLUMNS], axis=1)
        buf = io.BytesIO()
        np.save(buf, table, allow_pickle=False)
        sample["particles.npy"] = buf.getvalue()
        meta["particle_columns"] = list(PARTICLE_READ_COLUMNS)
    sample["json"] = json.dumps(meta, default=float).encode()
    return sample


def _sample_job(args: tuple) -> dict:
    results_root, row, particles, spec = args
    return scene_sample(results_root, row, particles, spec)


@dataclass(frozen=True)
class Block:
    """One manifest shard of a packed dataset: the packer's unit of reading."""

    dataset: str
    scenes: Path  # <results>/<dataset>/manifest/scenes/shard-NNNNN.parquet
    particles: Path  # its particle shard (same name under particles/)


LIGHT_COLUMNS = ("scene_id", "split", "mm_per_px", "resolution", "size_definition", "weighting", *TARGETS)


def manifest_blocks(results_root: Path, datasets: list[str] | tuple[str, ...]) -> list[Block]:
    blocks = []
    for ds in datasets:
        folder = results_root / ds / "manifest" / "scenes"
        files = sorted(folder.glob("*.parquet"))
        if not files:
            raise PsdError(f"no manifest at {folder}; run the workflow first (snakemake -j2)")
        blocks += [Block(ds, f, results_root / ds / "manifest" / "particles" / f.name) for f in files]
    return blocks


def _block_scenes(results_root: Path, blocks: list[Block], order: list[int], split: str, spec: PackSpec):
    """The work items of one split's scenes, block by block in `order`, each block's scenes in an
    order of their own; one block's rows and particles in memory at a time."""
    import pyarrow.parquet as pq

    from ..manifest import group_by_scene

    for k in order:
        b = blocks[k]
        table = read_parquet(b.scenes)
        rows = [r for r in table.to_pylist() if r["split"] == split]
        if not rows:
            continue
        particles = {}
        if spec.masks:
            if not b.particles.is_file():
                raise PsdError(f"missing {b.particles} (the particles of {b.scenes}); rerun the workflow's manifest "
                               "jobs")
            particles = group_by_scene(pq.read_table(b.particles, columns=["scene_id", *PARTICLE_READ_COLUMNS]),
                                       PARTICLE_READ_COLUMNS)
        for i in block_rows_order(len(rows), spec.seed, k):
            yield results_root, rows[i], particles.get(rows[i]["scene_id"]) if spec.masks else None, spec


def _write_split(work, n: int, split: str, out: Path, spec: PackSpec, pool, jobs: int, bar) -> list[dict]:
    """The split's `n` scenes (`work`: their work items, in packing order) as shards in `out`,
    encoded in `pool` (`jobs` processes) or, without one, here; per shard its name, scene count,
    bytes and SHA-256."""
    import webdataset as wds

    shards = []
    samples = ordered_map(_sample_job, work, pool, jobs) if pool is not None else map(_sample_job, work)
    try:
        for k, m in enumerate(shard_sizes(n, spec.shard_scenes)):
            name = shard_name(split, k)
            with open(out / name, "wb") as f, wds.TarWriter(f, mtime=0.0, mode=0o644) as tar:
                for sample in islice(samples, m):
                    tar.write(sample)
                    bar.update(1)
            shards.append({"name": name, "scenes": m, "bytes": (out / name).stat().st_size,
                           "sha256": sha256_of(out / name)})
    finally:
        if hasattr(samples, "close"):
            samples.close()  # stops the worker processes of an interrupted split
    return shards


def _one_thread() -> None:
    torch.set_num_threads(1)  # a pack worker is one of --jobs processes: one core each


def ordered_map(fn, items, ex, jobs: int, ahead: int = 4):
    """fn over `items` in the process pool `ex` of `jobs` processes, results in the items' order,
    with at most `ahead` x `jobs` items handed out and not yet taken back (multiprocessing.Pool.imap
    would read the whole input at once: a million scenes' rows and particle tables). A process that
    dies is an error."""
    from collections import deque
    from concurrent.futures.process import BrokenProcessPool

    pending: deque = deque()
    try:
        for item in items:
            pending.append(ex.submit(fn, item))
            if len(pending) >= ahead * jobs:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()
    except BrokenProcessPool:
        raise PsdError(f"a worker process of --jobs {jobs} died (out of memory, or killed); rerun with fewer "
                       "--jobs") from None
    finally:
        for f in pending:
            f.cancel()


def pack(results_root: Path, datasets: list[str] | tuple[str, ...], out_dir: Path, spec: PackSpec,
         splits: tuple[str, ...] | None = None, jobs: int = 1) -> dict:
    """Pack the scenes of `splits` (default: every split of the manifests) of `datasets` (one
    results root's) into WebDataset shards in `out_dir`, replaced as a whole when every shard is
    written; returns the index. Reads the manifests one shard at a time."""
    import pyarrow as pa
    import pyarrow.parquet as pq
    from tqdm import tqdm

    if spec.problems():
        raise PsdError("; ".join(spec.problems()))
    results_root, out_dir = Path(results_root), Path(out_dir)
    for d in [results_root, *(results_root / d for d in datasets)]:
        inside = is_within(out_dir, d) and d != results_root  # a pack may sit in the results root
        if inside or is_within(d, out_dir):
            raise PsdError(f"--out {out_dir} overlaps {d}, which the pack reads (the pack replaces its whole "
                           "folder): write the pack to a folder of its own")
    if out_dir.is_dir() and any(out_dir.iterdir()) and not (out_dir / INDEX).is_file():
        raise PsdError(f"--out {out_dir} holds files and is not a pack (no {INDEX}): the pack replaces the whole "
                       "folder; give a new or empty folder, or an earlier pack")
    blocks = manifest_blocks(results_root, datasets)
    light = pa.concat_tables([pq.read_table(b.scenes, columns=list(LIGHT_COLUMNS)) for b in blocks])
    split_of = np.asarray(light.column("split").to_pylist())
    found = [s for s in SPLIT_ORDER if s in split_of] + sorted(set(split_of) - set(SPLIT_ORDER))
    names = [s for s in found if not splits or s in splits]
    bad = [s for s in names if not SPLIT_NAME.match(s)]
    if bad:
        raise PsdError(f"splits {bad}: a split's shards are named after it, so its name may hold letters, digits "
                       "and _ only; rename it in datasets.<name>.split")
    missing = [s for s in (splits or ()) if s not in found]
    if missing or not names:
        raise PsdError(f"{', '.join(datasets)}: no scenes in the split{'s' * (len(missing) > 1)} "
                       f"{', '.join(missing) or 'of the manifests'} to pack (the manifests have: "
                       f"{', '.join(found) or 'none'})")
    chosen = light.filter(pa.array(np.isin(split_of, names)))
    kinds = zip(chosen.column("size_definition").to_pylist(), chosen.column("weighting").to_pylist(), strict=True)
    definition = label_definition([{"size_definition": d, "weighting": w} for d, w in set(kinds)])
    count = {s: int((split_of == s).sum()) for s in names}
    logger.info(f"packing {chosen.num_rows} scenes of {', '.join(datasets)} "
                f"({', '.join(f'{s} {count[s]}' for s in names)}) at {spec.size} px {spec.image_format} into shards of "
                f"{spec.shard_scenes} in {out_dir}")
    index = {"format": FORMAT, "version": FORMAT_VERSION, "psdfactory_version": __version__,
             "datasets": list(datasets), **definition, **asdict(spec), "splits": {}}
    order = pack_order(len(blocks), spec.seed)
    with atomic_dir(out_dir, "--out", ".pack") as stage, \
            tqdm(total=chosen.num_rows, desc="pack", unit="scene", mininterval=2.0,
                 disable=not logger.isEnabledFor(logging.INFO)) as bar:
        pool = None
        if jobs > 1:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            pool = ProcessPoolExecutor(jobs, mp_context=multiprocessing.get_context("spawn"), initializer=_one_thread)
        try:
            for s in names:
                shards = _write_split(_block_scenes(results_root, blocks, order, s, spec), count[s], s, stage, spec,
                                      pool, jobs, bar)
                mine = light.filter(pa.array(split_of == s))
                y = np.stack([np.asarray(mine.column(t).to_pylist(), float) for t in TARGETS], axis=1)
                index["splits"][s] = {**split_summary(y, np.asarray(mine.column("mm_per_px").to_pylist(), float),
                                                      np.asarray(mine.column("resolution").to_pylist())),
                                      "shards": shards}
        finally:
            if pool is not None:
                pool.shutdown(wait=True, cancel_futures=True)
        write_json(stage / INDEX, index)
    total = sum(sh["bytes"] for v in index["splits"].values() for sh in v["shards"])
    logger.info(f"wrote {out_dir}: {chosen.num_rows} scenes, {total / 1e6:.1f} MB "
                f"({total / chosen.num_rows / 1e3:.1f} kB a scene)")
    return index


class ShardScenes(torch.utils.data.IterableDataset):
    """One split of a pack, scene by scene: the `fields` of each (image: uint8 3 x size x size;
    targets: float32 d10/d50/d90 in mm; mask: int32 size x size; codes: the dense size task's uint8
    size x size code map, `size_cells`; particles: float64 n x 3; meta: the manifest row), as a
    tuple in that order.

    Each epoch the split's shards are put in an order drawn from (seed, epoch), dealt to the ranks
    and then to each rank's loader workers (`num_workers` must be the DataLoader's), and read
    through a shuffle buffer of `shuffle_buffer` scenes. `len()` is the samples one rank yields an
    epoch, the same on every rank. `url` turns a shard's name into what WebDataset opens (default:
    the file in the index's folder); `world` = (0, 1) reads the whole split on any rank (validation);
    `transform` maps each scene's fields to what is yielded."""

    def __init__(self, pack_dir: Path | str, split: str = "train", fields: tuple[str, ...] = ("image", "targets"),
                 shuffle_buffer: int = 1000, seed: int = 0, num_workers: int = 0, url: str | None = None,
                 world: tuple[int, int] | None = None, transform=None):
        super().__init__()
        self.dir = Path(pack_dir)
        self.index = read_index(self.dir)
        bad = [f for f in fields if f not in FIELDS]
        if bad or not fields:
            raise PsdError(f"fields {bad or '(none)'}: choose from {', '.join(FIELDS)}")
        if not self.index["masks"] and {"mask", "codes", "particles"} & set(fields):
            raise PsdError(f"{self.dir} was packed without masks (--no-masks): it has no masks, size codes or "
                           "particles")
        if split not in self.index["splits"]:
            has = ", ".join(self.index["splits"]) or "none"
            raise PsdError(f"{self.dir} holds no {split!r} scenes (it has: {has})")
        self.split, self.fields, self.seed = split, tuple(fields), int(seed)
        self.shards = self.index["splits"][split]["shards"]
        self.shuffle_buffer, self.num_workers, self.url = int(shuffle_buffer), int(num_workers), url
        self.world = world  # (rank, world size); default: what torch.distributed or RANK/WORLD_SIZE say
        self.transform = transform  # applied to each scene's fields (a module-level function: workers pickle it)
        self.epoch = 0
        rank, size = self._rank()
        workers = max(self.num_workers, 1)
        if len(self.shards) < size * workers:
            raise PsdError(f"{self.dir}: {len(self.shards)} {split} shards for {size} ranks x {workers} loader "
                           "workers; each needs a shard of its own: pack with a smaller --shard-scenes, or use fewer "
                           "workers")
        counts = [s["scenes"] for s in self.shards]
        lost = left_out(counts, size, workers)
        if rank == 0 and lost > 0.1 * sum(counts):
            logger.warning(f"{self.dir}: {lost} of the {sum(counts)} {split} scenes are left out of each epoch: "
                           f"{len(counts)} shards do not deal evenly to {size} ranks x {workers} loader workers "
                           f"(pack with --shard-scenes {max(1, sum(counts) // (size * workers))}, or another "
                           "number of workers)")

    def _rank(self) -> tuple[int, int]:
        if self.world is not None:
            return self.world
        from webdataset.utils import pytorch_worker_info

        rank, size, _, _ = pytorch_worker_info()
        return rank, size

    def set_epoch(self, epoch: int) -> None:
        """Another shard order and shuffle (as DistributedSampler.set_epoch); call before each epoch."""
        self.epoch = int(epoch)

    def _per_worker(self) -> list[int]:
        """The scenes each of this rank's loader workers yields this epoch (`shard_plan`)."""
        rank, size = self._rank()
        counts = [s["scenes"] for s in epoch_order(self.shards, self.seed, self.epoch)]
        workers = max(self.num_workers, 1)
        return [shard_plan(counts, rank, size, w, workers)[1] for w in range(workers)]

    def __len__(self) -> int:
        return sum(self._per_worker())

    def batches(self, batch_size: int) -> int:
        """DataLoader batches of this rank an epoch: each loader worker ends on a batch of its own
        (what a one-cycle schedule must count; len(DataLoader) assumes one stream)."""
        return sum(-(-n // batch_size) for n in self._per_worker())

    def _open(self, name: str) -> str:
        if self.url is not None:
            return self.url.format(name=name)
        return str(self.dir / name)

    def _check_local(self, shard: dict) -> None:
        path = self.dir / shard["name"]
        if self.url is None and (not path.is_file() or path.stat().st_size != shard["bytes"]):
            found = f"{path.stat().st_size} bytes" if path.is_file() else "missing"
            raise PsdError(f"shard {path} is {found}, the pack's index says {shard['bytes']} bytes: the copy is "
                           "incomplete or another pack's; copy or pack it again")

    def __iter__(self):
        import webdataset as wds

        rank, size = self._rank()
        info = torch.utils.data.get_worker_info()
        worker, workers = (info.id, info.num_workers) if info is not None else (0, 1)
        if workers != max(self.num_workers, 1):
            raise PsdError(f"ShardScenes(num_workers={self.num_workers}) read by a DataLoader with {workers} "
                           "workers: give the DataLoader's num_workers")
        order = epoch_order(self.shards, self.seed, self.epoch)
        mine, n = shard_plan([s["scenes"] for s in order], rank, size, worker, workers)
        for i in mine:
            self._check_local(order[i])
        sources = [{"url": self._open(order[i]["name"])} for i in mine]

        def damaged(exn: Exception) -> bool:
            where = exn.args[-1] if exn.args else "a shard"
            raise PsdError(f"{where}: not a readable shard ({exn.args[0] if exn.args else exn}); copy or pack it "
                           "again") from None

        samples = wds.tarfile_to_samples(handler=damaged)(iter(sources))
        rng = random.Random(f"{self.seed}:{self.epoch}:{rank}:{worker}")
        samples = wds.shuffle(self.shuffle_buffer, initial=min(self.shuffle_buffer, 100), rng=rng)(samples) \
            if self.shuffle_buffer > 1 else samples
        for sample in islice(samples, n):
            item = decode(sample, self.fields, self.index["image_format"])
            yield item if self.transform is None else self.transform(*item)


def stack_codes(image: torch.Tensor, codes: torch.Tensor, targets: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(image with the size codes as a fourth channel, targets): what the CNNs' training with the
    dense size task takes (`size_cells.ScenesWithSizeCodes` gives the same from scene folders)."""
    return torch.cat([image, codes[None]]), targets


def decode(sample: dict, fields: tuple[str, ...], image_format: str) -> tuple:
    """A WebDataset sample of a pack as the `fields` (see ShardScenes)."""
    from PIL import Image

    def member(ext: str) -> bytes:
        if ext not in sample:
            raise PsdError(f"{sample.get('__url__', 'a shard')}: scene {sample.get('__key__')} has no .{ext} (the "
                           "shard is truncated or not of this pack); copy or pack it again")
        return sample[ext]

    out = []
    meta = json.loads(member("json"))
    for f in fields:
        if f == "image":
            with Image.open(io.BytesIO(member(image_format))) as im:
                out.append(torch.from_numpy(np.array(im.convert("RGB"))).permute(2, 0, 1).contiguous())
        elif f == "targets":
            out.append(torch.tensor([meta[t] for t in TARGETS], dtype=torch.float32))
        elif f == "mask":
            with Image.open(io.BytesIO(member("mask.png"))) as im:
                out.append(torch.from_numpy(np.asarray(im).astype(np.int32)))
        elif f == "codes":
            with Image.open(io.BytesIO(member("codes.png"))) as im:
                out.append(torch.from_numpy(np.array(im, dtype=np.uint8)))
        elif f == "particles":
            out.append(np.load(io.BytesIO(member("particles.npy")), allow_pickle=False))
        else:
            out.append(meta)
    return tuple(out)
