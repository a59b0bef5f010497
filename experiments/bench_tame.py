"""TAME fitness evaluations per second, against the PPO fitness on the same device.

TAME needs no learning at evaluation time: `episodes` rollouts of random motor primitives per
body (32 x 100 control steps by default, 12,800 physics steps) and one classifier pass per
rollout. The PPO fitness at the standard budget (bench_fitness.py) trains a controller for
10,000 control steps and evaluates it for 1,000 (44,000 physics steps). For each batch size B
this prints TAME's evals/s and physics steps/s, and, where timed (--ppo-batches), the PPO
fitness's evals/s and how many times faster TAME is. The classifier's weights do not change the
cost, so a freshly initialised one is timed. Timings exclude compilation (a warm-up call
first) and are medians of --repeats calls.

  python -m experiments.bench_tame --batches 1 16 --ppo-batches 16            # CPU
  python -m experiments.bench_tame --batches 16 256 1024 --ppo-batches 1024   # GPU
"""

from __future__ import annotations

import argparse
import json

import jax

import evojax_morph as em
from evojax_morph import ppo, tame
from experiments.bench_fitness import STANDARD, median_time


def main():
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--space", default="bad_walker")
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 16])
    parser.add_argument("--ppo-batches", type=int, nargs="*", default=[16])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    jax.config.update("jax_default_matmul_precision", "highest")

    space = em.make_space(args.space)
    cfg = tame.TameConfig()
    t = tame.Tame(space, cfg)
    params = tame.init_classifier(space, cfg, jax.random.PRNGKey(0))
    fitness = jax.jit(jax.vmap(lambda k, m: t.fitness(params, k, m)[0]))
    walk = jax.jit(jax.vmap(space.random_morphology, (0, None)), static_argnums=1)
    physics_steps = cfg.episodes * cfg.episode_length * t.task.cfg.frame_skip
    ppo_physics = (
        ppo.env_steps_per_morphology(STANDARD.task, STANDARD.ppo) * STANDARD.task.frame_skip
    )
    rows = []
    for batch in args.batches:
        keys = jax.random.split(jax.random.PRNGKey(batch), batch)
        morphs = walk(keys, 3)
        t_tame = median_time(lambda: fitness(keys, morphs), args.repeats)  # noqa: B023
        row = {
            "space": args.space,
            "device": jax.devices()[0].device_kind,
            "batch": batch,
            "tame_evals_per_s": batch / t_tame,
            "tame_physics_steps_per_s": batch * physics_steps / t_tame,
            "tame_physics_steps_per_eval": physics_steps,
            "ppo_physics_steps_per_eval": ppo_physics,
        }
        if batch in args.ppo_batches:
            evaluate = lambda: em.evaluate(space, morphs, keys, STANDARD).fitness  # noqa: B023
            t_ppo = median_time(evaluate, 1)
            row.update(ppo_evals_per_s=batch / t_ppo, tame_speedup=t_ppo / t_tame)
        rows.append(row)
        print(json.dumps(row), flush=True)

    print(
        f"\n{'B':>5} {'TAME evals/s':>13} {'TAME phys/s':>12} {'PPO evals/s':>12} {'speed-up':>9}"
    )
    for r in rows:
        ppo_rate = (
            f"{r['ppo_evals_per_s']:>12.3g} {r['tame_speedup']:>8.1f}x"
            if "ppo_evals_per_s" in r
            else ""
        )
        print(
            f"{r['batch']:>5} {r['tame_evals_per_s']:>13.3g} "
            f"{r['tame_physics_steps_per_s']:>12.3g} {ppo_rate}"
        )


if __name__ == "__main__":
    main()
