"""Which method finds the better bodies in a space of 2.75 million? (issue 63) Every method and
every seed of the Crawler comparison in one batched program (`evojax_morph.search.study`).

The study: --methods x --seeds runs, each --num-envs evolutions x --steps steps (N x T
evaluations a run, equal for every method: evolution's re-measures of its survivors are among
its N a step; every run also evaluates m0 N times at its start), every child of a step
evaluated in ONE fitness call of methods x seeds x N bodies. A run's returned body is the body
of the highest mean fitness over the run's evaluations so far (m0's at its start among them;
ties to the body evaluated more often, then to the one seen first: `study.best_mean_bodies`),
the first of the `run` command's ranking (one rule: `bodylog.ranked`; `run` then confirms
its first 8 on a GPU from scratch and reports the best of them, the study only its first): the
fitness is noisy, and a run's best single draw is the luckiest of many. Every run's returned
bodies at every --curve-every evaluations (and at its end) are confirmed: --confirm-controllers
controllers trained from scratch, with keys of their own (`confirm_keys`: the method, the seed
and the body's index folded in, then split a controller, so no two runs share a measurement);
the best confirmed body of the whole study again with --best-controllers, its controller of
median return kept (DATA/best_controller) and one of its evaluation episodes drawn by MuJoCo's
renderer where OpenGL works (OUT/study_SPACE_TASK_best.gif).
Methods are compared on the returned bodies' confirmed means with Welch 95% intervals, Holm's
p and intervals that hold together over all the differences (`reproduce.compare_effects`).

A call runs the part of the seeds [--first-seed, --first-seed + --seeds) (seed s starts from
fold_in(PRNGKey(0), s) in any part) and resumes where it stopped: the agents' states after
every chunk in DATA/seeds_A-B/state/ (a run's checkpoints, the newest two, hundreds of MB each
on the Crawler: they stay on the machine that ran them; checked against the SHA-256 of every
array at a resume), the confirmations as they come. A finished part leaves
DATA/seeds_A-B/results.pkl (small, no agent state: it travels), and every call ends by making
the data file OUT/study_SPACE_TASK.json and its figure (.png: confirmed fitness against
evaluations spent, a band over seeds per method; distinct bodies each run visited) from every
finished part under DATA. Run the same command again until it says its seeds are done.
DATA/held.jsonl, a line a session copied from the device tool's lease (the machine's start,
installs and compiles included), makes the data file's `held_seconds`: the study's device time
counted whole, beside `device_seconds` (the study's and confirmations' own calls).

  python -m experiments.crawler_study --physics warp   # GPU: experiments/README.md
  python -m experiments.crawler_study --toy --out /tmp/cs   # CPU smoke, about a minute
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import pickle
import sys
import time
import zlib
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import scipy.stats

import evojax_morph as em
from evojax_morph.figures import video
from evojax_morph.fitnesses import get_fitness
from evojax_morph.physics import engines
from evojax_morph.records import saved_controllers
from evojax_morph.records.checkpoints import write_atomic
from evojax_morph.search import study
from evojax_morph.search.pipeline import build
from evojax_morph.tasks import gait_word
from experiments.build_tables import revision
from experiments.common import Setup, agent_overrides, band, plt, run_config, save
from experiments.reproduce import COMPARED, compare_effects

CONFIRM_SEED = 63  # every confirming key descends from it (`confirm_keys`)
STUDY_SEED = 0  # seed s of every method starts from fold_in(PRNGKey(0), s) (`seed_keys`)


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


def seed_keys(seeds: range) -> jax.Array:
    """(S,) the runs' keys: seed s of every method starts from fold_in(PRNGKey(0), s), whichever
    part of the seeds a call runs."""
    return jnp.stack([jax.random.fold_in(jax.random.PRNGKey(STUDY_SEED), s) for s in seeds])


def run_part(args, seeds: range, part: Path, deadline: float) -> dict | None:
    """Runs (or resumes) the study of `seeds`, confirms its runs' returned bodies and keeps
    what the data file needs in PART/results.pkl (small: no agent state); None past the
    deadline. The agents' states (PART/state/, hundreds of MB on the Crawler) stay where
    the call ran."""
    cfg = run_config(args.methods[0], setup_of(args))
    methods, p = study.methods_from(cfg, args.methods,
                                    overrides=agent_overrides(args.agent_settings)[0])
    s = study.make_study(methods, len(seeds))
    preload = engines.registered(cfg.physics).preload  # Warp's kernels, while compiling
    res = study.run_study(s, seed_keys(seeds), args.steps, args.chunk,
                          resume=part / "state", deadline=deadline,
                          log=lambda line: print(line, flush=True),
                          preload=preload and (lambda: preload(jax.local_devices(), p.space)))
    if res is None:
        return None
    print(f"seeds {seeds.start} to {seeds.stop - 1}: {s.evaluations} evaluations a call, "
          f"{res['evaluations_per_second']:.1f} evaluations/s over its chunks", flush=True)
    bodies = returned_bodies(p.space, res, seeds, args)
    confirmed = confirm_all(p.space, p.fitness, bodies, part / "confirmed.pkl", args, deadline)
    if confirmed is None:
        return None
    runs = []
    for m in methods:
        ends = study.best_mean_bodies(res["metrics"][m.name], args.steps,
                                      res["states"][m.name].first)
        for i, seed in enumerate(seeds):
            mine = [(b, c) for b, c in zip(bodies, confirmed["found"], strict=True)
                    if (b["method"], b["seed"]) == (m.name, seed)]
            settings = study.settings_of(run_config(m.name, setup_of(args)), m.name, m.env,
                                         agent_overrides(args.agent_settings)[0])
            runs.append({
                "method": m.name, "seed": seed,
                "agent_settings": dataclasses.asdict(settings) if settings is not None else {},
                "returned": next(c for b, c in mine if args.steps * args.num_envs in b["at"]),
                "returned_mean": ends[i]["mean"], "returned_draws": ends[i]["draws"],
                "returned_draw": float(res["states"][m.name].best_fitness[i]),
                "curve": sorted((e, c["mean"]) for b, c in mine for e in b["at"]),
                "distinct_bodies": distinct_bodies(res["metrics"][m.name]["signature"])[i],
                "draws": np.asarray(res["metrics"][m.name]["fitness"][:, i], np.float32),
                "candidates": [(c["mean"], b["morph"], c["body"]) for b, c in mine]})
    device = jax.devices()[0]
    results = {"seeds": list(seeds), "runs": runs, "evaluations_per_call": s.evaluations,
               "evaluations_per_second": res["evaluations_per_second"],
               "study_seconds": res["seconds"], "confirm_seconds": confirmed["seconds"],
               "device": f"{device.platform}: {device.device_kind}", "revision": revision(),
               "task": p.fitness.task.name}
    write_atomic(part / "results.pkl", pickle.dumps(results))
    return results


def returned_bodies(space, res, seeds: range, args) -> list[dict]:
    """Every (method, seed)'s returned body (`study.best_mean_bodies`) at each curve point
    (every --curve-every evaluations, and the end), equal bodies of a run confirmed once:
    [{method, seed, index (its distinct bodies' order), morph, at: [evaluations]}]."""
    n = args.num_envs
    every = max(args.curve_every // n, 1) * n
    points = [t for t in range(args.steps + 1) if (t * n) % every == 0 or t == args.steps]
    found = []
    for m in args.methods:
        at = {t: study.best_mean_bodies(res["metrics"][m], t, res["states"][m].first)
              for t in points}
        for i, seed in enumerate(seeds):
            mine = {}
            for t in points:
                morph = at[t][i]["morph"]
                name = space.canonical(morph)
                if name not in mine:
                    mine[name] = {"method": m, "seed": seed, "index": len(mine), "body": name,
                                  "morph": morph, "at": []}
                mine[name]["at"].append(t * n)
            found += mine.values()
    return found


def confirm_all(space, fit_cfg, bodies: list[dict], path: Path, args,
                deadline: float) -> dict | None:
    """em.confirm of every body of `bodies` with its run's own keys, --confirm-batch bodies a
    call, each batch saved (`path`): resumes; None past the deadline."""
    c = args.confirm_controllers
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
        print(f"confirmed {len(done['found'])} of {len(bodies)} returned bodies "
              f"({c} controllers each), {done['seconds']:.0f} s", flush=True)
    return done


def entry(c) -> dict:
    """A confirmed body as the data files keep it (`reproduce.confirm`'s fields)."""
    return {"body": c.body, "mean": c.mean, "ci95": list(c.ci95), "controllers": len(c.values),
            "distance": float(np.mean(c.distance)), "upright": float(np.mean(c.upright)),
            "upright_whole": c.upright_whole}


def gait(e: dict) -> str | None:
    """"walks" or "moves" for a confirmed entry (`tasks.gait_word`); None without a gait (a
    table's fitness keeps none)."""
    return None if np.isnan(e["distance"]) else gait_word(e["distance"], e["upright_whole"])


def distinct_bodies(signatures: np.ndarray) -> list[int]:
    """(steps, S, N, 2) children's signatures -> per seed, how many distinct bodies."""
    per_seed = np.moveaxis(signatures, 1, 0).reshape(signatures.shape[1], -1, 2)
    return [len(np.unique(s, axis=0)) for s in per_seed]


def confirm_best(space, fit_cfg, runs: list[dict], args, video_stem: Path) -> dict:
    """The best confirmed body of the whole study (every part present), confirmed again by
    --best-controllers with keys of their own (DATA/best.pkl, again if the best changed). With
    trained controllers, the one of median return is kept (DATA/best_controller) and one of its
    evaluation episodes drawn (VIDEO_STEM.gif, `video.render_saved`, whose replay steps MJX's
    JAX engine whatever engine trained it): a controller typical of the body, not its luckiest;
    the drawn episode is one of that controller's, not its mean."""
    path, kept = args.data / "best.pkl", args.data / "best_controller"
    controllers = saved_controllers.has_controllers(fit_cfg)
    mean, morph, name, run = max(((*c, r) for r in runs for c in r["candidates"]),
                                 key=lambda x: x[0])
    if (path.exists() and (best := pickle.loads(path.read_bytes()))["entry"]["body"] == name
            and (kept.exists() or not controllers)):
        return best
    start = time.time()
    key = jax.random.fold_in(jax.random.PRNGKey(CONFIRM_SEED), zlib.crc32(b"best"))
    (c,) = em.confirm(space, em.stack([morph]), key, fit_cfg, args.best_controllers)
    best = {"entry": {**entry(c), "method": run["method"], "seed": run["seed"]},
            "seconds": time.time() - start}
    if controllers:
        j = typical(c.values)
        saved_controllers.save(kept, saved_controllers.SavedController(
            space, fit_cfg, run["seed"], c.morph, jax.tree.map(lambda x: x[j], c.params),
            float(c.values[j]), f"the study's best body, controller {j} of {len(c.values)}"))
        shown = video.render_saved(saved_controllers.load(kept), video_stem, width=640,
                                   height=360, mp4=False)
        best["video"] = {"file": shown.paths[0].name, "controller": j,
                         "controller_return": float(c.values[j]),
                         "episode_return": shown.replay.episode_return,
                         "episode_distance": float(shown.replay.distance[-1]),
                         "episode_physics": "jax",  # `video.replay` steps MJX's JAX engine
                         "drawn_by": shown.backend}
        print(f"the best body's controller {j} of {len(c.values)} (return {c.values[j]:.1f}): "
              f"{shown.replay.distance[-1]:+.2f} m in the drawn episode, by {shown.backend}",
              flush=True)
    write_atomic(path, pickle.dumps(best))
    return best


def picks(runs: dict, start: str) -> dict | None:
    """Does a run's pick predict its body's own fitness? The returned body's mean over its
    draws in the run (controllers inherited, the rule's measure) against its confirmed mean
    (controllers from scratch), Spearman's rank correlation over the runs whose returned body
    is not the start body `start` (a method that stays there repeats one body); None below 3
    such runs."""
    pairs = [(mean, draws, e["mean"]) for r in runs.values()
             for mean, draws, e in zip(r["returned_mean"], r["returned_draws"], r["returned"])
             if e["body"] != start]
    if len(pairs) < 3:
        return None
    in_run, draws, confirmed = np.asarray(pairs, float).T
    rho = scipy.stats.spearmanr(in_run, confirmed)
    return {"runs": len(pairs), "one_draw": int((draws == 1).sum()),
            "in_run_mean": [float(in_run.min()), float(in_run.max())],
            "confirmed": [float(confirmed.min()), float(confirmed.max())],
            "spearman": float(rho.statistic), "p": float(rho.pvalue)}


def typical(values: np.ndarray) -> int:
    """The index of the median of `values` (the lower one of an even count)."""
    return int(np.argsort(values, kind="stable")[(len(values) - 1) // 2])


def summary(parts: list[dict], best: dict, args, start: str) -> dict:
    """The data file from every part's results: settings, cost, each run's confirmed returned
    bodies along the run, the effects (Holm), how well the runs' picks predict their bodies
    (`picks`; `start`: the start body's name) and the best body."""
    n, seeds = args.num_envs, sorted(s for p in parts for s in p["seeds"])
    runs = {}
    for m in args.methods:
        mine = sorted((r for p in parts for r in p["runs"] if r["method"] == m),
                      key=lambda r: r["seed"])
        points = sorted({e for r in mine for e, _ in r["curve"]})
        runs[m] = {
            "agent": m, "seeds": len(mine), "agent_settings": mine[0]["agent_settings"],
            "returned": [r["returned"] for r in mine],
            "returned_gait": [gait(r["returned"]) for r in mine],  # "walks" as tasks.py says
            "returned_mean": [r["returned_mean"] for r in mine],
            "returned_draws": [r["returned_draws"] for r in mine],
            "returned_draw": [r["returned_draw"] for r in mine],
            "curve": [{"evaluations": e, "confirmed": [dict(r["curve"])[e] for r in mine]}
                      for e in points],
            "distinct_bodies": [r["distinct_bodies"] for r in mine],
        }
    study_seconds = sum(p["study_seconds"] for p in parts)
    # The device tool's lease (machine start, installs, compiles and calls: the study's device
    # time counted whole), a line a session, copied by hand from its replies.
    held = args.data / "held.jsonl"
    leases = [json.loads(line) for line in held.read_text().splitlines()] if held.exists() else []
    confirm_seconds = sum(p["confirm_seconds"] for p in parts) + best["seconds"]
    trains = get_fitness(args.fitness).trains_controllers  # each child's from its parent's
    return {
        "space": args.space, "task": parts[0]["task"],
        "fitness": {"kind": args.fitness, "controllers": 1,
                    "train_steps": args.train_steps if trains else None,
                    "inheritance": trains},
        "physics": args.physics, "agents": list(args.methods), "seeds": len(seeds),
        "agent_settings": args.agent_settings or None,  # over the run's defaults
        "tuning": agent_overrides(args.agent_settings)[1],  # the tuning table, if frozen
        "seed_indices": seeds, "evaluations_per_run": n * args.steps,
        "start_evaluations_per_run": n, "num_envs": n, "steps": args.steps, "chunk": args.chunk,
        "parts": [{k: p[k] for k in ("seeds", "evaluations_per_call", "evaluations_per_second",
                                     "study_seconds", "confirm_seconds", "device", "revision")}
                  for p in parts],
        "device": parts[0]["device"],
        "device_seconds": round(study_seconds + confirm_seconds, 1),
        "study_seconds": round(study_seconds, 1), "confirm_seconds": round(confirm_seconds, 1),
        "held_seconds": round(sum(lease["held_seconds"] for lease in leases), 1),
        "leases": leases,
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "revision": revision(),
        "confirm_controllers": args.confirm_controllers,
        "confirm_keys": f"split(fold_in(fold_in(fold_in(PRNGKey({CONFIRM_SEED}), "
                        "crc32(method)), seed), body index in the run), controllers)",
        "runs": runs, "picks": picks(runs, start),
        "best": {**best["entry"], "gait": gait(best["entry"])},
        "best_video": best.get("video"),
        # the effects need 2 seeds a method
        "effects": compare_effects(runs) if len(seeds) > 1 else None,
    }


def draw(data: dict, out: Path, name: str) -> None:
    """Confirmed fitness of the returned body against evaluations spent (median over seeds,
    quartile band, per method); distinct bodies each run visited; each run's returned body,
    its mean in the run against its confirmed mean (`picks`)."""
    fig, (ax_c, ax_d, ax_p) = plt.subplots(1, 3, figsize=(15, 4),
                                           gridspec_kw={"width_ratios": [3, 2, 2]})
    steps = data["fitness"]["train_steps"]
    budget = f"{steps:,} PPO steps" if steps else f"the {data['fitness']['kind']} fitness"
    for i, (m, r) in enumerate(data["runs"].items()):
        x = [p["evaluations"] for p in r["curve"]]
        band(ax_c, np.asarray(x), np.asarray([p["confirmed"] for p in r["curve"]]), m,
             color=f"C{i}")
        ax_d.plot(np.full(len(r["distinct_bodies"]), i), r["distinct_bodies"], "o",
                  color=f"C{i}", alpha=0.6)
        ax_p.plot(r["returned_mean"], [e["mean"] for e in r["returned"]], "o", color=f"C{i}",
                  alpha=0.6)
    task = em.make_task(data["task"])
    if standing := task.healthy_reward * task.episode_length:  # the walking task's floor
        ax_c.axhline(standing, color="gray", ls=":", label="standing the whole episode")
    ax_c.set(xlabel="evaluations spent per run",
             ylabel=f"returned body, mean of {data['confirm_controllers']} fresh controllers",
             title=f"{data['space'].title()}, {data['task']} task, {budget}: median over "
                   f"{data['seeds']} seeds, quartiles")
    ax_c.legend(fontsize=8)
    ax_d.set_xticks(range(len(data["runs"])), list(data["runs"]), rotation=20, fontsize=8)
    ax_d.set(ylabel="distinct bodies evaluated in a run",
             title=f"{data['evaluations_per_run']:,} evaluations a run")
    rho = f"Spearman {data['picks']['spearman']:.2f}, {data['picks']['runs']} runs off m0" \
        if data["picks"] else "under 3 runs off m0"
    ax_p.set(xlabel="returned body: its mean in the run (inherited)",
             ylabel="its confirmed mean (from scratch)", title=f"the picks: {rho}")
    save(fig, out, name, data)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add = parser.add_argument
    add("--methods", nargs="+", default=list(COMPARED), help="registered agents")
    add("--seeds", type=int, help="runs a method in this part (default 10; --toy 2)")
    add("--first-seed", type=int, default=0,
        help="the part's first seed: a study too long for one machine runs in parts of seeds")
    add("--num-envs", type=int, default=64, help="evolutions a run (N a step)")
    add("--steps", type=int, default=32, help="steps a run (N x steps evaluations)")
    add("--chunk", type=int, default=2, help="steps a compiled call (state saved after each)")
    add("--space", default="crawler")
    add("--task", default="walk", choices=em.list_tasks())
    add("--fitness", default="ppo", help="ppo; table for the CPU smoke")
    add("--train-steps", type=int, default=50_000, help="PPO steps an evaluation")
    add("--physics", default="jax", help="the fitness's engine: jax | warp")
    add("--hidden", type=int, default=64, help="the agents' GNN width")
    add("--agent-settings", default="", help="{method: {field: value}} over the run's "
        "defaults: JSON, or a frozen settings file (experiments/frozen_settings.json)")
    add("--tag", default="", help="appended to the data file's name (OUT/study_SPACE_TASK"
        "TAG.json)")
    add("--confirm-controllers", type=int, default=16)
    add("--best-controllers", type=int, default=32)
    add("--curve-every", type=int, default=512, help="evaluations between curve points")
    add("--confirm-batch", type=int, default=256, help="bodies a confirming call")
    add("--budget", type=float, default=420,
        help="seconds: start no chunk or confirming call after this")
    add("--data", type=Path, help="the study's state (default: docs/figures/crawler_study; "
        "with --toy, OUT/crawler_study)")
    add("--out", type=Path, default=Path("docs/figures"))
    add("--toy", action="store_true", help="the CPU smoke: Bad Walker's table, 2 seeds")
    args = parser.parse_args(argv)
    if args.toy:
        args.space, args.fitness, args.task, args.physics = "bad_walker", "table", "", "jax"
        args.num_envs, args.steps, args.chunk = 4, 6, 2
        args.confirm_controllers, args.best_controllers, args.curve_every = 2, 4, 8
    args.seeds = args.seeds or (2 if args.toy else 10)
    args.data = args.data or (args.out / "crawler_study" if args.toy
                              else Path("docs/figures/crawler_study"))
    deadline = time.time() + args.budget
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    part = args.data / f"seeds_{seeds.start}-{seeds.stop - 1}"
    part.mkdir(parents=True, exist_ok=True)
    if not (part / "results.pkl").exists() and run_part(args, seeds, part, deadline) is None:
        print("not done: run the same command again", flush=True)
        return 0
    parts = [pickle.loads(f.read_bytes()) for f in sorted(args.data.glob("seeds_*/results.pkl"))]
    space = em.make_space(args.space)
    cfg = build(run_config(args.methods[0], setup_of(args))).fitness  # the confirmations'
    name = f"study_{args.space}_{parts[0]['task']}{args.tag}"
    args.out.mkdir(parents=True, exist_ok=True)  # the best body's video goes there first
    best = confirm_best(space, cfg, [r for p in parts for r in p["runs"]], args,
                        args.out / f"{name}_best")
    data = summary(parts, best, args, space.canonical(space.initial()))
    draw(data, args.out, name)
    print(f"the study's seeds {data['seed_indices']} are done", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
