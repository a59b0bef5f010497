"""The run command: bad input, resume and the body log (its PPO smoke run is in
test_sharding_run.py, on 4 devices, in the slow set)."""

import collections
import concurrent.futures
import csv
import dataclasses
import json
import logging
import os
import shutil
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import DAMAGES, data_files, flip, run_shape, truncate

import evojax_morph as em
from evojax_morph.physics import engines
from evojax_morph.records.checkpoints import (
    DAMAGED,
    FINITE,
    Damaged,
    _drop_cut_short_reports,
    check,
    checkpoint_manager,
    digests,
    restore_checked,
    restore_newest,
    write_atomic,
)
from evojax_morph.run import cli, compile_ahead
from evojax_morph.search import confirm as confirming
from evojax_morph.search.pipeline import RunConfig, build

TINY = [
    "--space",
    "bad_walker",
    "--fitness",
    "predefined",
    "--num-envs",
    "4",
    "--chunk",
    "3",
    "--explore-steps",
    "4",
    "--learning-starts",
    "8",
]


@pytest.mark.parametrize(
    "args, message",
    [
        (["--space", "nope"], "unknown space 'nope'"),
        (["--space", "bad_walker", "--steps", "-3"], "--steps must be positive"),
        (["--space", "bad_walker", "--fitness", "magic"], "invalid choice"),
        (["--space", "bad_walker", "--task", "run"],
         "unknown task 'run'; known tasks: distance, walk"),
        (["--space", "bad_walker", "--fitness", "table", "--task", "walk"],
         "was built under the task 'distance', but the fitness asks for 'walk' (--task)"),
        (["--agent", "nope"], "regularized_evolution"),  # the agents named
        (["--agent", "regularized_evolution", "--population", "3"],
         "the population (3) must hold at least a step's 4 children"),
        (["--agent", "regularized_evolution", "--population", "8", "--tournament", "9"],
         "the tournament must sample between 1 and the population (8) members, got 9"),
        (["--agent", "regularized_evolution", "--num-envs", "1", "--population", "1"],
         "the population must be at least 2, got 1"),
        (["--agent", "evolution", "--num-envs", "1"], "it needs at least 2 parallel evolutions"),
        (["--agent", "predictor", "--population", "3"],  # its parents' settings, shared flags
         "the population (3) must hold at least a step's 4 children"),
        (["--agent", "predictor", "--agent.acquisition", "best"],
         "predictor: acquisition must be 'its' or 'ucb', got 'best'"),
        (["--agent", "random", "--population", "3"], None),  # a shared setting not its
        (["--seed", str(2**64)], "--seed must fit in 64 bits"),
        (["--space", "bad_walker", "--fitness", "table", "--controllers", "1000"],
         "--controllers 1000: the table holds 32 results a body"),
    ],
)
def test_bad_input_exits_with_2(args, message, capsys, tmp_path):
    if message is None:  # good input: it parses
        assert cli.parse(args + ["--out", str(tmp_path / "run")])[0].agent == args[1]
        return
    with pytest.raises(SystemExit) as e:
        cli.main(args + ["--out", str(tmp_path / "run")])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and message in err[0] and "--help" in err[1], err  # no usage block
    assert not (tmp_path / "run").exists()  # nothing half-written


@pytest.mark.parametrize("space, evolutions, steps", [
    ("bad_walker", 256, 100), ("length_walker", 256, 100), ("crawler", 256, 100),
    ("constructor", 128, 60)])
def test_on_a_gpu_the_agents_settings_follow_the_spaces_batch(space, evolutions, steps):
    """A space gives its GPU batch and steps (`Space.gpu_defaults`), the agents' settings
    follow: epsilon over half the steps, learning after one step's batch; the values each
    space listed itself before (50 and 256; the Constructor's 30 and 128)."""
    got = cli.gpu_defaults(space)
    assert (got["num_envs"], got["steps"]) == (evolutions, steps)
    assert (got["explore_steps"], got["learning_starts"]) == {
        256: (50, 256), 128: (30, 128)}[evolutions]
    assert set(got) <= {f.name for f in dataclasses.fields(RunConfig)}


@pytest.mark.parametrize("record", ['{"space": "bad_walker"}', '{"space": ', '[1]'])
def test_a_tame_classifier_that_is_not_whole_exits_2(record, capsys, tmp_path):
    """A classifier folder with tame.json alone (no weights), or a tame.json that is not JSON
    or not a classifier's: exit 2, one line and the hint, nothing created."""
    (tmp_path / "tame").mkdir()
    (tmp_path / "tame" / "tame.json").write_text(record)
    with pytest.raises(SystemExit) as e:
        cli.main(["--space", "bad_walker", "--fitness", "tame", "--classifier",
                  str(tmp_path / "tame"), "--out", str(tmp_path / "run")])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 2 and "python -m evojax_morph.tame" in err[0], err
    assert not (tmp_path / "run").exists()


