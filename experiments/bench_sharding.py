"""Batched fitness across devices: evaluations per second on 1 device and on all of them.

For each device count n (1, every visible device, and the powers of 2 between), `em.evaluate`
runs --per-device x n random Bad Walker bodies split over a mesh of n devices, at the standard
budget of bench_fitness.py (10,920 control steps per body). The 1-device row is also run at the
largest batch, which shows whether one device was already full. Then the same for one
environment step of the Double-DQN loop (mutate every body, evaluate the children, store,
update the replicated agent) at --envs-per-device x n parallel evolutions. Speed-up = evals/s
on n devices over evals/s on one device at its full batch. Timings exclude compilation.
With --agreement N, instead: N random bodies x --seeds keys on one device and on all of them,
whether the split changes the fitness in distribution (Spearman of the body means, and the
mean difference over all draws with its 95% interval).

  XLA_FLAGS=--xla_force_host_platform_device_count=2 \
    python -m experiments.bench_sharding --per-device 2 --envs-per-device 2 \
      --dqn-train-steps 320 --repeats 1
  python -m experiments.bench_sharding --per-device 1024 --envs-per-device 256     # GPUs
  python -m experiments.bench_sharding --per-device 1024 --physics warp \
      --out docs/warp/sharding.jsonl                                           # Warp, GPUs
  python -m experiments.bench_sharding --agreement 64 --seeds 16 --physics warp \
      --out docs/warp/sharding_agreement.json                                  # Warp, GPUs
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
from pathlib import Path

import jax

import evojax_morph as em
from evojax_morph.agents import dqn
from evojax_morph.physics.determinism import full_precision
from evojax_morph.search.pipeline import RunConfig, build
from evojax_morph.sharding import batch_mesh
from experiments.bench_fitness import STANDARD, median_time
from experiments.bench_fitness import agreement as fitness_agreement
from experiments.build_tables import revision


def bench_evaluate(space, devices, batch: int, repeats: int, physics: str = "jax") -> float:
    keys = jax.random.split(jax.random.PRNGKey(batch), batch)
    morphs = jax.jit(jax.vmap(space.random_morphology, (0, None)), static_argnums=1)(keys, 3)
    mesh, cfg = batch_mesh(devices), dataclasses.replace(STANDARD, physics=physics)
    t = median_time(lambda: em.evaluate(space, morphs, keys, cfg, mesh=mesh).fitness, repeats)
    return batch / t


def bench_dqn_step(space, devices, num_envs: int, train_steps: int, repeats: int,
                   physics: str = "jax") -> float:
    run = RunConfig(space=space.name, agent="ddqn", num_envs=num_envs, horizon=4,
                    train_steps=train_steps, physics=physics)
    init, chunk, _ = build(run, batch_mesh(devices), dqn.DQNConfig(learning_starts=0)).agent
    state = jax.jit(init)(jax.random.PRNGKey(0))
    holder = [state]

    def one_step():
        holder[0], metrics = chunk(holder[0], 1)
        return metrics["fitness"]

    return num_envs / median_time(one_step, repeats)


def agreement(space, devices, bodies: int, seeds: int, physics: str) -> dict:
    """`bench_fitness.agreement` of one device against all `devices`."""
    cfg = dataclasses.replace(STANDARD, physics=physics)
    ways = {"1": (cfg, batch_mesh(devices[:1])), "n": (cfg, batch_mesh(devices))}
    return fitness_agreement(space, ways, bodies, seeds, 3) | {
        "physics": physics, "devices": len(devices), "revision": revision()}


def main():
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--per-device", type=int, default=16,
                        help="bodies per device for em.evaluate")
    parser.add_argument("--envs-per-device", type=int, default=0,
                        help="DQN parallel evolutions per device (0: skip)")
    parser.add_argument("--dqn-train-steps", type=int, default=5_000)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--space", default="bad_walker")
    parser.add_argument("--physics", default="jax", help="the fitness's engine: jax | warp")
    parser.add_argument("--out", type=Path, help="append each row to this JSON-lines file")
    parser.add_argument("--agreement", type=int, default=0,
                        help="bodies for the agreement check instead of timings (0: timings)")
    parser.add_argument("--seeds", type=int, default=16, help="keys per body for --agreement")
    args = parser.parse_args()
    full_precision()  # as the run command
    space = em.make_space(args.space)
    devices = jax.devices()
    if args.agreement:
        row = agreement(space, devices, args.agreement, args.seeds, args.physics)
        print(json.dumps(row))
        if args.out:
            args.out.write_text(json.dumps(row, indent=1) + "\n")
        return
    # 1 device, all of them, the powers of 2 between, then one device at the largest batch
    # (the rows the speed-ups need first: a run cut short keeps them)
    most = len(devices)
    counts = [1, most] + [2**k for k in range(1, most.bit_length()) if 2**k < most]
    rows = []
    for what in ("evaluate", "dqn_step") if args.envs_per_device else ("evaluate",):
        per = args.per_device if what == "evaluate" else args.envs_per_device
        runs = [(n, per * n) for n in dict.fromkeys(counts)]
        if most > 1:
            runs.append((1, per * most))  # was one device already full?
        for n, batch in runs:
            if what == "evaluate":
                rate = bench_evaluate(space, devices[:n], batch, args.repeats, args.physics)
            else:
                rate = bench_dqn_step(space, devices[:n], batch, args.dqn_train_steps,
                                      args.repeats, args.physics)
            rows.append({"what": what, "space": space.name, "physics": args.physics,
                         "device": devices[0].device_kind, "devices": n, "batch": batch,
                         "evals_per_s": rate, "date": datetime.date.today().isoformat(),
                         "revision": revision(), "jax": jax.__version__})
            print(json.dumps(rows[-1]), flush=True)
            if args.out:
                with args.out.open("a") as f:
                    f.write(json.dumps(rows[-1]) + "\n")

    print(f"\n{'what':>9} {'devices':>7} {'batch':>6} {'evals/s':>9} {'speed-up':>9}")
    for r in rows:
        base = max(x["evals_per_s"] for x in rows if x["what"] == r["what"] and x["devices"] == 1)
        print(
            f"{r['what']:>9} {r['devices']:>7} {r['batch']:>6} {r['evals_per_s']:>9.4g} "
            f"{r['evals_per_s'] / base:>9.2f}"
        )


if __name__ == "__main__":
    main()
