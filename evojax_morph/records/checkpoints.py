"""A run's Orbax checkpoints, and a study's (`search.study.run_study`): the manager of
RUN/checkpoints, and the restore of the newest that reads (`restore_newest`), the damaged ones
moved aside, for a --resume (`run.resume`), and metrics.csv's rows up to it (`metrics_rows`).

Every checkpoint proves what it holds: beside the agent state it keeps, in the same atomic save,
the SHA-256 of each array's bytes (`save_args`); a restore recomputes them (`restore_checked`).
A digest that does not match or is missing, or non-finite values where the state must be finite
(`FINITE`), make the checkpoint damaged, as one that does not read is. It also records which
it is: its step and the proof of the run's body log up to it (`bodylog.BodyLog.proof`), so a
checkpoint copied or renamed to another step is damaged too, and a --resume checks the body log
against it (`run.resume`). Saved controllers and confirmed.json carry digests of the same kind
(`digests`, `seal`); confirmed.json also the log's proof, kept only by a resume of that log.
"""

from __future__ import annotations

import contextlib
import csv
import fcntl
import hashlib
import itertools
import json
import logging
import os
import re
import sys
from pathlib import Path

import jax
import numpy as np

from evojax_morph.sharding import to_host

# The parts of the agent state that must be finite: the agent's networks, optimiser and memory,
# and the controllers; a fitness, a distance (NaN: no episode) or the best fitness (-inf at
# first) may not be.
FINITE = (".learner", ".evo.params", ".first.params", ".best_params")


def write_atomic(path: Path, data: bytes | str) -> None:
    """`data` (str: UTF-8) to `path`: written to PATH.tmp beside it, flushed to the disk and
    renamed over it, the folder flushed after, so a reader, or a resume after a kill or a power
    cut, finds the last whole file or the new whole one, never a part (a run's metrics.csv,
    config.json, summary.json, confirmed.json; the experiments' resumable pickles)."""
    data = data.encode() if isinstance(data, str) else data
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    folder = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(folder)
    finally:
        os.close(folder)


def checkpoint_manager(out: Path):
    import orbax.checkpoint as ocp

    options = ocp.CheckpointManagerOptions(max_to_keep=2, create=True)
    return ocp, ocp.CheckpointManager(out.resolve() / "checkpoints", options=options)


OS_ERROR = re.compile(r"os_error_code='(\d+)'")  # how TensorStore's errors name the OS's


@contextlib.contextmanager
def saving(folder: Path):
    """A checkpoint save the machine refused (a full disk, a folder made read-only), which
    Orbax raises as TensorStore's ValueError naming the OS's error code, raised as the OSError
    it is, naming `folder` (`python -m evojax_morph.run` says it in one line, exit 1); the logs
    of it from Orbax's threads (a traceback each) are dropped from then on."""
    logging.getLogger("absl").addFilter(_not_a_machine_fault)
    try:
        yield
    except ValueError as e:
        found = OS_ERROR.search(str(e))
        if found is None:
            raise
        code = int(found.group(1))
        raise OSError(code, os.strerror(code), str(folder)) from e


def _not_a_machine_fault(record) -> bool:
    """Whether the log `record` is not of a write the machine refused (`saving`)."""
    e = record.exc_info[1] if record.exc_info else None
    return not (OS_ERROR.search(record.getMessage()) or (e and OS_ERROR.search(str(e))))


class ResumeError(RuntimeError):
    """No checkpoint of a run directory could be read back."""


class Locked(RuntimeError):
    """Another run or resume holds the run directory (`lock`)."""


@contextlib.contextmanager
def lock(out: Path):
    """An exclusive lock on the run directory `out` for the run's whole life: its file .lock
    holds the holder's pid, locked with flock (released by the kernel when the process ends,
    however it ends). A second run or resume on `out` raises `Locked` at once, naming the
    holder; `python -m evojax_morph.run` says so in one line and exits 2. The lead process of
    a distributed run holds it for them all."""
    if jax.process_index() != 0:
        yield
        return
    f = open(out / ".lock", "a+")  # noqa: SIM115  (held open for the run's life)
    try:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        f.seek(0)
        pid = f.read().strip() or "unknown"
        f.close()
        raise Locked(in_use(out, pid)) from None
    try:
        f.seek(0)
        f.truncate()
        f.write(str(os.getpid()))
        f.flush()
        yield
    finally:
        f.close()


