#!/usr/bin/env python
"""Inference speed per architecture at the paper's input sizes (table 3 layout).

On the CPU (default) or a CUDA GPU (--device cuda), times the plain fp32 eager model and every
candidate path for that hardware (channels-last; bf16 autocast where the CPU has native bf16,
fp32 and int8 ONNX Runtime; fp16/bf16 autocast on a GPU) side by side in one run (medians of
repeated runs), at batch 1 and batched, reports the fastest, prints which CPU (and GPU) and
features it ran on (ATEN_CPU_CAPABILITY=avx2 forces PyTorch's portable path), and compares with
the paper's figures for that kind of device (its Table 3: an 8-core CPU, an RTX 3060 GPU) and, on
the CPU, this project's goal (3× the paper, batched). Speed does not depend on the weights, so
untrained models are timed; pass --results to also measure the accuracy change of the fast path
with the trained models of a workflow run (results/models/<arch>/model.pt).

    .venv/bin/python bench/inference_benchmark.py [--batch 16] [--seconds 2] [--repeats 5] [--results results]
    python bench/inference_benchmark.py --device cuda   # on a GPU node
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from psdfactory import PsdError
from psdfactory.cli import configure_logging
from psdfactory.config import default_input_size
from psdfactory.deploy.benchmark import benchmark, benchmark_estimator
from psdfactory.deploy.quantize import r2_change
from psdfactory.learn.capability import detect
from psdfactory.learn.cnn import CnnRegressor
from psdfactory.learn.models import TargetStats, build_model
from psdfactory.learn.runtime import pick_device, torch_runner
from psdfactory.paper import TABLE3, TABLE3_CPU, TABLE3_GPU


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--archs", nargs="+", default=list(TABLE3))
    ap.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N (default: %(default)s)")
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--seconds", type=float, default=2.0)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--results", help="results root of a workflow run, for the accuracy of the fast path")
    ap.add_argument("--json", help="also write the figures to this file")
    a = ap.parse_args()
    configure_logging()  # the benchmark's per-path lines, on stderr

    stats = TargetStats([2.0, 9.0, 16.0], [1.0, 1.0, 1.0], [2.0, 7.0, 7.0], [1.0, 1.0, 1.0])
    rows, out = [], {}
    try:
        dev = pick_device(a.device)
    except PsdError as e:
        raise SystemExit(f"--device {a.device}: {e}") from None
    gpu = dev.type == "cuda"
    paper_key, paper_where = ("gpu_fps", TABLE3_GPU) if gpu else ("cpu_fps", TABLE3_CPU)
    print(f"CPU: {detect().summary()}")
    if gpu:
        print(f"GPU: {torch.cuda.get_device_name(dev)}; PyTorch {torch.__version__}, CUDA {torch.version.cuda}")
    print(f"CPU threads: {torch.get_num_threads()}; batch {a.batch}; medians of {a.repeats} runs of ~{a.seconds} s")
    for arch in a.archs:
        size = default_input_size(arch)
        model, _ = build_model(arch, stats, "none", size=size)
        print(f"{arch} at {size} px:")
        meta = {"arch": arch, "input_size": size, "image_resolution": size, "mm_per_px": 1.0}
        est = CnnRegressor(meta, None, model.eval())
        est.run = torch_runner(est.inference_module(), dev)
        r = benchmark_estimator(est, dev, None, None, a.batch, a.seconds, a.repeats)
        out[arch] = r
        if a.results:
            mp = Path(a.results) / "models" / arch / "model.pt"
            if mp.is_file():  # accuracy of every path with the trained model (at its own input size)
                acc = benchmark(mp, Path(a.results), "train", a.batch, 0.2, 1,
                                device=a.device)["results"][-1]["paths"]
                # per target, the change of the one that moved most (quantize.r2_change: the benchmark's budget)
                r["r2_change_fast"] = r2_change(acc[r["fast_key"]]["accuracy"], acc["fp32"]["accuracy"])
                r["r2_change_all"] = {k: r2_change(v["accuracy"], acc["fp32"]["accuracy"])
                                      for k, v in acc.items() if k != "fast"}
        rows.append((arch, size, r))

    print()
    print("| CNN model | input | fp32 b1 img/s | fp32 b16 img/s | fast path | fast b1 img/s | fast b16 img/s "
          f"| ms/img (fast b{a.batch}) | speed-up | paper {'GPU' if gpu else 'CPU'} FPS | goal (3×) | met | params (M) "
          "| GFLOPs | R² change fp32 → fast, the target that moved most |")
    print("|" + "---|" * 15)
    for arch, size, r in rows:
        f, s = r["paths"]["fp32"], r["paths"]["fast"]
        paper = TABLE3.get(arch, {}).get(paper_key)
        goal = 3 * paper if paper and not gpu else None  # the project's goal is a CPU one
        met = "–" if goal is None else ("yes" if s["batched"]["images_per_s"] >= goal else "no")
        acc = f"{r['r2_change_fast'][0]:+.4f} ({r['r2_change_fast'][1]})" if "r2_change_fast" in r else "–"
        print(f"| {arch} | {size} | {f['batch1']['images_per_s']:.1f} | {f['batched']['images_per_s']:.1f} "
              f"| {s['name']} | {s['batch1']['images_per_s']:.1f} | {s['batched']['images_per_s']:.1f} "
              f"| {s['batched']['ms_per_image']:.2f} "
              f"| {r['speedup_batched']:.2f}× | {paper or '–'} | {goal and round(goal, 1) or '–'} | {met} "
              f"| {r['params_m']:.1f} | {r['gflops']:.2f} | {acc} |")
    print(f"\n(paper: {paper_where})\nEvery path, batched images/s (and overall R² with the trained models):")
    for arch, _, r in rows:
        paths = {k: v for k, v in r["paths"].items() if k != "fast"}
        print(f"  {arch}: " + ", ".join(
            f"{v['name']} {v['batched']['images_per_s']:.1f}" + (f" (R² {r['r2_all'][k]:.4f})" if "r2_all" in r else "")
            for k, v in paths.items()))
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
