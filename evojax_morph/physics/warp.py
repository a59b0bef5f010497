"""MuJoCo Warp behind MJX: a flat batch of B bodies x E envs as one Warp model.

MJX's Warp implementation (`mjx.put_model(..., impl="warp")`) steps `nworld` worlds in one
kernel launch per stage. A model field may vary per world: Warp reads a field with a leading
axis of size n as `field[world % n]`, for the fields MuJoCo Warp allows to vary (`_BATCH_DIM`).
So every field `specialise` writes is repeated E times per body, world `w = b * E + e` being env
e of body b, and the worlds step under ONE `jax.vmap(mjx.step, (None, 0))`. A vmap over bodies
nested around a vmap over envs would be wrong, not slow: Warp sees the B x E worlds flattened
while the model keeps its (B,) axis, so world `b * E + e` would read body `(b * E + e) % B`.

Not reproducible on a GPU. `set_deterministic(True)` asks for MuJoCo Warp's
`Option.deterministic` (each world's contacts sorted, constraint rows in a canonical order, sums
in a fixed order), which only the mujoco-warp package has, not MJX's vendored copy: it needs
EVOJAX_MORPH_MUJOCO_WARP=package (`physics.MUJOCO_WARP`). Measured on an H100 it cost 12.5x and
still left 919 of 1,024 fitness values differing between two calls with the same keys
(docs/benchmarks.md), so nothing asks for it by default. Set it before the process's first Warp
call.

Contacts and constraint rows are allocated per world for the largest body of the space
(`buffers`), and an auto-reset selects the state alone (`where_worlds`): Warp's solver kernels
and the reset's copies run over every allocated row of every world, used or not. The solver's
iterations run as a plain loop, not a CUDA graph conditional (`put_model`).

The modules of MuJoCo Warp a step loads compile ahead on a thread (`warp_kernels.preload`, the
engine's preload). Float32 only. The derived constants are computed by `specialise` in the JAX
impl and copied; `dof_M0` and `stat.meaninertia` are not read by Warp. `geom_aabb` (the
broadphase's boxes) is recomputed from the capsule sizes.

  from evojax_morph.physics import warp
  ok, reason = warp.available()
  model, data = warp.to_warp(space, jax.vmap(space.mjx_model)(morphs), envs=8)
  data = warp.step_worlds(model, data, ctrl)   # ctrl: (B * E, nu)
  data = warp.steps(model, data, 4)            # 4 physics steps in one call into Warp
"""

from __future__ import annotations

import contextlib
import functools
import os
import sys

import jax
import jax.numpy as jnp
import mujoco

from evojax_morph.physics.templates import MUJOCO_WARP, SpaceLike, flat_models, mjx

INSTALL_HINT = "pip install 'evojax_morph[warp]'"
# Fields `specialise` writes that Warp does not read.
_NOT_IN_WARP = ("dof_M0",)


def available() -> tuple[bool, str]:
    """`(True, "")` when MJX's Warp implementation can run here, else `(False, why not)`."""
    ok, why = importable()
    if not ok:
        return ok, why
    platform = jax.devices()[0].platform
    if platform not in ("gpu", "cpu"):
        return False, f"MuJoCo Warp runs on a CUDA GPU or the CPU, not on {platform}"
    if platform == "cpu":
        import warp

        if not warp.is_cpu_available():  # a warp-lang without its LLVM (seen on a GPU host)
            return False, "warp-lang here cannot compile CPU kernels (no LLVM)"
    return True, ""


def importable() -> tuple[bool, str]:
    """`available()`'s checks that start no JAX backend: MJX's Warp implementation, warp-lang
    and MuJoCo Warp import, and x64 is off."""
    try:
        from mujoco.mjx import warp as mjx_warp
    except ImportError as e:  # an MJX too old to have the Warp implementation
        return False, f"mujoco.mjx.warp does not import ({e}); {INSTALL_HINT}"
    if not mjx_warp.WARP_INSTALLED:
        return False, f"warp-lang is not installed; {INSTALL_HINT}"
    if mjx_warp.mujoco_warp is None:
        return False, f"MuJoCo Warp (mujoco-warp) does not import; {INSTALL_HINT}"
    if jax.config.jax_enable_x64:
        return False, "MuJoCo Warp runs in float32 only; jax_enable_x64 is on"
    return True, ""


