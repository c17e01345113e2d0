#!/usr/bin/env python
"""What the instance estimator's training augmentations cost beside its training step, per batch.

The instance estimator trains on batches of random crops (train.batch_size 16, train.input_size.instances 128 px).
Before a batch reaches the network it can go through `learn.augment.surface_texture`
(train.instances.surface_texture; drawn per image in Python) and `learn.augment.photometric` (the camera and light
augmentation, on by default). This script times, on batches of that shape:

- **photometric**: `photometric(x, gen, 1.0)`;
- **surface_texture**: `surface_texture(x, foreground, gen, 1.0)` (it draws texture on half the images);
- **training step**: one optimiser step of the instance network (forward, loss, backward, Adam) at the precision
  training picks here (`auto`: bf16 where the CPU has it and it measures faster);

each the median of --repeats runs of --batches batches, the three interleaved run by run so that they see the same
load, and prints each one's milliseconds per batch and its share of a step with everything on. The images are random
(the augmentations' cost does not depend on what the image shows), the foreground a random half of each image.

    .venv/bin/python bench/augment_cost.py [--batch 16] [--size 128] [--repeats 5] [--batches 10] [--threads N]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time

import torch


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--batch", type=int, default=16, help="crops per batch (default: %(default)s, train.batch_size)")
    ap.add_argument("--size", type=int, default=128, help="crop side in px (default: %(default)s)")
    ap.add_argument("--repeats", type=int, default=5, help="runs of each part (median) (default: %(default)s)")
    ap.add_argument("--batches", type=int, default=10, help="batches a run (default: %(default)s)")
    ap.add_argument("--threads", type=int, default=os.cpu_count() or 1, help="torch threads (default: all cores)")
    a = ap.parse_args(argv)
    if min(a.batch, a.size, a.repeats, a.batches, a.threads) < 1:
        ap.error("--batch, --size, --repeats, --batches and --threads must be at least 1")
    torch.set_num_threads(a.threads)

    from psdfactory.learn.augment import photometric, surface_texture
    from psdfactory.learn.data import normalise
    from psdfactory.learn.instances.net import build_instance_net
    from psdfactory.learn.instances.targets import MAPS, instance_loss
    from psdfactory.learn.runtime import optimise_step, training_precision

    gen = torch.Generator().manual_seed(0)
    x = torch.randint(0, 256, (a.batch, 3, a.size, a.size), dtype=torch.uint8, generator=gen)
    fg = (torch.rand((a.batch, a.size, a.size), generator=gen) < 0.5).float()
    targets = torch.zeros(a.batch, len(MAPS), a.size, a.size)
    targets[:, 0] = fg
    model, _ = build_instance_net("none")
    model = model.to(memory_format=torch.channels_last)
    device = torch.device("cpu")
    opt = torch.optim.Adam(model.parameters(), lr=1e-4)
    precision = training_precision("auto", device, model, a.size, a.batch,
                                   lambda out: instance_loss(out, targets, 1.0)[0])

    def step() -> None:
        optimise_step(model, opt, normalise(x), lambda out: instance_loss(out, targets, 1.0)[0], device, precision,
                      "lr")

    parts = {
        "photometric": lambda: photometric(x, gen, 1.0),
        "surface_texture": lambda: surface_texture(x, fg, gen, 1.0),
        "training step": step,
    }
    for fn in parts.values():  # warm-up: kernels, allocator
        fn()
    times: dict[str, list[float]] = {k: [] for k in parts}
    t_all = time.perf_counter()
    for r in range(a.repeats):
        for name, fn in parts.items():
            t0 = time.perf_counter()
            for _ in range(a.batches):
                fn()
            times[name].append((time.perf_counter() - t0) / a.batches * 1e3)
        done = r + 1
        el = time.perf_counter() - t_all
        print(f"run {done}/{a.repeats}, {el:.0f} s, ETA {el / done * (a.repeats - done):.0f} s", flush=True)
    med = {k: statistics.median(v) for k, v in times.items()}
    total = sum(med.values())
    print(f"\n{platform.processor() or platform.machine()}, {a.threads} threads, torch {torch.__version__}; batches of "
          f"{a.batch} x {a.size}x{a.size} px; training step in {precision}; medians of {a.repeats} runs of "
          f"{a.batches} batches")
    print(f"{'part':18s}{'ms / batch':>12s}{'range':>20s}{'share of all':>14s}")
    for k, v in med.items():
        print(f"{k:18s}{v:12.1f}{f'{min(times[k]):.1f}-{max(times[k]):.1f}':>20s}{100 * v / total:13.0f}%")
    print(f"surface_texture adds {100 * med['surface_texture'] / (med['photometric'] + med['training step']):.0f} % to "
          f"a training batch with photometric on")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
