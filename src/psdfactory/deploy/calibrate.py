"""``psdfactory calibrate``: a model calibrated against reference samples — images whose d10/d50/d90
were measured another way (a sieve analysis, a laser diffraction) — as camera PSD instruments are
calibrated in plants and in the field. The math (fit, leave-one-out, the meta block) is
`learn.calibration`; this module reads the references, matches them to the images, predicts the
images with the model as `psdfactory predict` does and writes the calibrated model file."""

from __future__ import annotations

import csv
import datetime
import logging
import math
from pathlib import Path

import numpy as np

from .. import PsdError, __version__
from ..io import same_file
from ..learn import calibration as cal
from ..photoset import Region
from ..psd import NAMES, TARGETS, check_grain_weighting
from .predict import describe_model, image_files, load_predictor, predict_one, reading

logger = logging.getLogger(__name__)
COLUMNS = ("image", *TARGETS)
MAX_REFERENCE_BYTES = 20_000_000  # a reference table far bigger than this is not one


def read_references(path: Path) -> tuple[list[str], np.ndarray]:
    """REF.csv (``image,d10_mm,d50_mm,d90_mm``; other columns ignored, blank lines skipped) →
    (image names, N x 3 values), checked (`learn.calibration.check_references`): each problem one
    line naming the file and the rows."""
    path = Path(path)
    where = f"--reference {path}"
    if not path.is_file():
        raise PsdError(f"{where}: file not found" if not path.exists() else f"{where} is not a file")
    if path.stat().st_size > MAX_REFERENCE_BYTES:
        raise PsdError(f"{where}: {path.stat().st_size} bytes is far more than a table of reference samples holds")
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            reader = csv.reader(f)
            header = [h.strip() for h in next(reader, [])]
            rows = [(i, r) for i, r in enumerate(reader, start=2) if any(c.strip() for c in r)]
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise PsdError(f"{where}: cannot read it as CSV ({e})") from None
    missing = [c for c in COLUMNS if c not in header]
    if missing:
        found = ", ".join(h for h in header if h) or "nothing"
        raise PsdError(f"{where}: missing column(s) {', '.join(missing)} (found: {found}); the header must name "
                       f"{','.join(COLUMNS)}")
    dup = sorted({h for h in header if header.count(h) > 1 and h in COLUMNS})
    if dup:
        raise PsdError(f"{where}: the column(s) {', '.join(dup)} appear twice in the header")
    col = {c: header.index(c) for c in COLUMNS}
    names, values = [], []
    for line, r in rows:
        cells = {c: (r[k].strip() if k < len(r) else "") for c, k in col.items()}
        if not cells["image"]:
            raise PsdError(f"{where}, line {line}: no image name")
        row = []
        for t in TARGETS:
            try:
                row.append(float(cells[t]))
            except ValueError:
                shown = repr(cells[t]) if cells[t] else "empty"
                raise PsdError(f"{where}, line {line} ({cells['image']}): {t} is {shown}, not a number of mm") from None
        names.append(cells["image"])
        values.append(row)
    values = np.array(values, dtype=float).reshape(-1, len(TARGETS))
    cal.check_references(names, values, where)
    return names, values


def _shown(items: list[str], limit: int = 8) -> str:
    return ", ".join(items[:limit]) + (f" and {len(items) - limit} more" if len(items) > limit else "")


