#!/usr/bin/env python
"""Scene throughput at the paper's scene size with the default backend.

Runs sample → simulate → render → label for N scenes of the paper's setup (700–1000 crushed-rock
particles on a 300 mm table, 512 px) in W worker processes (default: one per core), and prints
per-stage timings (median over scenes), peak memory per worker, the start-up cost of a stage
process (what each Snakemake job pays on top) and scenes per hour.

    .venv/bin/python bench/scene_throughput.py [--scenes 8] [--workers 2] [--resolution 512]
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
STAGES = ("sample", "simulate", "render", "label")


def one_scene(args: tuple) -> dict:
    from psdfactory import config as psd_config
    from psdfactory.config import load_config
    from psdfactory.scene.stages import run_label, run_render, run_sample, run_simulate

    config_path, resolution, index, root = args
    cfg = load_config(config_path)
    cfg["render"]["resolution"] = resolution
    d = Path(root) / "train" / "scenes" / f"train-{index:06d}"
    steps = [
        ("sample", run_sample, psd_config.sample_params(cfg, "train", index)),
        ("simulate", run_simulate, psd_config.simulate_params(cfg)),
        ("render", run_render, psd_config.render_params(cfg)),
        ("label", run_label, psd_config.label_params(cfg)),
    ]
    out = {"index": index}
    for name, fn, params in steps:
        t0 = time.perf_counter()
        res = fn(params, d)  # (the stages' log records: not shown, logging is not configured here)
        out[name] = time.perf_counter() - t0
        if name == "sample":
            out["n"] = res["samplesize"]
        if name == "simulate":
            out["attempts"] = res["attempt"] + 1
            out["steps"] = res["steps"]
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return out


def startup_cost(repeats: int = 5) -> float:
    exe = Path(sys.executable).with_name("psdfactory")
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        subprocess.run([str(exe), "--version"], check=True, capture_output=True)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def import_cost(repeats: int = 5) -> float:
    code = ("import psdfactory.scene.stages, psdfactory.scene.physics, psdfactory.scene.render, pybullet, "
            "scipy.ndimage, pyarrow.parquet")
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-c", code], check=True, capture_output=True)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", type=int, default=8)
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--resolution", type=int, default=512)
    ap.add_argument("--config", default=str(REPO / "config" / "paper.yaml"))
    a = ap.parse_args()

    rows = []
    with tempfile.TemporaryDirectory() as root:
        t0 = time.perf_counter()
        with ProcessPoolExecutor(a.workers) as pool:
            futs = [pool.submit(one_scene, (a.config, a.resolution, i, root)) for i in range(a.scenes)]
            for k, f in enumerate(as_completed(futs), 1):
                rows.append(f.result())
                el = time.perf_counter() - t0
                rate = k / el
                print(f"  scene {k}/{a.scenes}: {rows[-1]['n']} particles, "
                      f"{sum(rows[-1][s] for s in STAGES):.1f} s | {rate * 3600:.0f} scenes/h, "
                      f"ETA {(a.scenes - k) / rate:.0f} s", flush=True)
        wall = time.perf_counter() - t0

    start = startup_cost()
    imports = import_cost()
    print()
    print(f"Scene throughput: paper setup ({a.config}), {a.resolution} px, backend tiny, "
          f"{a.scenes} scenes, {a.workers} workers on {os.cpu_count()} cores")
    print(f"{'stage':<10} {'median s':>9} {'min s':>7} {'max s':>7}")
    for s in STAGES:
        v = [r[s] for r in rows]
        print(f"{s:<10} {statistics.median(v):>9.2f} {min(v):>7.2f} {max(v):>7.2f}")
    tot = [sum(r[s] for s in STAGES) for r in rows]
    print(f"{'total':<10} {statistics.median(tot):>9.2f} {min(tot):>7.2f} {max(tot):>7.2f}")
    print(f"particles per scene: median {statistics.median(r['n'] for r in rows):.0f}; "
          f"simulation steps: median {statistics.median(r['steps'] for r in rows):.0f}; "
          f"scenes needing a retry: {sum(r['attempts'] > 1 for r in rows)}")
    print(f"peak RSS per worker: {max(r['peak_rss_mb'] for r in rows):.0f} MB")
    print(f"stage process start-up: `psdfactory --version` {start:.2f} s, "
          f"stage imports {imports:.2f} s (median of 5) → ×4 per scene in the workflow")
    per_scene_in_process = wall / a.scenes
    print(f"in-process throughput: {3600 / per_scene_in_process:.0f} scenes/hour "
          f"({per_scene_in_process:.2f} s wall per scene with {a.workers} workers)")
    with_startup = per_scene_in_process + 4 * imports / a.workers
    print(f"with 4 stage processes per scene: ~{3600 / with_startup:.0f} scenes/hour")


if __name__ == "__main__":
    main()
