#!/usr/bin/env python
"""Models on scenes made to look like the seed paper's own renders, which are not available here.

The paper's renders (Eljarida et al.) are Blender images of 1000 px over a 300 mm table (0.3 mm/px),
1,000-1,350 orange-brown crushed-rock particles on a white table, labelled with its generator's
size (this project's b-axis). This script makes N such scenes in-process (sample → simulate →
render → label): config/paper.yaml's scene distribution, rendered by Blender Cycles (`make
blender`) at 1000 px with a near-white table and an orange-brown palette (PAPER_LOOK below), a
look the default config never trains on. Then each model reads them with `psdfactory predict
--mm-per-px 0.3` — an instance model in the b-axis definition (`--size-definition b-axis`,
uncalibrated), a CNN in its own definition — and the script prints, per model and target, the
Spearman rank correlation with the labels, the mean relative error and the mean absolute one.

    .venv/bin/python bench/paper_look.py --models results/models/*/model.pt [--scenes 12] [--seed 99]

The scenes are kept in --work (default /tmp/psd-paper-look) and made again only where missing,
so a second call with other models costs the predictions alone. A Cycles scene at 1000 px takes
~30-120 s on 2 CPU cores.
"""

from __future__ import annotations

import argparse
import copy
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
NAMES = ("d10", "d50", "d90")
# the paper's look: a near-white table, orange-brown rock, 1000 px over 300 mm, Blender Cycles
PAPER_LOOK = {
    "backend": "cycles",
    "resolution": 1000,
    "table_palette": [[0.86, 0.85, 0.83], [0.9, 0.89, 0.88]],
    "table_texture": [0.02, 0.02],
    "palette": [[0.62, 0.42, 0.26], [0.55, 0.37, 0.22], [0.7, 0.5, 0.32]],
}
MM_PER_PX = 0.3
DATASET = "paper_renders"  # the scenes' dataset name: with --seed, what their random streams derive from


def paper_look_config(base: Path, seed: int) -> dict:
    """config/paper.yaml's training dataset with PAPER_LOOK's render settings, validated."""
    from psdfactory.config import load_config, validate

    cfg = copy.deepcopy(load_config(base))
    cfg["seed"] = seed
    cfg["render"] = {**cfg["render"], **PAPER_LOOK}
    cfg["datasets"] = {DATASET: cfg["datasets"]["train"]}
    cfg["train"] = {**cfg["train"], "datasets": [DATASET], "instances": {**cfg["train"]["instances"], "datasets": None}}
    return validate(cfg)


def make_scenes(cfg: dict, n: int, work: Path) -> list[Path]:
    from psdfactory import config as C
    from psdfactory.scene.stages import run_label, run_render, run_sample, run_simulate

    dirs = []
    t0 = time.perf_counter()
    for i in range(n):
        d = work / "scenes" / f"paper-look-{i:04d}"
        if not (d / "labels.json").is_file():
            run_sample(C.sample_params(cfg, DATASET, i), d)
            run_simulate(C.simulate_params(cfg, DATASET), d)
            run_render(C.render_params(cfg, DATASET), d)
            run_label(C.label_params(cfg), d)
        dirs.append(d)
        rate = (i + 1) / (time.perf_counter() - t0)
        print(f"  scenes {i + 1}/{n}, ETA {(n - i - 1) / rate:.0f} s", flush=True)
    return dirs


def predictions(model: Path, images: list[Path], out: Path) -> tuple[dict[str, np.ndarray], str]:
    """d10/d50/d90 per image, in b-axis for a model that finds grains, else the model's own definition."""
    from psdfactory.deploy.predict import read_rows
    from psdfactory.learn.registry import estimator_class
    from psdfactory.learn.runtime import load_checkpoint

    finds = estimator_class(load_checkpoint(model)["meta"]["arch"]).finds_grains
    cmd = [str(Path(sys.executable).with_name("psdfactory")), "-q", "predict", "--model", str(model),
           "--mm-per-px", str(MM_PER_PX), "--out", str(out), *(["--size-definition", "b-axis"] if finds else []),
           *map(str, images)]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    rows = {Path(r["image"]).parent.name: r for r in read_rows(out)}
    definition = next(iter(rows.values()))["size_definition"]
    return {n: np.array([rows[p.parent.name][f"{n}_mm"] for p in images]) for n in NAMES}, definition


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", nargs="+", required=True, type=Path)
    ap.add_argument("--scenes", type=int, default=12)
    ap.add_argument("--seed", type=int, default=99)
    ap.add_argument("--config", type=Path, default=REPO / "config" / "paper.yaml")
    ap.add_argument("--work", type=Path, default=Path("/tmp/psd-paper-look"))
    a = ap.parse_args()
    from scipy.stats import spearmanr

    cfg = paper_look_config(a.config, a.seed)
    print(f"{a.scenes} scenes of {a.config.name}'s distribution (seed {a.seed}) in the paper's look, "
          f"{PAPER_LOOK['resolution']} px, {MM_PER_PX} mm/px, Cycles; in {a.work}")
    dirs = make_scenes(cfg, a.scenes, a.work)
    labels = [json.loads((d / "labels.json").read_text(encoding="utf-8")) for d in dirs]
    images = [d / "image.png" for d in dirs]
    print(f"\n{'model':<48}{'labels':>8}  " + "  ".join(f"{n + ': rho, mean err, mean |err|':>30}" for n in NAMES))
    for i, model in enumerate(a.models):
        pred, definition = predictions(model, images, a.work / f"predictions-{i}.csv")
        key = definition.replace("-", "_")
        cells = []
        for n in NAMES:
            true = np.array([lab[f"{n}_{key}_mm"] for lab in labels])
            rel = (pred[n] - true) / true
            cells.append(f"{spearmanr(pred[n], true).statistic:+.2f}, {rel.mean():+.1%}, {np.abs(rel).mean():.1%}")
        name = str(model)[-48:]
        print(f"{name:<48}{definition:>8}  " + "  ".join(f"{c:>30}" for c in cells))


if __name__ == "__main__":
    main()
