#!/usr/bin/env python
"""How much larger a grain finder draws the grains than the particles in view, and what predicts it.

Per scene: the found grains' number-weighted min Feret d50 (a `bench/calibration_basis.py --save`
file's `feret-min|number` reading, one row per scene folder in sorted order) over that of the
particles in view (`particles.parquet`: settled particles with pixels in view), beside scene
statistics from the truth: the particles in view's b-axis d50 in px at the model's scale, their
number per cm², the share of the image they cover, the share of the background that is dark
(grey level <= 0.6: shadows, shaded gaps). Printed: the medians per set, each statistic's Spearman
correlation with the ratio over every set but the last, and the fit ratio = a + b / (d50 in px)
on those sets with what it predicts for the last (docs/experiments.md, 2026-11-30: it predicts the
paper look's 1.29 from the training looks).

    .venv/bin/python bench/finder_size_bias.py --model-mm-per-px 0.5859 \\
        dense=results/train_cycles_bright/scenes:dense.npz test=cyc/:test.npz paper=/tmp/psd-paper-look/scenes:paper.npz
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

STATS = ("d50_px", "in_view_per_cm2", "covered", "dark_background")


def scene_stats(scene: Path, model_mm_per_px: float) -> dict:
    """The truth of one scene folder: its particles in view's min Feret d50 (mm) and the STATS."""
    import pandas as pd
    from PIL import Image

    t = pd.read_parquet(scene / "particles.parquet")
    t = t[t["settled"]] if "settled" in t else t
    v = t[t["visible_px"] > 0]
    mm = float(json.loads((scene / "labels.json").read_text(encoding="utf-8"))["mm_per_px"])
    ref = np.asarray(Image.open(scene / "mask.png"))
    img = np.asarray(Image.open(scene / "image.png").convert("L"), float) / 255
    bg = ref == 0
    return {"in_view_feret_min_d50_mm": float(np.median(v["feret_min_mm"])),
            "d50_px": float(np.median(v["b_axis_mm"])) / model_mm_per_px,
            "in_view_per_cm2": len(v) / (ref.size * mm * mm / 100), "covered": float(1 - bg.mean()),
            "dark_background": float((img[bg] <= 0.6).mean()) if bg.any() else float("nan")}


def fit_rim(d50_px: np.ndarray, ratio: np.ndarray) -> tuple[float, float]:
    """(a, b) of ratio = a + b / d50_px by least squares."""
    b, a = np.polyfit(1 / np.asarray(d50_px, float), np.asarray(ratio, float), 1)
    return float(a), float(b)


def main() -> None:
    from scipy.stats import spearmanr

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sets", nargs="+", metavar="NAME=SCENES:READINGS.npz",
                    help="scene folders and the model's readings of them; the last set is the one predicted")
    ap.add_argument("--model-mm-per-px", type=float, required=True, help="the scale the model reads at")
    a = ap.parse_args()
    if len(a.sets) < 2:
        raise SystemExit("finder_size_bias.py: give at least two sets: the last is predicted from the others")
    if not (np.isfinite(a.model_mm_per_px) and a.model_mm_per_px > 0):
        raise SystemExit("finder_size_bias.py: --model-mm-per-px must be a positive number")
    rows: dict[str, list[dict]] = {}
    for spec in a.sets:
        name, _, rest = spec.partition("=")
        folder, _, npz = rest.rpartition(":")
        if not (name and Path(folder).is_dir() and Path(npz).is_file()):
            raise SystemExit(f"finder_size_bias.py: {spec!r}: give NAME=SCENES_FOLDER:READINGS.npz, both existing")
        scenes = sorted(p for p in Path(folder).iterdir() if (p / "particles.parquet").is_file())
        found = np.load(npz)["feret-min|number"][:, 1]
        if len(found) != len(scenes):
            raise SystemExit(f"finder_size_bias.py: {npz} holds {len(found)} scenes, {folder} {len(scenes)}")
        rows[name] = []
        for scene, f in zip(scenes, found, strict=True):
            s = scene_stats(scene, a.model_mm_per_px)
            rows[name].append(s | {"ratio": f / s["in_view_feret_min_d50_mm"]})
    print("| set | scenes | found / in view, min Feret d50 | " + " | ".join(STATS) + " |")
    print("|---|---|---|" + "---|" * len(STATS))
    for name, rs in rows.items():
        med = {k: np.nanmedian([r[k] for r in rs]) for k in ("ratio", *STATS)}
        print(f"| {name} | {len(rs)} | {med['ratio']:.3f} | " + " | ".join(f"{med[k]:.3g}" for k in STATS) + " |")
    *known, last = rows
    train = [r for n in known for r in rows[n]]
    ratio = np.array([r["ratio"] for r in train])
    for k in STATS:
        print(f"{k}: Spearman with the ratio over {', '.join(known)} ({len(train)} scenes) "
              f"{spearmanr([r[k] for r in train], ratio, nan_policy='omit')[0]:+.2f}")
    fa, fb = fit_rim([r["d50_px"] for r in train], ratio)
    pred = np.median([fa + fb / r["d50_px"] for r in rows[last]])
    print(f"ratio = {fa:.3f} + {fb:.2f} / d50_px over {', '.join(known)}; it predicts {last} at {pred:.3f}, "
          f"measured {np.median([r['ratio'] for r in rows[last]]):.3f}")


if __name__ == "__main__":
    main()
