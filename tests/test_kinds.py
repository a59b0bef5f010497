"""Kinds know their rules: no module of the library compares a registered kind's name outside
that kind's own module and its registry (the run asks the kind instead, issue 64)."""

import ast
import csv
import dataclasses
import json
from pathlib import Path

import jax.numpy as jnp
import pytest

import evojax_morph as em
from evojax_morph import agents
from evojax_morph.physics import engines

PACKAGE = Path(em.__file__).parent
# Where each kind's names may be compared: its own modules and its registry.
HOMES = {
    "space": (em.list_spaces(), ("spaces/",)),
    "fitness": (em.list_fitnesses(), ("fitnesses/",)),
    "agent": (agents.list_agents(), ("agents/",)),
    "engine": (engines.list_engines(), ("physics/engines.py", "physics/warp")),  # warp*.py
}


def _strings(node: ast.AST) -> set[str]:
    """The string constants of a compared value, a tuple, list or set of them included."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return {node.value}
    if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
        return set().union(*(_strings(e) for e in node.elts)) if node.elts else set()
    return set()


def test_no_kind_name_is_compared_outside_its_home():
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        where = path.relative_to(PACKAGE).as_posix()
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.Compare):
                continue
            compared = set().union(*(_strings(side) for side in [node.left, *node.comparators]))
            for kind, (names, homes) in HOMES.items():
                if compared & set(names) and not where.startswith(homes):
                    found.append(f"{where}:{node.lineno}: {kind} {ast.unparse(node)}")
    assert not found, "\n".join(found)


def test_the_check_sees_a_compare():
    """The scan finds what it looks for (a compare of the kind the run used to make)."""
    tree = ast.parse('if cfg.physics == "warp" or space in ("constructor",): pass')
    compares = [n for n in ast.walk(tree) if isinstance(n, ast.Compare)]
    assert [_strings(c.comparators[0]) for c in compares] == [{"warp"}, {"constructor"}]


def test_every_sort_of_kind_has_one_registry():
    """Spaces, fitnesses, agents, engines and tasks are registered the same way
    (`registry.Registry`): an unknown name's error names the sort and the known ones, `list`
    keeps each sort's order, and a kind registered later is got back and listed."""
    from evojax_morph import spaces, tasks
    from evojax_morph.fitnesses import base as fitnesses
    from evojax_morph.registry import Registry

    found = {"space": spaces._REGISTRY, "fitness": fitnesses._REGISTRY,
             "agent": agents._REGISTRY, "physics": engines._REGISTRY, "task": tasks.TASKS}
    listed = {"space": em.list_spaces(), "fitness": em.list_fitnesses(),
              "agent": agents.list_agents(), "physics": engines.list_engines(),
              "task": em.list_tasks()}
    for what, registry in found.items():
        assert isinstance(registry, Registry) and registry.list() == listed[what]
        try:
            registry.get("nope")
        except ValueError as e:
            assert str(e) == (f"unknown {what} 'nope'; known {registry.plural}: "
                              f"{', '.join(listed[what])}")
        else:
            raise AssertionError(f"{what}: an unknown name got back")
    assert em.list_spaces() == sorted(em.list_spaces())  # sorted; agents as registered
    assert agents.list_agents()[:2] == ["ddqn", "dqn"]
    mine = Registry("thing", sort=True)
    mine.register(tasks.TaskConfig(name="b"), tasks.TaskConfig(name="a"))
    assert mine.list() == ["a", "b"] and mine.get("b").name == "b" and "a" in mine


@dataclasses.dataclass(frozen=True)
class NthConfig:
    nth: int = 0  # which valid mutation, counted from the first
    loud: bool = False  # a second setting, of another type


def make_nth(env, cfg: NthConfig):
    """A toy agent: always the `nth` valid mutation (modulo how many are valid)."""

    def act(learner, keys, obs, step):
        rank = jnp.cumsum(obs.mask, axis=1) - 1
        wanted = cfg.nth % obs.mask.sum(axis=1, keepdims=True)
        action = jnp.argmax(obs.mask & (rank == wanted), axis=1).astype(jnp.int32)
        return action, {"nth": jnp.full((), cfg.nth + 100 * cfg.loud, jnp.float32)}

    return agents.Policy(keys=(0, 1, 0), init=lambda keys, obs: None, act=act,
                         learn=lambda learner, keys, transition, step: (learner, {}),
                         scores=None)


