"""Fitness evaluations per second of the batched PPO fitness, and what batching buys.

Standard budget (per morphology): 10,000 training control steps (16 envs x 20-step unrolls x
31 updates = 9,920 steps) plus 4 deterministic evaluation episodes of 250 steps; a control step
is 4 physics steps of 5 ms. For each batch size B this prints:
  evals/s        B / (time of one `em.evaluate` call on B random Bad Walker bodies)
  train steps/s  PPO control steps per second, training and evaluation, over the batch
  ppo/physics    physics steps per second inside PPO over the raw rate of the same template
                 stepping the same B x 16 worlds with no learning (the physics limit)
  one-at-a-time  the same code evaluating the bodies with B = 1, one call each (timed on up to
                 --single bodies and scaled to B); `batching gain` is its time over the batch's
Timings exclude compilation (a warm-up call first) and are medians of --repeats calls.

  python -m experiments.bench_fitness --batches 1 16                 # CPU
  python -m experiments.bench_fitness --batches 1 16 256 1024        # GPU
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import numpy as np

import evojax_morph as em
from evojax_morph import ppo
from experiments import bench_physics

STANDARD = em.FitnessConfig(ppo=em.standard_ppo(10_000))


def median_time(fn, repeats: int) -> float:
    jax.block_until_ready(fn())  # compile and warm up
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def main():
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--space", default="bad_walker")
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 16])
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--single", type=int, default=8, help="bodies timed one at a time")
    args = parser.parse_args()
    jax.config.update("jax_default_matmul_precision", "highest")

    space = em.make_space(args.space)
    cfg = STANDARD
    steps = ppo.env_steps_per_morphology(cfg.task, cfg.ppo)
    frame_skip = cfg.task.frame_skip
    walk = jax.jit(jax.vmap(space.random_morphology, (0, None)), static_argnums=1)
    rows = []
    for batch in args.batches:
        keys = jax.random.split(jax.random.PRNGKey(batch), batch)
        morphs = walk(keys, 3)
        evaluate = lambda: em.evaluate(space, morphs, keys, cfg).fitness  # noqa: B023  (timed now)
        t_batch = median_time(evaluate, args.repeats)

        single = min(batch, args.single)
        pick = lambda i: jax.tree.map(lambda x: x[i : i + 1], morphs)  # noqa: B023
        em.evaluate(space, pick(0), keys[:1], cfg).fitness.block_until_ready()  # compile B = 1
        start = time.perf_counter()
        for i in range(single):
            em.evaluate(space, pick(i), keys[i : i + 1], cfg).fitness.block_until_ready()
        t_single = (time.perf_counter() - start) / single * batch

        # Raw physics at the same worlds: B bodies x num_envs worlds, no learning.
        models = jax.jit(jax.vmap(space.mjx_model))(morphs)
        data = jax.vmap(lambda m: bench_physics.broadcast_data(m, 1, cfg.ppo.num_envs)[0])(models)
        rollout = bench_physics.make_rollout(100, batched_models=True)
        t_phys = median_time(lambda: rollout(models, data), args.repeats)  # noqa: B023
        physics_rate = batch * cfg.ppo.num_envs * 100 / t_phys

        train_rate = batch * steps / t_batch
        rows.append(
            {
                "space": args.space,
                "device": jax.devices()[0].device_kind,
                "batch": batch,
                "env_steps_per_morphology": steps,
                "evals_per_s": batch / t_batch,
                "train_steps_per_s": train_rate,
                "physics_steps_per_s_raw": physics_rate,
                "ppo_over_physics": train_rate * frame_skip / physics_rate,
                "one_at_a_time_s": t_single,
                "batch_s": t_batch,
                "batching_gain": t_single / t_batch,
            }
        )
        print(json.dumps(rows[-1]), flush=True)

    print(
        f"\n{'B':>5} {'evals/s':>9} {'steps/s':>10} {'raw phys/s':>11} {'ppo/phys':>9} "
        f"{'1-at-a-time s':>14} {'batch s':>8} {'gain':>6}"
    )
    for r in rows:
        print(
            f"{r['batch']:>5} {r['evals_per_s']:>9.3g} {r['train_steps_per_s']:>10.3g} "
            f"{r['physics_steps_per_s_raw']:>11.3g} {r['ppo_over_physics']:>9.0%} "
            f"{r['one_at_a_time_s']:>14.3g} {r['batch_s']:>8.3g} {r['batching_gain']:>6.1f}"
        )


if __name__ == "__main__":
    main()
