"""Soak: a dataset made under random `kill -9`, resumed each time, ends identical to one made
in a single run.

N scenes of a tiny config (`snakemake scenes`: sample, simulate, render, label, manifests,
contact sheet) are made twice in a scratch folder: once straight through, and once with the whole
Snakemake process group (Snakemake and every job it runs) killed with SIGKILL after a random
delay, then `snakemake --unlock` and a rerun with `--rerun-incomplete`, again and again until a
run finishes. Then every output file of the two runs is compared by hash (logs and the run lock
aside; simulate.json without its wall-clock seconds, a batch stamp without its time and the list
of scenes its last run made). Prints the kills, resumes, wall times and
how many files are identical, different, missing or extra; exits 1 unless all are identical.

    .venv/bin/python bench/soak.py                                  # 500 scenes, one job per scene
    .venv/bin/python bench/soak.py --scenes 200 --scenes-per-job 20 --kill-after 5 30
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
SNAKEMAKE = str(Path(sys.executable).with_name("snakemake"))
LOCK_NAME = ".psdfactory.lock"


def tiny_config(n_scenes: int, scenes_per_job: int, seed: int) -> dict:
    """Scenes of 10-14 particles at 48 px: seconds of physics and rendering, hundreds of files."""
    return {
        "seed": seed,
        "results": "results",
        "scenes_per_job": scenes_per_job,
        "datasets": {"soak": {"n_scenes": n_scenes, "shard_size": 50, "table_size": 40, "count": [10, 14],
                              "size": {"mean": [4, 6], "sigma": [1, 2], "bounds": [1, 8]}}},
        "render": {"resolution": 48},
        "train": {"datasets": ["soak"]},
        "show": {"compare_backends": 0},
    }


def command(work: Path, jobs: int, *extra: str) -> list[str]:
    return [SNAKEMAKE, "-s", str(REPO / "Snakefile"), "-d", str(work), f"-j{jobs}", "scenes", "--configfile",
            str(work / "c.yaml"), *extra]


def start(cmd: list[str], work: Path, log) -> subprocess.Popen:
    """A Snakemake run in its own process group (so that one killpg reaches every job)."""
    return subprocess.Popen(cmd, cwd=work, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)


def straight_run(work: Path, jobs: int) -> float:
    t0 = time.perf_counter()
    with open(work / "snakemake.log", "w") as log:
        rc = start(command(work, jobs), work, log).wait()
    if rc != 0:
        raise SystemExit(f"the uninterrupted run failed (exit {rc}); see {work / 'snakemake.log'}")
    return time.perf_counter() - t0


def killed_run(work: Path, jobs: int, kill_after: tuple[float, float], rng: random.Random,
               max_runs: int) -> tuple[float, int, list[float]]:
    """Runs until one finishes, each killed (SIGKILL to the group) after a random delay unless it
    finishes first. Returns the wall time, the number of runs and the kill times."""
    t0, kills = time.perf_counter(), []
    with open(work / "snakemake.log", "w") as log:
        for run in range(max_runs):
            extra = ("--rerun-incomplete",) if run else ()
            proc = start(command(work, jobs, *extra), work, log)
            delay = rng.uniform(*kill_after)
            try:
                rc = proc.wait(timeout=delay)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
                kills.append(round(time.perf_counter() - t0, 1))
                print(f"  kill {len(kills)} at {kills[-1]:.0f} s (after {delay:.0f} s of run {run + 1})", flush=True)
                unlock = subprocess.run(command(work, jobs, "--unlock"), cwd=work, stdout=log, stderr=subprocess.STDOUT)
                if unlock.returncode != 0:
                    raise SystemExit(f"snakemake --unlock failed; see {work / 'snakemake.log'}") from None
                continue
            if rc != 0:
                raise SystemExit(f"run {run + 1} failed (exit {rc}) rather than being killed; see "
                                 f"{work / 'snakemake.log'}")
            return time.perf_counter() - t0, run + 1, kills
    raise SystemExit(f"no run finished within {max_runs} runs: raise --kill-after")


def digest(path: Path) -> str:
    """A file's hash, leaving out what is not reproducible: simulate.json's wall-clock seconds,
    and a batch stamp's time and the list of scenes its last run made (a resumed batch makes
    only those the killed one had not finished)."""
    data = path.read_bytes()
    drop = (("wall_s",) if path.name == "simulate.json" and path.parent.name != "stages"
            else ("seconds", "ran") if path.parent.parent.name == "batches" else ())
    if drop:
        d = json.loads(data)
        for k in drop:
            d.pop(k, None)
        data = json.dumps(d, sort_keys=True).encode()
    return hashlib.sha256(data).hexdigest()


def tree(results: Path) -> dict[str, str]:
    """Every output file's hash, by path under the results root (not the logs, not the lock)."""
    return {str(p.relative_to(results)): digest(p) for p in sorted(results.rglob("*"))
            if p.is_file() and "logs" not in p.relative_to(results).parts and p.name != LOCK_NAME}


