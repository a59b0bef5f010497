"""Fitness evaluations per second of the batched PPO fitness, and what batching buys.

Standard budget (per morphology): 10,000 training control steps (16 envs x 20-step unrolls x
31 updates = 9,920 steps) plus 4 deterministic evaluation episodes of 250 steps; a control step
is 4 physics steps of 5 ms. For each batch size B this prints:
  evals/s        B / (time of one `em.evaluate` call on B random Bad Walker bodies)
  train steps/s  PPO control steps per second, training and evaluation, over the batch
  ppo/physics    physics steps per second inside PPO over the raw rate of the same engine
                 stepping the same B x 16 worlds with no learning (the physics limit)
  one-at-a-time  the same code evaluating the bodies with B = 1, one call each (timed on up to
                 --single bodies and scaled to B); `batching gain` is its time over the batch's;
                 both null (printed "-") with --single 0, which skips them and their B = 1 compile
  repeat diff    the largest fitness difference between the repeated calls (same program, same
                 keys), and how many of the B bodies differ: 0 when the engine and XLA are
                 deterministic
Timings exclude compilation (a warm-up call first) and are medians of --repeats calls.
--update-epochs sets PPO's epochs per update: timing 1 against the standard 8 (and
--train-steps 0, the evaluation episodes alone) splits a call into learner and rollouts.
Its device traces (`--trace DIR`) and its count of Warp's graph captures answered where a
Warp call's time goes (docs/benchmarks.md) and are retired (at git 88d6bf1).
--physics names the engine (`physics.engines`); --deterministic asks XLA for deterministic
GPU ops first, as the run command does on the JAX engine unless --fast-gpu (on Warp it leaves
them off: they buy no reproducibility there); --warp-deterministic MuJoCo Warp's
`Option.deterministic`, under EVOJAX_MORPH_MUJOCO_WARP=package (`evojax_morph.physics.templates`).

  python -m experiments.bench_fitness --batches 1 16                 # CPU
  python -m experiments.bench_fitness --batches 1 256 1024 4096 --physics warp
  python -m experiments.bench_fitness --space constructor --batches 256 --physics warp \
      --single 0 --mutations 8 --classes   # one template against size classes
  python -m experiments.bench_fitness --space constructor --mutations 8 --classes \
      --agreement 16 --seeds 8 --train-steps 2000   # ...and in distribution (CPU)
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import time

import jax
import jax.numpy as jnp
import numpy as np
import scipy.stats

import evojax_morph as em
from evojax_morph import ppo
from evojax_morph.physics import engines
from evojax_morph.physics import warp as ew
from evojax_morph.physics.determinism import full_precision
from evojax_morph.physics.templates import MUJOCO_WARP
from evojax_morph.search.confirm import t_interval

STANDARD = em.FitnessConfig(ppo=em.standard_ppo(10_000))


def timed(fn, repeats: int) -> tuple[float, float, int]:
    """(median seconds of `repeats` calls after a warm-up, largest difference between the
    outputs of all calls, how many outputs differ in any call)."""
    first = np.asarray(jax.block_until_ready(fn()))  # compile and warm up
    times, diff, differ = [], 0.0, np.zeros(first.shape, bool)
    for _ in range(repeats):
        start = time.perf_counter()
        out = np.asarray(jax.block_until_ready(fn()))
        times.append(time.perf_counter() - start)
        diff = max(diff, float(np.nanmax(np.abs(out - first))) if out.size else 0.0)
        differ |= out != first
    return float(np.median(times)), diff, int(differ.sum())


def median_time(fn, repeats: int) -> float:
    return timed(fn, repeats)[0]


def one_at_a_time(space, morphs, keys, cfg, single: int) -> float | None:
    """Seconds to evaluate all B bodies with B = 1 calls, timed on the first `single` (after a
    compile) and scaled to B; None if `single` is 0."""
    if single == 0:
        return None
    pick = lambda i: jax.tree.map(lambda x: x[i : i + 1], morphs)
    em.evaluate(space, pick(0), keys[:1], cfg).fitness.block_until_ready()  # compile B = 1
    start = time.perf_counter()
    for i in range(single):
        em.evaluate(space, pick(i), keys[i : i + 1], cfg).fitness.block_until_ready()
    return (time.perf_counter() - start) / single * morphs.active.shape[0]


def fmt(value, spec: str) -> str:
    """`value` formatted by `spec` ('>14.3g'), or "-" aligned to its width if None."""
    return format("-", spec.split(".")[0]) if value is None else format(value, spec)


def make_raw_physics(engine: engines.Engine, space, steps: int):
    """jit(fn(models (B,), worlds_per_body) -> qpos): `steps` physics steps of every world of the
    engine's flat batch with sinusoidal controls, no learning."""

    def rollout(models, worlds_per_body):
        worlds = engine.prepare(space, models, worlds_per_body)
        n = models.body_mass.shape[0] * worlds_per_body
        data = engine.forward(worlds, engine.make_data(worlds, space, n))
        phase = jnp.arange(n)[:, None] + jnp.arange(space.template.nu)

        def body(data, t):
            ctrl = jnp.sin(8.0 * t * space.template.opt.timestep + phase)
            # one physics step a call (the fitness makes one call a control step on Warp)
            return engine.step(worlds, data.replace(ctrl=ctrl), 1), None

        return jax.lax.scan(body, data, jnp.arange(steps))[0].qpos

    return jax.jit(rollout, static_argnums=1)


