"""What this process asks of warp-lang and MuJoCo Warp: whether they can run here (`available`),
deterministic execution (`set_deterministic`), the lock Warp's host work runs under
(`callback_lock`), counted CUDA stream registrations (`count_stream_registrations`) and the
solver's loop (`graph_conditional`).

Not reproducible on a GPU. `set_deterministic(True)` asks for MuJoCo Warp's
`Option.deterministic` (each world's contacts sorted, constraint rows in a canonical order, sums
in a fixed order), which only the mujoco-warp package has, not MJX's vendored copy: it needs
EVOJAX_MORPH_MUJOCO_WARP=package (`physics.MUJOCO_WARP`). Measured on an H100 it cost 12.5x and
still left 919 of 1,024 fitness values differing between two calls with the same keys
(docs/benchmarks.md), so nothing asks for it by default. Set it before the process's first Warp
call.
"""

from __future__ import annotations

import contextlib
import os
import sys

import jax

from evojax_morph.physics.templates import MUJOCO_WARP

INSTALL_HINT = "pip install 'evojax_morph[warp]'"


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


def require() -> None:
    """A RuntimeError with the reason where MJX's Warp implementation cannot run here."""
    ok, reason = available()
    if not ok:
        raise RuntimeError(f"the Warp physics cannot run: {reason}")


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


def apply_determinism() -> None:
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
                      "may fail with 'unknown stream' (evojax_morph.physics.warp_runtime)",
                      stacklevel=2)
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
