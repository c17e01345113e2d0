"""Inference speed per architecture, in the layout of the paper's table 3.

Side by side in one run, every inference path worth trying on this machine — PyTorch fp32
eager (the baseline), channels-last fp32, channels-last + bf16 autocast where the CPU has native
bf16, fp32 and int8 through ONNX Runtime where it is installed, fp16/bf16 autocast on a CUDA GPU
— each timed (median of repeated runs, at batch 1 and batched) and checked on the test split.
The fast path is the fastest whose R² of every target stays within ``MAX_R2_CHANGE`` of fp32's and, for
a model that finds grains, whose instance masks match fp32's with F1 ≥ ``MIN_GRAIN_F1`` on every
test image: chosen by measurement on the machine at hand, never by a list of CPU flags (fp32
eager is always a candidate, so there is always an answer).
"""

from __future__ import annotations

import logging
import math
import statistics
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from ..learn import capability
from ..learn.capability import Capabilities
from ..learn.models import count_parameters
from .quantize import MAX_R2_CHANGE, MIN_GRAIN_F1, r2_change, r2_moves

logger = logging.getLogger(__name__)
# timed runs at least of a step that alone outlasts the benchmark's `seconds` (`throughput`): a median of three
MIN_SLOW_RUNS = 3


def gflops(model: nn.Module, size: int) -> float:
    """Forward FLOPs (multiply + add counted as 2) of one image, in 10⁹."""
    from torch.utils.flop_counter import FlopCounterMode

    model = model.eval()
    x = torch.zeros(1, 3, size, size, device=next(model.parameters()).device)
    with torch.no_grad(), FlopCounterMode(display=False) as counter:
        model(x)
    return counter.get_total_flops() / 1e9


@dataclass(frozen=True)
class Candidate:
    """One way to run a model: an engine, a precision and a memory layout."""

    name: str
    engine: str  # "torch" | "onnxruntime"
    precision: str  # fp32 | bf16 | fp16 | int8
    channels_last: bool = False


def candidates(device: torch.device, caps: Capabilities,
               int8: bool = True) -> tuple[dict[str, Candidate], dict[str, str]]:
    """(the paths worth timing on this device, {path: why it is not tried}) — keys are stable
    names used in the benchmark JSON and the report. `int8`: whether the estimator allows it."""
    paths = {"fp32": Candidate("fp32 eager", "torch", "fp32")}
    skipped: dict[str, str] = {}
    if device.type == "cuda":
        prec = "bf16" if torch.cuda.is_bf16_supported() else "fp16"
        paths[prec] = Candidate(f"channels_last + {prec} autocast", "torch", prec, True)
        return paths, skipped
    paths["channels_last"] = Candidate("channels_last fp32", "torch", "fp32", True)
    if caps.native_bf16:
        paths["bf16"] = Candidate("channels_last + bf16 autocast", "torch", "bf16", True)
    else:
        why = f"forced to {caps.forced_isa}" if caps.forced_isa else "the CPU has none"
        skipped["bf16"] = f"no native bf16 ({why}; emulated bf16 is slower than fp32)"
    if caps.onnxruntime:
        paths["ort_fp32"] = Candidate("fp32 ONNX Runtime", "onnxruntime", "fp32")
        if int8:
            paths["int8"] = Candidate("int8 ONNX Runtime (static, QDQ)", "onnxruntime", "int8")
        else:
            skipped["int8"] = "not offered for this estimator (its outputs feed post-processing)"
    else:
        skipped["ort_fp32"] = skipped["int8"] = "onnxruntime is not installed"
    return paths, skipped


def throughput(step: Callable[[], object], batch: int, seconds: float, repeats: int,
               sync: Callable[[], None] = lambda: None) -> dict:
    """Median images/s of `step` (one batch of `batch` images) over `repeats` timed runs of about
    `seconds` each, after a warm-up. A step that alone takes longer than `seconds` (a large batch
    read over eight views: ~11 s on 2 cores) is warmed up once and timed in runs of one step, as
    many as `repeats` × `seconds` holds but at least MIN_SLOW_RUNS (fewer where `repeats` asks),
    the first being the step that measured it: its figure is still a median, and the benchmark's
    cost no longer grows with every second a step takes."""

    def run(k: int) -> float:
        sync()
        t0 = time.perf_counter()
        for _ in range(k):
            step()
        sync()
        return time.perf_counter() - t0

    if run(1) < seconds:  # warm-up: kernel selection, caches; a second warm-up step where it is cheap
        run(1)
    first = run(1)
    k = max(1, int(seconds / max(first, 1e-4)))
    if k > 1:
        times = [run(k) for _ in range(repeats)]
    else:
        n = min(repeats, max(MIN_SLOW_RUNS, math.ceil(repeats * seconds / first)))
        times = [first] + [run(1) for _ in range(n - 1)]
    ips = statistics.median(k * batch / t for t in times)
    return {"batch": batch, "images_per_s": ips, "ms_per_image": 1000.0 / ips, "runs": len(times), "iters_per_run": k}