_DETERMINISTIC = [False]  # set_deterministic's setting, applied by put_model


def set_deterministic(on: bool) -> bool:
    """Asks MuJoCo Warp for deterministic contacts, constraint rows and sums (all of
    `DeterminismType`) in the Warp models this process makes from now on.

    Returns:
      True if in force: False when `on` and the vendored copy runs (it has no such option).
    """
    _DETERMINISTIC[0] = bool(on) and MUJOCO_WARP == "package"
    return _DETERMINISTIC[0] == bool(on)


def deterministic() -> bool:
    """Whether Warp models made now ask for deterministic execution (`set_deterministic`)."""
    return _DETERMINISTIC[0]


def _apply_determinism() -> None:
    """Sets `Option.deterministic` on the Option object MJX's Warp calls share: MJX builds the
    MuJoCo Warp model of every call from its JAX fields into one module-level `_o`, which has
    no JAX field for this option and so keeps what is set here."""
    if MUJOCO_WARP != "package":
        return
    import importlib

    from mujoco_warp import DeterminismType

    flag = DeterminismType.ALL if _DETERMINISTIC[0] else DeterminismType.NONE
    for name in ("forward", "smooth", "collision_driver"):
        module = importlib.import_module(f"mujoco.mjx.warp.{name}")
        if hasattr(module, "_o"):
            module._o.deterministic = flag


def callback_lock():
    """The lock Warp's JAX calls run under, or a null context while warp-lang is not loaded (no
    Warp call can run then); `put_model` and `make_worlds` hold it. MJX's `put_model` and
    `make_data` for Warp build MuJoCo Warp's host copy under `wp.ScopedDevice("cpu")`, which
    makes Warp's CPU device the default device of the whole process while they run; a Warp call
    running meanwhile on another thread would launch its kernels there (it crashed so on a GPU
    while a run's compile-ahead thread traced a program, `compile_ahead`). Private to warp-lang
    1.19: on a version without it, the ImportError says so."""
    if "warp" not in sys.modules:
        return contextlib.nullcontext()
    from warp._src.jax.ffi import _FFI_CALLBACK_LOCK

    return _FFI_CALLBACK_LOCK


def count_stream_registrations() -> None:
    """Makes warp-lang count its registrations of an external CUDA stream (idempotent).

    Each Warp call from JAX wraps XLA's stream in a new `wp.Stream`, which enters the handle in
    a native table; any such object that dies erases the entry, however many others still use
    the handle (warp-lang 1.19, and its main branch of 2026-08: `wp_cuda_stream_unregister` in
    warp.cu). One that outlives its call and is collected during a later call (by the cyclic
    garbage collector, whenever the call allocates) takes the entry from under that call, whose
    graph capture then fails: `Warp error: unknown stream` (seen on an H100, in a process that
    steps a second Warp program after a first). Counted, the native entry is made at the first
    registration of a handle and erased at its last unregistration. Private to warp-lang 1.19:
    on a version without these internals, a warning says the counting is off."""
    import ctypes
    import threading
    import warnings

    import warp as wp

    wp.init()
    try:
        core = wp._src.context.runtime.core
        register, unregister = core.wp_cuda_stream_register, core.wp_cuda_stream_unregister
    except AttributeError as e:
        warnings.warn(f"warp-lang's stream registrations are not counted ({e}): a Warp call "
                      "may fail with 'unknown stream' (evojax_morph.physics.warp)", stacklevel=2)
        return
    if getattr(register, "counted", False):
        return
    refs: dict = {}
    lock = threading.RLock()  # a collection inside a registration re-enters on the same thread
    key = lambda context, stream: tuple(
        x.value if isinstance(x, ctypes.c_void_p) else x for x in (context, stream)
    )

    def counted_register(context, stream):
        with lock:
            k = key(context, stream)
            refs[k] = refs.get(k, 0) + 1
            if refs[k] == 1:
                register(context, stream)

    def counted_unregister(context, stream):
        with lock:
            k = key(context, stream)
            refs[k] = refs.get(k, 0) - 1
            if refs[k] <= 0:
                del refs[k]
                unregister(context, stream)

    counted_register.counted = True
    core.wp_cuda_stream_register = counted_register
    core.wp_cuda_stream_unregister = counted_unregister


