"""What this machine can run fast: CPU features, PyTorch's effective vector ISA, ONNX Runtime.

Detection only says which inference/training paths are *worth trying* here; which one is
fastest is decided by timing them (``benchmark``, ``runtime.faster_cpu_precision``), never by
a flag list. PyTorch's own ``ATEN_CPU_CAPABILITY`` is honoured: with ``ATEN_CPU_CAPABILITY=avx2``
on an AVX-512 machine, PyTorch runs its portable AVX2 kernels and this module reports no native
bf16, so a user or a test can force the portable path anywhere.
"""

from __future__ import annotations

import os
import platform
from dataclasses import asdict, dataclass
from pathlib import Path

# /proc/cpuinfo flags worth naming in a report (x86 and aarch64 spellings)
REPORTED_FLAGS = ("avx2", "fma", "avx512f", "avx512_bf16", "avx512_vnni", "avx_vnni", "amx_bf16", "amx_int8",
                  "amx_tile", "asimd", "bf16", "i8mm", "sve")
# PyTorch's vector ISAs that include AVX-512 (bf16 kernels need it on x86)
AVX512_ISAS = {"AVX512", "AVX512_BF16", "AVX512_VNNI", "AMX"}


@dataclass(frozen=True)
class Capabilities:
    """One machine's CPU as the fast paths see it."""

    machine: str  # x86_64, aarch64, ...
    cpu_model: str
    flags: tuple[str, ...]  # the REPORTED_FLAGS present in /proc/cpuinfo
    torch_isa: str  # torch.backends.cpu.get_cpu_capability(): honours ATEN_CPU_CAPABILITY
    forced_isa: str  # ATEN_CPU_CAPABILITY as set, or ""
    native_bf16: bool  # bf16 matmuls/convolutions in hardware, and PyTorch allowed to use them
    int8_dot: bool  # VNNI / AMX-INT8 / i8mm: int8 dot products in hardware (informational)
    onnxruntime: bool  # onnxruntime (with its quantisation tools) importable

    def summary(self) -> str:
        feats = ", ".join(self.flags) or "none of the listed"
        forced = f", ATEN_CPU_CAPABILITY={self.forced_isa}" if self.forced_isa else ""
        return (f"{self.cpu_model} ({self.machine}); PyTorch ISA {self.torch_isa}{forced}; features: {feats}; "
                f"native bf16: {'yes' if self.native_bf16 else 'no'}; int8 dot products: "
                f"{'yes' if self.int8_dot else 'no'}; ONNX Runtime: {'yes' if self.onnxruntime else 'no'}")

    def as_dict(self) -> dict:
        return {**asdict(self), "flags": list(self.flags), "summary": self.summary()}


def _cpuinfo() -> tuple[str, set[str]]:
    """(model name, flag set) from /proc/cpuinfo; ("", {}) where there is none (macOS, Windows)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return platform.processor() or "unknown CPU", set()
    model, flags = "", set()
    for line in text.splitlines():
        key, _, value = line.partition(":")
        key = key.strip().lower()
        if key in ("model name", "cpu model", "hardware") and not model:
            model = value.strip()
        elif key in ("flags", "features") and not flags:
            flags = set(value.split())
    return model or platform.processor() or "unknown CPU", flags


def onnxruntime_available() -> bool:
    try:
        import onnxruntime.quantization  # noqa: F401 -- imported only to see that it loads (int8 needs this part)
    except ImportError:
        return False
    return True


def detect() -> Capabilities:
    """This machine's capabilities (reads /proc/cpuinfo and asks PyTorch; cheap)."""
    import torch

    model, flags = _cpuinfo()
    isa = str(torch.backends.cpu.get_cpu_capability()).upper()
    machine = platform.machine()
    hw_bf16 = any(getattr(torch.cpu, c, lambda: False)()
                  for c in ("_is_avx512_bf16_supported", "_is_amx_tile_supported"))
    if machine.lower() in ("aarch64", "arm64"):
        native_bf16 = "bf16" in flags
    else:
        native_bf16 = hw_bf16 and isa in AVX512_ISAS
    int8 = bool(flags & {"avx512_vnni", "avx_vnni", "amx_int8", "i8mm"})
    return Capabilities(machine=machine, cpu_model=model, flags=tuple(f for f in REPORTED_FLAGS if f in flags),
                        torch_isa=isa, forced_isa=os.environ.get("ATEN_CPU_CAPABILITY", ""), native_bf16=native_bf16,
                        int8_dot=int8, onnxruntime=onnxruntime_available())
