#!/usr/bin/env python
"""How well could a grain finder find a photo set's grains if it read each photo at the best scale?

`predict --auto-scale` picks one scale per photo from the network's own size map (docs/photos.md,
"Grains larger than the model's"). This sweeps the scale instead: each photo is scored as
`psdfactory evaluate-photos` scores it, read without the automatic scale at forced factors f of the
model's scale (the photo given f x its mm per px, so the network sees it f x as many px smaller as
at its true scale). Only the grain detection is comparable between factors: every size read at a
forced factor is off by it. Printed per photo and factor: precision / recall / F1 as drawn and,
where the set declares an outline band, against its outlines restored; then the automatic scale's
own reading (the factor it picks, from its log, and its F1), and the best factor's F1: what a
perfect scale choice would give this model, the ceiling of any change to how the scale is chosen.

    .venv/bin/python bench/photo_scales.py --model results/models/instances/model.pt \
        [--config config/config.yaml] [--photoset real] [--factors 0.18 0.25 0.36 0.5 0.7 1]

The development photos are for measuring, never for choosing (issue 24): a factor picked here by
its score would be tuned to these photos. Outputs go to --work (a temporary folder by default),
under a name of the model file, and are read again there by a later run with the same model.
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import json
import math
import re
import subprocess
import sys
import tempfile
from pathlib import Path

FACTORS = (0.18, 0.25, 0.36, 0.5, 0.7, 1.0)


def check_run(model: Path, factors: list[float], work: Path | None, photo_folder: Path) -> list[str]:
    """What is wrong with a run, before any work: a model file that is not there, a factor that is not a
    finite number in (0, 4], a --work that is the model or lies in the photo set's folder (its copies of
    the scale CSV and its readings would mix with the photos)."""
    problems = []
    if not model.is_file():
        problems.append(f"--model {model}: no such file")
    bad = [f for f in factors if not (math.isfinite(f) and 0 < f <= 4)]
    if bad:
        problems.append(f"--factors {' '.join(map(str, bad))}: give factors of the model's scale in (0, 4]")
    if work is not None:
        w, folder = work.resolve(), photo_folder.resolve()
        if w == model.resolve():
            problems.append(f"--work {work} is the model file")
        elif w == folder or folder in w.parents:
            problems.append(f"--work {work} lies in the photo set's folder {photo_folder}: give another folder")
    return problems


def model_key(model: Path) -> str:
    """A short name for this model file as it is now (path, size, modification time): the readings
    kept in --work are read again only for the same file."""
    st = model.stat()
    return hashlib.sha1(f"{model.resolve()}|{st.st_size}|{st.st_mtime_ns}".encode()).hexdigest()[:10]


def photo_set_at(params: dict, factor: float, work: Path) -> dict:
    """The photo set's params with every photo's mm per px multiplied by `factor` (a copy of its CSV
    in `work` where the scale comes from one), its folder and CSV paths made absolute."""
    p = json.loads(json.dumps(params))
    folder = Path(p["folder"]).resolve()
    p["folder"] = str(folder)
    if isinstance(p.get("reference"), dict) and "csv" in p["reference"]:
        p["reference"]["csv"] = str((folder / p["reference"]["csv"]).resolve())
    scale = p["mm_per_px"]
    if isinstance(scale, dict):
        src = folder / scale["csv"]
        out = work / f"scale_{factor:g}.csv"
        with open(src, newline="", encoding="utf-8") as f:
            rows = list(csv.DictReader(f))
        with open(out, "w", newline="", encoding="utf-8") as f:
            w = csv.DictWriter(f, fieldnames=list(rows[0]))
            w.writeheader()
            for r in rows:
                r[scale["column"]] = repr(float(r[scale["column"]]) * factor)
                w.writerow(r)
        p["mm_per_px"] = {"csv": str(out), "column": scale["column"]}
    else:
        p["mm_per_px"] = float(scale) * factor
    p["auto_scale"] = False
    return p


def evaluate(model: Path, params: dict, out: Path, precision: str) -> tuple[dict, str]:
    """evaluate-photos' metrics.json and log for one reading of the set (kept in `out` and read again)."""
    if not (out / "metrics.json").is_file():
        out.mkdir(parents=True, exist_ok=True)
        cmd = [str(Path(sys.executable).with_name("psdfactory")), "--log", str(out / "log"), "evaluate-photos",
               "--params", json.dumps({"photoset": params, "precision": precision}), "--model", str(model),
               "--out-dir", str(out)]
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return json.loads((out / "metrics.json").read_text(encoding="utf-8")), (out / "log").read_text(encoding="utf-8")


def detection(p: dict) -> tuple[str, float]:
    """A photo's P / R / F1 as drawn (and F1 against its outlines restored, where scored), and its F1."""
    d = p["detection"]
    r = (p.get("outlines_restored") or {}).get("detection")
    return f"{d['precision']:.2f} / {d['recall']:.2f} / {d['f1']:.3f}" + (f" ({r['f1']:.3f})" if r else ""), d["f1"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", required=True, type=Path)
    ap.add_argument("--config", type=Path, default=Path("config/config.yaml"))
    ap.add_argument("--photoset", default="real", help="the config's photo set (default: real)")
    ap.add_argument("--factors", nargs="+", type=float, default=list(FACTORS), help="of the model's scale")
    ap.add_argument("--precision", default="auto")
    ap.add_argument("--work", type=Path, help="where the readings are kept (default: a temporary folder)")
    a = ap.parse_args()

    from psdfactory import config as psd_config

    params = psd_config.photo_params(psd_config.load_config(a.config), a.photoset)
    if problems := check_run(a.model, a.factors, a.work, Path(params["folder"])):
        raise SystemExit("photo_scales.py: " + "; ".join(problems))
    work = (a.work or Path(tempfile.mkdtemp(prefix="photo_scales_"))) / model_key(a.model)
    work.mkdir(parents=True, exist_ok=True)
    auto = photo_set_at(params, 1.0, work) | {"auto_scale": True}  # as the photo set reads them with this model
    m_auto, log_auto = evaluate(a.model, auto, work / "auto", a.precision)
    rows: dict[str, list[str]] = {}
    best: dict[str, tuple[float, float]] = {}
    for f in a.factors:
        m, _ = evaluate(a.model, photo_set_at(params, f, work), work / f"f{f:g}", a.precision)
        for name, p in m["photos"].items():
            text, f1 = detection(p)
            rows.setdefault(name, []).append(f"| {f:g} | {text} |")
            if f1 > best.get(name, (None, -1.0))[1]:
                best[name] = (f, f1)
    print(f"{a.model}: photo set {a.photoset!r}; precision / recall / F1 as drawn (restored)\n")
    for name, lines in rows.items():
        picked = re.findall(rf"{re.escape(name)}: its grains look .*? read at ([0-9.]+) x", log_auto)
        text, f1 = detection(m_auto["photos"][name])
        print(f"{name}\n\n| factor of the model's scale | P / R / F1 |\n|---|---|")
        print("\n".join(lines))
        print(f"| automatic scale ({picked[0] if picked else '1'}) | {text} |")
        print(f"\nbest factor {best[name][0]:g}: F1 {best[name][1]:.3f}, the automatic scale {f1:.3f}\n")


if __name__ == "__main__":
    main()
