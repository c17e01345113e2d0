"""``psdfactory evaluate-photos``: a trained model on a photo set (the config's `photos`) —
labelled photographs, read as `psdfactory predict` reads a photo (at its mm per px, resized to
the model's scale, tile by tile where it is large; a calibrated model's correction applied, in the
definition and weighting it was calibrated to), scored against the set's reference masks and d10/d50/d90.

What is measured, per photo and pooled over the set:

- **detection** (a model that finds grains, where the set has masks): precision / recall / F1
  of the grains found against the reference grains, matched one-to-one at IoU >= 0.5, with the
  border rule of `learn.instances.scoring.BorderMatch` (the reference leaves out the grains the
  image border cuts: so are they here; a grain found on the border counts only if it matches a
  reference grain). Compared at the **photo's resolution**: the estimator's instance mask (at
  its network scale) is resized nearest-neighbour to the photo's size, so the reference stays
  exactly the peer's grains (resizing the reference instead would merge or drop its smallest
  grains); whether a found grain touches the border is the estimator's own call, on its mask.
  What the misses are (`error_kinds`): each reference grain not matched as cut into pieces,
  merged into one found grain with a neighbour, missed or misfit, and each found grain not
  matched as a merge of several, on the reference's background, a piece of one or a misfit
  (photos.csv: `fn_<kind>`, `fp_<kind>`).
- **grain size error** of the matched grains not touching the border: median and p90 of
  |est − ref| / ref, of the grain's size in the set's size definition (both measured the same
  way, by `learn.instances.measure`: ours on the estimator's mask at its scale, the reference's
  on its mask at the photo's) and of the estimator's sieve-size estimate against the same
  reference size.
- **PSD**: d10/d50/d90 in the set's size definition, number-weighted 'hazen' percentiles of the
  grains found not touching the border, and their relative error against the reference's
  (its CSV; without one, the same percentiles of its masks' grains). A model that finds no
  grains (a CNN) gives its own reading only, in its own size definition (a calibrated one: its
  calibration's definition and weighting): compared with the reference all the same, the
  definitions named beside the figures (photos.csv: `reading_size_definition`, `reading_weighting`).

Where the set declares an outline band (`outline_band_px`: the reference masks keep that much
background between grains that touch, as segmenteverygrain's do), every figure is given again
against the reference grains grown by half of it (`outlines_restored`, `pooled_outlines_restored`).

Nothing here is fitted or chosen on the photos: the model's own post-processing and read-out run
as they are; the band is read off the reference masks alone.
"""

from __future__ import annotations

import csv
import logging
from pathlib import Path

import numpy as np

from .. import PsdError
from ..io import atomic_path, open_image, read_photo, write_json
from ..learn.estimator import Estimator, Reading, reading_of
from ..learn.instances.scoring import FN_KINDS, FP_KINDS
from ..photoset import Photo, PhotoSet
from ..psd import NAMES, weighted_percentiles
from .predict import (
    DEFAULT_TILE_PX,
    corrected_reading,
    grain_count_problem,
    load_predictor,
    network_scale,
    not_a_psd_warning,
    read_at_scale,
    say_warnings,
    target_size,
)

logger = logging.getLogger(__name__)

IOU = 0.5
# a size definition of a photo set → the measurement (learn.instances.measure) that gives it
MEASURE_OF = {"ellipse-minor": "ellipse_minor_mm", "feret-min": "min_feret_mm", "feret-max": "max_feret_mm",
              "ecd": "eq_diameter_mm"}
OVERLAY_MAX_PX = 800  # the overlay's long side: legible beside the report's 1000 px page
FOUND_RGB = (255, 214, 0)  # outlines of the grains a model found
REFERENCE_RGB = (0, 190, 255)  # outlines of the reference grains
CAPTION_PX = 15  # the overlay caption's font size


def read_mask(path: Path, size_hw: tuple[int, int]) -> np.ndarray:
    """A reference instance mask (single-channel integer PNG) as int64, checked against its photo's size."""
    with open_image(path) as img:
        img.load()
        m = np.asarray(img)
    if m.ndim != 2 or not np.issubdtype(m.dtype, np.integer):
        raise PsdError(f"{path} is not an instance mask (one channel of integer ids), got {m.dtype} {m.shape}")
    if m.shape != tuple(size_hw):
        raise PsdError(f"{path} is {m.shape[1]} x {m.shape[0]} px, its photo {size_hw[1]} x {size_hw[0]} px")
    return m.astype(np.int64)