def graph_conditional() -> bool:
    """The solver's iterations as MJX's CUDA graph conditional (EVOJAX_MORPH_WARP_CONDITIONAL=1,
    for benchmarks), else a plain loop (`put_model`)."""
    return os.environ.get("EVOJAX_MORPH_WARP_CONDITIONAL") == "1"


def _require() -> None:
    ok, reason = available()
    if not ok:
        raise RuntimeError(f"the Warp physics cannot run: {reason}")


def _capsule_aabb(template: mujoco.MjModel, geom_size: jax.Array) -> jax.Array:
    """(..., ngeom, 2, 3) geom_aabb (centre, half sizes in the geom frame) for `geom_size`.

    A capsule's box is centred with half sizes (r, r, r + half length); every other geom keeps
    the template's box.
    """
    aabb = jnp.asarray(template.geom_aabb.reshape(-1, 2, 3), jnp.float32)
    aabb = jnp.broadcast_to(aabb, geom_size.shape[:-2] + aabb.shape)
    r, half = geom_size[..., 0], geom_size[..., 1]
    capsule = jnp.stack([jnp.zeros_like(r)] * 3 + [r, r, r + half], -1).reshape(aabb.shape)
    is_capsule = template.geom_type == mujoco.mjtGeom.mjGEOM_CAPSULE
    return jnp.where(is_capsule[:, None, None], capsule, aabb)


def to_warp(
    space: SpaceLike,
    models: mjx.Model,
    envs: int,
    naconmax_per_world: int | None = None,
    njmax: int | None = None,
    graph_mode=None,
) -> tuple[mjx.Model, mjx.Data]:
    """A Warp model and initial data of N = B x E worlds for B specialised bodies.

    Args:
      space: the space whose padded template (`space.template`) the bodies specialise.
      models: B bodies from `space.mjx_model` (JAX impl, float32 or float64), every leaf with a
        leading (B,) axis.
      envs: E, worlds per body; world `w = b * E + e` is env e of body b.
      naconmax_per_world: contacts allocated per world (Warp's pool holds N times this);
        None for `make_worlds`'s default.
      njmax: constraint rows per world; None for `make_worlds`'s default.
      graph_mode: a `warp.JaxCallableGraphMode`; None is MJX's default (WARP on a GPU, JAX on
        the CPU).

    Returns:
      `(model, data)`: a Warp-impl `mjx.Model` whose `plan.specialised_fields` (but `dof_M0`) and
      `geom_aabb` have a leading (N,) float32 axis, the rest the template's; and `mjx.Data` of
      the template at qpos0 with a leading (N,) axis on its per-world fields.

    Raises:
      RuntimeError: when MJX's Warp implementation cannot run here (the reason is given).
    """
    _require()
    model = world_model(space, models, envs, graph_mode)
    worlds = models.body_mass.shape[0] * envs
    return model, make_worlds(space, worlds, naconmax_per_world, njmax)


def world_model(space: SpaceLike, models: mjx.Model, envs: int, graph_mode=None) -> mjx.Model:
    """The Warp model of `to_warp` alone: B bodies' `plan.specialised_fields` (but `dof_M0`) and
    `geom_aabb` repeated per world, a leading (B x envs,) axis on each; jittable."""
    _require()
    template = space.template
    base = put_model(template, graph_mode)
    flat, _ = flat_models(models, envs, space.plan.specialised_fields)  # one per world
    fields = {n: jnp.asarray(getattr(flat, n), jnp.float32) for n in written(space)}
    fields["geom_aabb"] = _capsule_aabb(template, fields["geom_size"])
    return base.replace(**fields)


def written(space: SpaceLike) -> list[str]:
    """The fields `specialise` writes that Warp reads: a run holds one of each per world."""
    return [n for n in space.plan.specialised_fields if n not in _NOT_IN_WARP]


