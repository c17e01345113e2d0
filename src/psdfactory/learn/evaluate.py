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
    if meta["arch"] == "instances":  # + segmentation P/R/F1 and particle size errors
        return evaluate_instances(model, meta, results_root, datasets, out_dir, dev, prec)
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


def evaluate_instances(model: torch.nn.Module, meta: dict, results_root: Path, datasets: list[str], out_dir: Path,
                       device, precision: str) -> dict:
    """metrics.json (the CNNs' regression metrics of the calibrated d10/d50/d90 per dataset,
    plus 'raw', 'segmentation' and 'size_error'), predictions.csv and scatter.png."""
    from ..io import read_png
    from .data import targets as label_targets
    from .instances import (
        ARCH,
        InstanceEstimator,
        fully_visible,
        read_particles,
        size_errors,
        size_map_px,
        torch_maps_fn,
    )
    from .particles import SIEVE_METHODS, match_instances, measure_instances, sieve_size

    est = InstanceEstimator(torch_maps_fn(model, device, precision), meta)
    result = {"arch": meta["arch"], "weights": meta["weights"], "precision": precision, "datasets": {}}
    preds_rows = []
    for ds in datasets:
        rows = eval_rows(results_root, ds)
        if not rows:
            raise PsdError(f"dataset {ds!r} has no scenes to evaluate")
        particles = read_particles(results_root, ds)
        cal, raw = [], []
        tp = n_pred = n_true = 0
        ious, f1s = [], []
        sizes: dict[str, dict[str, list]] = {k: {"est": {m: [] for m in SIEVE_METHODS}, "true": []}
                                              for k in ("matched", "matched_fully_visible", "true_mask_fully_visible")}
        for r in rows:
            img = read_png(Path(results_root) / r["image_path"])
            true = read_png(Path(results_root) / r["mask_path"]).astype(np.int64)
            x = torch.from_numpy(np.array(img, dtype=np.uint8, copy=True)).permute(2, 0, 1)[None]
            maps = est.maps(x)[0]
            res = est.analyse_maps(maps, float(r["mm_per_px"]))
            cal.append(res.calibrated)
            raw.append(res.raw)
            match = match_instances(res.mask, true)
            tp, n_pred, n_true = tp + match.n_matched, n_pred + match.n_pred, n_true + match.n_true
            ious += match.iou.tolist()
            f1s.append(match.f1)
            p = particles.get(r["scene_id"])
            if p is None:
                raise PsdError(f"the particle manifest of {ds!r} has no rows for {r['scene_id']}")
            size_by_id = np.full(int(p["particle_id"].max()) + 2, np.nan)
            z_by_id = np.full(len(size_by_id), -np.inf)
            size_by_id[p["particle_id"] + 1] = p["size_mm"]  # mask id = particle_id + 1
            z_by_id[p["particle_id"] + 1] = p["z_mm"]
            visible = fully_visible(true, z_by_id)
            m = res.measurements
            k = np.searchsorted(m.ids, match.pred_ids)
            inner = ~m.touches_edge[k]
            tid = match.true_ids
            for key, sel in (("matched", inner), ("matched_fully_visible", inner & visible[tid])):
                sizes[key]["true"] += size_by_id[tid[sel]].tolist()
                for meth in m.methods():
                    sizes[key]["est"][meth] += sieve_size(m, meth)[k[sel]].tolist()
            # the estimators on perfect masks (the size map: the network's, read on the true instances)
            tm = measure_instances(true, float(r["mm_per_px"]), size_map_px=size_map_px(maps))
            vis = visible[tm.ids]
            sizes["true_mask_fully_visible"]["true"] += size_by_id[tm.ids[vis]].tolist()
            for meth in tm.methods():
                sizes["true_mask_fully_visible"]["est"][meth] += sieve_size(tm, meth)[vis].tolist()
            preds_rows.append({"dataset": ds, "scene_id": r["scene_id"], "split": r["split"],
                               **{f"true_{n}_mm": float(r[f"{n}_mm"]) for n in NAMES},
                               **{f"pred_{n}_mm": float(v) for n, v in zip(NAMES, res.calibrated, strict=True)},
                               **{f"raw_{n}_mm": float(v) for n, v in zip(NAMES, res.raw, strict=True)},
                               "n_pred": match.n_pred, "n_true": match.n_true, "n_matched": match.n_matched,
                               "f1": match.f1})
        y = label_targets(rows).numpy()
        mets = regression_metrics(y, np.stack(cal))
        mets["split"] = "test" if rows[0]["split"] == "test" else "all"
        raw_arr = np.stack(raw)
        mets["raw"] = regression_metrics(y, np.where(np.isfinite(raw_arr), raw_arr, np.nanmean(raw_arr, axis=0)))
        mets["raw"]["images_without_instances"] = int((~np.isfinite(raw_arr).all(axis=1)).sum())
        mets["segmentation"] = {"iou": 0.5, "precision": tp / n_pred if n_pred else float("nan"),
                                "recall": tp / n_true if n_true else float("nan"),
                                "f1": 2 * tp / (n_pred + n_true) if n_pred + n_true else float("nan"),
                                "mean_image_f1": float(np.nanmean(f1s)), "n_pred": n_pred, "n_true": n_true,
                                "n_matched": tp, "mean_matched_iou": float(np.mean(ious)) if ious else float("nan")}
        mets["size_error"] = {"relative_to": "true sieve size", "method": est.method,
                              **{key: {meth: size_errors(v["est"][meth], v["true"]) for meth in SIEVE_METHODS}
                                 for key, v in sizes.items()}}
        result["datasets"][ds] = mets
        se = mets["size_error"]["matched"][est.method]
        seg = mets["segmentation"]
        logger.info(f"{ARCH} on {ds} ({mets['n']} scenes): R² calibrated "
            + " / ".join(f"{mets[n]['r2']:.3f}" for n in NAMES)
            + ", raw " + " / ".join(f"{mets['raw'][n]['r2']:.3f}" for n in NAMES)
            + f"; P/R/F1 {seg['precision']:.3f}/{seg['recall']:.3f}/{seg['f1']:.3f}; size error of matched particles "
            + (f"median {100 * se['median']:.1f} %, p90 {100 * se['p90']:.1f} %" if se["n"] else "(none matched)"))
    write_evaluation(out_dir, preds_rows, meta["arch"], result)
    return result
