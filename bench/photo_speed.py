#!/usr/bin/env python
"""How fast, and in how much memory, `psdfactory predict` measures a phone photo with the instance
estimator: a 3 MP and a 12 MP photo (../shared/real/barton_creek.jpg, 2000 x 1500 px, and that
photo upscaled 2x; any size with --sizes), each run by predict's own `predict_one` in a fresh
process (the particle table, the 16-bit mask and the overlay written as a user would), and
reported as photo MP per second and the process's peak resident memory (ru_maxrss).

By default every photo is given the model's network scale as its mm per px, so it runs at its
own pixel count (the worst case: a 12 MP photo is 12 MP at the network's scale, cut into tiles of
--tile px); --true-scale gives them their own scale (0.288 mm/px for the 3 MP, 0.144 for the
12 MP) instead, resized to the model's first.

Without --model the network is an untrained InstanceNet of the shipped architecture (its cost
does not depend on its weights), and since random weights find no grains, the maps it reads are
the reference mask's (barton_creek_mask.png, segmenteverygrain's 347 grains, as instance_targets
makes them for training), resized to the network's size: the watershed and the measurement then
see real grains. That reference copy of the maps stays in memory beside the stitched ones, so the
peak overstates predict's by ~12 B per network pixel. With --model, the model's own maps.

    .venv/bin/python bench/photo_speed.py                      # 3 and 12 MP at network scale
    .venv/bin/python bench/photo_speed.py --sizes 3 12 48 --out bench/out/photo_speed.json
    .venv/bin/python bench/photo_speed.py --model results/models/instances/model.pt --true-scale
    .venv/bin/python bench/photo_speed.py --model results/models/instances/model.pt --true-scale \
        --runtimes torch auto --repeats 3      # predict's engines side by side, medians of 3

Besides the wall time, each run prints its process's CPU time: on cores shared with other work
that is the steadier figure, and only runs interleaved in one invocation compare.

Measured on the development machine (2 shared CPU cores, 23 GB; 2026-11-25), untrained network,
reference maps, at network scale, tiles of 1024 px: see docs/photos.md ("Large photos") for the
table and what it means for a 48 MP photo.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from psdfactory.config import PREDICT_RUNTIMES, PREDICT_TILE_PX

REPO = Path(__file__).resolve().parents[1]
PHOTO = REPO / "data" / "photos" / "real" / "barton_creek.jpg"  # the repository's copy of ../shared/real
REFERENCE_MASK = PHOTO.with_name("barton_creek_mask.png")


def photo_scale(photo: Path) -> float:
    """The photo's mm per px, from labels.csv beside it (the photo set's reference table)."""
    import csv

    with open(photo.with_name("labels.csv"), newline="", encoding="utf-8") as f:
        return next(float(r["mm_per_px"]) for r in csv.DictReader(f) if r["image"] == photo.name)


PHOTO_MM_PER_PX = photo_scale(PHOTO)


def make_photo(src: Path, mp: float, out: Path) -> tuple[Path, float]:
    """`src` upscaled (Lanczos) to about `mp` megapixels as a JPEG (quality 92, as a phone's);
    → (file, its mm per px)."""
    from PIL import Image

    with Image.open(src) as im:
        w, h = im.size
        k = math.sqrt(mp * 1e6 / (w * h))
        size = (round(w * k), round(h * k))
        (im if size == (w, h) else im.resize(size, Image.Resampling.LANCZOS)).convert("RGB").save(out, quality=92)
    return out, PHOTO_MM_PER_PX * w / size[0]


def reference_maps(mask_path: Path, out: Path) -> Path:
    """The reference mask's maps (foreground, boundary, distance) as the network is trained to
    give them, float16, at the mask's own size."""
    import numpy as np

    from psdfactory.io import read_png
    from psdfactory.learn.instances.targets import instance_targets

    fg, bd, dist = instance_targets(read_png(mask_path).astype(np.int64))
    np.save(out, np.stack([fg, bd, dist]).astype(np.float16))
    return out


def one_photo(a: argparse.Namespace) -> dict:
    """Run in a child process: one photo through predict_one; what it took."""
    import numpy as np
    import torch

    from psdfactory.deploy import predict
    from psdfactory.learn.instances.draw import resize_mask
    from psdfactory.learn.instances.estimator import InstanceEstimator
    from psdfactory.learn.instances.net import InstanceMaps, net_from_meta
    from psdfactory.learn.instances.watershed import DEFAULT_POSTPROCESS
    from psdfactory.learn.runtime import torch_runner

    ref = np.load(a.maps) if a.maps else None

    class ReferenceMaps(InstanceEstimator):
        """The network runs (and is timed) as it is; what is read is the reference's maps."""

        def read(self, outputs, mm_per_px):
            maps = resize_mask(ref, outputs.shape[-2:]).astype(np.float32)[None]
            return super().read(maps, mm_per_px)

    if a.model:
        est = predict.load_predictor(Path(a.model), device=a.device, runtime=a.runtime)
        if ref is not None:
            est.__class__ = ReferenceMaps
    else:
        meta = {"arch": "instances", "mm_per_px": PHOTO_MM_PER_PX, "image_resolution": 512, "input_size": 512,
                "postprocess": dict(DEFAULT_POSTPROCESS), "sieve_method": "min_feret", "size_definition": "sieve",
                "weighting": "number", "maps": ["foreground", "boundary", "distance"], "readouts": {}}
        torch.manual_seed(0)
        net = net_from_meta(meta).eval()
        est = ReferenceMaps(meta, torch_runner(InstanceMaps(net), a.device), net)
    timing = {"network_s": 0.0, "post_s": 0.0}
    outputs, read = est.outputs, est.read

    def timed(key, fn):
        def run(*args):
            t = time.perf_counter()
            try:
                return fn(*args)
            finally:
                timing[key] += time.perf_counter() - t
        return run

    def read_noting_size(maps, mm_per_px):  # the size the network read the photo at (predict's automatic scale)
        timing["read_hw"] = list(maps.shape[-2:])
        return read(maps, mm_per_px)

    if a.auto_scale is not None:  # else the model's own default, as predict reads
        est.auto_scale = a.auto_scale
    est.outputs, est.read = timed("network_s", outputs), timed("post_s", read_noting_size)
    mm = a.mm_per_px if a.mm_per_px else predict.network_scale(est.meta)
    photo = Path(a.photo)
    with tempfile.TemporaryDirectory() as tmp:
        grains = predict.GrainOutputs(est.meta, overlay_dir=Path(tmp) / "ov", masks_dir=Path(tmp) / "masks",
                                      particles_out=Path(tmp) / "grains.csv")
        grains.name_outputs([photo])
        base_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        t0, c0 = time.perf_counter(), time.process_time()
        row = predict.predict_one(est, photo, mm, grains, tile=a.tile)
        seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
        grains.finish()
        n = grains.n_particles
    if row["error"]:
        raise SystemExit(row["error"])
    from PIL import Image

    with Image.open(photo) as im:
        w, h = im.size
    scale = mm / predict.network_scale(est.meta)
    nh, nw = predict.target_size(h, w, est.meta, mm)
    return {"photo": photo.name, "photo_mp": w * h / 1e6, "network_mp": nh * nw / 1e6, "network_scale_factor": scale,
            "read_scale": timing["read_hw"][0] / nh, "read_mp": timing["read_hw"][0] * timing["read_hw"][1] / 1e6,
            "tiles": len(predict.tile_spans(nh, a.tile, est.tile_margin_px))
            * len(predict.tile_spans(nw, a.tile, est.tile_margin_px)),
            "seconds": seconds, "cpu_s": cpu, "photo_mp_per_s": w * h / 1e6 / seconds, **timing,
            "runtime": getattr(est, "engine", "torch"), "device": a.device,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, "rss_before_mb": base_rss,
            "grains": n, "d50_mm": row["d50_mm"], "threads": torch.get_num_threads()}


def run_one(a: argparse.Namespace, photo: Path, mm: float, maps: Path | None, runtime: str) -> dict | None:
    """One photo through predict_one in a fresh process; its row, printed."""
    cmd = [sys.executable, __file__, "--one", "1", "--photo", str(photo), "--tile", str(a.tile), "--runtime", runtime,
           "--device", a.device]
    cmd += [] if a.auto_scale is None else ["--auto-scale" if a.auto_scale else "--no-auto-scale"]
    cmd += ["--model", a.model] if a.model else []
    cmd += ["--maps", str(maps)] if maps else []
    cmd += ["--mm-per-px", str(mm)] if a.true_scale else []
    path = [str(REPO / "src"), os.environ.get("PYTHONPATH", "")]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, path)))
    r = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if r.returncode:
        print(f"{photo.name}: failed ({r.returncode}): {r.stderr.strip().splitlines()[-1:]}", file=sys.stderr)
        return None
    row = json.loads(r.stdout.strip().splitlines()[-1])
    row["bytes_per_network_px"] = (row["peak_rss_mb"] - row["rss_before_mb"]) * 2**20 / (row["network_mp"] * 1e6)
    print(f"{row['photo']:<26} {row['photo_mp']:5.1f} MP photo, {row['network_mp']:5.1f} MP at the network's "
          f"scale in {row['tiles']:2d} tile(s), read at {row['read_scale']:.2f}x it, "
          f"{row['runtime']} on {row['device']}: "
          f"{row['seconds']:6.1f} s = "
          f"{row['photo_mp_per_s']:.3f} MP/s, CPU {row['cpu_s']:.1f} s (network {row['network_s']:.1f} s, "
          f"post-processing {row['post_s']:.1f} s), peak RSS {row['peak_rss_mb']:,.0f} MB "
          f"({row['bytes_per_network_px']:.0f} B per network px above the {row['rss_before_mb']:,.0f} MB before), "
          f"{row['grains']} grains, {row['threads']} threads", flush=True)
    row["asked"] = runtime
    return row


