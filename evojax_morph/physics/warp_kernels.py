"""Warp's kernels compiled ahead: the modules of MuJoCo Warp that a step loads, started on a
thread while a run compiles its own programs (`Engine.preload`).

Without it they compile one after another inside the first Warp call. `preload` starts the
`FIXED_MODULES` (every space's) and the modules `model_modules` finds for a space's template,
several at once; a run waits for them before its first Warp call.

  from evojax_morph.physics import warp_kernels
  warp_kernels.preload(jax.local_devices(), space).result()
"""

from __future__ import annotations

import concurrent.futures
import math
import os

from evojax_morph.physics.templates import SpaceLike
from evojax_morph.physics.warp_models import buffers, written
from evojax_morph.physics.warp_runtime import callback_lock, graph_conditional

# The modules of MuJoCo Warp that a step loads on every space, all at their default block size,
# beside MJX's own Warp call (`mujoco.mjx.warp.ffi`). Measured on the CPU (warp-lang 1.19, MJX
# 3.17, one PPO evaluation of each of the four spaces, every module load and kernel launch
# recorded): these 7, and 23 to 28 modules of one kernel each, which MuJoCo Warp makes from the
# model when a step first runs, some launched at the block sizes of `BlockDim`.
FIXED_MODULES = ("smooth", "passive", "forward", "solver", "support", "constraint")


def preload(devices, space: SpaceLike | None = None) -> concurrent.futures.Future:
    """Starts compiling (or loading from Warp's kernel cache) the `FIXED_MODULES` for the JAX
    `devices`, and with a `space` the modules `model_modules` finds for its template, several at
    once, on a thread; `.result()` waits for them (and raises what a load raised). Without it
    they compile one after another inside the first Warp call: on an H200 with an empty Warp
    cache, 46.9 s of compiling for the fixed modules and 28.3 s for the 26 made from Bad
    Walker's model that `model_modules` finds. With both preloaded, a fresh Bad Walker run's
    m0 call took 22.9 s there, against 52.8 s with the fixed modules alone and 21.4 s warm
    (docs/benchmarks.md). A run waits for it before its first call, because a module loaded
    during Warp's graph capture is untested."""
    import importlib

    import warp as wp
    from mujoco.mjx import warp as mjx_warp

    package = mjx_warp.mujoco_warp.__name__ + "._src."
    names = [package + name for name in FIXED_MODULES] + ["mujoco.mjx.warp.ffi"]
    for name in names:  # a module's kernels are registered with Warp when it is imported
        importlib.import_module(name)
    targets = list({str(d): d for d in map(wp.device_from_jax, devices)}.values())
    workers = max(1, (os.cpu_count() or 2) // 2)

    def load():
        with callback_lock():  # no other thread's Warp host work meanwhile (`callback_lock`)
            groups = {None: [wp.get_module(name) for name in names]}  # by block size
            for block_dim, made in (model_modules(space) if space is not None else {}).items():
                groups.setdefault(block_dim, []).extend(made)
            with concurrent.futures.ThreadPoolExecutor(len(groups)) as pool:  # groups at once
                loads = [pool.submit(wp.force_load, targets, modules, block_dim=block_dim,
                                     max_workers=min(len(modules), workers))
                         for block_dim, modules in groups.items()]
                for done in loads:
                    done.result()

    pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="warp-preload")
    future = pool.submit(load)
    pool.shutdown(wait=False)
    return future


def model_modules(space: SpaceLike) -> dict:
    """{block size (None: Warp's default): [Warp module]}: the modules of one kernel each that
    MuJoCo Warp makes from `space`'s template (as `put_model` sets it) when a step first runs,
    those whose code does not depend on the number of worlds. Found by running a step of one
    world, and again of two, with `warp.launch` and `warp.launch_tiled` recording each kernel
    and block size in place of launching it (nothing compiles, nothing runs), and keeping what
    both steps made: a kernel specialised on how many worlds hold a field (the broadphase's)
    differs between them, and still compiles at the step. Call it holding `callback_lock`: it
    swaps Warp's launch functions for the step. tests/test_warp.py checks that a PPO evaluation
    then makes no other module of the kind."""
    import warp as wp
    from mujoco.mjx.warp import forward as mjx_forward

    mjwarp, template = mjx_forward.mjwarp, space.template
    contacts, rows = buffers(space)
    batched = [*written(space), "geom_aabb"]  # per world in a run, as `world_model` sets

    def made(worlds: int) -> dict:
        found = {}

        def record(kernel, dim, inputs=(), outputs=(), *args, block_dim=None, **kwargs):
            if math.prod([dim] if isinstance(dim, int) else dim) == 0:
                return  # Warp loads no module for an empty launch
            if kernel.is_generic:  # the overload a launch would pick
                kernel = kernel._add_normalized_overload(
                    kernel.infer_argument_types([*inputs, *outputs]))
            found.setdefault(kernel.module.name, (kernel.module, set()))[1].add(block_dim)

        def record_tiled(*args, block_dim, **kwargs):
            record(*args, block_dim=block_dim, **kwargs)

        with wp.ScopedDevice("cpu"):
            m = mjwarp.put_model(template)
            m.opt.warn_overflow, m.opt.graph_conditional = 0, graph_conditional()
            for name in batched:  # per world in a run (`world_model`)
                field = getattr(m, name)
                setattr(m, name, wp.empty((worlds, *field.shape[1:]), dtype=field.dtype))
            d = mjwarp.make_data(template, nworld=worlds, naconmax=contacts * worlds, njmax=rows)
            launch, launch_tiled = wp.launch, wp.launch_tiled
            wp.launch, wp.launch_tiled = record, record_tiled
            try:
                mjwarp.step(m, d)
            finally:
                wp.launch, wp.launch_tiled = launch, launch_tiled
        return found

    one, two = made(1), made(2)
    by_block = {}
    for name, (module, block_dims) in one.items():
        if name in two and "." not in name:  # made from the model, not a Python module's
            for block_dim in block_dims:
                by_block.setdefault(block_dim, []).append(module)
    return by_block
