"""Evolve a robot body with a learning agent: `python -m evojax_morph.run --space bad_walker`.

Each environment step mutates the body of every parallel evolution once and evaluates all the
children in one batched fitness call; the agent learns which mutations raise fitness. The run
directory gets config.json, metrics.csv, TensorBoard events (tb/), curve.png, trajectory.png,
best.xml, summary.json and Orbax checkpoints; --resume continues a run from its last checkpoint.
The fitness batch is split across every visible device; --distributed spans several hosts.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import sys
from pathlib import Path

import jax
import numpy as np

import evojax_morph as em
from evojax_morph import agents, plots
from evojax_morph.agents import dqn
from evojax_morph.evolution import EvolutionEnv
from evojax_morph.fitness import make_fitness_fn
from evojax_morph.sharding import barrier, batch_mesh, init_distributed, replicated, to_host

FITNESS_SCALE = {"ppo": 100.0, "tame": 1.0}  # typical fitness magnitude; rewards are divided by it


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """Everything that defines a run; saved as config.json, reloaded by --resume."""

    space: str = "bad_walker"
    fitness: str = "ppo"  # ppo | predefined | tame
    classifier: str = ""  # tame: directory of the trained classifier
    agent: str = "ddqn"
    steps: int = 40  # environment steps; each mutates every parallel evolution once
    seed: int = 0
    num_envs: int = 4  # parallel evolutions, each step's fitness batch
    horizon: int = 0  # mutations per episode; 0 picks the space's default
    train_steps: int = 10_000  # PPO control steps per fitness evaluation
    hidden: int = 64  # GNN width
    explore_steps: int = 20  # environment steps over which epsilon anneals from 1 to 0.05
    learning_starts: int = 32  # transitions stored before the Q-network learns
    chunk: int = 5  # environment steps per jitted call
    checkpoint_every: int = 1  # chunks between checkpoints

    def resolved_horizon(self) -> int:
        if self.horizon:
            return self.horizon
        return em.make_space(self.space).max_nodes - 1 if self.space == "constructor" else 4


def gpu_defaults() -> dict:
    """On a GPU the same command evaluates a larger batch with a longer PPO budget."""
    return {"num_envs": 256, "train_steps": 50_000, "steps": 100, "explore_steps": 50, "learning_starts": 256,
            "chunk": 10, "checkpoint_every": 2}


def build(cfg: RunConfig):
    space = em.make_space(cfg.space)
    fit_cfg = em.FitnessConfig(
        kind=cfg.fitness, ppo=em.PPOConfig(train_steps=cfg.train_steps, num_envs=16, unroll_length=20),
        classifier=cfg.classifier,
    )
    init_fn, fitness_fn = make_fitness_fn(space, fit_cfg)
    horizon = cfg.resolved_horizon()
    env = EvolutionEnv(space, fitness_fn, init_fn, horizon=horizon, num_envs=cfg.num_envs)
    scale = FITNESS_SCALE.get(cfg.fitness, space.fitness_scale)
    extra = {
        "ddqn": {"epsilon_steps": cfg.explore_steps, "learning_starts": cfg.learning_starts, "batch_size": 32},
        "a2c": {"unroll": horizon},  # one update per episode of every parallel evolution
    }.get(cfg.agent, {})
    init, chunk, scores_fn = agents.make_agent(cfg.agent, env, cfg.hidden, 1.0 / scale, **extra)
    greedy_env = dataclasses.replace(env, num_envs=1)
    return space, env, greedy_env, init, chunk, scores_fn


def make_greedy_rollout(space, env1: EvolutionEnv, scores_fn):
    """`rollout(params, first, key)`: from m0 (as `first`, the evaluated start of env 0), the
    agent's greedy mutations, with each body's fitness. Compiled once, reused across calls."""

    @jax.jit
    def run(params, first, key):
        evo = jax.tree.map(lambda x: x[:1], first)

        def body(evo, key):
            obs = env1.observe(evo)
            action = dqn.masked_argmax(scores_fn(params, obs), obs.mask)
            _, evo, *_ = env1.step(key, evo, action)
            return evo, (evo.morph, evo.fitness[0], action[0])

        _, (morphs, fitness, actions) = jax.lax.scan(body, evo, jax.random.split(key, env1.horizon))
        return morphs, fitness, actions

    def rollout(params, first, key):
        morphs, fitness, actions = to_host(run(params, first, key))
        first_morph, first_fitness = to_host((first.morph, first.fitness))
        m0 = jax.tree.map(lambda x: x[0], first_morph)
        seq = [m0] + [jax.tree.map(lambda x, i=i: x[i, 0], morphs) for i in range(env1.horizon)]
        names = [f"node {a // space.num_mutations}: {space.mutation_names[a % space.num_mutations]}" for a in actions]
        return seq, [float(first_fitness[0])] + [float(f) for f in fitness], names

    return rollout


def checkpoint_manager(out: Path):
    import orbax.checkpoint as ocp

    options = ocp.CheckpointManagerOptions(max_to_keep=2, create=True)
    return ocp, ocp.CheckpointManager(out.resolve() / "checkpoints", options=options)


def fresh_run_dir(cfg: RunConfig) -> Path:
    """runs/SPACE-FITNESS-seedS, or the first of -2, -3, ... that does not exist yet."""
    base = Path("runs") / f"{cfg.space}-{cfg.fitness}-seed{cfg.seed}"
    out, n = base, 1
    while out.exists():
        n += 1
        out = base.with_name(f"{base.name}-{n}")
    return out


def add_distributed_flags(parser: argparse.ArgumentParser) -> None:
    add = parser.add_argument
    add("--distributed", action="store_true",
        help="call jax.distributed.initialize() first: one process per host, all with the same flags and --out; "
        "under SLURM nothing else is needed")
    add("--coordinator", default=None, help="with --distributed outside SLURM: host:port of process 0")
    add("--num-processes", type=int, default=None, help="with --distributed outside SLURM: number of processes")
    add("--process-id", type=int, default=None, help="with --distributed outside SLURM: this process's id")


def start_distributed(argv) -> None:
    """Must run before anything touches a JAX backend, so before the main parser's defaults."""
    pre = argparse.ArgumentParser(add_help=False)
    add_distributed_flags(pre)
    known, _ = pre.parse_known_args(argv)
    if known.distributed:
        init_distributed(known.coordinator, known.num_processes, known.process_id)


