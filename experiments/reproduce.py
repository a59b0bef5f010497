"""The source's experiments at its scale (Figures 5 to 8, RL against evolution on Constructor).

Each stage trains agents with the NGE fitness (PPO with the parent's controller inherited, on
--physics) and keeps its data under --data; a stage resumes where it stopped (the agents'
states are saved after every chunk), so the whole section spans device calls of a few minutes:
run the same command again until it says every stage asked for is done. `--draw` makes the
figures from the data files alone.

  fig6_h20, fig6_h100  Double-DQN on Bad Walker, Q-network width 20 and 100 (Figure 6)
  fig5                 the width-100 agents' greedy unrolls from m0, each body confirmed (Fig. 5)
  fig8                 the actor-critic on Constructor: return and policy entropy (Figure 8)
  fig7                 its greedy unrolls, each body confirmed (Figure 7)
  compare              actor-critic, Double-DQN, evolution and random walks on Constructor at
                       equal evaluations; each returned body confirmed

A body is "confirmed" by `em.confirm`: --confirm-controllers controllers trained from scratch
(no inheritance) with fresh keys in one batched call, the mean and its 95% t-interval.

  python -m experiments.reproduce --stages fig6_h20 fig6_h100 fig5 --physics warp --budget 480
  python -m experiments.reproduce --draw --data docs/figures/reproduce --out docs/figures
  python -m experiments.reproduce --task walk --stages compare --physics warp   # walking task
  python -m experiments.reproduce --task walk --stages compare --physics warp --space crawler
  python -m experiments.reproduce --toy --stages all --data /tmp/r --out /tmp/r   # CPU smoke
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
import numpy as np
import scipy.stats

import evojax_morph as em
from evojax_morph.figures import plots
from evojax_morph.physics.determinism import full_precision
from evojax_morph.search.confirm import t_interval
from evojax_morph.search.pipeline import (
    NO_OP,
    agent_config,
    build,
)
from experiments.build_tables import revision
from experiments.common import Setup, band, episode_returns, holm, plt, run_agent, run_config, save

TRAIN_STEPS = 5_000  # the source's PPO budget per evaluation (it names 3,000 and 5,000)


@dataclasses.dataclass(frozen=True)
class Group:
    """One run group: `seeds` runs of `agent`, each `num_envs` x `steps` evaluations."""

    space: str
    agent: str
    num_envs: int
    steps: int
    hidden: int = 64
    seeds: int = 3
    chunk: int = 8


COMPARED = ("a2c", "ddqn", "evolution", "regularized_evolution", "random")
GROUPS = {  # at least the evaluations per run and seeds the issue asks for
    "fig6_h20": Group("bad_walker", "ddqn", 64, 160, hidden=20),  # 10,240 evaluations a run
    "fig6_h100": Group("bad_walker", "ddqn", 64, 160, hidden=100),
    "fig8": Group("constructor", "a2c", 256, 160),  # 40,960
    **{f"compare_{a}": Group("constructor", a, 128, 160) for a in COMPARED},  # 20,480
}
# The walking task's comparison (issue 44): 10 seeds a method at 50,000 PPO steps, where it
# separates Constructor bodies (results.md, "Bodies that walk"); 1,024 evaluations a run (32
# evolutions x 4 episodes of 8) fit 40 runs into 30 GPU-minutes. Drawn as compare_constructor_walk.
WALK_TRAIN_STEPS, WALK_DATA = 50_000, Path("docs/figures/reproduce_walk")
WALK_GROUPS = {f"compare_{a}": Group("constructor", a, 32, 32, seeds=10, chunk=4)
               for a in COMPARED}
UNROLLS = {"fig5": "fig6_h100", "fig7": "fig8"}  # a figure of greedy unrolls: its agents' group
STAGES = {  # a stage runs these groups and unrolls in turn; each group is a stage too
    "fig6_h20": ["fig6_h20"], "fig6_h100": ["fig6_h100"], "fig5": ["fig5"], "fig8": ["fig8"],
    "fig7": ["fig7"], "compare": [g for g in GROUPS if g.startswith("compare_")],
    **{g: [g] for g in GROUPS if g.startswith("compare_")},
}


def toy(g: Group) -> Group:
    """The CPU smoke's size: 2 seeds of 2 evolutions x 8 steps (an episode of either space)."""
    return dataclasses.replace(g, num_envs=2, steps=8, chunk=4, seeds=2, hidden=min(g.hidden, 20))