def percentiles(sizes: np.ndarray) -> np.ndarray:
    """Number-weighted d10/d50/d90 (numpy's 'hazen'); NaN without a grain."""
    return weighted_percentiles(sizes, None) if len(sizes) else np.full(3, np.nan)


def relative(est: np.ndarray, ref: np.ndarray | None) -> list[float | None]:
    if ref is None:
        return [None] * 3
    return [float((e - r) / r) if np.isfinite(e) else None for e, r in zip(est, ref, strict=True)]


def _d(values) -> dict:
    return {n: (None if v is None or not np.isfinite(v) else float(v)) for n, v in zip(NAMES, values, strict=True)}


def detection(tp: int, fp: int, fn: int, left_out_pred: int, left_out_true: int) -> dict:
    """Counts of a BorderMatch (or a sum of them) as precision / recall / F1 (NaN where undefined)."""
    from ..learn.instances.scoring import f1_score

    nan = float("nan")
    return {"iou": IOU, "tp": tp, "fp": fp, "fn": fn, "left_out_found": left_out_pred,
            "left_out_reference": left_out_true, "precision": tp / (tp + fp) if tp + fp else nan,
            "recall": tp / (tp + fn) if tp + fn else nan, "f1": f1_score(tp, tp + fp, tp + fn)}


