#!/usr/bin/env python
"""How the grains an instance model finds sit on the reference grains' outlines: whether found
grains are fatter or thinner than the reference's, and where the difference lies.

For each image the model's instance mask (`psdfactory predict --masks`, as a user runs it) is
matched to the reference mask at IoU >= 0.5 (the photo scorer's border rule), and the script
prints, over the matched grains: the median ratio of found to reference area and of ellipse minor
axis (the photo sets' size definition), the share of the found grains' pixels that the reference
calls background (gaps, shadows, table) or another grain, and the share of the image each mask
leaves as background. Then the outline band the reference mask keeps between grains that meet
(`learn.instances.scoring.outline_band_px`: 0 where its grains touch, as a rendered scene's) and
the two ratios again against its grains grown back by half of it (`restore_outlines`), and the F1 as
drawn that a finder outlining every grain where it meets its neighbour would score (those grains grown back,
scored against the mask as drawn: what the reference's own band allows). Last, what the
grains the match missed are (`learn.instances.scoring.error_kinds`, on the mask as drawn): the
reference grains no found grain matches, cut into pieces, merged with a neighbour into one found
grain, missed or misfit; the found grains that match none, a merge of several, on the reference's
background, a piece of one grain or a misfit.

Photo sets (a folder with labels.csv and <stem>_mask.png, as data/photos/real) are read at their
labels.csv scale, with --auto-scale as the default config's photo set reads them; synthetic test
scenes (--results/--datasets, the manifests' test split) at their own scale against their true
masks.

    .venv/bin/python bench/mask_fit.py --model results/models/instances/model.pt \
        --photos data/photos/real --auto-scale --results results --datasets train train_cycles
"""

from __future__ import annotations

import argparse
import csv
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def predict_masks(model: Path, images: list[Path], out: Path, mm_per_px: float | None, auto_scale: bool) -> None:
    cmd = [sys.executable, "-m", "psdfactory.cli", "-q", "predict", "--model", str(model), "--masks", str(out)]
    if mm_per_px is not None:
        cmd += ["--mm-per-px", str(mm_per_px)]
    cmd += ["--auto-scale" if auto_scale else "--no-auto-scale"]
    subprocess.run(cmd + [str(p) for p in images], check=True, stdout=subprocess.DEVNULL)


def fit(found: np.ndarray, ref: np.ndarray, mm_per_px: float) -> dict:
    """The figures of one image (see the module's docstring), and the ratios again against the
    reference grains grown back by half the outline band its mask keeps between them."""
    from psdfactory.learn.instances.scoring import border_ids, outline_band_px, restore_outlines

    out = fit_as_drawn(found, ref, mm_per_px)
    band = outline_band_px(ref)
    restored = restore_outlines(ref, band) if band else ref
    again = fit_as_drawn(found, restored, mm_per_px, border_ids(ref)) if band else out
    return {**out, "band_px": band, "area_ratio_restored": again["area_ratio"],
            "minor_ratio_restored": again["minor_ratio"], "f1_ceiling": f1_ceiling(ref, restored)}


def f1_ceiling(ref: np.ndarray, restored: np.ndarray) -> float:
    """The F1 as drawn of a finder whose grains are the reference's grown back to meet (`restored`),
    by the photo scorer's rule: 1 where the mask keeps no band; below 1 where the band is wide
    against the grains (a grain d px across, drawn w px short of its neighbours, keeps IoU >= 0.5 only
    while (d / (d + w))**2 >= 0.5, d >= 2.4 w)."""
    from psdfactory.deploy.photos import IOU
    from psdfactory.learn.instances.scoring import match_off_border

    return float(match_off_border(restored, ref, IOU).f1)


def fit_as_drawn(found: np.ndarray, ref: np.ndarray, mm_per_px: float, ref_on_border=None) -> dict:
    """How the found grains sit on the reference mask as it is (`ref_on_border`: the reference
    grains the border rule leaves out, where decided on another copy of it)."""
    from psdfactory.deploy.photos import IOU
    from psdfactory.learn.instances.measure import measure_instances
    from psdfactory.learn.instances.scoring import error_kinds, match_off_border

    bm = match_off_border(found, ref, IOU, true_on_border=ref_on_border)
    fa = np.bincount(found.ravel(), minlength=int(found.max()) + 1)
    ra = np.bincount(ref.ravel(), minlength=int(ref.max()) + 1)
    mf, mr = measure_instances(found, mm_per_px), measure_instances(ref, mm_per_px)
    minor_f = dict(zip(mf.ids.tolist(), mf.ellipse_minor_mm, strict=True))
    minor_r = dict(zip(mr.ids.tolist(), mr.ellipse_minor_mm, strict=True))
    matched = np.zeros(int(found.max()) + 1, bool)
    matched[bm.pred_ids] = True
    owner = np.zeros(int(found.max()) + 1, np.int64)  # found id -> its reference grain
    owner[bm.pred_ids] = bm.true_ids
    sel = matched[found]
    under = ref[sel]
    return {
        "matched": int(len(bm.pred_ids)),
        "area_ratio": float(np.median(fa[bm.pred_ids] / ra[bm.true_ids])) if len(bm.pred_ids) else np.nan,
        "minor_ratio": float(np.median([minor_f[p] / minor_r[t] for p, t in zip(bm.pred_ids.tolist(),
                                                                                bm.true_ids.tolist(), strict=True)]))
        if len(bm.pred_ids) else np.nan,
        "on_ref_background": float((under == 0).mean()) if sel.any() else np.nan,
        "on_other_grain": float(((under != 0) & (under != owner[found[sel]])).mean()) if sel.any() else np.nan,
        "ref_background": float((ref == 0).mean()),
        "found_background": float((found == 0).mean()),
        "kinds": error_kinds(found, ref, bm),
    }