def match_images(names: list[str], files: list[Path], reference_csv: Path | None = None) -> list[Path]:
    """The image of each reference name: matched by path (as given, or relative to the reference
    table's folder), else by file name, else by stem. Refused in one line, naming both sides, unless
    references and images match one-to-one."""
    resolved = [f.resolve() for f in files]
    twice = sorted({str(f) for f, r in zip(files, resolved, strict=True) if resolved.count(r) > 1})
    if twice:
        raise PsdError(f"images given more than once: {_shown(twice)}")
    by_resolved = dict(zip(resolved, files, strict=True))
    found: dict[str, Path] = {}
    ambiguous, unclear = [], set()
    for name in names:
        p = Path(name)
        places = [p] + ([reference_csv.parent / p] if reference_csv is not None and not p.is_absolute() else [])
        hit = next((by_resolved[q.resolve()] for q in places if q.resolve() in by_resolved), None)
        if hit is None:
            for keys in ((p.name,), (p.name, p.stem)):  # by file name, else by stem
                hits = [f for f in files if (f.name if len(keys) == 1 else f.stem) in keys]
                if len(hits) > 1:
                    ambiguous.append(f"{name} ({len(hits)} images: {_shown([str(h) for h in hits], 3)})")
                    unclear.add(name)
                    break
                if hits:
                    hit = hits[0]
                    break
        if hit is not None:
            found[name] = hit
    no_image = [n for n in names if n not in found and n not in unclear]
    used: dict[Path, list[str]] = {}
    for n, f in found.items():
        used.setdefault(f, []).append(n)
    no_reference = [str(f) for f in files if f not in used]
    shared = [f"{f} ({', '.join(ns)})" for f, ns in used.items() if len(ns) > 1]
    parts = [f"references with no image: {_shown(no_image)}" if no_image else "",
             f"images with no reference: {_shown(no_reference)}" if no_reference else "",
             f"images matched by more than one reference: {_shown(shared)}" if shared else "",
             f"references matching several images (give their paths): {_shown(ambiguous)}" if ambiguous else ""]
    parts = [p for p in parts if p]
    if parts:
        raise PsdError(f"the references and the images do not match one-to-one: {'; '.join(parts)} (a reference's "
                       "image is matched by its path, else by file name, else by file name without suffix)")
    return [found[n] for n in names]


def check_out(out: Path, model: Path, reference: Path, inputs: list[str]) -> None:
    """Refuse, before any work, an --out that is not a .pt file or that is the model, the
    reference table or an input image; and a model that is not a model.pt."""
    out, model = Path(out), Path(model)
    if model.suffix.lower() == ".onnx":
        raise PsdError(f"--model {model}: calibrate a model.pt (training's), then export the calibrated model: "
                       "its meta.json carries the calibration to the ONNX model")
    if out.is_dir():
        raise PsdError(f"--out {out} is a folder; give a file name")
    if same_file(out, model):
        raise PsdError(f"--out {out} is the model: write the calibrated model to another file (the uncalibrated "
                       "one stays as it is)")
    if same_file(out, reference):
        raise PsdError(f"--out {out} is the reference table: choose another file")
    hit = next((f for f in image_files(inputs) if same_file(out, f)), None)
    if hit is not None:
        raise PsdError(f"--out {out} is the input image {hit}: choose another file")
    if out.suffix.lower() != ".pt":
        raise PsdError(f"--out {out}: must end in .pt (the calibrated model file)")


def references_reading(est, size_definition: str | None, weighting: str | None) -> tuple[dict, dict]:
    """(what the references are of, the model's reading the correction takes: `cal.basis_for`). The
    references' definition must be one the model reads (default: its own), their weighting one of
    `psd.GRAIN_WEIGHTINGS` (default: the model's weighting of that definition)."""
    meta = est.meta
    wanted = reading(meta, size_definition)  # the definition, refused where the model cannot read it
    if weighting is not None:
        check_grain_weighting(weighting)
        wanted = {**wanted, "weighting": weighting}
    basis = cal.basis_for(wanted, lambda d, w: est.reads(meta, d, w), lambda d: reading(meta, d)["weighting"])
    return wanted, basis


