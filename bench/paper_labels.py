#!/usr/bin/env python
"""How close a config's label distribution comes to the paper's.

The paper's 933 test labels (Eljarida et al.) have mean ± sd d10 2.55 ± 0.88, d50 7.31 ± 1.29,
d90 12.01 ± 1.11 mm; its size is its generator's size, this project's b-axis (`labels.
size_definition: b-axis`), which a scene's drawn sizes are by construction. So the labels of a
config's scenes are the number-weighted percentiles (the labels' own estimator,
`psd.weighted_percentiles`) of the sizes its sample stage draws — drawn here exactly as the sample
stage does (`sampling.draw_sizes`: the same random streams), without making the particles.

    .venv/bin/python bench/paper_labels.py [--config config/paper-cpu.yaml] [--dataset train] [--scenes 2000]
"""

from __future__ import annotations

import argparse

import numpy as np

PAPER = {"d10": (2.55, 0.88), "d50": (7.31, 1.29), "d90": (12.01, 1.11)}  # mean, sd over 933 test labels


def main() -> None:
    from psdfactory.config import load_config, sample_params
    from psdfactory.psd import weighted_percentiles
    from psdfactory.scene.sampling import SampleParams, draw_sizes

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default="config/paper-cpu.yaml")
    ap.add_argument("--dataset", default="train")
    ap.add_argument("--scenes", type=int, default=2000, help="scenes drawn (the first N of the dataset's indices)")
    a = ap.parse_args()
    cfg = load_config(a.config)
    n = min(a.scenes, cfg["datasets"][a.dataset]["n_scenes"])
    labels, counts = [], []
    for i in range(n):
        count, _, _, sizes = draw_sizes(SampleParams.from_dict(sample_params(cfg, a.dataset, i)))
        labels.append(weighted_percentiles(sizes, None))
        counts.append(count)
    y = np.array(labels)
    print(f"{a.config} [{a.dataset}]: {n} scenes, {min(counts)}-{max(counts)} particles each")
    print("| label | this config: mean ± sd (mm) | the paper's test labels | difference of the means |")
    print("|---|---|---|---|")
    for k, (name, (m, s)) in enumerate(PAPER.items()):
        print(f"| {name} | {y[:, k].mean():.2f} ± {y[:, k].std():.2f} | {m:.2f} ± {s:.2f} | "
              f"{y[:, k].mean() - m:+.2f} ({100 * (y[:, k].mean() / m - 1):+.0f} %) |")


if __name__ == "__main__":
    main()
