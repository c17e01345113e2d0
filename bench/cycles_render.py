#!/usr/bin/env python
"""Seconds per scene of the two render backends, side by side, at the paper's scene size.

Samples and settles N scenes of config/paper.yaml (700–1000 crushed-rock particles on a 300 mm
table), then renders each with TinyRenderer and with Blender Cycles at 512² (16 samples,
OpenImageDenoise by default), one scene at a time, and prints per-backend medians, Cycles'
split into Blender start-up + scene building vs path tracing, and the mask agreement.
Cycles uses every core it sees (here: the CPU; a GPU when one is present).

    .venv/bin/python bench/cycles_render.py [--scenes 3] [--resolution 512] [--samples 16]
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", type=int, default=3)
    ap.add_argument("--resolution", type=int, default=512)
    ap.add_argument("--samples", type=int, default=16)
    ap.add_argument("--no-denoise", action="store_true")
    a = ap.parse_args()

    from psdfactory import config as psd_config
    from psdfactory.io import read_json, read_png
    from psdfactory.scene.show import mask_agreement
    from psdfactory.scene.stages import run_render, run_sample, run_simulate

    cfg = psd_config.load_config(REPO / "config" / "paper.yaml")
    cfg["render"]["resolution"] = a.resolution
    cfg["render"]["cycles"].update(samples=a.samples, denoise=not a.no_denoise)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(a.scenes):
            d = Path(tmp) / f"train-{i:06d}"
            spec = run_sample(psd_config.sample_params(cfg, "train", i), d)  # (their log records: not shown)
            run_simulate(psd_config.simulate_params(cfg), d)
            row = {"n": spec["samplesize"]}
            masks = {}
            for backend in ("tiny", "cycles"):
                b = Path(tmp) / backend / d.name
                shutil.copytree(d, b)
                params = psd_config.render_params({**cfg, "render": {**cfg["render"], "backend": backend}})
                t0 = time.perf_counter()
                run_render(params, b)
                row[backend] = time.perf_counter() - t0
                masks[backend] = read_png(b / "mask.png")
                if backend == "cycles":
                    meta = read_json(b / "render.json")["cycles"]
                    row.update(device=meta["device"], path_tracing=meta["render_s"])
            row["agree"], row["agree_off_edges"] = mask_agreement(masks["tiny"], masks["cycles"])
            rows.append(row)
            print(f"scene {i}: {row['n']} particles, tiny {row['tiny']:.2f} s, cycles {row['cycles']:.1f} s "
                  f"(path tracing {row['path_tracing']:.1f} s on {row['device']}), masks agree "
                  f"{100 * row['agree']:.1f} % ({100 * row['agree_off_edges']:.2f} % off edges)", flush=True)

    def med(k: str) -> float:
        return statistics.median(r[k] for r in rows)

    print(f"\n{a.resolution}² px, Cycles {a.samples} samples, denoiser {'off' if a.no_denoise else 'on'}, "
          f"median of {len(rows)} scenes:")
    print(f"  tiny   {med('tiny'):6.2f} s/scene")
    print(f"  cycles {med('cycles'):6.2f} s/scene (path tracing {med('path_tracing'):.2f} s; the rest is Blender's "
          f"start-up, scene building and I/O) — {med('cycles') / med('tiny'):.0f}× the fast backend")
    print(f"  masks agree on {100 * med('agree'):.1f} % of pixels, "
          f"{100 * med('agree_off_edges'):.2f} % away from edges")
    print(json.dumps({"rows": rows}))


if __name__ == "__main__":
    main()