def parse(argv) -> tuple[RunConfig, Path, bool]:
    parser = argparse.ArgumentParser(
        prog="python -m evojax_morph.run", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    gpu = jax.default_backend() == "gpu"
    defaults = dataclasses.replace(RunConfig(), **gpu_defaults()) if gpu else RunConfig()
    add = parser.add_argument
    add("--space", default=defaults.space, help=f"morphology space: {', '.join(em.list_spaces())}")
    add("--fitness", default=defaults.fitness, choices=["ppo", "predefined", "tame"],
        help="ppo: return of a controller trained with PPO on the body (inherited from the parent); "
        "predefined: the space's hand-crafted fitness; tame: task-agnostic, with --classifier")
    add("--classifier", default="", help="tame: directory of a classifier trained by `python -m evojax_morph.tame`")
    add("--agent", default=defaults.agent, choices=list(agents.AGENTS),
        help="who chooses the mutations: ddqn (Double-DQN), a2c (actor-critic), or the baselines random "
        "(random mutation walks) and evolution (a population, random mutations, the fittest survive)")
    add("--steps", type=int, default=defaults.steps, help="environment steps; each mutates every parallel evolution once")
    add("--seed", type=int, default=defaults.seed, help="seed of every random choice of the run")
    add("--out", default=None, help="run directory (default: a new runs/SPACE-FITNESS-seedS[-N])")
    add("--resume", action="store_true", help="continue the run in --out from its last checkpoint, up to --steps")
    add("--num-envs", type=int, default=defaults.num_envs, help="parallel evolutions: the fitness batch of a step")
    add("--horizon", type=int, default=defaults.horizon, help="mutations per episode (0: 4 for bad_walker, the capacity for constructor)")
    add("--train-steps", type=int, default=defaults.train_steps, help="PPO control steps per fitness evaluation")
    add("--hidden", type=int, default=defaults.hidden, help="width of the agent's GNN")
    add("--explore-steps", type=int, default=defaults.explore_steps, help="ddqn: environment steps of epsilon annealing")
    add("--learning-starts", type=int, default=defaults.learning_starts, help="ddqn: transitions stored before learning")
    add("--chunk", type=int, default=defaults.chunk, help="environment steps per jitted call (progress and checkpoint granularity)")
    add("--checkpoint-every", type=int, default=defaults.checkpoint_every, help="chunks between checkpoints")
    add_distributed_flags(parser)
    args = parser.parse_args(argv)
    if jax.process_count() > 1 and not args.out:
        parser.error("with several processes pass --out: every process must write the same run directory")

    if args.space not in em.list_spaces():
        parser.error(f"unknown space {args.space!r}; known spaces: {', '.join(em.list_spaces())}")
    for name in ("steps", "num_envs", "train_steps", "hidden", "chunk", "checkpoint_every", "explore_steps"):
        if getattr(args, name) < (0 if name == "train_steps" else 1):
            parser.error(f"--{name.replace('_', '-')} must be positive, got {getattr(args, name)}")
    if args.horizon < 0:
        parser.error("--horizon must be >= 0")
    if args.fitness == "tame" and not args.resume:
        meta = Path(args.classifier) / "tame.json"
        if not args.classifier or not meta.exists():
            parser.error("--fitness tame needs --classifier DIR, a classifier trained by "
                         f"`python -m evojax_morph.tame --space {args.space} --out DIR`")
        if json.loads(meta.read_text())["space"] != args.space:
            parser.error(f"the classifier in {args.classifier!r} was trained on another space than {args.space}")
    cfg = RunConfig(
        space=args.space, fitness=args.fitness, agent=args.agent, steps=args.steps, seed=args.seed,
        classifier=str(Path(args.classifier).resolve()) if args.classifier else "",
        num_envs=args.num_envs, horizon=args.horizon, train_steps=args.train_steps, hidden=args.hidden,
        explore_steps=args.explore_steps, learning_starts=args.learning_starts,
        chunk=args.chunk, checkpoint_every=args.checkpoint_every,
    )
    out = Path(args.out) if args.out else fresh_run_dir(cfg)
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
        cfg = dataclasses.replace(RunConfig(**json.loads(saved.read_text())), steps=args.steps)
    elif (out / "checkpoints").exists():
        parser.error(f"{str(out)!r} already holds a run: pass --resume to continue it, or another --out")
    return cfg, out, args.resume


def main(argv: list[str] | None = None) -> int:
    start_distributed(sys.argv[1:] if argv is None else argv)
    cfg, out, resume = parse(argv)
    barrier("parsed")  # every process checked --out before any of them writes there
    jax.config.update("jax_default_matmul_precision", "highest")
    lead = jax.process_index() == 0  # the process that writes files and prints
    if lead:
        (out / "config.json").write_text(json.dumps(dataclasses.asdict(cfg), indent=1))
    space, env, greedy_env, init, chunk_fn, scores_fn = build(cfg)
    ocp, manager = checkpoint_manager(out)
    log = print if lead else (lambda *a, **k: None)
    log(f"evojax_morph: {cfg.agent} on {cfg.space} with {cfg.fitness} fitness, {cfg.num_envs} parallel "
        f"evolutions x {cfg.steps} steps, horizon {env.horizon}, on {jax.device_count()} {jax.default_backend()} "
        f"device(s) in {jax.process_count()} process(es); run in {out}")

    key = jax.random.PRNGKey(cfg.seed)
    key_init, key_greedy = jax.random.split(key)
    rows = []
    if resume and manager.latest_step() is not None:
        step = manager.latest_step()
        # Restored onto this run's devices, however many the saving run had.
        on_mesh = lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=replicated(batch_mesh()))
        abstract = jax.tree.map(on_mesh, jax.eval_shape(init, key_init))
        state = manager.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore(abstract)))["state"]
        with open(out / "metrics.csv") as f:
            rows = [r for r in csv.DictReader(f) if int(r["step"]) <= step]
        log(f"resumed at step {step}")
    else:
        log("evaluating m0 in every evolution...")
        state = init(key_init)
        step = 0

    from tensorboardX import SummaryWriter
    from tqdm import tqdm

    writer = SummaryWriter(str(out / "tb")) if lead else None
    bar = tqdm(total=cfg.steps, initial=min(step, cfg.steps), unit="step", dynamic_ncols=True, file=sys.stdout,
               disable=not lead)
    chunks_done = 0
    while step < cfg.steps:
        n = min(cfg.chunk, cfg.steps - step)
        state, metrics = chunk_fn(state, n)
        metrics = to_host(metrics)
        for i in range(n):
            reward = metrics["reward"][i]
            row = {
                "step": step + i + 1,
                "reward_median": float(np.median(reward)),
                "reward_q25": float(np.quantile(reward, 0.25)),
                "reward_q75": float(np.quantile(reward, 0.75)),
                "fitness_mean": float(np.mean(metrics["fitness"][i])),
            }
            row.update({k: float(v[i]) for k, v in metrics.items() if k not in ("reward", "fitness")})
            rows.append(row)
            for name, value in row.items():
                if lead and name != "step":
                    writer.add_scalar(name.replace("_", "/", 1), value, row["step"])
        step += n
        chunks_done += 1
        bar.update(n)
        bar.set_postfix(reward=f"{row['reward_median']:.3g}", best=f"{row['best_fitness']:.3g}")
        if lead:
            with open(out / "metrics.csv", "w", newline="") as f:
                w = csv.DictWriter(f, fieldnames=list(rows[0]))
                w.writeheader()
                w.writerows(rows)
        if chunks_done % cfg.checkpoint_every == 0 or step >= cfg.steps:
            manager.save(step, args=ocp.args.Composite(state=ocp.args.StandardSave(state)))
    bar.close()
    manager.wait_until_finished()

    # RESULTS
    best, best_fitness = to_host((state.best_morph, state.best_fitness))
    greedy = None
    if scores_fn is not None:  # the baselines have no policy to roll out
        greedy = make_greedy_rollout(space, greedy_env, scores_fn)(state.params, state.first, key_greedy)
    if not lead:
        return 0
    writer.close()
    col = lambda name: np.array([r[name] for r in rows], float)  # resumed rows are strings
    plots.plot_curve(out / "curve.png", col("step"), col("reward_median"), col("reward_q25"), col("reward_q75"))
    (out / "best.xml").write_text(space.to_mjcf(best))
    summary = {"best_fitness": float(best_fitness), "best_morphology": best.to_dict(), "env_steps": step,
               "greedy_trajectory": None}
    print(f"\nbest morphology (fitness {float(best_fitness):.4g}):")
    print(space.format(best))
    written = "curve.png best.xml summary.json metrics.csv tb/ checkpoints/"
    if greedy is not None:
        morphs, fitness, actions = greedy
        plots.plot_trajectory(out / "trajectory.png", space, morphs, fitness, actions)
        summary["greedy_trajectory"] = [
            {"action": a, "fitness": f, "morphology": m.to_dict()} for a, f, m in zip(["m0"] + actions, fitness, morphs)
        ]
        print("\ngreedy trajectory from m0:")
        for a, f in zip(["m0"] + actions, fitness):
            print(f"  {a:<32} fitness {f:.4g}")
        print(f"\nfinal greedy morphology:\n{space.format(morphs[-1])}")
        written = "trajectory.png " + written
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    print(f"\nwrote {out}/: {written}")
    return 0

if __name__ == "__main__":
    sys.exit(main())