class PhotoScorer:
    """One model on one photo set: `add` per photo (its figures), `pooled` at the end. With
    `outlines_restored` it scores against each reference mask's grains grown by half its outline
    band (the set's `outline_band_px`, or the mask's own where that says auto:
    `learn.instances.scoring.outline_band_px`, `restore_outlines`): the same reference grains as
    drawn (the border rule decided on the mask as drawn), their d-values measured on the grown
    mask, not the CSV's (which are of the grains as drawn)."""

    def __init__(self, est: Estimator, photos: PhotoSet, outlines_restored: bool = False):
        self.est, self.set, self.outlines_restored = est, photos, outlines_restored
        self.measure = MEASURE_OF[photos.size_definition]
        self.counts = np.zeros(5, np.int64)  # tp, fp, fn, left out found, left out reference
        # the FN and FP of every photo by kind, summed (error_kinds)
        self.kinds = {"fn": dict.fromkeys(FN_KINDS, 0), "fp": dict.fromkeys(FP_KINDS, 0)}
        self.pairs: dict[str, list] = {"est": [], "sieve": [], "ref": []}
        self.psd_err: list[list[float | None]] = []

    def reference_of(self, photo: Photo, rm, on_border: np.ndarray | None = None
                     ) -> tuple[np.ndarray | None, str | None]:
        """The photo's reference d10/d50/d90 and where they come from (its CSV, else its mask's
        grains, `rm` its measurements, not on the border: those of `on_border`, ids, where given)."""
        if photo.reference_mm is not None and not self.outlines_restored:
            return np.asarray(photo.reference_mm, float), "csv"
        if rm is None:
            return None, None
        edge = rm.touches_edge if on_border is None else np.isin(rm.ids, on_border)
        return percentiles(getattr(rm, self.measure)[~edge]), "mask"

    def add(self, photo: Photo, reading, ref_mask: np.ndarray | None) -> dict:
        """A photo's figures against its reference mask as drawn (restored here where the scorer
        restores outlines)."""
        from ..learn.instances.measure import measure_instances
        from ..learn.instances.scoring import border_ids, outline_band_px, restore_outlines

        band = on_border = None
        if self.outlines_restored and ref_mask is not None:
            band = self.set.outline_band_px
            band = outline_band_px(ref_mask) if band == "auto" else float(band)
            on_border = border_ids(ref_mask)
            ref_mask = restore_outlines(ref_mask, band)
        # the reference grains measured once: for its d-values (no CSV, or outlines restored) and the size pairs
        need = ref_mask is not None and (self.est.finds_grains or photo.reference_mm is None or self.outlines_restored)
        rm = measure_instances(ref_mask, photo.mm_per_px) if need else None
        ref, source = self.reference_of(photo, rm, on_border)
        row: dict = {"reference_mm": _d(ref) if ref is not None else None, "reference_from": source,
                     "reading_mm": _d(reading.d_mm), "reading_rel_err": _d(relative(reading.d_mm, ref))}
        if band is not None:
            row["band_px"] = band
        if not self.est.finds_grains:
            row["psd_mm"], row["psd_rel_err"] = row["reading_mm"], row["reading_rel_err"]
            self.psd_err.append(relative(reading.d_mm, ref))
            return row
        from ..learn.instances.draw import resize_mask
        from ..learn.instances.scoring import error_kinds, match_off_border, size_errors

        res = reading.grains
        m = res.measurements
        size = getattr(m, self.measure)
        off = ~m.touches_edge
        psd = percentiles(size[off])
        self.psd_err.append(relative(psd, ref))
        row.update(psd_mm=_d(psd), psd_rel_err=_d(relative(psd, ref)), n_found=len(m),
                   n_found_off_border=int(off.sum()))
        if ref_mask is None:
            return row
        pred = resize_mask(res.mask, ref_mask.shape)  # compared at the photo's resolution
        bm = match_off_border(pred, ref_mask, IOU, pred_on_border=m.ids[m.touches_edge], true_on_border=on_border)
        counts = (bm.tp, bm.fp, bm.fn, bm.left_out_pred, bm.left_out_true)
        self.counts += counts
        ek = error_kinds(pred, ref_mask, bm)
        kinds = {"fn": ek.fn, "fp": ek.fp}
        for side, by_kind in kinds.items():
            for kind, n in by_kind.items():
                self.kinds[side][kind] += n
        ref_size = np.full(int(rm.ids.max(initial=0)) + 1, np.nan)
        ref_size[rm.ids] = getattr(rm, self.measure)
        k = np.searchsorted(m.ids, bm.pred_ids)
        inner = off[k]  # a found grain the border cuts is measured cut: not a size pair
        pairs = {"est": size[k[inner]], "sieve": res.sizes_mm[k[inner]], "ref": ref_size[bm.true_ids[inner]]}
        for key, v in pairs.items():
            self.pairs[key] += v.tolist()
        row.update(n_reference=int(bm.tp + bm.fn), detection=detection(*counts), error_kinds=kinds,
                   size_error={"size_definition": size_errors(pairs["est"], pairs["ref"]),
                               "sieve": size_errors(pairs["sieve"], pairs["ref"])})
        return row

    def pooled(self) -> dict:
        from ..learn.instances.scoring import size_errors

        err = np.array([[np.nan if v is None else abs(v) for v in e] for e in self.psd_err], float)
        have = np.isfinite(err)
        out = {"psd_abs_rel_err": _d([np.mean(err[have[:, j], j]) if have[:, j].any() else None
                                      for j in range(3)])}
        if self.est.finds_grains and self.set.has_masks:
            out["detection"] = detection(*map(int, self.counts))
            out["error_kinds"] = self.kinds
            out["size_error"] = {"size_definition": size_errors(self.pairs["est"], self.pairs["ref"]),
                                 "sieve": size_errors(self.pairs["sieve"], self.pairs["ref"])}
        return out


