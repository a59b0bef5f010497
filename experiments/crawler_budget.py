"""How many PPO steps does a Crawler body need to walk? Fixed bodies, growing budgets.

Each body is confirmed (`em.confirm`: --controllers controllers trained from scratch, the
walking task) at each budget of --budgets, smallest first; the data file OUT/crawler_budget.json
grows by a budget a call, so the command resumes across device calls. When every budget is in,
the best controller of the body with the best mean at the largest budget is saved
(OUT/crawler_best/) and one of its evaluation episodes is written as OUT/crawler_best.gif (.mp4)
by MuJoCo's renderer where OpenGL works (else a matplotlib drawing), and the figure
OUT/crawler_budget.png.

  python -m experiments.crawler_budget --physics warp --out docs/figures   # GPU
  python -m experiments.crawler_budget --budgets 320 640 --controllers 2 --out /tmp/cb   # CPU
"""

from __future__ import annotations

import argparse
import datetime
import json
import sys
import time
from pathlib import Path

import jax
import numpy as np

import evojax_morph as em
from evojax_morph.figures import video
from evojax_morph.records import saved_controllers
from evojax_morph.spaces.crawler import ADD, EXTEND
from experiments.build_tables import revision
from experiments.common import plt, save

# (name, the torso sites holding a chain, limbs per chain): site s is front/middle/back left
# for s = 0/1/2 and right for 3/4/5; a chain's first limb swings, the ones below it lift
BODIES = (
    ("four legs (the actor-critic's best)", (1, 2, 3, 4), 1),  # compare_a2c.json, 124.6
    ("four corner legs", (0, 2, 3, 5), 1),
    ("six legs", (0, 1, 2, 3, 4, 5), 1),
    ("four corner legs with knees", (0, 2, 3, 5), 2),
)


def body(space, sites, limbs):
    """The body grown from m0 by mutations: `add` at each site, then `extend` down its chain."""
    m = space.initial()
    for s in sites:
        m = space.mutate(m, 0, ADD[s])
        for d in range(1, limbs):
            m = space.mutate(m, 1 + 3 * s + d - 1, EXTEND)
    return m


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--budgets", type=int, nargs="+",
                        default=[20_000, 50_000, 100_000, 200_000, 500_000])
    parser.add_argument("--controllers", type=int, default=16)
    parser.add_argument("--physics", default="jax")
    parser.add_argument("--budget", type=float, default=420,
                        help="seconds after which no further budget starts")
    parser.add_argument("--out", type=Path, default=Path("runs/crawler_budget"))
    args = parser.parse_args(argv)
    space = em.make_space("crawler")
    morphs = [body(space, sites, limbs) for _, sites, limbs in BODIES]
    path = args.out / "crawler_budget.json"
    device = jax.devices()[0]
    data = json.loads(path.read_text()) if path.exists() else {
        "space": "crawler", "task": "walk", "physics": args.physics,
        "device": f"{device.platform}: {device.device_kind}", "controllers": args.controllers,
        "bodies": [{"name": n, "body": space.canonical(m)} for (n, _, _), m in zip(BODIES, morphs)],
        "budgets": {}, "device_seconds": 0.0}
    start = time.time()
    for steps in args.budgets:
        if str(steps) in data["budgets"] or time.time() - start > args.budget:
            continue
        called = time.time()
        cfg = em.FitnessConfig(kind="ppo", task=em.make_task("walk"), physics=args.physics,
                               ppo=em.standard_ppo(steps, 1))
        found = em.confirm(space, em.stack(morphs), jax.random.PRNGKey(steps), cfg,
                           args.controllers)
        by_name = {c.body: c for c in found}
        rows = [by_name[space.canonical(m)] for m in morphs]
        if steps == max(args.budgets):  # keep the best controller of the best body
            i = int(np.argmax([c.mean for c in rows]))
            j = int(np.argmax(rows[i].values))
            saved_controllers.save(args.out / "crawler_best", saved_controllers.SavedController(
                space, cfg, steps, rows[i].morph, jax.tree.map(lambda x, j=j: x[j], rows[i].params),
                float(rows[i].values[j]), BODIES[i][0]))
        data["budgets"][str(steps)] = [{
            "mean": c.mean, "ci95": list(c.ci95), "values": c.values.tolist(),
            "distance": c.distance.tolist(), "upright_whole": c.upright_whole} for c in rows]
        data["device_seconds"] = round(data["device_seconds"] + time.time() - called, 1)
        data["date"] = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")
        data["revision"] = revision()
        args.out.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(data, indent=1))
        for (name, _, _), c in zip(BODIES, rows):
            print(f"{steps:>7} steps  {name:<36} {c.mean:7.1f} [{c.ci95[0]:.1f}, "
                  f"{c.ci95[1]:.1f}]  median {np.median(c.distance):.2f} m  upright "
                  f"{c.upright_whole:.0%}", flush=True)
    if any(str(s) not in data["budgets"] for s in args.budgets):
        print("out of --budget: run the same command again")
        return 0
    if not (args.out / "crawler_best.gif").exists():
        saved = saved_controllers.load(args.out / "crawler_best")
        shown = video.render_saved(saved, args.out / "crawler_best", width=640, height=360)
        print(f"{saved.label}: walked {shown.replay.distance[-1]:+.2f} m in one episode, "
              f"drawn by {shown.backend}")
    draw(data, args.out)
    return 0


def draw(data: dict, out: Path) -> None:
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(10, 3.8))
    budgets = sorted(int(b) for b in data["budgets"])
    for i, b in enumerate(data["bodies"]):
        rows = [data["budgets"][str(s)][i] for s in budgets]
        ax.errorbar(budgets, [r["mean"] for r in rows], label=b["name"], capsize=3,
                    yerr=np.array([[r["mean"] - r["ci95"][0], r["ci95"][1] - r["mean"]]
                                   for r in rows]).T)
        bx.plot(budgets, [np.median(r["distance"]) for r in rows], "o-")
    ax.axhline(125, color="gray", ls=":", label="standing still 5 s")
    for a, label in ((ax, "confirmed fitness (95% CI)"), (bx, "median distance in 5 s (m)")):
        a.set(xscale="log", xlabel="PPO steps per controller", ylabel=label)
        a.set_xticks(budgets, [f"{b // 1000}k" for b in budgets], minor=False)
        a.minorticks_off()
    ax.legend(fontsize=7)
    fig.suptitle(f"Crawler, walking task: {data['controllers']} controllers a body and budget")
    save(fig, out, "crawler_budget", data)


if __name__ == "__main__":
    sys.exit(main())
