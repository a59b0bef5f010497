"""Batched fitness of morphologies: `evaluate(space, morphs, key, cfg) -> FitnessResult`."""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
from flax import struct

from evojax_morph import ppo
from evojax_morph.locomotion import TaskConfig
from evojax_morph.morphology import Morphology
from evojax_morph.ppo import Params, PPOConfig
from evojax_morph.sharding import batch_mesh, replicated, shard_batch
from evojax_morph.spaces import Space

FITNESS_KINDS = ("ppo", "predefined", "tame")


@dataclasses.dataclass(frozen=True)
class FitnessConfig:
    """Which fitness, and its budgets.

    kind: "ppo" (the return of a controller trained with PPO on the body, NGE-style),
      "predefined" (the space's hand-crafted deterministic fitness) or "tame" (task-agnostic:
      how well random motor primitives can be told apart from where they leave the body, with
      a pre-trained classifier; see `evojax_morph.tame`).
    classifier: for "tame", the directory of a classifier saved by `python -m evojax_morph.tame`.
    """

    kind: str = "ppo"
    task: TaskConfig = TaskConfig()
    ppo: PPOConfig = PPOConfig()
    classifier: str = ""

    def __post_init__(self):
        if self.kind not in FITNESS_KINDS:
            raise ValueError(f"unknown fitness {self.kind!r}; choose one of {', '.join(FITNESS_KINDS)}")
        if self.kind == "tame" and not self.classifier:
            raise ValueError("the tame fitness needs classifier= the directory of a trained TAME classifier "
                             "(train one with `python -m evojax_morph.tame --space SPACE --out DIR`)")
        self.ppo.validate()


@struct.dataclass
class FitnessResult:
    fitness: jax.Array  # (B,) float: the fitness of each morphology
    fitness_std: jax.Array  # (B,) float: spread across evaluation episodes (0 if deterministic)
    diverged: jax.Array  # (B,) bool: a simulation diverged; its fitness is finite but suspect
    params: Params | None  # batched (B, ...) trained controllers; None for "predefined"
    train_return: jax.Array  # (B,) mean over envs of the last finished training episode's return
    entropy: jax.Array  # (B,) policy entropy per motor at the end of training
    env_steps: int = struct.field(pytree_node=False)  # control steps spent per morphology


@functools.lru_cache(maxsize=16)
def _predefined(space: Space):
    return jax.jit(jax.vmap(space.predefined_fitness))


def _tame(space: Space, cfg: FitnessConfig):
    """The vmapped TAME fitness of cfg.classifier, checked to be trained on `space`."""
    from evojax_morph import tame

    trained_on, _, fitness = tame.load_fitness(str(cfg.classifier))
    if trained_on != space.name:
        raise ValueError(f"the TAME classifier in {cfg.classifier!r} was trained on {trained_on}, not {space.name}")
    return fitness


@functools.lru_cache(maxsize=16)
def _tame_compiled(space: Space, cfg: FitnessConfig, mesh):
    return jax.jit(shard_batch(_tame(space, cfg), mesh))


@functools.lru_cache(maxsize=16)
def _compiled(space: Space, cfg: FitnessConfig, mesh):
    """(init, train) vmapped over morphologies, the batch split across `mesh`, jitted; cached.

    With several processes the outputs are replicated, so that every host can read them."""
    init, train = ppo.make_train(space, cfg.task, cfg.ppo)
    out = replicated(mesh) if jax.process_count() > 1 else None
    jit = lambda fn: jax.jit(shard_batch(jax.vmap(fn), mesh), out_shardings=out)
    return jit(init), jit(train)