def test_distributed_without_a_coordinator_exits_2(tmp_path):
    """--distributed where no cluster is found and no --coordinator given: exit 2 with one
    line saying what to pass, nothing written (a process of its own: JAX's distributed start
    must come before its backend, which this one has already started)."""
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    env.pop("JAX_COORDINATOR_ADDRESS", None)
    proc = subprocess.run([sys.executable, "-m", "evojax_morph.run", "--distributed", "--out",
                           str(tmp_path / "run")], capture_output=True, text=True, env=env,
                          timeout=300)
    err = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(err) == 2, proc.stderr[-2000:]
    assert "--distributed:" in err[0] and "--coordinator" in err[0]
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("damage", ["cut", "key", "type", "space", "seed", "steps"])
def test_a_resume_of_a_damaged_config_exits_2(damage, capsys, tmp_path):
    """A config.json cut short, with a key RunConfig does not know, a value of the wrong type,
    an unknown space, or a value no run starts with (a seed past 64 bits, negative steps):
    --resume exits 2 saying the file is not a run's config, and changes nothing there."""
    import dataclasses

    config = dataclasses.asdict(RunConfig())
    text = {"cut": json.dumps(config)[:40],
            "key": json.dumps({**config, "speed": 3}),
            "type": json.dumps({**config, "steps": "nine"}),
            "space": json.dumps({**config, "space": "nope"}),
            "seed": json.dumps({**config, "seed": 2**70}),
            "steps": json.dumps({**config, "steps": -5})}[damage]
    out = tmp_path / "run"
    out.mkdir()
    (out / "config.json").write_text(text)
    with pytest.raises(SystemExit) as e:
        cli.main(["--out", str(out), "--resume"])
    assert e.value.code == 2 and "is not a run's config.json" in capsys.readouterr().err
    assert [p.name for p in out.iterdir()] == ["config.json"]
    assert (out / "config.json").read_text() == text


@pytest.mark.parametrize("table", ["garbage", "cut", "other space"])
def test_a_table_that_is_not_the_spaces_exits_2(table, capsys, tmp_path):
    """--table naming a file that is not a table, one cut short, or another space's table:
    exit 2 with why, before anything is written."""
    from evojax_morph.fitnesses import table as tb

    packaged = tb.TABLES / "bad_walker.npz"
    path = tmp_path / "t.npz"
    path.write_bytes({"garbage": b"not a table", "cut": packaged.read_bytes()[:5000],
                      "other space": packaged.read_bytes()}[table])
    space = "length_walker" if table == "other space" else "bad_walker"
    with pytest.raises(SystemExit) as e:
        cli.main(["--space", space, "--fitness", "table", "--table", str(path),
                  "--out", str(tmp_path / "run")])
    err = capsys.readouterr().err
    assert e.value.code == 2
    assert ("of the space 'bad_walker', not 'length_walker'" if table == "other space"
            else "is not a readable table") in err, err
    assert not (tmp_path / "run").exists()


def test_unwritable_out_and_missing_resume(capsys, tmp_path, monkeypatch):
    """An --out that cannot be written, a --resume of no run or without --out: exit 2, two
    lines, nothing made (not the directory, not a fresh runs/...-seed0)."""
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(SystemExit) as e:
        cli.main(TINY + ["--out", str(blocker / "run")])
    assert e.value.code == 2 and "cannot write to --out" in capsys.readouterr().err
    monkeypatch.chdir(tmp_path)  # where a fresh run directory would go (runs/...)
    for resume, says in ((["--out", str(tmp_path / "missing")], "no run in"),
                         ([], "--resume needs --out")):
        with pytest.raises(SystemExit) as e:
            cli.main(TINY + resume + ["--resume"])
        err = capsys.readouterr().err.strip().splitlines()
        assert e.value.code == 2 and len(err) == 2 and says in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]  # nothing made


def test_physics_that_cannot_run_exits_with_2(monkeypatch, capsys, tmp_path):
    """--physics warp where Warp cannot run: exit 2 with the engine's own reason, nothing
    written; "auto" on a CPU takes the JAX engine."""
    cannot = engines.WARP._replace(available=lambda: (False, "warp-lang is not installed"))
    monkeypatch.setitem(engines._REGISTRY, "warp", cannot)
    out = tmp_path / "run"
    with pytest.raises(SystemExit) as e:
        cli.main(["--space", "bad_walker", "--physics", "warp", "--out", str(out)])
    assert e.value.code == 2
    assert "the warp physics cannot run here: warp-lang is not installed" in capsys.readouterr().err
    assert not out.exists()
    assert engines.resolve("auto")[0] == "jax"  # the tests run on the CPU backend
    with pytest.raises(ValueError, match="unknown physics 'mujoco'"):
        em.FitnessConfig(physics="mujoco")


@pytest.fixture(scope="module")
def straight(tmp_path_factory):
    """An uninterrupted 9-step run, seed 3 (checkpoints at steps 3, 6 and 9). Its confirm stage
    makes no fitness call: the predefined fitness is deterministic. Its engine has a preload
    (as Warp's, `Engine.preload`), asked once for this process's devices and the run's space."""
    out = tmp_path_factory.mktemp("straight") / "run"

    def no_call(*_, **__):
        raise AssertionError("a deterministic fitness confirmed")

    asked = []
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(confirming, "confirm", no_call)
        patch.setitem(engines._REGISTRY, "jax", engines.JAX._replace(preload=preloads(asked)))
        assert cli.main(TINY + ["--steps", "9", "--seed", "3", "--out", str(out)]) == 0
    assert asked == [(jax.local_devices(), "bad_walker")]
    return out


def preloads(asked: list):
    """An engine's preload (`Engine.preload`, as Warp's) that lists the devices and the space
    it is asked for and is done at once."""

    def preload(devices, space):
        asked.append((list(devices), space.name))
        done = concurrent.futures.Future()
        done.set_result(None)
        return done

    return preload


def test_confirm_is_a_no_op_on_a_deterministic_fitness(straight):
    summary = json.loads((straight / "summary.json").read_text())
    assert summary["confirmed"] == [] and "deterministic" in summary["confirm_note"]
    assert not (straight / "confirmed.json").exists() and not (straight / "confirmed.png").exists()
    draw = summary["best_single_draw"]  # the best body is the highest draw, its true value
    assert summary["best_fitness"] == pytest.approx(draw["fitness"])
    assert summary["best_body"] == draw["body"]


