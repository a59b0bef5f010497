"""The table fitness: a draw from stored PPO results of every body of an enumerable space.

A landscape table (NAS-Bench-101's idea) holds, for every body of a space (`enumerate_bodies`,
told apart by `Space.canonical`), S independent results of the PPO fitness, each one controller
trained from scratch. The fitness of a body is the mean of K results drawn without replacement
from its row, K = `cfg.ppo.controllers`: the noise of the real fitness with K controllers, at
the cost of a lookup; its gait (distance, upright) is the mean of the same K results' gaits,
NaN where the table holds none. It runs inside the jitted agent loop: a body is matched to its
row by a jittable signature of its tree (`morphology.signature`), equal exactly when the
canonical names are.

No controllers and no inheritance: every draw is a fresh training's result, so a child does not
start from its parent's controller and a no-op (or a revisit) draws again instead of training
further. Under the PPO fitness a lineage's fitness rises with training alone; here it does not,
so rewards are differences of independent draws, and a body's value is its table mean.

Tables are built by `python -m experiments.build_tables` (see there) and live in
`evojax_morph/fitnesses/tables/SPACE.npz` unless `FitnessConfig.table` names another file.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import zipfile
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from evojax_morph.fitnesses.base import Fitness, FitnessConfig, FitnessResult, Inputs
from evojax_morph.morphology import Morphology, signature, stack
from evojax_morph.spaces import Space
from evojax_morph.tasks import make_task

TABLES = Path(__file__).resolve().parent / "tables"
FORMAT = 1  # the file layout's version, in every table's metadata


def default_path(space_name: str) -> Path:
    """Where the packaged table of a space lives."""
    return TABLES / f"{space_name}.npz"


def table_path(space: Space, cfg: FitnessConfig) -> Path:
    """The table `cfg` names, or the packaged one of `space`."""
    return named_path(Inputs(space.name, table=cfg.table))


def named_path(inputs: Inputs) -> Path:
    """The table `inputs` names, or the packaged one of their space."""
    return Path(inputs.table) if inputs.table else default_path(inputs.space)


@dataclasses.dataclass
class Table:
    """Stored fitness results of each of T bodies; a NaN result is not measured (yet).

    Every body has the table's `base` results (`meta["seeds"]`, 32 in the packaged tables);
    the bodies with the highest means may have more, up to S (deep rows, so that the best
    bodies can be told apart: `build_tables --deep-top`), NaN beyond a row's own count.
    Each result may carry its gait (`FitnessResult.distance` and `.upright`), NaN where not
    measured: tables built before the gait (the packaged ones) have none.
    Saved as one compressed .npz (a few tens of KB for 256 bodies x 32 results).
    """

    space: str
    names: list[str]  # (T,) canonical names (`Space.canonical`)
    bodies: Morphology  # (T, max_nodes, ...) the bodies, as numpy arrays
    fitness: np.ndarray  # (T, S) float32; NaN where not measured
    diverged: np.ndarray  # (T, S) bool: the result's simulation diverged (fitness zeroed)
    meta: dict  # how the results were made: settings, engine, device, date, revision, ...
    distance: np.ndarray | None = None  # (T, S) float32: metres forward; None: all NaN
    upright: np.ndarray | None = None  # (T, S) float32: fraction before a fall; None: all NaN

    def __post_init__(self):
        as_gait = lambda x: (np.full(self.fitness.shape, np.nan, np.float32) if x is None
                             else np.asarray(x, np.float32))
        self.distance, self.upright = as_gait(self.distance), as_gait(self.upright)

    @property
    def task(self) -> str:
        """The task its results were trained under (`make_task`); tables built before tasks
        were named trained under the source's, "distance"."""
        return str(self.meta.get("task", "distance"))

    @property
    def seeds(self) -> int:
        """S: the most results a row can hold."""
        return self.fitness.shape[1]

    @property
    def base(self) -> int:
        """The results every body has (the deep rows have more)."""
        return int(self.meta.get("seeds", self.seeds))

    @property
    def done(self) -> np.ndarray:
        """(T, S) bool: the results measured."""
        return ~np.isnan(self.fitness)

    @property
    def complete(self) -> bool:
        """Every body has its `base` results."""
        return bool(self.done[:, : self.base].all())

    def counts(self) -> np.ndarray:
        """(T,) int: the results of each body."""
        return self.done.sum(1)

    def mean(self) -> np.ndarray:
        """(T,) each body's mean over its results: its true fitness, as far as the table
        knows."""
        return np.nanmean(self.fitness, 1)

    def row(self, space: Space, m: Morphology) -> int:
        """The row of body `m` (outside jit); a ValueError naming it if the table lacks it."""
        name = space.canonical(m)
        try:
            return self.names.index(name)
        except ValueError:
            raise ValueError(f"body {name} is not in the {self.space} table") from None

    def save(self, path) -> None:
        """Writes the table to `path` (.npz) under a temporary name, then renames it."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp.npz")
        b = self.bodies
        np.savez_compressed(
            tmp, names=np.asarray(self.names), active=b.active, parent=b.parent, kind=b.kind,
            site=b.site, attrs=b.attrs, fitness=self.fitness.astype(np.float32),
            diverged=self.diverged, distance=self.distance, upright=self.upright,
            meta=np.asarray(json.dumps({"space": self.space, "format": FORMAT, **self.meta})),
        )
        os.replace(tmp, path)

    @classmethod
    def load(cls, path) -> Table:
        with np.load(path, allow_pickle=False) as f:
            meta = json.loads(str(f["meta"]))
            bodies = Morphology(*(np.asarray(f[k]) for k in
                                  ("active", "parent", "kind", "site", "attrs")))
            space = meta.pop("space")
            if meta.get("format") != FORMAT:
                raise ValueError(f"{path}: table format {meta.get('format')}, expected {FORMAT}")
            gait = [np.asarray(f[k], np.float32) if k in f.files else None
                    for k in ("distance", "upright")]  # absent from tables before the gait
            return cls(space, [str(n) for n in f["names"]], bodies,
                       np.asarray(f["fitness"], np.float32), np.asarray(f["diverged"]), meta,
                       *gait)


# --- the fitness kind --------------------------------------------------------------------------


def validate(cfg: FitnessConfig) -> None:
    if cfg.table and not Path(cfg.table).is_file():
        raise ValueError(f"no table at {cfg.table!r} (build one with "
                         "`python -m experiments.build_tables --space SPACE --out PATH`)")


_signatures = jax.jit(jax.vmap(signature))  # (B, 2) of a batch of bodies


@functools.lru_cache(maxsize=8)
def _prepared(space: Space, path: str, mtime_ns: int):
    """(table, (T, 2) signatures) of a checked table; cached per file version."""
    del mtime_ns  # part of the cache key only
    table = Table.load(path)
    if table.space != space.name:
        raise ValueError(f"the table {path} is of {table.space}, not {space.name}")
    if not table.complete:
        raise ValueError(f"the table {path} is incomplete ({table.done[:, :table.base].sum()} "
                         f"of {table.done[:, :table.base].size} results): resume its build")
    sigs = np.asarray(_signatures(table.bodies))
    if len({tuple(s) for s in sigs}) != len(sigs):
        raise ValueError(f"two bodies of the table {path} share a signature")
    for i in range(len(table.names)):
        body = jax.tree.map(lambda x, i=i: x[i], table.bodies)
        if space.canonical(body) != table.names[i]:
            raise ValueError(f"the table {path} names body {i} {table.names[i]}, but it is "
                             f"{space.canonical(body)}")
    _check_closed(space, table, sigs, path)
    return table, sigs


def _check_closed(space: Space, table: Table, sigs: np.ndarray, path: str) -> None:
    """Every body reachable from m0 is in the table: m0 is, and every valid mutation of a body
    of the table gives one (one jitted call over all bodies x actions). So no body an agent
    meets from m0 is missing; ValueError naming the first missing body otherwise."""
    m0 = space.initial()
    if not (sigs == np.asarray(signature(m0))).all(-1).any():
        raise ValueError(f"m0 {space.canonical(m0)} is not in the table {path}")
    actions = np.arange(space.max_nodes * space.num_mutations)

    @jax.jit
    def children(bodies):
        def of(m):
            mutate = lambda a: space.mutate(m, a // space.num_mutations, a % space.num_mutations)
            kids = jax.vmap(mutate)(actions)
            return kids, jax.vmap(signature)(kids), space.action_mask(m).reshape(-1)

        return jax.vmap(of)(bodies)

    kids, kid_sigs, valid = jax.device_get(children(table.bodies))  # (T, A, ...)
    known = (kid_sigs[:, :, None, :] == sigs[None, None]).all(-1).any(-1)  # (T, A)
    missing = np.argwhere(valid & ~known)
    if len(missing):
        t, a = missing[0]
        kid = jax.tree.map(lambda x: x[t, a], kids)
        raise ValueError(
            f"the table {path} lacks body {space.canonical(kid)}, reached from its body "
            f"{table.names[t]} by node {a // space.num_mutations}: "
            f"{space.mutation_names[a % space.num_mutations]} ({len(missing)} such mutations)"
        )


def load(space: Space, cfg: FitnessConfig) -> tuple[Table, np.ndarray]:
    """The checked table `cfg` names for `space` and its (T, 2) signatures; ValueError when it
    is missing, of another space, incomplete, or lacks a body reachable from m0."""
    path = table_path(space, cfg)
    if not path.is_file():
        raise ValueError(
            f"no table for {space.name} at {path}: build one with `python -m "
            f"experiments.build_tables --space {space.name} --out {path}`, or set "
            "FitnessConfig(table=PATH)"
        )
    return _prepared(space, str(path.resolve()), path.stat().st_mtime_ns)


def task_of(path: Path) -> str:
    """The task the table at `path` was built under ("distance" where it cannot be read: the
    run's own checks then say what is wrong with the table)."""
    try:
        return Table.load(path).task
    except (OSError, ValueError, KeyError):
        return "distance"


def default_task(inputs: Inputs) -> str:
    """The task the table was built under: its results were trained under it."""
    return task_of(named_path(inputs))


def _other_task(path: Path, built: str, asked: str) -> str:
    return (f"the table {str(path)!r} was built under the task {built!r}, but the fitness asks "
            f"for {asked!r} (--task): ask for {built!r} or build a table under {asked!r} "
            f"(`python -m experiments.build_tables --task {asked}`)")


def check(inputs: Inputs) -> None:
    """The table file is there, built under the task asked for (if any), with as many results
    a body as the controllers asked for."""
    path = named_path(inputs)
    if not path.is_file():
        raise ValueError(
            f"--fitness table: no table at {str(path)!r}; build one with `python -m "
            f"experiments.build_tables --space {inputs.space} --out PATH` and pass --table PATH"
        )
    try:
        table = Table.load(path)
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as e:  # not a table
        raise ValueError(f"--fitness table: {str(path)!r} is not a readable table ({e})") from None
    if table.space != inputs.space:
        raise ValueError(f"--fitness table: the table {str(path)!r} is of the space "
                         f"{table.space!r}, not {inputs.space!r}")
    if inputs.task and inputs.task != table.task:
        raise ValueError(_other_task(path, table.task, inputs.task))
    if inputs.controllers > table.base:
        raise ValueError(f"--controllers {inputs.controllers}: the table holds {table.base} "
                         "results a body")


def make(space: Space, cfg: FitnessConfig):
    table, sigs_np = load(space, cfg)
    if table.task != cfg.task.name:
        raise ValueError(_other_task(table_path(space, cfg), table.task, cfg.task.name))
    if cfg.task != make_task(cfg.task.name):
        raise ValueError(f"the table's results were trained under the {table.task} task's "
                         "registered settings: a table fitness takes no task settings")
    k, seeds = cfg.ppo.controllers, table.seeds
    if k > table.base:
        raise ValueError(f"{k} controllers per body, but the table holds {table.base} results "
                         "a body")
    sigs = jnp.asarray(sigs_np)
    fitness, diverged = jnp.asarray(table.fitness), jnp.asarray(table.diverged)
    distance, upright = jnp.asarray(table.distance), jnp.asarray(table.upright)
    measured = jnp.asarray(table.done)
    env_steps = k * int(table.meta.get("env_steps_per_result", 0))

    def one(key: jax.Array, m: Morphology):
        hit = (sigs == signature(m)).all(-1)  # (T,)
        row = jnp.argmax(hit)
        # k distinct measured results: the k largest of S uniforms, -1 where a deep row's
        # column is unmeasured (10x faster than random.choice's permutation on the CPU)
        uniform = jax.random.uniform(key, (seeds,))
        draws = jax.lax.top_k(jnp.where(measured[row], uniform, -1.0), k)[1]
        found = hit.any()
        nan = jnp.float32(jnp.nan)
        mean = lambda x: jnp.where(found, x[row, draws].mean(), nan)  # fitness and gait alike
        return (mean(fitness), jnp.where(found, fitness[row, draws].std(), nan),
                diverged[row, draws].any() | ~found, found, mean(distance), mean(upright))

    def evaluate(keys: jax.Array, morphs: Morphology, params) -> FitnessResult:
        # A body outside the table gets NaN, flagged diverged: a table that loads holds every
        # body reachable from m0 (`_check_closed`), so agents never meet one, and `em.evaluate`
        # names such a body before its call (`check_bodies`). No host callback here: a program
        # with one is never kept in JAX's persistent cache, so every run would compile it anew.
        f, std, div, found, dist, up = jax.vmap(one)(keys, morphs)
        zeros = jnp.zeros_like(f)
        return FitnessResult(f, std, div, params, zeros, zeros, dist, up, env_steps=env_steps)

    return None, evaluate


def check_bodies(space: Space, cfg: FitnessConfig, morphs: Morphology) -> None:
    """Raises a ValueError naming the first of the batch `morphs` that the table lacks."""
    table, sigs = load(space, cfg)
    known = {row.tobytes() for row in sigs}
    batch = np.asarray(_signatures(morphs))
    for i, sig in enumerate(batch):
        if sig.tobytes() not in known:
            body = space.canonical(jax.tree.map(lambda x, i=i: x[i], morphs))
            raise ValueError(f"body {body} is not in the {space.name} table "
                             f"{table_path(space, cfg)}")


FITNESS = Fitness(name="table", validate=validate, scale=lambda space: 100.0, make=make,
                  engines=(), default_task=default_task, check=check, check_bodies=check_bodies)


def stacked(bodies: list[Morphology]) -> Morphology:
    """The bodies as one numpy `Morphology` batch, as a `Table` keeps them."""
    return jax.tree.map(np.asarray, jax.device_get(stack(bodies)))