def in_use(out: Path, pid: str) -> str:
    """What a run says of `out` held by the run of `pid` (`lock`, `holder`)."""
    return (f"{str(out)!r} is in use by another run (pid {pid}): wait for it to end, or pass "
            "another --out")


def holder(out: Path) -> str | None:
    """The pid of the run that holds `out` (`lock`), None where none does: asked before
    saying that `out` holds a run to --resume, which a live run's directory does not."""
    try:
        f = open(out / ".lock")  # noqa: SIM115
    except FileNotFoundError:
        return None
    with f:
        try:  # shared, for a moment: taken where no run holds the exclusive lock
            fcntl.flock(f, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return f.read().strip() or "unknown"
    return None


class Damaged(ValueError):
    """Saved data that does not prove what it holds: a digest that does not match or is
    missing, or non-finite values where they must be finite."""


def digests(tree) -> dict[str, str]:
    """The SHA-256 of each array of the host pytree `tree` (its dtype, shape and bytes), by
    its key path (`jax.tree_util.keystr`)."""
    found = {}
    for path, x in jax.tree_util.tree_flatten_with_path(tree)[0]:
        x = np.ascontiguousarray(x)
        h = hashlib.sha256(f"{x.dtype.str}{x.shape}".encode())
        h.update(x.tobytes())
        found[jax.tree_util.keystr(path)] = h.hexdigest()
    return found


def check(tree, saved: dict | None, finite=("",)) -> None:
    """Raises `Damaged`, naming the array and the check, unless every array of the host pytree
    `tree` has the digest `saved` keeps for it (`digests`) and the float arrays whose key path
    starts with one of `finite` are finite."""
    if not isinstance(saved, dict):
        raise Damaged("no digest saved")
    found = digests(tree)
    for path in list(found) + [p for p in saved if p not in found]:
        if path not in saved:
            raise Damaged(f"{path}: no digest saved")
        if path not in found:
            raise Damaged(f"{path}: saved with a digest, not restored")
        if saved[path] != found[path]:
            raise Damaged(f"{path}: its SHA-256 is not the saved one")
    for path, x in jax.tree_util.tree_flatten_with_path(tree)[0]:
        name, x = jax.tree_util.keystr(path), np.asarray(x)
        if name.startswith(finite) and x.dtype.kind in "fc" and not np.isfinite(x).all():
            raise Damaged(f"{name}: non-finite values where they must be finite")


def save_args(state, step: int, log: dict | None):
    """Orbax's save of the agent `state` at `step` with its digest and its record, {"step",
    "log"}, in one atomic step; every process. log (JSON): a run's body log's proof
    (`bodylog.BodyLog.proof`), None on the processes that keep no log; a study's timings so
    far (`search.study.run_study`)."""
    import orbax.checkpoint as ocp

    return ocp.args.Composite(state=ocp.args.StandardSave(state),
                              digest=ocp.args.JsonSave(digests(to_host(state))),
                              record=ocp.args.JsonSave({"step": step, "log": log}))


def restore_checked(manager, step: int, abstract):
    """(the agent state of checkpoint `step`, restored as `abstract` and checked against its
    digest (`check`, the `FINITE` parts finite); its record, whose step must be `step`).
    Raises: `Damaged` or Orbax's read error."""
    import orbax.checkpoint as ocp

    args = ocp.args.Composite(state=ocp.args.StandardRestore(abstract),
                              digest=ocp.args.JsonRestore(), record=ocp.args.JsonRestore())
    try:
        restored = manager.restore(step, args=args)
    except KeyError as e:  # Orbax's for an item the checkpoint lacks
        if '"digest"' in str(e):
            raise Damaged("no digest saved (saved before checkpoints had digests?)") from None
        if '"record"' in str(e):
            raise Damaged("no step or body log recorded (saved before checkpoints recorded "
                          "them?)") from None
        raise
    check(to_host(restored["state"]), restored["digest"], FINITE)
    record = restored["record"]
    if not isinstance(record, dict) or record.get("step") != step:
        saved = record.get("step") if isinstance(record, dict) else None
        raise Damaged(f"it holds the state of step {saved}, not of step {step} (copied or "
                      "renamed?)")
    return restored["state"], record


def seal(record: dict) -> dict:
    """`record` (JSON) with the SHA-256 of its canonical text under "sha256" (`unseal`)."""
    body = {k: v for k, v in record.items() if k != "sha256"}
    text = json.dumps(body, sort_keys=True)
    return body | {"sha256": hashlib.sha256(text.encode()).hexdigest()}


def unseal(record, name: str = "") -> dict:
    """The `seal`ed `record` without its digest. Raises `Damaged` (its message begins with
    `name`) where the digest is missing or does not match."""
    name = f"{name}: " if name else ""
    if not isinstance(record, dict) or "sha256" not in record:
        raise Damaged(f"{name}no digest saved")
    if seal(record)["sha256"] != record["sha256"]:
        raise Damaged(f"{name}its SHA-256 is not the saved one")
    return {k: v for k, v in record.items() if k != "sha256"}


def read_sealed(path: Path) -> dict:
    """The record `seal`ed in the JSON file `path`; `Damaged` where it does not read."""
    with read_error(str(path)):
        return unseal(json.loads(Path(path).read_text()))


DAMAGED = "checkpoints_damaged"  # where damaged checkpoints are moved, under the run


def metrics_rows(path: Path, step: int) -> list[dict]:
    """The rows of steps 1 to `step` of metrics.csv `path`, which a resume from `step` keeps.
    Raises `Damaged` where the file does not hold them whole (deleted, emptied,
    cut short: a run resumed from it would end with rows missing); rows after `step` (the
    steps the resume redoes) may be cut short."""
    with read_error(str(path)), open(path, newline="") as f:
        rows = list(itertools.islice(csv.DictReader(f), step))
    whole = 0  # the rows of steps 1, 2, ... in order, every value there
    for r in rows:
        if None in r or None in r.values() or r.get("step") != str(whole + 1):
            break
        whole += 1
    if whole < step:
        raise Damaged(
            f"--resume: {str(path)!r} does not hold the rows of steps 1 to {step} whole (it "
            f"holds {whole}): the run cannot go on from it (a file changed or damaged)")
    return rows


def _why(e: Exception) -> str:
    """The first line of a restore error's innermost cause (where TensorStore names the array),
    without the spec TensorStore appends."""
    while e.__cause__ is not None:
        e = e.__cause__
    text = str(e).split(" [tensorstore_spec")[0].strip().splitlines()
    text = text[0] if text else ""
    return f"{type(e).__name__}: {text[:300]}"


@contextlib.contextmanager
def read_error(name: str):
    """Any error of the reads inside raised as `Damaged`, naming `name` (and `_why`)."""
    try:
        yield
    except Damaged as e:
        raise Damaged(f"{name} is damaged: {e}") from None
    except Exception as e:
        _drop_cut_short_reports()
        raise Damaged(f"{name} does not read ({_why(e)})") from e


CUT_SHORT = ("Event loop is closed", "Encountered error while reading array index")


def _cut_short_log(record) -> bool:
    """Whether asyncio's log `record` is of a read a failed restore left unawaited."""
    text = record.getMessage()
    return "exception was never retrieved" in text and (
        "tensorstore_spec" in text or CUT_SHORT[1] in text)


def _drop_cut_short_reports() -> None:
    """From now on, drop the reports of reads cut short by a failed restore (idempotent).

    A restore that fails (a damaged array) ends Orbax's event loop while TensorStore still
    reads the checkpoint's other arrays; each read that completes then calls back into the
    closed loop, and each that fails too (a truncated or missing data file holds several
    arrays) is left unawaited: Python prints a traceback for each (an unraisable exception or
    asyncio's log), one per array (about 270 for a run), whenever it completes, also after
    the restore returned. They say nothing the one line about the damage does not."""
    previous = sys.unraisablehook
    if getattr(previous, "drops_cut_short", False):
        return

    def hook(report):
        e = report.exc_value
        cut_short = (isinstance(e, RuntimeError) and str(e) == CUT_SHORT[0]) or (
            type(e) is Exception and str(e).startswith(CUT_SHORT[1]))
        if not cut_short:
            previous(report)

    hook.drops_cut_short = True
    sys.unraisablehook = hook
    logging.getLogger("asyncio").addFilter(lambda record: not _cut_short_log(record))


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
            _drop_cut_short_reports()
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
        log(f"checkpoint {bad} is damaged, skipped ({why})")
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
