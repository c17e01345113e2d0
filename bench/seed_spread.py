#!/usr/bin/env python
"""Run-to-run spread of every model over training seeds.

One training run says little: with the datasets fixed, the same recipe trained with another
seed reads the same test scenes differently (the instance estimator's read-out, d10 most of all,
moves by a few hundredths of R²; a CNN across renderers by much more). This script measures that
spread, so that a figure is quoted as mean ± spread, not as one draw:

1. the datasets are made once: `snakemake scenes` on the config (every scene, manifest and contact
   sheet; nothing is redone where the results folder already holds them), or, with
   --no-snakemake, an existing results folder is used as it is;
2. every architecture of `train.architectures` is trained once per seed, the way rules/train.smk
   trains it — `psdfactory train --params <train_params(config, arch)>` — with only the params'
   `seed` changed (the scenes keep the config's seed), into <results>/seed_spread/<seed>/<arch>/;
3. each model is evaluated as rules/evaluate.smk does (`psdfactory evaluate`, on every dataset the
   config evaluates: the training dataset's test split, the out-of-distribution set and the
   Cycles re-render of the test scenes in the default config), into .../<arch>/eval/, and on
   every photo set of the config's `photos` as rules/photos.smk does (`psdfactory
   evaluate-photos`), into .../<arch>/eval/photos/<set>/;
4. per model, dataset and target, R², the mean absolute error (mm) and the mean relative error
   |pred − true| / true over the seeds are printed and written as Markdown (spread.md) and JSON
   (spread.json) under --out: mean ± half-range, i.e. (max − min) / 2, and [min, max] in the
   JSON; per model and photo, the grain detection F1 (grain finders) and the error of
   d10/d50/d90 against the photo's reference, in mm and relative, in the reference's size
   definition where the model gives it (a CNN: its own).

Each model's seeds run back to back, the models in the order of --archs, and both files are
rewritten after every run (marked partial until the last), so a run cut short still holds the
whole spread of the models it got through; a row's `seeds` column says how many runs it holds
(one run is shown without a spread).

A run whose model.pt and metrics.json exist (with the same params, trained and scored on the same
scenes and labels: data.json beside params.json) is not redone, so a killed run resumes where it
stopped (training itself resumes from its checkpoints/last.pt). Progress lines,
each with the elapsed time and an ETA, go to stdout; each command's own log goes to the run's
train.log / eval/evaluate.log, Snakemake's to <out>/snakemake.log.

An arm that differs from a finished spread only in what the instance estimator does with its
trained network (train.instances' tta, sieve_method, readout, calibration_datasets:
config.CALIBRATION_SETTINGS) need not train it again: with --recalibrate-from <that spread's
seed_spread folder> each seed's network is taken from there and only calibrated again
(post-processing and read-out: minutes), so the
arm and its baseline share their networks seed for seed (--results: a folder of its own holding the
same datasets, e.g. hard links, `cp -al results_gravel/gravel arm/`).

    nice -n 10 .venv/bin/python bench/seed_spread.py                         # config/config.yaml, 3 seeds
    .venv/bin/python bench/seed_spread.py --seeds 5 --archs instances         # one model, 5 seeds
    .venv/bin/python bench/seed_spread.py --seed-list 42 7 11 --no-snakemake  # reuse results/ as it is
    .venv/bin/python bench/seed_spread.py --config config/gravel.yaml --no-snakemake --results arm/ \
        --set train.instances.tta=d4 --recalibrate-from results_gravel/seed_spread --out arm/spread

The datasets cost what `make demo`'s scenes do (the Cycles re-render needs .venv-blender: `make
blender`), and each seed what its training does (about 10 min on 2 idle AMD EPYC cores), plus the
evaluations; on cores shared with other work, many times that.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import re
import shutil
import subprocess
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
NAMES = ("d10", "d50", "d90")
ARCH_LABELS = {"instances": "instance estimator", "resnet50": "ResNet-50", "inception_v3": "InceptionV3",
               "efficientnet_b0": "EfficientNet-B0"}
BACKEND_LABELS = {"tiny": "TinyRenderer", "cycles": "Cycles"}


def commit() -> str:
    """The checkout's commit (and whether src/ or rules/ differ from it); where the tree is a
    copy without git (a GPU node), $PSD_COMMIT or "unknown"."""
    def git(*args: str) -> str:
        try:
            return subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True).stdout.strip()
        except OSError:
            return ""

    head = git("rev-parse", "--short", "HEAD")
    if not head:
        return os.environ.get("PSD_COMMIT", "unknown")
    dirty = git("status", "--porcelain", "--untracked-files=no", "--", "src", "rules")
    return head + (" (+ uncommitted changes in src/ or rules/)" if dirty else "")


def gpu_name() -> str | None:
    """The CUDA device the runs train on (device auto), if PyTorch sees one."""
    try:
        import torch
    except ImportError:
        return None
    return torch.cuda.get_device_name(0) if torch.cuda.is_available() else None


def fmt_time(s: float) -> str:
    s = max(0, int(round(s)))
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60}:{s % 60:02d}"


class Progress:
    """Progress lines with the elapsed time and an ETA, estimated per kind of run (an
    architecture's training, its evaluation) from the runs of that kind done so far."""

    def __init__(self, jobs: list[tuple[str, str]]):
        self.t0 = time.monotonic()
        self.jobs = jobs  # (kind, label) in the order they run
        self.done: dict[str, list[float]] = {}
        self.next = 0

    def eta(self, current_elapsed: float = 0.0, current_total: float | None = None) -> str:
        """`current_total`: the running job's own estimate of its length (from its epochs so far)."""
        left = 0.0
        unknown = 0
        all_done = [t for ts in self.done.values() for t in ts]
        for i, (kind, _) in enumerate(self.jobs[self.next:]):
            ts = self.done.get(kind)
            if i == 0 and current_total is not None:
                left += max(0.0, current_total - current_elapsed)
            elif ts:
                est = sum(ts) / len(ts)
                left += max(0.0, est - current_elapsed) if i == 0 else est
            elif all_done:
                left += sum(all_done) / len(all_done)
            else:
                unknown += 1
        if unknown == len(self.jobs) - self.next and unknown:
            return "ETA after the first run"
        return f"ETA {fmt_time(left)}" + (" (+ runs not yet timed)" if unknown else "")

    def say(self, msg: str, current_elapsed: float = 0.0, current_total: float | None = None) -> None:
        print(f"[{fmt_time(time.monotonic() - self.t0)}] [{self.next + 1}/{len(self.jobs)}] {msg} — "
              f"{self.eta(current_elapsed, current_total)}", flush=True)

    def finish(self, kind: str, seconds: float | None) -> None:
        """One run done (`seconds` None: kept from before, not timed now)."""
        if seconds:
            self.done.setdefault(kind, []).append(seconds)
        self.next += 1


def psdfactory_cmd() -> list[str]:
    exe = Path(sys.executable).with_name("psdfactory")
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "psdfactory.cli"]