def test_a_new_agent_with_a_setting_runs_from_the_command_line(tmp_path, monkeypatch, capsys):
    """An agent registered with a settings dataclass and nothing else gets `--agent.FIELD`
    flags (typed, with its comment as help), its run records the setting in config.json and
    acts on it; a bad value, a setting of another agent and a --resume that would change it
    exit 2; a shared setting given as `--agent.population` resolves the tournament from it."""
    from evojax_morph.run import cli
    from evojax_morph.search.pipeline import RunConfig, agent_config, build

    monkeypatch.setitem(agents._REGISTRY, "nth", agents.AgentKind("nth", NthConfig, make_nth))
    with pytest.raises(SystemExit):
        cli.main(["--agent", "nth", "--help"])
    assert "--agent.nth INT which valid mutation, counted from the first (its default 0)" in (
        " ".join(capsys.readouterr().out.split()))
    tiny = ["--space", "bad_walker", "--fitness", "table", "--num-envs", "2", "--steps", "2",
            "--chunk", "2", "--confirm", "0", "--no-gif", "--agent", "nth"]
    out = tmp_path / "run"
    assert cli.main(tiny + ["--agent.nth", "3", "--agent.loud", "true", "--out", str(out)]) == 0
    assert json.loads((out / "config.json").read_text())["agent_params"] == {"nth": 3,
                                                                              "loud": True}
    rows = list(csv.DictReader((out / "metrics.csv").open()))
    assert [float(r["nth"]) for r in rows] == [103.0, 103.0]
    for bad, why in ((["--agent.loud", "maybe"], "true or false, not 'maybe'"),
                     (["--agent.reach", "2"], "unrecognized arguments: --agent.reach 2")):
        with pytest.raises(SystemExit) as e:
            cli.main(tiny + bad + ["--out", str(tmp_path / "bad")])
        assert e.value.code == 2 and why in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        cli.main(tiny + ["--agent.nth", "4", "--out", str(out), "--resume"])
    assert e.value.code == 2
    assert "--agent.* {'nth': 4} would make another run" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        cli.main(["--agent", "predictor", "--agent.reach", "0", "--fitness", "table",
                  "--out", str(tmp_path / "bad")])
    assert e.value.code == 2 and "a reach of at least 1" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()

    p = build(RunConfig(fitness="table", agent="random", num_envs=4))
    got = agent_config(RunConfig(fitness="table", agent="regularized_evolution", num_envs=4,
                                 agent_params={"population": 64}), p.env)
    assert (got.population, got.tournament) == (64, 8)
    # the agents' reward scale comes with the env (1 / the fitness kind's `scale`, 100 for the
    # table), and `--agent.reward_scale` is set over it
    assert p.env.reward_scale == 1 / 100
    env = dataclasses.replace(p.env, reward_scale=0.25)
    for name in ("ddqn", "qrdqn", "a2c"):
        assert agent_config(RunConfig(fitness="table", agent=name), env).reward_scale == 0.25
    assert agent_config(RunConfig(fitness="table", agent_params={"reward_scale": 2.0}),
                        env).reward_scale == 2.0


@dataclasses.dataclass(frozen=True)
class LevelParams:
    level: float = 1.0  # the fitness of every body

    def __post_init__(self):
        if self.level <= 0:
            raise ValueError(f"a level above 0, not {self.level}")


def make_level(space, cfg):
    """A toy fitness: every body scores `cfg.params.level`."""
    from evojax_morph.fitnesses.base import untrained_result

    def evaluate(keys, morphs, params):
        fitness = jnp.full(morphs.active.shape[:1], cfg.params.level, jnp.float32)
        return untrained_result(fitness, jnp.zeros_like(fitness, bool), params, env_steps=0)

    return None, evaluate