def put_model(mj_model: mujoco.MjModel, graph_mode=None) -> mjx.Model:
    """`mj_model` as one Warp-impl model shared by every world (no per-world fields).

    graph_mode None is EVOJAX_MORPH_WARP_GRAPH's `GraphMode` if set (`jax`, `warp`, `none`, ...;
    for benchmarks), else MJX's default: WARP (Warp's own CUDA graph per call) on a GPU."""
    _require()
    _apply_determinism()
    count_stream_registrations()
    if graph_mode is None and os.environ.get("EVOJAX_MORPH_WARP_GRAPH"):
        from mujoco.mjx.warp.types import GraphMode

        graph_mode = GraphMode[os.environ["EVOJAX_MORPH_WARP_GRAPH"].upper()]
    with callback_lock():
        model = mjx.put_model(mj_model, impl="warp", graph_mode=graph_mode)
    # Warp prints a warning for each step whose solver hits its iteration budget: ours is small
    # on purpose (BodyPlan.iterations), so these would flood the output.
    # The solver's iterations as a plain loop of `iterations` passes, not a CUDA graph
    # conditional that stops once every world has converged: the same kernels, and a world that
    # has converged skips each pass (bit-identical on the CPU, tests/test_warp.py), but on an
    # H100 3-7% faster (docs/benchmarks.md). EVOJAX_MORPH_WARP_CONDITIONAL=1 keeps MJX's
    # conditional (for benchmarks).
    impl = model.opt._impl.replace(warn_overflow=0, graph_conditional=graph_conditional())
    return model.replace(opt=model.opt.replace(_impl=impl))


def buffers(space: SpaceLike) -> tuple[int, int]:
    """`(contacts, rows)` per world: what the largest body of `space` can need at once.

    MuJoCo Warp sizes its contact pool and constraint rows ahead, and launches many solver
    kernels over every row of every world, used or not; an overflow drops contacts or rows
    silently (`put_model` turns the warning off). Only capsule-floor pairs collide, a capsule on
    a plane touches it at 2 points at most, an inactive capsule never does (its margin, see
    `physics`), and a body has at most one active capsule per node: so 2 x max_nodes contacts.
    Each takes 4 rows (pyramidal cone, condim 3; 3 in an elliptic cone); each limited joint 1
    more. Other constraint kinds are refused rather than counted.
    """
    t = space.template
    if (
        set(t.geom_condim.tolist()) != {3}
        or t.neq
        or t.npair
        or t.ntendon
        or (t.dof_frictionloss > 0).any()
        or (t.geom_conaffinity[t.geom_type == mujoco.mjtGeom.mjGEOM_CAPSULE] != 0).any()
    ):
        raise ValueError(f"{space.name}: buffers() counts capsule-floor contacts and limits only")
    capsules = int((t.geom_type == mujoco.mjtGeom.mjGEOM_CAPSULE).sum())
    contacts = 2 * min(space.max_nodes, capsules)
    per_contact = 4 if t.opt.cone == mujoco.mjtCone.mjCONE_PYRAMIDAL else 3  # elliptic: 3
    return contacts, per_contact * contacts + int(t.jnt_limited.sum())


def make_worlds(
    space: SpaceLike,
    worlds: int,
    naconmax_per_world: int | None = None,
    njmax: int | None = None,
    mj_model: mujoco.MjModel | None = None,
) -> mjx.Data:
    """Warp-impl data of the space's template (or `mj_model`) at qpos0 for `worlds` worlds, the
    contact pool shared; contacts and rows per world default to `buffers(space)`."""
    _require()
    contacts, rows = buffers(space)
    naconmax_per_world = contacts if naconmax_per_world is None else naconmax_per_world
    njmax = rows if njmax is None else njmax
    mj_model = space.template if mj_model is None else mj_model
    with callback_lock():
        data = mjx.make_data(mj_model, impl="warp", naconmax=naconmax_per_world * worlds,
                             njmax=njmax)
    # Data's own vmap rule batches the per-world fields and keeps the contact pool shared.
    return jax.vmap(lambda _: data)(jnp.arange(worlds))


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
    control step of 4 physics steps now pays that once: on an H100 a PPO fitness call got 2.3%
    to 4.9% faster (docs/benchmarks.md). EVOJAX_MORPH_WARP_FUSE=0 makes `n` calls instead (for
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
