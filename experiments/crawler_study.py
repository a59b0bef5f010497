"""Which method finds the better bodies in a space of 2.75 million? (issue 63) Every method and
every seed of the Crawler comparison in one batched program (`evojax_morph.study`).

The study: --methods x --seeds runs, each --num-envs evolutions x --steps steps (N x T
evaluations a run, equal for every method: evolution's re-measures of its survivors are among
its N a step; every run also evaluates m0 N times at its start), every child of a step
evaluated in ONE fitness call of methods x seeds x N bodies. Each run's returned body (its best
single draw so far) is recorded after every chunk. Then every run's returned bodies at every
--curve-every evaluations (and at its end) are confirmed: --confirm-controllers controllers
trained from scratch, with keys of their own (`confirm_keys`: the method and the seed folded
in, so no two runs share a measurement); the best confirmed body of the whole study again with
--best-controllers. Methods are compared on the returned bodies' confirmed means with Welch
95% intervals, Holm-corrected (`reproduce.compare_effects`).

Each stage keeps its state under --data and resumes where it stopped: run the same command
again until it says the study is done. Writes OUT/study_SPACE_TASK.json (the data file) and
.png (confirmed fitness against evaluations spent, a band over seeds per method; distinct
bodies each method visited).

  python -m experiments.crawler_study --physics warp   # GPU: experiments/README.md
  python -m experiments.crawler_study --toy --out /tmp/cs   # CPU smoke, about a minute
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import pickle
import sys
import time
import zlib
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import evojax_morph as em
from evojax_morph import study
from evojax_morph.checkpoints import write_atomic
from evojax_morph.pipeline import agent_config
from experiments.build_tables import revision
from experiments.common import Setup, band, plt, run_config, save
from experiments.reproduce import COMPARED, compare_effects

CONFIRM_SEED = 63  # every confirming key descends from it (`confirm_keys`)
STUDY_SEED = 0  # seed s of every method starts from split(PRNGKey(0), S)[s], as run_agent's


def confirm_keys(method: str, seed: int, body: int, controllers: int) -> jax.Array:
    """(controllers, 2) keys confirming body `body` (its index among the run's distinct
    returned bodies) of run (`method`, `seed`): no two runs, nor two bodies of a run, share
    one."""
    key = jax.random.fold_in(jax.random.PRNGKey(CONFIRM_SEED), zlib.crc32(method.encode()))
    key = jax.random.fold_in(jax.random.fold_in(key, seed), body)
    return jax.random.split(key, controllers)


def setup_of(args) -> Setup:
    return Setup(space=args.space, fitness=args.fitness, task=args.task,
                 train_steps=args.train_steps, num_envs=args.num_envs, steps=args.steps,
                 chunk=args.chunk, hidden=args.hidden, physics=args.physics)


def run_the_study(args, deadline: float):
    """Runs (or resumes) the study; (its `run_study` result or None past the deadline, the
    pipeline, the methods)."""
    cfg = run_config(args.methods[0], setup_of(args))
    methods, p = study.methods_from(cfg, args.methods)
    s = study.make_study(methods, args.seeds)

    def best(states, done):
        del done
        return {"best": study.best_bodies(states),
                "best_fitness": {m: np.asarray(st.best_fitness) for m, st in states.items()}}

    res = study.run_study(s, jax.random.PRNGKey(STUDY_SEED), args.steps, args.chunk,
                          resume=args.data / "study.pkl", deadline=deadline, on_chunk=best)
    return res, p, methods, s


def returned_bodies(space, res, args) -> list[dict]:
    """Every (method, seed)'s returned body at each curve point (every --curve-every
    evaluations, and the end), equal bodies of a run confirmed once: [{method, seed,
    index (its distinct bodies' order), morph, at: [evaluations]}]."""
    n = args.num_envs
    every = max(args.curve_every // n, 1) * n
    points = [a for a in res["at_chunks"] if (a["steps"] * n) % every == 0
              or a["steps"] == args.steps]
    found = []
    for m in args.methods:
        for seed in range(args.seeds):
            mine = {}
            for a in points:
                morph = jax.tree.map(lambda x, s=seed: np.asarray(x[s]), a["best"][m])
                name = space.canonical(morph)
                if name not in mine:
                    mine[name] = {"method": m, "seed": seed, "index": len(mine), "body": name,
                                  "morph": morph, "at": []}
                mine[name]["at"].append(a["steps"] * n)
            found += mine.values()
    return found


def confirm_all(space, fit_cfg, bodies: list[dict], args, deadline: float) -> list | None:
    """em.confirm of every body of `bodies` with its run's own keys, --confirm-batch bodies a
    call, each batch saved (DATA/confirmed.pkl): resumes; None past the deadline."""
    path, c = args.data / "confirmed.pkl", args.confirm_controllers
    done = pickle.loads(path.read_bytes()) if path.exists() else {"found": [], "seconds": 0.0}
    while len(done["found"]) < len(bodies):
        if time.time() > deadline:
            return None
        start = time.time()
        part = bodies[len(done["found"]): len(done["found"]) + args.confirm_batch]
        keys = jnp.concatenate([confirm_keys(b["method"], b["seed"], b["index"], c)
                                for b in part])
        found = em.confirm(space, em.stack([b["morph"] for b in part]), keys, fit_cfg, c,
                           ranked=False)
        done["found"] += [entry(f) for f in found]
        done["seconds"] += time.time() - start
        write_atomic(path, pickle.dumps(done))
    return done


def entry(c) -> dict:
    """A confirmed body as the data files keep it (`reproduce.confirm`'s fields)."""
    return {"body": c.body, "mean": c.mean, "ci95": list(c.ci95), "controllers": len(c.values),
            "distance": float(np.mean(c.distance)), "upright": float(np.mean(c.upright)),
            "upright_whole": c.upright_whole}


def distinct_bodies(signatures: np.ndarray) -> list[int]:
    """(steps, S, N, 2) children's signatures -> per seed, how many distinct bodies."""
    per_seed = np.moveaxis(signatures, 1, 0).reshape(signatures.shape[1], -1, 2)
    return [len(np.unique(s, axis=0)) for s in per_seed]


def summary(res, p, s, methods, bodies, confirmed, best, args) -> dict:
    """The data file: settings, cost, each run's confirmed returned bodies, the effects."""
    device = jax.devices()[0]
    n = args.num_envs
    by_run = {}
    for b, c in zip(bodies, confirmed["found"], strict=True):
        by_run.setdefault((b["method"], b["seed"]), []).append((b, c))
    runs = {}
    for m in methods:
        mine = [by_run[(m.name, s)] for s in range(args.seeds)]
        final = [next(c for b, c in run if args.steps * n in b["at"]) for run in mine]
        points = sorted({e for run in mine for b, _ in run for e in b["at"]})
        curve = [{"evaluations": e, "confirmed": [next(c["mean"] for b, c in run if e in b["at"])
                                                  for run in mine]} for e in points]
        settings = agent_config(run_config(m.name, setup_of(args)), m.env)
        runs[m.name] = {
            "agent": m.name, "seeds": args.seeds,
            "agent_settings": dataclasses.asdict(settings) if settings is not None else {},
            "returned": final,
            "returned_draw": res["states"][m.name].best_fitness.tolist(),
            "curve": curve,
            "distinct_bodies": distinct_bodies(res["metrics"][m.name]["signature"]),
        }
    return {
        "space": args.space, "task": p.fitness.task.name,
        "fitness": {"kind": args.fitness, "controllers": 1,
                    "train_steps": args.train_steps if args.fitness == "ppo" else None,
                    "inheritance": args.fitness == "ppo"},
        "physics": args.physics, "agents": list(args.methods), "seeds": args.seeds,
        "evaluations_per_run": n * args.steps, "start_evaluations_per_run": n,
        "num_envs": n, "steps": args.steps, "chunk": args.chunk,
        "evaluations_per_call": s.evaluations,
        "evaluations_per_second": res["evaluations_per_second"],
        "device": f"{device.platform}: {device.device_kind}",
        "device_seconds": round(res["seconds"] + confirmed["seconds"] + best["seconds"], 1),
        "study_seconds": round(res["seconds"], 1),
        "confirm_seconds": round(confirmed["seconds"] + best["seconds"], 1),
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "revision": revision(),
        "confirm_controllers": args.confirm_controllers,
        "confirm_keys": f"split(fold_in(fold_in(fold_in(PRNGKey({CONFIRM_SEED}), "
                        "crc32(method)), seed), body index in the run), controllers)",
        "runs": runs, "effects": compare_effects(runs), "best": best["entry"],
    }


def confirm_best(space, fit_cfg, confirmed, bodies, args) -> dict:
    """The best confirmed body of the whole study, confirmed again by --best-controllers with
    keys of its own (DATA/best.pkl)."""
    path = args.data / "best.pkl"
    if path.exists():
        return pickle.loads(path.read_bytes())
    start = time.time()
    i = int(np.argmax([c["mean"] for c in confirmed["found"]]))
    b = bodies[i]
    key = jax.random.fold_in(jax.random.PRNGKey(CONFIRM_SEED), zlib.crc32(b"best"))
    (c,) = em.confirm(space, em.stack([b["morph"]]), key, fit_cfg, args.best_controllers)
    best = {"entry": {**entry(c), "method": b["method"], "seed": b["seed"]},
            "seconds": time.time() - start}
    write_atomic(path, pickle.dumps(best))
    return best


def draw(data: dict, out: Path, name: str) -> None:
    """Confirmed fitness of the returned body against evaluations spent (median over seeds,
    quartile band, per method); distinct bodies each run visited."""
    fig, (ax_c, ax_d) = plt.subplots(1, 2, figsize=(11, 4), gridspec_kw={"width_ratios": [3, 2]})
    steps = data["fitness"]["train_steps"]
    budget = f"{steps:,} PPO steps" if steps else f"the {data['fitness']['kind']} fitness"
    for i, (m, r) in enumerate(data["runs"].items()):
        x = [p["evaluations"] for p in r["curve"]]
        band(ax_c, np.asarray(x), np.asarray([p["confirmed"] for p in r["curve"]]), m,
             color=f"C{i}")
        ax_d.plot(np.full(len(r["distinct_bodies"]), i), r["distinct_bodies"], "o",
                  color=f"C{i}", alpha=0.6)
    ax_c.set(xlabel="evaluations spent per run",
             ylabel=f"returned body, mean of {data['confirm_controllers']} fresh controllers",
             title=f"{data['space'].title()}, {data['task']} task, {budget}: median over "
                   f"{data['seeds']} seeds, quartiles")
    ax_c.legend(fontsize=8)
    ax_d.set_xticks(range(len(data["runs"])), list(data["runs"]), rotation=20, fontsize=8)
    ax_d.set(ylabel="distinct bodies evaluated in a run",
             title=f"{data['evaluations_per_run']:,} evaluations a run")
    save(fig, out, name, data)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add = parser.add_argument
    add("--methods", nargs="+", default=list(COMPARED), help="registered agents")
    add("--seeds", type=int, default=10)
    add("--num-envs", type=int, default=64, help="evolutions a run (N a step)")
    add("--steps", type=int, default=40, help="steps a run (N x steps evaluations)")
    add("--chunk", type=int, default=2, help="steps a compiled call (state saved after each)")
    add("--space", default="crawler")
    add("--task", default="walk", choices=em.list_tasks())
    add("--fitness", default="ppo", help="ppo; table for the CPU smoke")
    add("--train-steps", type=int, default=50_000, help="PPO steps an evaluation")
    add("--physics", default="jax", help="the fitness's engine: jax | warp")
    add("--hidden", type=int, default=64, help="the agents' GNN width")
    add("--confirm-controllers", type=int, default=16)
    add("--best-controllers", type=int, default=32)
    add("--curve-every", type=int, default=512, help="evaluations between curve points")
    add("--confirm-batch", type=int, default=256, help="bodies a confirming call")
    add("--budget", type=float, default=480,
        help="seconds: start no chunk or confirming call after this")
    add("--data", type=Path, help="the study's state (default: docs/figures/crawler_study; "
        "with --toy, OUT/crawler_study)")
    add("--out", type=Path, default=Path("docs/figures"))
    add("--toy", action="store_true", help="the CPU smoke: Bad Walker's table, 2 seeds")
    args = parser.parse_args(argv)
    if args.toy:
        args.space, args.fitness, args.task, args.physics = "bad_walker", "table", "", "jax"
        args.seeds, args.num_envs, args.steps, args.chunk = 2, 4, 6, 2
        args.confirm_controllers, args.best_controllers, args.curve_every = 2, 4, 8
    args.data = args.data or (args.out / "crawler_study" if args.toy
                              else Path("docs/figures/crawler_study"))
    deadline = time.time() + args.budget
    args.data.mkdir(parents=True, exist_ok=True)
    res, p, methods, s = run_the_study(args, deadline)
    if res is None:
        print("not done: run the same command again", flush=True)
        return 0
    print(f"study: {s.evaluations} evaluations a call, {res['evaluations_per_second']:.1f} "
          f"evaluations/s over its chunks", flush=True)
    bodies = returned_bodies(p.space, res, args)
    confirmed = confirm_all(p.space, p.fitness, bodies, args, deadline)
    if confirmed is None:
        print("not done: run the same command again", flush=True)
        return 0
    best = confirm_best(p.space, p.fitness, confirmed, bodies, args)
    data = summary(res, p, s, methods, bodies, confirmed, best, args)
    draw(data, args.out, f"study_{args.space}_{data['task']}")
    print("the study is done", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