def data_identity(results: Path, datasets: list[str]) -> str:
    """A hash of the scenes `datasets` hold (ids, splits and labels): a run trained or scored on
    other data — relabelled scenes, another split — is redone, not kept."""
    import hashlib

    from psdfactory.manifest import read_scenes
    from psdfactory.psd import TARGETS

    rows = []
    for ds in sorted(set(datasets)):
        t = read_scenes(results, ds).select(["scene_id", "split", *TARGETS]).to_pylist()
        rows += sorted((ds, r["scene_id"], r["split"], *(repr(r[k]) for k in TARGETS)) for r in t)
    return hashlib.sha256(json.dumps(rows).encode()).hexdigest()[:16]


def make_datasets(config_path: Path, jobs: int, log: Path) -> None:
    """`snakemake scenes` on the config: every dataset's scenes, manifests and contact sheets.
    Its output goes to `log`; its 'N of M steps' lines are echoed with an ETA."""
    snakemake = Path(sys.executable).with_name("snakemake")
    cmd = [str(snakemake) if snakemake.exists() else "snakemake", f"-j{jobs}", "scenes",
           "--configfile", str(config_path)]
    print(f"making the datasets: {' '.join(cmd)} (log: {log})", flush=True)
    log.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    last_print = 0.0
    with open(log, "w", encoding="utf-8") as f:
        proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        assert proc.stdout is not None
        for line in proc.stdout:
            f.write(line)
            m = re.search(r"(\d+) of (\d+) steps", line)
            now = time.monotonic()
            if m and (now - last_print > 30 or m.group(1) == m.group(2)):
                done, total = int(m.group(1)), int(m.group(2))
                el = now - t0
                eta = el / done * (total - done) if done else 0.0
                print(f"[{fmt_time(el)}] scenes: {done} of {total} jobs — ETA {fmt_time(eta)}", flush=True)
                last_print = now
        rc = proc.wait()
    if rc:
        sys.exit(f"snakemake failed (exit code {rc}); see {log}")
    print(f"datasets ready in {fmt_time(time.monotonic() - t0)}", flush=True)


