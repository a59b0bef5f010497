"""Why do the learned agents fail on a table? What their scores know of the truth, as they train.

On a landscape table every body's true fitness is known (its mean over the table's results), so
an agent's scores of a state's actions (`Agent.scores`: Double-DQN's Q-values, the
actor-critic's logits, the predictor's predicted child fitness) can be held against what each
action really does: the true fitness change of the child, true(child) - true(parent). Per
method, --seeds runs of --num-envs evolutions x --steps steps at K = --k (compare_table's
settings, their defaults resolved the same way), and after each chunk of --chunk steps, over
the runs' current parents:

- rank agreement: Spearman's rho between the scores of a parent's valid actions and their
  children's true fitness change, averaged over parents (0: the scores know nothing of which
  mutation is better; Q-values also carry what follows, so 1 is not their target, but a
  greedy step should still prefer the better child);
- the true fitness change of the action the agent took (its children's, minus their parents');
- the distinct bodies evaluated so far (exploration), and the share of a chunk's evaluations
  that are revisits of a body evaluated before in the run.

  python -m experiments.diagnose_agents --table docs/landscapes/length_walker_walk.npz \\
      --out docs/figures                                                     # 10 seeds, 10,000
  python -m experiments.diagnose_agents --steps 20 --chunk 10 --seeds 2 --out /tmp/d  # smoke
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np
from scipy.stats import spearmanr

from evojax_morph.fitnesses import FitnessConfig
from evojax_morph.fitnesses import table as table_fitness
from evojax_morph.spaces import make_space
from experiments.common import agent_overrides, band, save
from experiments.compare_table import (
    Settings,
    pipeline,
    rows_fn,
    settings_from,
    settings_parser,
)


def children_rows(space, rows, obs):
    """(N, A) the table row of every action's child of each parent, -1 where masked."""
    nm = space.num_mutations
    actions = jnp.arange(obs.mask.shape[-1])
    kids = jax.vmap(lambda m: jax.vmap(lambda a: space.mutate(m, a // nm, a % nm))(actions))(
        obs.morph)
    return jnp.where(obs.mask, rows(kids), -1)


def rank_agreement(scores: np.ndarray, kid_rows: np.ndarray, parent_rows: np.ndarray,
                   true: np.ndarray) -> float:
    """Mean over parents of Spearman(scores, true change) over the valid actions whose children
    differ in true fitness (a parent with fewer than 3 such actions is left out)."""
    rhos = []
    for s, kids, parent in zip(scores, kid_rows, parent_rows):
        ok = kids >= 0
        change = true[kids[ok]] - true[parent]
        if ok.sum() >= 3 and np.ptp(change) > 0 and np.ptp(s[ok]) > 0:
            rhos.append(spearmanr(s[ok], change)[0])
    return float(np.mean(rhos)) if rhos else float("nan")


def diagnose(method: str, s: Settings, k: int, true: np.ndarray, sigs) -> dict:
    p, agent_cfg = pipeline(method, k, s)
    rows = rows_fn(sigs)
    space = p.space

    def chunk(state):
        state, m = p.agent.chunk(state, s.chunk)
        obs = p.env.observe(state.evo)
        scores = p.agent.scores(state.learner, obs)
        return (state, rows(m["bodies"]["morph"]), rows(m["bodies"]["parent"]), scores,
                children_rows(space, rows, obs), rows(state.evo.morph))

    keys = jax.random.split(jax.random.PRNGKey(0), s.seeds)
    states = jax.jit(jax.vmap(p.agent.init))(keys)
    step = jax.jit(jax.vmap(chunk))
    seen = [set() for _ in range(s.seeds)]
    out = {"evaluations": [], "rank_agreement": [], "taken_change": [], "distinct": [],
           "revisits": [], "agent_settings": dataclasses.asdict(agent_cfg)}
    start = time.perf_counter()
    for done in range(s.chunk, s.steps + 1, s.chunk):
        states, *found = step(states)
        kids, parents, scores, kid_rows, parent_rows = map(np.asarray, jax.device_get(found))
        agree, taken, distinct, revisit = [], [], [], []
        for i in range(s.seeds):
            agree.append(rank_agreement(scores[i], kid_rows[i], parent_rows[i], true))
            taken.append(float(np.mean(true[kids[i]] - true[parents[i]])))
            flat = kids[i].reshape(-1)
            revisit.append(float(np.mean([r in seen[i] for r in flat])))
            seen[i].update(flat.tolist())
            distinct.append(len(seen[i]))
        out["evaluations"].append(done * s.num_envs)
        for name, v in (("rank_agreement", agree), ("taken_change", taken),
                        ("distinct", distinct), ("revisits", revisit)):
            out[name].append(v)  # (chunks, seeds)
    out["seconds"] = time.perf_counter() - start
    return out


def main():
    parser = settings_parser(__doc__)
    parser.add_argument("--k", type=int, default=1)
    parser.add_argument("--methods", default="ddqn,a2c,predictor")
    parser.add_argument("--out", default="runs/figures")
    parser.set_defaults(space="length_walker")
    args = parser.parse_args()
    s = settings_from(args)
    space = make_space(s.space)
    table, sigs = table_fitness.load(space, FitnessConfig(kind="table", table=s.table))
    true = table.mean()
    name = f"diagnose_{s.space}" + (f"_{Path(s.table).stem.split('_')[-1]}" if s.table else "")
    summary = {"settings": dataclasses.asdict(s), "k": args.k, "task": table.task,
               "device": f"{jax.default_backend()}: {jax.devices()[0].device_kind}",
               "tuning": agent_overrides(s.agent_settings)[1], "methods": {}}
    for method in args.methods.split(","):
        r = summary["methods"][method] = diagnose(method, s, args.k, true, sigs)
        last = lambda key, r=r: np.nanmean(r[key][-1])  # noqa: E731
        print(f"{method}: rank agreement {last('rank_agreement'):.2f} at the end, taken change "
              f"{last('taken_change'):.1f}, distinct bodies {last('distinct'):.0f}, revisits "
              f"{last('revisits'):.2f} ({r['seconds']:.0f} s)", flush=True)
    fig, axes = plt.subplots(1, 4, figsize=(17, 3.8))
    for method, r in summary["methods"].items():
        x = np.asarray(r["evaluations"])
        for ax, key in zip(axes, ("rank_agreement", "taken_change", "distinct", "revisits")):
            band(ax, x, np.asarray(r[key], float), method)
    titles = ("scores against the true change\n(Spearman over a parent's valid actions)",
              "true change of the mutations taken", "distinct bodies evaluated",
              "share of a chunk's evaluations\nthat revisit a body")
    for ax, title in zip(axes, titles):
        ax.set(title=title, xlabel="evaluations per run")
    axes[0].axhline(0, color="k", lw=0.8, ls=":")
    axes[1].axhline(0, color="k", lw=0.8, ls=":")
    axes[0].legend(fontsize=8)
    fig.suptitle(f"{s.space} table ({table.task}), K = {args.k}, {s.seeds} seeds: median and "
                 ".25-.75 band", fontsize=10)
    fig.tight_layout()
    save(fig, Path(args.out), name, summary)
    print(json.dumps({m: r["seconds"] for m, r in summary["methods"].items()}))


if __name__ == "__main__":
    main()
