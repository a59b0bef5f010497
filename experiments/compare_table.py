"""RL against evolution on a landscape table: which method returns the better body?

Every registered agent (Double-DQN, QR-DQN, actor-critic, evolution, random walks) runs --seeds
times on the `table` fitness of --space, each run --num-envs parallel evolutions x --steps
steps (num_envs x steps fitness evaluations per run), at each K of --ks (the fitness of a body
is the mean of K of its stored results, drawn anew at every evaluation). The seeds of a
(method, K) run together under `jax.vmap` in this script's own loop (it tallies each chunk's
children by table row between chunks); it builds its own `RunConfig` because it sets K, the
exploration schedule and the chunk.

The measure is the true fitness (the table's mean over all its results) of the body each run
returns, its regret to the table's best body and its rank (1 = best), under two rules for what
a run returns: "draw", the body of the highest single evaluation seen (the agent state's
`best_morph`), and "confirmed", `run`'s confirm stage on the run's own draws (the --confirm
bodies of the highest mean over the run's evaluations, ties to the more evaluated, each
evaluated afresh as the mean of --confirm-draws results drawn from the table; the best of
those; its cost, confirm x confirm-draws results, is not counted in the run's evaluations). A
regret is also judged against what the table can tell apart: the bodies whose difference to
the table's best has a bootstrap 95% interval (over each body's results) containing 0. Also
kept: the true fitness of the best body each run ever evaluated (what it found, whether or not
it returned it), and the number of distinct bodies it evaluated. Per method, K and rule: median
and mean regret with bootstrap 95% intervals over seeds; pairwise, each RL agent against
evolution and against random (and plain DQN against Double-DQN): the
difference of mean true fitness with bootstrap 95% intervals, over seeds alone (the table's
means taken as exact) and over seeds and the table's results (the means are estimates of S
results each), and P(a seed of A beats a seed of B). Wall-clock: the vmapped batch of all seeds
on this machine, compilation apart.

Results are saved per (method, K) in OUT/compare_table_SPACE.json after each one; run again
with the same flags to resume (finished pairs with the same settings are kept).

  python -m experiments.compare_table --out docs/figures                      # the full run
  python -m experiments.compare_table --steps 20 --seeds 2 --ks 1 --out /tmp/ct  # smoke
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
import zlib
from pathlib import Path

import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

import evojax_morph as em
from evojax_morph.agents import list_agents, predictor
from evojax_morph.fitnesses import FitnessConfig
from evojax_morph.fitnesses import table as table_fitness
from evojax_morph.search.pipeline import RunConfig, agent_config, build
from evojax_morph.spaces import make_space
from experiments.common import agent_overrides, band, save
from experiments.table_stats import stats, table_lines

CONFIRM_SEED = 1_000_003  # the confirming draws' key (the runs use PRNGKey(0))
EARLY = 2_000  # evaluations a run at which the confirmed rule is also taken


@dataclasses.dataclass(frozen=True)
class Settings:
    space: str = "bad_walker"
    table: str = ""  # "": the space's packaged table
    num_envs: int = 16  # parallel evolutions per run: evaluations per step
    steps: int = 625  # environment steps per run
    chunk: int = 25  # steps per jitted call; the curve has one point per chunk
    hidden: int = 64
    explore_steps: int = 250  # (qr)dqn: epsilon anneals 1 -> 0.05 over these steps
    learning_starts: int = 256  # (qr)dqn: transitions stored before learning
    seeds: int = 10
    confirm: int = 8  # the confirmed rule: bodies re-evaluated at the end of a run
    confirm_draws: int = 32  # results drawn from the table for each
    # {method: {field: value}} over its config: JSON, or a frozen settings file
    # (experiments/frozen_settings.json: its "settings", tuned on its "tuning_table")
    agent_settings: str = ""
    tag: str = ""  # appended to the data file's name (a tuning variant's)


def rows_fn(sigs: np.ndarray):
    """Jitted: (..., max_nodes) bodies -> (...,) int32 row of the table (every body an agent
    meets from m0 is in it: the table checks that when loaded)."""
    sigs = jnp.asarray(sigs)

    def row(m):
        return jnp.argmax((sigs == table_fitness.signature(m)).all(-1)).astype(jnp.int32)

    def rows(morphs):
        lead = morphs.active.shape[:-1]
        flat = jax.tree.map(lambda x: x.reshape((-1,) + x.shape[len(lead):]), morphs)
        return jax.vmap(row)(flat).reshape(lead)

    return rows


def confirm_keys(method: str, k: int, evaluations: int, seeds: int) -> jax.Array:
    """(seeds,) keys of each run's confirmation, its own: the method, K, the budget and the
    seed folded into CONFIRM_SEED, so no two runs share a measurement of a body."""
    key = jax.random.PRNGKey(CONFIRM_SEED)
    for part in (zlib.crc32(method.encode()), k, evaluations):
        key = jax.random.fold_in(key, part)
    return jax.vmap(lambda i: jax.random.fold_in(key, i))(jnp.arange(seeds))


def confirm_rows(visits, sums, s: Settings, space, table, cfg, keys) -> tuple[np.ndarray,
                                                                             np.ndarray]:
    """The confirmed rule: per seed, the `s.confirm` bodies of the highest mean over the run's
    own evaluations (ties to the more evaluated, then the lower row), each the mean of
    `s.confirm_draws` fresh results drawn from the table (the table fitness at K =
    confirm_draws), with the run's own key (`confirm_keys`); the best of them.

    Args:
      visits, sums: (seeds, T) evaluations of each row in each run and their fitness sum.
      keys: (seeds,) the runs' confirming keys.
    Returns:
      (seeds,) rows returned and (seeds,) their confirming means.
    """
    mean = np.where(visits > 0, sums / np.maximum(visits, 1), -np.inf)
    order = np.lexsort((np.arange(mean.shape[1])[None].repeat(len(mean), 0), -visits, -mean))
    cand = order[:, : s.confirm]  # (seeds, n), lexsort sorts by its last key first
    cand = np.where(np.take_along_axis(visits, cand, 1) > 0, cand, cand[:, :1])
    bodies = jax.tree.map(lambda x: x[cand.reshape(-1)], table.bodies)
    confirm_cfg = dataclasses.replace(cfg, ppo=dataclasses.replace(
        cfg.ppo, controllers=s.confirm_draws))
    per_run = jax.tree.map(lambda x: x.reshape(cand.shape + x.shape[1:]), bodies)
    means = np.stack([np.asarray(em.evaluate(space, jax.tree.map(lambda x, i=i: x[i], per_run),
                                             key, confirm_cfg).fitness)
                      for i, key in enumerate(keys)])
    pick = means.argmax(1)
    return cand[np.arange(len(cand)), pick], means[np.arange(len(cand)), pick]


def pipeline(method: str, k: int, s: Settings):
    """(the run's pipeline of `method` on the table at K = `k`, its agent's config): the run's
    defaults resolved, then --agent-settings' overrides."""
    cfg = RunConfig(space=s.space, fitness="table", table=s.table, agent=method,
                    num_envs=s.num_envs, controllers=k, hidden=s.hidden,
                    explore_steps=s.explore_steps, learning_starts=s.learning_starts)
    env = build(dataclasses.replace(cfg, agent="random")).env
    agent_cfg = agent_config(cfg, env)
    overrides = agent_overrides(s.agent_settings)[0].get(method, {})
    agent_cfg = dataclasses.replace(agent_cfg, **overrides) if overrides else agent_cfg
    return build(cfg, agent_cfg=agent_cfg), agent_cfg