def setup_of(g: Group, args) -> Setup:
    return Setup(space=g.space, fitness="ppo", task=args.task, train_steps=args.train_steps,
                 num_envs=g.num_envs, steps=g.steps, chunk=g.chunk, hidden=g.hidden,
                 physics=args.physics)


def record(g: Group, args, seconds: float, **data) -> dict:
    """A run group's data file: what the figure is drawn from, with its settings and cost."""
    device = jax.devices()[0]
    return {
        "space": g.space, "agent": g.agent, "hidden": g.hidden, "seeds": g.seeds,
        "fitness": {"kind": "ppo", "train_steps": args.train_steps, "controllers": 1,
                    "inheritance": True},
        "task": args.task, "physics": args.physics,
        "device": f"{device.platform}: {device.device_kind}",
        "evaluations_per_run": g.num_envs * g.steps, "num_envs": g.num_envs, "steps": g.steps,
        "device_seconds": round(seconds, 1),
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "revision": revision(), **data,
    }


def group_key(base: int, name: str) -> jax.Array:
    """A group's own confirming key: `base` with the group's name folded in, so that no two
    groups (nor two runs of a group: each body takes its own splits) share a measurement."""
    return jax.random.fold_in(jax.random.PRNGKey(base), zlib.crc32(name.encode()))


def confirm(space, morphs: list, key, args) -> list[dict]:
    """`em.confirm` of each body in the order of `morphs`, each with keys of its own: equal
    bodies of two runs are measured apart (before issue 60 they shared one measurement)."""
    cfg = em.FitnessConfig(kind="ppo", task=em.make_task(args.task), physics=args.physics,
                           ppo=em.standard_ppo(args.train_steps, 1))
    found = em.confirm(space, em.stack(list(morphs)), key, cfg, args.confirm_controllers,
                       ranked=False)
    return [{"body": c.body, "mean": c.mean, "ci95": list(c.ci95), "controllers": len(c.values),
             "distance": float(c.distance.mean()), "upright": float(c.upright.mean()),
             "upright_whole": c.upright_whole} for c in found]


def run_group(name: str, g: Group, args, deadline: float) -> bool:
    """Runs (or resumes) group `name`; writes DATA/name.json when complete."""
    path = args.data / f"{name}.json"
    if path.exists():
        return True
    res = run_agent(g.agent, setup_of(g, args), g.seeds, resume=args.data / f"{name}.state",
                    deadline=deadline)
    if res is None:
        return False
    m, horizon, space = res["metrics"], res["horizon"], res["space"]
    data = {
        "returns": episode_returns(m["reward"], horizon).tolist(),  # (episodes, seeds)
        "best_fitness": m["best_fitness"].tolist(),  # (steps, seeds) best single draw so far
        "step_seconds": float(np.median(res["step_seconds"])),
        "horizon": horizon,
    }
    if "entropy" in m:
        data["entropy"] = m["entropy"].reshape(len(m["entropy"]), g.seeds, -1).mean(-1).tolist()
    settings = agent_config(run_config(g.agent, setup_of(g, args)), res["pipeline"].env)
    data["agent_settings"] = dataclasses.asdict(settings) if settings is not None else {}
    if name.startswith("compare_"):  # each run's returned body (its best single draw), confirmed
        data["returned"] = confirm(space, res["best_bodies"], group_key(11, name), args)
        data["confirm_keys"] = f"fold_in(PRNGKey(11), crc32({name!r})), a split a controller"
        data["returned_draw"] = res["best_fitness"].tolist()
    if name in UNROLLS.values():  # the trained agents, for the unroll figure
        keep = {"learner": res["states"].learner, "first": res["states"].first}
        (args.data / f"{name}.agents").write_bytes(pickle.dumps(jax.device_get(keep)))
    path.write_text(json.dumps(record(g, args, res["seconds"], **data), indent=1))
    print(f"{name}: done in {res['seconds']:.0f} s", flush=True)
    return True


