"""Does the TAME fitness rank Bad Walker's bodies as the PPO fitness does? Overfit vs held out.

Trains two TAME classifiers with the same seed and budget (`em.tame.pretrain`): one the source's
way, on whatever bodies its genealogy reaches, with no held-out set ("overfit"), and one that
never trains on a random --held-out fraction of the landscape's bodies (m0 excluded). Each then
scores every body of the PPO landscape (landscapes.py) with fresh rollouts, and this prints the
Spearman rank correlation of TAME fitness with the landscape's PPO mean fitness: over all
bodies, over the held-out bodies alone, and for the control (classifier) and coverage terms
apart. Writes tame_bad_walker.json and .png (training curves and scatter plots) and both
classifiers (Orbax checkpoints, usable with --fitness tame --classifier).

  python -m experiments.tame_landscape --out docs/figures                           # GPU or CPU
  python -m experiments.tame_landscape --generations 2 --population 4 --episodes 4  # smoke
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import jax
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from scipy.stats import spearmanr  # noqa: E402

import evojax_morph as em  # noqa: E402
from evojax_morph import landscape, tame  # noqa: E402

DEFAULT_LANDSCAPE = Path(__file__).parents[1] / "docs" / "landscapes" / "landscape_bad_walker.json"


def terms(pre: tame.Pretrained, bodies, key):
    """Per body: (F, control term, coverage term) on fresh rollouts drawn with `key`."""
    space = em.make_space(pre.space)
    t = tame.Tame(space, pre.config)

    def one(k, m):
        r = t.rollout(k, m)
        return tame.fitness_terms(
            pre.config, tame.log_likelihood(t.classifier, pre.params, m, r)[0], r
        )

    control, coverage = jax.device_get(
        jax.jit(tame.over_bodies(one, pre.config.episodes))(
            jax.random.split(key, len(bodies)), em.stack(bodies)
        )
    )
    return control + pre.config.coverage * coverage, control, coverage


def rho(x, y) -> float:
    return float(spearmanr(x, y).statistic) if len(x) > 2 else float("nan")


def main():
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--landscape", default=str(DEFAULT_LANDSCAPE))
    parser.add_argument("--held-out", type=float, default=0.2)
    parser.add_argument("--population", type=int, default=16)
    parser.add_argument("--generations", type=int, default=20)
    parser.add_argument("--epochs", type=int, default=10)
    parser.add_argument("--episodes", type=int, default=tame.TameConfig.episodes)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="runs/figures")
    args = parser.parse_args()
    jax.config.update("jax_default_matmul_precision", "highest")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    ls = landscape.Landscape.load(args.landscape)
    space = em.make_space(ls.space)
    bodies = [em.Morphology.from_dict(b) for b in ls.bodies]
    assert ls.index(space.initial()) == 0, (
        "landscapes list bodies as enumerate_bodies does, m0 first"
    )
    held = tame.pick_held_out(len(bodies), args.held_out, args.seed)
    cfg = tame.TameConfig(episodes=args.episodes)
    summary = {
        "landscape": args.landscape,
        "bodies": len(bodies),
        "held_out_bodies": [ls.keys[i] for i in held],
        "config": dataclasses.asdict(cfg),
        "population": args.population,
        "generations": args.generations,
        "device": jax.devices()[0].device_kind,
    }
    results = {}
    for name, held_out in (("overfit", []), ("held_out", [bodies[i] for i in held])):
        start = time.perf_counter()
        pre = tame.pretrain(
            space,
            jax.random.PRNGKey(args.seed),
            cfg,
            args.population,
            args.generations,
            held_out,
            args.epochs,
        )
        pre.save(out / f"tame_classifier_{name}")
        seconds = time.perf_counter() - start
        # The fitness through the library (Orbax checkpoint -> em.evaluate), and its two terms.
        keys = jax.random.split(jax.random.PRNGKey(args.seed + 1), len(bodies))
        classifier = str(out / f"tame_classifier_{name}")
        f = np.asarray(
            em.evaluate(
                space, em.stack(bodies), keys, em.FitnessConfig(kind="tame", classifier=classifier)
            ).fitness
        )
        f_terms, control, coverage = terms(pre, bodies, jax.random.PRNGKey(args.seed + 1))
        seen = np.array([k in set(pre.train_bodies) for k in ls.keys])
        unseen = np.array([i in held for i in range(len(bodies))])
        res = {
            "pretrain_seconds": seconds,
            "distinct_bodies_trained_on": len(pre.train_bodies),
            "history": pre.history,
            "tame_fitness": f.tolist(),
            "control": control.tolist(),
            "coverage": coverage.tolist(),
            # Same keys, another compiled program: contacts amplify rounding differences.
            "terms_max_abs_difference": float(np.max(np.abs(f_terms - f))),
            "spearman_all": rho(f, ls.mean),
            "spearman_trained_on": rho(f[seen], ls.mean[seen]),
            "spearman_not_trained_on": rho(f[~seen], ls.mean[~seen]),
            "spearman_held_out": rho(f[unseen], ls.mean[unseen]),
            "spearman_control_all": rho(control, ls.mean),
            "spearman_coverage_all": rho(coverage, ls.mean),
            "bodies_trained_on": int(seen.sum()),
        }
        results[name] = res
        print(
            name,
            {
                k: v
                for k, v in res.items()
                if k not in ("history", "tame_fitness", "control", "coverage")
            },
            flush=True,
        )
    summary.update(results)

    fig, axes = plt.subplots(1, 3, figsize=(14, 3.8))
    gens = [h["generation"] for h in results["held_out"]["history"]]
    for name, style in (("overfit", "--"), ("held_out", "-")):
        h = results[name]["history"]
        axes[0].plot(
            gens,
            [r["train_loglik"] for r in h],
            style,
            color="C0",
            label=f"{name}: training bodies",
        )
    h = results["held_out"]["history"]
    axes[0].plot(
        gens, [r["held_out_loglik"] for r in h], "-", color="C3", label="held_out: held-out bodies"
    )
    axes[0].axhline(h[0]["chance_loglik"], color="0.5", ls=":", label="chance")
    axes[0].set(title="classifier: log q per motor", xlabel="generation", ylabel="log-likelihood")
    axes[0].legend(fontsize=7)
    for ax, name in zip(axes[1:], ("overfit", "held_out")):
        r = results[name]
        f = np.asarray(r["tame_fitness"])
        unseen = np.isin(np.arange(len(bodies)), held)
        ax.scatter(ls.mean[~unseen], f[~unseen], s=12, label="other bodies")
        ax.scatter(ls.mean[unseen], f[unseen], s=16, color="C3", label="held-out bodies")
        ax.set(
            title=f"{name}: Spearman {r['spearman_all']:.2f} "
            f"(held-out {r['spearman_held_out']:.2f})",
            xlabel="PPO fitness (landscape mean)",
            ylabel="TAME fitness",
        )
    axes[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / f"tame_{ls.space}.png", dpi=120)
    (out / f"tame_{ls.space}.json").write_text(json.dumps(summary, indent=1))
    print(f"wrote {out}/tame_{ls.space}.png and .json")


if __name__ == "__main__":
    main()