def run_watched(cmd: list[str], progress: Progress, label: str, history: Path | None, epochs: int | None) -> float:
    """Run one command; every minute, a progress line (with the epoch reached, from history.csv)."""
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    next_line = t0 + 60
    while proc.poll() is None:
        time.sleep(2)
        if time.monotonic() >= next_line:
            next_line += 60
            epoch, total = "", None
            elapsed = time.monotonic() - t0
            if history is not None and history.is_file():
                n = max(0, len(history.read_text(encoding="utf-8").strip().splitlines()) - 1)
                epoch = f", epoch {n}/{epochs}" if epochs else f", epoch {n}"
                if n and epochs:  # this run's own pace (early stopping may end it sooner)
                    total = elapsed / n * epochs
            progress.say(f"{label}: running {fmt_time(elapsed)}{epoch}", elapsed, total)
    err = proc.stderr.read() if proc.stderr else ""
    if proc.returncode:
        sys.exit(f"{label} failed (exit code {proc.returncode}):\n{err.strip()[-2000:]}\ncommand: {' '.join(cmd)}")
    return time.monotonic() - t0


def aggregate(values: list[float]) -> dict:
    return {"mean": sum(values) / len(values), "min": min(values), "max": max(values),
            "half_range": (max(values) - min(values)) / 2, "n": len(values), "values": values}


def dataset_label(cfg: dict, ds: str, n_scenes: int | None) -> str:
    from psdfactory import config as psd_config

    backend = psd_config.dataset_render(cfg, ds)["backend"]
    label = f"{ds}: {BACKEND_LABELS.get(backend, backend)}"
    return label + (f", {n_scenes} scenes" if n_scenes else "")


