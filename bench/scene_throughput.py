#!/usr/bin/env python
"""Scene throughput at the paper's scene size with the default backend, and the settled pile's quality.

Runs sample → simulate → render → label for N scenes of a config (default config/paper.yaml:
crushed rock on a 300 mm table, 512 px) in W worker processes (default: one per core), and prints
per-stage timings (median over scenes, wall and CPU), the physics quality figures of every settled
pile (settled fraction, worst penetration, mean resting height of the particles' centres, lowest
point, steps, retries), peak memory per worker, the start-up cost of a stage process and scenes
per hour.

--compare REF runs the same scenes a second time with the code of git revision REF (its src/,
extracted with `git archive`), interleaved in rounds of W scenes so that both see the same load
(on a shared machine the absolute times drift; the ratios are the result), and prints both side
by side: the stages, scenes per hour, the quality figures, and whether the sample stage's outputs
are identical. --against REV compares with another revision instead of this working tree.

--shape-library K runs the scenes with ``shape_library: K`` (the dataset's particles drawn from K
shapes made once per worker process or batch job; with --compare, on both sides); two values
(e.g. ``--shape-library 0 2048``) run this tree twice, one side each, interleaved as --compare does.

--dag N also runs the workflow (`snakemake -j2 scenes`: every stage in scenes_per_job batches,
the manifests and contact sheets) on N scenes of the config with each side's code, alternately,
and prints the wall time and scenes per hour.

    .venv/bin/python bench/scene_throughput.py [--scenes 8] [--workers 2] [--resolution 512]
    .venv/bin/python bench/scene_throughput.py --compare a7657c7 --scenes 16 --dag 50
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
STAGES = ("sample", "simulate", "render", "label")
QUALITY = ("settled_fraction", "worst_penetration_mm", "mean_height_mm", "lowest_point_mm", "steps", "attempt")


def _use_tree(src: str) -> None:
    """Worker initializer: import psdfactory from `src` (a revision's src/ folder)."""
    sys.path.insert(0, src)


def one_scene(args: tuple) -> dict:
    import numpy as np

    from psdfactory import config as psd_config
    from psdfactory.config import load_config
    from psdfactory.scene.stages import load_poses, run_label, run_render, run_sample, run_simulate

    config_path, resolution, count, index, root, library = args
    cfg = load_config(config_path)
    cfg["render"]["resolution"] = resolution
    if count:
        cfg["datasets"]["train"]["count"] = list(count)
    if library is not None:
        cfg["datasets"]["train"]["shape_library"] = library
    d = Path(root) / "train" / "scenes" / f"train-{index:06d}"
    steps = [
        ("sample", run_sample, psd_config.sample_params(cfg, "train", index)),
        ("simulate", run_simulate, psd_config.simulate_params(cfg)),
        ("render", run_render, psd_config.render_params(cfg)),
        ("label", run_label, psd_config.label_params(cfg)),
    ]
    out = {"index": index}
    for name, fn, params in steps:
        t0, c0 = time.perf_counter(), time.process_time()
        res = fn(params, d)  # (the stages' log records: not shown, logging is not configured here)
        out[name], out[name + "_cpu"] = time.perf_counter() - t0, time.process_time() - c0
        if name == "sample":
            out["n"] = res["samplesize"]
        if name == "simulate":
            out.update({k: res[k] for k in QUALITY if k in res})
            out["mean_height_mm"] = float(np.mean(load_poses(d)[0][:, 2]))
    out["labels"] = json.loads((d / "labels.json").read_text())
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return out


def startup_cost(env: dict, repeats: int = 5) -> float:
    exe = Path(sys.executable).with_name("psdfactory")
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        subprocess.run([str(exe), "--version"], check=True, capture_output=True, env=env)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def import_cost(env: dict, repeats: int = 5) -> float:
    code = ("import psdfactory.scene.stages, psdfactory.scene.physics, psdfactory.scene.render, pybullet, "
            "scipy.ndimage, pyarrow.parquet")
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, env=env)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


class Side:
    """One revision's code: its src/ folder, a worker pool importing it, its scenes and times."""

    def __init__(self, name: str, tree: Path, workers: int, root: Path, library: int | None = None):
        self.name, self.tree, self.root, self.library = name, tree, root, library
        self.pool = ProcessPoolExecutor(workers, mp_context=get_context("spawn"), initializer=_use_tree,
                                        initargs=(str(tree / "src"),))
        self.rows: list[dict] = []
        self.wall = 0.0
        self.env = {**os.environ, "PYTHONPATH": str(tree / "src")}

    def run(self, config: str, resolution: int, count, indices: list[int]) -> None:
        t0 = time.perf_counter()
        futs = [self.pool.submit(one_scene, (config, resolution, count, i, str(self.root), self.library))
                for i in indices]
        self.rows += [f.result() for f in futs]
        self.wall += time.perf_counter() - t0