def unroll(name: str, of: str, args) -> bool:
    """Greedy unrolls from m0 of every seed's trained agent in group `of`, each body
    confirmed; writes DATA/name.json."""
    path, agents = args.data / f"{name}.json", args.data / f"{of}.agents"
    if path.exists():
        return True
    if not agents.exists():
        print(f"{name} waits for {of}", flush=True)
        return False
    start = time.time()
    g = groups(args)[of]
    p = build(run_config(g.agent, setup_of(g, args)))
    trained = pickle.loads(agents.read_bytes())
    walk, evaluate = p.greedy_walk, p.greedy_evaluation  # as a run does
    unrolls = []
    for seed in range(g.seeds):
        learner, first = jax.tree.map(lambda x, s=seed: x[s], (trained["learner"],
                                                               trained["first"]))
        key = jax.random.PRNGKey(100 + seed)
        unrolls.append(evaluate(walk(learner, first, key), key))
    morphs = [m for u in unrolls for m in u.morphs]
    confirmed = iter(confirm(p.space, morphs, group_key(12, name), args))
    data = {"unrolls": [{"actions": u.actions,
                         "bodies": [next(confirmed) for _ in u.morphs],
                         # one fresh controller each (files before 2026-11-28 kept
                         # "inherited_fitness", the lineage's controllers)
                         "fresh_fitness": u.fitness} for u in unrolls],
            "confirm_controllers": args.confirm_controllers}
    path.write_text(json.dumps(record(g, args, time.time() - start, of=of, **data), indent=1))
    print(f"{name}: done in {time.time() - start:.0f} s", flush=True)
    return True


def groups(args) -> dict[str, Group]:
    """The run groups of --task: the source's, or the walking task's comparison; on another
    --space the comparison runs there, 5 seeds of --episodes episodes (the Crawler's, issue 47)."""
    chosen = {**GROUPS, **WALK_GROUPS} if args.task == "walk" else GROUPS
    horizon = em.make_space(args.space).default_horizon
    other = dict(space=args.space, seeds=5, steps=args.episodes * horizon)
    chosen = {k: dataclasses.replace(g, **other) if k.startswith("compare_") and args.space !=
              "constructor" else g for k, g in chosen.items()}
    return {k: toy(g) if args.toy else g for k, g in chosen.items()}


def compare_effects(runs: dict[str, dict]) -> dict:
    """The Constructor comparison's answer from its groups' data files (`runs`, by agent).

    Per agent: the confirmed fitness of each seed's returned body (`returned[i]["mean"]`, the
    mean of its confirming controllers) beside that body's best single draw in the run
    (`returned_draw`), and the mean over seeds with a 95% t-interval over seeds. Per pair: each
    agent minus evolution and minus random, with a 95% Welch t-interval over seeds (independent
    groups, variances not taken equal; `scipy.stats.ttest_ind(equal_var=False)`). Welch, not a
    bootstrap: with 3 seeds a bootstrap over seeds has at most 10 distinct resamples and too
    narrow an interval, and the data files keep each body's confirming controllers only as a
    mean and interval, so a bootstrap over them cannot be drawn from the files. The interval
    over seeds holds both the run-to-run spread and the confirming controllers' noise. Over
    all pairs at once: Holm's adjusted p, and intervals that hold together at 95% (Bonferroni:
    each Welch interval at 1 - 0.05 / the number of pairs; one clear of 0 is also significant
    after Holm, which rejects at least what Bonferroni does).
    """
    agents = {}
    for agent, r in runs.items():
        means = np.array([b["mean"] for b in r["returned"]])
        agents[agent] = {
            "confirmed": means.tolist(), "confirmed_ci95": [b["ci95"] for b in r["returned"]],
            "controllers": r["returned"][0]["controllers"], "returned_draw": r["returned_draw"],
            "mean": float(means.mean()), "ci95": list(t_interval(means)), "seeds": len(means),
        }
    differences, tests = {}, {}
    for ref in ("regularized_evolution", "evolution", "random"):
        for agent in agents:
            if ref not in agents or agent == ref or f"{ref} - {agent}" in differences:
                continue
            a, b = agents[agent]["confirmed"], agents[ref]["confirmed"]
            test = tests[f"{agent} - {ref}"] = scipy.stats.ttest_ind(a, b, equal_var=False)
            ci = test.confidence_interval(0.95)
            differences[f"{agent} - {ref}"] = {
                "difference": float(np.mean(a) - np.mean(b)), "ci95": [float(ci.low),
                                                                       float(ci.high)],
                "df": float(test.df), "p": float(test.pvalue)}
    holm(differences)
    for pair, test in tests.items():
        ci = test.confidence_interval(1 - 0.05 / len(tests))
        differences[pair]["ci95_simultaneous"] = [float(ci.low), float(ci.high)]
    return {"agents": agents, "differences": differences,
            "interval": "agents: 95% t over seeds; differences: 95% Welch t over seeds, "
                        "p Holm-adjusted over all of them (p_holm), and intervals that hold "
                        "together at 95% (ci95_simultaneous: Bonferroni, each at 1 - 0.05 / "
                        "the number of differences)"}


