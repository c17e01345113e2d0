"""A photo read at two scales, its grains fused: measured, not adopted (docs/experiments.md, 2026-11-27).

`predict --auto-scale` reads a photo whose grains look larger than the model's training grains at a
coarser scale, where a mixed bed's fines are lost. This script tries the obvious remedy, with its
one threshold fixed beforehand from the model's meta (never chosen on the photos): read the photo
at the coarse scale `choose_scale` picks *and* at the model's own scale; keep each coarse grain whose
sieve size at the model's scale is above `grain_px_max` (the largest validation image's grain size
there: what the model's own scale is no longer trusted with), and add each grain of the fine reading
that lies at least half outside those kept grains. The size map is the coarse one (rescaled) inside
kept grains, the fine one elsewhere. Then the photo set is scored as `psdfactory evaluate-photos`
scores it, both ways:

    .venv/bin/python bench/two_scale_fusion.py --model results/models/instances/model.pt

prints, per photo and way, the grains found, TP / FP / FN and F1 at IoU 0.5 (as drawn, and with
the reference outlines restored), the matched grains' size error and the PSD's relative error.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from psdfactory import photoset
from psdfactory.config import load_config
from psdfactory.deploy import photos as photos_mod
from psdfactory.deploy import predict as pr
from psdfactory.learn.estimator import Reading

_auto = pr.read_at_scale


def read_two_scales(est, image, size_hw, mm_per_px, tile=pr.DEFAULT_TILE_PX, where=""):
    found_c, hw_c = _auto(est, image, size_hw, mm_per_px, tile, where)
    meta = est.meta
    x = pr.prepare(image, meta, mm_per_px, size_hw, pr.MAX_TILED_PIXELS, 1.0)
    hw_f = tuple(x.shape[-2:])
    if hw_f == tuple(hw_c):  # read at the model's scale already: nothing to fuse
        return found_c, hw_c
    fine_mm = pr.network_mm_per_px(size_hw, hw_f, meta, mm_per_px)
    fine = est.analyse_maps(pr.image_outputs(est, x, tile, where)[0], fine_mm)
    coarse = found_c.grains
    rows = np.arange(hw_f[0]) * coarse.mask.shape[0] // hw_f[0]
    cols = np.arange(hw_f[1]) * coarse.mask.shape[1] // hw_f[1]
    up = coarse.mask[rows[:, None], cols[None, :]]
    big = coarse.measurements.ids[coarse.sizes_mm / fine_mm > float(meta["grain_px_max"])]
    keep = np.isin(up, big)
    fused = np.where(keep, up, 0).astype(np.int64)
    area = np.bincount(fine.mask.ravel())
    inside = np.bincount(fine.mask[keep].ravel(), minlength=len(area))
    added = [i for i in fine.measurements.ids if inside[i] < 0.5 * area[i]]
    sel = np.isin(fine.mask, added) & ~keep
    fused[sel] = fine.mask[sel] + int(up.max()) + 1
    _, inv = np.unique(fused, return_inverse=True)
    fused = inv.reshape(fused.shape).astype(np.uint16)  # 0 stays 0: every mask has background
    size_px = None
    if coarse.size_map_px is not None and fine.size_map_px is not None:
        size_px = np.where(keep, coarse.size_map_px[rows[:, None], cols[None, :]] * hw_f[0] / coarse.mask.shape[0],
                           fine.size_map_px)
    res = est.result(fused, fine_mm, size_px)
    print(f"{where}: coarse {len(coarse.measurements)} grains, {len(big)} kept (> {meta['grain_px_max']:.0f} px at "
          f"the model's scale); fine {len(fine.measurements)}, {len(added)} added; fused {len(res.measurements)}")
    return Reading(res.calibrated, grains=res), hw_f


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", required=True)
    ap.add_argument("--config", default="config/config.yaml")
    ap.add_argument("--photoset", default="real")
    a = ap.parse_args()
    sets, _ = photoset.resolve_all(load_config(a.config))
    for way in ("auto-scale", "two scales"):
        photos_mod.read_at_scale = _auto if way == "auto-scale" else read_two_scales
        with tempfile.TemporaryDirectory() as out:
            m = photos_mod.evaluate_photos(Path(a.model), sets[a.photoset], Path(out), device="cpu")
        for name, r in m["photos"].items():
            d, rest = r["detection"], (r.get("outlines_restored") or {}).get("detection") or {}
            psd = {k: f"{v:+.0%}" for k, v in (r.get("psd_rel_err") or {}).items() if v is not None}
            print(f"{way:10s} {name}: found {r['n_found']}, TP {d['tp']} FP {d['fp']} FN {d['fn']}, F1 {d['f1']:.3f} "
                  f"(restored {rest.get('f1', float('nan')):.3f}); size error "
                  f"{r['size_error']['size_definition']['median']:.1%}; PSD {psd}")


if __name__ == "__main__":
    main()