def choose_fast(paths: dict[str, dict], max_r2_change: float = MAX_R2_CHANGE) -> str:
    """The fastest path (batched images/s) whose R² of every target is within ± the budget of fp32's
    (`r2_change`: `quantize.r2_change`, the target that moved most) and whose grains, where it finds
    grains, match fp32's (`grain_f1_vs_fp32` ≥ MIN_GRAIN_F1); a path measured without a dataset has
    neither figure and counts as within; fp32 itself always is."""
    def within(p: dict) -> bool:
        r2, f1 = p.get("r2_change"), p.get("grain_f1_vs_fp32")
        return (r2 is None or abs(r2) <= max_r2_change) and (f1 is None or f1 >= MIN_GRAIN_F1)

    ok = [k for k, p in paths.items() if k == "fp32" or within(p)]
    return max(ok, key=lambda k: paths[k]["batched"]["images_per_s"])


def grain_agreement(masks: list, base: list) -> float | None:
    """The lowest instance-mask F1 (IoU 0.5) of `masks` against `base`, image by image (images
    where `base` has no grain left out); None where the readings hold no masks."""
    from ..learn.instances.scoring import match_instances

    if not masks or any(m is None for m in masks + base):
        return None
    f1s = [m.f1 for m in (match_instances(a, b) for a, b in zip(masks, base, strict=True)) if m.n_true]
    return min(f1s, default=1.0)


def onnx_runners(est, size: int, keys: list[str], calibration: np.ndarray, tmp: Path) -> dict:
    """ONNX Runtime runners (normalised images → outputs) for the requested keys (ort_fp32, int8),
    from one fp32 export of the estimator's inference module."""
    from .quantize import OrtModel, export_onnx, quantize_int8

    fp32 = export_onnx(est.inference_module().cpu(), size, tmp / "fp32.onnx", est.output_name, est.any_size)
    files = {"ort_fp32": fp32}
    if "int8" in keys:
        files["int8"] = quantize_int8(fp32, tmp / "int8.onnx", calibration)
    sessions = {k: OrtModel(files[k], torch.get_num_threads()) for k in keys}
    return {k: (lambda x, s=s: s(x.numpy())) for k, s in sessions.items()}


def model_summary(model: nn.Module, size: int, device: torch.device, caps: Capabilities) -> dict:
    """What every benchmark result starts with: device, input size, model size and cost, CPU, budget."""
    return {
        "device": str(device) if device.type == "cpu" else torch.cuda.get_device_name(device),
        "input_size": size,
        "params_m": count_parameters(model) / 1e6,
        "gflops": gflops(model.float().to(device), size),
        "threads": torch.get_num_threads(),
        "cpu": caps.as_dict(),
        "max_r2_change": MAX_R2_CHANGE,
        "paths": {},
    }


