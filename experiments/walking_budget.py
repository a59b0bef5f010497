"""Which PPO budget (and which walking task) tells Constructor bodies apart, and how many walk?

Bodies: --bodies distinct random unrolls of 8 mutations from m0 (by canonical name), then
Figure 7's three final bodies (rebuilt from docs/figures/reproduce/fig7.json). A cell is a task
and a PPO budget, `walk:50000` or `walk,healthy_reward=1:50000` (overrides of the task's
settings after commas): every body trains --seeds controllers from scratch, one evaluation of
one controller each (K = 1, no inheritance), --seeds-per-call seeds of every body in one fitness
call. Each evaluation records its fitness, distance (metres forward, mean over its evaluation
episodes) and upright (the fraction of an episode before a fall, mean). Per cell:

  dist50     median distance of the evaluations; best5: the 5 highest body means of distance
  whole      the fraction of evaluations upright for the whole of every episode
  walk2m     the fraction upright the whole episode and at least 2 m forward
  n/s        noise-to-signal: median over the 20 bodies of highest mean fitness of the std over
             seeds, over the std of all body means (as bench_reliability)
  split      Spearman between the body means of the first and second halves of the seeds
  s/eval     device seconds per evaluation (compile excluded)

Each cell goes to --out/CELL.json (arrays (bodies, seeds)); a cell already there with the same
settings is not run again, so a call that stops at --deadline (seconds) resumes in the next.
--out/budget.png draws every cell there.

  python -m experiments.walking_budget --physics warp --bodies 256 --seeds 8   # GPU
  python -m experiments.walking_budget --bodies 4 --seeds 2 --cells walk:320 --tiny   # CPU
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import sys
import time
from pathlib import Path

import jax
import numpy as np

import evojax_morph as em
from evojax_morph.fitness import lower_evaluate
from experiments.bench_reliability import spearman
from experiments.build_tables import revision
from experiments.fig7_video import rebuild

CELLS = ["walk:50000", "walk:10000", "walk:25000", "distance:50000",
         "walk,healthy_reward=1:50000", "walk:100000", "walk,healthy_reward=0.25:50000"]


def parse_cell(cell: str) -> tuple[em.TaskConfig, int]:
    """'TASK[,key=value...]:BUDGET' -> (task settings, PPO steps)."""
    task, budget = cell.rsplit(":", 1)
    name, *overrides = task.split(",")
    return em.make_task(name, **{k: float(v) for k, v in (o.split("=") for o in overrides)}), \
        int(budget)


def bodies(space, n: int, seed: int = 0) -> tuple[list, list[str]]:
    """n distinct random 8-mutation bodies, then Figure 7's final bodies; and their names."""
    sample = jax.jit(jax.vmap(space.random_morphology, (0, None)), static_argnums=1)
    morphs = jax.device_get(sample(jax.random.split(jax.random.PRNGKey(seed), 8 * n), 8))
    found, names = [], []
    for i in range(8 * n):
        m = jax.tree.map(lambda x, i=i: np.asarray(x[i]), morphs)
        name = space.canonical(m)
        if name not in names and len(found) < n:
            found.append(m), names.append(name)
    fig7 = json.loads(Path("docs/figures/reproduce/fig7.json").read_text())
    for unroll in fig7["unrolls"]:
        m = rebuild(space, unroll)
        found.append(m), names.append(space.canonical(m))
    return found, names


def statistics(f: np.ndarray, d: np.ndarray, u: np.ndarray) -> dict:
    """A cell's figures from (bodies, seeds) fitness, distance and upright."""
    mean = f.mean(1)
    top = np.argsort(-mean)[:20]
    half = f.shape[1] // 2
    whole = u >= 1.0
    return {
        "dist50": float(np.median(d)),
        "best5_distance": np.sort(d.mean(1))[-5:][::-1].round(3).tolist(),
        "whole": float(whole.mean()),
        "walk2m": float((whole & (d >= 2.0)).mean()),
        "fitness_median": float(np.median(f)),
        "best5_fitness": np.sort(mean)[-5:][::-1].round(1).tolist(),
        "noise_to_signal": float(np.median(f[top].std(1, ddof=1)) / mean.std()),
        "split_half": spearman(f[:, :half].mean(1), f[:, half:].mean(1)),
    }