def calibrate(model_path: Path, reference: Path, inputs: list[str], out: Path, mm_per_px: float | None = None,
              size_definition: str | None = None, device: str = "cpu", auto_scale: bool | None = None,
              weighting: str | None = None, roi: Region | None = None) -> dict:
    """Predict the reference images with the model (uncalibrated: a calibrated model's own
    correction is left out and replaced), fit the correction (`learn.calibration`) and write the
    model with it in its meta to `out` (the same weights). `size_definition`, `weighting`: what the
    references are of (`references_reading`). `auto_scale`: read them as predict --auto-scale /
    --no-auto-scale does (None: the model's default); the block records which. `roi`: the part of
    every reference image to read (predict --roi); the block records it.
    → the calibration block."""
    from ..learn.runtime import load_checkpoint, meta_problems, write_torch

    model_path, reference, out = Path(model_path), Path(reference), Path(out)
    check_out(out, model_path, reference, inputs)
    names, values = read_references(reference)
    files = match_images(names, image_files(inputs), reference)
    est = load_predictor(model_path, device)
    if auto_scale is not None:
        est.auto_scale = bool(auto_scale)
    old = est.meta.get("calibration")
    est.meta = {k: v for k, v in est.meta.items() if k != "calibration"}  # its readings before any correction
    if old is not None:
        logger.warning(f"{model_path} is calibrated already ({old['n']} references, {old['date']}): the new "
                       "calibration replaces that one, fitted on the model's uncalibrated readings")
    what, basis = references_reading(est, size_definition, weighting)
    for line in describe_model(est.meta, model_path, mm_per_px):
        logger.info(line)
    logger.info(f"predicting {len(files)} reference images: d10/d50/d90 of the {basis['size_definition']} size, "
                f"{basis['weighting']}-weighted")
    if basis != what:
        logger.info(f"the references are of the {what['size_definition']} size, {what['weighting']}-weighted, which "
                    f"this {est.meta['arch']} model does not read: the correction maps its {basis['size_definition']} "
                    f"reading, {basis['weighting']}-weighted, to them (docs/calibration.md)")
    rows = [predict_one(est, f, mm_per_px, what=basis, roi=roi) for f in files]
    failed = [r["error"] for r in rows if r["error"]]
    if failed:
        raise PsdError(f"{len(failed)} of {len(rows)} reference images failed to predict, so the model cannot be "
                       f"calibrated on them: {'; '.join(failed[:5])}{' ...' if len(failed) > 5 else ''}")
    predicted = np.array([[r[t] for t in TARGETS] for r in rows], dtype=float)
    date = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")
    block = cal.calibration_block(names, predicted, values, what["size_definition"], what["weighting"], mm_per_px,
                                  date, __version__, basis=basis)
    for ref, f in zip(block["references"], files, strict=True):
        ref["file"] = str(f)
    if est.finds_grains and mm_per_px is not None:  # how its photos were read (without a scale: at the model's
        block["auto_scale"] = bool(est.auto_scale)  # scale either way); predict warns where it reads them otherwise
    if roi is not None:
        block["roi"] = str(roi)
    for line in cal.calibration_warnings(block):
        logger.warning(line)
    ckpt = load_checkpoint(model_path)
    meta = {**ckpt["meta"], "calibration": block}
    if "auto_scale" in block:  # the calibrated model reads photos as its references were read, unless told otherwise
        meta["auto_scale"] = block["auto_scale"]
    problems = meta_problems(meta)
    if problems:  # what predict would refuse: never written
        raise PsdError(f"the calibrated model's meta is refused: {'; '.join(problems)}")
    try:
        write_torch(out, {**ckpt, "meta": meta})
    except OSError as e:
        raise PsdError(f"--out {out}: cannot write it ({e.strerror or e})") from None
    logger.info(f"wrote {out}: {model_path} with its calibration ({block['method']}, {block['n']} references)")
    return block


def table_lines(block: dict) -> list[str]:
    """The calibration's errors on the references, per target: uncalibrated beside calibrated
    (leave-one-out: each reference corrected by the fit on the others)."""
    def pct(v: float) -> str:
        return f"{v:>8.1f}" if math.isfinite(v) else f"{'-':>8}"

    lines = [f"calibration on {block['n']} references: {block['method']} correction per target, "
             f"{block['size_definition']} size, {block['weighting']}-weighted{cal.basis_phrase(block)}",
             f"{'':<8}{'uncalibrated':>20}   {'calibrated (leave-one-out)':>26}",
             f"{'target':<8}{'MAPE %':>10}{'MAE mm':>10}   {'MAPE %':>16}{'MAE mm':>10}"]
    for name in NAMES:
        u, c = block["uncalibrated"][name], block["loo"][name]
        lines.append(f"{name:<8}{pct(u['mape_pct']):>10}{u['mae_mm']:>10.3f}   {pct(c['mape_pct']):>16}"
                     f"{c['mae_mm']:>10.3f}")
    return lines
