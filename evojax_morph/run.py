"""Evolve a robot body with a learning agent: `python -m evojax_morph.run --space bad_walker`.

Each environment step mutates the body of every parallel evolution once and evaluates all the
children in one batched fitness call; the agent learns which mutations raise fitness. The run
directory gets config.json, metrics.csv, bodies.sqlite (every body evaluated), TensorBoard
events (tb/), curve.png, trajectory.png, best.xml, summary.json, timing.json (where the wall
clock went) and Orbax checkpoints, and with
the ppo fitness controllers/ (the best body's and the greedy trajectory's, for
`python -m evojax_morph.render`) and best.gif; --resume continues a run from its last checkpoint.
At the end the --confirm bodies of the highest mean fitness in the body log are evaluated again
from scratch, --confirm-controllers times each (confirmed.json, confirmed.png): the best of them
by that mean is the run's best body (best.xml, best.gif); summary.json keeps the highest single
draw apart, as best_single_draw.
The fitness batch is split across every visible device; --distributed spans several hosts.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import jax

from evojax_morph import agents, checkpoints, driver
from evojax_morph.determinism import deterministic_gpu, persistent_cache
from evojax_morph.engines import AUTO, list_engines, resolve
from evojax_morph.fitnesses import list_fitnesses
from evojax_morph.fitnesses.table import default_path as default_table
from evojax_morph.fitnesses.table import task_of
from evojax_morph.locomotion import list_tasks
from evojax_morph.pipeline import RunConfig
from evojax_morph.sharding import barrier, init_distributed
from evojax_morph.spaces import list_spaces


def gpu_defaults(space: str = "bad_walker") -> dict:
    """On a GPU the same command evaluates a larger batch with a longer PPO budget, and several
    controllers per body (`gpu_controllers`); the Constructor's come from its budget benchmark
    (`experiments.walking_budget` at git 119441b, docs/results.md "Bodies that walk")."""
    if space == "constructor":
        return CONSTRUCTOR_GPU
    return {
        "num_envs": 256,
        "train_steps": 50_000,
        "steps": 100,
        "explore_steps": 50,
        "learning_starts": 256,
        "chunk": 10,
        "checkpoint_every": 2,
        "confirm": 8,
        "confirm_controllers": 32,
    }


# The Constructor on the walking task (docs/results.md, "Bodies that walk"): at 100,000 PPO
# steps 2.1% of random 8-mutation bodies' evaluations walk 2 m upright (0.8% at 50,000, none at
# 10,000), at twice 50,000's cost; 128 evolutions x 1 controller keep a step at ~6 s on an H100
# (200,000 walks more, 3.8%, but doubles the greedy rollout's 8 one-body calls too).
CONSTRUCTOR_GPU = {
    "num_envs": 128,
    "train_steps": 100_000,
    "steps": 60,
    "explore_steps": 30,
    "learning_starts": 128,
    "chunk": 5,
    "checkpoint_every": 1,
    "confirm": 8,
    "confirm_controllers": 32,
}


def gpu_controllers(physics: str, space: str = "bad_walker") -> int:
    """Controllers per body on a GPU, spending each engine's speed on a fitness with less noise
    (docs/benchmarks.md, H100, 256 bodies of 50,000 PPO steps): 8 on MuJoCo Warp (cv 0.15,
    noise-to-signal 0.43, 27 s of fitness a step), 4 on the JAX engine (cv 0.23, 0.60; 66 s).
    The Constructor's budget goes to PPO steps and evolutions instead: 1."""
    if space == "constructor":
        return 1
    return 8 if physics == "warp" else 4


def add_distributed_flags(parser) -> None:
    """The flags of a run over several hosts, on `parser` (or an argument group)."""
    add = parser.add_argument
    add(
        "--distributed",
        action="store_true",
        help="call jax.distributed.initialize() first: one process per host, all with the same "
        "flags and --out; under SLURM nothing else is needed",
    )
    add("--coordinator", default=None,
        help="with --distributed outside SLURM: host:port of process 0")
    add("--num-processes", type=int, default=None,
        help="with --distributed outside SLURM: number of processes")
    add("--process-id", type=int, default=None,
        help="with --distributed outside SLURM: this process's id")


