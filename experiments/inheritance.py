"""Does a child trained from its parent's controller beat the same child trained from scratch?

For each parent/child pair (the child is one mutation from the parent), the parent is trained
from scratch with --seeds keys; then the child is trained, at the same budget, once from each
parent controller (inherited) and once from a fresh controller (scratch), with the same keys.
All parents go in one batched call, all children in another. Reported per pair: the mean of
both, their difference with a 95% bootstrap interval, P(inherited > scratch) over all pairings
of seeds (ties count half) with a Mann-Whitney p-value, and the same for the controllers before
any training of the child (inherited as it is against a fresh one: what inheritance hands over).

  python -m experiments.inheritance --variant standard --seeds 16                 # GPU
  python -m experiments.inheritance --variant tiny --seeds 2 --out /tmp/inh      # CPU smoke
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import evojax_morph as em
from evojax_morph import ppo
from evojax_morph.spaces import bad_walker as bw
from experiments.bench_reliability import STANDARD, VARIANTS


def pairs(space) -> dict:
    """name -> (parent, child), each child one mutation from its parent."""
    m0, star = space.initial(), space.optimum()
    long_forward = space.mutate(m0, bw.LONG, 2)  # long foot to front_inner: 2nd of 90 at 50k steps
    return {
        "m* -> front foot inward": (star, space.mutate(star, bw.FRONT, 2)),
        "m0 -> long foot removed": (m0, space.mutate(m0, bw.LONG, bw.REMOVE)),
        "long foot forward -> back foot removed": (
            long_forward,
            space.mutate(long_forward, bw.BACK, bw.REMOVE),
        ),
    }


def effect(a: np.ndarray, b: np.ndarray, key: int = 0) -> dict:
    """Difference of means of a and b with a 95% bootstrap interval; P(a > b) and Mann-Whitney p."""
    from scipy.stats import mannwhitneyu

    rng = np.random.default_rng(key)
    boot = [rng.choice(a, len(a)).mean() - rng.choice(b, len(b)).mean() for _ in range(4000)]
    greater = (a[:, None] > b[None]).mean() + 0.5 * (a[:, None] == b[None]).mean()
    return {
        "difference": float(a.mean() - b.mean()),
        "ci95": [float(np.quantile(boot, q)) for q in (0.025, 0.975)],
        "p_greater": float(greater),
        "mann_whitney_p": float(mannwhitneyu(a, b).pvalue),
    }


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--variant", default="standard", choices=list(VARIANTS))
    parser.add_argument("--controllers", type=int, default=1)
    parser.add_argument("--seeds", type=int, default=16)
    parser.add_argument("--out", default="runs/inheritance")
    args = parser.parse_args(argv)
    jax.config.update("jax_default_matmul_precision", "highest")
    space = em.make_space("bad_walker")
    cfg = dataclasses.replace(STANDARD, **VARIANTS[args.variant], controllers=args.controllers)
    init, train = ppo.make_train(space, em.TaskConfig(), cfg)
    train, init = jax.jit(train), jax.jit(jax.vmap(init))
    _, evaluate = ppo.make_train(space, em.TaskConfig(), dataclasses.replace(cfg, train_steps=0))
    evaluate = jax.jit(evaluate)
    named = pairs(space)
    n, s = len(named), args.seeds
    parents = em.stack([p for p, _ in named.values() for _ in range(s)])
    children = em.stack([c for _, c in named.values() for _ in range(s)])
    keys = jax.random.split(jax.random.PRNGKey(11), 3 * n * s).reshape(3, n * s, -1)
    start = time.perf_counter()
    parent_out = train(keys[0], parents, init(keys[0]))
    fresh = init(keys[1])
    both = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), parent_out.params, fresh)
    child_keys, child_morphs = (
        jnp.concatenate([keys[2], keys[2]]),
        jax.tree.map(lambda x: jnp.concatenate([x, x]), children),
    )
    trained = np.asarray(train(child_keys, child_morphs, both).fitness).reshape(2, n, s)
    untrained = np.asarray(evaluate(child_keys, child_morphs, both).fitness).reshape(2, n, s)
    seconds = time.perf_counter() - start
    parent_fit = np.asarray(parent_out.fitness).reshape(n, s)
    rows = []
    for i, name in enumerate(named):
        rows.append(
            {
                "pair": name,
                "parent_mean": float(parent_fit[i].mean()),
                "inherited_mean": float(trained[0, i].mean()),
                "scratch_mean": float(trained[1, i].mean()),
                "inherited_std": float(trained[0, i].std()),
                "scratch_std": float(trained[1, i].std()),
                "trained": effect(trained[0, i], trained[1, i]),
                "untrained": effect(untrained[0, i], untrained[1, i]),
                "inherited": trained[0, i].round(1).tolist(),
                "scratch": trained[1, i].round(1).tolist(),
            }
        )
        r = rows[-1]
        print(
            f"{name:<45} parent {r['parent_mean']:6.1f}  inherited {r['inherited_mean']:6.1f} +- "
            f"{r['inherited_std']:5.1f}  scratch {r['scratch_mean']:6.1f} +- "
            f"{r['scratch_std']:5.1f}  "
            f"diff {r['trained']['difference']:6.1f} "
            f"[{r['trained']['ci95'][0]:6.1f}, {r['trained']['ci95'][1]:6.1f}]"
            f"  P {r['trained']['p_greater']:.2f}  p {r['trained']['mann_whitney_p']:.3f}"
            "  |  untrained diff "
            f"{r['untrained']['difference']:6.1f}  P {r['untrained']['p_greater']:.2f}",
            flush=True,
        )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    result = {
        "variant": args.variant,
        "ppo": dataclasses.asdict(cfg),
        "seeds": s,
        "seconds_with_compile": seconds,
        "device": jax.devices()[0].device_kind,
        "jax": jax.__version__,
        "date": time.strftime("%Y-%m-%d"),
        "pairs": rows,
    }
    (out / f"inheritance_{args.variant}_k{args.controllers}.json").write_text(
        json.dumps(result, indent=1)
    )


if __name__ == "__main__":
    main()
