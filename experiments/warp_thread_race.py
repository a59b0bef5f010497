"""Can a second thread work while a MuJoCo Warp program runs? (issue 32, item 3)

A run would start faster if a second thread lowered and compiled its later programs while m0's
evaluation runs (`evojax_morph/warmup.py`). This script evaluates a batch of Bad Walker bodies
on Warp twice alone, then --calls times while a second thread does, in a loop, what MODE says,
and appends a JSON line to OUT/race.jsonl: the seconds of a call alone and with the thread at
work, how many rounds the thread made, whether the fitness stayed finite. MODE:

  put          `warp.put_model` and `warp.make_worlds`, as a trace of a Warp program does (both
               copy arrays to the device; since 2026-11-26 they hold Warp's call lock while
               in MJX, the `put_locked` mode of docs/benchmarks.md);
  lower        lowers the evaluation of a new batch size each round (`fitness.lower_evaluate`),
               as a run's warmup thread does;
  compile      compiles such programs, lowered beforehand on the main thread, with the
               persistent cache off, as a warmup thread would in a cold run (XLA autotunes on
               the device);
  compile_locked   the same, holding the lock Warp's JAX callbacks run under (on an H100 it
               deadlocks: the callback waits for the lock, the compile for the device).

On a GPU the process may die instead (no line; see its output): a Warp call captures a CUDA graph
of XLA's stream the first time it meets new buffer addresses, and device work from another
thread during that capture breaks it (docs/benchmarks.md, "Lowering on the second thread, tried
again" and "Compiling on the second thread breaks Warp's graph capture").

  python -m experiments.warp_thread_race put OUT       # GPU, 256 bodies, 10,000 PPO steps
  python -m experiments.warp_thread_race compile OUT --calls 10
  python -m experiments.warp_thread_race lower OUT --batch 4 --train-steps 640   # CPU smoke
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import threading
import time


def main(mode: str, out: str, batch: int, train_steps: int, calls: int) -> None:
    import jax
    import numpy as np

    import evojax_morph as em
    from evojax_morph import warp as ew
    from evojax_morph.fitness import lower_evaluate

    em.persistent_cache()
    space = em.make_space("bad_walker")
    keys = jax.random.split(jax.random.PRNGKey(0), batch)
    morphs = jax.jit(jax.vmap(space.random_morphology, (0, None)), static_argnums=1)(keys, 3)
    cfg = em.FitnessConfig(ppo=em.standard_ppo(train_steps), physics="warp")
    run = lambda: np.asarray(em.evaluate(space, morphs, keys, cfg).fitness)  # noqa: E731
    t = time.perf_counter()
    run()  # compiles
    first = time.perf_counter() - t
    t = time.perf_counter()
    alone = run()
    alone_s = time.perf_counter() - t

    held = contextlib.nullcontext()
    if mode == "compile_locked":
        held = ew.callback_lock()
    sizes = iter(range(batch + 1, batch + 1000))  # batch sizes not compiled before
    if mode.startswith("compile"):  # lowered now, compiled by the thread
        lowered = [one for _ in range(8) for one in lower_evaluate(space, next(sizes), cfg)]
        jax.config.update("jax_enable_compilation_cache", False)

    def one_round(i: int) -> bool:  # False: nothing left to do
        if mode == "put":
            ew.put_model(space.template)
            ew.make_worlds(space, 8)
        elif mode == "lower":
            lower_evaluate(space, next(sizes), cfg)
        elif i < len(lowered):
            with held:
                lowered[i].compile()
        else:
            return False
        return True

    sys.setswitchinterval(1e-4)  # as the run's warmup does
    stop, rounds = threading.Event(), [0]

    def work():
        while not stop.is_set() and one_round(rounds[0]):
            rounds[0] += 1
            time.sleep(1e-3)  # lets a callback waiting on Warp's call lock take it

    thread = threading.Thread(target=work, daemon=True)
    thread.start()
    t = time.perf_counter()
    busy = [run() for _ in range(calls)]
    busy_s = (time.perf_counter() - t) / calls
    stop.set()
    thread.join()
    row = dict(mode=mode, batch=batch, train_steps=train_steps, calls=calls,
               first_s=round(first, 2), alone_s=round(alone_s, 3), busy_s=round(busy_s, 3),
               rounds=rounds[0], finite=bool(all(np.isfinite(f).all() for f in busy)),
               mean_alone=float(alone.mean()), mean_busy=[float(f.mean()) for f in busy],
               device=jax.devices()[0].device_kind)
    print(json.dumps(row), flush=True)
    os.makedirs(out, exist_ok=True)
    with open(os.path.join(out, "race.jsonl"), "a") as f:
        f.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("mode",
                        choices=["put", "lower", "compile", "compile_locked"])
    parser.add_argument("out")
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--train-steps", type=int, default=10_000)
    parser.add_argument("--calls", type=int, default=3, help="evaluations while the thread works")
    a = parser.parse_args()
    main(a.mode, a.out, a.batch, a.train_steps, a.calls)
