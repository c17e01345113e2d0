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

REPO = Path(__file__).resolve().parents[1]
PHOTO = REPO.parent / "shared" / "real" / "barton_creek.jpg"
REFERENCE_MASK = REPO.parent / "shared" / "real" / "barton_creek_mask.png"
PHOTO_MM_PER_PX = 0.288  # ../shared/real/README.md


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
    from psdfactory.learn.instances.estimator import InstanceEstimator
    from psdfactory.learn.instances.net import InstanceMaps, net_from_meta
    from psdfactory.learn.instances.watershed import DEFAULT_POSTPROCESS
    from psdfactory.learn.runtime import torch_runner

    ref = np.load(a.maps) if a.maps else None

    class ReferenceMaps(InstanceEstimator):
        """The network runs (and is timed) as it is; what is read is the reference's maps."""

        def read(self, outputs, mm_per_px):
            h, w = outputs.shape[-2:]
            r = np.minimum(((np.arange(h) + 0.5) * ref.shape[1] / h).astype(int), ref.shape[1] - 1)
            c = np.minimum(((np.arange(w) + 0.5) * ref.shape[2] / w).astype(int), ref.shape[2] - 1)
            maps = ref[:, r[:, None], c[None, :]].astype(np.float32)[None]
            return super().read(maps, mm_per_px)

    if a.model:
        est = predict.load_predictor(Path(a.model))
        if ref is not None:
            est.__class__ = ReferenceMaps
    else:
        meta = {"arch": "instances", "mm_per_px": PHOTO_MM_PER_PX, "image_resolution": 512, "input_size": 512,
                "postprocess": dict(DEFAULT_POSTPROCESS), "sieve_method": "min_feret", "size_definition": "sieve",
                "weighting": "number", "maps": ["foreground", "boundary", "distance"], "readouts": {}}
        torch.manual_seed(0)
        net = net_from_meta(meta).eval()
        est = ReferenceMaps(meta, torch_runner(InstanceMaps(net)), net)
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

    est.outputs, est.read = timed("network_s", outputs), timed("post_s", read)
    mm = a.mm_per_px if a.mm_per_px else predict.network_scale(est.meta)
    photo = Path(a.photo)
    with tempfile.TemporaryDirectory() as tmp:
        grains = predict.GrainOutputs(est.meta, overlay_dir=Path(tmp) / "ov", masks_dir=Path(tmp) / "masks",
                                      particles_out=Path(tmp) / "grains.csv")
        grains.name_outputs([photo])
        base_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        t0 = time.perf_counter()
        row = predict.predict_one(est, photo, mm, grains, tile=a.tile)
        seconds = time.perf_counter() - t0
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
            "tiles": len(predict.tile_spans(nh, a.tile, est.tile_margin_px))
            * len(predict.tile_spans(nw, a.tile, est.tile_margin_px)),
            "seconds": seconds, "photo_mp_per_s": w * h / 1e6 / seconds, **timing,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, "rss_before_mb": base_rss,
            "grains": n, "d50_mm": row["d50_mm"], "threads": torch.get_num_threads()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=float, nargs="+", default=[3, 12], help="photo sizes in MP (default 3 12)")
    ap.add_argument("--model", help="an instance model.pt (default: an untrained network on the reference maps)")
    ap.add_argument("--reference-maps", action="store_true", help="with --model: read the reference's maps too")
    ap.add_argument("--true-scale", action="store_true", help="give each photo its own scale, not the network's")
    ap.add_argument("--tile", type=int, default=None, help="tile side at the network's scale (default: predict's)")
    ap.add_argument("--workdir", help="where the photos are made (default: a temporary folder)")
    ap.add_argument("--out", help="also write the rows to this JSON file")
    ap.add_argument("--one", help=argparse.SUPPRESS)  # the child: one photo
    ap.add_argument("--photo", help=argparse.SUPPRESS)
    ap.add_argument("--maps", help=argparse.SUPPRESS)
    ap.add_argument("--mm-per-px", type=float, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.tile is None:
        from psdfactory.config import PREDICT_TILE_PX

        a.tile = PREDICT_TILE_PX
    if a.one:
        print(json.dumps(one_photo(a)))
        return
    work = Path(a.workdir or tempfile.mkdtemp(prefix="photo_speed-"))
    work.mkdir(parents=True, exist_ok=True)
    maps = None if (a.model and not a.reference_maps) else reference_maps(REFERENCE_MASK, work / "reference_maps.npy")
    rows = []
    for mp in a.sizes:
        photo, mm = make_photo(PHOTO, mp, work / f"barton_creek_{mp:g}mp.jpg")
        cmd = [sys.executable, __file__, "--one", "1", "--photo", str(photo), "--tile", str(a.tile)]
        cmd += ["--model", a.model] if a.model else []
        cmd += ["--maps", str(maps)] if maps else []
        cmd += ["--mm-per-px", str(mm)] if a.true_scale else []
        env = dict(os.environ, PYTHONPATH=str(REPO / "src"))
        r = subprocess.run(cmd, capture_output=True, text=True, env=env)
        if r.returncode:
            print(f"{photo.name}: failed ({r.returncode}): {r.stderr.strip().splitlines()[-1:]}", file=sys.stderr)
            continue
        row = json.loads(r.stdout.strip().splitlines()[-1])
        row["bytes_per_network_px"] = (row["peak_rss_mb"] - row["rss_before_mb"]) * 2**20 / (row["network_mp"] * 1e6)
        rows.append(row)
        print(f"{row['photo']:<26} {row['photo_mp']:5.1f} MP photo, {row['network_mp']:5.1f} MP at the network's "
              f"scale in {row['tiles']:2d} tile(s): {row['seconds']:6.1f} s = {row['photo_mp_per_s']:.3f} MP/s "
              f"(network {row['network_s']:.1f} s, post-processing {row['post_s']:.1f} s), peak RSS "
              f"{row['peak_rss_mb']:,.0f} MB ({row['bytes_per_network_px']:.0f} B per network px above the "
              f"{row['rss_before_mb']:,.0f} MB before), {row['grains']} grains, "
              f"{row['threads']} threads", flush=True)
    if a.out:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