def photo_set(model: Path, folder: Path, auto_scale: bool, work: Path) -> list[tuple[str, dict]]:
    from psdfactory.deploy.photos import read_mask
    from psdfactory.io import read_png

    with open(folder / "labels.csv", newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    out = []
    for r in rows:
        image = folder / r["image"]
        ref_path = image.with_name(f"{image.stem}_mask.png")
        if not ref_path.is_file():
            continue
        predict_masks(model, [image], work, float(r["mm_per_px"]), auto_scale)
        found = read_png(work / f"{image.stem}.png").astype(np.int64)
        out.append((r["image"], fit(found, read_mask(ref_path, found.shape), float(r["mm_per_px"]))))
    return out


def scenes(model: Path, results: Path, dataset: str, split: str, work: Path) -> list[tuple[str, dict]]:
    from psdfactory.io import read_png
    from psdfactory.learn.data import manifest_rows

    rows = manifest_rows(results, dataset, (split,))
    inputs = work / f"in-{dataset}"
    inputs.mkdir()
    for r in rows:  # every scene's image is image.png: give each its scene id
        shutil.copy(results / r["image_path"], inputs / f"{r['scene_id']}.png")
    predict_masks(model, [inputs], work / dataset, None, False)
    return [(r["scene_id"], fit(read_png(work / dataset / f"{r['scene_id']}.png").astype(np.int64),
                                read_png(results / r["mask_path"]).astype(np.int64), r["mm_per_px"])) for r in rows]


COLUMNS = ("matched", "area_ratio", "minor_ratio", "on_ref_background", "on_other_grain", "ref_background",
           "found_background", "band_px", "area_ratio_restored", "minor_ratio_restored", "f1_ceiling")


def table(title: str, rows: list[tuple[str, dict]], each: bool) -> None:
    print(f"\n{title}\n| image | " + " | ".join(COLUMNS) + " |\n|---|" + "---|" * len(COLUMNS))
    if each:
        for name, r in rows:
            print(f"| {name} | " + " | ".join(f"{r[c]:.3f}" if c != "matched" else str(r[c]) for c in COLUMNS) + " |")
    med = {c: float(np.nanmedian([r[c] for _, r in rows])) for c in COLUMNS}
    print(f"| median of {len(rows)} | " + " | ".join(f"{med[c]:.3f}" if c != "matched" else f"{med[c]:.0f}"
                                                    for c in COLUMNS) + " |")


def kinds_table(title: str, rows: list[tuple[str, dict]], each: bool) -> None:
    """The unmatched grains by kind (error_kinds), per image and summed."""
    from psdfactory.learn.instances.scoring import FN_KINDS, FP_KINDS

    cols = [("fn", k) for k in FN_KINDS] + [("fp", k) for k in FP_KINDS]
    print(f"\n{title}: the grains the match missed, by kind\n| image | matched | "
          + " | ".join(f"{side.upper()} {k}" for side, k in cols) + " |\n|---|---|" + "---|" * len(cols))

    def line(name: str, matched: int, kinds: list) -> None:
        print(f"| {name} | {matched} | " + " | ".join(str(sum(getattr(k, side)[kind] for k in kinds))
                                                   for side, kind in cols) + " |")

    if each:
        for name, r in rows:
            line(name, r["matched"], [r["kinds"]])
    line(f"sum of {len(rows)}", sum(r["matched"] for _, r in rows), [r["kinds"] for _, r in rows])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", type=Path, required=True, help="an instance model.pt")
    ap.add_argument("--photos", type=Path, nargs="*", default=[], help="photo set folders (labels.csv, *_mask.png)")
    ap.add_argument("--auto-scale", action="store_true", help="read the photos as predict --auto-scale does")
    ap.add_argument("--results", type=Path, help="a results root: also its datasets' test scenes")
    ap.add_argument("--datasets", nargs="*", default=[], help="datasets of --results")
    ap.add_argument("--split", default="test")
    a = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="mask-fit-"))
    try:
        for folder in a.photos:
            title = f"{folder} ({'--auto-scale' if a.auto_scale else 'at the labels scale'})"
            rows = photo_set(a.model, folder, a.auto_scale, work / folder.name)
            table(title, rows, each=True)
            kinds_table(title, rows, each=True)
        for ds in a.datasets:
            title = f"{a.results}/{ds}, {a.split} split"
            rows = scenes(a.model, a.results, ds, a.split, work)
            table(title, rows, each=False)
            kinds_table(title, rows, each=False)
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