def test_resume_matches_an_uninterrupted_run(tmp_path, straight, monkeypatch):
    split = tmp_path / "split"
    assert (
        cli.main(TINY + ["--steps", "3", "--seed", "3", "--out", str(split)]) == 0
    )  # "interrupted"
    with pytest.raises(SystemExit):  # a second start in the same directory must say --resume
        cli.main(TINY + ["--steps", "9", "--seed", "3", "--out", str(split)])
    asked = []  # the resumed call has no m0: it waits for the preload before its first chunk
    monkeypatch.setitem(engines._REGISTRY, "jax", engines.JAX._replace(preload=preloads(asked)))
    assert cli.main(TINY + ["--steps", "9", "--out", str(split), "--resume"]) == 0
    assert asked == [(jax.local_devices(), "bad_walker")]
    a, b = (json.loads((d / "summary.json").read_text()) for d in (straight, split))
    assert a == b
    # timing.json: this call's clock; the resumed call ran steps 4-9 in two chunks of 3
    t = json.loads((split / "timing.json").read_text())
    assert t["steps"] == 6 and t["seconds"] >= t["outside_steps_seconds"] >= 0
    assert list(t["phases"]) == ["build_and_m0", "steps", "greedy_walk", "confirm",
                                 "controllers", "results", "best_gif"]
    assert abs(sum(t["phases"].values()) - t["seconds"]) < 0.5, t  # the phases fill the call
    assert 0 <= t["first_chunk_dispatch"] <= t["phases"]["steps"], t
    # finer: the resumed call built and restored (no m0), and ran two chunks after their jobs
    assert list(t["parts"]) == ["build"] and len(t["chunk_seconds"]) == 2, t
    assert sum(t["chunk_seconds"]) <= t["phases"]["steps"] and "chunk 3" in t["waits"], t
    assert t["waits"]["preload"] >= 0, t
    first = json.loads((straight / "timing.json").read_text())["parts"]
    assert list(first) == ["build", "m0_lower", "m0_compile", "m0_preload_wait",
                           "m0_evaluate"], first
    assert t["where"]["devices"] == jax.device_count() and t["where"]["physics"] == "jax", t
    assert json.loads((split / "config.json").read_text())["physics"] == "jax"  # auto on a CPU
    assert (straight / "metrics.csv").read_text() == (split / "metrics.csv").read_text()
    assert log_rows(split) == log_rows(straight)
    import orbax.checkpoint as ocp

    args = ocp.args.Composite(state=ocp.args.StandardRestore())
    restore = lambda d: ocp.CheckpointManager(d.resolve() / "checkpoints").restore(9, args=args)[
        "state"
    ]
    for x, y in zip(jax.tree.leaves(restore(straight)), jax.tree.leaves(restore(split))):
        np.testing.assert_array_equal(x, y)


def test_a_rewritten_file_is_the_old_one_or_the_new_one_whole(tmp_path, monkeypatch):
    """metrics.csv and the other files a run rewrites go through `write_atomic`: a write that
    fails before its rename (here the flush to the disk) leaves the old file as it was; one
    that ends leaves the new file and no temporary beside it."""
    import os

    path = tmp_path / "metrics.csv"
    write_atomic(path, "step\n1\n")

    def cut(fd):
        raise OSError(28, "No space left on device")

    with monkeypatch.context() as m:
        m.setattr(os, "fsync", cut)
        with pytest.raises(OSError):
            write_atomic(path, "step\n1\n2\n")
    assert path.read_text() == "step\n1\n"
    write_atomic(path, b"step\n1\n2\n")
    assert path.read_text() == "step\n1\n2\n"
    assert [p.name for p in tmp_path.iterdir()] == ["metrics.csv"]