def run_method(method: str, k: int, s: Settings, true: np.ndarray, sigs, table,
               save_ensemble: str = "") -> dict:
    """`s.seeds` runs of `method` at K = `k`, vmapped; the rows of the bodies they return. With
    `save_ensemble` (the predictor), the first seed's trained ensemble is saved there
    (`predictor.save_ensemble`: what `transfer` starts another run from)."""
    p, agent_cfg = pipeline(method, k, s)
    rows = rows_fn(sigs)

    def step(state, n):
        state, m = p.agent.chunk(state, n)
        # the rows of every child evaluated (n, N) with its fitness, and of the returned body
        return state, rows(m["bodies"]["morph"]), m["fitness"], rows(state.best_morph)

    keys = jax.random.split(jax.random.PRNGKey(0), s.seeds)
    start = time.perf_counter()
    states = jax.block_until_ready(jax.jit(jax.vmap(p.agent.init))(keys))
    init_s = time.perf_counter() - start
    fns = {}
    done, curve, seconds, compile_s = 0, [], 0, 0
    visits, sums = np.zeros((s.seeds, len(true)), int), np.zeros((s.seeds, len(true)))
    early = None  # the confirmed rule at EARLY evaluations a run
    while done < s.steps:
        if early is None and done * s.num_envs >= EARLY:
            early = confirm_rows(visits, sums, s, p.space, table, p.fitness,
                                 confirm_keys(method, k, done * s.num_envs, s.seeds))
            early = {"evaluations": done * s.num_envs, "rows": early[0].tolist()}
        n = min(s.chunk, s.steps - done)
        if n not in fns:  # compile outside the clock
            start = time.perf_counter()
            fns[n] = jax.jit(jax.vmap(lambda st, n=n: step(st, n))).lower(states).compile()
            compile_s += time.perf_counter() - start
        start = time.perf_counter()
        states, child_rows, fitness, best_rows = jax.block_until_ready(fns[n](states))
        seconds += time.perf_counter() - start
        fitness = np.asarray(fitness).reshape(s.seeds, -1)
        for i, r in enumerate(np.asarray(child_rows).reshape(s.seeds, -1)):
            visits[i] += np.bincount(r, minlength=len(true))
            sums[i] += np.bincount(r, fitness[i], minlength=len(true))
        curve.append(true[np.asarray(best_rows)].tolist())
        done += n
    if save_ensemble:
        predictor.save_ensemble(save_ensemble, jax.tree.map(lambda x: x[0], states.learner))
    best_rows, top = np.asarray(best_rows), np.argsort(-true)[:5]
    confirmed, confirmed_mean = confirm_rows(visits, sums, s, p.space, table, p.fitness,
                                             confirm_keys(method, k, s.steps * s.num_envs,
                                                          s.seeds))
    return {
        "true_fitness": true[best_rows].tolist(),  # (seeds,) the returned body's table mean
        "best_rows": best_rows.tolist(),
        "confirmed_true_fitness": true[confirmed].tolist(),  # the same, the confirmed rule
        "confirmed_rows": confirmed.tolist(),
        "confirmed_mean": confirmed_mean.tolist(),  # the confirming draws' mean
        "confirmed_early": early,  # the confirmed rule's rows at EARLY evaluations a run
        "agent_settings": dataclasses.asdict(agent_cfg) if agent_cfg is not None else {},
        "in_run_fitness": np.asarray(states.best_fitness).tolist(),  # the draw that chose it
        "best_visited": [float(true[v > 0].max()) for v in visits],  # best body evaluated
        "distinct_bodies": (visits > 0).sum(1).tolist(),
        "top_rows": top.tolist(),  # the table's 5 best bodies, best first
        "top_visits": visits[:, top].tolist(),  # (seeds, 5) evaluations of each
        "curve": curve,  # (chunks, seeds) true fitness of the best-so-far body
        "seconds": seconds,  # all seeds together, compiled steps only
        "compile_seconds": compile_s,
        "init_seconds": init_s,
    }


