"""Batched fitness of morphologies, whatever the kind: `evaluate(space, morphs, key, cfg)`.

The kinds (`evojax_morph.fitnesses`, by `cfg.kind`) say what a fitness computes; this module
splits their batch across devices, compiles them once per (space, config, mesh), and gives the
agents' environment its pure `(init, fitness)` pair (`make_env`: the environment itself).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from evojax_morph.fitnesses import FitnessConfig, FitnessResult, get_fitness
from evojax_morph.mdp import EvolutionEnv
from evojax_morph.morphology import Morphology
from evojax_morph.physics import engines
from evojax_morph.ppo import Params
from evojax_morph.sharding import batch_mesh, replicated, shard_batch
from evojax_morph.spaces import Space, make_space


def make_fitness_fn(space: Space, cfg: FitnessConfig, mesh=None):
    """`(init, fitness)`, pure and jittable, for use inside a larger jitted loop.

    init(key) -> params of one controller (a dummy scalar for the kinds without one);
    fitness(keys (B,), morphs (B, ...), params (B, ...)) -> `FitnessResult` of (B,) arrays with
    the (B, ...) trained controllers: the PPO fitness trains each body starting from the given
    controller (inheritance), the batch split across the devices of `mesh` (default: all; see
    `sharding.batch_mesh`).
    """
    init, evaluate_batch = get_fitness(cfg.kind).make(space, cfg)
    manual = engines.foreign(cfg.physics)
    split = shard_batch(evaluate_batch, mesh, manual=manual)
    return (lambda key: jnp.zeros(())) if init is None else init, split


def make_env(space: Space | str, fitness: FitnessConfig = FitnessConfig(), num_envs: int = 8,
             horizon: int | None = None, mesh=None) -> EvolutionEnv:
    """`num_envs` parallel evolutions of `space` (an instance or a registered name) under the
    batched fitness of `fitness`, split across `mesh` (default: every device); `horizon`
    mutations an episode (default: the space's); its rewards scaled by 1 over the fitness's
    typical size on `space` for a run's agent."""
    space = make_space(space) if isinstance(space, str) else space
    init_fn, fitness_fn = make_fitness_fn(space, fitness, mesh)
    return EvolutionEnv(space, fitness_fn, init_fn, horizon or space.default_horizon, num_envs,
                        reward_scale=1.0 / get_fitness(fitness.kind).scale(space))


@functools.lru_cache(maxsize=16)
def _compiled(space: Space, cfg: FitnessConfig, mesh):
    """(init or None, evaluate), vmapped or batched over morphologies, the batch split across
    `mesh`, jitted; cached. With several processes the outputs are replicated, so that every
    host can read them."""
    init, evaluate_batch = get_fitness(cfg.kind).make(space, cfg)
    manual = engines.foreign(cfg.physics)
    out = replicated(mesh) if jax.process_count() > 1 else None
    jit = lambda fn, by_hand=False: jax.jit(shard_batch(fn, mesh, by_hand),  # noqa: E731
                                           out_shardings=out)
    return (None if init is None else jit(jax.vmap(init)), jit(evaluate_batch, manual))


def init_params(space: Space, keys: jax.Array, cfg: FitnessConfig = FitnessConfig()) -> Params:
    """Fresh controllers, one per key: a batch of shape (B, ...)."""
    init = _compiled(space, cfg, batch_mesh())[0]
    if init is None:
        raise ValueError(f"the {cfg.kind} fitness has no controller to initialise")
    return init(keys)


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
        then uses keys[i], whatever else is in the batch. Given controllers evaluated
        (`init_params`, `train_steps=0`) score a body alike alone and in any batch, up to
        rounding; a trained fitness also depends on the batch (XLA's reduction order, which
        training amplifies), so compare trained fitness across batches by statistics over keys
        (docs/guide/library.md, measured there). The same call repeated gives the same values
        on the CPU, and on a GPU under `em.deterministic_gpu()`.
      cfg: which fitness and its budgets.
      init_params: (B, ...) controllers to start training from (a parent's, for inheritance);
        fresh ones if None.
      mesh: the devices to split the batch across (default: all; `sharding.batch_mesh`).
    Returns:
      A `FitnessResult` of (B,) arrays, with the trained controllers for the "ppo" fitness.
    """
    if morphs.active.ndim != 2 or morphs.active.shape[-1] != space.max_nodes:
        raise ValueError(
            f"morphs must be a batch of shape (B, {space.max_nodes}) for {space.name}; "
            f"got active of shape {morphs.active.shape} (use em.stack([...]))"
        )
    get_fitness(cfg.kind).check_bodies(space, cfg, morphs)
    keys = _per_morphology_keys(key, morphs.active.shape[0])
    init, evaluate_batch = _compiled(space, cfg, batch_mesh() if mesh is None else mesh)
    if init_params is None and init is not None:
        init_params = init(jax.vmap(lambda k: jax.random.fold_in(k, 1))(keys))
    return evaluate_batch(keys, morphs, init_params)


def lower_evaluate(space: Space, batch: int, cfg: FitnessConfig, mesh=None) -> list:
    """The programs `evaluate` compiles for `batch` morphologies of `space` with fresh
    controllers and one PRNG key (initialising them, if `cfg` has any, and evaluating), lowered
    for compiling ahead (`compile_ahead`) with the shapes and placements of such a call on one
    device (on several, the fresh controllers come split across them, and the call compiles
    its own)."""
    init, evaluate_batch = _compiled(space, cfg, batch_mesh() if mesh is None else mesh)
    keys = jax.ShapeDtypeStruct((batch, 2), jnp.uint32)
    morphs = jax.eval_shape(
        lambda: jax.tree.map(lambda x: jnp.repeat(x[None], batch, 0), space.initial())
    )
    if init is None:
        return [evaluate_batch.lower(keys, morphs, None)]
    return [init.lower(keys), evaluate_batch.lower(keys, morphs, jax.eval_shape(init, keys))]


def _per_morphology_keys(key: jax.Array, batch: int) -> jax.Array:
    key = jnp.asarray(key)
    typed = jnp.issubdtype(key.dtype, jax.dtypes.prng_key)
    single = key.ndim == 0 if typed else key.shape == (2,)
    if single:
        return jax.random.split(key, batch)
    if key.shape[0] != batch:
        raise ValueError(f"got {key.shape[0]} keys for {batch} morphologies")
    return key
