"""Evaluation of a trained model on the test split of every dataset: metrics, predictions, plots."""

from __future__ import annotations

import csv
import logging
from pathlib import Path

import numpy as np

from .. import PsdError
from ..io import atomic_path, pyplot, save_figure, write_json
from ..psd import NAMES
from .data import manifest_rows
from .estimator import predictions, rows_readings
from .metrics import regression_metrics
from .runtime import load_estimator, pick_device, pick_precision, torch_runner

logger = logging.getLogger(__name__)


def eval_rows(results_root: Path, dataset: str) -> list[dict]:
    """The test split of a dataset; all of it when it has no test split."""
    rows = manifest_rows(results_root, dataset)
    test = [r for r in rows if r["split"] == "test"]
    return test or rows


def evaluate(model_path: Path, results_root: Path, datasets: list[str], out_dir: Path, precision: str = "fp32",
             device: str = "auto") -> dict:
    """Every dataset's test split (all of it without one) through the model's estimator: the
    regression metrics of its d10/d50/d90 per dataset, with whatever its scorer adds
    (`Estimator.scorer`); predictions.csv, scatter.png and metrics.json in `out_dir`."""
    dev = pick_device(device)
    prec = pick_precision(precision, dev)
    est = load_estimator(model_path, dev)
    est.run = torch_runner(est.inference_module(), dev, prec)
    meta = est.meta
    result = {"arch": meta["arch"], "weights": meta["weights"], "precision": prec, "datasets": {}}
    preds_rows = []
    for ds in datasets:
        rows = eval_rows(results_root, ds)
        if not rows:
            raise PsdError(f"dataset {ds!r} has no scenes to evaluate")
        scorer = est.scorer(results_root, ds)
        readings, y = rows_readings(est, results_root, rows)
        p = predictions(readings)
        for r, yy, reading in zip(rows, y, readings, strict=True):
            extra = scorer.add(r, reading)
            preds_rows.append({"dataset": ds, "scene_id": r["scene_id"], "split": r["split"],
                               **{f"true_{n}_mm": float(v) for n, v in zip(NAMES, yy, strict=True)},
                               **{f"pred_{n}_mm": float(v) for n, v in zip(NAMES, reading.d_mm, strict=True)},
                               **extra})
        m = regression_metrics(y, p)
        m["split"] = "test" if rows[0]["split"] == "test" else "all"
        m.update(scorer.metrics())
        result["datasets"][ds] = m
        logger.info(f"{meta['arch']} on {ds} ({m['n']} scenes): R² " + " / ".join(f"{m[n]['r2']:.3f}" for n in NAMES)
                    + f" (overall {m['overall']['r2']:.4f}); MAE {m['overall']['mae']:.3f} mm" + scorer.summary(m))
    write_evaluation(out_dir, preds_rows, meta["arch"], result)
    return result


def write_evaluation(out_dir: Path, preds_rows: list[dict], arch: str, result: dict) -> None:
    """predictions.csv, scatter.png and metrics.json of one evaluated model."""
    out_dir.mkdir(parents=True, exist_ok=True)
    with atomic_path(out_dir / "predictions.csv") as tmp, open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(preds_rows[0]))
        w.writeheader()
        w.writerows(preds_rows)
    plot_scatter(preds_rows, arch, out_dir / "scatter.png")
    write_json(out_dir / "metrics.json", result)


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
    axes[0].legend(fontsize=10)
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
