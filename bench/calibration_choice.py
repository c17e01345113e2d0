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

Each row's d10/d50/d90 are sorted afterwards, as `calibrate`'s corrected values are. Their error is the nested
leave-one-out: each reference predicted by the procedure run on the others alone (the choice or the weights
made again without it, from the methods N - 1 references allow); the fixed rule's is its plain leave-one-out.
Input: the .npz files `bench/calibration_basis.py --save` writes (one per model and scene set), whose references
are of the definition and weighting it was run with; --also scores a second definition too, number-weighted,
read from each scene's labels.json:

    .venv/bin/python bench/calibration_basis.py --model M --scenes /tmp/psd-paper-look/scenes \
        --mm-per-px 0.3 --subset 0 --save /tmp/r.paper.npz
    .venv/bin/python bench/calibration_choice.py /tmp/r.paper.npz
    .venv/bin/python bench/calibration_choice.py /tmp/r.test.npz --also sieve

(calibration_basis reads every scene folder under --scenes, every split alike: for one split, a folder of
links to its scenes.) Synthetic scenes only: the development photos are for measuring, never for choosing
(issue 24).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REL_FLOOR = 1e-8  # a candidate's mean squared relative error is at least this (an exact one does not divide by 0)


def methods_for(n: int) -> list[str]:
    """The corrections a choice may take at `n` references: affine, and the one `calibrate` fits there."""
    from psdfactory.learn.calibration import method_for

    return list(dict.fromkeys(["affine", method_for(n)]))


def candidates(reads: dict[str, np.ndarray], r: np.ndarray) -> list[tuple[str, str, np.ndarray]]:
    """(reading, method, N x 3 relative leave-one-out errors) of every candidate that can be fitted on `r`."""
    from psdfactory import PsdError
    from psdfactory.learn import calibration as cal

    out = []
    for key, p in reads.items():
        if not np.isfinite(p).all():
            continue
        for m in methods_for(len(r)):
            try:
                out.append((key, m, (cal.leave_one_out(p, r, m) - r) / r))
            except PsdError:  # a reading alike on every reference: nothing to fit
                continue
    return out


def predict(reads: dict[str, np.ndarray], r: np.ndarray, new: dict[str, np.ndarray], how: str) -> np.ndarray:
    """d10/d50/d90 (sorted) of a new image (`new`: its readings) by `how` (choice | committee) run on `reads`, `r`."""
    from psdfactory import PsdError
    from psdfactory.learn import calibration as cal

    cands = [c for c in candidates(reads, r) if np.isfinite(new[c[0]]).all()]
    if not cands:
        raise PsdError(f"no reading can be calibrated on these {len(r)} references")
    corrected = {(key, m): cal.apply(cal.fit(reads[key], r, m), new[key]) for key, m, _ in cands}
    out = np.empty(3)
    for k in range(3):
        if how == "choice":
            key, m, _ = min(cands, key=lambda c: float(np.mean(np.abs(c[2][:, k]))))
            out[k] = corrected[(key, m)][k]
        else:
            w = np.array([1.0 / max(float(np.mean(c[2][:, k] ** 2)), REL_FLOOR) for c in cands])
            v = np.array([corrected[(key, m)][k] for key, m, _ in cands])
            out[k] = float((w * v).sum() / w.sum())
    return np.sort(out)


def nested_loo(reads: dict[str, np.ndarray], r: np.ndarray, how: str) -> np.ndarray:
    """Each reference predicted by `how` run on the others alone (N x 3)."""
    n = len(r)
    keep = [np.arange(n) != i for i in range(n)]
    return np.array([predict({key: p[m] for key, p in reads.items()}, r[m], {key: p[i] for key, p in reads.items()},
                             how) for i, m in enumerate(keep)])


def fixed_basis(reads: dict[str, np.ndarray], definition: str, weighting: str) -> str:
    """The reading `psdfactory calibrate` corrects for references of `definition`, `weighting` (`basis_for`)."""
    from psdfactory import PsdError
    from psdfactory.learn import calibration as cal

    basis = cal.basis_for({"size_definition": definition, "weighting": weighting},
                          lambda d, w: f"{d}|{w}" in reads, lambda d: "number")
    key = f"{basis['size_definition']}|{basis['weighting']}"
    if key not in reads:
        raise PsdError(f"no reading {key} (the one calibrate corrects for {definition} {weighting}-weighted "
                       f"references) among {', '.join(sorted(reads))}")
    return key


def load(path: Path, also: str | None) -> tuple[dict[str, np.ndarray], list[tuple[str, str, np.ndarray]]]:
    """A --save file's readings and its reference sets: [(definition, weighting, N x 3)], --also's added."""
    from psdfactory import PsdError
    from psdfactory.io import read_npz
    from psdfactory.psd import definition_targets

    try:
        z = read_npz(path)
    except PsdError as e:
        raise PsdError(f"{e} (not the .npz of calibration_basis.py --save?)") from None
    missing = [k for k in ("reference", "scenes", "definition", "weighting") if k not in z]
    reads = {k: v for k, v in z.items() if "|" in k}
    if missing or not reads:
        raise PsdError(f"{path}: not an .npz of calibration_basis.py --save (missing: "
                       f"{', '.join(missing) or 'the readings'})")
    sets = [(str(z["definition"]), str(z["weighting"]), z["reference"])]
    if also:
        keys, rows = definition_targets(also, "number"), []
        for scene in z["scenes"]:
            labels = Path(str(scene)) / "labels.json"
            try:
                lab = json.loads(labels.read_text())
                rows.append([float(lab[t]) for t in keys])
            except (OSError, ValueError, KeyError, TypeError) as e:
                raise PsdError(f"--also {also}: {labels}: no {', '.join(keys)} ({type(e).__name__}: {e})") from None
        sets.append((also, "number", np.array(rows)))
    return reads, sets


def mape(e: np.ndarray, r: np.ndarray) -> np.ndarray:
    return 100 * np.mean(np.abs(e - r) / r, axis=0)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("readings", type=Path, nargs="+", help=".npz files of bench/calibration_basis.py --save")
    ap.add_argument("--also", default=None, help="a second reference definition, number-weighted, read from "
                    "each scene's labels.json (the .npz records where the scenes are)")
    args = ap.parse_args(argv)
    from psdfactory import PsdError
    from psdfactory.learn import calibration as cal

    print(f"{'readings':<28}{'references':<20}{'fixed rule %':>20}{'choice %':>20}{'committee %':>20}")
    for path in args.readings:
        try:
            reads, sets = load(path, args.also)
            for definition, weighting, r in sets:
                fixed = mape(cal.leave_one_out(reads[fixed_basis(reads, definition, weighting)], r), r)
                cells = [fixed] + [mape(nested_loo(reads, r, how), r) for how in ("choice", "committee")]
                print(f"{path.name:<28}{definition + ' ' + weighting:<20}"
                      + "".join(f"{' / '.join(f'{v:4.1f}' for v in c):>20}" for c in cells))
        except PsdError as e:
            ap.exit(1, f"calibration_choice.py: {e}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