def print_medians(rows: list[dict], runtimes: list[str]) -> None:
    """Per photo and runtime: the medians of the runs, and the ratio to the first runtime's."""
    import statistics

    print(f"\nmedians ({len(rows)} runs):")
    print(f"{'photo':<26} {'runtime':<14} {'runs':>4} {'s':>7} {'MP/s':>7} {'CPU s':>7} {'network s':>9} "
          f"{'post s':>7}  speed vs {runtimes[0]}")
    for photo in dict.fromkeys(r["photo"] for r in rows):
        base = None
        for runtime in runtimes:
            rs = [r for r in rows if r["photo"] == photo and r["asked"] == runtime]
            if not rs:
                continue
            med = {k: statistics.median(r[k] for r in rs) for k in ("seconds", "photo_mp_per_s", "cpu_s",
                                                                     "network_s", "post_s")}
            base = base or med
            engine = "/".join(dict.fromkeys(r["runtime"] for r in rs))
            print(f"{photo:<26} {runtime + ' (' + engine + ')':<14} {len(rs):>4} {med['seconds']:7.2f} "
                  f"{med['photo_mp_per_s']:7.3f} {med['cpu_s']:7.2f} {med['network_s']:9.2f} {med['post_s']:7.2f}  "
                  f"{base['seconds'] / med['seconds']:.2f}x", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=float, nargs="+", default=[3, 12], help="photo sizes in MP (default 3 12)")
    ap.add_argument("--model", help="an instance model.pt (default: an untrained network on the reference maps)")
    ap.add_argument("--reference-maps", action="store_true", help="with --model: read the reference's maps too")
    ap.add_argument("--true-scale", action="store_true", help="give each photo its own scale, not the network's")
    ap.add_argument("--tile", type=int, default=None, help="tile side at the network's scale (default: predict's)")
    ap.add_argument("--runtimes", nargs="+", choices=PREDICT_RUNTIMES, default=["torch"],
                    help="with --model: predict's --runtime, each timed on every photo, interleaved (default: torch)")
    ap.add_argument("--auto-scale", action=argparse.BooleanOptionalAction, default=None,
                    help="predict --auto-scale / --no-auto-scale (photos whose grains look larger than the validation "
                    "grains read coarser; default: the model's own, as predict)")
    ap.add_argument("--device", default="cpu", help="the network's device: cpu, cuda (default: %(default)s)")
    ap.add_argument("--repeats", type=int, default=1, help="runs of each photo and runtime; medians are printed")
    ap.add_argument("--workdir", help="where the photos are made (default: a temporary folder)")
    ap.add_argument("--out", help="also write the rows to this JSON file")
    ap.add_argument("--one", help=argparse.SUPPRESS)  # the child: one photo
    ap.add_argument("--photo", help=argparse.SUPPRESS)
    ap.add_argument("--maps", help=argparse.SUPPRESS)
    ap.add_argument("--mm-per-px", type=float, help=argparse.SUPPRESS)
    ap.add_argument("--runtime", default="torch", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.tile is None:
        a.tile = PREDICT_TILE_PX
    if a.one:
        print(json.dumps(one_photo(a)))
        return
    from psdfactory import PsdError
    from psdfactory.learn.runtime import pick_device

    try:
        pick_device(a.device)
    except PsdError as e:
        raise SystemExit(f"--device {a.device}: {e}") from None
    work = Path(a.workdir or tempfile.mkdtemp(prefix="photo_speed-"))
    work.mkdir(parents=True, exist_ok=True)
    maps = None if (a.model and not a.reference_maps) else reference_maps(REFERENCE_MASK, work / "reference_maps.npy")
    runtimes = a.runtimes if a.model else ["torch"]
    rows = []
    for mp in a.sizes:
        photo, mm = make_photo(PHOTO, mp, work / f"barton_creek_{mp:g}mp.jpg")
        for _ in range(a.repeats):
            for runtime in runtimes:  # interleaved: every runtime sees the same load
                row = run_one(a, photo, mm, maps, runtime)
                if row is not None:
                    rows.append(row)
    if len(rows) > len(a.sizes):
        print_medians(rows, runtimes)
    if a.out:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