def markdown(summary: dict) -> str:
    """Per model and dataset, R², MAE and relative error per target, mean ± half-range; per
    model and photo, F1 and the d-values' errors."""
    seeds = summary["seeds"]
    lines = [f"Per-target R², mean absolute error (mm) and mean relative error |pred − true| / true, "
             f"mean ± (max − min) / 2 over the "
             f"training seeds of each row (of {', '.join(map(str, seeds))}; a row of one seed is one run, no "
             f"spread); `{summary['command']}`, {summary['date'][:10]}, commit {summary['commit']}, "
             f"{summary['cpu']}" + (f", {summary['gpu']}" if summary.get("gpu") else "") + "."
             + ("" if summary["complete"] else " **Partial: not every run is done yet.**"), "",
             "| model | test scenes | seeds | R² d10 | R² d50 | R² d90 | "
             "error d10: MAE, rel. | error d50 | error d90 |",
             "|---|---|---|---|---|---|---|---|---|"]

    def cell(x: dict, scale: float = 1.0, digits: int = 2, unit: str = "") -> str:
        if x["n"] == 1:
            return f"{scale * x['mean']:.{digits}f}{unit}"
        return f"{scale * x['mean']:.{digits}f} ± {scale * x['half_range']:.{digits}f}{unit}"

    for arch, per_ds in summary["models"].items():
        for ds, m in per_ds.items():
            r2 = [cell(m[n]["r2"]) for n in NAMES]
            rel = [f"{cell(m[n]['mae'], unit=' mm')}, {cell(m[n]['rel_err'], 100, 0, ' %')}" for n in NAMES]
            lines.append(f"| {ARCH_LABELS.get(arch, arch)} | {summary['datasets'][ds]['label']} | "
                         f"{m['d10']['r2']['n']} | " + " | ".join(r2 + rel) + " |")
    if summary.get("photos"):
        lines += ["", "Photos: grain detection F1 at IoU ≥ 0.5 (grains cut by the border left out; grain finders "
                  "only), the median |error| of the matched grains' size (as drawn → against the reference "
                  "grains grown back by half their outline band, where the photo set declares one) and the "
                  "error pred − ref of d10/d50/d90 against the reference grains, in mm and "
                  "relative to ref, in the reference's size definition (a CNN reads its own).", "",
                  "| model | photo | seeds | F1 | matched grains' size error, median | error d10: mm, rel. | "
                  "error d50 | error d90 |",
                  "|---|---|---|---|---|---|---|---|"]
        for arch, per_photo in summary["photos"].items():
            for photo, m in per_photo.items():
                f1 = cell(m["f1"]) if m.get("f1") else "—"
                size = cell(m["size_err"], 100, 1, " %") if m.get("size_err") else "—"
                if m.get("f1_restored"):  # the photo set's outline_band_px: as drawn → outlines restored
                    f1 += f" → {cell(m['f1_restored'])}"
                    size += " → " + (cell(m["size_err_restored"], 100, 1, " %") if m.get("size_err_restored") else "—")
                rel = [f"{cell(m[n + '_mm'], digits=1, unit=' mm')}, {cell(m[n], 100, 0, ' %')}" for n in NAMES]
                lines.append(f"| {ARCH_LABELS.get(arch, arch)} | {photo} | {m['d50']['n']} | {f1} | {size} | "
                             + " | ".join(rel) + " |")
    if summary["train_minutes"]:  # none where every model was trained before, or calibrated again
        lines += ["", "Training minutes per run (mean over seeds): "
                  + ", ".join(f"{ARCH_LABELS.get(a, a)} {t:.1f}" for a, t in summary["train_minutes"].items()) + "."]
    return "\n".join(lines) + "\n"


def write_summary(out: Path, meta: dict, archs: list[str], seeds: list[int], datasets: list[str], cfg: dict,
                  metrics: dict, train_minutes: dict, complete: bool) -> str:
    """spread.json and spread.md from the runs done so far (rewritten after each one)."""
    summary: dict = {**meta, "seeds": seeds, "complete": complete,
                     "date": datetime.now(UTC).isoformat(timespec="seconds"),
                     "statistic": "mean, min, max and half_range = (max - min) / 2 over the seeds",
                     "datasets": {}, "models": {},
                     "train_minutes": {arch: sum(t) / len(t) for arch, t in train_minutes.items() if t}}
    for arch in archs:
        per_ds: dict = {}
        for ds in datasets:
            runs = [metrics[arch][s]["datasets"][ds] for s in seeds
                    if s in metrics.get(arch, {}) and ds in metrics[arch][s]["datasets"]]
            if not runs:
                continue
            summary["datasets"].setdefault(ds, {"n_scenes": runs[0]["n"],
                                                "label": dataset_label(cfg, ds, runs[0]["n"])})
            per_ds[ds] = {n: {k: aggregate([r[n][k] for r in runs]) for k in ("r2", "mae", "rel_err")}
                          for n in NAMES}
            per_ds[ds]["seeds"] = [s for s in seeds if s in metrics.get(arch, {})]
        if per_ds:
            summary["models"][arch] = per_ds
        per_photo: dict = {}
        for s in seeds:
            for pset, pm in metrics.get(arch, {}).get(s, {}).get("photos", {}).items():
                for photo, r in pm["photos"].items():
                    row = per_photo.setdefault(f"{pset}/{photo}", {
                        "f1": [], "f1_restored": [], "size_err": [], "size_err_restored": [],
                        **{n: [] for n in NAMES}, **{n + "_mm": [] for n in NAMES}})
                    if pm.get("finds_grains") and r.get("detection"):
                        row["f1"].append(r["detection"]["f1"])
                        rest = r.get("outlines_restored") or {}
                        if rest.get("detection"):  # against the reference grains grown back by half their band
                            row["f1_restored"].append(rest["detection"]["f1"])
                        for key, got in (("size_err", r), ("size_err_restored", rest)):
                            median = ((got.get("size_error") or {}).get("size_definition") or {}).get("median")
                            if median is not None:  # None: no grain matched
                                row[key].append(median)
                    for n in NAMES:
                        row[n].append(r["psd_rel_err"][n])
                        row[n + "_mm"].append(r["psd_mm"][n] - r["reference_mm"][n])
        if per_photo:
            summary.setdefault("photos", {})[arch] = {
                k: {n: aggregate(v) for n, v in row.items() if v} for k, row in per_photo.items()}
    out.mkdir(parents=True, exist_ok=True)
    md = markdown(summary)
    (out / "spread.json").write_text(json.dumps(summary, indent=1), encoding="utf-8")
    (out / "spread.md").write_text(md, encoding="utf-8")
    return md


