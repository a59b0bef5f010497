"""A run's one writer of files, as brax's `progress_fn` is its trainer's: the stages hand it
what they made and go on with the values in memory; it writes them into the run directory
(`evojax_morph.run` lists the files). Only the lead process writes, except the checkpoints and
the controllers, which every process saves (Orbax). What a stage needs of an earlier one never
goes through a file: the body log's best come back from `end_of_steps`, read from the log this
recorder kept, and reach every process."""

from __future__ import annotations

import csv
import dataclasses
import io
import json
from pathlib import Path

import jax
import numpy as np

from evojax_morph.figures import plots, video
from evojax_morph.records import bodylog, checkpoints, saved_controllers
from evojax_morph.run.resume import Start, start
from evojax_morph.sharding import broadcast_json


class Recorder:
    """The files of the run in `out`; `lead`: this process writes them."""

    def __init__(self, out: Path, lead: bool):
        self.out, self.lead = out, lead
        self.space = self.manager = self.log = self._tb = None
        self.rows: list[dict] = []  # metrics.csv's, in memory and on disk alike

    def open(self, run, resume: bool, abstract) -> Start:
        """Where the run `run` (`driver.Run`) starts, read from its directory first
        (`resume.start`: m0, or with `resume` its newest checkpoint that reads, restored to
        `abstract`; a file it reads back that is not the run's raises `checkpoints.Damaged`
        before anything is written); then the directory taken under the settings the run goes
        on under: config.json, the checkpoints, the body log of its space."""
        begin = start(run, resume, abstract)
        if self.lead:
            checkpoints.write_atomic(self.out / "config.json",
                                     json.dumps(dataclasses.asdict(run.cfg), indent=1))
        self.space = space = run.p.space
        _, self.manager = checkpoints.checkpoint_manager(self.out)  # Orbax's CheckpointManager
        self.log = bodylog.BodyLog(self.out / "bodies.sqlite", space) if self.lead else None
        return begin

    def begin(self, step: int, rows: list[dict], first=None) -> None:
        """The steps begin after `step` (-1 with `first`, m0 evaluated in every evolution,
        logged as step 0), with metrics.csv's `rows` of the steps before."""
        from tensorboardX import SummaryWriter

        self.rows = rows
        if not self.lead:
            return
        self.log.resume(step)
        if first is not None:
            self.log.add(0, first.morph, first.fitness, first.fitness_std, first.diverged,
                         distance=first.distance, upright=first.upright)
            self.log.commit()
        self._tb = SummaryWriter(str(self.out / "tb"))

    def chunk(self, step: int, metrics: dict) -> None:
        """The steps after `step` of a chunk's host `metrics`: their bodies into the body log,
        their rows into metrics.csv and TensorBoard."""
        bodies = metrics.pop("bodies")
        for i in range(len(metrics["reward"])):
            reward = metrics["reward"][i]
            row = {
                "step": step + i + 1,
                "reward_median": float(np.median(reward)),
                "reward_q25": float(np.quantile(reward, 0.25)),
                "reward_q75": float(np.quantile(reward, 0.75)),
                "fitness_mean": float(np.mean(metrics["fitness"][i])),
            }
            row.update({k: float(v[i]) for k, v in metrics.items()
                        if k not in ("reward", "fitness")})
            self.rows.append(row)
            if self.lead:
                at = lambda tree, i=i: jax.tree.map(lambda x: x[i], tree)  # noqa: E731
                self.log.add(step + i + 1, at(bodies["morph"]), bodies["fitness"][i],
                             bodies["fitness_std"][i], bodies["diverged"][i],
                             at(bodies["parent"]), bodies["distance"][i], bodies["upright"][i])
                for name, value in row.items():
                    if name != "step":
                        self._tb.add_scalar(name.replace("_", "/", 1), value, row["step"])
        if self.lead:
            self.log.commit()
            table = io.StringIO(newline="")
            w = csv.DictWriter(table, fieldnames=list(self.rows[0]))
            w.writeheader()
            w.writerows(self.rows)
            checkpoints.write_atomic(self.out / "metrics.csv", table.getvalue())

    def checkpoint(self, step: int, state) -> None:
        """A checkpoint of the agent `state` at `step`, with the body log's proof."""
        self.manager.save(step, args=checkpoints.save_args(
            state, step, self.log.proof() if self.lead else None))

    def end_of_steps(self, confirm: int) -> dict:
        """The steps are done: the checkpoints land, the log closes. Returns, on every process,
        what the log says of the run: its 10 best bodies ("best_bodies", `bodylog.best_bodies`),
        its highest single draw ("best_draw"), its proof ("log") and the `confirm` best with
        their shapes ("candidates": (entry, shape JSON) pairs, for the confirm stage)."""
        self.manager.wait_until_finished()
        found = None
        if self.lead:
            self._tb.close()
            proof = self.log.proof()
            self.log.close()
            path = self.out / "bodies.sqlite"
            ranked = bodylog.best_bodies(path, max(10, confirm))
            shapes = bodylog.shapes(path, self.space, [b["body"] for b in ranked[:confirm]])
            missing = [b["body"] for b in ranked[:confirm] if b["body"] not in shapes]
            if missing:  # every run that reaches here keeps each body's shape in its log
                raise checkpoints.Damaged(f"{path}: no shape kept for the body log's "
                                          f"{', '.join(missing)} (a damaged log): the run "
                                          "cannot confirm it")
            found = {"best_bodies": ranked[:10], "best_draw": bodylog.best_draw(path),
                     "log": proof, "candidates": [(b, self.space.to_json(shapes[b["body"]]))
                                                  for b in ranked[:confirm]]}
        return broadcast_json(found)

    def controllers(self, saved: dict[str, saved_controllers.SavedController]) -> None:
        """controllers/NAME for each body's `saved` controllers (every process saves)."""
        for name, one in saved.items():
            if one is not None:  # None: kept from the first finish
                saved_controllers.save(self.out / saved_controllers.DIR / name, one)

    def confirmed(self, record: dict) -> None:
        """confirmed.json, sealed (a --resume reads it back only as written)."""
        if self.lead:
            checkpoints.write_atomic(self.out / "confirmed.json",
                         json.dumps(checkpoints.seal(record), indent=1))

    def figures(self, summary: dict, best, greedy) -> list[str]:
        """curve.png, best.xml, confirmed.png (bodies confirmed) and trajectory.png (a greedy
        trajectory); returns the names written, newest first."""
        col = lambda name: np.array([r[name] for r in self.rows], float)  # noqa: E731
        plots.plot_curve(self.out / "curve.png", col("step"), col("reward_median"),
                         col("reward_q25"), col("reward_q75"))
        checkpoints.write_atomic(self.out / "best.xml", self.space.to_mjcf(best))
        written = []
        if summary["confirmed"]:
            plots.plot_confirmed(self.out / "confirmed.png", summary["confirmed"])
            written = ["confirmed.json", "confirmed.png"]
        if greedy is not None:
            plots.plot_trajectory(self.out / "trajectory.png", self.space, greedy.morphs,
                                  greedy.fitness, greedy.actions)
            written = ["trajectory.png"] + written
        return written

    def video(self, saved: saved_controllers.SavedController) -> video.Rendered:
        """best.gif: one episode of the best body's first controller."""
        return video.render_saved(saved, self.out / "best", mp4=False)

    def summary(self, summary: dict) -> None:
        checkpoints.write_atomic(self.out / "summary.json", json.dumps(summary, indent=1))

    def timing(self, times: dict) -> None:
        checkpoints.write_atomic(self.out / "timing.json", json.dumps(times, indent=1))
