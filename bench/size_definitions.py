#!/usr/bin/env python
"""How the size definitions relate, per shape family, and what they cost.

1. Per family (N particles each): the sieve size, c-axis and equivalent-sphere diameter over the
   b-axis (median and p10–p90), and sedimentology's approximation √((b² + c²)/2) / b.
2. Per family: the seconds the minimum boxes and sieve sizes of 1,000 particles take (median of
   --repeats runs), the cost a scene's sample stage pays for them.
3. Scene level, on scenes drawn from a config's dataset (the sample stage only: the solid
   definitions need no pose): each definition's d10/d50/d90 over the b-axis ones (mean ratio),
   and how well the b-axis labels (what the models learnt before sizes had names) read the
   sieve labels: R² as they are and after the best affine map.

    .venv/bin/python bench/size_definitions.py [--particles 150] [--scenes 40] [--config config/config.yaml]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np


def family_table(n: int, seed: int) -> None:
    from psdfactory.scene.shapes import ShapeParams, make_particles
    from psdfactory.scene.sizes import equivalent_sphere_diameter

    print(f"\n1. size definitions over the b-axis, {n} particles per family (b = the drawn size)")
    print(f"{'family':<14}{'sieve/b median':>16}{'p10 – p90':>16}{'√((b²+c²)/2)/b':>16}{'c/b':>8}{'esd/b':>8}")
    for family in ("crushed_rock", "ellipsoid", "granule"):
        rng = np.random.default_rng(seed)
        parts = make_particles(family, rng.uniform(2, 20, n), rng, ShapeParams.for_family(family))
        b = np.array([p.dims_mm[1] for p in parts])
        c = np.array([p.dims_mm[2] for p in parts])
        sieve = np.array([p.sieve_mm for p in parts]) / b
        esd = equivalent_sphere_diameter(np.array([p.volume_mm3 for p in parts])) / b
        p10, p90 = np.percentile(sieve, [10, 90])
        print(f"{family:<14}{np.median(sieve):>16.3f}{f'{p10:.3f} – {p90:.3f}':>16}"
              f"{np.median(np.sqrt((b**2 + c**2) / 2) / b):>16.3f}{np.median(c / b):>8.3f}{np.median(esd):>8.3f}")


def timing(repeats: int, seed: int) -> None:
    from psdfactory.scene.shapes import MAKERS, ShapeParams
    from psdfactory.scene.sizes import box_and_sieve, grid_widths, minimum_box, pad_vertices, sieve_sizes

    print(f"\n2. seconds for 1,000 particles (median of {repeats}; {time.strftime('%Y-%m-%d')})")
    print(f"{'family':<14}{'vertices':>9}{'grid':>7}{'minimum box':>13}{'sieve':>9}{'all (as sampling runs it)':>27}")
    for family in ("crushed_rock", "ellipsoid", "granule"):
        rng = np.random.default_rng(seed)
        p = ShapeParams.for_family(family)
        shapes = [MAKERS[family](rng, p) for _ in range(1000)]
        offsets = np.concatenate([[0], np.cumsum([len(v) for v, _ in shapes])])
        verts = pad_vertices(np.concatenate([v for v, _ in shapes]), offsets)
        grid, box, sieve, whole = [], [], [], []
        for _ in range(repeats):
            t0 = time.perf_counter()
            w = grid_widths(verts)
            t1 = time.perf_counter()
            _, axes = minimum_box(verts, w)
            t2 = time.perf_counter()
            sieve_sizes(verts, axes, w)
            t3 = time.perf_counter()
            box_and_sieve([v for v, _ in shapes])
            grid.append(t1 - t0)
            box.append(t2 - t1)
            sieve.append(t3 - t2)
            whole.append(time.perf_counter() - t3)
        med = statistics.median
        print(f"{family:<14}{verts.shape[1]:>9}{med(grid):>7.2f}{med(box):>13.2f}{med(sieve):>9.2f}{med(whole):>27.2f}")


def scene_table(config_path: str, dataset: str, n_scenes: int) -> None:
    from psdfactory import config as psd_config
    from psdfactory.psd import NAMES, SOLID_DEFINITIONS, weighted_percentiles
    from psdfactory.scene.sampling import SampleParams, sample_scene
    from psdfactory.scene.sizes import equivalent_sphere_diameter

    cfg = psd_config.load_config(config_path)
    d = {name: [] for name in SOLID_DEFINITIONS}
    t0 = time.perf_counter()
    for i in range(n_scenes):
        _, g = sample_scene(SampleParams.from_dict(psd_config.sample_params(cfg, dataset, i)))
        sizes = {"sieve": g["sieve_mm"], "b-axis": g["dims_mm"][:, 1], "c-axis": g["dims_mm"][:, 2],
                 "esd": equivalent_sphere_diameter(g["volume_mm3"])}
        for name in SOLID_DEFINITIONS:
            d[name].append(weighted_percentiles(sizes[name], None))
    d = {k: np.array(v) for k, v in d.items()}
    shape = cfg["datasets"][dataset]["shape"]
    print(f"\n3. {n_scenes} scenes of {config_path}:{dataset} ({shape}), number-weighted labels "
          f"({time.perf_counter() - t0:.0f} s to sample)")
    print(f"{'definition':<12}" + "".join(f"{n + ' / b-axis':>16}" for n in NAMES))
    for name in SOLID_DEFINITIONS:
        print(f"{name:<12}" + "".join(f"{np.mean(d[name][:, k] / d['b-axis'][:, k]):>16.3f}" for k in range(3)))
    y, x = d["sieve"], d["b-axis"]
    raw = [1 - np.sum((y[:, k] - x[:, k]) ** 2) / np.sum((y[:, k] - y[:, k].mean()) ** 2) for k in range(3)]
    aff = [np.corrcoef(x[:, k], y[:, k])[0, 1] ** 2 for k in range(3)]
    print("b-axis labels read as sieve labels: R² " + " / ".join(f"{v:.3f}" for v in raw)
          + " as they are, " + " / ".join(f"{v:.3f}" for v in aff) + " after the best affine map (d10 / d50 / d90)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--particles", type=int, default=150)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--scenes", type=int, default=40)
    ap.add_argument("--config", default="config/config.yaml")
    ap.add_argument("--dataset", default="train")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    family_table(a.particles, a.seed)
    timing(a.repeats, a.seed)
    scene_table(a.config, a.dataset, a.scenes)


if __name__ == "__main__":
    main()
