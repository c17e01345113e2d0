"""Inference speed per architecture, in the layout of the paper's table 3.

Two paths side by side in one run: the plain fp32 eager model, and the fastest path for the
hardware at hand — channels-last memory layout with bf16 autocast on CPUs with native bf16
(AVX512-BF16 / AMX), fp16/bf16 autocast on CUDA GPUs — plus the accuracy change of the fast path.
"""

from __future__ import annotations

import statistics
import time
from pathlib import Path

import torch
from torch import nn

from .models import count_parameters, main_output
from .train import autocast, cpu_has_fast_bf16


def gflops(model: nn.Module, size: int) -> float:
    """Forward FLOPs (multiply + add counted as 2) of one image, in 10⁹."""
    from torch.utils.flop_counter import FlopCounterMode

    model = model.eval()
    x = torch.zeros(1, 3, size, size, device=next(model.parameters()).device)
    with torch.no_grad(), FlopCounterMode(display=False) as counter:
        model(x)
    return counter.get_total_flops() / 1e9


def fast_path(device: torch.device) -> tuple[str, str]:
    """(name, precision) of the fastest path for this hardware."""
    if device.type == "cuda":
        prec = "bf16" if torch.cuda.is_bf16_supported() else "fp16"
        return f"channels_last + {prec} autocast", prec
    if cpu_has_fast_bf16():
        return "channels_last + bf16 autocast", "bf16"
    return "channels_last fp32", "fp32"


def images_per_second(model: nn.Module, size: int, batch: int, device: torch.device, precision: str,
                      channels_last: bool, seconds: float = 2.0, repeats: int = 5) -> dict:
    """Median images/s over `repeats` timed runs of about `seconds` each (after a warm-up)."""
    fmt = torch.channels_last if channels_last else torch.contiguous_format
    model = model.to(device).eval().to(memory_format=fmt)
    x = torch.randn(batch, 3, size, size, device=device).contiguous(memory_format=fmt)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)

    def run(k: int) -> float:
        sync()
        t0 = time.perf_counter()
        for _ in range(k):
            main_output(model(x))
        sync()
        return time.perf_counter() - t0

    with torch.inference_mode(), autocast(device, precision):
        run(2)  # warm-up: kernel selection, caches
        per_iter = run(1)
        k = max(1, int(seconds / max(per_iter, 1e-4)))
        rates = [k * batch / run(k) for _ in range(repeats)]
    ips = statistics.median(rates)
    return {"batch": batch, "images_per_s": ips, "ms_per_image": 1000.0 / ips, "runs": repeats, "iters_per_run": k}


def benchmark_model(model: nn.Module, size: int, device: torch.device, batch: int = 16, seconds: float = 2.0,
                    repeats: int = 5, log=print) -> dict:
    name, prec = fast_path(device)
    out = {
        "device": str(device) if device.type == "cpu" else torch.cuda.get_device_name(device),
        "input_size": size,
        "params_m": count_parameters(model) / 1e6,
        "gflops": gflops(model.float().to(device), size),
        "threads": torch.get_num_threads(),
        "paths": {},
    }
    for label, precision, cl in [("fp32 eager", "fp32", False), (name, prec, True)]:
        res = {}
        for b in (1, batch):
            r = images_per_second(model, size, b, device, precision, cl, seconds, repeats)
            res["batch1" if b == 1 else "batched"] = r
            log(f"  {label:<30} batch {b:>3}: {r['images_per_s']:7.1f} images/s, {r['ms_per_image']:7.2f} ms/image")
        out["paths"]["fp32" if label == "fp32 eager" else "fast"] = {"name": label, "precision": precision, **res}
        model = model.to(memory_format=torch.contiguous_format)
    f, s = out["paths"]["fp32"], out["paths"]["fast"]
    out["speedup_batched"] = s["batched"]["images_per_s"] / f["batched"]["images_per_s"]
    out["speedup_batch1"] = s["batch1"]["images_per_s"] / f["batch1"]["images_per_s"]
    return out


def benchmark(model_path: Path, results_root: Path, dataset: str, batch: int, seconds: float, repeats: int,
              device: str = "auto", log=print) -> dict:
    """Speed of both paths on this machine (CPU, and the GPU when present) and their accuracy."""
    from .evaluate import eval_rows, predict_rows
    from .metrics import regression_metrics
    from .train import load_model, pick_device

    model, meta = load_model(model_path, "cpu")
    size = meta["input_size"]
    devices = [torch.device("cpu")]
    if pick_device(device).type == "cuda":
        devices.append(torch.device("cuda"))
    result = {"arch": meta["arch"], "weights": meta["weights"], "results": []}
    for dev in devices:
        log(f"{meta['arch']} on {dev} at {size} px:")
        result["results"].append(benchmark_model(model, size, dev, batch, seconds, repeats, log))
    # accuracy of the fast path against fp32, on the test split
    dev = devices[-1]
    rows = eval_rows(results_root, dataset)
    model = model.to(dev)
    acc = {}
    for key, (name, prec) in {"fp32": ("fp32 eager", "fp32"), "fast": fast_path(dev)}.items():
        p, y = predict_rows(model, meta, results_root, rows, dev, prec)
        acc[key] = {"path": name, **regression_metrics(y, p)}
    result["accuracy"] = acc
    result["r2_change"] = acc["fast"]["overall"]["r2"] - acc["fp32"]["overall"]["r2"]
    log(f"R² overall: fp32 {acc['fp32']['overall']['r2']:.4f}, fast {acc['fast']['overall']['r2']:.4f} "
        f"(change {result['r2_change']:+.4f})")
    return result