def agreement(space, ways: dict, bodies: int, seeds: int, mutations: int) -> dict:
    """`bodies` random bodies of `mutations` mutations, each trained from scratch with `seeds`
    keys in each of two `ways` (name: (FitnessConfig, mesh)), the same keys, so only the way
    differs (a trained fitness is not fixed by its key across batches, `em.evaluate`: compare
    the distributions). The means; the mean over bodies of their differences (the second way
    minus the first) with its 95% interval; the Spearman of the body means, beside the first
    way's split half (its even keys' body means against its odd keys'), what noise allows."""
    keys = jax.random.split(jax.random.PRNGKey(7), bodies)
    morphs = jax.jit(jax.vmap(space.random_morphology, (0, None)), static_argnums=1)(keys,
                                                                                     mutations)
    morphs = jax.tree.map(lambda x: jnp.repeat(x, seeds, 0), morphs)  # body i: rows i*S..
    keys = jax.random.split(jax.random.PRNGKey(8), bodies * seeds)
    (a, fa), (b, fb) = [(name, np.asarray(em.evaluate(space, morphs, keys, cfg, mesh=mesh)
                                          .fitness).reshape(bodies, seeds))
                        for name, (cfg, mesh) in ways.items()]
    diff = fb.mean(1) - fa.mean(1)  # per body, the paired design's differences
    rho = lambda x, y: float(scipy.stats.spearmanr(x, y).statistic)  # noqa: E731
    return {"space": space.name, "device": jax.devices()[0].device_kind, "bodies": bodies,
            "seeds": seeds, "mutations": mutations, f"mean_{a}": float(fa.mean()),
            f"mean_{b}": float(fb.mean()), "difference": float(diff.mean()),
            "difference_ci95": t_interval(diff), "spearman_body_means": rho(fa.mean(1),
                                                                          fb.mean(1)),
            f"spearman_split_half_{a}": rho(fa[:, ::2].mean(1), fa[:, 1::2].mean(1)),
            "jax": jax.__version__, "date": time.strftime("%Y-%m-%d")}


def make_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--space", default="bad_walker")
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 16])
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--single", type=int, default=8, help="bodies timed one at a time (B = 1 "
                        "calls) for the batching gain; 0 skips it")
    parser.add_argument("--physics", default="jax", choices=engines.list_engines())
    parser.add_argument("--train-steps", type=int, default=10_000)
    parser.add_argument("--controllers", type=int, default=1)
    parser.add_argument(
        "--update-epochs", type=int, default=None,
        help="PPO epochs per update (default the standard's 8); timing 1 against 8 splits "
        "the learner's share of a call from the rollouts'",
    )
    parser.add_argument("--deterministic", action="store_true", help="XLA's deterministic GPU ops")
    parser.add_argument("--warp-deterministic", action="store_true",
                        help="MuJoCo Warp's Option.deterministic (evojax_morph.physics.warp)")
    parser.add_argument("--out", default=None, help="append each row to this JSON-lines file")
    parser.add_argument("--mutations", type=int, default=3, help="random mutations a body")
    parser.add_argument("--classes", action="store_true",
                        help="each batch also with the space's size classes (a row each)")
    parser.add_argument("--agreement", type=int, default=0, metavar="N",
                        help="instead of timings: N bodies x --seeds keys with "
                        "one template and with size classes, in distribution (`agreement`)")
    parser.add_argument("--seeds", type=int, default=16, help="keys per body for --agreement")
    return parser


def emit(row: dict, out: str | None) -> None:
    """Prints `row` as JSON, and appends it to the JSON-lines file `out` if given."""
    print(json.dumps(row), flush=True)
    if out:
        with open(out, "a") as f:
            f.write(json.dumps(row) + "\n")


