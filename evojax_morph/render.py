"""Watch a body of a run walk with its saved controller: `python -m evojax_morph.render RUN_DIR`.

Replays one evaluation episode of the controller the run trained on the body (the run keeps
them in RUN_DIR/controllers/, for the PPO fitness) and writes a GIF and, with imageio and
imageio-ffmpeg installed, an MP4, with the distance walked on screen. MuJoCo's renderer draws
the frames where OpenGL works: on MUJOCO_GL if set, else on the first of the display's GL
(GLFW), EGL and OSMesa that draws in a trial subprocess; where none does, a matplotlib drawing
of the capsules stands in. The command says which drew.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import jax

from evojax_morph.figures import video
from evojax_morph.flags import Parser
from evojax_morph.records import saved_controllers


def parse(argv) -> argparse.Namespace:
    parser = Parser(
        prog="python -m evojax_morph.render",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add = parser.add_argument
    add("run_dir", nargs="?",
        help="a run directory of `python -m evojax_morph.run` with the ppo fitness")
    add(
        "--body",
        nargs="+",
        default=["best"],
        metavar="{best,final,step N}",
        help="best (the best body found), final (the greedy trajectory's last body) or step N "
        "(its N-th body; step 0 is m0)",
    )
    add("--out", default=None,
        help="the files' path without suffix (default: RUN_DIR/best, RUN_DIR/final, "
        "RUN_DIR/stepN); .gif and .mp4 are added")
    add("--backend", default="auto", choices=video.BACKENDS,
        help="auto: MuJoCo's renderer if OpenGL works (MUJOCO_GL, else GLFW with a display, "
        "EGL or OSMesa), else a matplotlib drawing")
    add("--controller", type=int, default=0,
        help="which of the body's K controllers walks (PPOConfig.controllers)")
    add("--seed", type=int, default=None,
        help="seed of the episode's reset noise (default: the run's seed)")
    add("--width", type=int, default=480)
    add("--height", type=int, default=270)
    add("--stride", type=int, default=2,
        help="control steps (50 per second) per frame: 2 gives 25 frames per second")
    add("--no-mp4", action="store_true", help="write the GIF only")
    args = parser.parse_args(argv)
    if args.run_dir is None and len(args.body) > 1:  # `--body step 2 RUN_DIR`: --body took it
        args.run_dir = args.body.pop()
    if args.run_dir is None:
        parser.error("the following arguments are required: run_dir")
    for name in ("width", "height", "stride"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be positive, got {getattr(args, name)}")
    if not Path(args.run_dir).is_dir():
        parser.error(f"no run directory {args.run_dir!r}")
    args.body = " ".join(args.body)
    try:
        body = saved_controllers.body_dir(Path(args.run_dir), args.body)
        args.saved = saved_controllers.load(body)
    except (ValueError, FileNotFoundError) as e:
        parser.error(str(e))
    k = args.saved.fitness.ppo.controllers
    if not 0 <= args.controller < k:
        parser.error(f"--controller {args.controller} out of range: the body has {k}")
    if args.out is not None and not Path(args.out).parent.is_dir():
        parser.error(f"--out: no directory {str(Path(args.out).parent)!r}")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse(argv)
    saved = args.saved
    key = None if args.seed is None else jax.random.PRNGKey(args.seed)
    out = Path(args.out) if args.out else Path(args.run_dir) / args.body.replace(" ", "")
    shown = video.render_saved(saved, out, args.backend, args.controller, key, args.width,
                               args.height, args.stride, mp4=not args.no_mp4)
    rep = shown.replay
    print(f"{saved.label} of {args.run_dir} (fitness {saved.value:.4g} in the run), "
          f"controller {args.controller}:")
    print(saved.space.format(saved.morph))
    print(f"walked {rep.distance[-1]:+.2f} m in {(len(rep.qpos) - 1) * rep.dt:.1f} s, "
          f"return {rep.episode_return:.4g}")
    for note in shown.notes:
        print(note)
    print(f"drawn by {shown.backend}; wrote {' '.join(str(p) for p in shown.paths)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
