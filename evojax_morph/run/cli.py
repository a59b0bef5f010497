"""Evolve a robot body with a learning agent: `python -m evojax_morph.run --space bad_walker`.

Each environment step mutates the body of every parallel evolution once and evaluates all the
children in one batched fitness call; the agent learns which mutations raise fitness. The run
directory gets config.json, metrics.csv, bodies.sqlite (every body evaluated), TensorBoard
events (tb/), curve.png, trajectory.png, best.xml, summary.json, timing.json (where the wall
clock went, and on what) and Orbax checkpoints, and with the ppo fitness controllers/ (the best
body's and the greedy trajectory's, for `python -m evojax_morph.render`) and best.gif; --resume
continues a run from its last checkpoint.
A run holds its directory for its whole life (.lock, with its pid): a second run or resume there
exits 2 at once. The files it rewrites are replaced whole (`checkpoints.write_atomic`).
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
import os
import sys
from pathlib import Path

import jax

from evojax_morph import agents
from evojax_morph.fitnesses import Inputs, fitness_params, get_fitness, resolve_physics
from evojax_morph.flags import Parser, given_settings
from evojax_morph.physics.determinism import deterministic_gpu, full_precision, persistent_cache
from evojax_morph.physics.engines import AUTO, may_take, registered
from evojax_morph.records import checkpoints
from evojax_morph.run import driver
from evojax_morph.run.options import (
    add_agent_flags,
    add_agent_settings,
    add_confirm_flags,
    add_distributed_flags,
    add_fitness_flags,
    add_fitness_settings,
    add_run_flags,
    add_task_settings,
)
from evojax_morph.search.pipeline import RunConfig
from evojax_morph.sharding import barrier, init_distributed
from evojax_morph.spaces import Space, get_space, list_spaces
from evojax_morph.tasks import make_task


def start(argv) -> None:
    """What must come before anything touches a JAX backend, from one parse of `argv`'s flags
    for it: XLA's deterministic GPU ops, unless --fast-gpu or the fitness may step on an engine
    that no XLA flag makes reproducible (`may_step_unreproducibly`); with --distributed, the
    start over several hosts."""
    pre = Parser(prog="python -m evojax_morph.run", add_help=False)
    pre.add_argument("--fast-gpu", action="store_true")
    pre.add_argument("--physics", default=AUTO)
    pre.add_argument("--fitness", default=RunConfig().fitness)
    pre.add_argument("--resume", action="store_true")
    pre.add_argument("--out", default=None)
    add_distributed_flags(pre)
    known = pre.parse_known_args(argv)[0]
    if not known.fast_gpu and not may_step_unreproducibly(known):
        deterministic_gpu()
    if known.distributed:
        try:
            init_distributed(known.coordinator, known.num_processes, known.process_id)
        except ValueError as e:  # no cluster found and no coordinator given
            pre.error(f"--distributed: {e} (outside SLURM pass --coordinator, "
                      "--num-processes and --process-id)")


def may_step_unreproducibly(known: argparse.Namespace) -> bool:
    """Whether the run's fitness may step on an engine that a GPU runs unreproducibly whatever
    XLA does (`Engine.unreproducible`: MuJoCo Warp orders contacts by thread timing): one the
    fitness kind steps on (`Fitness.engines`), the --physics it is given where it takes the
    run's choice, "auto" as `engines.may_take` says. A --resume reads both from the run's
    config.json. There XLA's deterministic ops would only cost time (4.6% of a Bad Walker
    fitness call at B = 1,024 on an H100, docs/benchmarks.md)."""
    physics, fitness = known.physics, known.fitness
    if known.resume and known.out:
        try:
            saved = json.loads((Path(known.out) / "config.json").read_text())
            physics, fitness = saved["physics"], saved["fitness"]
        except (OSError, ValueError, KeyError, TypeError):
            pass  # the parser says what is wrong with --out
    try:
        bound = get_fitness(fitness).engines
    except ValueError:
        return False  # the parser says the fitness is unknown
    steps_on = may_take(physics) if bound is None else [registered(e) for e in bound]
    return any(engine.unreproducible for engine in steps_on)


def gpu_defaults(space: str) -> dict:
    """The settings a run of `space` takes on a GPU (`Space.gpu_defaults`; an unknown space
    gets the common ones, `check` then says it is unknown), and the agents' that follow from
    them: epsilon anneals over half the steps, learning waits for one step's batch."""
    run = (get_space(space) if space in list_spaces() else Space).gpu_defaults()
    return run | {"explore_steps": run["steps"] // 2, "learning_starts": run["num_envs"]}


# What a --resume may change (the rest would not fit its checkpoint or would make another run):
# how far it runs, on which engine, how often it saves, and its confirm stage.
RESUME_MAY_CHANGE = ("steps", "physics", "checkpoint_every", "confirm", "confirm_controllers")


def parse_given(parser: argparse.ArgumentParser, argv) -> tuple[argparse.Namespace, set[str]]:
    """`argv` parsed once: the flags, defaults where not given, and the names of those given."""
    defaults = {}
    for action in parser._actions:  # absent unless given, then filled in
        if action.default is not argparse.SUPPRESS:
            defaults[action.dest], action.default = action.default, argparse.SUPPRESS
    args = parser.parse_args(argv)
    given = set(vars(args))
    for dest, value in defaults.items():
        setattr(args, dest, getattr(args, dest, value))
    return args, given


def resumed(parser, cfg: RunConfig, args, given: set[str]) -> RunConfig:
    """The saved `cfg` with the flags given that a --resume may change (`RESUME_MAY_CHANGE`),
    said in one line; exit 2 where a flag given would change another setting."""
    new = {f.name: getattr(args, f.name) for f in dataclasses.fields(RunConfig)
           if f.name in given and getattr(args, f.name) != getattr(cfg, f.name)}
    flag = lambda name: (  # noqa: E731
        f"--{name.removesuffix('_params')}.*" if name.endswith("_params")
        else "--" + name.replace("_", "-"))
    fixed = [name for name in new if name not in RESUME_MAY_CHANGE]
    if fixed:
        name = fixed[0]
        parser.error(f"--resume: {flag(name)} {new[name]} would make another run (saved: "
                     f"{getattr(cfg, name)}); a resume may change only "
                     f"{', '.join(map(flag, RESUME_MAY_CHANGE))}")
    if new and jax.process_index() == 0:
        print("--resume: " + ", ".join(f"{flag(k)} {getattr(cfg, k)} -> {v}"
                                       for k, v in new.items()) + "; the rest as saved")
    return dataclasses.replace(cfg, **new)


def parse(argv) -> tuple[RunConfig, Path, bool, bool]:
    """The run's config, directory, --resume and whether to draw best.gif; exits 2 with the
    reason (`parser.error`) on a bad flag."""
    gpu = jax.default_backend() == "gpu"
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--space", default=RunConfig().space)
    pre.add_argument("--agent", default=RunConfig().agent)
    pre.add_argument("--fitness", default=RunConfig().fitness)
    pre.add_argument("--task", default="walk")
    known = pre.parse_known_args(argv)[0]
    defaults = RunConfig(**gpu_defaults(known.space)) if gpu else RunConfig()
    parser = make_parser(defaults, known.agent, known.fitness, known.task)
    args, given = parse_given(parser, argv)
    args.agent_params = given_settings(args, "agent")
    args.fitness_params = given_settings(args, "fitness")
    args.task_params = given_settings(args, "task")
    given |= {name for name in ("agent_params", "fitness_params", "task_params")
              if getattr(args, name)}
    check(parser, args)
    if not args.resume:
        args.physics = physics(parser, args.physics, args.fitness)
    if args.steps is None and not args.resume:  # a --resume takes its run's
        args.steps = defaults.steps
    if args.controllers is None:  # a --resume takes its run's
        args.controllers = defaults.controllers
        if gpu and not args.resume:
            args.controllers = get_space(args.space).gpu_controllers(registered(args.physics))
    cfg = RunConfig(**{f.name: getattr(args, f.name) for f in dataclasses.fields(RunConfig)})
    classifier = str(Path(args.classifier).resolve()) if args.classifier else ""
    table = str(Path(args.table).resolve()) if args.table else ""
    cfg = dataclasses.replace(cfg, classifier=classifier, table=table)
    if args.resume and not args.out:
        parser.error("--resume needs --out, the run directory to continue")
    out = Path(args.out) if args.out else driver.fresh_run_dir(cfg)
    if args.resume and not (out / "config.json").is_file():  # checked before anything is made
        parser.error(f"--resume: no run in {str(out)!r} (no config.json)")
    try:
        out.mkdir(parents=True, exist_ok=True)
        # apart for two runs starting there at once, and for the processes of one on several hosts
        probe = out / f".write_test{jax.process_index()}-{os.getpid()}"
        probe.write_text("")
        probe.unlink()
    except OSError as e:
        parser.error(f"cannot write to --out {str(out)!r}: {e.strerror or e}")
    saved = out / "config.json"
    if args.resume:
        try:  # a run begun before tasks were named trained under the source's task
            config = {"task": "distance", **json.loads(saved.read_text())}
            cfg, default = RunConfig(**config), RunConfig()
            get_space(cfg.space)
            wrong = [f.name for f in dataclasses.fields(RunConfig)
                     if type(getattr(cfg, f.name)) is not type(getattr(default, f.name))
                     and not (type(getattr(cfg, f.name)) is int
                              and type(getattr(default, f.name)) is float)]
            if wrong:
                raise TypeError(f"wrong type of {', '.join(wrong)}")
            if bad_value(cfg):  # a value no run starts with (a seed past 64 bits, -5 steps)
                raise ValueError(bad_value(cfg))
        except (ValueError, TypeError) as e:  # cut short, an unknown key, space, type or value
            parser.error(f"--resume: {str(saved)!r} is not a run's config.json ({e})")
        args.classifier, args.table = classifier, table  # compared resolved
        cfg = resumed(parser, cfg, args, given)
        cfg = dataclasses.replace(cfg, physics=physics(parser, cfg.physics, cfg.fitness))
    elif (out / "checkpoints").exists():
        pid = checkpoints.holder(out)
        if pid is not None:  # a live run: not one to --resume (yet)
            print(f"python -m evojax_morph.run: error: {checkpoints.in_use(out, pid)}",
                  file=sys.stderr)
            raise SystemExit(2)
        parser.error(
            f"{str(out)!r} already holds a run: pass --resume to continue it, or another --out"
        )
    return cfg, out, args.resume, not args.no_gif


def make_parser(defaults: RunConfig, agent: str = "", fitness: str = "",
                task: str = "walk") -> argparse.ArgumentParser:
    """The run's flags in groups, their defaults `defaults`' (a RunConfig, GPU defaults
    applied), with `--agent.FIELD`, `--fitness.FIELD` and `--task.FIELD` for each setting of
    `agent`, of the fitness kind `fitness` and of `task` (`flags.add_settings`)."""
    parser = Parser(
        prog="python -m evojax_morph.run",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_run_flags(parser.add_argument_group("run"), defaults)
    add_fitness_flags(parser.add_argument_group("fitness"), defaults)
    add_fitness_settings(parser, fitness)
    add_task_settings(parser, task)
    add_agent_flags(parser.add_argument_group("agent"), defaults)
    add_agent_settings(parser, agent)
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


POSITIVE = ("steps", "num_envs", "train_steps", "controllers", "hidden", "chunk",
            "checkpoint_every", "explore_steps")  # flags checked positive (train_steps: >= 0)


def check(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Exits 2 with the reason (`parser.error`) where the flags cannot make a run; sets
    args.task where it was left to its default (a table's own, else walk)."""
    if jax.process_count() > 1 and not args.out:
        parser.error(
            "with several processes pass --out: every process must write the same run directory"
        )
    try:
        get_space(args.space)
        if args.task is not None:
            make_task(args.task)
    except ValueError as e:  # an unknown name, said by its registry
        parser.error(str(e))
    problem = bad_value(args)
    if problem:
        parser.error(problem)
    kind = get_fitness(args.fitness)
    inputs = Inputs(args.space, args.task or "", args.classifier, args.table,
                    args.controllers or 0)
    if not args.resume:  # a --resume takes its run's, checked when it began
        try:
            kind.check(inputs)
        except ValueError as e:
            parser.error(str(e))
        if args.task_params and not kind.trains_controllers:
            parser.error(f"--task.*: the {kind.name} fitness trains no controller under the "
                         "task (ppo does), so the task's settings would change nothing")
    if args.task is None:
        args.task = kind.default_task(inputs)


def bad_value(args) -> str | None:
    """Why the sizes and numbers of `args` (the flags, or a saved RunConfig) cannot make a run,
    or None where they can."""
    if not -(2**63) <= args.seed < 2**63:  # what a PRNG key takes
        return f"--seed must fit in 64 bits (-2**63 to 2**63 - 1), got {args.seed}"
    for name in POSITIVE:
        value = getattr(args, name)  # None: the default, set by `parse`
        if value is not None and value < (0 if name == "train_steps" else 1):
            return f"--{name.replace('_', '-')} must be positive, got {value}"
    if args.horizon < 0:
        return "--horizon must be >= 0"
    problem = agents.settings_problem(args.agent, args.num_envs, args.agent_params, {
        "population": args.population, "tournament": args.tournament})
    if problem:
        return problem
    try:
        fitness_params(args.fitness, args.fitness_params)
    except (ValueError, TypeError) as e:
        return f"--fitness.*: {e}"
    try:
        make_task(args.task or "walk", **args.task_params)
    except (ValueError, TypeError) as e:
        return f"--task.*: {e}"
    if args.confirm < 0:
        return "--confirm must be >= 0 (0: no confirm stage)"
    if args.confirm_controllers < 2:
        return "--confirm-controllers must be at least 2 (an interval needs 2 values)"
    return None


def physics(parser: argparse.ArgumentParser, name: str, fitness: str) -> str:
    """The engine `name` ("auto") resolves to for the fitness kind `fitness`
    (`resolve_physics`), checked: exit 2 with the reason if it cannot run here."""
    try:
        name, why = resolve_physics(fitness, name)
    except (RuntimeError, ValueError) as e:
        parser.error(f"--physics: {e}")
    if get_fitness(fitness).engines is None:  # it steps on the run's choice: say which
        print(f"physics: {name} ({why})", flush=True)
        if registered(name).unreproducible:
            print(f"physics: {registered(name).unreproducible}, so this run is not "
                  "reproducible from its seed, and XLA's deterministic ops are left off (they "
                  "would only cost time); --physics jax is reproducible (docs/benchmarks.md)",
                  flush=True)
    return name


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    start(args)  # before anything touches a JAX backend
    cfg, out, resume, gif = parse(argv)
    barrier("parsed")  # every process checked --out before any of them writes there
    full_precision()  # the agents' networks too, not only the PPO fitness (`full_precision`)
    persistent_cache()  # a second run of the same shapes skips XLA's compiles
    try:
        with checkpoints.lock(out):
            driver.execute(cfg, out, resume, gif)
    except (checkpoints.ResumeError, checkpoints.Damaged, checkpoints.Locked) as e:
        # Bad input, as the parser's errors: code 2 and why (no checkpoint reads, a file the
        # run reads back, a saved controller or confirmed.json, is damaged, or another run
        # holds --out).
        print(f"python -m evojax_morph.run: error: {e}", file=sys.stderr)
        raise SystemExit(2) from None
    except OSError as e:  # the machine's fault (a full disk, a folder made read-only): code 1
        print(f"python -m evojax_morph.run: error: {e.strerror or e} ({e.filename or out}); "
              f"{resumable(out)}", file=sys.stderr)
        raise SystemExit(1) from None
    return 0


def resumable(out: Path) -> str:
    """What a run stopped by a fault can do next: resume from its newest checkpoint, if any."""
    folder = out / "checkpoints"
    steps = [int(d.name) for d in folder.iterdir() if d.name.isdigit()] if folder.is_dir() else []
    if steps:
        return f"the run can --resume from step {max(steps)} (--out {out} --resume)"
    return "no checkpoint was saved: start it again"


if __name__ == "__main__":
    sys.exit(main())
