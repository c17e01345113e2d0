#!/usr/bin/env python
"""What a CNN's dense size task (`train.size_cells`) learnt: could the CNN read d10/d50/d90 off
its own size-histogram cells? Measured, not adopted (docs/experiments.md, 2026-11-27).

Training with `size_cells` > 0 adds a 1×1 convolution on the backbone's last feature map that
learns, per cell, the share of its pixels in each half-octave sieve-size bin (and the table). It
is dropped from the saved model, but the last checkpoint (`checkpoints/last.pt`) keeps it. This
script puts it back on the last epoch's network and compares, on the test split of each dataset:

- `regression head`: the model's own d10/d50/d90;
- `cell histogram`: the cells' predicted bin shares averaged over the image, turned into a
  number-weighted distribution (each bin's share over the square of its size), its percentiles
  interpolated within the bins and mapped to the labels by an affine fit per target on the
  training and validation scenes;
- `true cells`: the same read-out of the cells' true shares (from the instance mask): what a
  perfect dense head would give, the ceiling of the route;
- the mean L1 distance between predicted and true image-level bin shares.

    .venv/bin/python bench/cnn_cell_head.py --models results/models/{resnet50,inception_v3,efficientnet_b0} \
        --datasets train train_cycles
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def bin_centres_log2() -> np.ndarray:
    """log2 px at the middle of each size class of `size_cells` (the open end bins half a bin out)."""
    from psdfactory.learn.size_cells import BIN_EDGES_LOG2_PX, BIN_OCTAVES

    e = np.array(BIN_EDGES_LOG2_PX)
    return np.concatenate([[e[0] - BIN_OCTAVES / 2], (e[:-1] + e[1:]) / 2, [e[-1] + BIN_OCTAVES / 2]])


def histogram_percentiles(shares: np.ndarray) -> np.ndarray:
    """Image-level class shares (N × N_CLASSES, table first) → number-weighted d10/d50/d90 in px."""
    from psdfactory.learn.size_cells import BIN_OCTAVES

    c = bin_centres_log2()
    area = shares[:, 1:] / np.maximum(shares[:, 1:].sum(1, keepdims=True), 1e-12)
    n = area / (2.0**c) ** 2
    cum = np.cumsum(n / n.sum(1, keepdims=True), axis=1)
    out = []
    for q in (0.1, 0.5, 0.9):
        k = np.clip((cum < q).sum(1), 0, len(c) - 1)
        rows = np.arange(len(k))
        lo = np.where(k > 0, cum[rows, np.maximum(k - 1, 0)], 0.0)
        t = (q - lo) / np.maximum(cum[rows, k] - lo, 1e-12)
        out.append(2.0 ** (c[k] - BIN_OCTAVES / 2 + BIN_OCTAVES * t))
    return np.stack(out, 1)


def main() -> None:
    import torch

    from psdfactory.config import load_config
    from psdfactory.io import read_png
    from psdfactory.learn import size_cells as sc
    from psdfactory.learn.data import normalised_images, particles_by_scene, training_rows
    from psdfactory.learn.evaluate import eval_rows
    from psdfactory.learn.metrics import r2_scores
    from psdfactory.learn.models import TargetStats, build_model, main_output

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default="config/config.yaml")
    ap.add_argument("--models", nargs="+", required=True, type=Path, help="model folders (model.pt, checkpoints/)")
    ap.add_argument("--datasets", nargs="+", default=["train", "train_cycles"])
    a = ap.parse_args()
    root = Path(load_config(Path(a.config))["results"])

    for folder in a.models:
        meta = torch.load(folder / "model.pt", weights_only=False, map_location="cpu")["meta"]
        ck = torch.load(folder / "checkpoints" / "last.pt", weights_only=False, map_location="cpu")
        if "cell_head" not in ck.get("modules", {}):
            print(f"{folder}: trained without the dense size task (train.size_cells: 0)")
            continue
        arch, size = meta["arch"], meta["input_size"]
        model, _ = build_model(arch, TargetStats(**meta["target_stats"]), "none", size=size)
        model.load_state_dict(ck["modules"]["model"])
        model.eval()
        tap = sc.FeatureTap(model, arch)
        head = sc.CellHead(ck["modules"]["cell_head"]["conv.weight"].shape[1])
        head.load_state_dict(ck["modules"]["cell_head"])
        head.eval()

        def read(rows: list[dict], dataset: str, model=model, tap=tap, head=head, size=size):
            x, y = normalised_images(root, rows, size)
            outs, shares = [], []
            with torch.no_grad():
                for i in range(0, len(x), 16):
                    outs.append(main_output(model(x[i : i + 16])).numpy())
                    shares.append(torch.softmax(head(tap.features.float()), 1).mean((2, 3)).numpy())
            parts = particles_by_scene(root, [dataset])
            true = np.stack([sc.cell_targets(sc.scene_codes(read_png(root / r["mask_path"]), parts[r["scene_id"]],
                                                            float(r["mm_per_px"]), size)[None], (1, 1))[0, :, 0, 0]
                             .numpy() for r in rows])
            return np.concatenate(outs), np.concatenate(shares), true, y

        tr, va, _ = training_rows(root, meta["params"]["datasets"])
        _, fit_pred, fit_true, fit_y = read(tr + va, meta["params"]["datasets"][0])

        def affine(p: np.ndarray, y: np.ndarray) -> list[np.ndarray]:
            return [np.polyfit(p[:, j], y[:, j], 1) for j in range(3)]

        cal_pred = affine(histogram_percentiles(fit_pred), fit_y)
        cal_true = affine(histogram_percentiles(fit_true), fit_y)

        def apply(c: list[np.ndarray], s: np.ndarray) -> np.ndarray:
            p = histogram_percentiles(s)
            return np.stack([np.polyval(c[j], p[:, j]) for j in range(3)], 1)

        def f(v) -> str:
            return " / ".join(f"{x:.2f}" for x in v)

        print(f"\n{arch} ({folder}), R² d10 / d50 / d90")
        print("| images | regression head | cell histogram | true cells | share L1 |")
        print("|---|---|---|---|---|")
        for d in a.datasets:
            rows = eval_rows(root, d)
            out, pred, true, y = read(rows, d)
            print(f"| {d} ({len(rows)}) | {f(r2_scores(y, out))} | {f(r2_scores(y, apply(cal_pred, pred)))} | "
                  f"{f(r2_scores(y, apply(cal_true, true)))} | {np.abs(pred - true).sum(1).mean():.3f} |")
        tap.remove()


if __name__ == "__main__":
    main()