def test_a_new_fitness_with_a_setting_runs_from_the_command_line(tmp_path, monkeypatch, capsys):
    """A fitness kind registered with a params dataclass and nothing else gets `--fitness.FIELD`
    flags (typed, with its comment as help), its run records the setting in config.json and
    its make reads it; a value its __post_init__ refuses and a --resume that would change it
    exit 2 before anything is made; a kind without settings takes none, and its config writes
    none (saved controllers' metadata as before)."""
    from evojax_morph.fitnesses import FitnessConfig, base
    from evojax_morph.run import cli

    kind = base.Fitness("level", validate=lambda cfg: None, scale=lambda space: 1.0,
                        make=make_level, deterministic=True, engines=(), params=LevelParams)
    monkeypatch.setitem(base._REGISTRY, "level", kind)
    with pytest.raises(SystemExit):
        cli.main(["--fitness", "level", "--help"])
    assert "--fitness.level FLOAT the fitness of every body (its default 1.0)" in (
        " ".join(capsys.readouterr().out.split()))
    tiny = ["--space", "bad_walker", "--agent", "random", "--num-envs", "2", "--steps", "2",
            "--chunk", "2", "--no-gif", "--fitness", "level"]
    out = tmp_path / "run"
    assert cli.main(tiny + ["--fitness.level", "2.5", "--out", str(out)]) == 0
    assert json.loads((out / "config.json").read_text())["fitness_params"] == {"level": 2.5}
    rows = list(csv.DictReader((out / "metrics.csv").open()))
    assert [float(r["fitness_mean"]) for r in rows] == [2.5, 2.5]
    for bad, why in ((["--fitness.level", "-1"], "--fitness.*: a level above 0, not -1.0"),
                     (["--fitness.level", "high"], "invalid float value: 'high'"),
                     (["--fitness", "predefined", "--fitness.level", "2"],
                      "unrecognized arguments: --fitness.level 2")):
        with pytest.raises(SystemExit) as e:
            cli.main(tiny + bad + ["--out", str(tmp_path / "bad")])
        assert e.value.code == 2 and why in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()
    with pytest.raises(SystemExit) as e:
        cli.main(tiny + ["--fitness.level", "3", "--out", str(out), "--resume"])
    assert e.value.code == 2
    assert "--fitness.* {'level': 3.0} would make another run" in capsys.readouterr().err

    cfg = FitnessConfig(kind="level", params=LevelParams(4.0))
    assert FitnessConfig.from_dict(cfg.to_dict()) == cfg and hash(cfg) == hash(
        FitnessConfig.from_dict(cfg.to_dict()))
    assert FitnessConfig(kind="level").params == LevelParams()
    assert "params" not in FitnessConfig().to_dict()
    with pytest.raises(ValueError, match="the ppo fitness's settings are none"):
        FitnessConfig(params=LevelParams())


def test_a_tasks_settings_are_flags_that_reach_the_ppo_fitness(tmp_path, capsys):
    """`--task.FIELD` for each setting of the task but its name, its help giving the named
    task's value as the default, kept in config.json as task_params and set over the
    registered task's in the fitness the run builds; a value `TaskConfig` refuses, a fitness
    that trains no controller under the task and a --resume that would change them exit 2."""
    from evojax_morph.run import cli
    from evojax_morph.search.pipeline import RunConfig, build

    for task, default in (("walk", 0.5), ("distance", 0.0)):
        with pytest.raises(SystemExit):
            cli.main(["--task", task, "--help"])
        flags = " ".join(capsys.readouterr().out.split())
        assert f"--task.healthy_reward FLOAT per step alive; 0 keeps a body that cannot move at " \
               f"fitness 0 (its default {default})" in flags and "--task.name" not in flags
    out = tmp_path / "run"
    cfg, *_ = cli.parse(["--num-envs", "1", "--task.healthy_reward", "0.25",
                         "--task.episode_length", "40", "--out", str(out)])
    assert cfg.task_params == {"healthy_reward": 0.25, "episode_length": 40}
    task = build(cfg).fitness.task
    assert task == em.make_task("walk", healthy_reward=0.25, episode_length=40)
    (out / "config.json").write_text(json.dumps(dataclasses.asdict(cfg)))
    for bad, why in ((["--task.frame_skip", "0"], "--task.*: a task needs frame_skip"),
                     (["--fitness", "predefined", "--task.ctrl_cost", "0"],
                      "--task.*: the predefined fitness trains no controller under the task"),
                     (["--task.name", "distance"], "unrecognized arguments: --task.name"),
                     (["--task.healthy_reward", "0.3", "--out", str(out), "--resume"],
                      "--task.* {'healthy_reward': 0.3} would make another run")):
        with pytest.raises(SystemExit) as e:
            cli.parse(bad + ([] if "--resume" in bad else ["--out", str(tmp_path / "bad")]))
        assert e.value.code == 2 and why in capsys.readouterr().err, bad
    assert not (tmp_path / "bad").exists()
    table = RunConfig(space="bad_walker", fitness="table", task_params={"ctrl_cost": 0.0})
    with pytest.raises(ValueError, match="a table fitness takes no task settings"):
        build(table)  # what the library refuses too