def measure(args, space, cfg, walk, batch: int) -> dict:
    """The row of one batch: the PPO fitness timed batched and one body at a time, and the raw
    physics at the same worlds (B bodies x K x worlds_per_controller worlds, no learning)."""
    keys = jax.random.split(jax.random.PRNGKey(batch), batch)
    morphs = walk(keys, args.mutations)
    evaluate = lambda: em.evaluate(space, morphs, keys, cfg).fitness  # timed now
    t_batch, repeat_diff, repeat_differing = timed(evaluate, args.repeats)

    t_single = one_at_a_time(space, morphs, keys, cfg, min(batch, args.single))

    # Raw physics at the same worlds: B bodies x K x worlds_per_controller worlds, no learning.
    models = jax.jit(jax.vmap(space.mjx_model))(morphs)
    worlds = args.controllers * cfg.ppo.worlds_per_controller
    rollout = make_raw_physics(engines.get_engine(args.physics), space, 100)
    t_phys = median_time(lambda: rollout(models, worlds), args.repeats)
    physics_rate = batch * worlds * 100 / t_phys

    steps = ppo.env_steps_per_morphology(cfg.task, cfg.ppo)
    train_rate = batch * steps / t_batch
    warp = args.physics == "warp"
    return {
        "space": args.space, "physics": args.physics, "device": jax.devices()[0].device_kind,
        "deterministic": args.deterministic, "mujoco_warp": MUJOCO_WARP if warp else None,
        "warp_deterministic": args.warp_deterministic, "train_steps": args.train_steps,
        "controllers": args.controllers, "update_epochs": cfg.ppo.update_epochs,
        "batch": batch, "mutations": args.mutations, "classes": cfg.classes,
        "env_steps_per_morphology": steps, "evals_per_s": batch / t_batch,
        "train_steps_per_s": train_rate, "physics_steps_per_s_raw": physics_rate,
        "ppo_over_physics": train_rate * cfg.task.frame_skip / physics_rate,
        "one_at_a_time_s": t_single, "batch_s": t_batch,
        "batching_gain": None if t_single is None else t_single / t_batch,
        "repeat_diff": repeat_diff,
        "repeat_differing": repeat_differing,  # of `batch` fitness values
        "date": time.strftime("%Y-%m-%d")}


def print_table(rows: list[dict]) -> None:
    print(f"\n{'B':>5} {'classes':>7} {'evals/s':>9} {'steps/s':>10} {'raw phys/s':>11} "
          f"{'ppo/phys':>9} {'1-at-a-time s':>14} {'batch s':>8} {'gain':>6} {'repeat diff':>11}")
    for r in rows:
        print(f"{r['batch']:>5} {str(r['classes']):>7} {r['evals_per_s']:>9.3g} "
              f"{r['train_steps_per_s']:>10.3g} {r['physics_steps_per_s_raw']:>11.3g} "
              f"{r['ppo_over_physics']:>9.0%} {fmt(r['one_at_a_time_s'], '>14.3g')} "
              f"{r['batch_s']:>8.3g} {fmt(r['batching_gain'], '>6.1f')} "
              f"{r['repeat_diff']:>11.3g} {r['repeat_differing']:>4}/{r['batch']}")


def main():
    parser = make_parser()
    args = parser.parse_args()
    if args.single < 0:
        parser.error("--single must be >= 0")
    if args.deterministic:
        em.deterministic_gpu()
    if args.warp_deterministic and not ew.set_deterministic(True):
        parser.error("--warp-deterministic: MJX runs its vendored MuJoCo Warp, which has no "
                     "such option; set EVOJAX_MORPH_MUJOCO_WARP=package (physics.templates)")
    full_precision()  # as the run command

    space = em.make_space(args.space)
    ppo_cfg = em.standard_ppo(args.train_steps, args.controllers)
    if args.update_epochs is not None:
        ppo_cfg = dataclasses.replace(ppo_cfg, update_epochs=args.update_epochs)
    cfg = em.FitnessConfig(ppo=ppo_cfg, physics=args.physics)
    if args.agreement:
        ways = {"one_template": (cfg, None), "classes": (dataclasses.replace(cfg, classes=True),
                                                         None)}
        row = agreement(space, ways, args.agreement, args.seeds, args.mutations) | {
            "physics": args.physics, "train_steps": args.train_steps}
        emit(row, args.out)
        return
    walk = jax.jit(jax.vmap(space.random_morphology, (0, None)), static_argnums=1)
    rows = []
    for batch, by_class in itertools.product(args.batches, [False, True][:1 + args.classes]):
        rows.append(measure(args, space, dataclasses.replace(cfg, classes=by_class), walk, batch))
        emit(rows[-1], args.out)
    print_table(rows)

if __name__ == "__main__":
    main()
