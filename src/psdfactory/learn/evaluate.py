"""Evaluation of a trained model on the test split of every dataset: metrics, predictions, plots."""

from __future__ import annotations

import csv
import logging
from pathlib import Path

import numpy as np
import torch

from .. import PsdError
from ..io import atomic_path, pyplot, save_figure, write_json
from ..psd import NAMES
from .data import SceneImages, manifest_rows
from .metrics import regression_metrics
from .runtime import load_model, pick_device, pick_precision, predict_batches

logger = logging.getLogger(__name__)


def eval_rows(results_root: Path, dataset: str) -> list[dict]:
    """The test split of a dataset; all of it when it has no test split."""
    rows = manifest_rows(results_root, dataset)
    test = [r for r in rows if r["split"] == "test"]
    return test or rows


def predict_rows(model, meta: dict, results_root: Path, rows: list[dict], device, precision: str, batch_size: int = 32):
    ds = SceneImages(results_root, rows, meta["input_size"], cache=False)
    loader = torch.utils.data.DataLoader(ds, batch_size=batch_size)
    pred, y = predict_batches(model, loader, device, precision)
    return pred.numpy(), y.numpy()


def evaluate(model_path: Path, results_root: Path, datasets: list[str], out_dir: Path, precision: str = "fp32",
             device: str = "auto") -> dict:
    dev = pick_device(device)
    prec = pick_precision(precision, dev)
    model, meta = load_model(model_path, dev)
    result = {"arch": meta["arch"], "weights": meta["weights"], "precision": prec, "datasets": {}}
    preds_rows = []
    for ds in datasets:
        rows = eval_rows(results_root, ds)
        if not rows:
            raise PsdError(f"dataset {ds!r} has no scenes to evaluate")
        p, y = predict_rows(model, meta, results_root, rows, dev, prec)
        m = regression_metrics(y, p)
        m["split"] = "test" if rows[0]["split"] == "test" else "all"
        result["datasets"][ds] = m
        logger.info(f"{meta['arch']} on {ds} ({m['n']} scenes): R² overall {m['overall']['r2']:.4f}, "
            + ", ".join(f"{n} {m[n]['r2']:.3f}" for n in NAMES) + f"; MAE {m['overall']['mae']:.3f} mm")
        for r, yy, pp in zip(rows, y, p, strict=True):
            preds_rows.append({"dataset": ds, "scene_id": r["scene_id"], "split": r["split"],
                               **{f"true_{n}_mm": float(v) for n, v in zip(NAMES, yy, strict=True)},
                               **{f"pred_{n}_mm": float(v) for n, v in zip(NAMES, pp, strict=True)}})
    out_dir.mkdir(parents=True, exist_ok=True)
    with atomic_path(out_dir / "predictions.csv") as tmp, open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(preds_rows[0]))
        w.writeheader()
        w.writerows(preds_rows)
    plot_scatter(preds_rows, meta["arch"], out_dir / "scatter.png")
    write_json(out_dir / "metrics.json", result)
    return result


def plot_scatter(rows: list[dict], arch: str, out: Path) -> None:
    plt = pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(11, 3.8))
    datasets = sorted({r["dataset"] for r in rows})
    for ax, n in zip(axes, NAMES, strict=True):
        for ds in datasets:
            t = np.array([r[f"true_{n}_mm"] for r in rows if r["dataset"] == ds])
            p = np.array([r[f"pred_{n}_mm"] for r in rows if r["dataset"] == ds])
            ax.scatter(t, p, s=12, alpha=0.7, label=ds)
        allv = np.array([[r[f"true_{n}_mm"], r[f"pred_{n}_mm"]] for r in rows])
        lo, hi = allv.min(), allv.max()
        ax.plot([lo, hi], [lo, hi], "k--", lw=1)
        ax.set_title(f"{arch}: {n}")
        ax.set_xlabel("true (mm)")
        ax.set_ylabel("predicted (mm)")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, out, dpi=100)


def plot_history(history_csv: Path, arch: str, out: Path) -> None:
    plt = pyplot()
    with open(history_csv) as f:
        rows = list(csv.DictReader(f))
    ep = [int(r["epoch"]) for r in rows]
    fig, ax = plt.subplots(figsize=(5, 3.5))
    ax.plot(ep, [float(r["train_loss"]) for r in rows], label="train")
    ax.plot(ep, [float(r["val_loss"]) for r in rows], label="validation")
    ax.set_yscale("log")
    ax.set_xlabel("epoch")
    ax.set_ylabel("MSE (standardised targets)")
    ax.set_title(f"{arch}: loss")
    ax.legend()
    fig.tight_layout()
    save_figure(fig, out, dpi=100)

