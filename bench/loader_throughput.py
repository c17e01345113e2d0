#!/usr/bin/env python
"""What a training job's data loader gets out of a pack against the scene folders: `psdfactory
pack` (scenes/s, bytes a scene) and then images/s through a PyTorch DataLoader at the networks'
input size, for each number of loader workers, from

- **folders**: the scene folders as training reads them today (`learn.data.SceneImages` with its
  cache off: each image a PNG decoded at render size and resized), and
- **pack**: the pack's tar shards (`learn.shards.ShardScenes`: JPEG at input size, read in order,
  through a shuffle buffer).

A run reads the train split --epochs times (batches of --batch), each pass timed from its first
batch on (the workers' start is paid once a job); the figure is the median of --repeats runs, the
two sources interleaved run by run so they see the same load. The pack is written to a temporary folder
(kept with --keep).

    .venv/bin/python bench/loader_throughput.py --results results --datasets train
    .venv/bin/python bench/loader_throughput.py --results results_paper --datasets train --workers 0 1 2 \
        --size 224 --repeats 3 --jobs 2

A multi-GPU job wants ~2,000 images/s per GPU (ResNet-50, bf16, 224 px on an A100): divide by
the images/s per loader worker measured here for the workers a GPU needs (docs/scale.md).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

from psdfactory.learn.data import SceneImages, manifest_rows
from psdfactory.learn.shards import ShardScenes, pack
from psdfactory.packs import PackSpec

REPO = Path(__file__).resolve().parents[1]


def passes(dataset, workers: int, batch: int, epochs: int) -> float:
    """Images per second over `epochs` passes over `dataset` through a DataLoader with `workers`
    workers, each pass counted from its first batch on (the workers' start is paid once a job, not
    per image)."""
    n, seconds = 0, 0.0
    for epoch in range(epochs):
        if hasattr(dataset, "set_epoch"):
            dataset.set_epoch(epoch)
        loader = iter(torch.utils.data.DataLoader(dataset, batch_size=batch, num_workers=workers, shuffle=False))
        next(loader)
        t0 = time.perf_counter()
        n += sum(len(x) for x, _ in loader)
        seconds += time.perf_counter() - t0
    return n / seconds


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--results", type=Path, default=REPO / "results", help="a results root with manifests")
    ap.add_argument("--datasets", nargs="+", default=["train"], help="the datasets whose train split is read")
    ap.add_argument("--size", type=int, default=PackSpec.size, help="the networks' input size (px)")
    ap.add_argument("--workers", type=int, nargs="+", default=[0, 1, 2], help="DataLoader workers to try")
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--repeats", type=int, default=3, help="runs per source and worker count (their median)")
    ap.add_argument("--epochs", type=int, default=4, help="passes over the train split a run")
    ap.add_argument("--jobs", type=int, default=1, help="pack's --jobs")
    ap.add_argument("--keep", type=Path, help="write the pack here and keep it (default: a temporary folder)")
    ap.add_argument("--out", type=Path, help="also write the figures as JSON")
    a = ap.parse_args()
    torch.set_num_threads(1)  # a loader worker's share of a node: one core each

    work = Path(tempfile.mkdtemp(prefix="loader-bench-"))
    pack_dir = a.keep or work / "pack"
    t0 = time.perf_counter()
    cpu0 = time.process_time()
    index = pack(a.results, a.datasets, pack_dir, PackSpec(size=a.size), jobs=a.jobs)
    pack_s, pack_cpu = time.perf_counter() - t0, time.process_time() - cpu0
    n_scenes = sum(v["scenes"] for v in index["splits"].values())
    n_bytes = sum(s["bytes"] for v in index["splits"].values() for s in v["shards"])
    rows = [r for ds in a.datasets for r in manifest_rows(a.results, ds, ("train",))]
    folder_bytes = sum(os.path.getsize(a.results / r["image_path"]) for r in rows)
    resolution = int(statistics.median(r["resolution"] for r in rows))
    print(f"pack: {n_scenes} scenes in {pack_s:.1f} s ({n_scenes / pack_s:.1f} scenes/s with --jobs {a.jobs}; "
          f"main process CPU {pack_cpu:.1f} s), {n_bytes / n_scenes / 1e3:.1f} kB a scene at {a.size} px "
          f"(JPEG q{PackSpec.quality}, mask, particles) against {folder_bytes / len(rows) / 1e3:.1f} kB of "
          f"{resolution} px PNG image alone in the scene folders")

    figures = {"pack_scenes_per_s": n_scenes / pack_s, "pack_jobs": a.jobs, "pack_bytes_per_scene": n_bytes / n_scenes,
               "folder_image_bytes_per_scene": folder_bytes / len(rows), "render_px": resolution,
               "size": a.size, "train_scenes": len(rows), "loader": {}}
    for workers in a.workers:
        # a pack of one shard per split cannot feed more than one worker: repack per worker count
        shard_scenes = max(1, -(-len(rows) // max(workers, 1)))
        wpack = work / f"pack-{workers}"
        pack(a.results, a.datasets, wpack, PackSpec(size=a.size, shard_scenes=shard_scenes), splits=("train",))
        times: dict[str, list[float]] = {"folders": [], "pack": []}
        for _ in range(a.repeats):
            times["folders"].append(passes(SceneImages(a.results, rows, a.size, cache=False), workers, a.batch,
                                           a.epochs))
            times["pack"].append(passes(ShardScenes(wpack, "train", num_workers=workers, shuffle_buffer=256), workers,
                                        a.batch, a.epochs))
        med = {k: statistics.median(v) for k, v in times.items()}
        figures["loader"][workers] = {k: {"median": med[k], "runs": v} for k, v in times.items()}
        print(f"{workers} loader worker{'s' if workers != 1 else ''}: folders {med['folders']:.0f} images/s, "
              f"pack {med['pack']:.0f} images/s ({med['pack'] / med['folders']:.1f}x), medians of {a.repeats} "
              f"(runs: folders {', '.join(f'{x:.0f}' for x in times['folders'])}; "
              f"pack {', '.join(f'{x:.0f}' for x in times['pack'])})")
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps(figures, indent=1) + "\n")
    if not a.keep:
        import shutil

        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