def compare(a: dict[str, str], b: dict[str, str]) -> dict[str, int]:
    return {"identical": sum(a[k] == b[k] for k in a.keys() & b.keys()),
            "different": sum(a[k] != b[k] for k in a.keys() & b.keys()),
            "missing": len(a.keys() - b.keys()), "extra": len(b.keys() - a.keys())}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", type=int, default=500)
    ap.add_argument("--scenes-per-job", type=int, default=1, help="the config's scenes_per_job (1: one job per scene)")
    ap.add_argument("--jobs", type=int, default=2, help="snakemake -j")
    ap.add_argument("--kill-after", type=float, nargs=2, default=(30.0, 180.0), metavar=("MIN", "MAX"),
                    help="each run is killed after a uniform random delay in [MIN, MAX] seconds")
    ap.add_argument("--max-runs", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0, help="of the kill delays (the config's seed is fixed)")
    ap.add_argument("--work", type=Path, help="scratch folder (default: a temporary one, removed at the end)")
    a = ap.parse_args()

    work = a.work or Path(tempfile.mkdtemp(prefix="psd-soak-"))
    cfg = tiny_config(a.scenes, a.scenes_per_job, seed=3)
    print(f"soak: {a.scenes} scenes, scenes_per_job {a.scenes_per_job}, -j{a.jobs}, kill -9 after "
          f"{a.kill_after[0]:g}-{a.kill_after[1]:g} s, in {work}", flush=True)
    try:
        for name in ("straight", "killed"):
            (work / name).mkdir(parents=True, exist_ok=True)
            (work / name / "c.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
        wall_straight = straight_run(work / "straight", a.jobs)
        print(f"uninterrupted: {wall_straight:.0f} s", flush=True)
        wall_killed, runs, kills = killed_run(work / "killed", a.jobs, tuple(a.kill_after), random.Random(a.seed),
                                              a.max_runs)
        ref, got = tree(work / "straight" / "results"), tree(work / "killed" / "results")
        c = compare(ref, got)
        temps = [p for p in (work / "killed" / "results").rglob("*.tmp*")]
        print(f"killed and resumed: {len(kills)} kills, {runs - 1} resumes, {wall_killed:.0f} s "
              f"(uninterrupted {wall_straight:.0f} s)")
        print(f"files: {c['identical']} identical, {c['different']} different, {c['missing']} missing, "
              f"{c['extra']} extra (of {len(ref)}); {len(temps)} temporary files left")
        for k in sorted(k for k in ref.keys() & got.keys() if ref[k] != got[k])[:20]:
            print(f"  different: {k}")
        ok = c["identical"] == len(ref) == len(got)
        print("IDENTICAL" if ok else "NOT IDENTICAL")
        return 0 if ok else 1
    finally:
        if a.work is None:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
