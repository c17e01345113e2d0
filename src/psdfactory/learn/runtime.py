"""What training, evaluation, the benchmark and prediction share: the device and precision
to run on, the loss, batched inference, and saving/loading a model file."""

from __future__ import annotations

import logging
import math
import time
from contextlib import nullcontext
from pathlib import Path

import numpy as np
import torch
from torch import nn

from .. import PsdError
from ..io import atomic_path
from .data import normalise
from .models import TargetStats, main_output

logger = logging.getLogger(__name__)


def pick_device(name: str) -> torch.device:
    """`auto`, `cpu`, `cuda`, `cuda:N` or another device PyTorch knows, refused in one line when
    PyTorch does not know it or this machine does not have it. `auto` in a SLURM job that was
    given GPUs but in which CUDA sees none runs on the CPU and logs a warning saying so."""
    if name == "auto":
        if torch.cuda.is_available():
            return torch.device("cuda")
        import os

        env = os.environ
        given = [f"{k}={env[k]}" for k in ("SLURM_JOB_GPUS", "SLURM_STEP_GPUS") if env.get(k)]
        if env.get("SLURM_GPUS_ON_NODE", "0") not in ("", "0"):
            given.append(f"SLURM_GPUS_ON_NODE={env['SLURM_GPUS_ON_NODE']}")
        if given:  # asked for (--gpus, --gres=gpu) and granted, but unusable: say why the job is slow
            why = "this PyTorch is built without CUDA" if torch.version.cuda is None else "no CUDA driver or device"
            visible = env.get("CUDA_VISIBLE_DEVICES", "(unset)")
            logger.warning(f"device auto: SLURM allocated GPU(s) to this job ({', '.join(given)}; "
                           f"CUDA_VISIBLE_DEVICES={visible}) but CUDA sees none ({why}); running on the CPU")
        return torch.device("cpu")
    try:
        dev = torch.device(name)
    except (RuntimeError, ValueError, TypeError):
        raise PsdError(f"device {name!r} is not one PyTorch knows; use auto, cpu, cuda or cuda:N") from None
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise PsdError(f"device {name!r} asked for, but CUDA is not available here")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise PsdError(f"device {name!r} asked for, but this machine has "
                           f"{torch.cuda.device_count()} CUDA device(s)")
    elif dev.type == "mps" and not torch.backends.mps.is_available():
        raise PsdError(f"device {name!r} asked for, but MPS is not available here")
    elif dev.type not in ("cpu", "cuda", "mps"):
        raise PsdError(f"device {name!r}: psdfactory runs on cpu, cuda or mps")
    return dev


def cpu_has_fast_bf16() -> bool:
    """Native bf16 matmuls/convolutions that PyTorch may use here (AVX512-BF16 or AMX, not masked
    by ATEN_CPU_CAPABILITY; Arm bf16). Only says bf16 is worth timing: see faster_cpu_precision."""
    from . import capability

    return capability.detect().native_bf16


def pick_precision(name: str, device: torch.device) -> str:
    if name != "auto":
        return name
    if device.type == "cuda":
        return "bf16" if torch.cuda.is_bf16_supported() else "fp16"
    return "bf16" if cpu_has_fast_bf16() else "fp32"


def autocast(device: torch.device, precision: str):
    if precision == "fp32":
        return nullcontext()
    dtype = torch.bfloat16 if precision == "bf16" else torch.float16
    return torch.autocast(device.type, dtype=dtype)


def optimise_step(model: nn.Module, opt: torch.optim.Optimizer, x: torch.Tensor, loss_of, device: torch.device,
                  precision: str, lr_key: str, scaler: torch.amp.GradScaler | None = None) -> float:
    """One optimiser step on the batch `x` (normalised, on `device`): forward under `precision`'s
    autocast, `loss_of(output)`, a clear error naming `lr_key` on a non-finite loss, backward,
    step. In fp16 the loss is scaled by `scaler` (`loss_scaler`: the training's own, kept in its
    resumable checkpoint): fp16 gradients underflow without it, where bf16 has fp32's range.
    Returns the batch's loss."""
    if precision == "fp16" and scaler is None:
        raise ValueError("an fp16 step needs the training's loss scaler (runtime.loss_scaler)")
    with autocast(device, precision):
        out = model(x)
    loss = loss_of(out)
    if not torch.isfinite(loss):
        raise PsdError(f"training diverged (non-finite loss); lower {lr_key}")
    opt.zero_grad(set_to_none=True)
    if scaler is not None:
        scaler.scale(loss).backward()
        scaler.step(opt)  # skipped, and the scale lowered, where a gradient overflowed
        scaler.update()
        if scaler.get_scale() < MIN_LOSS_SCALE:  # every step overflows: no step is taken any more
            raise PsdError(f"fp16 training stalled: the gradients overflow at every step (loss scale "
                           f"{scaler.get_scale():.2g}); train in bf16 or fp32 (train.precision), or lower {lr_key}")
    else:
        loss.backward()
        opt.step()
    return float(loss.detach())


