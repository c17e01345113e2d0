"""CPU capability detection: what the fast paths may try here (PyTorch's own ATEN_CPU_CAPABILITY honoured)."""

import json
import os
import subprocess
import sys

import pytest
import torch

from psdfactory import PsdError
from psdfactory.deploy.benchmark import candidates
from psdfactory.learn import capability


def _detect_with(env: dict) -> dict:
    code = "import json; from psdfactory.learn.capability import detect; print(json.dumps(detect().as_dict()))"
    out = subprocess.run([sys.executable, "-c", code], env={**os.environ, **env}, capture_output=True, text=True,
                         check=True)
    return json.loads(out.stdout)


@pytest.mark.parametrize("isa", ["avx2", "default"])
def test_aten_cpu_capability_forces_the_portable_path(isa):
    caps = _detect_with({"ATEN_CPU_CAPABILITY": isa})
    assert caps["forced_isa"] == isa
    if caps["machine"] == "x86_64":
        assert caps["torch_isa"] == isa.upper()
        assert caps["native_bf16"] is False  # bf16 kernels need AVX-512: masked by the forced ISA
    assert f"ATEN_CPU_CAPABILITY={isa}" in caps["summary"]


def test_detect_describes_this_machine():
    caps = capability.detect()
    assert caps.cpu_model and caps.machine
    assert caps.torch_isa == str(torch.backends.cpu.get_cpu_capability()).upper()
    assert set(caps.flags) <= set(capability.REPORTED_FLAGS)
    if caps.native_bf16 and caps.machine == "x86_64":
        assert caps.torch_isa in capability.AVX512_ISAS


def _caps(bf16: bool, ort: bool) -> capability.Capabilities:
    return capability.Capabilities("x86_64", "test", (), "AVX2", "", bf16, False, ort)


@pytest.mark.parametrize("bf16", [False, True])
@pytest.mark.parametrize("ort", [False, True])
def test_candidates_follow_the_capabilities(bf16, ort):
    paths, skipped = candidates(torch.device("cpu"), _caps(bf16, ort))
    assert {"fp32", "channels_last"} <= set(paths)
    assert ("bf16" in paths) == bf16 and ("bf16" in skipped) == (not bf16)
    assert ("int8" in paths) == ort == ("ort_fp32" in paths)
    assert not ort or paths["int8"].engine == "onnxruntime"
    assert not set(paths) & set(skipped)


def test_candidates_name_a_forced_isa():
    caps = capability.Capabilities("x86_64", "test", (), "AVX2", "avx2", False, True, True)
    _, skipped = candidates(torch.device("cpu"), caps)
    assert "forced to avx2" in skipped["bf16"]


def test_missing_onnxruntime_is_a_clear_error(monkeypatch):
    from psdfactory import PsdError
    from psdfactory.deploy.quantize import require_onnxruntime

    monkeypatch.setattr(capability, "onnxruntime_available", lambda: False)
    with pytest.raises(PsdError, match="int8 export needs ONNX Runtime"):
        require_onnxruntime("int8 export")


@pytest.mark.parametrize("spike_on, expected", [("bf16", "bf16"), ("fp32", "bf16"), (None, "bf16")])
def test_precision_auto_keeps_the_faster_despite_one_slow_pass(spike_on, expected):
    """On shared cores one timed pass can take many times its due: 'auto' times each precision in
    interleaved rounds and counts its fastest, so one spike does not flip the choice."""
    import itertools

    import torch
    from torch import nn

    from psdfactory.learn.runtime import PRECISION_ROUNDS, faster_cpu_precision

    order = ["bf16", "fp32"] + [p for r in range(PRECISION_ROUNDS)
                                for p in (["bf16", "fp32"] if r % 2 == 0 else ["fp32", "bf16"])]
    due = {"bf16": 0.1, "fp32": 1.0}  # bf16 is 10x faster here
    spiked = order.index(spike_on, 2) if spike_on else None  # the first timed pass of that precision
    durations = [due[p] * (50.0 if i == spiked else 1.0) for i, p in enumerate(order)]
    clock = itertools.accumulate(d for d in durations for d in (0.0, d))  # each pass reads the clock twice
    model = nn.Sequential(nn.Conv2d(3, 4, 3), nn.BatchNorm2d(4))
    before = {k: v.clone() for k, v in model.state_dict().items()}
    pick = faster_cpu_precision(model, 16, 2, lambda out: out.float().sum(), timer=lambda: next(clock))
    assert pick == expected
    assert all(torch.equal(before[k], v) for k, v in model.state_dict().items())  # its statistics restored


