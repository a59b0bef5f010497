"""MuJoCo Warp behind MJX: a flat batch of B bodies x E envs as one Warp model, stepped.

MJX's Warp implementation (`mjx.put_model(..., impl="warp")`) steps `nworld` worlds in one
kernel launch per stage. A model field may vary per world: Warp reads a field with a leading
axis of size n as `field[world % n]`, for the fields MuJoCo Warp allows to vary (`_BATCH_DIM`).
So every field `specialise` writes is repeated E times per body, world `w = b * E + e` being env
e of body b, and the worlds step under ONE `jax.vmap(mjx.step, (None, 0))`. A vmap over bodies
nested around a vmap over envs would be wrong, not slow: Warp sees the B x E worlds flattened
while the model keeps its (B,) axis, so world `b * E + e` would read body `(b * E + e) % B`.

This module steps the worlds (`step_worlds`, `steps`) and resets them (`where_worlds`: an
auto-reset selects the state alone, since the reset's copies run over every allocated row of
every world). The models and data come from `warp_models` (buffers sized ahead for the largest
body), what the process asks of warp-lang and MuJoCo Warp (availability, determinism, the call
lock) from `warp_runtime`; both are importable from here. The modules of MuJoCo Warp a step
loads compile ahead on a thread (`warp_kernels.preload`, the engine's preload).

  from evojax_morph.physics import warp
  ok, reason = warp.available()
  model, data = warp.to_warp(space, jax.vmap(space.mjx_model)(morphs), envs=8)
  data = warp.step_worlds(model, data, ctrl)   # ctrl: (B * E, nu)
  data = warp.steps(model, data, 4)            # 4 physics steps in one call into Warp
"""

from __future__ import annotations

import functools
import os

import jax
import jax.numpy as jnp

from evojax_morph.physics.templates import mjx
from evojax_morph.physics.warp_models import (
    buffers,
    make_worlds,
    put_model,
    to_warp,
    world_model,
    written,
)
from evojax_morph.physics.warp_runtime import (
    INSTALL_HINT,
    available,
    callback_lock,
    count_stream_registrations,
    deterministic,
    graph_conditional,
    importable,
    set_deterministic,
)

# What a Warp step reads of the data before writing it: MuJoCo's integration state
# (mjSTATE_INTEGRATION) and the warm start. Every other per-world field (kinematics, inertia,
# constraint rows, solver scratch) is recomputed from these before it is read.
STATE_FIELDS = (
    "time", "qpos", "qvel", "act", "qacc_warmstart", "ctrl", "qfrc_applied", "xfrc_applied",
    "eq_active", "mocap_pos", "mocap_quat", "userdata", "history",
)  # fmt: skip


def where_worlds(done: jax.Array, on_true: mjx.Data, on_false: mjx.Data) -> mjx.Data:
    """World by world, `on_true`'s state (`STATE_FIELDS`) where `done` (N,) is set, else
    `on_false`'s; every other field is `on_false`'s, which the next step recomputes: selecting
    the constraint rows and solver scratch of every world each control step cost more than the
    state (`tests/test_warp.py` checks that the fitness is unchanged). `mjx.Data.where` does
    this for one world inside a vmap; a flat batch of Warp data cannot be vmapped over."""
    select = lambda a, b: jnp.where(done.reshape((-1,) + (1,) * (a.ndim - 1)), a, b)
    return on_false.replace(
        **{n: select(getattr(on_true, n), getattr(on_false, n)) for n in STATE_FIELDS}
    )


def steps(model: mjx.Model, data: mjx.Data, n: int) -> mjx.Data:
    """`n` physics steps of every world (N,) in ONE call into Warp, the same kernels in the same
    order as `n` calls of `jax.vmap(mjx.step, (None, 0))`.

    Each call into Warp is a Python callback that XLA runs on the host, which reads the
    addresses of the step's ~800 buffers to find its captured CUDA graph (0.1 ms on a CPU). A
    control step of 4 physics steps pays that once, which makes a PPO fitness call 2.3% to 4.9%
    faster on an H100 (docs/benchmarks.md). EVOJAX_MORPH_WARP_FUSE=0 makes `n` calls instead (for
    benchmarks), as does an MJX whose internals `_fused_step` does not find (with a warning)."""
    fused = None if n == 1 or os.environ.get("EVOJAX_MORPH_WARP_FUSE") == "0" else _fused_step(n)
    if fused is None:
        one = jax.vmap(mjx.step, in_axes=(None, 0))
        return jax.lax.fori_loop(0, n, lambda _, d: one(model, d), data)
    return jax.vmap(fused, in_axes=(None, 0))(model, data)


@functools.cache
def _fused_step(n: int):
    """MJX's Warp `step` (`mujoco.mjx.warp.forward.step`) with its Warp function running
    `mujoco_warp.step` n times: a copy of MJX's functions whose module globals name an `n`-step
    shim in place of the one-step one. MJX's FFI wrapper caches its Warp callable per shim, so
    the copy gets its own. None where MJX's functions are not where MJX 3.17 has them."""
    import types
    import warnings

    from mujoco.mjx.warp import ffi
    from mujoco.mjx.warp import forward as mjx_warp

    # MJX wraps its shim in `ffi.format_args_for_warp`: the copy is of the function inside.
    one = getattr(getattr(mjx_warp, "_step_shim", None), "__wrapped__", None)
    if one is None or not hasattr(mjx_warp, "_step_jax_impl"):
        warnings.warn("MJX's Warp step is not as evojax_morph.physics.warp expects (MJX 3.17): one "
                      "call into Warp per physics step, slower", stacklevel=3)
        return None

    def mjwarp_step(m, d):
        for _ in range(n):
            mjx_warp.mjwarp.step(m, d)

    def copy(fn, **names):
        out = types.FunctionType(
            fn.__code__, {**fn.__globals__, **names}, f"{fn.__name__}_x{n}", fn.__defaults__
        )
        out.__annotations__, out.__kwdefaults__ = dict(fn.__annotations__), fn.__kwdefaults__
        return out

    shim = ffi.format_args_for_warp(copy(one, mjwarp=types.SimpleNamespace(step=mjwarp_step)))
    impl = copy(mjx_warp._step_jax_impl, _step_shim=shim)

    @jax.custom_batching.custom_vmap
    @ffi.marshal_jax_warp_callable
    def step(m, d):
        return impl(m, d)

    @step.def_vmap
    @ffi.marshal_custom_vmap
    def step_vmap(unused_axis_size, is_batched, m, d):
        return step(m, d), is_batched[1]

    return step


def step_worlds(model: mjx.Model, data: mjx.Data, ctrl: jax.Array) -> mjx.Data:
    """One physics step of every world, one flat vmap.

    Args:
      model: a model from `to_warp` (per-world fields with a leading (N,) axis).
      data: (N,) worlds.
      ctrl: (N, nu) controls.

    Returns:
      (N,) worlds after one step.
    """
    return jax.vmap(mjx.step, in_axes=(None, 0))(model, data.replace(ctrl=ctrl))


__all__ = [  # with the models' and the runtime's names: the engine's whole interface
    "INSTALL_HINT", "STATE_FIELDS", "available", "buffers", "callback_lock",
    "count_stream_registrations", "deterministic", "graph_conditional", "importable",
    "make_worlds", "put_model", "set_deterministic", "step_worlds", "steps", "to_warp",
    "where_worlds", "world_model", "written",
]