def freeze(data: Path, out: Path) -> dict:
    """The frozen settings: per method, of its tuning runs in `data` (compare_table files of
    one table, seeds and budget, a setting each: --tag tune_NAME), the setting of the lowest
    mean regret under the confirmed rule; written to `out` with every candidate's regret and
    the table they were tuned on, for --agent-settings of the held-out runs."""
    runs = [json.loads(f.read_text()) for f in sorted(data.glob("compare_table_*tune_*.json"))]
    tables = {(r["settings"]["space"], r["settings"]["table"], r["settings"]["seeds"],
               r["evaluations_per_run"]) for r in runs}
    if len(tables) != 1:
        raise SystemExit(f"--freeze: the tuning runs must share a table, seeds and budget: "
                         f"{sorted(tables)}")
    candidates: dict[str, list] = {}
    for r in runs:
        for k, by in r["stats"].items():
            if not k.isdigit():
                continue
            for method, st in by["confirmed"].items():
                if "-" in method:
                    continue
                spec = Settings(**r["settings"]).agent_settings
                overrides = agent_overrides(spec)[0].get(method, {})
                candidates.setdefault(method, []).append(
                    {"tag": r["settings"]["tag"], "overrides": overrides, "k": int(k),
                     "mean_regret": st["mean_regret"], "tied": st["indistinguishable"]})
    space, table, seeds, evaluations = tables.pop()
    frozen = {
        "tuning_table": f"{space}" + (f" ({table})" if table else " (packaged)"),
        "protocol": f"each method's settings (its defaults and the others listed) x {seeds} "
                    f"seeds x {evaluations} evaluations on the tuning table; the lowest mean "
                    "regret of the confirmed rule kept, frozen before any held-out run",
        "date": time.strftime("%Y-%m-%d", time.gmtime()),
        "candidates": candidates,
        "settings": {m: min(c, key=lambda x: x["mean_regret"][0])["overrides"]
                     for m, c in candidates.items()},
    }
    out.write_text(json.dumps(frozen, indent=1) + "\n")
    return frozen


