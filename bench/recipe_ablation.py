#!/usr/bin/env python
"""Training-recipe ablation: train one architecture with each recipe step added in turn, and
print its per-target R² in domain (the dataset's test split) and across renderers (re-render
datasets of the same test scenes), each beside the dataset's visible-particle ceiling.

Needs a results root with the datasets' manifests (e.g. after `snakemake -j2 scenes` on the
default config, plus the `train_cycles` re-render):

    .venv/bin/python bench/recipe_ablation.py --results results --config config/config.yaml \
        --arch efficientnet_b0 --steps baseline scale photometric scale+photometric --out bench/out/ablation.json

Each step trains from scratch with the config's training settings plus the step's overrides
(seeded: the same step gives the same figures on the same machine). Steps join with '+'
(`onecycle-3x+size-cells`). Two arms side by side on 2 cores, one thread each, as docs/experiments.md's
table was measured (a config with an `unseen` dataset and its Cycles re-render scores those too):

    for s in baseline onecycle-3x; do .venv/bin/python bench/recipe_ablation.py --results results \
        --arch instances --steps $s --threads 1 --work bench/out/ablation --out bench/out/$s.json & done
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

STEPS = {  # name → train-setting overrides ("instances": the instance estimator's own, merged into its slice)
    "baseline": {},
    "onecycle": {"lr_schedule": "onecycle"},
    "onecycle-3x": {"lr_schedule": "onecycle", "lr": 0.001, "instances": {"lr": 0.003}},
    "size-cells": {"size_cells": 1.0},
    "scale": {"scale_augment": [0.8, 1.25]},
    "photometric": {"photometric": 1.0},
    "epochs-30": {"epochs": 30},
    "epochs-40": {"epochs": 40},
}
# a step may join several with "+" (e.g. onecycle-3x+size-cells): their overrides together


def step_overrides(step: str) -> dict:
    """The overrides of a step: one of STEPS, or several joined with '+'."""
    out: dict = {}
    for part in step.split("+"):
        if part not in STEPS:
            raise SystemExit(f"unknown step {part!r} in {step!r}: one of {', '.join(STEPS)}, joined with '+'")
        for k, v in STEPS[part].items():
            out[k] = {**out.get(k, {}), **v} if isinstance(v, dict) else v
    return out


def main() -> None:
    import torch

    from psdfactory import config as psd_config
    from psdfactory.cli import configure_logging
    from psdfactory.learn.capability import detect
    from psdfactory.learn.ceiling import dataset_ceilings_from_config
    from psdfactory.learn.evaluate import evaluate
    from psdfactory.learn.train import train_from_params
    from psdfactory.psd import NAMES

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--results", required=True)
    ap.add_argument("--config", default="config/config.yaml")
    ap.add_argument("--arch", default="efficientnet_b0")
    ap.add_argument("--steps", nargs="+", default=["baseline", "scale", "photometric", "scale+photometric"],
                    help=f"steps to train, each one of {', '.join(STEPS)} or several joined with '+'")
    ap.add_argument("--epochs", type=int, help="override train.epochs")
    ap.add_argument("--threads", type=int, default=0)
    ap.add_argument("--work", default="bench/out/ablation", help="models are written here")
    ap.add_argument("--out", help="write the figures to this JSON file")
    a = ap.parse_args()
    configure_logging()  # training's epoch lines and progress bars, on stderr
    if a.threads:
        torch.set_num_threads(a.threads)
    cfg = psd_config.load_config(Path(a.config))
    root = Path(a.results)
    ds = psd_config.main_training_dataset(cfg)
    print(f"CPU: {detect().summary()}; {torch.get_num_threads()} threads")
    out: dict = {"arch": a.arch, "ceilings": {}, "steps": {}}
    evals: list[str] = []

    def scored_datasets() -> list[str]:
        """The evaluated datasets whose manifests exist when the first model is trained (the
        scenes may still be in the making when training starts), with their ceilings."""
        if not evals:
            evals.extend(d for d in psd_config.evaluation_datasets(cfg) if (root / d / "manifest" / "scenes").is_dir())
            for d in evals:
                c = dataset_ceilings_from_config(cfg, root, d)
                out["ceilings"][d] = c["visible"]
                if c["visible"]:
                    print(f"{d}: visible-particle ceiling R² " + " / ".join(f"{v:.3f}" for v in c["visible"].values()))
        return evals

    for step in a.steps:
        p = psd_config.train_params(cfg, a.arch)
        for k, v in step_overrides(step).items():
            if not isinstance(v, dict):
                p[k] = v
            elif k in p:  # a nested slice (train.instances) only where this arch has it
                p[k] = {**p[k], **v}
        if a.epochs:
            p["epochs"] = a.epochs
        work = Path(a.work) / step
        t0 = time.perf_counter()
        train_from_params(p, root, work)
        minutes = (time.perf_counter() - t0) / 60
        res = evaluate(work / "model.pt", root, scored_datasets(), work / "eval", precision="fp32")
        out["steps"][step] = {"overrides": step_overrides(step), "train_minutes": minutes,
                              "r2": {d: {n: res["datasets"][d][n]["r2"] for n in NAMES} for d in evals}}
        print(f"== {step}: trained in {minutes:.1f} min")
        if a.out:
            Path(a.out).parent.mkdir(parents=True, exist_ok=True)
            Path(a.out).write_text(json.dumps(out, indent=1))

    print(f"\n{a.arch}: per-target R² d10 / d50 / d90 (fraction of the visible-particle ceiling)")
    print("| step | " + " | ".join(evals) + " | train min |")
    print("|---|" + "---|" * (len(evals) + 1))
    for step, r in out["steps"].items():
        cells = []
        for d in evals:
            c = out["ceilings"].get(d) or {}
            cells.append(" / ".join(f"{r['r2'][d][n]:.2f}" + (f" ({100 * r['r2'][d][n] / c[n + '_mm']:.0f} %)"
                                                                if c.get(n + "_mm", 0) > 0 else "")
                                    for n in NAMES))
        print(f"| {step} | " + " | ".join(cells) + f" | {r['train_minutes']:.1f} |")
    print(f"(training dataset: {ds})")


if __name__ == "__main__":
    main()
