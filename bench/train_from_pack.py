#!/usr/bin/env python
"""A CNN's training speed from the scene folders, from a pack, and from a pack on several processes
(DDP under torchrun, each rank its own shards), side by side on one machine: the training images a
second of each epoch after the first (the first decodes and caches the folders' images), from each
run's history.csv, median over the epochs.

    .venv/bin/python bench/train_from_pack.py --results /tmp/paperbench --dataset train \
        --arch resnet18 --epochs 4 --procs 2

--procs N runs the DDP side as N processes of `--threads / N` threads each against one process of
`--threads` threads, so all sides use the same cores. On a CPU this measures what the pack and DDP
cost or save around the same arithmetic; on a GPU node, give --device cuda and --procs the GPUs.
"""

from __future__ import annotations

import argparse
import csv
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def train_slice(arch: str, dataset: str, epochs: int, size: int, batch: int, device: str) -> dict:
    from psdfactory import config as C

    cfg = C.validate({"datasets": {dataset: {"n_scenes": 10}}, "train": {"datasets": [dataset]}})
    p = C.train_params(cfg, arch)
    p.update(pretrained="none", epochs=epochs, batch_size=batch, input_size=size, precision="fp32", seed=1,
             early_stopping_patience=epochs, device=device, size_cells=0.0)
    return p


def run(label: str, cmd: list[str], out: Path) -> dict:
    t0 = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode:
        sys.exit(f"{label} failed:\n{r.stderr[-3000:]}")
    wall = time.perf_counter() - t0
    with open(out / "history.csv", newline="") as f:
        seconds = [float(row["seconds"]) for row in csv.DictReader(f)]
    return {"wall_s": wall, "epoch_s": seconds}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--results", type=Path, required=True)
    ap.add_argument("--dataset", default="train")
    ap.add_argument("--arch", default="resnet18")
    ap.add_argument("--size", type=int, default=224)
    ap.add_argument("--epochs", type=int, default=4)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--procs", type=int, default=2, help="processes of the DDP side")
    ap.add_argument("--device", default="cpu")
    a = ap.parse_args()

    from psdfactory.learn.data import manifest_rows
    from psdfactory.learn.shards import pack
    from psdfactory.packs import PackSpec

    work = Path(tempfile.mkdtemp(prefix="train-from-pack-"))
    n_train = len(manifest_rows(a.results, a.dataset, ("train",)))
    pack_dir = work / "pack"
    # as many train shards as the DDP side has ranks (one loader in each process: no workers)
    pack(a.results, [a.dataset], pack_dir, PackSpec(size=a.size, shard_scenes=max(1, n_train // a.procs)))
    params = json.dumps(train_slice(a.arch, a.dataset, a.epochs, a.size, a.batch, a.device))
    cli = [sys.executable, "-m", "psdfactory.cli", "-q", "train", "--params", params, "--results", str(a.results)]
    torchrun = str(Path(sys.executable).with_name("torchrun"))
    sides = {
        "folders, 1 process": cli + ["--out-dir", str(work / "a"), "--threads", str(a.threads)],
        "pack, 1 process": cli + ["--out-dir", str(work / "b"), "--threads", str(a.threads), "--pack", str(pack_dir)],
        f"pack, {a.procs} processes (DDP)": [torchrun, "--standalone", "--nproc-per-node", str(a.procs)] + cli[1:] + [
            "--out-dir", str(work / "c"), "--threads", str(max(1, a.threads // a.procs)), "--pack", str(pack_dir)],
    }
    outs = dict(zip(sides, ("a", "b", "c"), strict=True))
    print(f"{a.arch} at {a.size} px, batch {a.batch}, {n_train} training scenes of {a.results}/{a.dataset}, "
          f"{a.epochs} epochs, {a.threads} threads in all, {a.device}")
    for label, cmd in sides.items():
        r = run(label, cmd, work / outs[label])
        later = r["epoch_s"][1:] or r["epoch_s"]
        med = statistics.median(later)
        print(f"  {label}: {n_train / med:.1f} images/s (median of epochs 2-{a.epochs}: {med:.1f} s an epoch; "
              f"first epoch {r['epoch_s'][0]:.1f} s; {r['wall_s']:.0f} s in all)")


if __name__ == "__main__":
    main()