def recalibration_source(root: str, seed: int, arch: str, params: dict, data: str) -> Path | None:
    """ROOT/<seed>/<arch>/model.pt where that run trained the network `params` train (the same network
    recipe, config.network_recipe: it differs at most in settings applied after training) on the same
    scenes and labels (`data`, its data.json); else None, with the reason printed."""
    from psdfactory import config as psd_config

    run = Path(root) / str(seed) / arch
    try:
        theirs = json.loads((run / "params.json").read_text(encoding="utf-8"))
        their_data = json.loads((run / "data.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        print(f"    --recalibrate-from: no run record at {run} (params.json, data.json): trained instead", flush=True)
        return None
    if psd_config.network_recipe(theirs) != psd_config.network_recipe(params):
        print(f"    --recalibrate-from: {run} trained another network: trained instead", flush=True)
        return None
    if their_data != data:
        print(f"    --recalibrate-from: {run} was trained on other scenes or labels: trained instead", flush=True)
        return None
    if not (run / "model.pt").is_file():
        print(f"    --recalibrate-from: {run} has no model.pt (not finished): trained instead", flush=True)
        return None
    return run / "model.pt"


def recalibrate_run(source: Path, params: dict, results: Path, run: Path) -> None:
    """The instance model `source` calibrated under `params`' settings into run/model.pt (the calibration's log
    lines on stdout: what it picked, and its figures)."""
    import logging

    if not logging.getLogger().handlers:
        logging.basicConfig(level=logging.INFO, format="    %(message)s", stream=sys.stdout)
    from psdfactory.learn.fit import write_history
    from psdfactory.learn.instances.estimator import InstanceEstimator
    from psdfactory.learn.instances.training import InstanceSettings, recalibrate

    _, val_mae = recalibrate(source, InstanceSettings.from_dict(params["settings"]), results, run / "model.pt",
                             InstanceEstimator, params["device"])
    history = source.parent / "history.csv"
    if history.is_file():  # the network's training curve, for the evaluation's plot, with this calibration's error
        rows = list(csv.DictReader(history.open(encoding="utf-8")))
        if rows:
            rows[-1]["val_mae_mm"] = val_mae
            write_history(rows, run / "history.csv")


SETTABLE = ("train.", "evaluate.")  # the recipe; a dataset setting would not match the scenes Snakemake makes


def load_config(path: Path, settings: list[str]) -> dict:
    """The config, validated (Snakemake's validator and the project's checks) with `settings`
    applied; a .json file that --write-config wrote is taken as it is (no Snakemake needed)."""
    from psdfactory import PsdError
    from psdfactory import config as psd_config

    if path.suffix == ".json":
        if settings:
            sys.exit("--set applies to a YAML config; a written .json config is used as it is")
        try:
            cfg = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
            sys.exit(f"{path}: not a config that --write-config wrote ({e})")
        if not isinstance(cfg, dict) or not isinstance(cfg.get("train"), dict):
            sys.exit(f"{path}: not a config that --write-config wrote (no train section)")
        return cfg
    try:
        return psd_config.load_config(path, lambda raw: psd_config.apply_settings(raw, settings, SETTABLE))
    except PsdError as e:
        sys.exit(str(e))


def main() -> None:
    from psdfactory import config as psd_config

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default="config/config.yaml", help="the config (default: %(default)s)")
    ap.add_argument("--seeds", type=int, default=3, help="how many training seeds: the config's seed and the "
                    "next ones (default: %(default)s)")
    ap.add_argument("--seed-list", type=int, nargs="+", help="these training seeds instead of --seeds")
    ap.add_argument("--archs", nargs="+", help="these architectures only (default: the config's train.architectures)")
    ap.add_argument("--results", help="the results folder (default: the config's `results`)")
    ap.add_argument("--out", help="folder for spread.md, spread.json and snakemake.log "
                    "(default: <results>/seed_spread)")
    ap.add_argument("--no-snakemake", action="store_true", help="use the results folder's datasets as they are")
    ap.add_argument("--jobs", type=int, default=2, help="snakemake -j for the datasets (default: %(default)s)")
    ap.add_argument("--threads", type=int, default=os.cpu_count() or 1,
                    help="threads per training / evaluation (default: all cores, as the workflow's rules)")
    ap.add_argument("--summarise-only", action="store_true",
                    help="train and evaluate nothing: the spread of the finished runs of this recipe (e.g. runs "
                    "made side by side, one seed per process, each with its own --out)")
    ap.add_argument("--set", action="append", metavar="KEY=VALUE",
                    help="change one train.* or evaluate.* setting of the config for these runs (a dotted key, "
                    "a YAML value: --set train.epochs=50 --set train.device=cuda); repeatable")
    ap.add_argument("--recalibrate-from", metavar="DIR",
                    help="a seed_spread folder of runs of the same network (e.g. results/seed_spread): a run that "
                    "differs from its run of the same seed only in train.instances' tta, sieve_method, readout or "
                    "calibration_datasets takes that network and calibrates it again (minutes) instead of training it")
    ap.add_argument("--write-config", metavar="FILE",
                    help="write the validated config (schema defaults filled in, --set applied) as JSON and stop: "
                    "--config FILE then runs it where Snakemake is not installed (a GPU node with the training "
                    "stack only), with --no-snakemake")
    a = ap.parse_args()

    config_path = Path(a.config).resolve()
    cfg = load_config(config_path, a.set or [])
    if a.write_config:
        Path(a.write_config).write_text(json.dumps(cfg, indent=1) + "\n", encoding="utf-8")
        print(f"wrote the validated config{' with ' + ', '.join(a.set) if a.set else ''} to {a.write_config}")
        return
    if config_path.suffix == ".json" and not a.no_snakemake:
        sys.exit("a written config (.json) has no Snakefile config to make the datasets with: pass --no-snakemake")
    results = Path(a.results or cfg["results"])
    if not results.is_absolute():
        results = REPO / results
    if a.results and Path(a.results).resolve() != (REPO / cfg["results"]).resolve() and not a.no_snakemake:
        sys.exit("--results differs from the config's `results`: snakemake would make the datasets elsewhere; "
                 "pass --no-snakemake to use that folder's datasets as they are")
    out = Path(a.out) if a.out else results / "seed_spread"
    seeds = a.seed_list or [cfg["seed"] + i for i in range(a.seeds)]
    if len(set(seeds)) != len(seeds):
        sys.exit(f"a seed given twice: {seeds}")
    archs = a.archs or list(cfg["train"]["architectures"])
    datasets = psd_config.evaluation_datasets(cfg)
    eval_precision = cfg["evaluate"]["precision"]
    command = "python bench/seed_spread.py " + " ".join(sys.argv[1:])
    cpu = next((ln.split(":", 1)[1].strip() for ln in Path("/proc/cpuinfo").read_text().splitlines()
                if ln.startswith("model name")), "CPU") if Path("/proc/cpuinfo").is_file() else "CPU"
    cpu = f"{cpu}, {os.cpu_count()} cores"

    print(f"seeds {seeds}; models {', '.join(archs)}; evaluated on {', '.join(datasets)}; results {results}",
          flush=True)
    if not a.no_snakemake and not a.summarise_only:
        make_datasets(config_path, a.jobs, out / "snakemake.log")
    trained_on = psd_config.trained_datasets(cfg, archs)
    missing = [d for d in {*datasets, *trained_on} if not (results / d / "manifest" / "scenes").is_dir()]
    if missing:
        sys.exit(f"no manifests for {', '.join(sorted(missing))} under {results}: --results is the folder the "
                 f"workflow made the datasets in (the config's `results`: {cfg['results']}); point it there, or run "
                 "without --no-snakemake to make them")

    meta = {"config": str(Path(a.config)), "command": command, "cpu": cpu, "gpu": gpu_name(), "commit": commit()}
    # each model's seeds back to back, models in the order of --archs: a partial run holds whole spreads
    photo_sets = sorted(cfg.get("photos") or {})
    kinds = ("train", "eval", "photos") if photo_sets else ("train", "eval")
    jobs = [(f"{kind} {arch}", f"seed {s} {arch}") for arch in archs for s in seeds for kind in kinds]
    progress = Progress(jobs)
    psd = psdfactory_cmd()
    metrics: dict = {}  # arch -> seed -> metrics.json
    left_out = 0  # --summarise-only: runs not finished
    train_minutes: dict = {}
    for arch in archs:
        data = data_identity(results, [*psd_config.train_params(cfg, arch)["datasets"], *datasets])  # every seed's
        for seed in seeds:
            run = results / "seed_spread" / str(seed) / arch
            run.mkdir(parents=True, exist_ok=True)
            params = psd_config.train_params(cfg, arch)
            params["seed"] = seed
            pjson = json.dumps(params, sort_keys=True, separators=(",", ":"))
            stamp, data_stamp = run / "params.json", run / "data.json"
            # the same recipe (equal but for settings that change the model's meta only: config.training_recipe) on
            # the same scenes and labels; a run without the record of its data (of before it) is not known to be
            try:
                theirs = json.loads(stamp.read_text(encoding="utf-8")) if stamp.is_file() else None
                same_data = data_stamp.is_file() and json.loads(data_stamp.read_text(encoding="utf-8")) == data
                same_network = (same_data and theirs is not None
                                and psd_config.network_recipe(theirs) == psd_config.network_recipe(params))
                same = same_network and psd_config.training_recipe(theirs) == psd_config.training_recipe(params)
            except (TypeError, ValueError):  # a stamp cut short (JSONDecodeError) or edited: not this recipe's
                same = same_network = False
            if a.summarise_only:
                done = same and all((run / f).is_file() for f in (
                    "model.pt", "eval/metrics.json", *(f"eval/photos/{n}/metrics.json" for n in photo_sets)))
                if not done:
                    print(f"    seed {seed} {ARCH_LABELS.get(arch, arch)}: no finished run of this recipe, left out",
                          flush=True)
                    left_out += 1
                    continue
            if not same and (run / "model.pt").exists():  # another recipe's model: train anew
                for p in (run / "model.pt", run / "history.csv", run / "eval"):
                    shutil.rmtree(p) if p.is_dir() else p.unlink(missing_ok=True)
                if not same_network:  # the same network calibrated otherwise: training resumes its checkpoints
                    shutil.rmtree(run / "checkpoints", ignore_errors=True)
            stamp.write_text(pjson, encoding="utf-8")
            data_stamp.write_text(json.dumps(data), encoding="utf-8")
            label = f"seed {seed} {ARCH_LABELS.get(arch, arch)}"
            info = run / "run.json"
            timing = json.loads(info.read_text(encoding="utf-8")) if info.is_file() else {}
            source = None
            if a.recalibrate_from and not (run / "model.pt").is_file() and arch == "instances":
                source = recalibration_source(a.recalibrate_from, seed, arch, params, data)
            if (run / "model.pt").is_file():
                progress.say(f"{label}: trained before, kept")
                progress.finish(f"train {arch}", None)
            elif source is not None:
                progress.say(f"{label}: the network of {source} calibrated again ({params['settings']})")
                t0 = time.monotonic()
                recalibrate_run(source, params, results, run)
                progress.finish(f"train {arch}", time.monotonic() - t0)
            else:
                progress.say(f"{label}: training ({params['epochs']} epochs)")
                cmd = [*psd, "--log", str(run / "train.log"), "train", "--params", pjson, "--results", str(results),
                       "--out-dir", str(run), "--threads", str(a.threads)]
                timing["train_s"] = run_watched(cmd, progress, label, run / "history.csv", params["epochs"])
                info.write_text(json.dumps(timing), encoding="utf-8")
                progress.finish(f"train {arch}", timing["train_s"])
            ev = run / "eval"
            if (ev / "metrics.json").is_file():
                progress.say(f"{label}: evaluated before, kept")
                progress.finish(f"eval {arch}", None)
            else:
                progress.say(f"{label}: evaluating on {', '.join(datasets)}")
                ev.mkdir(exist_ok=True)
                ep = json.dumps({"datasets": datasets, "precision": eval_precision, "arch": arch})
                cmd = [*psd, "--log", str(ev / "evaluate.log"), "evaluate", "--params", ep, "--model",
                       str(run / "model.pt"), "--results", str(results), "--out-dir", str(ev), "--history",
                       str(run / "history.csv"), "--threads", str(a.threads)]
                timing["eval_s"] = run_watched(cmd, progress, label, None, None)
                info.write_text(json.dumps(timing), encoding="utf-8")
                progress.finish(f"eval {arch}", timing["eval_s"])
            m = json.loads((ev / "metrics.json").read_text(encoding="utf-8"))
            if photo_sets:
                todo = [n for n in photo_sets if not (ev / "photos" / n / "metrics.json").is_file()]
                if not todo:
                    progress.say(f"{label}: photos evaluated before, kept")
                    progress.finish(f"photos {arch}", None)
                else:
                    progress.say(f"{label}: evaluating on the photo set(s) {', '.join(todo)}")
                    t0 = time.monotonic()
                    for name in todo:
                        pdir = ev / "photos" / name
                        pdir.mkdir(parents=True, exist_ok=True)
                        pp = json.dumps({"photoset": psd_config.photo_params(cfg, name), "precision": eval_precision})
                        cmd = [*psd, "--log", str(pdir / "evaluate_photos.log"), "evaluate-photos", "--params", pp,
                               "--model", str(run / "model.pt"), "--out-dir", str(pdir), "--threads", str(a.threads)]
                        run_watched(cmd, progress, label, None, None)
                    progress.finish(f"photos {arch}", time.monotonic() - t0)
                m["photos"] = {n: json.loads((ev / "photos" / n / "metrics.json").read_text(encoding="utf-8"))
                               for n in photo_sets}
            metrics.setdefault(arch, {})[seed] = m
            if timing.get("train_s"):
                train_minutes.setdefault(arch, []).append(timing["train_s"] / 60)
            r = m["datasets"]
            print("    " + "; ".join(f"{d}: R² " + " / ".join(f"{r[d][n]['r2']:.3f}" for n in NAMES)
                                     for d in datasets if d in r), flush=True)
            write_summary(out, meta, archs, seeds, datasets, cfg, metrics, train_minutes, complete=False)

    md = write_summary(out, meta, archs, seeds, datasets, cfg, metrics, train_minutes, complete=not left_out)

    print(f"\n{md}\nwritten: {out / 'spread.md'}, {out / 'spread.json'}", flush=True)


if __name__ == "__main__":
    main()
