"""Train a TAME classifier on a space and save it for `--fitness tame --classifier DIR`.

  python -m evojax_morph.tame --space bad_walker --out runs/tame-bw
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import jax
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from evojax_morph.flags import Parser
from evojax_morph.spaces import list_spaces, make_space
from evojax_morph.tame import TameConfig, pick_held_out, pretrain
from evojax_morph.tame.fitness import refused

POSITIVE = ("population", "generations", "epochs", "episodes", "episode_length", "period",
            "num_freqs", "num_phases")


def parse(argv: list[str] | None) -> argparse.Namespace:
    parser = Parser(
        prog="python -m evojax_morph.tame",
        description="Train a TAME classifier on a space and save it for "
        "`--fitness tame --classifier DIR`.",
    )
    add = parser.add_argument
    add("--space", default="bad_walker", choices=list_spaces())
    add("--out", default=None, help="where to save the classifier (default: runs/tame-SPACE-seedS)")
    add("--seed", type=int, default=0)
    add("--population", type=int, default=16, help="bodies mutated per generation")
    add("--generations", type=int, default=20)
    add("--held-out", type=float, default=0.2,
        help="fraction of the bodies within --held-out-depth mutations of m0 (m0 excluded) kept "
        "out of training")
    add("--held-out-depth", type=int, default=3)
    add("--epochs", type=int, default=10, help="passes over the rollout buffer per generation")
    for f in dataclasses.fields(TameConfig):
        add("--" + f.name.replace("_", "-"), type=type(f.default), default=f.default,
            help=f"TameConfig.{f.name}")
    args = parser.parse_args(argv)
    if not 0 <= args.held_out < 1:
        parser.error(f"--held-out must be in [0, 1), got {args.held_out}")
    for name in POSITIVE:
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be positive")
    if refused(make_space(args.space)):
        parser.error(refused(make_space(args.space)))
    return args


def plot_history(path, history: list[dict]) -> None:
    """The TAME classifier per generation: log-likelihood per motor and accuracy, on the bodies
    it trains on and on held-out bodies, against chance."""
    gens = [h["generation"] for h in history]
    fig = Figure(figsize=(9, 3.4))
    FigureCanvasAgg(fig)  # drawn by Agg outside pyplot: matplotlib's backend left as it was
    axes = fig.subplots(1, 2)
    for ax, metric in zip(axes, ("loglik", "accuracy")):
        ax.plot(
            gens, [h[f"train_{metric}"] for h in history], label="training bodies (their rollouts)"
        )
        if "held_out_" + metric in history[0]:
            ax.plot(gens, [h[f"held_out_{metric}"] for h in history], label="held-out bodies")
        ax.axhline(history[0][f"chance_{metric}"], color="0.5", ls="--", label="chance")
        ax.set(xlabel="generation", ylabel="log q per motor" if metric == "loglik" else "accuracy")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv: list[str] | None = None) -> int:
    args = parse(argv)
    space = make_space(args.space)
    cfg = TameConfig(**{f.name: getattr(args, f.name) for f in dataclasses.fields(TameConfig)})
    out = Path(args.out or f"runs/tame-{args.space}-seed{args.seed}")

    bodies, _ = space.enumerate_bodies(args.held_out_depth)
    held_out = [bodies[i] for i in pick_held_out(len(bodies), args.held_out, args.seed)]
    print(f"TAME on {space.name}: {len(held_out)} of {len(bodies)} bodies within "
          f"{args.held_out_depth} mutations held out; {args.generations} generations of "
          f"{args.population}")
    pre = pretrain(space, jax.random.PRNGKey(args.seed), cfg, args.population, args.generations,
                   held_out, args.epochs)
    pre.save(out)
    plot_history(out / "history.png", pre.history)
    last = pre.history[-1]
    nan = float("nan")
    print(f"{len(pre.train_bodies)} distinct bodies trained on; last generation: log q per motor "
          f"{last['train_loglik']:.3f} on them (fresh rollouts {last['train_fresh_loglik']:.3f}), "
          f"{last.get('held_out_loglik', nan):.3f} held out (chance "
          f"{last['chance_loglik']:.3f}); accuracy {last['train_accuracy']:.2f} / "
          f"{last['train_fresh_accuracy']:.2f} / {last.get('held_out_accuracy', nan):.2f}")
    print(f"saved to {out} (use: --fitness tame --classifier {out})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
