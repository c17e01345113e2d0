#!/usr/bin/env python
"""Does a grain finder's score on a photo set hold when the photos are taken differently?

The development photos are two phone photos, each at one resolution, exposure and white balance.
Other people's photos differ in exactly those ways, so this takes each photo of a set (a folder
with labels.csv and reference masks, as data/photos/real) and makes it again as another camera or
another day would have: smaller (fewer px per grain; the mask shrunk nearest-neighbour and the
scale in labels.csv multiplied to match), darker, brighter with clipped highlights, flatter, with
a gamma, grey, with a warm cast, as a low-quality JPEG, blurred, noisy. Each variant is scored as
`psdfactory evaluate-photos` scores a photo set (the same code: `deploy.photos.evaluate_photos`),
and the script prints, per model and variant, grain F1 as drawn and against the outlines restored,
the matched grains' size error and the d50 error, beside the photos as taken.

    .venv/bin/python bench/photo_robustness.py --model results/models/instances/model.pt \
        [--photos data/photos/real] [--variants as_taken half dark jpeg25 ...] [--auto-scale|--no-auto-scale]

Measuring, not choosing: a variant that loses much says what kind of photo the model is fragile
to; nothing here is fitted to the photos. Outputs (the variants' folders, each model's metrics)
go to --work (a temporary folder by default); a later run with the same --work and the same photo set
reuses the variants made there (labels.csv, written last, marks a finished one).
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import json
import logging
import sys
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image, ImageFilter

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))


def _u8(a: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(a), 0, 255).astype(np.uint8)


def _gain(k: float):
    return lambda a: _u8(a.astype(np.float32) * k)


def _contrast(k: float):
    def f(a: np.ndarray) -> np.ndarray:
        x = a.astype(np.float32)
        return _u8(x.mean() + (x - x.mean()) * k)
    return f


def _gamma(g: float):
    return lambda a: _u8(255.0 * (a.astype(np.float32) / 255.0) ** g)


def _grey(a: np.ndarray) -> np.ndarray:
    y = a.astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)
    return _u8(np.repeat(y[..., None], 3, axis=2))


def _cast(a: np.ndarray) -> np.ndarray:
    return _u8(a.astype(np.float32) * np.array([1.15, 1.0, 0.8], np.float32))


def _blur(sigma: float):
    return lambda a: np.asarray(Image.fromarray(a).filter(ImageFilter.GaussianBlur(sigma)))


def _noise(sd: float):
    def f(a: np.ndarray) -> np.ndarray:
        rng = np.random.default_rng(0)  # the same noise on every run
        return _u8(a.astype(np.float32) + rng.normal(0.0, sd, a.shape))
    return f


# name: (what it is, pixel map or None, resize factor of the photo, JPEG quality or None)
VARIANTS = {
    "as_taken": ("the photo as it is", None, 1.0, None),
    "half": ("half the px a side (scale in labels.csv x 2)", None, 0.5, None),
    "third": ("a third of the px a side (scale x 3)", None, 1 / 3, None),
    "dark": ("exposure x 0.55", _gain(0.55), 1.0, None),
    "bright": ("exposure x 1.5, highlights clipped", _gain(1.5), 1.0, None),
    "flat": ("contrast x 0.6 about the mean", _contrast(0.6), 1.0, None),
    "gamma": ("gamma 1.6 (darker mid-tones)", _gamma(1.6), 1.0, None),
    "grey": ("grey (luma only)", _grey, 1.0, None),
    "warm": ("warm cast: red x 1.15, blue x 0.8", _cast, 1.0, None),
    "jpeg25": ("JPEG at quality 25", None, 1.0, 25),
    "blur": ("Gaussian blur, sigma 2 px of the photo", _blur(2.0), 1.0, None),
    "noise": ("Gaussian noise, sd 12 grey levels", _noise(12.0), 1.0, None),
}


def make_variant(src: Path, out: Path, name: str) -> None:
    """The photo set in `src` made again as VARIANTS[name] says, in `out` (labels.csv's scale
    column multiplied where the photos are resized; masks resized nearest-neighbour alike)."""
    from psdfactory.io import read_photo

    _, fn, factor, quality = VARIANTS[name]
    out.mkdir(parents=True, exist_ok=True)
    with open(src / "labels.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    for row in rows:
        photo = src / row["image"]
        rgb, (h, w) = read_photo(photo)  # upright, as predict reads it
        rgb = np.asarray(rgb)
        mask = np.asarray(Image.open(src / f"{photo.stem}_mask.png"))
        if factor != 1.0:
            size = (max(1, round(w * factor)), max(1, round(h * factor)))
            rgb = np.asarray(Image.fromarray(rgb).resize(size, Image.Resampling.LANCZOS))
            mask = np.asarray(Image.fromarray(mask).resize(size, Image.Resampling.NEAREST))
            row["mm_per_px"] = f"{float(row['mm_per_px']) * w / size[0]:.6g}"
        if fn is not None:
            rgb = fn(rgb)
        stem = photo.stem
        row["image"] = f"{stem}.jpg" if quality else f"{stem}.png"
        if quality:
            Image.fromarray(rgb).save(out / row["image"], quality=quality)
        else:
            Image.fromarray(rgb).save(out / row["image"])
        Image.fromarray(mask).save(out / f"{stem}_mask.png")
    with open(out / "labels.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)


def score(model: Path, folder: Path, out: Path, auto_scale: bool | None) -> dict:
    from psdfactory.deploy.photos import evaluate_photos
    from psdfactory.photoset import resolve

    spec = {"folder": str(folder), "mm_per_px": {"csv": "labels.csv", "column": "mm_per_px"},
            "masks": "{stem}_mask.png", "reference": {"csv": "labels.csv"}, "size_definition": "ellipse-minor",
            "outline_band_px": "auto"}
    if auto_scale is not None:
        spec["auto_scale"] = auto_scale
    return evaluate_photos(model, resolve(folder.name, spec), out, precision="fp32")


def figures(m: dict) -> dict:
    """Per photo (by stem): F1 as drawn, F1 restored, matched grains' median size error (%) as drawn and
    restored, d50 error (%)."""
    out = {}
    for name, r in m["photos"].items():
        rest = r.get("outlines_restored") or {}
        out[Path(name).stem] = {
            "f1": r["detection"]["f1"], "f1_restored": (rest.get("detection") or {}).get("f1"),
            "size_err": ((r.get("size_error") or {}).get("size_definition") or {}).get("median"),
            "size_err_restored": ((rest.get("size_error") or {}).get("size_definition") or {}).get("median"),
            "d50_err": (r.get("psd_rel_err") or {}).get("d50"),
        }
    return out


def _f(v, pct: bool = False) -> str:
    if v is None:
        return "—"
    return f"{100 * v:+.0f} %" if pct else f"{v:.2f}"


def output_problems(photos: Path, models: list[Path], work: Path | None, json_out: Path | None) -> list[str]:
    """What is wrong with where a run would write, before any work: --work inside the photo set (its variants would
    land among the photos) or a model file; --json a model, a file of the photo set, or inside --work."""
    from psdfactory.io import is_within, same_file

    found = []
    if work is not None:
        if is_within(work, photos):
            found.append(f"--work {work} lies in the photo set {photos}: choose a folder outside it")
        if any(same_file(work, m) for m in models):
            found.append(f"--work {work} is a --model file")
    if json_out is not None:
        if any(same_file(json_out, m) for m in models):
            found.append(f"--json {json_out} is a --model file")
        if is_within(json_out, photos):
            found.append(f"--json {json_out} lies in the photo set {photos}: choose a file outside it")
        if work is not None and is_within(json_out, work):
            found.append(f"--json {json_out} lies in --work {work}, which the run writes: choose a file outside it")
        if json_out.is_dir():
            found.append(f"--json {json_out} is a folder, not a file")
    return found


def variant_folder(work: Path, photos: Path, name: str) -> Path:
    """Where a variant of the photo set `photos` is kept in `work`: under a name of that set (its folder's name and a
    hash of its path), so that a later run with the same --work and another set makes its variants anew."""
    key = hashlib.sha1(str(photos.resolve()).encode()).hexdigest()[:8]
    return work / "photos" / f"{photos.resolve().name}-{key}" / name


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", type=Path, nargs="+", required=True)
    ap.add_argument("--photos", type=Path, default=REPO / "data/photos/real")
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--auto-scale", dest="auto_scale", action="store_true", default=None,
                    help="read every photo with the automatic scale (default: as each model reads by default)")
    ap.add_argument("--no-auto-scale", dest="auto_scale", action="store_false")
    ap.add_argument("--work", type=Path, default=None)
    ap.add_argument("--json", type=Path, default=None, help="also write every figure here")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    for m in args.model:
        if not m.is_file():
            ap.error(f"--model {m}: no such file")
    if not (args.photos / "labels.csv").is_file():
        ap.error(f"--photos {args.photos}: no labels.csv there (a photo set folder, as data/photos/real)")
    for problem in output_problems(args.photos, args.model, args.work, args.json):
        ap.error(problem)
    work = args.work or Path(tempfile.mkdtemp(prefix="photo-robustness-"))
    results: dict = {}
    for v in args.variants:
        folder = variant_folder(work, args.photos, v)
        if not (folder / "labels.csv").is_file():
            make_variant(args.photos, folder, v)
        for i, model in enumerate(args.model):
            key = f"model{i}"
            metrics = score(model, folder, work / key / v, args.auto_scale)
            results.setdefault(str(model), {})[v] = figures(metrics)
            row = results[str(model)][v]
            print(f"{v:9s} {key}: " + "; ".join(
                f"{stem} F1 {_f(r['f1'])} ({_f(r['f1_restored'])}) size {_f(r['size_err'], True)} "
                f"({_f(r['size_err_restored'], True)}) d50 {_f(r['d50_err'], True)}" for stem, r in row.items()),
                flush=True)
    print()
    for i, model in enumerate(args.model):
        print(f"model{i}: {model}")
        stems = list(next(iter(results[str(model)].values())))
        print("| variant | what | " + " | ".join(f"{s}: F1 (restored)" for s in stems) + " |")
        print("|---|---|" + "---|" * len(stems))
        for v, row in results[str(model)].items():
            print(f"| {v} | {VARIANTS[v][0]} | "
                  + " | ".join(f"{_f(row[s]['f1'])} ({_f(row[s]['f1_restored'])})" for s in stems) + " |")
        print()
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