MIN_LOSS_SCALE = 2.0 ** -10  # fp16's loss scale starts at 2^16 and halves at each overflowing step


def loss_scaler(device: torch.device | str, precision: str) -> torch.amp.GradScaler | None:
    """The loss scaler a training in `precision` steps with (`optimise_step`): fp16's, None otherwise."""
    return torch.amp.GradScaler(torch.device(device).type) if precision == "fp16" else None


LR_SCHEDULES = ("plateau", "onecycle")
ONECYCLE_WARMUP = 0.15  # share of the steps spent rising to train.lr
ONECYCLE_START_DIV, ONECYCLE_FINAL_DIV = 10.0, 100.0  # starts at lr / 10, ends at lr / 10 / 100


class LrSchedule:
    """`train.lr_schedule`: ``plateau`` (the paper's: ReduceLROnPlateau on the validation loss,
    stepped once per epoch) or ``onecycle`` (torch's OneCycleLR over every step of
    `train.epochs`: a rise from lr/10 to lr over the first 15 % of the steps, then a cosine decay
    to lr/1000 — the schedule for a fixed budget of steps, stepped after every batch)."""

    def __init__(self, opt: torch.optim.Optimizer, name: str, epochs: int, steps_per_epoch: int,
                 lr_factor: float, lr_patience: int):
        if name not in LR_SCHEDULES:
            raise PsdError(f"train.lr_schedule must be one of {', '.join(LR_SCHEDULES)}, got {name!r}")
        self.name = name
        if name == "plateau":
            self.sched = torch.optim.lr_scheduler.ReduceLROnPlateau(opt, mode="min", factor=lr_factor,
                                                                    patience=lr_patience)
        else:
            self.sched = torch.optim.lr_scheduler.OneCycleLR(
                opt, max_lr=[g["lr"] for g in opt.param_groups], total_steps=max(epochs * steps_per_epoch, 1),
                pct_start=ONECYCLE_WARMUP, anneal_strategy="cos", div_factor=ONECYCLE_START_DIV,
                final_div_factor=ONECYCLE_FINAL_DIV)

    @property
    def stops_early(self) -> bool:
        """Whether early stopping may end a training under it: under the plateau schedule. A one-cycle
        schedule's rate falls to its lowest only at the end of train.epochs: a training stopped early under it
        keeps weights of a high rate (measured: config/gravel.yaml at 200 epochs stopped at epoch 88 at
        2.2e-3, and read worse than at 100 epochs run to their end; docs/experiments.md, 2026-12-01)."""
        return self.name == "plateau"

    def after_step(self) -> None:
        # the last of the budgeted steps runs at the final rate; a step past it keeps that rate
        if self.name == "onecycle" and self.sched.last_epoch < self.sched.total_steps - 1:
            self.sched.step()

    def after_epoch(self, val_loss: float) -> None:
        if self.name == "plateau":
            self.sched.step(val_loss)

    def state_dict(self) -> dict:
        return self.sched.state_dict()

    def load_state_dict(self, state: dict) -> None:
        self.sched.load_state_dict(state)


def training_precision(requested: str, device: torch.device, model: nn.Module, size: int, batch: int,
                       loss_of) -> str:
    """The precision to train `model` in: `pick_precision`'s, and for `auto` on a CPU with native
    bf16 whichever of bf16 and fp32 trains it faster here (`faster_cpu_precision`, on a batch of
    `batch` `size`-px images, `loss_of(output)` the loss)."""
    precision = pick_precision(requested, device)
    if requested == "auto" and precision == "bf16" and device.type == "cpu":
        precision = faster_cpu_precision(model, size, batch, loss_of)
    return precision


PRECISION_ROUNDS = 3  # timed passes of each precision, interleaved; the fastest of each counts


