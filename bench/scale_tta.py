#!/usr/bin/env python
"""An instance model read at several scales of the same images, its d-values averaged (scale TTA).

Each image is predicted with `psdfactory predict --mm-per-px S×f` for each factor f: the photo is
then resized f× smaller than at its true scale and every size reads f× too large, so the d-values
are divided by f, and the readings are averaged (geometric mean). Printed per model, for one scale,
for the average and for each other factor: mean |error| of d10/d50/d90 against the scenes' labels,
Spearman ρ, and the leave-one-out error of the correction `psdfactory calibrate` would fit on them
(its method for N references, and affine).

    .venv/bin/python bench/scale_tta.py --models M [M ...] --scenes /tmp/psd-paper-look/scenes \
        --mm-per-px 0.3 --size-definition b-axis [--factors 0.8696 1 1.15]

Scenes are folders with image.png and labels.json (bench/paper_look.py makes them). The readings are
kept in --work, one CSV per model and factor, and read again where present.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
from scipy.stats import spearmanr

from psdfactory.deploy.predict import read_rows
from psdfactory.learn import calibration
from psdfactory.psd import NAMES


def read(model: Path, images: list[str], mm_per_px: float, definition: str, out: Path) -> np.ndarray:
    """d10/d50/d90 (mm) per image as `predict` reads them at `mm_per_px`."""
    if not out.is_file():
        cmd = [str(Path(sys.executable).with_name("psdfactory")), "-q", "predict", "--model", str(model),
               "--mm-per-px", repr(mm_per_px), "--size-definition", definition, "--out", str(out), *images]
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    rows = {r["image"]: r for r in read_rows(out)}
    return np.array([[float(rows[i][f"{n}_mm"]) for n in NAMES] for i in images])


def figures(p: np.ndarray, ref: np.ndarray) -> str:
    err = 100 * np.abs(p - ref) / ref
    rho = [spearmanr(p[:, k], ref[:, k])[0] for k in range(3)]
    loo = {m: 100 * np.abs(calibration.leave_one_out(p, ref, m) - ref) / ref
           for m in (calibration.method_for(len(p)), "affine")}

    def fmt(v) -> str:
        return " / ".join(f"{x:.1f}" for x in v)

    return (f"|error| {fmt(err.mean(0))} %, rho {' / '.join(f'{r:.2f}' for r in rho)}, "
            + ", ".join(f"LOO {m} {fmt(e.mean(0))} %" for m, e in loo.items()))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", nargs="+", required=True, type=Path)
    ap.add_argument("--scenes", required=True, type=Path, help="folder of scene folders (image.png, labels.json)")
    ap.add_argument("--mm-per-px", required=True, type=float)
    ap.add_argument("--size-definition", default="b-axis")
    ap.add_argument("--factors", nargs="+", type=float, default=[1 / 1.15, 1.0, 1.15])
    ap.add_argument("--work", type=Path, default=Path("/tmp/psd-scale-tta"))
    a = ap.parse_args()
    if not all(np.isfinite(v) and v > 0 for v in (a.mm_per_px, *a.factors)):
        ap.error("--mm-per-px and --factors must be finite and above 0")
    if 1.0 not in a.factors:
        ap.error("--factors must include 1 (the reading at the images' own scale)")
    scenes = sorted(d for d in a.scenes.iterdir() if (d / "labels.json").is_file() and (d / "image.png").is_file())
    if len(scenes) < 3:
        ap.error(f"{a.scenes} holds {len(scenes)} scene folders with image.png and labels.json; at least 3 are needed")
    images = [str(d / "image.png") for d in scenes]
    ref = np.array([[json.loads((d / "labels.json").read_text())[f"{n}_mm"] for n in NAMES] for d in scenes])
    a.work.mkdir(parents=True, exist_ok=True)
    print(f"{len(scenes)} scenes of {a.scenes}, {a.size_definition}, factors {a.factors}")
    for k, model in enumerate(a.models):
        reads = {f: read(model, images, a.mm_per_px * f, a.size_definition, a.work / f"model{k}_f{f:.4f}.csv") / f
                 for f in a.factors}
        mean = np.exp(np.mean([np.log(r) for r in reads.values()], axis=0))
        print(f"{model}:")
        print(f"  one scale       {figures(reads[1.0], ref)}")
        print(f"  {len(a.factors)} scales, mean  {figures(mean, ref)}")
        for f in a.factors:
            if f != 1.0:
                print(f"  f = {f:<11.3f} {figures(reads[f], ref)}")


if __name__ == "__main__":
    main()
