"""Does Double-DQN reach Bad Walker's m* and then hold it with no-ops? (predefined fitness)

The source reports that its agent reaches m* in 3 mutations and spends the rest of the
episode on no-ops. With episodes of `default_horizon` = 5 mutations there are 2 steps left
after m*. This trains Double-DQN on the predefined fitness for --seeds seeds (vmapped, one
compile), then counts, for every seed:

  greedy    the greedy rollout from m0 (no exploration): the step at which it first reaches
            m*, and how many of the steps after it leave the body unchanged (no-ops);
  training  the last --last episodes of every parallel evolution (epsilon at its final 0.05):
            the share of episodes that reach m*, and the share of steps after m* that are
            no-ops (after m* a step's reward is 0 exactly when the body is unchanged: every
            other mutation changes the predefined fitness).

  python -m experiments.bad_walker_holds --out docs/figures      # CPU, ~4 min
"""

from __future__ import annotations

import argparse

import chex
import jax
import matplotlib.pyplot as plt
import numpy as np

from evojax_morph.pipeline import make_greedy_rollout
from experiments.common import Setup, run_agent, save


def same(a, b) -> bool:
    try:
        chex.assert_trees_all_equal(a, b)
        return True
    except AssertionError:
        return False


def main():
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--num-envs", type=int, default=16)
    parser.add_argument(
        "--steps", type=int, default=500, help="environment steps (100 episodes of 5)"
    )
    parser.add_argument("--chunk", type=int, default=100)
    parser.add_argument("--last", type=int, default=10, help="training episodes counted at the end")
    parser.add_argument("--out", default=None)
    args = parser.parse_args()

    setup = Setup(
        space="bad_walker",
        fitness="predefined",
        num_envs=args.num_envs,
        steps=args.steps,
        chunk=args.chunk,
    )
    res = run_agent("ddqn", setup, args.seeds)
    space, horizon = res["space"], res["horizon"]
    f_star = float(space.predefined_fitness(space.optimum()))

    # GREEDY ROLLOUT OF EVERY SEED
    rollout = make_greedy_rollout(res["pipeline"])
    greedy = []
    for s in range(args.seeds):
        take = lambda x, s=s: x[s]  # noqa: E731
        seq, fitness, names, _ = rollout(
            jax.tree.map(take, res["states"].learner),
            jax.tree.map(take, res["states"].first),
            jax.random.PRNGKey(s),
        )
        at = [t for t, f in enumerate(fitness) if f >= f_star - 1e-6]
        reached = at[0] if at else None
        noops = (
            None
            if reached is None
            else sum(same(seq[t], seq[t + 1]) for t in range(reached, horizon))
        )
        greedy.append(
            {
                "reached_at": reached,
                "steps_after": None if reached is None else horizon - reached,
                "noops_after": noops,
                "ends_at_m_star": fitness[-1] >= f_star - 1e-6,
                "actions": names,
                "fitness": fitness,
            }
        )

    # THE LAST EPISODES OF TRAINING
    fit, rew = res["metrics"]["fitness"], res["metrics"]["reward"]  # (steps, seeds, N)
    episodes = fit.shape[0] // horizon
    fit = fit[: episodes * horizon].reshape(episodes, horizon, *fit.shape[1:])[-args.last :]
    rew = rew[: episodes * horizon].reshape(episodes, horizon, *rew.shape[1:])[-args.last :]
    at_star = fit >= f_star - 1e-6  # (E, horizon, seeds, N)
    reached = at_star.any(1)  # (E, seeds, N)
    first = np.argmax(at_star, 1)  # first step (0-based) whose child is m*
    after = np.arange(horizon)[None, :, None, None] > first[:, None]
    after &= reached[:, None]
    noop_share = (after & (rew == 0)).sum((0, 1, 3)) / np.maximum(
        after.sum((0, 1, 3)), 1
    )  # (seeds,)
    reach_share = reached.mean((0, 2))  # (seeds,)

    print(
        f"Bad Walker, predefined fitness, Double-DQN, horizon {horizon}, {args.seeds} seeds x "
        f"{args.num_envs} evolutions x {args.steps} steps ({episodes} episodes)"
    )
    print(
        "seed  greedy: reached m* at step  no-ops after / steps after  ends at m*  | training: "
        "episodes reaching m*  no-op share after m*"
    )
    for s, g in enumerate(greedy):
        print(
            f"{s:>4}  {str(g['reached_at']):>26}  {str(g['noops_after']):>12} / "
            f"{str(g['steps_after']):<13}"
            f" {str(g['ends_at_m_star']):>10}  | {reach_share[s]:>29.2f}  {noop_share[s]:>20.2f}"
        )
    reached_greedy = [g for g in greedy if g["reached_at"] is not None]
    total_after = sum(g["steps_after"] for g in reached_greedy)
    total_noops = sum(g["noops_after"] for g in reached_greedy)
    print(
        f"greedy: {len(reached_greedy)}/{args.seeds} seeds reach m*; "
        f"{total_noops}/{total_after} steps after it are no-ops; "
        f"{sum(g['ends_at_m_star'] for g in greedy)}/{args.seeds} end at m*"
    )
    print(
        f"training, last {args.last} episodes: median share reaching m* "
        f"{np.median(reach_share):.2f}, "
        f"median no-op share after m* {np.median(noop_share):.2f} (min {noop_share.min():.2f})"
    )

    fig, ax = plt.subplots(figsize=(5, 3.4))
    ax.bar(np.arange(args.seeds) - 0.2, reach_share, 0.4, label="episodes reaching m*")
    ax.bar(np.arange(args.seeds) + 0.2, noop_share, 0.4, label="no-op share after m*")
    ax.set(
        xlabel="seed", ylabel="share", title=f"Bad Walker, last {args.last} episodes of Double-DQN"
    )
    ax.legend(loc="lower right")
    summary = {
        "horizon": horizon,
        "seeds": args.seeds,
        "num_envs": args.num_envs,
        "steps": args.steps,
        "greedy": greedy,
        "training_reach_share": reach_share.tolist(),
        "training_noop_share_after_m_star": noop_share.tolist(),
        "greedy_noops_after": total_noops,
        "greedy_steps_after": total_after,
    }
    save(fig, args.out or "runs/figures", "bad_walker_holds", summary)


if __name__ == "__main__":
    main()
