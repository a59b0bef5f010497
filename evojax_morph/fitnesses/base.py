"""What every fitness kind provides, its settings, its result, and the registry of kinds."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from evojax_morph.fitness_result import FitnessResult
from evojax_morph.physics.engines import AUTO, list_engines, resolve
from evojax_morph.ppo import PPOConfig
from evojax_morph.registry import Registry
from evojax_morph.spaces import Space
from evojax_morph.tasks import TaskConfig


@dataclasses.dataclass(frozen=True)
class FitnessConfig:
    """Which fitness, and the settings of each kind (a kind reads only its own).

    Attributes:
      kind: a registered fitness (`list_fitnesses()`): "ppo" (the return of a controller trained
        with PPO on the body, NGE-style), "predefined" (the space's hand-crafted deterministic
        fitness) or "tame" (task-agnostic: how well random motor primitives can be told apart
        from where they leave the body, with a pre-trained classifier; see `evojax_morph.tame`)
        or "table" (the mean of `ppo.controllers` stored PPO results of the body, drawn from a
        landscape table; no controllers, no inheritance; see `fitnesses.table`).
      task: the locomotion task the PPO controller learns (`make_task(name)`; its name says
        which registered task it started from).
      ppo: the inner PPO's settings and budget.
      classifier: for "tame", the directory of a classifier saved by `python -m evojax_morph.tame`.
      physics: the engine that steps the worlds of the kinds that simulate ("jax" or "warp",
        `evojax_morph.physics.engines`; the CLI resolves its "auto" before it gets here).
      table: for "table", the .npz of a table built by `python -m experiments.build_tables`;
        "" for the space's packaged table (`evojax_morph/fitnesses/tables/SPACE.npz`).
      classes: for "ppo", train each body on the smallest of the space's size classes that holds
        it (`evojax_morph.physics.classes`; spaces without classes ignore it).
      params: the kind's own settings, an instance of its `Fitness.params` (None: its defaults,
        or nothing for a kind without settings); the CLI's `--fitness.FIELD`.
    """

    kind: str = "ppo"
    task: TaskConfig = TaskConfig()
    ppo: PPOConfig = PPOConfig()
    classifier: str = ""
    physics: str = "jax"
    table: str = ""
    classes: bool = False
    params: Any = None

    def __post_init__(self):
        if self.physics not in list_engines():
            raise ValueError(
                f"unknown physics {self.physics!r}; known physics: {', '.join(list_engines())}"
            )
        kind = get_fitness(self.kind)
        if kind.engines and self.physics not in kind.engines:
            raise ValueError(f"{_bound(kind)}, not {self.physics!r}")
        if self.params is None and kind.params is not None:
            object.__setattr__(self, "params", kind.params())
        if not (self.params is None if kind.params is None
                else isinstance(self.params, kind.params)):
            raise ValueError(f"the {kind.name} fitness's settings are "
                             f"{'none' if kind.params is None else kind.params.__name__}, "
                             f"not {self.params!r}")
        kind.validate(self)

    def with_controllers(self, k: int) -> FitnessConfig:
        """This config with K = `k` controllers per body."""
        return dataclasses.replace(self, ppo=dataclasses.replace(self.ppo, controllers=k))

    def to_dict(self) -> dict:
        """JSON-ready settings, `params` only for a kind with settings; `from_dict` rebuilds
        the same config."""
        d = dataclasses.asdict(self)
        return d if self.params is not None else {k: v for k, v in d.items() if k != "params"}

    @classmethod
    def from_dict(cls, d: dict) -> FitnessConfig:
        tuples = lambda c: {k: tuple(v) if isinstance(v, list) else v for k, v in c.items()}
        own, ppo = d.get("params"), tuples(d["ppo"])
        if "num_envs" in ppo:  # saved before PPOConfig.num_envs was named worlds_per_controller
            ppo["worlds_per_controller"] = ppo.pop("num_envs")
        return cls(kind=d["kind"], task=TaskConfig(**d["task"]), ppo=PPOConfig(**ppo),
                   classifier=d["classifier"], physics=d.get("physics", "jax"),
                   table=d.get("table", ""), classes=d.get("classes", False),
                   params=None if own is None else get_fitness(d["kind"]).params(**tuples(own)))


def untrained_result(fitness: jax.Array, diverged: jax.Array, params, env_steps: int):
    """The `FitnessResult` of a fitness that trains nothing and runs no episode it could
    measure a gait in: zero spread, return and entropy, NaN distance and upright, and the given
    controllers passed through unchanged."""
    zeros, nan = jnp.zeros_like(fitness), jnp.full_like(fitness, jnp.nan)
    return FitnessResult(fitness, zeros, diverged, params, zeros, zeros, nan, nan,
                         env_steps=env_steps)


class Inputs(NamedTuple):
    """What a run gives a fitness kind beyond its settings: the space's name, the task asked for
    ("": none), the files the kind reads (`FitnessConfig`'s classifier and table) and the
    controllers a body asked for (0: the run's default)."""

    space: str
    task: str = ""
    classifier: str = ""
    table: str = ""
    controllers: int = 0


class Fitness(NamedTuple):
    """A kind of fitness, registered by name.

    name: what `FitnessConfig.kind` and the CLI's --fitness call it.
    validate(cfg): raises ValueError when the kind's settings in a `FitnessConfig` are wrong.
    scale(space) -> float: the typical magnitude of its values; agents divide rewards by it.
    make(space, cfg) -> (init, evaluate): init(key) -> the parameters of one controller, or
      None for a kind without controllers; evaluate(keys (B,), morphs (B, ...), params (B, ...)
      or None) -> FitnessResult of (B,) arrays: pure, batched and jittable (the callers split
      the batch across devices and jit it).
    trains_controllers: whether its results carry trained controllers worth keeping (saved with
      the bodies, replayed by `render`).
    deterministic: whether a body's fitness is the same for every key (evaluating it again
      tells nothing new: `run` skips its confirm stage).
    engines: the engines its worlds step on: None for the one `FitnessConfig.physics` names
      (the run's choice), a tuple for a kind bound to those, () for a kind that simulates
      nothing (`resolve_physics`).
    default_task(inputs) -> str: the task of a run that names none (`Inputs.task` ""): "walk"
      unless the kind's results were trained under another.
    check(inputs): raises ValueError, saying why, where the files the kind reads are missing or
      do not fit the space or the task; run before anything compiles (the `run` command's exit
      2).
    check_bodies(space, cfg, morphs): raises ValueError naming a body of the batch the kind
      cannot evaluate; `em.evaluate` asks before its call (the table's bodies outside it).
    params: the kind's own settings, a frozen dataclass with a default for every field (None:
      it has none); `make` reads them from `cfg.params`. The run command makes each field of
      type bool, int, float or str a flag `--fitness.FIELD VALUE`, its help the field's
      comment; its `__post_init__` raises ValueError where the values cannot run (the
      command's exit 2).
    """

    name: str
    validate: Callable[[FitnessConfig], None]
    scale: Callable[[Space], float]
    make: Callable[[Space, FitnessConfig], tuple[Callable | None, Callable]]
    trains_controllers: bool = False
    deterministic: bool = False
    engines: tuple[str, ...] | None = None
    default_task: Callable[[Inputs], str] = lambda inputs: "walk"
    check: Callable[[Inputs], None] = lambda inputs: None
    check_bodies: Callable[[Space, FitnessConfig, Any], None] = lambda space, cfg, morphs: None
    params: type | None = None


def fitness_params(kind: str, given: dict) -> Any:
    """The settings of fitness `kind` with the fields `given` set over its defaults (None for
    a kind without settings, given none).

    Raises:
      ValueError: a field it does not have, or a value its `__post_init__` refuses.
    """
    own = get_fitness(kind).params
    if own is None:
        if given:
            raise ValueError(f"the {kind} fitness has no settings")
        return None
    unknown = set(given) - {f.name for f in dataclasses.fields(own)}
    if unknown:
        raise ValueError(f"the {kind} fitness has no setting {', '.join(sorted(unknown))}")
    return own(**given)


def _bound(kind: Fitness) -> str:
    return f"the {kind.name} fitness runs on the {' or '.join(kind.engines)} engine only"


def resolve_physics(kind: str, name: str) -> tuple[str, str]:
    """`(engine, why)`: the engine a fitness of `kind` takes when asked for `name` ("auto"
    resolved by `engines.resolve`, or to the first engine of a kind bound to some).

    Raises:
      ValueError: `name` is unknown, or not an engine the kind is bound to.
      RuntimeError: the engine cannot run here (with the reason).
    """
    bound = get_fitness(kind).engines
    if bound:
        if name not in (AUTO, *bound):
            raise ValueError(_bound(get_fitness(kind)))
        name = bound[0] if name == AUTO else name
    return resolve(name)


_REGISTRY: Registry[Fitness] = Registry("fitness", plural="fitnesses", sort=True)


def register(*kinds: Fitness) -> None:
    """Makes `kinds` known by their names (see `evojax_morph/fitnesses/__init__.py`)."""
    _REGISTRY.register(*kinds)


def list_fitnesses() -> list[str]:
    """Names accepted by `get_fitness` and `FitnessConfig.kind`."""
    return _REGISTRY.list()


def get_fitness(name: str) -> Fitness:
    """The fitness kind registered as `name`."""
    return _REGISTRY.get(name)
