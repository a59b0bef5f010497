"""Where a run starts: m0, or for `--resume` what its directory holds, read back once.

`start` is the one place a run reads its own directory: the newest checkpoint that reads, the
body log and metrics.csv checked against it, and a confirmed.json that a finished run wrote
(with the best body's controllers), which the confirm stage then keeps instead of confirming
again. Everything later is handed on in memory (`Start`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, NamedTuple

from evojax_morph.morphology import Morphology
from evojax_morph.records import bodylog, checkpoints, saved_controllers
from evojax_morph.search.confirm import confirm_skipped


class Start(NamedTuple):
    """Where the steps begin."""

    step: int | None  # the restored checkpoint's step; None: from m0
    state: Any  # the agent state restored (None: from m0)
    rows: list[dict]  # metrics.csv's rows up to `step`
    log: dict | None  # the body log's proof the checkpoint holds (None: none restored)
    kept: dict | None  # confirmed.json's record where the run was confirmed at its end with
    # these settings from this log (a --resume of a finished run); else None
    kept_best: Any = None  # its best body (`Morphology`) and SavedController (None for a
    # fitness that trains no controllers)
    stale: bool = False  # a confirmed.json is there that is not kept (it is confirmed again)
    skipped: str | None = None  # why the confirm stage evaluates nothing
    # (`search.confirm.confirm_skipped`)

    @property
    def confirms(self) -> bool:
        """Whether the confirm stage evaluates bodies: not skipped, not kept from a finished
        run. Then the greedy trajectory's bodies join its fitness call; else they have one of
        their own (`pipeline.make_greedy_evaluation`) unless kept."""
        return self.skipped is None and self.kept is None


def start(run, resume: bool, abstract) -> Start:
    """Where the run `run` (`driver.Run`) begins: m0, or with `resume` the newest checkpoint
    of its directory that reads, restored to `abstract` (the agent state's shapes and
    placement). Raises `checkpoints.Damaged` where a file it reads back is not the run's."""
    out, cfg = run.out, run.cfg
    done, skipped = out / "confirmed.json", confirm_skipped(cfg)
    if not resume:
        return Start(None, None, [], None, None, stale=done.exists(), skipped=skipped)
    before = checkpoints.read_sealed(done) if done.exists() else None
    step, restored, _ = checkpoints.restore_newest(
        out, lambda manager, step: checkpoints.restore_checked(manager, step, abstract), run.log)
    if step is None:
        run.log(f"--resume: {out} holds no checkpoint yet (the run stopped before its first), "
                "so it starts again from m0")
        state = log = None
        rows = []
    else:
        state, log = restored[0], restored[1]["log"]
        check_log(out / "bodies.sqlite", step, log)
        rows = checkpoints.metrics_rows(out / "metrics.csv", step)
    # confirmed.json's record where the run was confirmed at this step with these settings
    # from the body log whose proof the restored checkpoint holds, so that a --resume of a
    # finished run does not do it again; not another run's, nor one of a log since gone on
    now = {"env_steps": max(step or 0, cfg.steps), "bodies": cfg.confirm,
           "controllers": cfg.confirm_controllers, "log": log}
    kept = before if log is not None and before is not None and all(
        before.get(k) == v for k, v in now.items()) else None
    best = None
    if kept and kept["confirmed"]:
        controllers = (saved_controllers.load(out / saved_controllers.DIR / "best")
                       if saved_controllers.has_controllers(run.p.fitness) else None)
        best = Morphology.from_dict(kept["best_morphology"]), controllers
    return Start(step, state, rows, log, kept, best, before is not None and kept is None,
                 skipped)


def check_log(path: Path, step: int, saved: dict | None) -> None:
    """Raises `checkpoints.Damaged` unless the body log `path` holds, up to `step`, the rows
    whose proof the checkpoint of `step` recorded (`saved`; None: a process that kept no log):
    a log deleted, emptied, cut short, edited or another run's is not resumed."""
    if saved is None:
        return
    with checkpoints.read_error(str(path)):
        found = bodylog.proof(path, step)
    if found != saved:
        what = (f"{found['rows']:,}" if found["rows"] != saved["rows"]
                else "as many, with other values")
        raise checkpoints.Damaged(
            f"--resume: {str(path)!r} is not the body log checkpoint {step} was saved with "
            f"({saved['rows']:,} evaluations up to step {step}; it holds {what}): the run "
            "cannot go on from it (a log changed, damaged or of another run)")