def test_precision_auto_picks_fp32_where_it_is_faster():
    import itertools

    from torch import nn

    from psdfactory.learn.runtime import PRECISION_ROUNDS, faster_cpu_precision

    order = ["bf16", "fp32"] + [p for r in range(PRECISION_ROUNDS)
                                for p in (["bf16", "fp32"] if r % 2 == 0 else ["fp32", "bf16"])]
    durations = [{"bf16": 0.3, "fp32": 0.2}[p] for p in order]
    clock = itertools.accumulate(d for d in durations for d in (0.0, d))
    model = nn.Conv2d(3, 4, 3)
    assert faster_cpu_precision(model, 16, 2, lambda out: out.float().sum(), timer=lambda: next(clock)) == "fp32"


def test_fp16_training_scales_the_loss_and_skips_a_step_whose_gradients_overflow():
    """fp16 gradients underflow without loss scaling: a training in fp16 steps with its own
    GradScaler (runtime.loss_scaler; none in bf16 or fp32); a step whose gradients are not finite
    is skipped and the scale lowered; an fp16 step without the scaler is refused."""
    import torch

    from psdfactory.learn.runtime import loss_scaler, optimise_step

    torch.manual_seed(0)
    model = torch.nn.Linear(4, 1)
    opt = torch.optim.SGD(model.parameters(), lr=0.1)
    x, dev = torch.randn(8, 4), torch.device("cpu")
    assert loss_scaler(dev, "bf16") is None and loss_scaler(dev, "fp32") is None
    scaler = loss_scaler(dev, "fp16")

    def square(out):
        return out.float().pow(2).mean()

    before = model.weight.detach().clone()
    losses = [optimise_step(model, opt, x, square, dev, "fp16", "train.lr", scaler) for _ in range(30)]
    assert not torch.equal(model.weight, before) and losses[-1] < losses[0]  # it learns
    scale, kept = scaler.get_scale(), model.weight.detach().clone()
    hook = model.weight.register_hook(lambda g: g * float("inf"))  # a finite loss, an infinite gradient
    optimise_step(model, opt, x, square, dev, "fp16", "train.lr", scaler)
    hook.remove()
    assert torch.equal(model.weight, kept) and scaler.get_scale() < scale  # skipped, scale lowered
    optimise_step(model, opt, x, square, dev, "fp32", "train.lr")
    assert not torch.equal(model.weight, kept)  # fp32 steps as before, without a scaler
    with pytest.raises(ValueError, match="loss scaler"):
        optimise_step(model, opt, x, square, dev, "fp16", "train.lr")
    hook = model.weight.register_hook(lambda g: g * float("inf"))  # overflowing for good: a clear error
    with pytest.raises(PsdError, match="fp16 training stalled"):
        for _ in range(40):
            optimise_step(model, opt, x, square, dev, "fp16", "train.lr", scaler)
    hook.remove()


class _Clock:
    """A fake perf_counter that only the benchmarked step advances."""

    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now


@pytest.mark.parametrize("step_s, expected_steps, expected_runs", [
    (11.0, 1 + 3, 3),            # a step longer than `seconds`: one warm-up, then the measuring step + 2 more
    (0.01, 2 + 1 + 5 * 100, 5),  # a fast one: two warm-up steps, one to measure it, 5 runs of 100 steps
])
def test_throughput_times_a_slow_step_fewer_times(monkeypatch, step_s, expected_steps, expected_runs):
    from psdfactory.deploy import benchmark

    clock, calls = _Clock(), []
    monkeypatch.setattr(benchmark.time, "perf_counter", clock)

    def step():
        calls.append(1)
        clock.now += step_s

    r = benchmark.throughput(step, batch=16, seconds=1.0, repeats=5)
    assert len(calls) == expected_steps and r["runs"] == expected_runs
    assert r["images_per_s"] == pytest.approx(16 / step_s)  # the rate of the step, either way


def test_throughput_never_times_more_runs_than_asked(monkeypatch):
    from psdfactory.deploy import benchmark

    clock = _Clock()
    monkeypatch.setattr(benchmark.time, "perf_counter", clock)
    r = benchmark.throughput(lambda: setattr(clock, "now", clock.now + 5.0), batch=1, seconds=1.0, repeats=1)
    assert r["runs"] == 1 and r["images_per_s"] == pytest.approx(0.2)