def test_a_second_run_on_a_held_directory_exits_2_naming_the_holder(tmp_path, capsys):
    """While another process holds --out (its .lock flocked, its pid inside, as a run does),
    a run there exits 2 at once with one line naming that pid, also once it has saved a
    checkpoint (not "pass --resume"), and writes nothing there; once the holder is killed (-9:
    the kernel releases its lock), a run there goes."""
    out = tmp_path / "run"
    out.mkdir()
    hold = ("import fcntl, os, sys, time; f = open(sys.argv[1], 'a+'); "
            "fcntl.flock(f, fcntl.LOCK_EX); f.write(str(os.getpid())); f.flush(); "
            "print('held', flush=True); time.sleep(300)")
    holder = subprocess.Popen([sys.executable, "-c", hold, str(out / ".lock")],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        for made in ([], ["checkpoints"]):  # its first checkpoint saved: not one to --resume
            for name in made:
                (out / name).mkdir()
            with pytest.raises(SystemExit) as e:
                cli.main(TINY + ["--steps", "3", "--out", str(out)])
            assert e.value.code == 2
            err = capsys.readouterr().err.strip().splitlines()
            assert len(err) == 1 and f"in use by another run (pid {holder.pid})" in err[0], err
            assert sorted(p.name for p in out.iterdir()) == [".lock"] + made
    finally:
        holder.kill()
        holder.wait()
    (out / "checkpoints").rmdir()
    assert cli.main(TINY + ["--steps", "3", "--out", str(out)]) == 0


def test_a_resume_runs_to_its_saved_steps_unless_told(tmp_path, capsys):
    """--resume without --steps continues to the steps its run was started with (not the
    default 40, which would also rewrite the saved count); --steps N moves the end to N, and
    says so. A flag that would make another run (--num-envs, --seed, ...) exits 2 naming it;
    one given with its saved value is no change."""
    import dataclasses

    out = tmp_path / "run"
    out.mkdir()
    saved = dataclasses.replace(RunConfig(space="bad_walker", fitness="predefined"), steps=9)
    (out / "config.json").write_text(json.dumps(dataclasses.asdict(saved)))
    assert cli.parse(["--out", str(out), "--resume"])[0].steps == 9
    assert cli.parse(["--out", str(out), "--resume", "--seed", "0"])[0] == saved
    assert capsys.readouterr().out == ""
    cfg = cli.parse(["--out", str(out), "--resume", "--steps", "12", "--confirm", "2"])[0]
    assert (cfg.steps, cfg.confirm) == (12, 2)
    assert capsys.readouterr().out == (
        "--resume: --steps 9 -> 12, --confirm 4 -> 2; the rest as saved\n")
    for flag, value in (("--num-envs", "8"), ("--seed", "5"), ("--agent", "random")):
        with pytest.raises(SystemExit) as e:
            cli.parse(["--out", str(out), "--resume", flag, value])
        err = capsys.readouterr().err.strip().splitlines()
        assert e.value.code == 2 and len(err) == 2, err
        assert f"--resume: {flag} {value} would make another run (saved: " in err[0], err
    assert json.loads((out / "config.json").read_text()) == dataclasses.asdict(saved)
    assert cli.parse(["--out", str(tmp_path / "new")])[0].steps == RunConfig().steps


def stops_with_one_line(out: Path, capsys, why: str, where: Path, step: int) -> None:
    """A run of TINY to step 9 on `out` stopped by a machine's fault: exit 1 and one line on
    stderr, `why` at `where`, resumable from `step`."""
    with pytest.raises(SystemExit) as e:
        cli.main(TINY + ["--steps", "9", "--seed", "3", "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 1 and len(err) == 1, err
    assert err[0] == (f"python -m evojax_morph.run: error: {why} ({where}); the run can "
                      f"--resume from step {step} (--out {out} --resume)"), err


def test_a_full_disk_stops_the_run_with_one_line_and_exit_1(tmp_path, capsys, monkeypatch):
    """A write that fails mid-run (here metrics.csv after step 6's chunk, the disk full) stops
    the run with exit 1 and one line: the error, the file and the step it can resume from; the
    checkpoints before it are kept."""
    import errno

    from evojax_morph.records import checkpoints as ckpt

    write, metrics_writes = ckpt.write_atomic, []

    def full_after_6(path, data):
        if path.name == "metrics.csv":
            metrics_writes.append(path)
            if len(metrics_writes) == 3:  # after the chunks to steps 3 and 6 and their saves
                raise OSError(errno.ENOSPC, "No space left on device", str(path))
        write(path, data)

    monkeypatch.setattr(ckpt, "write_atomic", full_after_6)
    out = tmp_path / "run"
    stops_with_one_line(out, capsys, "No space left on device", out / "metrics.csv", 6)


def test_a_read_only_body_log_stops_the_run_with_one_line_and_resumes(tmp_path, straight,
                                                                     capsys, monkeypatch):
    """The run directory made read-only after step 3's chunk and checkpoint, where the body
    log writes (we run as root, where chmod stops no write, so its connection is opened again
    read-only: SQLite's own error, not an OSError): exit 1, one line naming bodies.sqlite and
    step 3, no traceback; a --resume once the fault is gone ends as the uninterrupted run."""
    from evojax_morph.records import bodylog

    add = bodylog.BodyLog.add

    def read_only_after_3(self, step, *args, **kwargs):
        if step == 4:
            self.db.close()
            self.db = sqlite3.connect(f"file:{self.path}?mode=ro", uri=True)
        return add(self, step, *args, **kwargs)

    out = tmp_path / "run"
    with monkeypatch.context() as m:
        m.setattr(bodylog.BodyLog, "add", read_only_after_3)
        stops_with_one_line(out, capsys, "attempt to write a readonly database",
                            out / "bodies.sqlite", 3)
    assert cli.main(TINY + ["--out", str(out), "--resume"]) == 0
    assert "resumed at step 3" in capsys.readouterr().out
    for name in ("metrics.csv", "summary.json"):
        assert (out / name).read_text() == (straight / name).read_text(), name
    assert log_rows(out) == log_rows(straight)


def test_a_checkpoint_save_on_a_full_disk_stops_the_run_with_one_line(tmp_path, capsys,
                                                                      monkeypatch):
    """A checkpoint save the disk refuses (Orbax raises TensorStore's ValueError, as on a real
    full disk, where it was a traceback after four from Orbax's threads' logs) stops the run
    with exit 1 and one line naming the checkpoints and the step it can resume from."""
    import orbax.checkpoint as ocp

    save = ocp.CheckpointManager.save

    def full_at_6(self, step, *args, **kwargs):
        if step == 6:
            raise ValueError('RESOURCE_EXHAUSTED: Error writing "evo.distance/0" in OCDBT '
                             "database: Failed to write 115488 bytes to file 19: No space left "
                             "on device [os_error_code='28']")
        return save(self, step, *args, **kwargs)

    monkeypatch.setattr(ocp.CheckpointManager, "save", full_at_6)
    out = tmp_path / "run"
    stops_with_one_line(out, capsys, "No space left on device", out / "checkpoints", 3)


def _snapshot(run_dir: Path) -> dict:
    return {str(f.relative_to(run_dir)): f.read_bytes()
            for f in sorted(run_dir.rglob("*")) if f.is_file()}


def test_resume_past_a_damaged_checkpoint(tmp_path, straight, capsys):
    """The newest checkpoint's arrays damaged as a disk error leaves them (bytes inverted in
    every data file of ocdbt.process_0/: they still read, as other values, which only the
    digest tells): the resume goes on from the one before, says which was skipped and why,
    keeps it aside, cuts metrics and the body log back, and ends as an uninterrupted run. Every
    checkpoint damaged: exit 2 with the reasons, the directory as it was."""
    split = tmp_path / "split"
    assert cli.main(TINY + ["--steps", "6", "--seed", "3", "--out", str(split)]) == 0
    checkpoints = split / "checkpoints"
    assert sorted(int(d.name) for d in checkpoints.iterdir()) == [3, 6]
    damage = lambda checkpoint: [flip(f) for f in data_files(checkpoint)  # noqa: E731
                                 if "ocdbt.process_0" in f.parts]
    damage(checkpoints / "6")

    none = tmp_path / "none"  # a copy with both checkpoints damaged
    shutil.copytree(split, none)
    damage(none / "checkpoints" / "3")
    before = _snapshot(none)
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        cli.main(TINY + ["--steps", "9", "--out", str(none), "--resume"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "no checkpoint of" in err
    assert "step 6: Damaged: .learner" in err and "step 3: Damaged: .learner" in err
    assert _snapshot(none) == before  # nothing deleted, moved or rewritten

    damaged = _snapshot(checkpoints / "6")
    assert cli.main(TINY + ["--steps", "9", "--out", str(split), "--resume"]) == 0
    printed = capsys.readouterr().out
    assert "checkpoint 6 is damaged, skipped (Damaged: .learner" in printed
    assert "its SHA-256 is not the saved one)" in printed
    assert "resumed at step 3" in printed
    assert _snapshot(split / DAMAGED / "6") == damaged  # kept as it was, not deleted
    assert sorted(int(d.name) for d in checkpoints.iterdir()) == [6, 9]  # saved afresh
    for name in ("metrics.csv", "summary.json"):
        assert (split / name).read_text() == (straight / name).read_text(), name
    assert log_rows(split) == log_rows(straight)


def test_a_resume_refuses_a_log_or_a_checkpoint_not_its_own(tmp_path, straight, capsys):
    """Every checkpoint records its step and the body log's proof up to it (issue 81): a log
    edited, deleted or cut short is refused with one line, exit 2, the directory as it was, and
    so is a metrics.csv that lacks rows up to the checkpoint (cut short, emptied, deleted); a
    checkpoint copied to another step's name is damaged (skipped, moved aside), and the resume
    goes on from the one before as an uninterrupted run does."""
    def refused(damage, says):
        out = tmp_path / damage.__name__
        shutil.copytree(straight, out)
        damage(out / "bodies.sqlite")
        before = _snapshot(out)
        capsys.readouterr()
        with pytest.raises(SystemExit) as e:
            cli.main(TINY + ["--steps", "12", "--out", str(out), "--resume"])
        err = capsys.readouterr().err.strip().splitlines()
        assert e.value.code == 2 and len(err) == 1 and says in err[0], err
        assert {k: v for k, v in _snapshot(out).items() if k != ".lock"} == {
            k: v for k, v in before.items() if k != ".lock"}

    def edit(f):  # one evaluation's fitness changed, as a flipped bit would
        db = sqlite3.connect(f)
        db.execute("UPDATE bodies SET fitness = fitness + 1 WHERE step = 2 AND evolution = 0")
        db.commit()
        db.close()

    ours = "is not the body log checkpoint 9 was saved with (40 evaluations up to step 9; "
    def metrics(damage):  # metrics.csv damaged, the log whole
        def damaged(f):
            damage(f.with_name("metrics.csv"))
        damaged.__name__ = f"metrics_{damage.__name__}"
        return damaged

    def empty(f):
        f.write_text("")

    refused(edit, ours + "it holds as many, with other values)")
    refused(Path.unlink, ours + "it holds 0)")
    refused(truncate, "bodies.sqlite does not read (DatabaseError: ")
    rows = "metrics.csv' does not hold the rows of steps 1 to 9 whole (it holds "
    refused(metrics(truncate), rows + "4)")  # cut in the row of step 5
    refused(metrics(empty), rows + "0)")
    refused(metrics(Path.unlink), "metrics.csv does not read (FileNotFoundError: ")

    copied = tmp_path / "copied"
    shutil.copytree(straight, copied)
    shutil.copytree(copied / "checkpoints" / "6", copied / "checkpoints" / "12")
    capsys.readouterr()
    assert cli.main(TINY + ["--steps", "9", "--out", str(copied), "--resume"]) == 0
    printed = capsys.readouterr().out
    assert ("checkpoint 12 is damaged, skipped (Damaged: it holds the state of step 6, not of "
            "step 12 (copied or renamed?))") in printed, printed
    assert "resumed at step 9" in printed and (copied / DAMAGED / "12").is_dir()
    assert (copied / "summary.json").read_text() == (straight / "summary.json").read_text()


def test_a_resume_rolls_back_a_body_log_write_cut_short(tmp_path, straight, capsys):
    """A kill -9 inside a body log's write (its pages spilled to the file, the hot journal
    beside it) leaves a log that a read-only open fails on: the resume rolls the write back,
    as SQLite does, and ends as the uninterrupted run."""
    out = tmp_path / "run"
    shutil.copytree(straight, out)
    cut = ("import os, sqlite3, sys; db = sqlite3.connect(sys.argv[1]); "
           "db.execute('PRAGMA cache_size=1'); db.executemany('INSERT INTO bodies (step, "
           "evolution, body, fitness, fitness_std, diverged) VALUES (99, ?, ?, 0, 0, 0)', "
           "[(i, 'x' * 200) for i in range(3000)]); os._exit(0)")
    subprocess.run([sys.executable, "-c", cut, str(out / "bodies.sqlite")], check=True)
    assert (out / "bodies.sqlite-journal").exists()
    capsys.readouterr()
    assert cli.main(TINY + ["--out", str(out), "--resume"]) == 0
    assert "resumed at step 9" in capsys.readouterr().out
    assert (out / "summary.json").read_text() == (straight / "summary.json").read_text()
    assert log_rows(out) == log_rows(straight)


def test_no_damaged_data_file_is_restored(tmp_path, straight, capsys):
    """Each data file of the newest checkpoint, one at a time, with bytes inverted in place,
    cut to half, then deleted: the restore a --resume makes (`restore_newest` with
    `restore_checked`) either says the checkpoint is damaged, naming the array or file and the
    check, moves it aside and goes on to the one before, or restores the state the run saved,
    bit for bit (from which a run ends as the uninterrupted one: the two tests above). The
    digest catches what the reader does not: inverted bytes of an array read as other values."""
    cfg = RunConfig(**json.loads((straight / "config.json").read_text()))
    abstract = jax.eval_shape(build(cfg).agent.init, jax.random.PRNGKey(0))
    _, manager = checkpoint_manager(straight)
    saved = jax.device_get(restore_checked(manager, 9, abstract)[0])
    # The one before is not read here: the test above restores one after a damaged one.
    restore = lambda manager, step: restore_checked(manager, step, abstract)[0] if step == 9 else 6
    reasons = []
    for i, f in enumerate(data_files(straight / "checkpoints" / "9")):
        for damage in DAMAGES:
            out = tmp_path / f"{i}{damage.__name__}"
            shutil.copytree(straight / "checkpoints", out / "checkpoints")
            damage(out / f.relative_to(straight))
            step, state, skipped = restore_newest(out, restore)
            if step == 9:  # the damage missed what the state is read from
                for x, y in zip(jax.tree.leaves(saved), jax.tree.leaves(jax.device_get(state))):
                    np.testing.assert_array_equal(x, y)
                continue
            assert (step, state, [s for s, _ in skipped]) == (6, 6, [9]), (f, damage)
            assert (out / DAMAGED / "9").is_dir() and not (out / "checkpoints" / "9").exists()
            reasons.append(skipped[0][1])
    printed = capsys.readouterr().out
    # Which of d/'s files the state is read from varies with how Orbax grouped its writes (here
    # 3 to 6 of 12 to 15 files; the rest unreferenced, their damage harmless), so the count is
    # bounded by what every save has: the digest's item and one file of arrays, each caught
    # under every damage (a bound of 10 failed 1 run in 3).
    assert printed.count("checkpoint 9 is damaged, skipped (") == len(reasons) >= 2 * len(DAMAGES)
    assert [r for r in reasons if r.startswith("Damaged: .learner")
            and r.endswith(": its SHA-256 is not the saved one")], reasons

    # Without its digest (saved before checkpoints had one) a checkpoint is damaged too, and so
    # is a state whose networks hold a NaN under a digest that matches; a distance may be NaN.
    out = tmp_path / "no_digest"
    shutil.copytree(straight / "checkpoints", out / "checkpoints")
    shutil.rmtree(out / "checkpoints" / "9" / "digest")
    assert [why for _, why in restore_newest(out, restore)[2]] == [
        "Damaged: no digest saved (saved before checkpoints had digests?)"]
    assert np.isnan(saved.evo.distance).any()
    check(saved, digests(saved), FINITE)
    nan = jax.tree.map(lambda x: x * np.nan, saved.learner.params)
    bad = saved.replace(learner=saved.learner.replace(params=nan))
    with pytest.raises(Damaged, match=r"^\.learner\.params\[.*: non-finite values where they"):
        check(bad, digests(bad), FINITE)


def test_a_failed_restore_drops_only_the_reports_of_reads_cut_short(monkeypatch, caplog):
    """After a restore fails, the reads it cut short report "Event loop is closed" as they
    complete, or their own failure (a truncated file holds several arrays), one traceback each
    (about 270 for a run), as unraisable exceptions or in asyncio's log: those are dropped,
    every other unraisable exception still reaches the hook that was there, and every other
    log record the log."""
    reported = []
    monkeypatch.setattr(sys, "unraisablehook", lambda r: reported.append(r.exc_value))

    class Raises:
        def __init__(self, e):
            self.e = e

        def __del__(self):
            raise self.e

    _drop_cut_short_reports()
    _drop_cut_short_reports()  # once is enough: not wrapped twice
    Raises(RuntimeError("Event loop is closed"))
    Raises(Exception("Encountered error while reading array index: (slice(0, 4, 1),)."))
    Raises(RuntimeError("something else"))
    Raises(ValueError("Event loop is closed"))
    Raises(ValueError("Encountered error while reading array index"))
    assert [(type(e).__name__, str(e)) for e in reported] == [
        ("RuntimeError", "something else"), ("ValueError", "Event loop is closed"),
        ("ValueError", "Encountered error while reading array index")]
    never = "Task exception was never retrieved\nfuture: <Task finished exception=ValueError("
    with caplog.at_level(logging.ERROR, logger="asyncio"):
        for text in ("'NOT_FOUND: Error reading [tensorstore_spec=...]')>", "'other')>"):
            logging.getLogger("asyncio").error(never + text)
    assert [r.getMessage() for r in caplog.records] == [never + "'other')>"]


def log_rows(run_dir):
    db = sqlite3.connect(run_dir / "bodies.sqlite")
    try:
        return db.execute("SELECT * FROM bodies ORDER BY step, evolution").fetchall()
    finally:
        db.close()


def test_body_log_of_a_run(straight):
    """Every body evaluated, once per evaluation, with its parent. (A resumed run's log equals
    an uninterrupted run's: the two resume tests above, one of which redoes steps.)"""
    rows = log_rows(straight)
    assert len(rows) == 4 * 10  # m0 in 4 evolutions, then 4 children a step
    space = em.make_space("bad_walker")
    m0 = space.canonical(space.initial())
    at = {(r[0], r[1]): r for r in rows}
    horizon = space.default_horizon
    for (step, evolution), (_, _, body, _, std, diverged, parent, *gait) in at.items():
        assert std == 0.0 and diverged == 0  # the predefined fitness
        assert gait == [None, None]  # which runs no episode to measure a gait in
        if step == 0:
            assert body == m0 and parent is None
        else:  # mutated from the evolution's previous body, or from m0 after a restart
            previous = m0 if (step - 1) % horizon == 0 else at[(step - 1, evolution)][2]
            assert parent == previous, (step, evolution)
    with open(straight / "metrics.csv") as f:
        for r in csv.DictReader(f):
            logged = [at[(int(r["step"]), e)][3] for e in range(4)]
            assert np.mean(logged) == pytest.approx(float(r["fitness_mean"]), abs=1e-6)
    summary = json.loads((straight / "summary.json").read_text())
    best = em.best_bodies(straight / "bodies.sqlite", 3)
    assert summary["best_bodies"][:3] == best
    every = em.best_bodies(straight / "bodies.sqlite", 99)
    means = [b["mean_fitness"] for b in every]
    assert means == sorted(means, reverse=True)  # ranked by mean
    # not by the best value: one canonical body holds slot arrangements of other values
    assert max(b["best_fitness"] for b in every) == pytest.approx(summary["best_fitness"])
    assert sum(b["evaluations"] for b in every) == 40
    assert summary["controllers"] == [] and not (straight / "best.gif").exists()


def test_a_damaged_shape_in_the_body_log_is_named(tmp_path, straight):
    """A body's shape in the log that does not read, or that is another body's, is an error
    naming the body (`checkpoints.Damaged`: the run exits 2), never a traceback in the confirm
    stage or a body confirmed that the log did not evaluate."""
    from evojax_morph.records import bodylog

    space = em.make_space("bad_walker")
    path = tmp_path / "bodies.sqlite"
    shutil.copy(straight / "bodies.sqlite", path)
    names = [b["body"] for b in bodylog.best_bodies(path, 2)]
    assert list(bodylog.shapes(path, space, names)) == names
    db = sqlite3.connect(path)
    db.execute("UPDATE shapes SET morphology = (SELECT morphology FROM shapes WHERE body = ?) "
               "WHERE body = ?", names[::-1])
    db.commit()
    with pytest.raises(Damaged, match=r"the shape kept for body .* is another body's$"):
        bodylog.shapes(path, space, names)
    db.execute("UPDATE shapes SET morphology = 'garbage' WHERE body = ?", names[:1])
    db.commit()
    db.close()
    with pytest.raises(Damaged, match=r"the shape of body .* does not read \(JSONDecodeError"):
        bodylog.shapes(path, space, names)


def _by_thread(records, done: str) -> collections.Counter:
    """(on the warmup thread, program name) -> how many of `records` begin with `done`."""
    return collections.Counter(
        (r.threadName.startswith(compile_ahead.THREAD), r.getMessage()[len(done):].split(" in ")[0])
        for r in records if r.getMessage().startswith(done)
    )


LOWERED = "Finished jaxpr to MLIR module conversion "
COMPILED = "Finished XLA compilation of "  # compiled, or loaded from the persistent cache


@pytest.mark.parametrize("confirm", [2, 0])
def test_a_run_compiles_its_later_programs_ahead(tmp_path, caplog, capsys, confirm):
    """The chunks (of 3 steps and of the last 1), the greedy walk and the confirm stage's
    fitness call (which evaluates the greedy bodies too), or with --confirm 0 the greedy
    bodies' own call, are lowered and compiled on the warmup thread, while m0 is evaluated:
    the main thread lowers and compiles none of them. (A table fitness: it has draws to
    confirm, and compiles fast.) The run leaves the files and prints the lines it did before
    its stages handed values in memory (tests/data/run_shape.json: `run_shape` of this run at
    8cf9bc6, the numbers, bodies and mutations left out; config.json's task_params since)."""
    args = ["--space", "bad_walker", "--fitness", "table", "--num-envs", "4", "--steps", "4",
            "--chunk", "3", "--explore-steps", "4", "--learning-starts", "8", "--confirm",
            str(confirm), "--confirm-controllers", "2", "--out", str(tmp_path / "run")]
    jax.config.update("jax_log_compiles", True)  # in every thread (`jax.log_compiles` in this)
    try:
        with caplog.at_level(logging.WARNING, logger="jax"):
            assert cli.main(args) == 0
    finally:
        jax.config.update("jax_log_compiles", False)
    # walk: the greedy walk's program; greedy_fitness: its bodies' call apart from confirm's
    later = ["jit(chunk)", "jit(walk)", "jit(evaluate)", "jit(greedy_fitness)"]
    ahead = [2, 1, 1, 0] if confirm else [2, 1, 0, 1]
    for done in (LOWERED, COMPILED):
        by_thread = _by_thread(caplog.records, done)
        assert [by_thread[True, name] for name in later] == ahead, done
        assert [by_thread[False, name] for name in later] == [0, 0, 0, 0], done
        assert by_thread[False, "jit(init)"] == 1, done  # m0's, on the main thread
    stored = json.loads((Path(__file__).parent / "data" / "run_shape.json").read_text())
    assert run_shape(tmp_path / "run", capsys.readouterr().out) == \
        stored[f"table, --confirm {confirm}"]


@pytest.mark.slow  # a PPO run, its confirm stage and best.gif: about 2 minutes on 2 cores
def test_a_ppo_run_leaves_the_files_and_lines_it_did(tmp_path, capsys):
    """A run of the PPO fitness (2 steps, a confirm stage, best.gif) leaves the files and
    prints the lines it did before its stages handed values in memory
    (tests/data/run_shape.json: `run_shape` of this run at 8cf9bc6; config.json's task_params
    since)."""
    out = tmp_path / "run"
    assert cli.main(["--space", "bad_walker", "--fitness", "ppo", "--num-envs", "2", "--steps",
                     "2", "--chunk", "1", "--train-steps", "256", "--explore-steps", "2",
                     "--learning-starts", "2", "--confirm", "2", "--confirm-controllers", "2",
                     "--seed", "1", "--out", str(out)]) == 0
    stored = json.loads((Path(__file__).parent / "data" / "run_shape.json").read_text())
    assert run_shape(out, capsys.readouterr().out) == stored["ppo, --confirm 2"]


def test_with_warp_on_a_gpu_the_warmup_thread_only_lowers(caplog):
    """`compiles` False (what a run sets with MuJoCo Warp on a GPU): the thread lowers, `wait`
    compiles on the calling thread, and the call finds the program compiled."""

    def warmup_probe(x):  # a program of its own name, compiled nowhere else
        return jnp.sin(x) * 3.0 + 1.0

    f, x = jax.jit(warmup_probe), jnp.arange(7.0)
    ahead = compile_ahead.Warmup(on=True, compiles=False)
    jax.config.update("jax_log_compiles", True)
    try:
        with caplog.at_level(logging.WARNING, logger="jax"):
            ahead.compile("probe", lambda: f.lower(x))
            ahead.wait("probe")
            np.testing.assert_allclose(f(x), np.sin(np.arange(7.0)) * 3 + 1, rtol=1e-6)
    finally:
        jax.config.update("jax_log_compiles", False)
        ahead.close()
    name = "jit(warmup_probe)"
    assert _by_thread(caplog.records, LOWERED) == {(True, name): 1}
    assert _by_thread(caplog.records, COMPILED) == {(False, name): 1}


@pytest.mark.parametrize("backend, devices, physics, on, compiles", [
    ("cpu", 1, "warp", True, True), ("gpu", 1, "jax", True, True),
    ("gpu", 1, "warp", True, False), ("gpu", 2, "warp", False, False)])
def test_a_runs_warmup_takes_its_engine_and_devices(monkeypatch, backend, devices, physics,
                                                     on, compiles):
    """`Warmup.for_engine`: the thread compiles, but only lowers for an engine that captures
    CUDA graphs (MuJoCo Warp) on a GPU, and is off there on several GPUs (a fake GPU here:
    the backend and device count it reads); leaving it closes it."""
    monkeypatch.setenv("EVOJAX_MORPH_WARMUP", "1")
    monkeypatch.setattr(jax, "default_backend", lambda: backend)
    monkeypatch.setattr(jax, "device_count", lambda: devices)
    waited = {}
    with compile_ahead.Warmup.for_engine(engines.registered(physics), waited) as ahead:
        assert (ahead.on, ahead.compiles, ahead.waited is waited) == (on, compiles, True)
    assert not ahead.on


def test_a_warmup_closed_on_an_error_lowers_nothing_more():
    """`close(wait=False)` (a run that failed) drops the jobs: the one already waiting for
    `start` on the thread returns without lowering, the others are cancelled."""
    called = []
    ahead = compile_ahead.Warmup(on=True)
    for name in "ab":
        ahead.compile(name, lambda name=name: called.append(name))
    jobs = list(ahead._jobs.values())
    ahead.close(wait=False)
    # Polled: `concurrent.futures.wait` counts a future cancelled before it ran as done only
    # once an executor notifies it, so it waited out its whole timeout here (10 s a run).
    deadline = time.monotonic() + 10
    while not all(job.done() for job in jobs) and time.monotonic() < deadline:
        time.sleep(0.01)
    assert all(job.done() for job in jobs) and called == []


@pytest.mark.parametrize("compiles", [True, False])
def test_a_failed_warmup_job_only_warns(compiles):
    """A program that fails to lower or compile ahead warns at `wait` (its call then does the
    work), whether the thread compiles it or `wait` does; `close` leaves the GIL's switch
    interval as it was."""

    class Unlowerable:
        def compile(self):
            raise RuntimeError("no program")

    before = sys.getswitchinterval()
    ahead = compile_ahead.Warmup(on=True, compiles=compiles)
    assert sys.getswitchinterval() == pytest.approx(compile_ahead.SWITCH_INTERVAL)
    ahead.compile("lower", lambda: 1 / 0)
    ahead.compile("compile", lambda: [Unlowerable()])
    for name, why in (("lower", "ZeroDivisionError"), ("compile", "RuntimeError: no program")):
        with pytest.warns(RuntimeWarning, match=f"warmup: {name} failed ahead \\({why}"):
            ahead.wait(name)
    ahead.close()
    assert sys.getswitchinterval() == before


def test_a_log_without_its_bodies_shapes_cannot_be_confirmed(tmp_path, capsys):
    """A finished run resumed to confirm again (confirmed.json gone) whose log lost the shapes
    of its best bodies stops with one line naming them (exit 2), not an IndexError in the
    confirm stage or a confirmation of fewer bodies than asked."""
    out = tmp_path / "run"
    tiny = ["--space", "bad_walker", "--fitness", "table", "--num-envs", "2", "--steps", "2",
            "--chunk", "2", "--confirm", "2", "--no-gif", "--agent", "random", "--out", str(out)]
    assert cli.main(tiny) == 0
    (out / "confirmed.json").unlink()
    db = sqlite3.connect(out / "bodies.sqlite")
    db.execute("DELETE FROM shapes")
    db.commit()
    db.close()
    with pytest.raises(SystemExit) as e:
        cli.main(tiny + ["--resume"])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1, err
    assert "no shape kept for the body log's" in err[0] and "cannot confirm it" in err[0]