def extract(rev: str, dest: Path) -> Path:
    """The files of git revision `rev` that the scenes and the workflow need, under `dest`."""
    dest.mkdir(parents=True)
    have = subprocess.run(["git", "-C", str(REPO), "ls-tree", "--name-only", rev], check=True, capture_output=True,
                          text=True).stdout.split()
    paths = [p for p in have if p not in ("tests", "docs", "bench", ".ci")]  # the package and the workflow
    archive = subprocess.run(["git", "-C", str(REPO), "archive", rev, *paths], check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)
    return dest


def describe(rev: str | None) -> str:
    """A revision's short hash, or the working tree's HEAD and whether src/ differs from it."""
    if rev is None:
        dirty = subprocess.run(["git", "-C", str(REPO), "status", "--porcelain", "--", "src"], capture_output=True,
                               text=True).stdout.strip()
        return f"the working tree (HEAD {describe('HEAD')}{', src/ modified' if dirty else ''})"
    return subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", rev], capture_output=True, text=True,
                          check=True).stdout.strip()


def library_cost(config: str, size: int) -> float:
    """Seconds of CPU to make and measure the config's train set's shape library of `size` shapes."""
    from psdfactory import config as psd_config
    from psdfactory.config import load_config
    from psdfactory.scene.sampling import SampleParams, dataset_library

    cfg = load_config(config)
    cfg["datasets"]["train"]["shape_library"] = size
    p = SampleParams.from_dict(psd_config.sample_params(cfg, "train", 0))
    c0 = time.process_time()
    dataset_library(p)
    return time.process_time() - c0


def med(rows: list[dict], key: str) -> float:
    return statistics.median(r[key] for r in rows)


def print_side(s: Side, a: argparse.Namespace) -> None:
    print(f"{'stage':<10} {'median s':>9} {'min s':>7} {'max s':>7} {'cpu s':>7}")
    for st in STAGES:
        v = [r[st] for r in s.rows]
        print(f"{st:<10} {statistics.median(v):>9.2f} {min(v):>7.2f} {max(v):>7.2f} {med(s.rows, st + '_cpu'):>7.2f}")
    tot = [sum(r[st] for st in STAGES) for r in s.rows]
    print(f"{'total':<10} {statistics.median(tot):>9.2f} {min(tot):>7.2f} {max(tot):>7.2f}")
    print(f"particles per scene: median {med(s.rows, 'n'):.0f}; simulation steps: median {med(s.rows, 'steps'):.0f}; "
          f"scenes needing a retry: {sum(r['attempt'] > 0 for r in s.rows)}")
    print(f"peak RSS per worker: {max(r['peak_rss_mb'] for r in s.rows):.0f} MB")
    print(f"in-process throughput: {3600 * len(s.rows) / s.wall:.0f} scenes/hour "
          f"({s.wall / len(s.rows):.2f} s wall per scene with {a.workers} workers)")


def quality_table(sides: list[Side]) -> None:
    """The settled piles, side by side: per scene figures summarised over the scenes."""
    def col(s: Side, k: str) -> list[float]:
        return [float(r[k]) for r in s.rows]

    lines = [
        ("settled fraction, mean", lambda s: f"{statistics.mean(col(s, 'settled_fraction')):.4f}"),
        ("settled fraction, lowest", lambda s: f"{min(col(s, 'settled_fraction')):.4f}"),
        ("worst penetration mm, median", lambda s: f"{statistics.median(col(s, 'worst_penetration_mm')):.3f}"),
        ("worst penetration mm, worst", lambda s: f"{max(col(s, 'worst_penetration_mm')):.3f}"),
        ("mean resting height mm, mean", lambda s: f"{statistics.mean(col(s, 'mean_height_mm')):.3f}"),
        ("lowest point mm, lowest", lambda s: f"{min(col(s, 'lowest_point_mm')):.3f}"),
        ("simulation steps, median", lambda s: f"{statistics.median(col(s, 'steps')):.0f}"),
        ("scenes retried", lambda s: f"{sum(a > 0 for a in col(s, 'attempt'))}"),
    ]
    print(f"{'physics quality (' + str(len(sides[0].rows)) + ' scenes)':<32}" + "".join(f"{s.name:>16}" for s in sides))
    for label, fn in lines:
        print(f"{label:<32}" + "".join(f"{fn(s):>16}" for s in sides))
    if len(sides) == 2:
        a, b = ({r["index"]: r for r in s.rows} for s in sides)
        ratio = [b[i]["mean_height_mm"] / a[i]["mean_height_mm"] for i in a]
        print(f"mean resting height {sides[1].name} / {sides[0].name}: {statistics.mean(ratio):.4f} "
              f"(scenes {min(ratio):.3f}-{max(ratio):.3f})")