def start_deterministic(argv) -> None:
    """XLA's deterministic GPU ops, before anything touches a JAX backend, unless --fast-gpu or
    the PPO fitness may step on MuJoCo Warp (`may_use_warp`)."""
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--fast-gpu", action="store_true")
    pre.add_argument("--physics", default=AUTO)
    pre.add_argument("--fitness", default="ppo")
    pre.add_argument("--resume", action="store_true")
    pre.add_argument("--out", default=None)
    known = pre.parse_known_args(argv)[0]
    if not known.fast_gpu and not may_use_warp(known):
        deterministic_gpu()


def may_use_warp(known: argparse.Namespace) -> bool:
    """Whether the run's PPO fitness may step on MuJoCo Warp: --physics warp, or auto where Warp
    imports (auto takes it on a GPU; without one, XLA's GPU flags change nothing). A --resume
    reads both from the run's config.json. Warp orders contacts by thread timing, so such a run
    is not reproducible whatever XLA does, and XLA's deterministic ops would only cost time
    (4.6% of a Bad Walker fitness call at B = 1,024 on an H100, docs/benchmarks.md)."""
    physics, fitness = known.physics, known.fitness
    if known.resume and known.out:
        try:
            saved = json.loads((Path(known.out) / "config.json").read_text())
            physics, fitness = saved["physics"], saved["fitness"]
        except (OSError, ValueError, KeyError, TypeError):
            pass  # the parser says what is wrong with --out
    if fitness != "ppo":
        return False
    return physics == "warp" or (physics == AUTO and warp_imports())


def warp_imports() -> bool:
    """MuJoCo Warp's `importable()` (False where the optional extra is not installed)."""
    from evojax_morph import warp  # imports without the extra; it loads Warp on first use

    return warp.importable()[0]


def start_distributed(argv) -> None:
    """Must run before anything touches a JAX backend, so before the main parser's defaults."""
    pre = argparse.ArgumentParser(add_help=False)
    add_distributed_flags(pre)
    known, _ = pre.parse_known_args(argv)
    if known.distributed:
        init_distributed(known.coordinator, known.num_processes, known.process_id)


def parse(argv) -> tuple[RunConfig, Path, bool, bool]:
    """The run's config, directory, --resume and whether to draw best.gif; exits 2 with the
    reason (`parser.error`) on a bad flag."""
    gpu = jax.default_backend() == "gpu"
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--space", default=RunConfig().space)
    space = pre.parse_known_args(argv)[0].space
    defaults = dataclasses.replace(RunConfig(), **gpu_defaults(space)) if gpu else RunConfig()
    parser = make_parser(defaults)
    args = parser.parse_args(argv)
    check(parser, args)
    if not args.resume:
        args.physics = physics(parser, args.physics, args.fitness)
    if args.controllers is None:
        args.controllers = gpu_controllers(args.physics, args.space) if gpu else \
            defaults.controllers
    cfg = RunConfig(**{f.name: getattr(args, f.name) for f in dataclasses.fields(RunConfig)})
    classifier = str(Path(args.classifier).resolve()) if args.classifier else ""
    table = str(Path(args.table).resolve()) if args.table else ""
    cfg = dataclasses.replace(cfg, classifier=classifier, table=table)
    out = Path(args.out) if args.out else driver.fresh_run_dir(cfg)
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / f".write_test{jax.process_index()}"
        probe.write_text("")
        probe.unlink()
    except OSError as e:
        parser.error(f"cannot write to --out {str(out)!r}: {e.strerror or e}")
    saved = out / "config.json"
    if args.resume:
        if not saved.exists():
            parser.error(f"--resume: no run in {str(out)!r} (no config.json)")
        # a run begun before tasks were named trained under the source's task
        config = {"task": "distance", **json.loads(saved.read_text())}
        cfg = dataclasses.replace(RunConfig(**config), steps=args.steps)
        cfg = dataclasses.replace(cfg, physics=physics(parser, cfg.physics, cfg.fitness))
    elif (out / "checkpoints").exists():
        parser.error(
            f"{str(out)!r} already holds a run: pass --resume to continue it, or another --out"
        )
    return cfg, out, args.resume, not args.no_gif


