"""Do MuJoCo Warp and MJX's JAX engine give the same PPO fitness, in distribution?

The engines part after a few contact steps at the library's 4 Newton iterations (both solves stop
unconverged: `warp_agreement.py`), so single trajectories and single trainings are not compared.
What is compared is what an agent sees: for 5 Bad Walker bodies (m0, m* and three others spread
over the landscape) the PPO fitness from scratch over --seeds keys on each engine, at the main
job's GPU budget with one controller; per body the difference of means (Warp - JAX) with a
bootstrap 95% interval. `--landscapes A B` also gives the Spearman correlation of two landscape
files of `bench_reliability.py` (every body's mean over its seeds), e.g. Warp's against JAX's.

Each engine runs in its own call (Warp may be installed later than JAX), its results saved to
--out/agreement_ENGINE.json; `--compare` reads both and prints the table.

  python -m experiments.engine_agreement --physics jax --out runs/agreement
  python -m experiments.engine_agreement --physics warp --out runs/agreement
  python -m experiments.engine_agreement --compare --out runs/agreement --landscapes \\
      runs/rel/reliability_standard.json runs/rel/reliability_standard_bad_walker_warp.json
  python -m experiments.engine_agreement --physics jax --seeds 2 --train-steps 320   # CPU smoke
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import numpy as np

import evojax_morph as em
from evojax_morph import engines
from evojax_morph.spaces import bad_walker as bw
from experiments.bench_reliability import spearman


def bodies(space) -> dict[str, em.Morphology]:
    """m0, m* and three other bodies: the long foot gone with one short foot moved in, both
    short feet gone, and m0 with its back foot moved out to the end."""
    m0, star = space.initial(), space.optimum()
    return {
        "m0": m0,
        "m*": star,
        "m* front foot in": space.mutate(star, bw.FRONT, 2),
        "long foot alone": space.mutate(space.mutate(m0, bw.BACK, bw.REMOVE), bw.FRONT, bw.REMOVE),
        "m0 back foot out": space.mutate(m0, bw.BACK, 0),
    }


def measure(physics: str, seeds: int, train_steps: int) -> dict:
    space = em.make_space("bad_walker")
    named = bodies(space)
    cfg = em.FitnessConfig(ppo=em.standard_ppo(train_steps), physics=physics)
    morphs = em.stack([m for m in named.values() for _ in range(seeds)])
    keys = jax.random.split(jax.random.PRNGKey(11), len(named) * seeds)
    em.evaluate(space, morphs, keys, cfg).fitness.block_until_ready()  # compile
    start = time.perf_counter()
    out = em.evaluate(space, morphs, keys, cfg)
    fitness = np.asarray(out.fitness).reshape(len(named), seeds)
    return {
        "physics": physics,
        "device": jax.devices()[0].device_kind,
        "jax": jax.__version__,
        "date": time.strftime("%Y-%m-%d"),
        "train_steps": train_steps,
        "seeds": seeds,
        "seconds": time.perf_counter() - start,
        "diverged": int(np.asarray(out.diverged).sum()),
        "fitness": {name: row.round(3).tolist() for name, row in zip(named, fitness)},
    }


def bootstrap_diff(a: np.ndarray, b: np.ndarray, n: int = 10_000, seed: int = 0):
    """Mean of b - mean of a, and its bootstrap 95% interval (each sample resampled apart)."""
    rng = np.random.default_rng(seed)
    da = rng.choice(a, (n, len(a))).mean(1)
    db = rng.choice(b, (n, len(b))).mean(1)
    lo, hi = np.quantile(db - da, [0.025, 0.975])
    return float(b.mean() - a.mean()), float(lo), float(hi)


def compare(out: Path, landscapes: list[str] | None) -> dict:
    jax_run = json.loads((out / "agreement_jax.json").read_text())
    warp_run = json.loads((out / "agreement_warp.json").read_text())
    rows = []
    print(f"{'body':<18} {'JAX mean':>9} {'Warp mean':>9} {'Warp - JAX':>10} {'95% interval':>18}")
    for name, a in jax_run["fitness"].items():
        a, b = np.asarray(a), np.asarray(warp_run["fitness"][name])
        diff, lo, hi = bootstrap_diff(a, b)
        rows.append({"body": name, "jax": a.mean(), "warp": b.mean(), "diff": diff,
                     "lo": lo, "hi": hi, "jax_std": a.std(), "warp_std": b.std()})
        print(f"{name:<18} {a.mean():>9.1f} {b.mean():>9.1f} {diff:>10.1f} "
              f"{f'[{lo:.1f}, {hi:.1f}]':>18}")
    result = {"bodies": rows}
    if landscapes:
        a, b = (json.loads(Path(p).read_text()) for p in landscapes)
        mean = lambda r: dict(zip(r["bodies"], np.asarray(r["fitness"]).mean(1)))
        ma, mb = mean(a), mean(b)
        common = sorted(set(ma) & set(mb))
        rho = spearman(np.array([ma[k] for k in common]), np.array([mb[k] for k in common]))
        top = sorted(common, key=lambda k: -ma[k])[:20]
        rho20 = spearman(np.array([ma[k] for k in top]), np.array([mb[k] for k in top]))
        best_a, best_b = max(common, key=ma.get), max(common, key=mb.get)
        result.update(landscape_spearman=rho, top20_spearman=rho20, bodies_compared=len(common),
                      best=[best_a, best_b])
        print(f"landscapes: Spearman {rho:.3f} over {len(common)} bodies, {rho20:.3f} over the "
              f"first's top 20; best body {best_a!r} and {best_b!r}")
    (out / "agreement.json").write_text(json.dumps(result, indent=1, default=float))
    return result


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--physics", default="jax", choices=engines.list_engines())
    parser.add_argument("--seeds", type=int, default=16)
    parser.add_argument("--train-steps", type=int, default=50_000)
    parser.add_argument("--deterministic", action="store_true", help="deterministic GPU ops")
    parser.add_argument("--compare", action="store_true", help="compare the two saved engines")
    parser.add_argument("--landscapes", nargs=2, default=None, help="two bench_reliability JSONs")
    parser.add_argument("--out", default="runs/agreement")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.compare:
        compare(out, args.landscapes)
        return
    if args.deterministic:
        em.deterministic_gpu()
    jax.config.update("jax_default_matmul_precision", "highest")
    result = measure(args.physics, args.seeds, args.train_steps)
    (out / f"agreement_{args.physics}.json").write_text(json.dumps(result))
    print(json.dumps({k: v for k, v in result.items() if k != "fitness"}), flush=True)
    for name, row in result["fitness"].items():
        print(f"{name:<18} mean {np.mean(row):8.1f} std {np.std(row):7.1f}", flush=True)


if __name__ == "__main__":
    main()
