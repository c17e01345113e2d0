#!/usr/bin/env python
"""Scale of the DAG: how long Snakemake takes to plan N scenes, and the per-job overhead.

1. Dry run (`snakemake -n`, whole workflow) for 1,000 / 10,000 / 50,000 scenes: seconds
   (median of --repeats runs) and jobs planned.
2. Per-job overhead of a local run: a tiny dataset (10 particles, 32 px) run with -j2; its
   wall time minus the time the stages themselves report, per job.

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


def config(n: int, results: Path, shard: int = 250) -> dict:
    return {
        "results": str(results),
        "seed": 1,
        "datasets": {"train": {"n_scenes": n, "shard_size": shard, "table_size": 40, "count": [8, 10],
                               "size": {"mean": [4, 6], "sigma": [1, 2], "bounds": [1, 8]}}},
        "render": {"resolution": 32},
        "train": {"architectures": ["resnet18"], "epochs": 1, "input_size": {"resnet18": 32}, "pretrained": "none"},
    }


def run(args: list[str], work: Path) -> tuple[float, str]:
    t0 = time.perf_counter()
    r = subprocess.run([SNAKEMAKE, "-s", str(REPO / "Snakefile"), "-d", str(work), *args], capture_output=True, text=True)
    dt = time.perf_counter() - t0
    if r.returncode != 0:
        sys.exit(f"snakemake failed:\n{r.stderr[-2000:]}")
    return dt, r.stdout + r.stderr


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000, 50000])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--local-scenes", type=int, default=20)
    a = ap.parse_args()

    print("Dry run of the whole workflow (snakemake -n):")
    print(f"{'scenes':>8} {'jobs':>8} {'median s':>9} {'runs':>18}")
    for n in a.sizes:
        with tempfile.TemporaryDirectory() as d:
            work = Path(d)
            cfg = work / "c.yaml"
            cfg.write_text(yaml.safe_dump(config(n, work / "results")))
            times, jobs = [], "?"
            for _ in range(a.repeats):
                dt, out = run(["-n", "-q", "rules", "--configfile", str(cfg)], work)
                times.append(dt)
                m = re.search(r"^total\s+(\d+)", out, re.M)
                jobs = m.group(1) if m else jobs
            print(f"{n:>8} {jobs:>8} {statistics.median(times):>9.1f} {', '.join(f'{t:.1f}' for t in times):>18}", flush=True)

    n = a.local_scenes
    with tempfile.TemporaryDirectory() as d:
        work = Path(d)
        cfg = work / "c.yaml"
        cfg.write_text(yaml.safe_dump(config(n, work / "results", shard=n)))
        dt, out = run(["-j2", "scenes", "--configfile", str(cfg)], work)
        stage_s = 0.0
        for log in (work / "results" / "train" / "logs").rglob("*.log"):
            for m in re.finditer(r"\((\d+\.\d+) s\)|, (\d+\.\d+) s$", log.read_text(), re.M):
                stage_s += float(m.group(1) or m.group(2))
        jobs = 4 * n + 2
        print(f"\nLocal run, {n} tiny scenes ({jobs} jobs) with -j2: {dt:.1f} s wall, "
              f"{dt * 2 / jobs:.2f} core-seconds per job; the stages report {stage_s:.1f} s of work in all, "
              f"so the overhead is ~{(2 * dt - stage_s) / jobs:.2f} core-seconds per job "
              "(process start-up, imports, Snakemake's scheduling and bookkeeping)")


if __name__ == "__main__":
    main()
