"""The run command's process before its work: an agent's, a fitness kind's and the task's
settings as its flags (`flags.add_settings`), and what must be set before anything starts a
JAX backend (`start`: XLA's deterministic GPU ops, the start of a run over several hosts)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from evojax_morph import agents
from evojax_morph.fitnesses import get_fitness, list_fitnesses
from evojax_morph.flags import Parser, add_settings
from evojax_morph.physics.determinism import deterministic_gpu
from evojax_morph.physics.engines import AUTO, may_take, registered
from evojax_morph.search.pipeline import RunConfig
from evojax_morph.sharding import init_distributed
from evojax_morph.tasks import TaskConfig, list_tasks, make_task


def add_agent_settings(parser, agent: str) -> None:
    """A group of `--agent.FIELD` flags on `parser` for the registered agent `agent`'s
    config, if it has one (`add_settings`)."""
    if agent in agents.list_agents() and agents.get_agent(agent).config is not None:
        add_settings(parser.add_argument_group(
            f"{agent}'s own settings (--agent.FIELD: any field of its config, over what the "
            "flags above make of it)"), "agent", agents.get_agent(agent).config)


def add_fitness_settings(parser, fitness: str) -> None:
    """A group of `--fitness.FIELD` flags on `parser` for the registered fitness kind
    `fitness`'s params, if it has any (`add_settings`)."""
    if fitness in list_fitnesses() and get_fitness(fitness).params is not None:
        add_settings(parser.add_argument_group(
            f"the {fitness} fitness's own settings (--fitness.FIELD: any field of its params)"),
            "fitness", get_fitness(fitness).params)


def add_task_settings(parser, task: str) -> None:
    """A group of `--task.FIELD` flags on `parser`: the settings of the registered task `task`
    (`TaskConfig`, its values the defaults; an unknown name: the class's) but its name, which
    `--task` gives (`add_settings`)."""
    add_settings(parser.add_argument_group(
        f"the {task} task's settings (--task.FIELD: any field of its `TaskConfig`, for a "
        "fitness that trains controllers under it: ppo)"), "task",
        make_task(task) if task in list_tasks() else TaskConfig, skip=("name",))


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