def same_samples(sides: list[Side]) -> str:
    import numpy as np

    a, b = sides
    differ = 0
    for r in a.rows:
        d = f"train/scenes/train-{r['index']:06d}"
        ga, gb = np.load(a.root / d / "geometry.npz"), np.load(b.root / d / "geometry.npz")
        sa = json.loads((a.root / d / "spec.json").read_text())
        sb = json.loads((b.root / d / "spec.json").read_text())
        sa.pop("psdfactory_version", None), sb.pop("psdfactory_version", None)
        differ += sa != sb or set(ga) != set(gb) or any(not np.array_equal(ga[k], gb[k]) for k in ga)
    return f"{len(a.rows) - differ} of {len(a.rows)} scenes identical (spec.json, geometry.npz)"


def dag_config(a: argparse.Namespace, results: Path, n: int, library: int | None = None) -> dict:
    import yaml

    cfg = yaml.safe_load(Path(a.config).read_text())
    train = cfg["datasets"]["train"]
    train.update(n_scenes=n, shard_size=n)
    if a.count:
        train["count"] = list(a.count)
    if library is not None:
        train["shape_library"] = library
    cfg["datasets"] = {"train": train}  # a re-render for Cycles (paper.yaml's train_cycles) left out
    cfg["results"] = str(results)
    cfg.setdefault("render", {})["resolution"] = a.resolution
    if a.scenes_per_job:
        cfg["scenes_per_job"] = a.scenes_per_job
    return cfg


