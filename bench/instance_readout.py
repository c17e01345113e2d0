#!/usr/bin/env python
"""The instance estimator's calibrated read-out, refitted every way it can be on a trained model:
what it reads (`train.instances.readout`: the footprints' statistics, or those and the size
map's, for every target or for d10 and d50 only), what it is fitted on (the training split, or
the training and validation splits) and the test-time views its maps are averaged over
(`train.instances.tta`; `--tta`, default the model's), scored per target on the test split of
each dataset beside its visible-particle ceiling.
`--write-models DIR` also writes each read-out fitted as training fits it (on train+val) into a copy
of the model, DIR/<tta>-<read-out>/model.pt, with the read-outs of the other size definitions refitted
alike: a model `predict` and the benches take, e.g. to see a read-out on images of another look
(bench/paper_look.py).

The network and the post-processing stay as trained; only the views and the ridge read-out
change, so the rows are comparable on one model (training fits `train+val`, with the config's
`train.instances.readout` and `tta`).

    .venv/bin/python bench/instance_readout.py --config config/config.yaml \
        --model results/models/instances/model.pt --datasets train train_cycles --tta none d4 \
        --out bench/out/readout.json [--write-models /tmp/readouts]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


def stats_of(est, rows: list[dict], root: Path, batch: int = 8) -> np.ndarray:
    """`instance_stats` of the estimator's instances in each row's image (images of one size)."""
    import torch

    from psdfactory.io import read_png
    from psdfactory.learn.data import to_input

    out = []
    for i in range(0, len(rows), batch):
        chunk = rows[i : i + batch]
        images = torch.stack([to_input(read_png(root / r["image_path"]), None) for r in chunk])
        maps = est.outputs(images)
        out += [est.analyse_maps(m, float(r["mm_per_px"])).stats for m, r in zip(maps, chunk, strict=True)]
    return np.stack(out)


def main() -> None:
    import torch

    from psdfactory import config as psd_config
    from psdfactory.cli import configure_logging
    from psdfactory.learn.augment import TTA_VIEWS
    from psdfactory.learn.ceiling import dataset_ceilings_from_config
    from psdfactory.learn.data import targets, training_rows
    from psdfactory.learn.evaluate import eval_rows
    from psdfactory.learn.instances.estimator import InstanceEstimator
    from psdfactory.learn.instances.stats import READOUTS
    from psdfactory.learn.instances.training import other_readouts, readout_features
    from psdfactory.learn.metrics import r2_scores
    from psdfactory.learn.readout import apply_readout, fit_readout
    from psdfactory.learn.runtime import load_estimator, save_model
    from psdfactory.psd import NAMES, TARGETS

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default="config/config.yaml")
    ap.add_argument("--results", help="results root (default: the config's)")
    ap.add_argument("--model", required=True, help="an instance estimator's model.pt")
    ap.add_argument("--datasets", nargs="+", help="datasets to score (default: the config's evaluated datasets)")
    ap.add_argument("--tta", nargs="+", choices=list(TTA_VIEWS),
                    help="test-time views to score (default: the model's own)")
    ap.add_argument("--threads", type=int, default=0)
    ap.add_argument("--out", help="write the figures to this JSON file")
    ap.add_argument("--write-models", metavar="DIR",
                    help="write a copy of the model per read-out fitted on train+val: DIR/<tta>-<read-out>/model.pt")
    a = ap.parse_args()
    configure_logging()
    if a.threads:
        torch.set_num_threads(a.threads)
    cfg = psd_config.load_config(Path(a.config))
    root = Path(a.results or cfg["results"])
    loaded = load_estimator(Path(a.model))
    meta = loaded.meta
    if not isinstance(loaded, InstanceEstimator):
        raise SystemExit(f"{a.model} is a {meta.get('arch')} model, not the instance estimator")
    ttas = a.tta or [meta.get("tta", "none")]

    def written(tta: str, readout: str) -> Path:  # --write-models' file of one refitted read-out
        return Path(a.write_models) / f"{tta}-{readout.replace('+', '-')}" / "model.pt"

    if a.write_models:  # refused before any work: it must not overwrite the model read or the --out file
        taken = {Path(a.model).resolve(), *([Path(a.out).resolve()] if a.out else [])}
        clash = [w for t in ttas for r in READOUTS if (w := written(t, r)).resolve() in taken]
        if clash:
            raise SystemExit(f"--write-models {a.write_models} would overwrite {clash[0]}: give another folder")
    datasets = a.datasets or psd_config.evaluation_datasets(cfg)
    # the scenes training fits the read-out on: those of its calibration_datasets where it names them
    train_rows, val_rows, _ = training_rows(root, meta.get("calibration_datasets") or meta["params"]["datasets"])
    fit_y = {"train": targets(train_rows).numpy()}
    fit_y["train+val"] = np.concatenate([fit_y["train"], targets(val_rows).numpy()])
    ceilings = {}
    for d in datasets:
        vis = dataset_ceilings_from_config(cfg, root, d)["visible"]
        ceilings[d] = [vis[t] for t in TARGETS] if vis else None

    out = {"model": str(a.model), "trained_with": {k: meta.get(k) for k in ("readout_features", "tta")},
           "ceilings": ceilings, "rows": []}
    for tta in ttas:
        est = InstanceEstimator({**meta, "tta": tta}, loaded.run, loaded.net)
        t0 = time.perf_counter()
        fit_x = {"train": stats_of(est, train_rows, root)}
        fit_x["train+val"] = np.concatenate([fit_x["train"], stats_of(est, val_rows, root)])
        scored = {}
        for d in datasets:
            rows = eval_rows(root, d)
            scored[d] = (stats_of(est, rows, root), targets(rows).numpy())
        print(f"tta {tta} ({len(TTA_VIEWS[tta])} views): instance statistics of {len(fit_y['train+val'])} training "
              f"and {sum(len(y) for _, y in scored.values())} scored images in {time.perf_counter() - t0:.0f} s")
        for fit in fit_x:
            for readout in READOUTS:
                ro = fit_readout(fit_x[fit], fit_y[fit], **readout_features(readout))
                r2 = {d: r2_scores(y, apply_readout(ro, x)).tolist() for d, (x, y) in scored.items()}
                out["rows"].append({"tta": tta, "readout": readout, "fitted_on": fit, "n_scenes": ro["n_scenes"],
                                    "cv_r2": ro["cv_r2"], "r2": r2})
                if a.write_models and fit == "train+val":  # as training fits it
                    path = written(tta, readout)
                    kept = {k: v for k, v in meta.items() if k not in ("val", "calibration")}  # the old read-out's
                    save_model(path, loaded.net, {
                        **kept, "tta": tta, "readout_features": readout, "readout": ro,
                        "readouts": other_readouts(fit_x[fit], train_rows + val_rows, readout)})
                    print(f"wrote {path}")

    def cell(r: list[float], c: list[float] | None) -> str:
        return " / ".join(f"{v:.3f}" + (f" ({100 * v / cv:.0f} %)" if c and cv > 0 else "")
                          for v, cv in zip(r, c or [None] * len(r), strict=True))

    print(f"\nper-target R² {' / '.join(NAMES)} (fraction of the dataset's visible-particle ceiling)")
    print("| tta | read-out | fitted on | " + " | ".join(datasets) + " |")
    print("|---|---|---|" + "---|" * len(datasets))
    print("| | visible-particle ceiling | | " + " | ".join(cell(ceilings[d], None) if ceilings[d] else "n/a"
                                                      for d in datasets) + " |")
    for row in out["rows"]:
        print(f"| {row['tta']} | {row['readout']} | {row['fitted_on']} ({row['n_scenes']} scenes) | "
              + " | ".join(cell(row["r2"][d], ceilings[d]) for d in datasets) + " |")
    if a.out:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
