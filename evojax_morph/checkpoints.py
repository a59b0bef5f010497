"""A run's Orbax checkpoints: the manager of RUN/checkpoints, and the restore of the newest
that reads (`restore_newest`), the damaged ones moved aside, for `driver`'s --resume."""

from __future__ import annotations

import sys
from pathlib import Path

import jax


def checkpoint_manager(out: Path):
    import orbax.checkpoint as ocp

    options = ocp.CheckpointManagerOptions(max_to_keep=2, create=True)
    return ocp, ocp.CheckpointManager(out.resolve() / "checkpoints", options=options)


class ResumeError(RuntimeError):
    """No checkpoint of a run directory could be read back."""


DAMAGED = "checkpoints_damaged"  # where checkpoints that do not read are moved, under the run


def _why(e: Exception) -> str:
    """The first part of a restore error (TensorStore appends its whole spec)."""
    text = str(e).split(" [tensorstore_spec")[0].strip().splitlines()
    text = text[0] if text else ""
    return f"{type(e).__name__}: {text[:300]}"


def _drop_closed_loop_reports() -> None:
    """From now on, drop the "Event loop is closed" reports of reads cut short (idempotent).

    A restore that fails (a damaged array) ends Orbax's event loop while TensorStore still
    reads the checkpoint's other arrays; each read that completes then calls back into the
    closed loop, and Python prints a traceback for it, one per array (about 270 for a run),
    whenever it completes, also after the restore returned. They say nothing the one line
    about the skipped checkpoint does not."""
    previous = sys.unraisablehook
    if getattr(previous, "drops_closed_loop", False):
        return

    def hook(report):
        e = report.exc_value
        if not (isinstance(e, RuntimeError) and str(e) == "Event loop is closed"):
            previous(report)

    hook.drops_closed_loop = True
    sys.unraisablehook = hook


def restore_newest(out: Path, restore_fn, log=print):
    """The state of the newest checkpoint of `out` that reads, newer ones that do not moved
    aside to OUT/checkpoints_damaged/STEP (kept, and out of the way of the steps the resumed
    run saves again).

    Args:
      out: the run directory.
      restore_fn: `restore_fn(manager, step)` -> state; an exception says the step is damaged.
      log: prints what was skipped and why.
    Returns:
      (step, state, [(skipped step, why)]), or (None, None, []) if there is no checkpoint.
    Raises:
      ResumeError: there are checkpoints and none reads; each step's reason is in the message.
    """
    _, manager = checkpoint_manager(out)
    skipped = []
    for step in sorted(manager.all_steps(), reverse=True):
        try:
            state = restore_fn(manager, step)
        except Exception as e:  # damaged data, metadata or a cut-short copy: TensorStore's
            skipped.append((step, _why(e)))  # DATA_LOSS, JSON and file errors alike
            _drop_closed_loop_reports()
            continue
        break
    else:
        if skipped:
            raise ResumeError(
                f"--resume: no checkpoint of {str(out)!r} reads, so there is nothing to resume "
                "from (nothing was changed): " + "; ".join(f"step {s}: {w}" for s, w in skipped)
            )
        return None, None, []
    for bad, why in skipped:
        log(f"checkpoint {bad} does not read, skipped ({why})")
    if skipped:
        if jax.process_index() == 0:
            for bad, _ in skipped:
                target = out / DAMAGED / str(bad)
                n = 1
                while target.exists():
                    n += 1
                    target = out / DAMAGED / f"{bad}-{n}"
                target.parent.mkdir(exist_ok=True)
                (out / "checkpoints" / str(bad)).rename(target)
                log(f"moved it to {target} (kept, not deleted)")
        if jax.process_count() > 1:  # every process sees the moves before it saves
            from jax.experimental import multihost_utils

            multihost_utils.sync_global_devices("damaged checkpoints moved")
    manager.close()
    return step, state, skipped
