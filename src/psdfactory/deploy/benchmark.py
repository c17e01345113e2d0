"""Inference speed per architecture, in the layout of the paper's table 3.

Side by side in one run: the plain fp32 eager model, and the candidate fast paths for the
hardware at hand — channels-last memory layout with bf16 autocast on CPUs with native bf16
(AVX512-BF16 / AMX), fp16/bf16 autocast on CUDA GPUs, and int8 through ONNX Runtime on CPUs with
VNNI/AMX-INT8 — each with its accuracy on the test split. The fast path reported is the fastest
whose overall R² is within 0.005 of fp32.
"""

from __future__ import annotations

import statistics
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn

from ..learn.models import count_parameters, main_output
from .quantize import int8_available
from ..learn.runtime import autocast, cpu_has_fast_bf16


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


MAX_R2_DROP = 0.005  # a fast path's overall R² must stay this close to fp32's


def choose_fast(paths: dict[str, dict], max_r2_drop: float = MAX_R2_DROP) -> str:
    """The fastest path (batched images/s) other than fp32 whose R² is within ± the budget; the
    first non-fp32 candidate if none is, so the report shows what the budget refused."""
    others = [k for k in paths if k != "fp32"]
    ok = [k for k in others if paths[k].get("r2_change") is None or abs(paths[k]["r2_change"]) <= max_r2_drop]
    pool = ok or others[:1]
    return max(pool, key=lambda k: paths[k]["batched"]["images_per_s"])


def benchmark_model(model: nn.Module, meta: dict, device: torch.device, results_root: Path | None = None,
                    dataset: str | None = None, batch: int = 16, seconds: float = 2.0, repeats: int = 5,
                    log=print) -> dict:
    """Every candidate path on one device: speed at batch 1 and batched, and (with a dataset)
    accuracy on its test split; the fastest within the accuracy budget becomes the "fast" path.
    Without a dataset only speed is measured (int8 is then calibrated on random inputs)."""
    from ..learn.evaluate import eval_rows, predict_rows
    from ..learn.metrics import regression_metrics

    size = meta["input_size"]
    out = {
        "device": str(device) if device.type == "cpu" else torch.cuda.get_device_name(device),
        "input_size": size,
        "params_m": count_parameters(model) / 1e6,
        "gflops": gflops(model.float().to(device), size),
        "threads": torch.get_num_threads(),
        "paths": {},
    }
    rows = eval_rows(results_root, dataset) if results_root is not None else None
    name, prec = fast_path(device)
    torch_paths = {"fp32": ("fp32 eager", "fp32", False), prec: (name, prec, True)}
    for key, (label, precision, cl) in torch_paths.items():
        res = {"name": label, "precision": precision}
        for b in (1, batch):
            r = images_per_second(model, size, b, device, precision, cl, seconds, repeats)
            res["batch1" if b == 1 else "batched"] = r
            log(f"  {label:<32} batch {b:>3}: {r['images_per_s']:7.1f} images/s, {r['ms_per_image']:7.2f} ms/image")
        model = model.to(memory_format=torch.contiguous_format)
        if rows:
            p, y = predict_rows(model.to(device), meta, results_root, rows, device, precision)
            res["accuracy"] = regression_metrics(y, p)
        out["paths"][key] = res
    if device.type == "cpu" and int8_available():
        out["paths"]["int8"] = int8_path(model, meta, results_root, dataset, rows, batch, seconds, repeats, log)
    base = out["paths"]["fp32"]
    for res in out["paths"].values():
        if rows:
            res["r2_change"] = res["accuracy"]["overall"]["r2"] - base["accuracy"]["overall"]["r2"]
    key = choose_fast(out["paths"])
    out["fast_key"] = key
    fast = out["paths"]["fast"] = dict(out["paths"][key])
    out["speedup_batched"] = fast["batched"]["images_per_s"] / base["batched"]["images_per_s"]
    out["speedup_batch1"] = fast["batch1"]["images_per_s"] / base["batch1"]["images_per_s"]
    if rows:
        log(f"  fast path: {fast['name']} ({out['speedup_batched']:.2f}× fp32 batched); R² change "
            + ", ".join(f"{k} {v['r2_change']:+.4f}" for k, v in out["paths"].items() if k not in ("fp32", "fast")))
    return out


def int8_path(model: nn.Module, meta: dict, results_root: Path | None, dataset: str | None, rows: list[dict] | None,
              batch: int, seconds: float, repeats: int, log=print, n_calibration: int = 64) -> dict:
    """ONNX Runtime int8, calibrated on up to `n_calibration` training images (random inputs
    when there is no dataset: then only its speed means anything)."""
    import tempfile

    from ..learn.data import manifest_rows, normalised_images
    from ..learn.metrics import regression_metrics
    from .quantize import OrtModel, export_onnx, quantize_int8

    size = meta["input_size"]
    if rows:
        train = manifest_rows(results_root, dataset, ("train",))[:n_calibration] or rows
        calib = normalised_images(results_root, train, size)[0].numpy()
    else:
        calib = np.random.default_rng(0).standard_normal((8, 3, size, size)).astype(np.float32)
    with tempfile.TemporaryDirectory() as tmp:
        fp32 = export_onnx(model.cpu(), size, Path(tmp) / "fp32.onnx")
        int8 = quantize_int8(fp32, Path(tmp) / "int8.onnx", calib)
        ort = OrtModel(int8, torch.get_num_threads())
    label = "int8 ONNX Runtime (static, QDQ)"
    res = {"name": label, "precision": "int8", "calibration_images": len(calib) if rows else 0}
    for b in (1, batch):
        r = ort.images_per_second(size, b, seconds, repeats)
        res["batch1" if b == 1 else "batched"] = r
        log(f"  {label:<32} batch {b:>3}: {r['images_per_s']:7.1f} images/s, {r['ms_per_image']:7.2f} ms/image")
    if rows:
        x, y = normalised_images(results_root, rows, size)
        p = np.concatenate([ort(x[i : i + 32].numpy()) for i in range(0, len(x), 32)])
        res["accuracy"] = regression_metrics(y, p)
    return res


def benchmark(model_path: Path, results_root: Path, dataset: str, batch: int, seconds: float, repeats: int,
              device: str = "auto", log=print) -> dict:
    """Speed and accuracy of every path on this machine (CPU, and the GPU when present)."""
    from ..learn.runtime import load_model, pick_device

    model, meta = load_model(model_path, "cpu")
    devices = [torch.device("cpu")]
    if pick_device(device).type == "cuda":
        devices.append(torch.device("cuda"))
    result = {"arch": meta["arch"], "weights": meta["weights"], "results": []}
    for dev in devices:
        log(f"{meta['arch']} on {dev} at {meta['input_size']} px:")
        result["results"].append(benchmark_model(model, meta, dev, results_root, dataset, batch, seconds, repeats, log))
    fast = result["results"][-1]["paths"]
    result["r2_change"] = fast["fast"]["r2_change"]
    log(f"R² overall: fp32 {fast['fp32']['accuracy']['overall']['r2']:.4f}, fast "
        f"{fast['fast']['accuracy']['overall']['r2']:.4f} (change {result['r2_change']:+.4f})")
    return result
