"""What the CPU offers for int8: onnxruntime's x86 uint8 x int8 kernels need VNNI to be exact.

Without AVX-512 VNNI (or AVX-VNNI) onnxruntime multiplies uint8 activations by int8 weights with
vpmaddubsw, whose 16-bit sums saturate; its documentation advises `reduce_range` (7-bit weights) there.
Measured: the default int8 recipe agreed with fp32 on the chosen cell 82 % of the time on such a CPU,
94 % with VNNI. ARM and other CPUs have no such saturation and are never flagged.
"""

from __future__ import annotations

import platform
import sys
from functools import cache
from pathlib import Path

VNNI_FLAGS = ("avx512_vnni", "avx_vnni")
X86 = ("x86_64", "amd64", "i386", "i686", "x86")


def cpu_flags(cpuinfo: str) -> set[str]:
    """The `flags` words of a /proc/cpuinfo text (the first processor's)."""
    for line in cpuinfo.splitlines():
        key, sep, value = line.partition(":")
        if sep and key.strip() == "flags":
            return set(value.split())
    return set()


@cache
def int8_saturates(machine: str | None = None, cpuinfo: str | None = None) -> bool:
    """True on an x86 CPU known to lack VNNI (int8 accuracy then depends on it); False when unknown."""
    if (machine or platform.machine()).lower() not in X86:
        return False
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text(errors="replace")
        except OSError:
            return False
    flags = cpu_flags(cpuinfo)
    return bool(flags) and not any(f in flags for f in VNNI_FLAGS)


INT8_WARNING = (
    "this CPU has no AVX-512 VNNI / AVX-VNNI: onnxruntime's int8 kernels saturate here, so int8 results drift "
    "from fp32 more than measured in docs/performance.md (cell agreement 82 % vs 94 %); prefer the fp32 model, "
    "or export int8 on this CPU (dadiff-export --quantize int8 uses reduce_range, 7-bit weights, for it)"
)


def int8_warning(meta: dict[str, str] | object) -> str | None:
    """The warning for an int8 model on a CPU whose int8 kernels saturate, unless it was quantised for one."""
    get = getattr(meta, "get", None)
    if get is None or get("precision") != "int8" or not int8_saturates():
        return None
    if '"reduce_range": true' in str(get("quantization", "")):
        return None
    return INT8_WARNING


def warn_int8(prog: str, tracker: object) -> None:
    """One warning line on stderr when `tracker` runs an int8 model where its int8 kernels saturate."""
    warning = int8_warning(getattr(getattr(tracker, "backend", None), "meta", None))
    if warning:
        print(f"{prog}: warning: {warning}", file=sys.stderr)
