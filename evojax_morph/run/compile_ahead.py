"""A run's later programs lowered and compiled on a second thread while its first one runs.

After m0's evaluation a run calls four more compiled programs: a chunk of steps, the greedy
walk, the confirm stage's fitness call (with the greedy trajectory's bodies; where it confirms
nothing, they get a call of their own) and best.gif's replay. Before its first call each one
costs the host seconds: tracing and lowering it, then compiling it (or, with a warm persistent
cache, loading it). Meanwhile m0's evaluation, a step's worth of work, keeps the device busy and
the host mostly idle. The run queues the later programs before m0's evaluation, for the shapes
and placements their calls will have, and `Warmup` lowers them on one thread once m0's program
is lowered (`start`), and compiles them there too unless MuJoCo Warp runs on a GPU, so that each
call finds its program in JAX's caches (tests/test_cli.py checks by thread). They are the
programs the calls would compile themselves: no result changes. `EVOJAX_MORPH_WARMUP=0` turns
it off.

Why not compile on the thread with Warp on a GPU: a Warp call captures a CUDA graph of XLA's
stream, and a compile that misses the persistent cache autotunes on that stream; one during the
other breaks the capture (`Warp CUDA error 901`). So `wait` compiles such a program on the
calling thread, where no Warp call can be running; lowering launches no kernel and stays on the
thread. The MJX functions it runs that set Warp's default device for the whole process hold
Warp's call lock (`evojax_morph.physics.warp.callback_lock`). With Warp on several GPUs a run's
warmup is off (`Warmup.for_engine`): runs there hung. What was measured, and what was tried
and reverted: docs/benchmarks.md, "Compiling on the second thread breaks Warp's graph capture"
and "The Warp fitness across GPUs".
"""

from __future__ import annotations

import os
import sys
import threading
import time
import warnings
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import NamedTuple

import jax

THREAD = "evojax_morph-warmup"  # the compiling thread's name prefix
# How long a thread may hold the GIL while another waits, while the warmup runs: MuJoCo Warp's
# JAX call takes the GIL once a control step, so a thread in Python may delay the device by as
# much.
SWITCH_INTERVAL = 1e-4


class Job(NamedTuple):
    """A job a stage offers to do ahead: `fn` lowers a program of its, compiled on the
    compiling thread in the order given; or, `own_thread`, a probe on a thread of its own."""

    name: str
    fn: Callable
    own_thread: bool = False


def enabled() -> bool:
    return os.environ.get("EVOJAX_MORPH_WARMUP", "1") != "0"


class Warmup:
    """Jobs run ahead, by name: `compile(name, lower)` on the compiling thread, in the order
    given, once `start` is called; `run(name, fn)` on a thread of its own (a subprocess probe,
    say); `wait(name)` before the call that needs the job's result. `compiles` False: the
    thread only lowers, and `wait` compiles. A job that fails only warns: its call then
    compiles the program itself, as without the warmup. As a context manager it closes on
    leaving, dropping the jobs not begun (a run that failed)."""

    def __init__(self, on: bool | None = None, compiles: bool = True,
                 waited: dict | None = None):
        self.on = enabled() if on is None else on
        self.compiles = compiles
        self._jobs: dict[str, Future] = {}
        # job name: seconds `wait` took (timing.json); `waited` given: filled in
        self.waited: dict[str, float] = {} if waited is None else waited
        self._lowering: set[str] = set()  # the names of `compile`'s jobs
        self._go = threading.Event()  # `start`
        self._dropped = False  # `close(wait=False)`: the jobs not begun return at once
        self._pool = ThreadPoolExecutor(1, thread_name_prefix=THREAD) if self.on else None
        self._interval = sys.getswitchinterval()
        if self.on:
            sys.setswitchinterval(SWITCH_INTERVAL)

    @classmethod
    def for_engine(cls, engine, waited: dict | None = None) -> Warmup:
        """The warmup of a run whose fitness steps on `engine` (`engines.Engine`): it compiles
        on its thread, but lowers only where the engine captures graphs on a GPU (MuJoCo Warp),
        which a compile's autotuning breaks, and there on several GPUs it is off."""
        graphs = engine.graph_capture and jax.default_backend() == "gpu"
        return cls(on=False if graphs and jax.device_count() > 1 else None,
                   compiles=not graphs, waited=waited)

    def __enter__(self) -> Warmup:
        return self

    def __exit__(self, *error) -> None:
        self.close(wait=False)

    def compile(self, name: str, lower: Callable) -> None:
        """Calls `lower()` on the compiling thread once `start` is called, and compiles what it
        returns (a `jax.stages.Lowered` or a list of them) there, or at `wait`."""
        if self.on:
            self._jobs[name] = self._pool.submit(self._lower, lower)
            self._lowering.add(name)

    def collect(self, jobs: list[Job]) -> None:
        """Takes the jobs the stages offer, in their order: it only collects them."""
        for job in jobs:
            (self.run if job.own_thread else self.compile)(job.name, job.fn)

    def start(self) -> None:
        """Lets the compiling thread begin (`wait` and `close` do too)."""
        self._go.set()

    def _lower(self, lower: Callable) -> list:
        self._go.wait()
        if self._dropped:
            return []
        lowered = lower()
        lowered = lowered if isinstance(lowered, list) else [lowered]
        if self.compiles:
            for one in lowered:
                one.compile()
        return lowered

    def run(self, name: str, fn: Callable) -> None:
        """Calls `fn()` ahead, on a thread of its own."""
        if self.on:
            job = self._jobs[name] = Future()
            threading.Thread(target=_fill, args=(job, fn), name=f"{THREAD}-{name}",
                             daemon=True).start()

    def wait(self, name: str) -> None:
        """Returns once job `name` is done (at once if there is none)."""
        self.start()
        job = self._jobs.pop(name, None)
        if job is None:
            return
        start = time.perf_counter()
        try:
            result = job.result()
            if name in self._lowering and not self.compiles:
                for one in result:
                    one.compile()
        except Exception as e:  # the call compiles it instead
            warnings.warn(f"warmup: {name} failed ahead ({type(e).__name__}: {e}); its call "
                          "does the work", RuntimeWarning, stacklevel=2)
        self.waited[name] = round(time.perf_counter() - start, 2)

    def close(self, wait: bool = True) -> None:
        """Waits for every job (or, `wait` False, drops those not begun); then the thread is
        gone and the GIL's interval as it was."""
        self._dropped = not wait
        self.start()
        if wait:
            for name in list(self._jobs):
                self.wait(name)
        if self.on:
            self._pool.shutdown(wait=wait, cancel_futures=True)
            sys.setswitchinterval(self._interval)
            self.on = False


def _fill(job: Future, fn: Callable) -> None:
    try:
        job.set_result(fn())
    except Exception as e:
        job.set_exception(e)