def make_parser(defaults: RunConfig) -> argparse.ArgumentParser:
    """The run's flags in groups, their defaults `defaults`' (a RunConfig, GPU defaults
    applied)."""
    parser = argparse.ArgumentParser(
        prog="python -m evojax_morph.run",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_run_flags(parser.add_argument_group("run"), defaults)
    add_fitness_flags(parser.add_argument_group("fitness"), defaults)
    add_agent_flags(parser.add_argument_group("agent"), defaults)
    add_confirm_flags(parser.add_argument_group("confirm"), defaults)
    output = parser.add_argument_group("output and devices")
    output.add_argument(
        "--no-gif",
        action="store_true",
        help="skip best.gif at the end (its replay compiles and draws for up to a minute on a "
        "CPU); the controllers are saved either way, for `python -m evojax_morph.render`",
    )
    output.add_argument(
        "--fast-gpu",
        action="store_true",
        help="leave XLA's deterministic GPU ops off: about 1.4x faster on the JAX engine, but "
        "the same seed no longer gives the same run on a GPU (CPU runs are deterministic "
        "either way). A PPO fitness on MuJoCo Warp leaves them off anyway: Warp's own contact "
        "order is not reproducible",
    )
    add_distributed_flags(output)
    return parser


def add_run_flags(group, defaults: RunConfig) -> None:
    """The space, seed, run directory and the size of the run."""
    add = group.add_argument
    add("--space", default=defaults.space, help=f"morphology space: {', '.join(list_spaces())}")
    add("--steps", type=int, default=defaults.steps,
        help="environment steps; each mutates every parallel evolution once")
    add("--seed", type=int, default=defaults.seed, help="seed of every random choice of the run")
    add("--out", default=None, help="run directory (default: a new runs/SPACE-FITNESS-seedS[-N])")
    add("--resume", action="store_true",
        help="continue the run in --out from its last checkpoint, up to --steps")
    add("--num-envs", type=int, default=defaults.num_envs,
        help="parallel evolutions: the fitness batch of a step")
    add(
        "--horizon",
        type=int,
        default=defaults.horizon,
        help="mutations per episode (0: the space's default_horizon: 5 for bad_walker, the "
        "capacity for constructor)",
    )
    add("--chunk", type=int, default=defaults.chunk,
        help="environment steps per jitted call (progress and checkpoint granularity)")
    add("--checkpoint-every", type=int, default=defaults.checkpoint_every,
        help="chunks between checkpoints")


def add_fitness_flags(group, defaults: RunConfig) -> None:
    """The fitness, its task and inputs, and what a PPO evaluation trains on."""
    add = group.add_argument
    add(
        "--task",
        default=None,
        help=f"the locomotion task a PPO controller learns: {' | '.join(list_tasks())}. walk "
        "(the default): forward velocity plus a reward per step upright, the episode ending at a "
        "fall (Gymnasium's walkers' terms); distance: the source's, the distance covered before "
        "the episode ends (falling forward scores). Default: walk; with --fitness table, the "
        "table's own",
    )
    add(
        "--fitness",
        default=defaults.fitness,
        choices=list_fitnesses(),
        help="ppo: return of a controller trained with PPO on the body (inherited from the "
        "parent); predefined: the space's hand-crafted fitness; tame: task-agnostic, with "
        "--classifier; table: the mean of --controllers stored PPO results of the body, drawn "
        "from a landscape table (no controllers, no inheritance; --table)",
    )
    add(
        "--table",
        default="",
        help="table: the landscape table (.npz) built by `python -m experiments.build_tables` "
        "(default: the space's packaged one, evojax_morph/tables/SPACE.npz)",
    )
    add("--classifier", default="",
        help="tame: directory of a classifier trained by `python -m evojax_morph.tame`")
    add("--train-steps", type=int, default=defaults.train_steps,
        help="PPO control steps per fitness evaluation")
    add(
        "--controllers",
        type=int,
        default=None,
        help="independent PPO controllers trained per body; the fitness is their mean (default: "
        "1 on a CPU; on a GPU 8 with Warp, 4 with the JAX engine: docs/benchmarks.md)",
    )
    add(
        "--physics",
        default="auto",
        choices=[AUTO] + list_engines(),
        help="the engine that steps the fitness's worlds: jax (MJX's JAX engine), warp (MuJoCo "
        "Warp, `pip install 'evojax_morph[warp]'`), or auto: warp where it runs on a GPU, else "
        "jax (the run says which it took)",
    )
    add("--size-classes", dest="classes", action="store_true",
        help="ppo: train each body on the smallest of the space's size-class templates that "
        "holds it, not the one padded template (the Constructor's; evojax_morph.classes)")


def add_agent_flags(group, defaults: RunConfig) -> None:
    """Who chooses the mutations, and how it learns."""
    add = group.add_argument
    add(
        "--agent",
        default=defaults.agent,
        choices=agents.list_agents(),
        help="who chooses the mutations: ddqn (Double-DQN), dqn (plain DQN), qrdqn "
        "(quantile-regression DQN), a2c (actor-critic), or the baselines "
        "random (random mutation walks), evolution ((mu + lambda), its survivors evaluated "
        "again every step and ranked by their mean) and regularized_evolution (aging "
        "evolution: tournaments pick the parents, each child replaces the oldest member)",
    )
    add("--hidden", type=int, default=defaults.hidden, help="width of the agent's GNN")
    add("--explore-steps", type=int, default=defaults.explore_steps,
        help="ddqn, dqn, qrdqn: environment steps of epsilon annealing")
    add("--learning-starts", type=int, default=defaults.learning_starts,
        help="ddqn, dqn, qrdqn: transitions stored before learning")
    add("--population", type=int, default=defaults.population,
        help="regularized_evolution: members, at least --num-envs (0: 2 x --num-envs)")
    add("--tournament", type=int, default=defaults.tournament,
        help="regularized_evolution: members sampled per tournament, 1 to --population "
        "(0: an eighth of the population)")


def add_confirm_flags(group, defaults: RunConfig) -> None:
    """The confirm stage at the end of a run."""
    add = group.add_argument
    add(
        "--confirm",
        type=int,
        default=defaults.confirm,
        help="at the end, evaluate again the N distinct bodies of the highest mean fitness in "
        "the body log (ties: more evaluations, then seen first), from scratch: fresh keys and "
        "controllers, no inheritance, one fitness call; the best by the fresh mean is the run's "
        "best body. 0: off (the best body is the highest single draw). Skipped for the "
        "deterministic predefined fitness. Default 8 on a GPU (8 x 32 controllers: one fitness "
        "batch), 4 on a CPU (4 x 4 at the default 10,000 PPO steps: 3 min on a loaded 2-core "
        "CPU, 2 of them compiling; a run of the table fitness: under a second)",
    )
    add(
        "--confirm-controllers",
        type=int,
        default=defaults.confirm_controllers,
        help="fresh evaluations per confirmed body (each one controller trained from scratch; "
        "table: one draw), at least 2: the 95%% interval of its mean is a Student-t interval "
        "over them (default: 32 on a GPU, 4 on a CPU)",
    )


POSITIVE = ("steps", "num_envs", "train_steps", "controllers", "hidden", "chunk",
            "checkpoint_every", "explore_steps")  # flags checked positive (train_steps: >= 0)


def check(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Exits 2 with the reason (`parser.error`) where the flags cannot make a run; sets
    args.task where it was left to its default (a table's own, else walk)."""
    if jax.process_count() > 1 and not args.out:
        parser.error(
            "with several processes pass --out: every process must write the same run directory"
        )
    if args.space not in list_spaces():
        parser.error(f"unknown space {args.space!r}; known spaces: {', '.join(list_spaces())}")
    if args.task is not None and args.task not in list_tasks():
        parser.error(f"unknown task {args.task!r}; known tasks: {', '.join(list_tasks())}")
    for name in POSITIVE:
        value = getattr(args, name)  # None: the default, set by `parse`
        if value is not None and value < (0 if name == "train_steps" else 1):
            parser.error(f"--{name.replace('_', '-')} must be positive, got {value}")
    if args.horizon < 0:
        parser.error("--horizon must be >= 0")
    problem = agents.settings_problem(args.agent, args.num_envs, args.population, args.tournament)
    if problem:
        parser.error(problem)
    if args.confirm < 0:
        parser.error("--confirm must be >= 0 (0: no confirm stage)")
    if args.confirm_controllers < 2:
        parser.error("--confirm-controllers must be at least 2 (an interval needs 2 values)")
    if args.fitness == "tame" and not args.resume:
        meta = Path(args.classifier) / "tame.json"
        if not args.classifier or not meta.exists():
            parser.error(
                "--fitness tame needs --classifier DIR, a classifier trained by "
                f"`python -m evojax_morph.tame --space {args.space} --out DIR`"
            )
        if json.loads(meta.read_text())["space"] != args.space:
            parser.error(
                f"the classifier in {args.classifier!r} was trained on another space than "
                f"{args.space}"
            )
    if args.fitness == "table" and not args.resume:
        table = Path(args.table) if args.table else default_table(args.space)
        if not table.is_file():
            parser.error(
                f"--fitness table: no table at {str(table)!r}; build one with `python -m "
                f"experiments.build_tables --space {args.space} --out PATH` and pass --table PATH"
            )
        built = task_of(table)
        if args.task is not None and args.task != built:
            parser.error(
                f"--fitness table: the table {str(table)!r} was built under the task {built!r}, "
                f"but --task asks for {args.task!r}; pass --task {built} or a table built "
                f"under {args.task!r} (`python -m experiments.build_tables --task {args.task}`)"
            )
        args.task = built
    if args.task is None:
        args.task = "walk"


def physics(parser: argparse.ArgumentParser, name: str, fitness: str) -> str:
    """The engine `name` resolves to ("auto"), checked: exit 2 with the reason if it cannot
    run here."""
    if fitness == "tame" and name not in (AUTO, "jax"):
        parser.error("--physics: the tame fitness runs on the JAX engine only")
    try:
        name, why = resolve("jax" if fitness == "tame" else name)
    except (RuntimeError, ValueError) as e:
        parser.error(f"--physics: {e}")
    if fitness == "ppo":
        print(f"physics: {name} ({why})", flush=True)
    if fitness == "ppo" and name == "warp":
        print("physics: on a GPU MuJoCo Warp orders contacts by thread timing, so this run "
              "is not reproducible from its seed, and XLA's deterministic ops are left off "
              "(they would only cost time); --physics jax is reproducible "
              "(docs/benchmarks.md)", flush=True)
    return name


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    start_deterministic(args)
    start_distributed(args)
    cfg, out, resume, gif = parse(argv)
    barrier("parsed")  # every process checked --out before any of them writes there
    jax.config.update("jax_default_matmul_precision", "highest")
    persistent_cache()  # a second run of the same shapes skips XLA's compiles
    try:
        driver.execute(cfg, out, resume, gif)
    except (checkpoints.ResumeError, checkpoints.Damaged) as e:
        # Bad input, as the parser's errors: code 2 and why (no checkpoint reads, or a file the
        # run reads back, a saved controller or confirmed.json, is damaged).
        print(f"python -m evojax_morph.run: error: {e}", file=sys.stderr)
        raise SystemExit(2) from None
    return 0


if __name__ == "__main__":
    sys.exit(main())