def bench_images(est, results_root: Path | None, rows: list[dict] | None, batch: int) -> tuple[torch.Tensor, float]:
    """uint8 images at the network's input (the test split's first ones, repeated to `batch`;
    random ones without a dataset) and their mm per pixel at that input."""
    from ..learn.data import SceneImages
    from ..learn.estimator import network_scale

    size = est.meta["input_size"]
    if rows:
        ds = SceneImages(results_root, rows[:batch], size, cache=False)
        images = torch.stack([ds[i][0] for i in range(len(ds))])
        scale = network_scale(rows[0], size)
    else:
        gen = torch.Generator().manual_seed(0)
        images = torch.randint(0, 256, (max(batch, 1), 3, size, size), dtype=torch.uint8, generator=gen)
        scale = est.meta["mm_per_px"] * est.meta["image_resolution"] / size
    return images.repeat(-(-batch // len(images)), 1, 1, 1)[:batch], scale


def benchmark_estimator(est, device: torch.device, results_root: Path | None, dataset: str | None, batch: int,
                        seconds: float, repeats: int, caps: Capabilities | None = None) -> dict:
    """Every candidate path on one device, end to end (`Estimator.predict`: the network and what
    reads its outputs): speed at batch 1 and batched, and (with a dataset) accuracy on its test
    split; the fastest within the accuracy budget becomes the "fast" path, and its time alone is
    split into the network's and the reading's share (`stages`). Without a dataset only speed is
    measured (int8 is then calibrated on random inputs)."""
    from ..learn.estimator import predictions, rows_readings
    from ..learn.evaluate import eval_rows
    from ..learn.metrics import regression_metrics
    from ..learn.runtime import torch_runner
    from .quantize import calibration_images

    caps = caps or capability.detect()
    size = est.meta["input_size"]
    module = est.inference_module()
    out = model_summary(module, size, device, caps)
    rows = eval_rows(results_root, dataset) if results_root is not None else None
    todo, out["skipped"] = candidates(device, caps, est.int8)
    ort_keys = [k for k, c in todo.items() if c.engine == "onnxruntime"]
    pool, scale = bench_images(est, results_root, rows, batch)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    with tempfile.TemporaryDirectory() as tmp:
        runners = {}
        if ort_keys:
            calib = (calibration_images(results_root, dataset, size) if rows
                     else np.random.default_rng(0).standard_normal((8, 3, size, size)).astype(np.float32))
            runners = onnx_runners(est, size, ort_keys, calib, Path(tmp))

        def runner(key: str):
            path = todo[key]
            return (torch_runner(module, device, path.precision, path.channels_last) if path.engine == "torch"
                    else runners[key])

        for key, path in todo.items():
            res = {"name": path.name, **asdict(path)}
            if key == "int8":
                res["calibration_images"] = len(calib) if rows else 0
            e = est.with_runner(runner(key))
            for b in (1, batch):
                x = pool[:b]
                r = throughput(lambda e=e, x=x: e.predict(x, scale), b, seconds, repeats, sync)
                res["batch1" if b == 1 else "batched"] = r
                logger.info(f"  {path.name:<32} batch {b:>3}: {r['images_per_s']:7.1f} images/s, "
                            f"{r['ms_per_image']:7.2f} ms/image")
            if rows:
                readings, y = rows_readings(e, results_root, rows)
                res["accuracy"] = regression_metrics(y, predictions(readings))
                res["masks"] = [getattr(r.grains, "mask", None) for r in readings]
            out["paths"][key] = res
            module.to(memory_format=torch.contiguous_format)
        base = out["paths"]["fp32"]
        for res in out["paths"].values():
            res["r2_change"], res["r2_change_target"] = (r2_change(res["accuracy"], base["accuracy"]) if rows
                                                         else (None, None))
        if rows and est.finds_grains:
            out["min_grain_f1"] = MIN_GRAIN_F1
            for res in out["paths"].values():
                res["grain_f1_vs_fp32"] = grain_agreement(res["masks"], base["masks"])
        for res in out["paths"].values():
            res.pop("masks", None)
        # the network's and the reading's share of the time: of the fast path only, the one reported
        key = out["fast_key"] = choose_fast(out["paths"])
        e = est.with_runner(runner(key))
        outputs = e.outputs(pool)
        net = throughput(lambda: e.outputs(pool), batch, seconds, repeats, sync)
        post = throughput(lambda: e.read(outputs, [scale] * len(outputs)), batch, seconds, repeats)
        out["paths"][key]["stages"] = {"network_ms_per_image": net["ms_per_image"],
                                       "read_ms_per_image": post["ms_per_image"]}
        module.to(memory_format=torch.contiguous_format)
    fast = out["paths"]["fast"] = dict(out["paths"][key])
    out["stages"] = fast["stages"]
    out["speedup_batched"] = fast["batched"]["images_per_s"] / base["batched"]["images_per_s"]
    out["speedup_batch1"] = fast["batch1"]["images_per_s"] / base["batch1"]["images_per_s"]
    for k, why in out["skipped"].items():
        logger.info(f"  (not tried: {k}: {why})")
    changes = ", ".join(f"{k} {v['r2_change']:+.4f} ({v['r2_change_target']})"
                        + (f" (grain F1 vs fp32 {v['grain_f1_vs_fp32']:.3f})" if v.get("grain_f1_vs_fp32") is not None
                           else "")
                        for k, v in out["paths"].items() if k not in ("fp32", "fast") and v["r2_change"] is not None)
    st = fast["stages"]
    logger.info(f"  fast path: {fast['name']} ({out['speedup_batched']:.2f}× fp32 batched; network "
                f"{st['network_ms_per_image']:.1f} ms/image, reading {st['read_ms_per_image']:.1f} ms/image)"
                + (f"; largest R² change of a target {changes}" if changes else ""))
    return out


def benchmark(model_path: Path, results_root: Path, dataset: str, batch: int, seconds: float, repeats: int,
              device: str = "auto") -> dict:
    """Speed and accuracy of every path on this machine: `device` auto, the CPU and the GPU when
    present (the workflow's benchmark); cpu, the CPU only; cuda[:N], that GPU only."""
    from ..learn.runtime import load_estimator, pick_device

    est = load_estimator(model_path, "cpu")
    meta = est.meta
    picked = pick_device(device)
    devices = [picked]
    if device == "auto" and picked.type == "cuda":  # the workflow's benchmark: the CPU as well
        devices = [torch.device("cpu"), picked]
    caps = capability.detect()
    logger.info(f"CPU: {caps.summary()}")
    result = {"arch": meta["arch"], "weights": meta["weights"], "cpu": caps.as_dict(), "results": []}
    for dev in devices:
        logger.info(f"{meta['arch']} on {dev} at {meta['input_size']} px:")
        result["results"].append(benchmark_estimator(est, dev, results_root, dataset, batch, seconds, repeats, caps))
    fast = result["results"][-1]["paths"]
    result["r2_change"] = fast["fast"]["r2_change"]
    if fast["fp32"].get("accuracy"):
        logger.info(f"R² fp32 → fast, {r2_moves(fast['fast']['accuracy'], fast['fp32']['accuracy'])} (largest "
                    f"change {result['r2_change']:+.4f})")
    return result
