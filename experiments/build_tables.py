"""Build a landscape table: every body of an enumerable space x S results of the PPO fitness.

Each result is one controller trained from scratch at the `run` command's GPU settings
(`em.standard_ppo(50_000)`, one controller, XLA's deterministic GPU ops unless --fast-gpu or
--physics warp), result s of body k with key fold_in(fold_in(PRNGKey(--seed), k), s), so any K
can be drawn from them later (the `table` fitness, `evojax_morph.fitnesses.table`). The (body,
seed) jobs run in batches of --batch in `em.evaluate` calls of one shape; the table is saved
after every batch and a rerun with the same flags skips what is done, so a build can span
several device sessions (a few minutes of H200 per space and 32 seeds: see the table's
metadata).

  python -m experiments.build_tables --space bad_walker --seeds 32              # GPU: the table
  python -m experiments.build_tables --space length_walker --seeds 32
  python -m experiments.build_tables --space crawler_near --seeds 16 --task walk \\
      --physics warp --budget 480 --out docs/landscapes/crawler_near_walk.npz  # rerun until done
  python -m experiments.build_tables --space bad_walker --seeds 2 --train-steps 320 \\
      --out /tmp/bw.npz                                                         # CPU check

Deep rows: with --deep-top N --deep-seeds S2, once every body has its --seeds results, the N
bodies with the highest means get results --seeds .. S2-1 as well (the same keys, continued),
enough to tell the best bodies apart; the other rows stay at --seeds (NaN-padded). The deep
rows are chosen by the means of the --seeds results and recorded in the metadata ("deep").

Each result keeps its gait beside its fitness (`FitnessResult.distance` and `.upright`). The
controllers learn --task (`em.list_tasks()`; "distance", the source's task and the packaged
tables', by default), recorded in the metadata ("task"): the table fitness serves that task
only, so a table of another task needs its own --out.

Writes evojax_morph/fitnesses/tables/SPACE.npz by default (the table fitness's packaged table).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np

import evojax_morph as em
from evojax_morph import ppo
from evojax_morph.fitnesses import get_fitness
from evojax_morph.fitnesses import table as tables
from evojax_morph.physics.determinism import full_precision
from evojax_morph.run import cli

GPU_TRAIN_STEPS = 50_000  # `run`'s GPU budget per controller (`Space.gpu_defaults`)


def engine_flags() -> list[str]:
    """`FitnessConfig`'s settings the table records as its engine and the CLI may set (only
    those the config has): the physics engine, where the fitness offers a choice."""
    return [f.name for f in dataclasses.fields(em.FitnessConfig) if f.name in ("physics",)]


def revision() -> str:
    """The code's git revision, "+dirty" with uncommitted changes ("" outside git);
    EVOJAX_MORPH_REVISION if set (a copy of the tree whose .git is not its own, as on the
    device machines)."""
    if os.environ.get("EVOJAX_MORPH_REVISION"):
        return os.environ["EVOJAX_MORPH_REVISION"]
    root = Path(__file__).resolve().parents[1]
    try:
        rev = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True,
                             text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                               cwd=root, capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return ""
    return rev + ("+dirty" if dirty.strip() else "")


def fitness_config(args) -> em.FitnessConfig:
    extra = {name: getattr(args, name) for name in engine_flags()}
    extra["task"] = em.make_task(args.task)
    if args.fitness == "predefined":
        return em.FitnessConfig(kind="predefined", **extra)
    return em.FitnessConfig(kind="ppo", ppo=em.standard_ppo(args.train_steps, 1), **extra)


def settings(space: em.Space, cfg: em.FitnessConfig, args, names: list[str]) -> dict:
    """What makes two builds the same table: a resumed build must match them."""
    return {
        "task": cfg.task.name,  # `Table.task`: the table fitness serves this task only
        "fitness": cfg.to_dict(),
        "seed": args.seed,
        "seeds": args.seeds,
        "bodies": len(names),
        "env_steps_per_result": (ppo.env_steps_per_morphology(cfg.task, cfg.ppo)
                                 if get_fitness(cfg.kind).trains_controllers else 0),
        "engine": {name: getattr(cfg, name) for name in engine_flags()} or "mjx (jax)",
    }


def deepen(table: tables.Table, top: int, seeds: int) -> None:
    """Widens `table` to `seeds` columns and marks its `top` best rows (by their mean over the
    base results) deep; the new columns are NaN (to be measured) in those rows only."""
    base = table.base
    rows = table.meta.get("deep", {}).get("rows")
    if rows is None:
        rows = [int(k) for k in np.argsort(-table.fitness[:, :base].mean(1), kind="stable")[:top]]
    wide = max(seeds, table.seeds)
    if wide > table.seeds:
        pad = lambda a, fill: np.concatenate(  # noqa: E731
            [a, np.full((a.shape[0], wide - a.shape[1]), fill, a.dtype)], 1)
        table.fitness, table.diverged = pad(table.fitness, np.nan), pad(table.diverged, False)
        table.distance, table.upright = pad(table.distance, np.nan), pad(table.upright, np.nan)
    table.meta["deep"] = {"top": top, "seeds": wide, "rows": rows,
                          "chosen_by": f"the mean of the first {base} results"}


def wanted(table: tables.Table) -> np.ndarray:
    """(T, S) bool: the results still to measure: the base of every row, all of a deep row."""
    want = np.zeros(table.fitness.shape, bool)
    want[:, : table.base] = True
    want[table.meta.get("deep", {}).get("rows", []), :] = True
    return want & ~table.done


def build(args) -> tables.Table:
    space = em.make_space(args.space)
    cfg = fitness_config(args)
    bodies, _ = space.enumerate_bodies()
    names = [space.canonical(m) for m in bodies]
    want = settings(space, cfg, args, names)
    out = Path(args.out)
    if out.exists():
        table = tables.Table.load(out)
        had = {k: table.meta.get(k) for k in want}
        if table.space != space.name or table.names != names or had != json.loads(json.dumps(want)):
            sys.exit(f"{out} holds a table of other settings; pass another --out or remove it\n"
                     f"  it has:  {had}\n  wanted: {want}")
        print(f"resuming {out}: {int(table.done.sum())} of {table.done.size} results done")
    else:
        table = tables.Table(
            space.name, names, tables.stacked(bodies),
            np.full((len(bodies), args.seeds), np.nan, np.float32),
            np.zeros((len(bodies), args.seeds), bool),
            {**want, "seconds": 0.0, "batches": []},
        )
    if args.deep_top:
        if not table.complete:
            print(f"deep rows wait for the base: {int(wanted(table).sum())} results first")
        else:
            deepen(table, args.deep_top, args.deep_seeds)
    jobs = [(k, s) for k, s in np.argwhere(wanted(table))]
    key = jax.random.PRNGKey(args.seed)
    # one shape for every call, a full build or a rest
    batch = min(args.batch, len(names) * max(args.seeds, args.deep_seeds if args.deep_top else 0))
    last = 0.0  # the last batch's seconds, for --budget
    for n, start in enumerate(range(0, len(jobs), batch)):
        if args.max_batches is not None and n >= args.max_batches:
            print(f"stopped after {n} batches (--max-batches); rerun to continue")
            break
        if args.budget is not None and n and time.time() - args.began + last > args.budget:
            print(f"stopped after {n} batches: another would pass --budget {args.budget:g} s; "
                  "rerun to continue")
            break
        part = jobs[start : start + batch]
        padded = part + [part[0]] * (batch - len(part))
        keys = jax.numpy.stack(
            [jax.random.fold_in(jax.random.fold_in(key, int(k)), int(s)) for k, s in padded]
        )
        t = time.time()
        res = em.evaluate(space, em.stack([bodies[k] for k, _ in padded]), keys, cfg)
        fitness, diverged, distance, upright = jax.device_get(
            (res.fitness, res.diverged, res.distance, res.upright))
        seconds = last = time.time() - t
        for i, (k, s) in enumerate(part):
            table.fitness[k, s], table.diverged[k, s] = fitness[i], diverged[i]
            table.distance[k, s], table.upright[k, s] = distance[i], upright[i]
        device = jax.devices()[0]
        device = f"{device.platform}: {device.device_kind} x {jax.device_count()}"
        table.meta.update(
            device=device,  # the last batch's; each batch records its own below
            date=datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
            revision=revision(),
            jax=jax.__version__,
            seconds=table.meta["seconds"] + seconds,
            command="python -m experiments.build_tables " + " ".join(args.argv),
        )
        table.meta["batches"].append({"results": len(part), "batch": batch, "device": device,
                                      "seconds": round(seconds, 2)})
        table.save(out)
        print(f"batch {n + 1}: {len(part)} results in {seconds:.1f} s, "
              f"{int(wanted(table).sum())} to go", flush=True)
    if args.deep_top and table.complete and "deep" not in table.meta:
        return build(args)  # the base just completed: now the deep rows
    if table.complete and not wanted(table).any():
        mean = table.mean()
        deep = table.meta.get("deep")
        print(f"{out}: complete, {len(names)} bodies x {args.seeds} results"
              + (f", the {deep['top']} best x {deep['seeds']}" if deep else "")
              + f"; best mean {mean.max():.4g} ({names[int(mean.argmax())]}), m0 "
              f"{mean[0]:.4g}, {out.stat().st_size / 1024:.0f} KB")
    return table


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    cli.start(argv)  # before JAX starts a backend: XLA's deterministic GPU ops
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add = parser.add_argument
    add("--space", required=True, help="an enumerable space: bad_walker or length_walker")
    add("--seeds", type=int, default=32, help="independent results per body")
    add("--train-steps", type=int, default=GPU_TRAIN_STEPS,
        help="PPO control steps per controller (the run command's GPU budget by default)")
    add("--batch", type=int, default=1024,
        help="(body, seed) results per compiled call (the run's GPU batch: 256 bodies x 4)")
    add("--seed", type=int, default=0, help="the results' keys derive from it")
    add("--task", default="distance", choices=em.list_tasks(),
        help="the task the controllers learn (`em.make_task`); the table fitness serves only "
        "this task")
    add("--out", default=None, help="the table (.npz); default: the packaged "
        "evojax_morph/fitnesses/tables/SPACE.npz")
    add("--max-batches", type=int, default=None, help="stop after this many batches")
    add("--budget", type=float, default=None,
        help="seconds: start no batch that would end past them (by the last batch's time), so "
        "a device call ends in time; rerun to continue")
    add("--deep-top", type=int, default=0,
        help="give the N bodies of the highest means --deep-seeds results (0: none)")
    add("--deep-seeds", type=int, default=256, help="results of each deep row")
    add("--fitness", default="ppo", choices=["ppo", "predefined"],
        help="predefined: a table of the deterministic fitness, for tests of the machinery")
    add("--fast-gpu", action="store_true",
        help="leave XLA's deterministic GPU ops off (faster; results no longer reproducible)")
    for name in engine_flags():
        field = {f.name: f for f in dataclasses.fields(em.FitnessConfig)}[name]
        add(f"--{name}", default=field.default, help=f"FitnessConfig.{name}")
    args = parser.parse_args(argv)
    if args.seeds < 1 or args.batch < 1 or args.train_steps < 0 or args.deep_top < 0:
        parser.error("--seeds and --batch must be positive, --train-steps and --deep-top at "
                     "least 0")
    if args.deep_top and args.deep_seeds <= args.seeds:
        parser.error("--deep-seeds must exceed --seeds")
    args.out = args.out or str(tables.default_path(args.space))
    args.argv = argv
    args.began = time.time()  # --budget counts from here
    full_precision()  # as the run command
    build(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
