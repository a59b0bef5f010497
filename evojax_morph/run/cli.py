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
from evojax_morph.fitnesses import (
    Inputs,
    fitness_params,
    get_fitness,
    list_fitnesses,
    resolve_physics,
)
from evojax_morph.flags import Parser, given_settings
from evojax_morph.physics.determinism import full_precision, persistent_cache
from evojax_morph.physics.engines import AUTO, list_engines, registered
from evojax_morph.records import checkpoints
from evojax_morph.run import driver
from evojax_morph.run.process import (
    add_agent_settings,
    add_distributed_flags,
    add_fitness_settings,
    add_task_settings,
    start,
)
from evojax_morph.search.pipeline import RunConfig
from evojax_morph.sharding import barrier
from evojax_morph.spaces import Space, get_space, list_spaces
from evojax_morph.tasks import list_tasks, make_task


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


def add_run_flags(group, defaults: RunConfig) -> None:
    """The space, seed, run directory and the size of the run."""
    add = group.add_argument
    add("--space", default=defaults.space, help=f"morphology space: {', '.join(list_spaces())}")
    add("--steps", type=int, default=None,
        help=f"environment steps; each mutates every parallel evolution once (default: "
        f"{defaults.steps}; a --resume: its run's)")
    add("--seed", type=int, default=defaults.seed, help="seed of every random choice of the run")
    add("--out", default=None, help="run directory (default: a new runs/SPACE-FITNESS-seedS[-N])")
    add("--resume", action="store_true",
        help="continue the run in --out from its last checkpoint, up to its --steps or a new one")
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
    add("--table", default="",
        help="table: the landscape table (.npz) built by `python -m experiments.build_tables` "
        "(default: the space's packaged one, evojax_morph/fitnesses/tables/SPACE.npz)")
    add("--classifier", default="",
        help="tame: directory of a classifier trained by `python -m evojax_morph.tame`")
    add("--train-steps", type=int, default=defaults.train_steps,
        help="PPO control steps per fitness evaluation")
    add("--controllers", type=int, default=None,
        help="independent PPO controllers trained per body; the fitness is their mean (default: "
        "1 on a CPU; on a GPU 8 with Warp, 4 with the JAX engine: docs/benchmarks.md)")
    add("--physics", default="auto", choices=[AUTO] + list_engines(),
        help="the engine that steps the fitness's worlds: jax (MJX's JAX engine), warp (MuJoCo "
        "Warp, `pip install 'evojax_morph[warp]'`), or auto: warp where it runs on a GPU, else "
        "jax (the run says which it took)")
    add("--size-classes", dest="classes", action="store_true",
        help="ppo: train each body on the smallest of the space's size-class templates that "
        "holds it, not the one padded template (the Constructor's; evojax_morph.physics.classes)")


def add_agent_flags(group, defaults: RunConfig) -> None:
    """Who chooses the mutations, and how it learns."""
    add = group.add_argument
    add(
        "--agent",
        default=defaults.agent,
        choices=agents.list_agents(),
        help="who chooses the mutations: ddqn (Double-DQN), dqn (plain DQN), qrdqn "
        "(quantile-regression DQN), bootdqn (bootstrapped DQN: 10 Q-heads, an episode greedy "
        "on one), a2c (actor-critic), predictor (a GNN ensemble that learns body -> fitness "
        "from every evaluation picks each parent's child among walks of up to 3 mutations; "
        "parents as regularized_evolution's), or the baselines "
        "random (random mutation walks), evolution ((mu + lambda), its survivors evaluated "
        "again every step and ranked by their mean) and regularized_evolution (aging "
        "evolution: tournaments pick the parents, each child replaces the oldest member)",
    )
    add("--hidden", type=int, default=defaults.hidden, help="width of the agent's GNN")
    add("--explore-steps", type=int, default=defaults.explore_steps,
        help="ddqn, dqn, qrdqn: environment steps of epsilon annealing (bootdqn: none)")
    add("--learning-starts", type=int, default=defaults.learning_starts,
        help="ddqn, dqn, qrdqn, bootdqn: transitions stored before learning")
    add("--population", type=int, default=defaults.population,
        help="regularized_evolution, predictor: members, at least --num-envs (0: 2 x "
        "--num-envs)")
    add("--tournament", type=int, default=defaults.tournament,
        help="regularized_evolution, predictor: members sampled per tournament, 1 to "
        "--population (0: an eighth of the population)")


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
        help="fresh evaluations per confirmed body and per body of the greedy trajectory, "
        "which joins the confirm call (each one controller trained from scratch; "
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
