"""Reproducible fitness on a GPU: XLA's deterministic GPU ops, asked for before JAX starts.

MJX's step sums forces with scatter-adds (18 in one step of these bodies), which XLA runs on a
GPU with atomic additions: their order, and so the rounding, changes from call to call, and a
walking gait turns a rounding difference into another controller. Measured on one H200 (jax
0.11.2, docs/benchmarks.md): two calls of one compiled fitness program with the same keys gave
different fitness for all 256 of 256 bodies (by up to 176); with `--xla_gpu_deterministic_ops`
none differed, within a process or across processes, at 1.38x the time per call. The CPU is
deterministic without it. The `run` command switches it on unless given --fast-gpu.
"""

from __future__ import annotations

import os

from jax._src import xla_bridge

FLAG = "--xla_gpu_deterministic_ops=true"


def deterministic_gpu() -> bool:
    """Asks XLA for deterministic GPU ops in this process (XLA_FLAGS), before any backend starts.

    Returns:
      True if the flag is in force; False if a JAX backend had already started without it (XLA
      reads its flags once), in which case nothing changes: call this first, or set
      XLA_FLAGS=--xla_gpu_deterministic_ops=true in the environment.
    """
    flags = os.environ.get("XLA_FLAGS", "")
    if FLAG in flags.split():
        return True
    if xla_bridge.backends_are_initialized():
        return False
    os.environ["XLA_FLAGS"] = f"{flags} {FLAG}".strip()
    return True
