"""Training that repeats bit for bit on any x86-64 CPU, and the record of the CPU a run used.

The same seed on the same machine gives the same run. Across CPUs it need not: PyTorch picks its kernels by
the CPU's instruction set (ATen's CPU capability) and MKL picks its code path by CPU (AVX-512 on some
Intel CPUs, AVX2 on this AMD EPYC), and the kernels round differently. Measured here: a short TD3 run gives
different actions with ``ATEN_CPU_CAPABILITY=default`` than with ``avx2`` or ``avx512``, and different again
with ``MKL_CBWR=COMPATIBLE``. With both fixed (:data:`PORTABLE_ENV`) the run is the same whatever
instructions MKL is allowed (``MKL_ENABLE_INSTRUCTIONS=SSE4_2``, ``AVX2``, unrestricted), at about 1.6x
the training time. Both are read when torch loads, so ``--portable`` starts the command again in a fresh
process with them set.
"""

from __future__ import annotations

import os
import platform
import sys
from collections.abc import Sequence
from typing import Any

from embedrl.train.errors import UsageError

PORTABLE_ENV = {"MKL_CBWR": "COMPATIBLE", "ATEN_CPU_CAPABILITY": "default"}
"""MKL's CPU-independent code path and PyTorch's generic kernels."""


def in_effect() -> bool:
    """Whether this process runs with :data:`PORTABLE_ENV`."""
    return all(os.environ.get(k) == v for k, v in PORTABLE_ENV.items())


def restart_portable(argv: Sequence[str], as_command: bool) -> None:
    """Run ``embedrl ARGV`` again in this process's place with :data:`PORTABLE_ENV` (no return), unless it
    is in effect already. Only a process that is the command itself restarts (not a caller of ``main``)."""
    if in_effect():
        return
    if not as_command:
        raise UsageError("--portable starts the command again in a fresh process: run it as a command")
    sys.stdout.flush()
    sys.stderr.flush()
    os.execve(sys.executable, [sys.executable, "-m", "embedrl.cli", *argv], {**os.environ, **PORTABLE_ENV})


def machine() -> dict[str, Any]:
    """The CPU and the numerical code paths a run used (recorded in its config.json)."""
    import torch

    model = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            model = next(
                (line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), model
            )
    except OSError:
        pass
    return {
        "cpu": model,
        "cpu_count": os.cpu_count(),
        "torch_cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "torch_threads": torch.get_num_threads(),
        "portable": in_effect(),
        **{k: os.environ.get(k) for k in PORTABLE_ENV},
    }