def make_fitness_fn(space: Space, cfg: FitnessConfig, mesh=None):
    """`(init, fitness)`, pure and jittable, for use inside a larger jitted loop.

    init(key) -> params of one controller (a dummy scalar for the fitnesses without one);
    fitness(keys (B,), morphs (B, ...), params (B, ...)) -> (fitness (B,), params (B, ...)):
    the PPO fitness trains each body starting from the given controller (inheritance), the
    batch split across the devices of `mesh` (default: all; see `sharding.batch_mesh`).
    """
    if cfg.kind == "predefined":
        return (lambda key: jnp.zeros(())), (
            lambda keys, morphs, params: (jax.vmap(space.predefined_fitness)(morphs), params)
        )
    if cfg.kind == "tame":
        tame_fitness = shard_batch(_tame(space, cfg), mesh)
        return (lambda key: jnp.zeros(())), (lambda keys, morphs, params: (tame_fitness(keys, morphs)[0], params))
    init, train = ppo.make_train(space, cfg.task, cfg.ppo)

    def fitness_one(key, morph, params):
        out = train(key, morph, params)
        return out.fitness, out.params

    return init, shard_batch(jax.vmap(fitness_one), mesh)


def init_params(space: Space, keys: jax.Array, cfg: FitnessConfig = FitnessConfig()) -> Params:
    """Fresh controllers, one per key: a batch of shape (B, ...)."""
    return _compiled(space, cfg, batch_mesh())[0](keys)


def evaluate(
    space: Space,
    morphs: Morphology,
    key: jax.Array,
    cfg: FitnessConfig = FitnessConfig(),
    init_params: Params | None = None,
    mesh=None,
) -> FitnessResult:
    """Fitness of a batch of morphologies, in one compiled call on the default backend.

    Args:
      space: the space the morphologies belong to.
      morphs: a batch of B >= 1 morphologies (`em.stack`), arrays of shape (B, max_nodes, ...).
      key: one PRNG key, split into one per morphology, or a (B,) array of keys: morphology i
        then uses keys[i], so the same body with the same key gives the same result in any batch.
      cfg: which fitness and its budgets.
      init_params: (B, ...) controllers to start training from (a parent's, for inheritance);
        fresh ones if None.
    Returns:
      A `FitnessResult` of (B,) arrays, with the trained controllers for the "ppo" fitness.
    """
    if morphs.active.ndim != 2 or morphs.active.shape[-1] != space.max_nodes:
        raise ValueError(
            f"morphs must be a batch of shape (B, {space.max_nodes}) for {space.name}; "
            f"got active of shape {morphs.active.shape} (use em.stack([...]))"
        )
    batch = morphs.active.shape[0]
    keys = _per_morphology_keys(key, batch)
    if cfg.kind == "predefined":
        fitness = _predefined(space)(morphs)
        zeros = jnp.zeros_like(fitness)
        return FitnessResult(fitness, zeros, zeros.astype(bool), init_params, zeros, zeros, env_steps=0)
    if cfg.kind == "tame":
        from evojax_morph.tame import load_fitness

        fitness, diverged = _tame_compiled(space, cfg, batch_mesh() if mesh is None else mesh)(keys, morphs)
        zeros = jnp.zeros_like(fitness)
        tame_cfg = load_fitness(str(cfg.classifier))[1]
        steps = tame_cfg.episodes * tame_cfg.episode_length
        return FitnessResult(fitness, zeros, diverged, init_params, zeros, zeros, env_steps=steps)

    init, train = _compiled(space, cfg, batch_mesh() if mesh is None else mesh)
    if init_params is None:
        init_params = init(jax.vmap(lambda k: jax.random.fold_in(k, 1))(keys))
    out = train(keys, morphs, init_params)
    return FitnessResult(
        fitness=out.fitness,
        fitness_std=out.fitness_std,
        diverged=out.diverged,
        params=out.params,
        train_return=out.train_return,
        entropy=out.entropy,
        env_steps=ppo.env_steps_per_morphology(cfg.task, cfg.ppo),
    )


def _per_morphology_keys(key: jax.Array, batch: int) -> jax.Array:
    key = jnp.asarray(key)
    typed = jnp.issubdtype(key.dtype, jax.dtypes.prng_key)
    single = key.ndim == 0 if typed else key.shape == (2,)
    if single:
        return jax.random.split(key, batch)
    if key.shape[0] != batch:
        raise ValueError(f"got {key.shape[0]} keys for {batch} morphologies")
    return key
