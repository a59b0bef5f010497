"""Shared by the figure scripts: run one agent over several seeds at once, and plot bands.

An agent's seeds run as a study of one method (`evojax_morph.search.study`): S seeds of N parallel
evolutions evaluate S x N bodies a step in one fitness call, one compiled call a chunk; the
wall-clock time of a step is that of the whole batch (all seeds together).
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import jax
import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from evojax_morph.search import study  # noqa: E402
from evojax_morph.search.pipeline import RunConfig  # noqa: E402


@dataclasses.dataclass(frozen=True)
class Setup:
    space: str = "bad_walker"
    fitness: str = "ppo"
    task: str = "distance"  # the source's task; "walk" for the walking task
    train_steps: int = 10_000
    num_envs: int = 8  # parallel evolutions per seed
    steps: int = 12  # environment steps
    chunk: int = 4
    hidden: int = 64
    horizon: int = 0  # 0: the space's default
    physics: str = "jax"  # the PPO fitness's engine: jax | warp (`evojax_morph.physics.engines`)


def agent_overrides(spec: str) -> tuple[dict, dict]:
    """({method: {field: value}}, what the file says of how they were chosen ({} for JSON)) of
    --agent-settings: JSON, or a frozen settings file (experiments/frozen_settings.json: its
    "settings", tuned on its "tuning_table")."""
    if spec.endswith(".json"):
        frozen = json.loads(Path(spec).read_text())
        return frozen["settings"], {k: v for k, v in frozen.items() if k != "settings"}
    return json.loads(spec or "{}"), {}


def add_setup_flags(parser, seeds: int = 3, **defaults):
    d = dataclasses.replace(Setup(), **defaults)
    for f in dataclasses.fields(Setup):
        parser.add_argument(
            "--" + f.name.replace("_", "-"),
            type=type(getattr(d, f.name)),
            default=getattr(d, f.name),
        )
    parser.add_argument("--seeds", type=int, default=seeds)
    parser.add_argument("--out", default=None)


def setup_from(args) -> Setup:
    return Setup(**{f.name: getattr(args, f.name) for f in dataclasses.fields(Setup)})


def run_config(agent: str, setup: Setup) -> RunConfig:
    """The run command's settings for `agent` under `setup`."""
    return RunConfig(
        space=setup.space,
        fitness=setup.fitness,
        task=setup.task,
        agent=agent,
        num_envs=setup.num_envs,
        horizon=setup.horizon,
        train_steps=setup.train_steps,
        hidden=setup.hidden,
        explore_steps=max(setup.steps // 2, 1),
        learning_starts=4 * setup.num_envs,
        physics=setup.physics,
    )


def run_agent(agent: str, setup: Setup, seeds: int, resume: Path | None = None,
              deadline: float | None = None) -> dict | None:
    """`seeds` independent runs of `agent`, built as the run command builds them and run by the
    library's loop (a study of one method, `search.study.run_study`; seed s from
    split(PRNGKey(0), seeds)[s]); returns per-step arrays of shape (steps, seeds, ...).

    With `resume`, the runs so far are saved there after every chunk and picked up from there
    by the next call; past `deadline` (time.time()) it returns None after the chunk in
    progress, to be called again. "seconds" counts every call's wall clock, building and
    compiling included."""
    called = time.time()
    methods, p = study.methods_from(run_config(agent, setup), [agent])
    res = study.run_study(study.make_study(methods, seeds),
                          jax.random.split(jax.random.PRNGKey(0), seeds), setup.steps,
                          setup.chunk, resume, deadline, since=called)
    if res is None:
        return None
    states, steps = res["states"][agent], res["chunk_steps"]
    return {
        "agent": agent,
        "metrics": res["metrics"][agent],  # (steps, seeds, ...)
        # (steps,) a step, all seeds together: its chunk's compiled call over its steps
        "step_seconds": np.repeat(np.divide(res["chunk_seconds"], steps), steps),
        "init_seconds": res["init_seconds"],  # compile and evaluate m0 (the first call)
        "seconds": res["seconds"],  # all calls, compiles included
        "evals_per_step": setup.num_envs,  # per seed
        "best_bodies": [jax.tree.map(lambda x, i=i: x[i], states.best_morph)
                        for i in range(seeds)],
        "best_fitness": np.asarray(states.best_fitness),
        "space": p.space,
        "horizon": p.env.horizon,
        "states": states,  # the agents' final states, (seeds, ...), host-side
        "pipeline": p,
    }


def band(ax, x, y, label, color=None):
    """Median over the last axis with a .25-.75 quantile band."""
    med, lo, hi = np.median(y, -1), np.quantile(y, 0.25, -1), np.quantile(y, 0.75, -1)
    (line,) = ax.plot(x, med, label=label, color=color)
    ax.fill_between(x, lo, hi, alpha=0.25, color=line.get_color())
    return line


def save(fig, out, name: str, summary: dict):
    from pathlib import Path

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(out / f"{name}.png", dpi=120)
    plt.close(fig)
    (out / f"{name}.json").write_text(json.dumps(summary, indent=1, default=float))
    print(f"wrote {out / name}.png and .json")


def episode_returns(reward: np.ndarray, horizon: int) -> np.ndarray:
    """(steps, seeds, N) rewards -> (episodes, seeds): each episode's return f_k - f_0, averaged
    over the N parallel evolutions (all of a run's evolutions start and end episodes together)."""
    episodes = reward.shape[0] // horizon
    r = reward[: episodes * horizon].reshape(episodes, horizon, *reward.shape[1:])
    return r.sum(1).mean(-1)


def holm(effects: dict) -> None:
    """Adds each comparison's Holm-adjusted p ("p_holm") and whether it holds at 5% after the
    correction ("significant_holm"), over every comparison of `effects` at once."""
    order = sorted(effects, key=lambda pair: effects[pair]["p"])
    running = 0.0
    for i, pair in enumerate(order):
        running = max(running, min(1.0, (len(order) - i) * effects[pair]["p"]))
        effects[pair]["p_holm"] = running
        effects[pair]["significant_holm"] = running < 0.05