def unroll_bodies(space, unroll: dict) -> list:
    """The bodies of a recorded greedy unroll (`{"actions": ["node 0: add_leg_start", ...],
    "bodies": [{"body": canonical name}, ...]}`), m0 first, by replaying its mutations.

    Raises:
      ValueError: a replayed body's canonical name differs from the recorded one.
    """
    bodies = [space.initial()]
    for action, recorded in zip(unroll["actions"], unroll["bodies"][1:], strict=True):
        node, mutation = action.removeprefix("node ").removesuffix(NO_OP).split(": ")
        bodies.append(space.mutate(bodies[-1], int(node), space.mutation_names.index(mutation)))
        if space.canonical(bodies[-1]) != recorded["body"]:
            raise ValueError(f"after {action!r} the body is {space.canonical(bodies[-1])}, "
                             f"not the recorded {recorded['body']}")
    return bodies


def draw_unrolls(r: dict, title: str):
    """Figures 5 and 7: each seed's greedy unroll as its confirmed fitness (top) and as its
    bodies, one row a seed, each drawn with its confirmed mean (as the source draws them)."""
    space, unrolls = em.make_space(r["space"]), r["unrolls"]
    n = max(len(u["bodies"]) for u in unrolls)
    fig = plt.figure(figsize=(max(6.0, 1.5 * n), 3.4 + 1.0 * len(unrolls)))
    grid = fig.add_gridspec(1 + len(unrolls), n, height_ratios=[3.4] + [1.0] * len(unrolls))
    ax = fig.add_subplot(grid[0, :])
    for i, u in enumerate(unrolls):
        mean = [b["mean"] for b in u["bodies"]]
        lo = [b["mean"] - b["ci95"][0] for b in u["bodies"]]
        ax.errorbar(np.arange(len(mean)) + 0.05 * i, mean, yerr=lo, marker="o",
                    capsize=3, label=f"seed {i}")
    ax.set(title=f"{title}:\ngreedy unroll, confirmed fitness", xlabel="mutation",
           ylabel=f"mean of {r['confirm_controllers']}\nfresh controllers, 95% CI")
    ax.legend(fontsize=8)
    cells = [[fig.add_subplot(grid[1 + i, j]) for j in range(len(u["bodies"]))]
             for i, u in enumerate(unrolls)]
    fig.tight_layout()  # settle the axes' sizes before drawing in data units
    for i, (u, row) in enumerate(zip(unrolls, cells)):
        for j, (cell, m, b) in enumerate(zip(row, unroll_bodies(space, u), u["bodies"])):
            plots.draw_morphology(cell, space, m)
            cell.set_title(f"seed {i}: " * (j == 0) + f"{b['mean']:.3g}", fontsize=8)
    return fig


