"""How much of one PPO fitness evaluation is noise, and what cutting it costs.

For a PPO setting (a named variant below), every Bad Walker body (90, told apart by shape) is
trained from scratch with S independent keys, batched: single-controller fitness f[body, s].
An evaluation with K controllers (`PPOConfig.controllers`) is their mean (or, as an
alternative, their max), so its statistics follow from groups of K columns:
g[body, j] = agg(f[body, jK : (j+1)K]) for j < S / K. Reported for K in --ks:

  cv          median over the 10 bodies of highest mean of std_j g / mean_j g
  n/s         noise-to-signal: median over the top 20 of std_j g, over the std of the 90 means
  pair20, pair90   Spearman between two single evaluations (columns j != j'), averaged over
              pairs, over the top 20 / all bodies: how well one evaluation ranks bodies
  split20, split90 Spearman between the means of the two halves of the columns
  agree       the best body by the first half of the columns is the best by the second
  s/eval      seconds per evaluation of one `train` call on --cost-batch random bodies (the main
              job's batch) with K controllers trained side by side; compile excluded

Top 10 / top 20 are by the mean over all S columns. Results go to --out/reliability_VARIANT.json
(a variant already there with the same settings is not rerun) and a table and a plot of the
frontier (cost against noise-to-signal) over every variant in --out.

  python -m experiments.bench_reliability --variants standard wide --seeds 32   # GPU
  python -m experiments.bench_reliability --variants tiny --seeds 2 --ks 1 2 --cost-batch 4   # CPU
  python -m experiments.bench_reliability --cost-only --train-steps 10000 --cost-batch 4 --ks 1 4
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
import scipy.stats

import evojax_morph as em
from evojax_morph import ppo
from evojax_morph.physics import engines
from evojax_morph.physics.determinism import full_precision

# The main job's inner PPO on a GPU today (run/cli.py: 16 envs, 20-step unrolls, 50,000 steps).
STANDARD = em.standard_ppo(50_000)
VARIANTS = {
    "standard": {},
    # the same sequential length (156 updates of 20 steps) with 4x the envs: 4x the samples
    "wide": dict(worlds_per_controller=64, num_minibatches=8, train_steps=200_000),
    # between the two: 2x the envs and samples at the same sequential length
    "mid": dict(worlds_per_controller=32, num_minibatches=8, train_steps=100_000),
    # standard with the value loss kept small: rewards / 10, so grad clipping acts on the policy too
    "scaled": dict(reward_scaling=0.1),
    # both, with brax-like epochs
    "wide_scaled": dict(worlds_per_controller=64, num_minibatches=8, train_steps=200_000,
                        reward_scaling=0.1),
    "lr3e-4": dict(learning_rate=3e-4),
    "no_clip": dict(max_grad_norm=1e9),
    "long": dict(train_steps=100_000),
    # a CPU smoke budget
    "tiny": dict(train_steps=320, worlds_per_controller=8, num_minibatches=2, update_epochs=2,
                 eval_episodes=1),
}
AGGREGATES = ("mean", "max")


def spearman(a: np.ndarray, b: np.ndarray) -> float:
    return float(scipy.stats.spearmanr(a, b).statistic)


def statistics(f: np.ndarray, k: int, aggregate: str) -> dict:
    """The reliability figures of evaluations with k controllers, from (bodies, S) single ones."""
    groups = f.shape[1] // k
    g = getattr(np, aggregate)(f[:, : groups * k].reshape(f.shape[0], groups, k), -1)
    mean = f.mean(1) if aggregate == "mean" else g.mean(1)
    order = np.argsort(-mean)
    top10, top20 = order[:10], order[:20]
    std = g.std(1, ddof=1) if groups > 1 else np.full(len(g), np.nan)
    out = {
        "k": k,
        "aggregate": aggregate,
        "evaluations_per_body": groups,
        "cv": float(np.median(std[top10] / np.abs(g[top10].mean(1)))),
        "noise_to_signal": float(np.median(std[top20]) / mean.std()),
        "top10_mean": float(mean[top10].mean()),
    }
    pairs = [(i, j) for i in range(groups) for j in range(i + 1, groups)]
    for name, rows in (("20", top20), ("90", order)):
        out["pair" + name] = (
            float(np.mean([spearman(g[rows, i], g[rows, j]) for i, j in pairs])) if pairs else None
        )
    if groups >= 2:
        half_a, half_b = g[:, : groups // 2].mean(1), g[:, groups // 2 : 2 * (groups // 2)].mean(1)
        out["split20"] = spearman(half_a[top20], half_b[top20])
        out["split90"] = spearman(half_a, half_b)
        out["agree"] = bool(np.argmax(half_a) == np.argmax(half_b))
    return out


def compiled_train(space, cfg: em.PPOConfig, batch: int, physics: str = "jax"):
    """(init, train, compile seconds): `train` of `batch` bodies, compiled."""
    init, train = ppo.make_train(space, em.TaskConfig(), cfg, physics)
    keys = jax.random.split(jax.random.PRNGKey(0), batch)
    morphs = jax.vmap(space.random_morphology, (0, None))(keys, 3)
    params = jax.jit(jax.vmap(init))(keys)
    start = time.perf_counter()
    fn = jax.jit(train).lower(keys, morphs, params).compile()
    return jax.jit(jax.vmap(init)), fn, time.perf_counter() - start


def landscape_fitness(space, cfg: em.PPOConfig, seeds: int, batch: int,
                      physics: str = "jax") -> tuple[np.ndarray, float, list]:
    """(bodies, seeds) single-controller fitness of every body, its seconds (compile excluded)."""
    bodies, _ = space.enumerate_bodies()
    jobs = [(b, s) for b in range(len(bodies)) for s in range(seeds)]
    batch = min(batch, len(jobs))
    init, train, _ = compiled_train(space, cfg, batch, physics)
    fitness = np.zeros((len(bodies), seeds))
    seconds = 0.0
    for start in range(0, len(jobs), batch):
        part = jobs[start : start + batch]
        part = part + [part[0]] * (batch - len(part))  # one compiled shape
        keys = jnp.stack([jax.random.fold_in(jax.random.fold_in(jax.random.PRNGKey(7), b), s)
                          for b, s in part])
        morphs = em.stack([bodies[b] for b, _ in part])
        params = init(jax.vmap(lambda k: jax.random.fold_in(k, 1))(keys))
        t = time.perf_counter()
        out = jax.block_until_ready(train(keys, morphs, params))
        seconds += time.perf_counter() - t
        for (b, s), value in zip(part[: len(jobs) - start], np.asarray(out.fitness)):
            fitness[b, s] = value
    return fitness, seconds, [space.canonical(m) for m in bodies]


def cost(space, cfg: em.PPOConfig, k: int, batch: int, repeats: int, physics: str = "jax") -> dict:
    """Seconds per evaluation of one call on `batch` random bodies with k controllers each."""
    cfg = dataclasses.replace(cfg, controllers=k)
    init, train, compile_s = compiled_train(space, cfg, batch, physics)
    keys = jax.random.split(jax.random.PRNGKey(1), batch)
    morphs = jax.vmap(space.random_morphology, (0, None))(keys, 3)
    params = init(keys)
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(train(keys, morphs, params))
        times.append(time.perf_counter() - t)
    return {"k": k, "batch": batch, "seconds_per_call": float(np.median(times)),
            "seconds_per_eval": float(np.median(times)) / batch, "compile_s": compile_s}


def table(results: list[dict]) -> str:
    lines = [f"{'variant':<12} {'K':>2} {'agg':<4} {'evals':>5} {'cv':>6} {'n/s':>6} "
             f"{'pair20':>7} {'pair90':>7} {'split20':>7} {'split90':>7} {'agree':>5} "
             f"{'top10':>7} {'s/eval':>8}"]
    for r in results:
        costs = {c["k"]: c["seconds_per_eval"] for c in r["cost"]}
        for s in r["stats"]:
            fmt = lambda x: "-" if x is None else f"{x:.2f}"
            c = costs.get(s["k"])
            lines.append(
                f"{r['variant']:<12} {s['k']:>2} {s['aggregate']:<4} "
                f"{s['evaluations_per_body']:>5} {s['cv']:>6.2f} {s['noise_to_signal']:>6.2f} "
                f"{fmt(s['pair20']):>7} {fmt(s['pair90']):>7} {fmt(s.get('split20')):>7} "
                f"{fmt(s.get('split90')):>7} {str(s.get('agree', '-')):>5} {s['top10_mean']:>7.1f} "
                f"{'-' if c is None else f'{c:.4f}':>8}"
            )
    return "\n".join(lines)


def plot(results: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    for r in results:
        costs = {c["k"]: c["seconds_per_eval"] for c in r["cost"]}
        pts = [(costs[s["k"]], s["noise_to_signal"], s["cv"], s["k"]) for s in r["stats"]
               if s["aggregate"] == "mean" and s["k"] in costs]
        if not pts:
            continue
        x, ns, cv, ks = map(np.array, zip(*pts))
        for ax, y in zip(axes, (ns, cv)):
            (line,) = ax.plot(x, y, marker="o", label=r["variant"])
            for xi, yi, k in zip(x, y, ks):
                ax.annotate(f"K={k}", (xi, yi), fontsize=7, color=line.get_color())
    today = [c["seconds_per_eval"] for r in results if r["variant"] == "standard"
             for c in r["cost"] if c["k"] == 1]
    for ax, name, target in zip(axes, ("noise-to-signal", "CV of the top 10"), (0.3, 0.15)):
        ax.axhline(target, color="0.5", ls="--", lw=1, label="target")
        if today:
            ax.axvline(2 * today[0], color="0.5", ls=":", lw=1, label="2x the standard cost")
        ax.set(xlabel="seconds per evaluation at the main job's batch", ylabel=name,
               title="fitness = mean of K controllers")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--variants", nargs="+", default=["standard"], choices=list(VARIANTS))
    add = parser.add_argument
    add("--seeds", type=int, default=32, help="single-controller evaluations per body")
    add("--ks", type=int, nargs="+", default=[1, 2, 4, 8], help="controllers per evaluation")
    add("--cost-ks", type=int, nargs="*", default=None, help="K timed (default: --ks)")
    add("--batch", type=int, default=2880, help="bodies x seeds per compiled landscape call")
    add("--cost-batch", type=int, default=256, help="bodies per timed call (the main job's batch)")
    add("--repeats", type=int, default=1)
    add("--cost-only", action="store_true", help="time --cost-ks only, at --train-steps")
    add("--train-steps", type=int, default=None, help="with --cost-only: the budget")
    add("--out", default="runs/reliability")
    add("--space", default="bad_walker", help="an enumerable space")
    add("--physics", default="jax", choices=engines.list_engines())
    add("--deterministic", action="store_true", help="deterministic GPU ops")
    args = parser.parse_args(argv)
    if args.deterministic:
        em.deterministic_gpu()
    full_precision()  # as the run command
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    space = em.make_space(args.space)
    # Bad Walker on the JAX engine keeps the old file names; anything else is named apart.
    default = (args.space, args.physics) == ("bad_walker", "jax")
    suffix = "" if default else f"_{args.space}_{args.physics}"
    device = jax.devices()[0].device_kind
    for name in args.variants:
        cfg = dataclasses.replace(STANDARD, **VARIANTS[name])
        if args.cost_only:
            cfg = dataclasses.replace(cfg, train_steps=args.train_steps or cfg.train_steps)
            for k in (args.ks if args.cost_ks is None else args.cost_ks):
                c = cost(space, cfg, k, args.cost_batch, args.repeats, args.physics)
                print(f"{name} at {cfg.train_steps} steps, K={k}, {args.cost_batch} bodies on "
                      f"{device}: {c['seconds_per_call']:.2f} s per call, "
                      f"{c['seconds_per_eval']:.3f} s per evaluation", flush=True)
            continue
        path = out / f"reliability_{name}{suffix}.json"
        settings = {"ppo": dataclasses.asdict(cfg), "seeds": args.seeds, "device": device}
        if suffix:
            settings.update(space=args.space, physics=args.physics)
        if path.exists() and json.loads(path.read_text())["settings"] == settings:
            print(f"{name}: already in {path}", flush=True)
            continue
        fitness, seconds, keys = landscape_fitness(space, cfg, args.seeds, args.batch, args.physics)
        stats = [statistics(fitness, k, agg) for agg in AGGREGATES for k in args.ks
                 if k <= args.seeds]
        costs = [cost(space, cfg, k, args.cost_batch, args.repeats, args.physics)
                 for k in (args.ks if args.cost_ks is None else args.cost_ks)]
        result = {"variant": name + suffix, "settings": settings, "landscape_seconds": seconds,
                  "evaluations": fitness.size, "bodies": keys, "fitness": fitness.round(3).tolist(),
                  "stats": stats, "cost": costs, "jax": jax.__version__,
                  "date": time.strftime("%Y-%m-%d")}
        path.write_text(json.dumps(result))
        print(f"{name}: {fitness.size} evaluations in {seconds:.1f} s (compile excluded)",
              flush=True)
        print(table([result]), flush=True)
    if args.cost_only:
        return
    results = [json.loads(p.read_text()) for p in sorted(out.glob("reliability_*.json"))]
    print("\n" + table(results))
    plot(results, out / "reliability.png")
    print(f"wrote {out}/reliability.png")


if __name__ == "__main__":
    main()