def overlay(image: np.ndarray, ref_mask: np.ndarray | None, found_mask: np.ndarray | None, caption: str) -> np.ndarray:
    """The photo at most OVERLAY_MAX_PX on its long side, the reference grains outlined in
    REFERENCE_RGB and the grains found in FOUND_RGB over them, under a caption band."""
    from PIL import Image, ImageDraw, ImageFont

    from ..learn.instances.draw import instance_outlines, resize_mask

    h, w = image.shape[:2]
    f = min(1.0, OVERLAY_MAX_PX / max(h, w))
    dh, dw = max(1, round(h * f)), max(1, round(w * f))
    img = np.array(Image.fromarray(image).resize((dw, dh), Image.Resampling.LANCZOS))
    for mask, rgb in ((ref_mask, REFERENCE_RGB), (found_mask, FOUND_RGB)):
        if mask is not None:
            img[instance_outlines(resize_mask(mask, (dh, dw)))] = rgb
    font = ImageFont.load_default(size=CAPTION_PX)
    measure = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    lines: list[str] = []
    for part in caption.split(" · "):  # as many parts a line as fit the width
        joined = f"{lines[-1]} · {part}" if lines else part
        if lines and measure.textlength(joined, font=font) <= dw - 12:
            lines[-1] = joined
        else:
            lines.append(part)
    step = CAPTION_PX + 4
    band = Image.new("RGB", (dw, step * len(lines) + 6), (255, 255, 255))
    draw = ImageDraw.Draw(band)
    for i, line in enumerate(lines):
        draw.text((6, 4 + i * step), line, fill=(0, 0, 0), font=font)
    return np.concatenate([np.asarray(band), img], axis=0)