def settings_parser(doc: str) -> argparse.ArgumentParser:
    """A parser of `doc` with a flag per `Settings` field (`settings_from` reads them back)."""
    parser = argparse.ArgumentParser(description=doc,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    for f in dataclasses.fields(Settings):
        parser.add_argument("--" + f.name.replace("_", "-"), type=type(f.default),
                            default=f.default)
    return parser


def settings_from(args) -> Settings:
    return Settings(**{f.name: getattr(args, f.name) for f in dataclasses.fields(Settings)})


def parse_args(argv=None):
    parser = settings_parser(__doc__)
    parser.add_argument("--ks", type=int, nargs="+", default=[1, 4, 16])
    parser.add_argument("--methods", default=",".join(list_agents()),
                        help="comma-separated subset of " + ",".join(list_agents()))
    parser.add_argument("--out", default="runs/figures")
    parser.add_argument("--save-ensemble", default="",
                        help="PATH.npz: the predictor's first seed's trained ensemble, for "
                        "another run's transfer setting (at the last K run)")
    parser.add_argument("--swap-in", default="",
                        help="a tuning variant's data file (--tag): print the statistics with "
                        "its methods' runs in place of this file's, at the K both hold; no run")
    parser.add_argument("--freeze", default="",
                        help="a folder of tuning runs (--tag tune_NAME): write each method's "
                        "best setting to --out (a .json for --agent-settings); no run")
    return parser.parse_args(argv)


def data_name(s: Settings) -> str:
    """The data file's name (no suffix): compare_table_SPACE, _walk for a walking table, _TAG."""
    name = f"compare_table_{s.space}" + (f"_{Path(s.table).stem.split('_')[-1]}" if s.table
                                         else "")  # a walking table: _walk
    return name + (f"_{s.tag}" if s.tag else "")


def start_summary(s: Settings, space, table, path: Path) -> dict:
    """The data file's header, with the results of `path` kept when its settings are `s`'s."""
    true = table.mean()
    summary = {"settings": dataclasses.asdict(s), "task": table.task,
               "evaluations_per_run": s.num_envs * s.steps,
               "table": {"path": str(table_fitness.table_path(space, FitnessConfig(
                   table=s.table))), "meta": table.meta, "best": float(true.max()),
                   "best_body": table.names[int(true.argmax())]},
               "device": f"{jax.default_backend()}: {jax.devices()[0].device_kind}",
               # the tuning table and protocol, if frozen
               "tuning": agent_overrides(s.agent_settings)[1],
               "results": {}}
    if path.exists():
        old = json.loads(path.read_text())
        if old.get("settings") == summary["settings"]:
            summary["results"] = old.get("results", {})
            print("resuming: kept", {k: list(v) for k, v in summary["results"].items()}, flush=True)
    return summary


def run_missing(args, s: Settings, summary: dict, path: Path, sigs, table) -> None:
    """Each (K, method) of `args` not yet in `summary`, saved to `path` after each."""
    true = table.mean()
    for k in args.ks:
        for method in args.methods.split(","):
            if method not in list_agents():
                raise SystemExit(f"unknown method {method!r}; choose from {list_agents()}")
            if method in summary["results"].get(str(k), {}):
                continue
            start = time.time()
            res = run_method(method, k, s, true, sigs, table,
                             args.save_ensemble if method == "predictor" else "")
            res["date"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
            res["device"] = summary["device"]  # a file resumed elsewhere holds runs of both
            summary["results"].setdefault(str(k), {})[method] = res
            print(f"K={k} {method}: median true fitness {np.median(res['true_fitness']):.1f}, "
                  f"{res['seconds']:.1f} s + {res['compile_seconds']:.1f} s compiling "
                  f"({time.time() - start:.0f} s in all)", flush=True)
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(json.dumps(summary, indent=1))


def draw(summary: dict, s: Settings, table, out: Path, name: str) -> None:
    """The best-so-far body's true fitness against evaluations, a panel per K, saved with
    `summary` as OUT/NAME (.png, .json)."""
    true = table.mean()
    ks = sorted((k for k in summary["results"] if summary["results"][k]), key=int)
    fig, axes = plt.subplots(1, len(ks), figsize=(max(4.2 * len(ks), 7.0), 4.0), sharey=True,
                             squeeze=False)
    for ax, k in zip(axes[0], ks):
        for method, r in summary["results"][k].items():
            curve = np.asarray(r["curve"])
            x = s.num_envs * np.minimum(s.chunk * np.arange(1, len(curve) + 1), s.steps)
            line = band(ax, x, curve, method)
            confirmed = np.median(r["confirmed_true_fitness"])  # the confirmed rule's return
            ax.plot(x[-1], confirmed, "x", ms=8, color=line.get_color())
        ax.axhline(true.max(), color="k", lw=0.8, ls=":")
        ax.set(title=f"K = {k}", xlabel="fitness evaluations per run")
    axes[0][0].set(ylabel="true fitness of the body returned")
    axes[0][0].legend(fontsize=8)
    which = f"{s.space} table" + (f" ({table.task})" if s.table else "")
    fig.suptitle(f"{which}, {s.seeds} seeds: the best-so-far body's median, .25-.75 band\n"
                 "(x: the confirmed rule's median at the end)", fontsize=10)
    save(fig, out, name, summary)


def main():
    args = parse_args()
    if args.freeze:
        frozen = freeze(Path(args.freeze), Path(args.out))
        print(json.dumps(frozen["settings"], indent=1))
        return
    s = settings_from(args)
    space = make_space(s.space)
    table, sigs = table_fitness.load(space, FitnessConfig(kind="table", table=s.table))
    out, name = Path(args.out), data_name(s)
    path = out / f"{name}.json"
    summary = start_summary(s, space, table, path)
    run_missing(args, s, summary, path, sigs, table)
    if args.swap_in:  # a tuned variant against the others' runs: printed, nothing written
        variant = json.loads(Path(args.swap_in).read_text())["results"]
        swapped = {k: {**by, **variant.get(k, {})} for k, by in summary["results"].items()}
        print(f"with the runs of {args.swap_in} swapped in:")
        print("\n".join(table_lines({**summary, "results": swapped,
                                     "stats": stats(swapped, table.fitness)})))
        return
    summary["stats"] = stats(summary["results"], table.fitness)
    print("\n".join(table_lines(summary)))
    draw(summary, s, table, out, name)

if __name__ == "__main__":
    main()
