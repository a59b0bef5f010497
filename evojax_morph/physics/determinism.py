"""XLA flags this library asks for before JAX starts: reproducible GPU runs, CPU runs that finish.

Reproducible fitness on a GPU (`deterministic_gpu`). MJX's step sums forces with scatter-adds (18
in one step of these bodies), which XLA runs on a GPU with atomic additions: their order, and so
the rounding, changes from call to call, and a walking gait turns a rounding difference into
another controller. Measured on one H200 (jax 0.11.2, docs/benchmarks.md): two calls of one
compiled fitness program with the same keys gave different fitness for all 256 of 256 bodies (by
up to 176); with `--xla_gpu_deterministic_ops` none differed, within a process or across
processes, at 1.38x the time per call. The CPU is deterministic without it. The `run` command
switches it on unless given --fast-gpu.

CPU runs that finish (`cpu_scheduler_workaround`, asked for when evojax_morph is imported). With
jaxlib 0.10.2, XLA's CPU runtime can deadlock while running a large vmapped MJX program: every
thread waits on a condition variable and the call never returns. Reproduced here with the
Constructor's 82-geom template: 300 steps of 48 bodies run, 50 bodies hang, every time, while
either body alone runs. `--xla_cpu_enable_concurrency_optimized_scheduler=false` (XLA's older
thunk scheduler) runs it, and no slower.

GPU runs whose small sums across devices finish (`all_reduce_workaround`, asked for when
evojax_morph is imported). With jax 0.12.0 on 2 H200s, XLA's one-shot all-reduce kernel failed in
`em.evaluate` of 3 bodies split over 2 GPUs (tests/test_warp.py::test_ppo_fitness_on_warp):
"NCCL operation ncclGetPeerDevicePointer(...) failed: unhandled system error". With
`--xla_gpu_unsupported_use_all_reduce_one_shot_kernel=false` (NCCL's all-reduce instead) the test
passed (docs/benchmarks.md, 2026-11-28). The flag changes only how XLA sums small arrays across
GPUs; every jaxlib this library supports (0.10 to 0.12) knows it, and a CPU run ignores it.
"""

from __future__ import annotations

import os

from jax._src import xla_bridge

FLAG = "--xla_gpu_deterministic_ops=true"
CPU_FLAG = "--xla_cpu_enable_concurrency_optimized_scheduler=false"
ALL_REDUCE_FLAG = "--xla_gpu_unsupported_use_all_reduce_one_shot_kernel=false"
CACHE = "~/.cache/evojax_morph/jax"  # persistent_cache's default


def _ask(flag: str) -> bool:
    """Adds `flag` to XLA_FLAGS unless there already or too late; True if it is in force."""
    flags = os.environ.get("XLA_FLAGS", "")
    name = flag.split("=")[0]
    if any(f.split("=")[0] == name for f in flags.split()):
        return flag in flags.split()
    if xla_bridge.backends_are_initialized():
        return False
    os.environ["XLA_FLAGS"] = f"{flags} {flag}".strip()
    return True


def deterministic_gpu() -> bool:
    """Asks XLA for deterministic GPU ops in this process (XLA_FLAGS), before any backend starts.

    Returns:
      True if the flag is in force; False if a JAX backend had already started without it (XLA
      reads its flags once), in which case nothing changes: call this first, or set
      XLA_FLAGS=--xla_gpu_deterministic_ops=true in the environment.
    """
    return _ask(FLAG)


def cpu_scheduler_workaround() -> bool:
    """Asks XLA's CPU runtime for the scheduler that does not deadlock (see the module docstring).

    A no-op if XLA_FLAGS already sets the scheduler either way, or if a backend has started.
    """
    return _ask(CPU_FLAG)


def all_reduce_workaround() -> bool:
    """Asks XLA for NCCL's all-reduce in place of its one-shot kernel (see the module docstring).

    A no-op if XLA_FLAGS already sets that kernel either way, or if a backend has started.
    """
    return _ask(ALL_REDUCE_FLAG)


def full_precision() -> None:
    """Full float32 matrix products in every program this process traces from now on
    (`jax_default_matmul_precision` "highest"): the one place a command asks for them.

    On a GPU XLA's default multiplies float32 matrices in TF32, which perturbs physics and RL
    more than they tolerate. The PPO fitness asks for full precision itself (`ppo.make_train`
    traces its `train` under `jax.default_matmul_precision("highest")`, wherever it is called),
    so this matters for what that does not reach: the agents' networks, the TAME classifier and
    its rollouts, and physics stepped outside a PPO fitness (`experiments.bench_physics`). The
    `run` command and the experiments call it before they trace anything, so that their programs
    are the same ones. On a CPU float32 products are full precision either way.
    """
    import jax

    jax.config.update("jax_default_matmul_precision", "highest")


def persistent_cache(path: str | None = None) -> str:
    """Keeps this process's compiled programs on disk (JAX's persistent compilation cache), so a
    later process compiling the same program loads it instead: the tests and the run command.

    Args:
      path: the directory; None for EVOJAX_MORPH_JAX_CACHE, else ~/.cache/evojax_morph/jax.

    Returns:
      The directory. MuJoCo Warp keeps its compiled kernels apart, in ~/.cache/warp.
    """
    import jax

    path = path or os.environ.get("EVOJAX_MORPH_JAX_CACHE") or os.path.expanduser(CACHE)
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    return path
