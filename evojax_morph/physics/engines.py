"""Physics engines by name: how a flat batch of worlds of different bodies is stepped.

A fitness call simulates B bodies x W worlds each (K controllers x E envs for the PPO fitness)
as ONE flat batch of N = B x W worlds, world `w = b * W + i` being world i of body b. An engine
says how that batch is made and stepped:

* "jax": MJX's JAX engine. The B specialised models stay a (B,) batch and a step is a vmap over
  bodies around a vmap over each body's W worlds (the model shared by its worlds).
* "warp": MuJoCo Warp through MJX (`evojax_morph.physics.warp`): the fields that differ per body are
  repeated per world and Warp steps the N worlds in one kernel launch per stage. Float32, a GPU
  (or, slowly, the CPU), and `pip install 'evojax_morph[warp]'`.

`physics="auto"` (the CLI's default) takes Warp where it can run on a GPU and JAX elsewhere.
Warp's data keeps its contact pool shared by every world, so the data of a flat batch is never
vmapped over: reset, step and select (`where`) are this module's, on the whole batch.

  engine = get_engine("jax")
  worlds = engine.prepare(space, models, W)          # models: (B,) from space.mjx_model
  data = engine.forward(worlds, engine.make_data(worlds, space, B * W))
  data = engine.step(worlds, data.replace(ctrl=ctrl), 4)   # 4 physics steps; ctrl: (B * W, nu)
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from evojax_morph.morphology import tree_select
from evojax_morph.physics.templates import SpaceLike, mjx
from evojax_morph.registry import Registry


class Engine(NamedTuple):
    """A physics engine for flat batches of worlds, registered by name.

    available() -> (ok, reason): whether it can run here, and why not.
    prepare(space, models, worlds_per_body) -> worlds: what `step` needs of B specialised
      bodies (`space.mjx_model`, leaves with a leading (B,) axis), each simulated in
      `worlds_per_body` worlds; a pytree, jittable.
    make_data(worlds, space, n) -> (n,) data at qpos0 (n = B x worlds_per_body).
    step(worlds, data, n) -> data n physics steps later (one engine call where it can);
      forward(worlds, data) -> data with positions and velocities propagated (after a reset).
    where(done, on_true, on_false) -> data: world by world, `on_true` where done (n,) is set.
    foreign: its step is a foreign (FFI) call, which XLA's partitioner cannot split across
      devices: a batch of bodies splits by `jax.shard_map` instead (`sharding.shard_batch`).
    graph_capture: on a GPU its step replays CUDA graphs captured from XLA's stream, which a
      compile on another thread breaks: a run compiles nothing ahead beside it, and on several
      GPUs lowers nothing ahead either (a run there can hang; `compile_ahead`, `driver.execute`).
    unreproducible: why a run stepping on it on a GPU is not reproducible from its seed whatever
      XLA does ("" where it is): the run then leaves XLA's deterministic ops off, which would
      only cost time (`run.cli.start`).
    preload: None, or preload(devices, space) -> a Future: starts compiling, on a thread, what
      the engine's first call on those JAX devices, for bodies of `space`, would otherwise
      compile inside it; wait on the Future before that call (`run.stages.Evolve`, m0's evaluation).
    gpu_controllers: the controllers per body a run on a GPU trains by default
      (`Space.gpu_controllers`), spending the engine's speed on a fitness with less noise
      (docs/benchmarks.md, H100, 256 bodies of 50,000 PPO steps): 4 on the JAX engine (cv 0.23,
      noise-to-signal 0.60, 66 s of fitness a step), 8 on MuJoCo Warp (cv 0.15, 0.43; 27 s).
    """

    name: str
    available: Callable[[], tuple[bool, str]]
    prepare: Callable[[SpaceLike, mjx.Model, int], Any]
    make_data: Callable[[Any, SpaceLike, int], mjx.Data]
    step: Callable[[Any, mjx.Data, int], mjx.Data]
    forward: Callable[[Any, mjx.Data], mjx.Data]
    where: Callable[[jax.Array, mjx.Data, mjx.Data], mjx.Data]
    foreign: bool = False
    graph_capture: bool = False
    unreproducible: str = ""
    preload: Callable[[Any, SpaceLike], Any] | None = None
    gpu_controllers: int = 4


def _per_body(fn):
    """`fn(model, data)` of one world, over (B,) models and (B x W,) data: nested vmaps."""

    def batched(models: mjx.Model, data: mjx.Data) -> mjx.Data:
        bodies, worlds = models.body_mass.shape[0], data.qpos.shape[0]
        split = jax.tree.map(lambda x: x.reshape((bodies, worlds // bodies) + x.shape[1:]), data)
        out = jax.vmap(jax.vmap(fn, (None, 0)))(models, split)
        return jax.tree.map(lambda x: x.reshape((worlds,) + x.shape[2:]), out)

    return batched


def _jax_make_data(models: mjx.Model, space: SpaceLike, n: int) -> mjx.Data:
    del space
    one = mjx.make_data(jax.tree.map(lambda x: x[0], models))
    return jax.tree.map(lambda x: jnp.broadcast_to(x, (n,) + x.shape), one)


_jax_step = _per_body(mjx.step)

JAX = Engine(
    name="jax",
    available=lambda: (True, ""),
    prepare=lambda space, models, worlds_per_body: models,
    make_data=_jax_make_data,
    step=lambda models, data, n: jax.lax.fori_loop(0, n, lambda _, d: _jax_step(models, d), data),
    forward=_per_body(mjx.forward),
    where=tree_select,
)


def _warp():
    """evojax_morph.physics.warp, imported on first use (it needs the optional MuJoCo Warp)."""
    from evojax_morph.physics import warp

    return warp


def _warp_kernels():
    """evojax_morph.physics.warp_kernels, imported on first use (as `_warp`)."""
    from evojax_morph.physics import warp_kernels

    return warp_kernels


_flat = lambda fn: lambda model, data: jax.vmap(fn, (None, 0))(model, data)

WARP = Engine(
    name="warp",
    available=lambda: _warp().available(),
    prepare=lambda space, models, worlds_per_body: _warp().world_model(
        space, models, worlds_per_body
    ),
    make_data=lambda worlds, space, n: _warp().make_worlds(space, n),
    step=lambda model, data, n: _warp().steps(model, data, n),
    forward=_flat(mjx.forward),
    where=lambda done, on_true, on_false: _warp().where_worlds(done, on_true, on_false),
    foreign=True,
    graph_capture=True,
    unreproducible="on a GPU MuJoCo Warp orders contacts by thread timing",
    preload=lambda devices, space: _warp_kernels().preload(devices, space),
    gpu_controllers=8,
)

_REGISTRY: Registry[Engine] = Registry("physics", (JAX, WARP), plural="physics")
AUTO = "auto"


def foreign(name: str) -> bool:
    """Whether engine `name` steps by a foreign call (`Engine.foreign`); no check that it runs
    here, so that a fitness can be split before it is built."""
    return name in _REGISTRY and _REGISTRY.get(name).foreign


def registered(name: str) -> Engine:
    """The engine registered as `name`, not checked that it runs here: its traits, read before
    a JAX backend starts; a ValueError for an unknown name."""
    return _REGISTRY.get(name)


def warp_imports() -> bool:
    """MuJoCo Warp's `importable()` (False where the optional extra is not installed)."""
    return _warp().importable()[0]  # imports without the extra; it loads Warp on first use


def may_take(name: str) -> list[Engine]:
    """The engines `name` may resolve to (`resolve`), found without starting a JAX backend:
    "auto" gives the JAX engine, and Warp where it imports (auto takes it on a GPU; without
    one, XLA's GPU flags change nothing); an unknown name none (its user says so)."""
    if name == AUTO:
        return [JAX, WARP] if warp_imports() else [JAX]
    return [_REGISTRY.get(name)] if name in _REGISTRY else []


def list_engines() -> list[str]:
    """Names accepted by `get_engine` and `FitnessConfig.physics` ("auto" is resolved first)."""
    return _REGISTRY.list()


def get_engine(name: str) -> Engine:
    """The engine `name`; a ValueError for an unknown name, a RuntimeError with the reason for
    one that cannot run here."""
    engine = registered(name)
    ok, reason = engine.available()
    if not ok:
        raise RuntimeError(f"the {name} physics cannot run here: {reason}")
    return engine


def resolve(name: str) -> tuple[str, str]:
    """`(engine, why)`: "auto" becomes "warp" where Warp can run on a GPU, else "jax" (with the
    reason); any other name is checked (`get_engine`) and returned as it is."""
    if name != AUTO:
        get_engine(name)
        return name, "asked for"
    if jax.default_backend() != "gpu":
        return "jax", f"no GPU ({jax.default_backend()})"
    ok, reason = WARP.available()
    return ("warp", "a GPU with MuJoCo Warp") if ok else ("jax", reason)


def repeat_worlds(tree, worlds_per_body: int):
    """Every leaf's leading (B,) axis repeated to (B x worlds_per_body,): world b x W + i gets
    body b's row."""
    return jax.tree.map(lambda x: jnp.repeat(x, worlds_per_body, axis=0), tree)


__all__ = ["AUTO", "Engine", "JAX", "WARP", "get_engine", "list_engines", "may_take",
           "registered", "repeat_worlds", "resolve"]