def draw_compare(runs: dict[str, dict], out: Path) -> None:
    """RL against evolution (`runs`: compare_METHOD): each run's confirmed body, the
    differences of the means, and each returned body's draw against its confirmation."""
    effects = compare_effects(runs)
    fig, (ax_m, ax_d, ax_g) = plt.subplots(1, 3, figsize=(15, 4.2),
                                           gridspec_kw={"width_ratios": [4, 4, 3]})
    colors = {agent: f"C{i}" for i, agent in enumerate(effects["agents"])}
    for i, (agent, e) in enumerate(effects["agents"].items()):
        spread = 0.45 * np.arange(e["seeds"]) / max(e["seeds"] - 1, 1)  # left of the mean
        x, y = i - 0.4 + spread, np.asarray(e["confirmed"])
        lo, hi = np.asarray(e["confirmed_ci95"]).T
        ax_m.errorbar(x, y, yerr=[y - lo, hi - y],
                      fmt="o", ms=4, capsize=2, color=colors[agent], alpha=0.6)
        ax_m.errorbar(i + 0.2, e["mean"], fmt="s", ms=7, capsize=5, color="k",
                      yerr=[[e["mean"] - e["ci95"][0]], [e["ci95"][1] - e["mean"]]])
        ax_g.plot([i - 0.15, i + 0.15], [e["returned_draw"], e["confirmed"]], "-o", ms=4,
                  color=colors[agent], alpha=0.7)
    short = lambda text: text.replace("regularized_evolution", "reg. evol.")  # noqa: E731
    names = [short(n) for n in effects["agents"]]
    ax_m.set_xticks(range(len(names)), names)
    ax_m.set_title("each run's returned body, confirmed (colour);\n"
                   "mean over seeds with 95% t-CI (black)", fontsize=10)
    ax_m.set(ylabel=f"mean of {e['controllers']} fresh controllers (95% CI)")
    for j, d in enumerate(effects["differences"].values()):
        lo, hi = d["difference"] - d["ci95"][0], d["ci95"][1] - d["difference"]
        ax_d.errorbar(j, d["difference"], yerr=[[lo], [hi]], fmt="s", capsize=5, color="k")
    ax_d.axhline(0.0, color="0.5", lw=0.8)
    ax_d.set_xticks(range(len(effects["differences"])),
                    [short(d) for d in effects["differences"]], rotation=30, fontsize=8,
                    ha="right")
    ax_d.set_title("difference of the means over seeds,\n95% Welch t-CI (none holds "
                   "after Holm)" if not any(d["significant_holm"] for d in
                                             effects["differences"].values())
                   else "difference of the means over seeds,\n95% Welch t-CI", fontsize=10)
    ax_d.set(ylabel="confirmed fitness difference")
    ax_g.set_xticks(range(len(names)), names)
    ax_g.set_yscale("log")
    ax_g.set_title("each run's returned body: its best single draw\nin the run (left), "
                   "its confirmed mean (right)", fontsize=10)
    ax_g.set(ylabel="fitness of the returned body")
    first = next(iter(runs.values()))
    task, space = first.get("task", "distance"), first.get("space", "constructor")
    default = WALK_TRAIN_STEPS if task == "walk" else TRAIN_STEPS
    steps = first.get("fitness", {}).get("train_steps", default)
    fig.suptitle(f"{space.title()}, {task} task, {first['evaluations_per_run']:,} evaluations "
                 f"a run of {steps:,} PPO steps: RL against evolution and random walks",
                 fontsize=10)
    name = f"compare_{space}" + ("" if task == "distance" else f"_{task}")
    if steps != default:  # another budget than the task's, said in the name: _20k, _320
        name += f"_{steps // 1000}k" if steps % 1000 == 0 else f"_{steps}"
    save(fig, out, name, {"task": task, "effects": effects, "runs": runs})


