"""The run command's flags in their groups (`run.cli.make_parser` puts them together): the
run's, the fitness's, the agent's and the confirm stage's, with their defaults and help, and
an agent's, a fitness kind's and the task's own settings as `--agent.FIELD`, `--fitness.FIELD`
and `--task.FIELD` (`flags.add_settings`)."""

from __future__ import annotations

from evojax_morph import agents
from evojax_morph.fitnesses import get_fitness, list_fitnesses
from evojax_morph.flags import add_settings
from evojax_morph.physics.engines import AUTO, list_engines
from evojax_morph.search.pipeline import RunConfig
from evojax_morph.spaces import list_spaces
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
