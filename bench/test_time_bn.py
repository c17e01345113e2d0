#!/usr/bin/env python
"""Test-time BatchNorm statistics for the grain finder (prediction-time BN, AdaBN): measured, not adopted.

A network trained on renders normalises each layer with the mean and variance it saw in training; on
a photo those statistics are another camera's. Test-time adaptation replaces them with the image's
own, blended: mean = (1 - a) x the training mean + a x the image's (likewise the variance), a from 0
(the model as trained) to 1 (AdaBN, Li et al. 2016; Schneider et al. 2020 blend with a prior). Each
image (each tile of a large one) is adapted on itself alone, then read as the estimator reads it
(its views averaged). Scored as `psdfactory evaluate-photos` scores a photo set and, with
--results, as `psdfactory evaluate` scores the synthetic datasets named by --datasets. Runs on the
PyTorch engine (ONNX Runtime has no BatchNorm buffers to change).

    .venv/bin/python bench/test_time_bn.py --model results/models/instances/model.pt --alphas 0 0.15 0.5 1 \
        [--config config/config.yaml --photoset real] [--results results --datasets train train_cycles]

Prints, per a: each photo's precision / recall / F1, and each dataset's grain F1 and R² d10 / d50 / d90
(the read-out as fitted on the unadapted network).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
from pathlib import Path

import numpy as np
import torch


def adapt(net: torch.nn.Module, x: torch.Tensor, alpha: float) -> None:
    """Set `net`'s BatchNorm statistics to (1 - alpha) x those it was trained with + alpha x those of `x`."""
    bns = [m for m in net.modules() if isinstance(m, torch.nn.modules.batchnorm._BatchNorm)]
    if not hasattr(net, "_trained_bn"):
        net._trained_bn = [(m.running_mean.clone(), m.running_var.clone()) for m in bns]
    if alpha == 0:
        return
    for m in bns:
        m.reset_running_stats()
        m.momentum = None  # a cumulative average: after one batch, that batch's statistics
        m.train()
    with torch.no_grad():
        net(x.float())
    for m, (mean, var) in zip(bns, net._trained_bn, strict=True):
        m.running_mean.mul_(alpha).add_((1 - alpha) * mean)
        m.running_var.mul_(alpha).add_((1 - alpha) * var)
        m.momentum = 0.1
        m.eval()


def patch(alpha: float) -> None:
    """Make every InstanceEstimator adapt its network to each image it reads, on PyTorch."""
    import psdfactory.deploy.fastpath as fastpath
    from psdfactory.learn.data import normalise
    from psdfactory.learn.instances.estimator import InstanceEstimator, averaged_maps, on_grid

    if not hasattr(fastpath, "_choose_as_shipped"):  # once: later calls change the blend only
        fastpath._choose_as_shipped = choose = fastpath.choose
        fastpath.choose = lambda est, path, runtime, device, cache=None: choose(est, path, "torch", device, cache)

    def outputs(self, images_u8: torch.Tensor) -> np.ndarray:
        x = normalise(images_u8)
        out = []
        for i in range(len(x)):
            adapt(self.net, on_grid(x[i:i + 1]), alpha)  # the statistics of what the network then runs
            out.append(averaged_maps(self.run, x[i:i + 1], self.views))
        return np.concatenate(out)

    InstanceEstimator.outputs = outputs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", required=True, type=Path)
    ap.add_argument("--alphas", nargs="+", type=float, default=[0.0, 0.15, 0.5, 1.0])
    ap.add_argument("--config", type=Path, default=Path("config/config.yaml"))
    ap.add_argument("--photoset", default="real")
    ap.add_argument("--results", type=Path, help="a results folder whose --datasets to score too")
    ap.add_argument("--datasets", nargs="*", default=[])
    ap.add_argument("--precision", default="auto")
    ap.add_argument("--work", type=Path)
    a = ap.parse_args()

    from photo_scales import check_run  # bench/ is on the path of a script run from it
    from psdfactory import config as psd_config
    from psdfactory.cli import main as cli

    photoset = psd_config.photo_params(psd_config.load_config(a.config), a.photoset)
    photoset["folder"] = str(Path(photoset["folder"]).resolve())
    problems = check_run(a.model, [], a.work, Path(photoset["folder"]))  # the model, --work: as photo_scales.py
    if bad := [x for x in a.alphas if not 0 <= x <= 1]:  # NaN is refused too
        problems.append(f"--alphas {' '.join(map(str, bad))}: give blends in [0, 1]")
    if problems:
        raise SystemExit("test_time_bn.py: " + "; ".join(problems))
    work = a.work or Path(tempfile.mkdtemp(prefix="test_time_bn_"))

    def run(args: list[str]) -> None:
        """`psdfactory ARGS` in this process (so the patch holds); its --log takes over stdout and
        stderr for good, so they are given back after it."""
        saved = os.dup(1), os.dup(2)
        try:
            code = cli(args)
        finally:
            for fd, keep in zip((1, 2), saved, strict=True):
                os.dup2(keep, fd)
                os.close(keep)
        if code:
            raise SystemExit(f"psdfactory {args[3]} failed: see {args[2]}")
    for alpha in a.alphas:
        patch(alpha)
        out = work / f"a{alpha:g}"
        (out / "photos").mkdir(parents=True, exist_ok=True)
        run(["-q", "--log", str(out / "photos.log"), "evaluate-photos", "--params",
             json.dumps({"photoset": photoset, "precision": a.precision}), "--model", str(a.model),
             "--out-dir", str(out / "photos")])
        m = json.loads((out / "photos" / "metrics.json").read_text(encoding="utf-8"))
        line = [f"{n}: P/R/F1 {p['detection']['precision']:.2f} / {p['detection']['recall']:.2f} / "
                f"{p['detection']['f1']:.3f}" for n, p in m["photos"].items()]
        if a.results and a.datasets:
            run(["-q", "--log", str(out / "evaluate.log"), "evaluate", "--params",
                 json.dumps({"datasets": a.datasets, "precision": a.precision, "arch": "instances"}),
                 "--model", str(a.model), "--results", str(a.results), "--out-dir", str(out / "eval")])
            d = json.loads((out / "eval" / "metrics.json").read_text(encoding="utf-8"))["datasets"]
            line += [f"{n}: F1 {d[n]['segmentation']['f1']:.3f}, R² "
                     + " / ".join(f"{d[n][t]['r2']:.2f}" for t in ("d10", "d50", "d90")) for n in a.datasets if n in d]
        print(f"a = {alpha:g}: " + "; ".join(line), flush=True)


if __name__ == "__main__":
    main()