def draw(data: Path, out: Path) -> None:
    """The figures from the data files present."""
    load = lambda n: json.loads((data / f"{n}.json").read_text())  # noqa: E731
    have = {p.stem for p in data.glob("*.json")}
    if {"fig6_h20", "fig6_h100"} & have:
        fig, (ax_r, ax_b) = plt.subplots(1, 2, figsize=(10, 3.6))
        runs = {n: load(n) for n in ("fig6_h20", "fig6_h100") if n in have}
        for r in runs.values():
            ret, best = np.asarray(r["returns"]), np.asarray(r["best_fitness"])
            band(ax_r, np.arange(1, len(ret) + 1), ret, f"hidden {r['hidden']}")
            band(ax_b, r["num_envs"] * np.arange(1, len(best) + 1), best, f"hidden {r['hidden']}")
        ax_r.set(title="Double-DQN, Bad Walker, NGE fitness", xlabel="episode",
                 ylabel="episode return (f_k - f_0)")
        ax_b.set(title="best single draw so far", xlabel="fitness evaluations per run")
        ax_r.legend()
        save(fig, out, "fig6_ddqn_hidden",
             {"task": next(iter(runs.values())).get("task", "distance"), **runs})
    for name, title in (("fig5", "Double-DQN (width 100), Bad Walker"),
                        ("fig7", "actor-critic, Constructor")):
        if name in have:
            r = load(name)
            save(draw_unrolls(r, title), out, name + "_unroll", r)
    if "fig8" in have:
        r = load("fig8")
        fig, (ax_r, ax_e) = plt.subplots(1, 2, figsize=(10, 3.6))
        ret, ent = np.asarray(r["returns"]), np.asarray(r["entropy"])
        band(ax_r, np.arange(1, len(ret) + 1), ret, "actor-critic")
        band(ax_e, r["num_envs"] * np.arange(1, len(ent) + 1), ent, "actor-critic")
        ax_r.set(title="actor-critic, Constructor, NGE fitness", xlabel="episode",
                 ylabel="episode return (f_k - f_0)")
        ax_e.set(title="policy entropy", xlabel="fitness evaluations per run")
        save(fig, out, "fig8_a2c_constructor", r)
    runs = {n[len("compare_"):]: load(n) for n in sorted(have) if n.startswith("compare_")}
    if runs:
        draw_compare(runs, out)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add = parser.add_argument
    add("--stages", nargs="+", default=[], help=f"all, or of {', '.join(STAGES)}")
    add("--physics", default="jax", help="the fitness's engine: jax | warp")
    add("--train-steps", type=int, help=f"PPO steps per evaluation (the source's "
        f"{TRAIN_STEPS:,}; on the walking task {WALK_TRAIN_STEPS:,})")
    add("--task", default="distance", choices=em.list_tasks(),
        help="the PPO fitness's task: distance (the source's, the shipped figures) or walk")
    add("--confirm-controllers", type=int, default=32, help="controllers confirming a body")
    add("--budget", type=float, default=480,
        help="seconds: start no chunk after this (a device call's limit, less a margin)")
    add("--space", default="constructor", help="the comparison's space (crawler: issue 47)")
    add("--episodes", type=int, default=4, help="on another --space: episodes a run")
    add("--data", type=Path, help="the data files (docs/figures/reproduce, and "
        "reproduce_walk for the walking task, reproduce_SPACE on another space)")
    add("--out", type=Path, default=Path("docs/figures"), help="the figures")
    add("--toy", action="store_true", help="the CPU smoke's size (and 320 PPO steps)")
    add("--draw", action="store_true", help="draw the figures from the data files")
    args = parser.parse_args(argv)
    stages = list(STAGES) if "all" in args.stages else args.stages
    if unknown := [s for s in stages if s not in STAGES]:
        parser.error(f"unknown stages {unknown}; choose from all, {', '.join(STAGES)}")
    walk = args.task == "walk"
    args.train_steps = args.train_steps or (WALK_TRAIN_STEPS if walk else TRAIN_STEPS)
    default = WALK_DATA if walk else Path("docs/figures/reproduce")
    args.data = args.data or (default if args.space == "constructor" else
                              Path(f"docs/figures/reproduce_{args.space}"))
    if args.toy:
        args.train_steps, args.confirm_controllers = 320, 2
    full_precision()  # as the run command
    deadline = time.time() + args.budget
    args.data.mkdir(parents=True, exist_ok=True)
    done = True
    names = [name for stage in stages for name in STAGES[stage]]
    for i, name in enumerate(names):  # past the deadline no other group starts (a start
        if i and time.time() > deadline:  # compiles and evaluates m0)
            done = False
            break
        if name in UNROLLS:
            done &= unroll(name, UNROLLS[name], args)
        else:
            done &= run_group(name, groups(args)[name], args, deadline)
    print("every stage asked for is done" if done else "not done: run the same command again",
          flush=True)
    if args.draw:
        draw(args.data, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