def write_overlay(path: Path, rgb: np.ndarray) -> None:
    """An overlay as a 256-colour PNG (a third of the bytes of an RGB one, for the report to embed)."""
    from PIL import Image

    img = Image.fromarray(rgb).quantize(256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        img.save(tmp, format="PNG", optimize=True)


def _caption(arch: str, photo: Photo, row: dict, definition: str) -> str:
    parts = [f"{photo.name} · {arch}"]
    if "detection" in row:
        d = row["detection"]
        parts.append(f"yellow: found ({d['tp']} matched, {d['fp']} not) · blue: reference ({d['tp'] + d['fn']}) · "
                     f"F1 {d['f1']:.2f}")
    elif "n_found" in row:
        parts.append(f"yellow: found ({row['n_found_off_border']} off the border)")
    else:
        parts.append("finds no grains" + (" · blue: reference" if photo.mask else ""))
    if row.get("reference_mm") and row["psd_mm"]["d50"] is not None:
        parts.append(f"d50 {row['psd_mm']['d50']:.1f} vs {row['reference_mm']['d50']:.1f} mm ({definition})")
    return " · ".join(parts)


TABLE_COLUMNS = ["image", "mm_per_px", "network_h", "network_w", "n_found", "n_found_off_border", "n_reference",
                 "tp", "fp", "fn", "left_out_found", "left_out_reference", "precision", "recall", "f1",
                 *(f"fn_{k}" for k in FN_KINDS), *(f"fp_{k}" for k in FP_KINDS),
                 "size_err_median", "size_err_p90", "sieve_err_median", "sieve_err_p90",
                 *(f"{n}_mm" for n in NAMES), *(f"reference_{n}_mm" for n in NAMES), *(f"rel_err_{n}" for n in NAMES),
                 "psd_size_definition", *(f"reading_{n}_mm" for n in NAMES), "reading_size_definition",
                 "reading_weighting",
                 "outline_band_px", "restored_f1", "restored_size_err_median", "restored_size_err_p90",
                 *(f"restored_reference_{n}_mm" for n in NAMES), *(f"restored_rel_err_{n}" for n in NAMES), "overlay",
                 "warning"]
# the figures given again against the reference with its outlines restored (PhotoScorer's outlines_restored)
RESTORED_KEYS = ("band_px", "reference_mm", "reference_from", "psd_rel_err", "n_reference", "detection",
                 "size_error")


def table_row(photo: Photo, r: dict, psd_definition: str, reading: dict) -> dict:
    """A photo's row of photos.csv (empty cells where a figure does not exist); `reading`: what the
    model's own d-values are of (``reading_of``)."""
    det, ref = r.get("detection") or {}, r.get("reference_mm") or {}
    se = {k: (r.get("size_error") or {}).get(k) or {} for k in ("size_definition", "sieve")}
    out = {"image": photo.name, "mm_per_px": photo.mm_per_px, "network_h": r["network_hw"][0],
           "network_w": r["network_hw"][1], "psd_size_definition": psd_definition,
           "reading_size_definition": reading["size_definition"], "reading_weighting": reading["weighting"],
           "overlay": r["overlay"], "warning": r.get("warning", "")}
    out.update({k: r.get(k) for k in ("n_found", "n_found_off_border", "n_reference")})
    out.update({k: det.get(k) for k in ("tp", "fp", "fn", "left_out_found", "left_out_reference", "precision",
                                        "recall", "f1")})
    for side, by_kind in (r.get("error_kinds") or {}).items():
        out.update({f"{side}_{kind}": n for kind, n in by_kind.items()})
    out.update(size_err_median=se["size_definition"].get("median"), size_err_p90=se["size_definition"].get("p90"),
               sieve_err_median=se["sieve"].get("median"), sieve_err_p90=se["sieve"].get("p90"))
    for n in NAMES:
        out.update({f"{n}_mm": r["psd_mm"][n], f"reference_{n}_mm": ref.get(n), f"rel_err_{n}": r["psd_rel_err"][n],
                    f"reading_{n}_mm": r["reading_mm"][n]})
    rest = r.get("outlines_restored")
    if rest:
        se = (rest.get("size_error") or {}).get("size_definition") or {}
        out.update(outline_band_px=rest["band_px"], restored_f1=(rest.get("detection") or {}).get("f1"),
                   restored_size_err_median=se.get("median"), restored_size_err_p90=se.get("p90"))
        for n in NAMES:
            out.update({f"restored_reference_{n}_mm": (rest.get("reference_mm") or {}).get(n),
                        f"restored_rel_err_{n}": rest["psd_rel_err"][n]})
    return out


def evaluate_photos(model_path: Path, photos: PhotoSet, out_dir: Path, device: str = "auto",
                    precision: str = "fp32") -> dict:
    """The model on every photo of the set: metrics.json, photos.csv (a row per photo) and
    overlays/<photo stem>.png in `out_dir`; returns the metrics."""
    from ..learn.runtime import pick_device, pick_precision, torch_runner

    dev = pick_device(device)
    est = load_predictor(Path(model_path), str(dev))
    if photos.auto_scale is not None:  # the set's photos read as predict --auto-scale reads, where it says so
        est.auto_scale = photos.auto_scale  # (else as predict reads them with this model by default)
    prec = pick_precision(precision, dev)
    if est.net is not None:
        est.run = torch_runner(est.inference_module(), dev, prec)
    meta, arch = est.meta, est.meta["arch"]
    own = reading_of(type(est), meta, None)
    if not est.finds_grains and own["weighting"] != "number":  # a CNN calibrated to references by mass or area
        logger.warning(f"{arch} reads {own['weighting']}-weighted d-values (its calibration's): the photo set's "
                       "references count grains (number-weighted), so its d-errors compare unlike distributions")
    psd_definition = photos.size_definition if est.finds_grains else own["size_definition"]
    scorer = PhotoScorer(est, photos)
    restored = PhotoScorer(est, photos, outlines_restored=True) if photos.outline_band_px != 0 else None
    overlays = Path(out_dir) / "overlays"
    per_photo, rows = {}, []
    for photo in photos.photos:
        net_hw = target_size(*photo.size_hw, meta, photo.mm_per_px)
        if not est.any_size and min(net_hw) < meta["input_size"]:  # below it a CNN's layers run out of pixels
            raise PsdError(f"{photo.path}: at {arch}'s scale ({network_scale(meta):.3f} mm/px) this photo is "
                           f"{net_hw[1]} x {net_hw[0]} px, smaller than the {meta['input_size']} px the model reads; "
                           f"it needs photos of at least {meta['input_size'] * network_scale(meta):.0f} mm a side")
        # as predict reads a photo: at the model's scale (or coarser, where its grains look larger than the training
        # grains: predict.choose_scale), tile by tile where it is larger than a tile
        image, size_hw = read_photo(photo.path, need=lambda h, w, p=photo: target_size(h, w, meta, p.mm_per_px))
        found, network_hw = read_at_scale(est, image, size_hw, photo.mm_per_px, DEFAULT_TILE_PX, str(photo.path))
        # its own reading as predict gives it (a calibrated model's correction applied)
        reading = Reading(corrected_reading(est, found, own, str(photo.path))[0], grains=found.grains)
        where = f"{photos.name}/{photo.name}"
        # a reading that is no size distribution, or rests on no or few whole grains: scored all the same (a photo
        # with no grain found scores F1 0), said in the log and beside its figures (metrics, photos.csv, the report)
        warning = say_warnings(where, [not_a_psd_warning(where, arch, reading.d_mm),
                                       *grain_count_problem(where, found.grains)], logger)
        ref_mask = read_mask(photo.mask, size_hw) if photo.mask is not None else None
        r = scorer.add(photo, reading, ref_mask)
        if restored is not None and ref_mask is not None:
            rest = restored.add(photo, reading, ref_mask)
            r["outlines_restored"] = {k: rest[k] for k in RESTORED_KEYS if k in rest}
        r["network_hw"] = [int(v) for v in network_hw]
        r["warning"] = warning
        r["mm_per_px"] = photo.mm_per_px
        found = reading.grains.mask if est.finds_grains else None
        r["overlay"] = f"{photo.stem}.png"
        caption = _caption(arch, photo, r, psd_definition)
        write_overlay(overlays / r["overlay"], overlay(image, ref_mask, found, caption))
        per_photo[photo.name] = r
        rows.append(table_row(photo, r, psd_definition, own))
        logger.info(f"{arch} on {photos.name}/{photo.name}: " + summary_line(r, psd_definition))
    result = {
        "arch": arch, "photoset": photos.name, "weights": meta.get("weights"), "precision": prec,
        "finds_grains": bool(est.finds_grains), "calibrated": "calibration" in meta,
        "size_definition": photos.size_definition,
        "psd_size_definition": psd_definition, "reading": own, "network_mm_per_px": network_scale(meta),
        "compared_at": ("the photo's resolution: the model's instance mask, made at its network scale, resized "
                        "nearest-neighbour to the photo's size; the reference masks as they are"),
        "iou": IOU, "photos": per_photo, "pooled": scorer.pooled(),
        "pooled_outlines_restored": restored.pooled() if restored is not None else None,
    }
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    with atomic_path(out_dir / "photos.csv") as tmp, open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=TABLE_COLUMNS)
        w.writeheader()
        w.writerows(rows)
    write_json(out_dir / "metrics.json", result)
    logger.info(f"{arch} on {photos.name}, pooled: " + pooled_line(result["pooled"]))
    if restored is not None:
        logger.info(f"{arch} on {photos.name}, pooled, outlines restored: "
                    + pooled_line(result["pooled_outlines_restored"]))
    return result


