"""Figure 7's video: the final body of the actor-critic's greedy unroll, walking.

The body is the final one of the Figure 7 unroll (`--data`, made by `experiments.reproduce`)
whose final body confirmed highest, rebuilt by replaying that unroll's mutations from m0 (each
rebuilt body's canonical name must equal the one the data file records). `--controllers`
controllers are trained on it from scratch with fresh keys in one batched call (`em.confirm`,
on the default backend with --physics); each plays one evaluation episode, and the one of
median fitness plays it into OUT.gif and OUT.mp4 (`video.render_saved`). OUT.json records the
body, the budget, every controller's fitness and episode, the one shown, and the seconds spent.

  python -m experiments.fig7_video --train-steps 50000 --controllers 4
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
from evojax_morph import video
from evojax_morph.controllers import SavedController
from evojax_morph.pipeline import NO_OP
from evojax_morph.spaces import Space, make_space
from experiments.build_tables import revision


def unroll_bodies(space: Space, unroll: dict) -> list:
    """The bodies of a recorded greedy unroll (`{"actions": ["node 0: add_leg_start", ...],
    "bodies": [{"body": canonical name}, ...]}`), m0 first, by replaying its mutations.

    Raises:
      ValueError: a replayed body's canonical name differs from the recorded one.
    """
    bodies = [space.initial()]
    for action, recorded in zip(unroll["actions"], unroll["bodies"][1:], strict=True):
        node, mutation = action.removeprefix("node ").removesuffix(NO_OP).split(": ")
        bodies.append(space.mutate(bodies[-1], int(node), space.mutation_names.index(mutation)))
        if space.canonical(bodies[-1]) != recorded["body"]:
            raise ValueError(f"after {action!r} the body is {space.canonical(bodies[-1])}, "
                             f"not the recorded {recorded['body']}")
    return bodies


def rebuild(space: Space, unroll: dict):
    """The final body of a recorded greedy unroll (`unroll_bodies`)."""
    return unroll_bodies(space, unroll)[-1]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    add = parser.add_argument
    add("--data", type=Path, default=Path("docs/figures/reproduce/fig7.json"),
        help="the Figure 7 unrolls")
    add("--out", type=Path, default=Path("docs/figures/fig7_final_body"),
        help="the files' path without suffix")
    add("--train-steps", type=int, default=50_000, help="PPO steps per controller")
    add("--controllers", type=int, default=4, help="controllers trained from scratch")
    add("--physics", default="jax", help="jax | warp")
    add("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    start = time.time()
    r = json.loads(args.data.read_text())
    space = make_space(r["space"])
    finals = [u["bodies"][-1]["mean"] for u in r["unrolls"]]
    seed = int(np.argmax(finals))
    morph = rebuild(space, r["unrolls"][seed])
    print(f"seed {seed}'s final body (confirmed {finals[seed]:.1f} at {r['fitness']['train_steps']}"
          f" PPO steps):\n{space.format(morph)}", flush=True)

    cfg = em.FitnessConfig(kind="ppo", physics=args.physics,
                           ppo=em.standard_ppo(args.train_steps, args.controllers))
    (found,) = em.confirm(space, em.stack([morph]), jax.random.PRNGKey(args.seed), cfg,
                          args.controllers)
    trained = time.time() - start
    print(f"trained in {trained:.0f} s", flush=True)
    shown = int(np.argsort(found.values)[(args.controllers - 1) // 2])  # the (lower) median
    saved = SavedController(space, cfg, args.seed, found.morph, found.params,
                            float(found.values[shown]), f"fig7 seed {seed} final")
    episodes = []  # one evaluation episode of each controller, with the run's reset key
    for c in range(args.controllers):
        rep = video.replay(saved, jax.random.PRNGKey(args.seed), c)
        episodes.append({"return": rep.episode_return, "distance_m": float(rep.distance[-1]),
                         "seconds": (len(rep.qpos) - 1) * rep.dt})
    args.out.parent.mkdir(parents=True, exist_ok=True)
    rendered = video.render_saved(saved, args.out, controller=shown, stride=2)
    device = jax.devices()[0]
    data = {
        "body": found.body, "of": str(args.data), "unroll_seed": seed,
        "confirmed_in_fig7": r["unrolls"][seed]["bodies"][-1],
        "fitness": {"kind": "ppo", "train_steps": args.train_steps, "controllers": 1,
                    "inheritance": False, "ppo": dataclasses.asdict(cfg.ppo)},
        "task": cfg.task.name, "physics": args.physics,
        "device": f"{device.platform}: {device.device_kind}",
        "values": found.values.tolist(), "mean": found.mean, "ci95": list(found.ci95),
        "diverged": found.diverged.tolist(), "shown": shown,
        "shown_value": float(found.values[shown]),
        "episodes": episodes,  # each controller's, as the video's (which ends when it falls)
        "drawn_by": rendered.backend, "files": [str(p) for p in rendered.paths],
        "train_seconds": round(trained, 1), "seconds": round(time.time() - start, 1),
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "revision": revision(),
    }
    args.out.with_suffix(".json").write_text(json.dumps(data, indent=1))
    print(f"controllers' fitness {np.round(found.values, 1).tolist()}: mean {found.mean:.1f} "
          f"[{found.ci95[0]:.1f}, {found.ci95[1]:.1f}]; their episodes (metres, seconds, "
          f"return): {[tuple(round(v, 2) for v in e.values()) for e in episodes]}; the video "
          f"shows controller {shown}; drawn by {rendered.backend}; {data['seconds']:.0f} s; "
          f"wrote {' '.join(data['files'])} and {args.out.with_suffix('.json')}", flush=True)
    for note in rendered.notes:
        print(note)
    return 0


if __name__ == "__main__":
    sys.exit(main())
