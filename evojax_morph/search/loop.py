"""The host's loop of every search: a run's steps (`run.stages.Evolve`) and a study's
(`study.run_study`) alike, in calls of at most `chunk` steps, each call's results brought to
the host. What a caller does between calls (a body log, a checkpoint, a save, a progress line)
is its own."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from typing import Any, NamedTuple

from evojax_morph.sharding import to_host


class Chunk(NamedTuple):
    """One call of the loop: its steps, and what it left."""

    step: int  # steps done, this call's included
    n: int  # this call's steps
    state: Any  # the search's state after them (on its devices)
    metrics: dict  # the call's metrics (host-side), stacked over its steps
    seconds: float  # the call until its metrics reached the host
    dispatch: float  # the call until it returned (its program then still running)


def chunks(program: Callable, state, step: int, steps: int, chunk: int,
           deadline: float | None = None) -> Iterator[Chunk]:
    """The calls from `step` steps done to `steps`, each of min(chunk, steps left).

    program(n) -> call: the function stepping a state n steps, call(state) -> (state, metrics);
    asked before each call's clock starts (where a caller compiles, or waits for a compile).
    deadline: past it (time.time()), no further call begins; the caller sees the steps done.
    """
    while step < steps:
        if deadline is not None and time.time() > deadline:
            return
        n = min(chunk, steps - step)
        call = program(n)
        start = time.perf_counter()
        state, metrics = call(state)
        dispatch = time.perf_counter() - start
        metrics = to_host(metrics)  # waits for the call's program
        step += n
        yield Chunk(step, n, state, metrics, time.perf_counter() - start, dispatch)