def _pct(v) -> str:
    return "—" if v is None or not np.isfinite(v) else f"{100 * v:+.1f} %"


def summary_line(r: dict, definition: str) -> str:
    text = f"d10/d50/d90 {' / '.join('—' if v is None else f'{v:.2f}' for v in r['psd_mm'].values())} mm ({definition})"
    if r.get("reference_mm"):
        text += (f" vs reference {' / '.join(f'{v:.2f}' for v in r['reference_mm'].values())} mm: "
                 + " / ".join(_pct(v) for v in r["psd_rel_err"].values()))
    if "detection" in r:
        d, s = r["detection"], r["size_error"]["size_definition"]
        text += f"; P/R/F1 {d['precision']:.3f}/{d['recall']:.3f}/{d['f1']:.3f}"
        if s["n"]:
            text += (f"; size error of {s['n']} matched grains median {100 * s['median']:.1f} %, "
                     f"p90 {100 * s['p90']:.1f} %")
    rest = r.get("outlines_restored")
    if rest and "detection" in rest:
        s = rest["size_error"]["size_definition"]
        text += (f"; outlines restored (band {rest['band_px']:.1f} px): F1 {rest['detection']['f1']:.3f}, "
                 f"size error median {_pct(s['median']).lstrip('+')}, d-errors "
                 + " / ".join(_pct(v) for v in rest["psd_rel_err"].values()))
    return text


def pooled_line(p: dict) -> str:
    text = "mean |PSD error| d10/d50/d90 " + " / ".join(
        "—" if v is None else f"{100 * v:.1f} %" for v in p["psd_abs_rel_err"].values())
    if "detection" in p:
        d = p["detection"]
        text += f"; P/R/F1 {d['precision']:.3f}/{d['recall']:.3f}/{d['f1']:.3f}"
    return text
