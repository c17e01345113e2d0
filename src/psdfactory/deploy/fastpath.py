"""Which engine runs a model.pt's network in `predict`: PyTorch, or an ONNX Runtime copy of it,
chosen by measurement on the machine it runs on.

On a CPU, ONNX Runtime runs some networks much faster than PyTorch's eager mode (the instance
estimator's U-Net about 2x on an AVX2 EPYC; docs/performance.md) and others slower, and which
one wins depends on the CPU: so `auto` times both on this machine, once, and keeps the faster.

- The ONNX copy is the estimator's inference module exported as `psdfactory export` does it
  (`quantize.export_onnx`, fp32 only: its outputs are the same numbers up to rounding), checked
  against PyTorch on an input of odd size each time it is loaded (max |difference| < 1e-3), and
  kept in a cache folder (`cache_dir`) under the model file's SHA-256, so that only the first
  run of a model pays for the export.
- The measurement (median of `TIMED_RUNS` passes of each engine, interleaved, after a warm-up,
  on one `TIMING_SIZE` px input) is kept beside it, keyed by the CPU, the thread count and the
  engines' versions: a later run on the same machine reuses the choice, another machine
  measures again.
- On a GPU, or without onnxruntime, PyTorch runs it. A model that is itself an .onnx runs in
  ONNX Runtime whatever is asked (`predict.load_predictor`).

Nothing here changes what a model reads beyond float rounding: tests/test_fastpath.py holds the
grains found through either engine the same (F1 >= 0.99).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import platform
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from .. import PsdError
from ..config import PREDICT_RUNTIMES as RUNTIMES
from ..io import write_json

logger = logging.getLogger(__name__)

TIMING_SIZE = 256  # px side of the input the engines are timed on (a fixed-size model: its own input size)
TIMED_RUNS = 3
MAX_ABS_DIFF = 1e-3  # the ONNX copy's outputs against PyTorch's, as export checks them


def cache_dir() -> Path:
    """Where ONNX copies and timings are kept: $PSDFACTORY_CACHE, else $XDG_CACHE_HOME/psdfactory,
    else ~/.cache/psdfactory."""
    if os.environ.get("PSDFACTORY_CACHE"):
        return Path(os.environ["PSDFACTORY_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "psdfactory"


def file_digest(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()[:24]


def cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_key(threads: int) -> str:
    import onnxruntime

    return f"{cpu_name()} | {threads} threads | torch {torch.__version__} | onnxruntime {onnxruntime.__version__}"


def check_inputs(est) -> list[torch.Tensor]:
    """Inputs the ONNX copy is checked on: one of the model's input size and one of odd size
    (predict gives a CNN images at the model's scale, of any size too)."""
    s = int(est.meta["input_size"])
    gen = torch.Generator().manual_seed(0)
    return [torch.randn(1, 3, s, s, generator=gen), torch.randn(1, 3, s // 2 + 3, s - 5, generator=gen)]


def onnx_runner(est, model_path: Path, cache: Path):
    """An ONNX Runtime runner (normalised float N×3×H×W tensor → float32 numpy outputs) of the
    estimator's network, from the cached export of `model_path` (made and cached if missing, made
    again if the cached file does not load or does not agree), checked against the estimator's
    PyTorch runner."""
    path = cache / f"{file_digest(model_path)}.onnx"
    xs = check_inputs(est)
    refs = [est.run(x) for x in xs]
    problem = None
    for attempt in range(2):
        if attempt or not path.is_file():
            _export(est, model_path, path)
        try:
            run = _ort_run(path)
            diff = max(float(np.abs(run(x) - ref).max()) for x, ref in zip(xs, refs, strict=True))
        except Exception as e:  # onnxruntime's own errors for a damaged file (InvalidProtobuf, Fail, InvalidArgument)
            problem = f"it does not load ({(str(e).strip().splitlines() or [type(e).__name__])[0][:200]})"
            continue
        if diff < MAX_ABS_DIFF:
            return run
        problem = f"it differs from PyTorch by {diff:.2e}"
        logger.warning(f"the cached ONNX copy {path}: {problem}; making it again")
    raise PsdError(f"the ONNX copy of {model_path} ({path}): {problem}; run with --runtime torch")


def _export(est, model_path: Path, path: Path) -> None:
    from .quantize import export_onnx

    path.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    try:  # any H x W: predict gives a CNN, too, images of any size at the model's scale
        export_onnx(est.inference_module().cpu(), int(est.meta["input_size"]), path, est.output_name, any_size=True)
    except OSError:
        raise
    except Exception as e:  # the exporter's own errors: an operator ONNX has no form for, ...
        first = (str(e).strip().splitlines() or [type(e).__name__])[0][:200]
        raise PsdError(f"{model_path} could not be exported to ONNX ({type(e).__name__}: {first})") from None
    logger.info(f"ONNX copy of {model_path} made in {time.perf_counter() - t0:.1f} s, kept as {path}")


def _ort_run(path: Path):
    from .quantize import OrtModel

    ort = OrtModel(path, torch.get_num_threads())
    return lambda x: ort(x.numpy())


def time_engines(runners: dict, size_hw: tuple[int, int], runs: int = TIMED_RUNS) -> dict[str, float]:
    """Median seconds per pass of each runner on one random input of `size_hw`, the engines
    interleaved (so both see the same load), after one warm-up pass each."""
    x = torch.randn(1, 3, *size_hw, generator=torch.Generator().manual_seed(1))
    for run in runners.values():
        run(x)
    times: dict[str, list[float]] = {k: [] for k in runners}
    for _ in range(runs):
        for k, run in runners.items():
            t0 = time.perf_counter()
            run(x)
            times[k].append(time.perf_counter() - t0)
    return {k: statistics.median(v) for k, v in times.items()}


def timing_size(est) -> tuple[int, int]:
    s = int(est.meta["input_size"])
    return (max(s, TIMING_SIZE), max(s, TIMING_SIZE)) if est.any_size else (s, s)


def choose(est, model_path: Path, runtime: str, device: torch.device, cache: Path | None = None):
    """`est` (a model.pt loaded in PyTorch) with its network run by the engine `runtime` asks
    for: `torch` as loaded; `onnx` its ONNX Runtime copy; `auto` the faster of the two as timed
    on this machine (the timing kept in the cache), PyTorch on a GPU or without onnxruntime.
    Sets `est.engine` to what runs it, and returns `est`."""
    if runtime not in RUNTIMES:
        raise PsdError(f"runtime {runtime!r}: give one of {', '.join(RUNTIMES)}")
    est.engine = "torch"
    if runtime == "torch":
        return est
    why = None
    if device.type != "cpu":
        why = f"the model runs on {device}"
    else:
        try:
            import onnxruntime  # noqa: F401
        except ImportError:
            why = "onnxruntime is not installed (pip install onnxruntime)"
    if why:
        if runtime == "onnx":
            raise PsdError(f"--runtime onnx: {why}; ONNX Runtime runs models on the CPU here")
        logger.info(f"runtime: PyTorch ({why})")
        return est
    cache = cache or cache_dir()
    try:
        ort_run = onnx_runner(est, Path(model_path), cache)
    except (OSError, PsdError) as e:
        why = (f"the ONNX copy could not be kept in {cache} ({e}); set PSDFACTORY_CACHE to a writable folder"
               if isinstance(e, OSError) else str(e))
        if runtime == "onnx":
            raise PsdError(f"--runtime onnx: {why}") from None
        logger.warning(f"runtime: PyTorch ({why})")
        return est
    if runtime == "auto":
        key = machine_key(torch.get_num_threads())
        timings_path = cache / f"{file_digest(Path(model_path))}.timings.json"
        known = _read_timings(timings_path)
        if key not in known:
            size = timing_size(est)
            known[key] = {"size_hw": list(size), **time_engines({"torch": est.run, "onnx": ort_run}, size)}
            try:
                write_json(timings_path, known)
            except OSError:
                pass  # measured again next time
        t = known[key]
        if not t["onnx"] < t["torch"]:
            logger.info(f"runtime: PyTorch ({t['torch'] * 1e3:.0f} ms a pass against ONNX Runtime's "
                        f"{t['onnx'] * 1e3:.0f} ms, measured on this machine)")
            return est
        logger.info(f"runtime: ONNX Runtime fp32 ({t['torch'] / t['onnx']:.2f}x PyTorch's speed, measured on this "
                    f"machine at {t['size_hw'][1]} x {t['size_hw'][0]} px; --runtime torch to run PyTorch)")
    est.run = ort_run
    est.engine = "onnx"
    return est


def _read_timings(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
        return data if isinstance(data, dict) and all(isinstance(v, dict) and {"torch", "onnx"} <= v.keys()
                                                      for v in data.values()) else {}
    except (OSError, ValueError):
        return {}