def dag_run(side: Side, cfg: dict, work: Path) -> float:
    import yaml

    work.mkdir(parents=True)
    (work / "config.yaml").write_text(yaml.safe_dump(cfg))
    snakemake = str(Path(sys.executable).with_name("snakemake"))
    t0 = time.perf_counter()
    r = subprocess.run([snakemake, "-s", str(side.tree / "Snakefile"), "-d", str(work), "-j2", "scenes", "-q",
                        "--configfile", str(work / "config.yaml")], capture_output=True, text=True, env=side.env)
    wall = time.perf_counter() - t0
    if r.returncode:
        sys.exit(f"snakemake ({side.name}) failed:\n{r.stderr[-3000:]}")
    return wall


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", type=int, default=8)
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--resolution", type=int, default=512)
    ap.add_argument("--config", default=str(REPO / "config" / "paper.yaml"))
    ap.add_argument("--count", type=int, nargs=2, metavar=("LO", "HI"),
                    help="particles per scene instead of the config's")
    ap.add_argument("--compare", metavar="REF", help="also run git revision REF's code on the same scenes")
    ap.add_argument("--against", metavar="REV", help="the new side: git revision REV instead of this working tree")
    ap.add_argument("--dag", type=int, default=0, metavar="N", help="also run the workflow on N scenes per side")
    ap.add_argument("--dag-repeats", type=int, default=1)
    ap.add_argument("--scenes-per-job", type=int, help="the workflow's batches (default: the config's)")
    ap.add_argument("--shape-library", type=int, nargs="+", metavar="K",
                    help="shape_library of the scenes; two values: two sides of this tree (e.g. 0 2048)")
    a = ap.parse_args()
    if a.shape_library and len(a.shape_library) > 2:
        ap.error("--shape-library takes one or two values")
    if a.shape_library and len(a.shape_library) == 2 and (a.compare or a.against):
        ap.error("--shape-library with two values compares this tree with itself: not with --compare/--against")
    a.config = str(Path(a.config).resolve())

    with tempfile.TemporaryDirectory(prefix="scene_throughput-") as tmp:
        tmp = Path(tmp)
        new_tree = extract(a.against, tmp / "new-code") if a.against else REPO
        libs = a.shape_library or [None]
        if len(libs) == 2:
            sides = [Side(f"library {k}", REPO, a.workers, tmp / f"lib{k}", k) for k in libs]
            print(f"both sides: {describe(None)}; shape_library {libs[0]} and {libs[1]}")
            print(f"building a library of {libs[1]} shapes takes {library_cost(a.config, libs[1]):.2f} s "
                  "(once per worker process or batch job; included in the workflow's figures, and in the "
                  "first scene of each worker below)")
        else:
            sides = [Side("after" if a.compare else "now", new_tree, a.workers, tmp / "new", libs[0])]
            print(f"{sides[0].name}: {describe(a.against)}")
        if a.compare:
            sides.insert(0, Side("before", extract(a.compare, tmp / "old-code"), a.workers, tmp / "old", libs[0]))
            print(f"before: {describe(a.compare)}")
        indices = list(range(a.scenes))  # (--scenes 0: only the workflow)
        t0 = time.perf_counter()
        for k, lo in enumerate(range(0, a.scenes, a.workers)):
            chunk = indices[lo:lo + a.workers]
            for s in (sides if k % 2 == 0 else sides[::-1]):  # alternate who goes first
                s.run(a.config, a.resolution, a.count, chunk)
            el = time.perf_counter() - t0
            print(f"  scenes {lo + len(chunk)}/{a.scenes} on {len(sides)} side(s), {el:.0f} s", flush=True)

        print(f"\nScene throughput: {a.config}{f' with {a.count[0]}-{a.count[1]} particles' if a.count else ''}, "
              f"{a.resolution} px, backend tiny, {a.scenes} scenes, {a.workers} workers on {os.cpu_count()} cores")
        for s in sides if a.scenes else ():
            print(f"\n[{s.name}]")
            print_side(s, a)
        print()
        if a.scenes:
            quality_table(sides)
        if len(sides) == 2 and a.scenes:
            if sides[0].library == sides[1].library:
                print(f"sample stage: {same_samples(sides)}")
            else:
                print("sample stage: other shapes by design (another shape_library)")
            old, new = sides
            print(f"\n{'':<28}{old.name:>16}{new.name:>16}{'ratio':>8}")
            for st in STAGES:
                mo, mn = med(old.rows, st + "_cpu"), med(new.rows, st + "_cpu")
                print(f"{st + ' cpu s, median':<28}{mo:>16.2f}{mn:>16.2f}{mn / mo:>8.2f}")
            co, cn = (3600 * a.workers / sum(med(s.rows, st + "_cpu") for st in STAGES) for s in sides)
            print(f"{'CPU-bound scenes/hour':<28}{co:>16.0f}{cn:>16.0f}{cn / co:>8.2f}"
                  "   (workers x 3600 / summed stage CPU medians)")
            ho, hn = 3600 * len(old.rows) / old.wall, 3600 * len(new.rows) / new.wall
            print(f"{'in-process scenes/hour':<28}{ho:>16.0f}{hn:>16.0f}{hn / ho:>8.2f}")

        for s in sides:
            start, imports = startup_cost(s.env), import_cost(s.env)
            print(f"{s.name}: stage process start-up: `psdfactory --version` {start:.2f} s, "
                  f"stage imports {imports:.2f} s (median of 5)")

        if a.dag:
            walls: dict[str, list[float]] = {s.name: [] for s in sides}
            for rep in range(a.dag_repeats):
                for s in (sides if rep % 2 == 0 else sides[::-1]):
                    work = tmp / f"dag-{rep}-{len(walls[s.name])}-{s.name.split()[0]}"
                    walls[s.name].append(dag_run(s, dag_config(a, work / "results", a.dag, s.library), work))
                    shutil.rmtree(work, ignore_errors=True)
                    print(f"  workflow, {s.name}: {a.dag} scenes in {walls[s.name][-1]:.0f} s", flush=True)
            per_job = a.scenes_per_job or dag_config(a, tmp, a.dag).get("scenes_per_job", 1)
            print(f"\nThrough the workflow (snakemake -j2 scenes, {a.dag} scenes, scenes_per_job {per_job}, "
                  f"median of {a.dag_repeats}):")
            rates = {}
            for s in sides:
                w = statistics.median(walls[s.name])
                rates[s.name] = 3600 * a.dag / w
                print(f"  {s.name}: {w:.0f} s wall, {rates[s.name]:.0f} scenes/hour")
            if len(sides) == 2:
                print(f"  ratio: {rates[sides[1].name] / rates[sides[0].name]:.2f}")
        for s in sides:
            s.pool.shutdown()


if __name__ == "__main__":
    main()