def run_cell(space, morphs, names, cell, args) -> dict:
    task, budget = parse_cell(cell)
    ppo = em.standard_ppo(budget)
    if args.tiny:
        ppo = dataclasses.replace(ppo, num_envs=8, num_minibatches=2, update_epochs=2,
                                  eval_episodes=1)
    cfg = em.FitnessConfig(kind="ppo", task=task, ppo=ppo, physics=args.physics)
    n, per = len(morphs), args.seeds_per_call
    batch = em.stack(morphs * per)  # seed s of body b at s * n + b
    keys = jax.random.split(jax.random.PRNGKey(args.seed), args.seeds * n).reshape(
        args.seeds // per, per * n, -1)
    out = {k: [] for k in ("fitness", "distance", "upright", "diverged")}
    seconds = []
    # compiled ahead, so that the clock times the calls alone; as em.evaluate calls them
    init, evaluate = (p.compile() for p in lower_evaluate(space, per * n, cfg))
    fresh = jax.vmap(lambda key: jax.random.fold_in(key, 1))
    for call in keys:
        start = time.perf_counter()
        res = jax.block_until_ready(evaluate(call, batch, init(fresh(call))))
        seconds.append(time.perf_counter() - start)
        for k in out:
            out[k].append(np.asarray(getattr(res, k)).reshape(per, n).T)
        print(f"  {cell}: {len(seconds) * per}/{args.seeds} seeds, {seconds[-1]:.1f} s",
              flush=True)
    arrays = {k: np.concatenate(v, 1) for k, v in out.items()}  # (bodies, seeds)
    stats = statistics(arrays["fitness"], arrays["distance"], arrays["upright"])
    device = jax.devices()[0]
    return {
        "cell": cell, "space": space.name, "task": dataclasses.asdict(task),
        "train_steps": budget, "ppo": dataclasses.asdict(ppo), "physics": args.physics,
        "seeds": args.seeds, "bodies": names, "fig7_bodies": names[-3:],
        **stats, "seconds_per_eval": sum(seconds) / (n * args.seeds),
        "device": f"{device.platform}: {device.device_kind}",
        "device_seconds": round(sum(seconds), 1),
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "revision": revision(),
        **{k: (v if v.dtype == bool else v.round(4)).tolist() for k, v in arrays.items()},
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    add = parser.add_argument
    add("--cells", nargs="+", default=CELLS, help="TASK[,key=value...]:PPO_STEPS")
    add("--bodies", type=int, default=256, help="random 8-mutation bodies (Figure 7's added)")
    add("--seeds", type=int, default=8)
    add("--seeds-per-call", type=int, default=4)
    add("--physics", default="jax", choices=em.list_engines())
    add("--seed", type=int, default=0)
    add("--deadline", type=float, default=None, help="seconds: start no cell after this")
    add("--tiny", action="store_true", help="a CPU smoke budget (8 envs, 1 episode)")
    add("--out", type=Path, default=Path("docs/walking"))
    args = parser.parse_args(argv)
    if args.seeds % args.seeds_per_call or args.seeds < 2:
        parser.error("--seeds must be a multiple of --seeds-per-call, and at least 2")
    for cell in args.cells:
        try:
            parse_cell(cell)
        except ValueError as e:
            parser.error(f"--cells {cell!r}: {e}")
    start = time.time()
    space = em.make_space("constructor")
    morphs, names = bodies(space, args.bodies, args.seed)
    args.out.mkdir(parents=True, exist_ok=True)
    for cell in args.cells:
        path = args.out / (cell.replace(",", "_").replace("=", "").replace(":", "_") + ".json")
        if path.exists():
            old = json.loads(path.read_text())
            if old["bodies"] == names and old["seeds"] == args.seeds:
                print(f"{cell}: done before ({path})")
                continue
        if args.deadline is not None and time.time() - start > args.deadline:
            print(f"{cell}: past the deadline, left for the next call")
            continue
        data = run_cell(space, morphs, names, cell, args)
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps(data))
        tmp.replace(path)
        print(f"{cell}: dist50 {data['dist50']:.2f} m, whole {data['whole']:.1%}, walk2m "
              f"{data['walk2m']:.2%}, n/s {data['noise_to_signal']:.2f}, split "
              f"{data['split_half']:.2f}, best5 distance {data['best5_distance']}, "
              f"{data['seconds_per_eval'] * 1e3:.1f} ms/eval", flush=True)
    draw(args.out)
    return 0


def draw(out: Path) -> None:
    """OUT/budget.png from every cell in OUT: per budget of the walking task, the share of
    evaluations upright the whole episode and walking 2 m, and noise-to-signal; the other
    tasks at their budget as single markers."""
    cells = [json.loads(p.read_text()) for p in sorted(out.glob("*.json"))]
    if not cells:
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    walk = sorted((c for c in cells if c["cell"].startswith("walk:")),
                  key=lambda c: c["train_steps"])
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    figures = [("walk2m", "evaluations upright and >= 2 m", 100),
               ("whole", "evaluations upright the whole episode", 100),
               ("noise_to_signal", "noise-to-signal (top 20 bodies)", 1)]
    for ax, (key, title, scale) in zip(axes, figures):
        ax.plot([c["train_steps"] for c in walk], [c[key] * scale for c in walk], "o-",
                label="walk")
        for c in cells:
            if not c["cell"].startswith("walk:"):
                ax.plot(c["train_steps"], c[key] * scale, "x", label=c["cell"].rsplit(":")[0])
        ax.set_xscale("log")
        ax.set_xlabel("PPO steps per controller")
        ax.set_title(title + (" (%)" if scale == 100 else ""), fontsize=10)
    axes[0].legend(fontsize=7)
    n, seeds = len(cells[0]["bodies"]), cells[0]["seeds"]
    fig.suptitle(f"Constructor: {n} bodies x {seeds} seeds, one controller each "
                 f"({cells[0]['device']})", fontsize=10)
    fig.tight_layout()
    fig.savefig(out / "budget.png", dpi=110)
    plt.close(fig)
    print(f"wrote {out / 'budget.png'}")


if __name__ == "__main__":
    sys.exit(main())