def faster_cpu_precision(model: nn.Module, size: int, batch: int, loss_of, timer=time.perf_counter) -> str:
    """bf16 autocast or fp32 for CPU training, whichever trains this model faster here.

    Native bf16 helps the big convolutions (ResNet-50: ~2×; the instance network 1.8-2.1× on an
    AMD EPYC with AVX512-BF16) but not always the depthwise ones (EfficientNet-B0 can be slower in
    bf16), so 'auto' times forward+backward passes of each on a batch of `batch` random `size`-px
    images (`loss_of(output)` gives the loss to differentiate) without stepping the optimiser, and
    keeps the faster. After a warm-up pass of each, PRECISION_ROUNDS rounds time one pass of each,
    in alternating order, and each precision counts its fastest: on cores shared with other work a
    single pass can take several times its time (measured: fp32 picked over a 10× faster bf16).
    """
    x = torch.randn(batch, 3, size, size).contiguous(memory_format=torch.channels_last)
    dev = torch.device("cpu")
    saved = {k: v.clone() for k, v in model.state_dict().items()}  # BatchNorm statistics move in train mode
    model.train()

    def one_pass(prec: str) -> float:
        t0 = timer()
        with autocast(dev, prec):
            out = model(x)
        loss_of(out).backward()
        return timer() - t0

    order = ["bf16", "fp32"]
    for prec in order:  # warm-up
        one_pass(prec)
    times = {prec: math.inf for prec in order}
    for r in range(PRECISION_ROUNDS):
        for prec in (order if r % 2 == 0 else order[::-1]):
            times[prec] = min(times[prec], one_pass(prec))
    model.zero_grad(set_to_none=True)
    model.load_state_dict(saved)
    pick = "bf16" if times["bf16"] < times["fp32"] else "fp32"
    logger.info(f"precision auto: one training batch takes {times['bf16']:.2f} s in bf16, "
                f"{times['fp32']:.2f} s in fp32 (fastest of {PRECISION_ROUNDS} each) → {pick}")
    return pick


def loss_fn(model_out, y_std: torch.Tensor, stats: TargetStats, aux_weight: float) -> torch.Tensor:
    mse = nn.functional.mse_loss
    main = main_output(model_out).float()
    loss = mse(stats.standardise(main), y_std)
    aux = getattr(model_out, "aux_logits", None)
    if aux is not None and aux_weight > 0:
        loss = loss + aux_weight * mse(stats.standardise(aux.float()), y_std)
    return loss


@torch.no_grad()
def predict_batches(model, loader, device, precision) -> tuple[torch.Tensor, torch.Tensor]:
    model.eval()
    preds, ys = [], []
    for x, y in loader:
        x = normalise(x.to(device)).contiguous(memory_format=torch.channels_last)
        with autocast(device, precision):
            preds.append(main_output(model(x)).float().cpu())
        ys.append(y)
    return torch.cat(preds), torch.cat(ys)


def write_torch(path: Path, obj: dict) -> None:
    """torch.save, atomically and reproducibly: through a file object, because given a path torch
    names the archive's root folder after the file's name — here a random temporary one, which
    would make two saves of the same weights differ byte for byte."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        torch.save(obj, f)


def save_model(path: Path, model: nn.Module, meta: dict) -> None:
    state = {k: v.detach().cpu() for k, v in model.state_dict().items()}
    write_torch(path, {"meta": meta, "state_dict": state})


def unpickling_reason(e: Exception) -> str:
    """The line of torch's weights-only refusal that says what the file holds (e.g. "Unsupported
    global: GLOBAL io.open ..."), without its advice on how to load the file unsafely."""
    lines = [ln.strip() for ln in str(e).splitlines() if ln.strip()]
    found = [ln.split("error:", 1)[-1].strip() for ln in lines if "WeightsUnpickler error" in ln]
    text = found[0] if found else (lines[0] if lines else type(e).__name__)
    return text.split(" was not an allowed global")[0].replace("\x1b[1m", "").replace("\x1b[0m", "")[:160]


def _looks_like_torch_file(path: Path) -> bool:
    """A whole zip archive (torch.save's format since 1.6: the end-of-archive record is there) or
    a legacy pickle (it starts with the pickle protocol byte)."""
    import zipfile

    try:
        with open(path, "rb") as f:
            head = f.read(2)
        return zipfile.is_zipfile(path) or head[:1] == b"\x80"
    except OSError:
        return True  # let torch.load say what is wrong


def load_checkpoint(path: Path, what: str = "psdfactory model") -> dict:
    """A file written by torch.save, loaded with ``weights_only=True``: tensors and plain data
    (dict, list, tuple, str, int, float, bool, None) only. A file that holds other Python objects
    (which unpickling would construct, and so could run code) is refused, and nothing in it runs."""
    import pickle

    path = Path(path)
    if not path.is_file():
        raise PsdError(f"{what} file not found: {path}")
    if not _looks_like_torch_file(path):
        raise PsdError(f"{path} is not a {what}: not a file torch.save wrote (empty, truncated, or overwritten by "
                       "something else?); use the model.pt that training wrote")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as e:
        raise PsdError(f"{path} refused: it holds Python objects, not just tensors and plain data, and loading it "
                       f"could run code ({unpickling_reason(e)}); psdfactory loads model files with weights_only=True "
                       f"and runs nothing in them; this is not a {what} "
                       "(psdfactory writes only tensors and plain data)") from None
    except Exception as e:
        raise PsdError(f"{path} is not a {what} ({type(e).__name__}: {e})") from None
    if not isinstance(ckpt, dict):
        raise PsdError(f"{path} is not a {what} (it holds a {type(ckpt).__name__}, not a dict)")
    return ckpt


