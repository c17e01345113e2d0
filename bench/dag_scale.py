#!/usr/bin/env python
"""Scale of the DAG: how long Snakemake takes to plan N scenes, and the per-job overhead.

1. Dry run (`snakemake -n`, whole workflow) for 1,000 / 10,000 / 50,000 scenes: seconds
   (median of --repeats runs) and jobs planned, with one job per scene and stage
   (scenes_per_job: 1) and with batches (scenes_per_job: 50), side by side. One job per scene
   is skipped above --max-per-scene scenes (50,000 take ~7 minutes to plan).
2. A local run of a tiny dataset (10 particles, 32 px) with -j2 in both modes: wall time, and
   for one job per scene the overhead per job (wall time minus the time the stages report).

    .venv/bin/python bench/dag_scale.py [--sizes 1000 10000 50000] [--repeats 3]
"""

from __future__ import annotations

import argparse
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
SNAKEMAKE = str(Path(sys.executable).with_name("snakemake"))


def config(n: int, results: Path, shard: int = 250, per_job: int = 1) -> dict:
    return {
        "results": str(results),
        "seed": 1,
        "scenes_per_job": per_job,
        "datasets": {"train": {"n_scenes": n, "shard_size": shard, "table_size": 40, "count": [8, 10],
                               "size": {"mean": [4, 6], "sigma": [1, 2], "bounds": [1, 8]}}},
        "render": {"resolution": 32},
        "train": {"architectures": ["resnet18"], "epochs": 1, "input_size": {"resnet18": 32}, "pretrained": "none"},
    }


def run(args: list[str], work: Path) -> tuple[float, str]:
    t0 = time.perf_counter()
    r = subprocess.run([SNAKEMAKE, "-s", str(REPO / "Snakefile"), "-d", str(work), *args],
                       capture_output=True, text=True)
    dt = time.perf_counter() - t0
    if r.returncode != 0:
        sys.exit(f"snakemake failed:\n{r.stderr[-2000:]}")
    return dt, r.stdout + r.stderr


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000, 50000])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--local-scenes", type=int, default=20)
    ap.add_argument("--batch", type=int, default=50, help="scenes_per_job of the batched mode")
    ap.add_argument("--max-per-scene", type=int, default=10000, help="largest size planned with one job per scene")
    a = ap.parse_args()

    print("Dry run of the whole workflow (snakemake -n), median of runs:")
    print(f"{'scenes':>8} {'scenes/job':>10} {'jobs':>8} {'median s':>9} {'runs':>18}")
    for n in a.sizes:
        for per_job in (1, a.batch):
            if per_job == 1 and n > a.max_per_scene:
                continue
            with tempfile.TemporaryDirectory() as d:
                work = Path(d)
                cfg = work / "c.yaml"
                cfg.write_text(yaml.safe_dump(config(n, work / "results", per_job=per_job)))
                times, jobs = [], "?"
                for _ in range(a.repeats):
                    dt, out = run(["-n", "-q", "rules", "--configfile", str(cfg)], work)
                    times.append(dt)
                    m = re.search(r"^total\s+(\d+)", out, re.M)
                    jobs = m.group(1) if m else jobs
                print(f"{n:>8} {per_job:>10} {jobs:>8} {statistics.median(times):>9.1f} "
                      f"{', '.join(f'{t:.1f}' for t in times):>18}", flush=True)

    n = a.local_scenes
    print(f"\nLocal run of {n} tiny scenes with -j2 (stages, manifest, contact sheet):")
    for per_job in (1, a.batch):
        with tempfile.TemporaryDirectory() as d:
            work = Path(d)
            cfg = work / "c.yaml"
            cfg.write_text(yaml.safe_dump(config(n, work / "results", shard=n, per_job=per_job)))
            dt, out = run(["-j2", "scenes", "--configfile", str(cfg)], work)
            stage_s = 0.0
            for log in (work / "results" / "train" / "logs").rglob("*.log"):
                for m in re.finditer(r"\((\d+\.\d+) s\)|, (\d+\.\d+) s$", log.read_text(), re.M):
                    stage_s += float(m.group(1) or m.group(2))
            m = re.search(r"^(\d+) of \1 steps", out, re.M)
            jobs = int(m.group(1)) if m else 0
            print(f"  scenes_per_job {per_job:>3}: {jobs:>4} jobs, {dt:.1f} s wall; the stages report "
                  f"{stage_s:.1f} s of work, so the overhead is ~{(2 * dt - stage_s) / max(jobs, 1):.2f} "
                  "core-seconds per job (process start-up, imports, Snakemake's bookkeeping)", flush=True)


if __name__ == "__main__":
    main()
