#!/usr/bin/env python3
"""Should a calibration choose which of a model's readings it corrects, from the references themselves?

`psdfactory calibrate` corrects one reading of each image, fixed in advance (`learn.calibration.basis_for`):
the references' own size definition and weighting where the model reads it. An instance model has many
readings (every size definition in every weighting), and on images unlike its training scenes another may
calibrate better. Two procedures that let the references decide, per target, scored honestly:

- choice: the reading x correction method (affine; isotonic too from `ISOTONIC_FROM` references) with the
  lowest leave-one-out mean |error| / reference on the references, fitted on all of them;
- committee: every reading x method corrected, averaged with weights 1 / (its leave-one-out mean squared
  relative error on the references): a soft choice.

Their error is the nested leave-one-out: each reference predicted by the procedure run on the others alone
(the choice or the weights made again without it); the fixed rule's is its plain leave-one-out. Input: the
.npz files `bench/calibration_basis.py --save` writes (one per model and scene set; references in the
definition it was run with), and optionally a second definition read from the scenes' labels.json:

    .venv/bin/python bench/calibration_basis.py --model M --scenes /tmp/psd-paper-look/scenes \
        --mm-per-px 0.3 --subset 0 --save /tmp/r.paper.npz
    .venv/bin/python bench/calibration_choice.py /tmp/r.paper.npz
    .venv/bin/python bench/calibration_choice.py /tmp/r.tiny.npz --also sieve --scenes results/train/scenes

Synthetic scenes only: the development photos are for measuring, never for choosing (issue 24).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REL_FLOOR = 1e-8  # a candidate's mean squared relative error is at least this (an exact one does not divide by 0)


def _column(p: np.ndarray, r: np.ndarray, method: str, k: int, new: np.ndarray) -> np.ndarray:
    from psdfactory.learn import calibration as cal

    return np.atleast_2d(cal.apply(cal.fit(p, r, method), new))[:, k]


def loo_column(p: np.ndarray, r: np.ndarray, method: str, k: int) -> np.ndarray:
    """Target k of each reference corrected by the correction fitted on the others."""
    n = len(p)
    return np.array([_column(p[np.arange(n) != i], r[np.arange(n) != i], method, k, p[i])[0] for i in range(n)])


def methods_for(n: int) -> list[str]:
    from psdfactory.learn.calibration import ISOTONIC_FROM

    return ["affine"] + (["isotonic"] if n >= ISOTONIC_FROM else [])


def candidate_scores(reads: dict[str, np.ndarray], r: np.ndarray, k: int) -> list[tuple[float, float, str, str]]:
    """(leave-one-out mean |relative error| of target k, its mean square, reading, method) of every candidate that
    fits."""
    out = []
    for key, p in reads.items():
        for m in methods_for(len(r)):
            try:
                rel = (loo_column(p, r, m, k) - r[:, k]) / r[:, k]
            except Exception:  # a reading alike on every reference: nothing to fit
                continue
            out.append((float(np.mean(np.abs(rel))), float(np.mean(rel ** 2)), key, m))
    return out


def predict(reads: dict[str, np.ndarray], r: np.ndarray, new: dict[str, np.ndarray], how: str) -> np.ndarray:
    """d10/d50/d90 of a new image (`new`: its readings) by `how` (choice | committee) run on `reads`, `r`."""
    out = np.empty(3)
    for k in range(3):
        scores = candidate_scores(reads, r, k)
        if how == "choice":
            _, _, key, m = min(scores)
            out[k] = _column(reads[key], r, m, k, new[key])[0]
        else:
            w = np.array([1.0 / max(s2, REL_FLOOR) for _, s2, _, _ in scores])
            v = np.array([_column(reads[key], r, m, k, new[key])[0] for _, _, key, m in scores])
            out[k] = float((w * v).sum() / w.sum())
    return out


def nested_loo(reads: dict[str, np.ndarray], r: np.ndarray, how: str) -> np.ndarray:
    """Each reference predicted by `how` run on the others alone (N x 3)."""
    n = len(r)
    keep = [np.arange(n) != i for i in range(n)]
    return np.array([predict({key: p[m] for key, p in reads.items()}, r[m], {key: p[i] for key, p in reads.items()},
                             how) for i, m in enumerate(keep)])


def mape(e: np.ndarray, r: np.ndarray) -> np.ndarray:
    return 100 * np.mean(np.abs(e - r) / r, axis=0)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("readings", type=Path, nargs="+", help=".npz files of bench/calibration_basis.py --save")
    ap.add_argument("--definition", default="b-axis", help="the definition the .npz references are of (the "
                    "reading the fixed rule corrects: it, number-weighted)")
    ap.add_argument("--also", default=None, help="a second reference definition, number-weighted, read from "
                    "each scene's labels.json under --scenes")
    ap.add_argument("--scenes", type=Path, default=None, help="with --also: the folder of the .npz's scenes")
    args = ap.parse_args(argv)
    if args.also and not args.scenes:
        ap.error("--also needs --scenes (where the scenes' labels.json are)")
    from psdfactory.learn import calibration as cal
    from psdfactory.psd import definition_targets

    print(f"{'readings':<28}{'references':<12}{'fixed rule %':>20}{'choice %':>20}{'committee %':>20}")
    for path in args.readings:
        try:
            z = np.load(path)
            reads = {k: z[k] for k in z.files if "|" in k}
            sets = [(args.definition, z["reference"])]
        except (OSError, ValueError, KeyError) as e:
            ap.exit(1, f"calibration_choice.py: {path}: not an .npz of calibration_basis.py --save ({e})\n")
        if args.also:
            labels = [json.loads((args.scenes / str(s) / "labels.json").read_text()) for s in z["scenes"]]
            keys = definition_targets(args.also, "number")
            sets.append((args.also, np.array([[lab[t] for t in keys] for lab in labels], dtype=float)))
        for name, r in sets:
            fixed = mape(cal.leave_one_out(reads[f"{name}|number"], r), r)
            cells = [fixed] + [mape(nested_loo(reads, r, how), r) for how in ("choice", "committee")]
            print(f"{path.name:<28}{name:<12}" + "".join(f"{' / '.join(f'{v:4.1f}' for v in c):>20}" for c in cells))
    return 0


if __name__ == "__main__":
    sys.exit(main())
