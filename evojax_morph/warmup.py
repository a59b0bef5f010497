"""A run's later programs compiled on a second thread while its first one runs.

After m0's evaluation a run calls four more compiled programs: a chunk of steps, the greedy
rollout, the confirm stage's fitness call and best.gif's replay. Before its first call each one
costs the host seconds: tracing and lowering it, then compiling it (or, with a warm persistent
cache, loading it). Meanwhile m0's evaluation, a step's worth of work, keeps the device busy and
the host idle. The run lowers the later programs before m0's evaluation starts, for the shapes
and placements their calls will have, and `Warmup` compiles them on one thread while it runs, so
that each call finds its program in JAX's caches (tests/test_cli.py checks that the main thread
compiles none of them). They are the programs the calls would compile themselves: no result
changes. `EVOJAX_MORPH_WARMUP=0` turns it off.

Why lower first, on the main thread: lowering a program that steps on MuJoCo Warp copies
arrays to the device (MJX's `put_model` and `make_data` for Warp), and a Warp call of the
running program captures a CUDA graph of XLA's stream whenever it meets new buffer addresses.
Device work from another thread during a capture breaks it (`Warp CUDA error 904: capturing
stream has unjoined work`, then a segmentation fault: `experiments/warp_thread_race.py`).
Lowered on the second thread, 2 of 4 GPU runs (both cold) died of a segmentation fault after
their steps; compiling alone there crashed none of 3 (H100, 2026-11-25; docs/benchmarks.md,
"Lowering on the second thread, tried again").
"""

from __future__ import annotations

import os
import sys
import threading
import warnings
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor

THREAD = "evojax_morph-warmup"  # the compiling thread's name prefix
# How long a thread may hold the GIL while another waits, while the warmup runs: MuJoCo Warp's
# JAX call takes the GIL once a control step, so a thread in Python may delay the device by as
# much.
SWITCH_INTERVAL = 1e-4


def enabled() -> bool:
    return os.environ.get("EVOJAX_MORPH_WARMUP", "1") != "0"


class Warmup:
    """Jobs run ahead, by name: `compile(name, lower)` on the compiling thread, in the order
    given; `run(name, fn)` on a thread of its own (a subprocess probe, say); `wait(name)` before
    the call that needs the job's result. A job that fails only warns: its call then compiles
    the program itself, as without the warmup."""

    def __init__(self, on: bool | None = None):
        self.on = enabled() if on is None else on
        self._jobs: dict[str, Future] = {}
        self._pool = ThreadPoolExecutor(1, thread_name_prefix=THREAD) if self.on else None
        self._interval = sys.getswitchinterval()
        if self.on:
            sys.setswitchinterval(SWITCH_INTERVAL)

    def compile(self, name: str, lower: Callable) -> None:
        """Lowers now, on this thread, what `lower()` returns (a `jax.stages.Lowered` or a list
        of them), and compiles it ahead."""
        if self.on:
            try:
                lowered = lower()
            except Exception as e:  # warned of at `wait`, like a failed compile
                self._jobs[name] = Future()
                self._jobs[name].set_exception(e)
                return
            self._jobs[name] = self._pool.submit(_compile, lowered)

    def run(self, name: str, fn: Callable) -> None:
        """Calls `fn()` ahead, on a thread of its own."""
        if self.on:
            job = self._jobs[name] = Future()
            threading.Thread(target=_fill, args=(job, fn), name=f"{THREAD}-{name}",
                             daemon=True).start()

    def wait(self, name: str) -> None:
        """Returns once job `name` is done (at once if there is none)."""
        job = self._jobs.pop(name, None)
        if job is None:
            return
        try:
            job.result()
        except Exception as e:  # the call compiles it instead
            warnings.warn(f"warmup: {name} failed ahead ({type(e).__name__}: {e}); its call "
                          "does the work", RuntimeWarning, stacklevel=2)

    def close(self, wait: bool = True) -> None:
        """Waits for every job (or, `wait` False, drops those not begun); then the thread is
        gone and the GIL's interval as it was."""
        if wait:
            for name in list(self._jobs):
                self.wait(name)
        if self.on:
            self._pool.shutdown(wait=wait, cancel_futures=True)
            sys.setswitchinterval(self._interval)
            self.on = False


def _compile(lowered) -> None:
    for one in lowered if isinstance(lowered, list) else [lowered]:
        one.compile()


def _fill(job: Future, fn: Callable) -> None:
    try:
        job.set_result(fn())
    except Exception as e:
        job.set_exception(e)