def _is_int(v: object, lo: int, hi: int) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and lo <= v <= hi


def _is_number(v: object, lo: float, hi: float) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and lo < v < hi


def is_target_stats(v: object) -> bool:
    """TargetStats as plain data: four lists of three finite numbers, the spreads positive."""
    if not isinstance(v, dict) or set(v) != {"mean", "std", "part_mean", "part_std"}:
        return False
    ok = lambda xs, lo: isinstance(xs, list) and len(xs) == 3 and all(_is_number(x, lo, 1e9) for x in xs)  # noqa: E731
    return ok(v["mean"], -1e9) and ok(v["part_mean"], -1e9) and ok(v["std"], 0) and ok(v["part_std"], 0)


META_CHECKS = {  # what every model's meta must hold before anything is built or resized from it
    "arch": lambda v: isinstance(v, str) and 0 < len(v) < 100 and v.replace("_", "").isalnum(),
    "input_size": lambda v: _is_int(v, 16, 4096),
    "image_resolution": lambda v: _is_int(v, 16, 65536),
    "mm_per_px": lambda v: _is_number(v, 0, 1e4),
}


def meta_problems(meta: object) -> list[str]:
    """What is wrong with a model's metadata (model.pt's ``meta``, an export's meta.json): the
    keys predict and evaluate rely on, their types and sane ranges, and its estimator's own
    (`Estimator.meta_problems`), and a calibration block (`calibration.calibration_problems`).
    Empty when it is fine."""
    from .calibration import basis_of, calibration_problems
    from .registry import estimator_class

    if not isinstance(meta, dict):
        return ["it must hold a JSON object / dict"]
    problems = [f"{k} is missing or not valid (got {str(meta.get(k))[:80]!r})" for k, ok in META_CHECKS.items()
                if not ok(meta.get(k))]
    if problems:
        return problems
    try:
        est_cls = estimator_class(meta["arch"])
        problems = est_cls.meta_problems(meta)
    except PsdError as e:
        return [str(e)]
    if "calibration" in meta:  # any estimator's model may carry one (`psdfactory calibrate`)
        problems = problems + calibration_problems(meta["calibration"])
        definition = meta["calibration"]["size_definition"] if not problems else None
        if definition is not None and definition not in est_cls.definitions(meta):
            problems.append(f"calibration.size_definition {definition} is not one this {meta['arch']} model reads "
                            f"({', '.join(est_cls.definitions(meta))})")
        basis = basis_of(meta["calibration"]) if not problems else None
        if basis is not None and not est_cls.reads(meta, basis["size_definition"], basis["weighting"]):
            problems.append(f"calibration.basis: the correction takes the {basis['size_definition']} reading, "
                            f"{basis['weighting']}-weighted, which this {meta['arch']} model does not give (a "
                            "calibration of another model?): calibrate this model again")
    return problems


def load_model(path: Path, device: torch.device | str = "cpu") -> tuple[nn.Module, dict]:
    """A model file's network (built by its estimator, `Estimator.build_net`) and its meta."""
    from .registry import estimator_class

    path = Path(path)
    ckpt = load_checkpoint(path)
    problems = meta_problems(ckpt.get("meta"))
    if problems:
        raise PsdError(f"{path} is not a psdfactory model: its meta is refused: " + "; ".join(problems))
    try:
        meta = ckpt["meta"]
        model = estimator_class(meta["arch"]).build_net(meta)
        model.load_state_dict(ckpt["state_dict"])
    except PsdError:
        raise
    except Exception as e:
        raise PsdError(f"{path} is not a psdfactory model ({type(e).__name__}: {e})") from None
    return model.to(device).eval(), meta


def torch_runner(module: nn.Module, device: torch.device | str = "cpu", precision: str = "fp32",
                 channels_last: bool = False):
    """A network as a function: normalised float N×3×H×W → its outputs as a float32 numpy array,
    on `device`, under `precision`'s autocast, in `channels_last` memory format if asked."""
    dev = torch.device(device)
    fmt = torch.channels_last if channels_last else torch.contiguous_format
    module = module.to(dev).eval().to(memory_format=fmt)

    def run(x: torch.Tensor) -> np.ndarray:
        with torch.inference_mode(), autocast(dev, precision):
            return module(x.to(dev).contiguous(memory_format=fmt)).float().cpu().numpy()

    return run


def load_estimator(path: Path, device: torch.device | str = "cpu"):
    """A model file (`model.pt`) as its estimator (`learn.estimator.Estimator`), its network on
    `device` in fp32."""
    from .registry import estimator_class

    net, meta = load_model(path, device)
    est = estimator_class(meta["arch"])(meta, None, net)
    est.run = torch_runner(est.inference_module(), torch.device(device))
    return est
