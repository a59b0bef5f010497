"""The run command: bad input, resume, and a smoke run through a subprocess."""

import json
import os
import subprocess
import sys

import jax
import numpy as np
import pytest

from evojax_morph import run

TINY = ["--space", "bad_walker", "--fitness", "predefined", "--num-envs", "4", "--chunk", "3", "--explore-steps", "4",
        "--learning-starts", "8"]


@pytest.mark.parametrize(
    "args, message",
    [
        (["--space", "nope"], "unknown space 'nope'"),
        (["--space", "bad_walker", "--steps", "-3"], "--steps must be positive"),
        (["--space", "bad_walker", "--fitness", "magic"], "invalid choice"),
    ],
)
def test_bad_input_exits_with_2(args, message, capsys, tmp_path):
    with pytest.raises(SystemExit) as e:
        run.main(args + ["--out", str(tmp_path / "run")])
    assert e.value.code == 2
    assert message in capsys.readouterr().err


def test_unwritable_out_and_missing_resume(capsys, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(SystemExit) as e:
        run.main(TINY + ["--out", str(blocker / "run")])
    assert e.value.code == 2 and "cannot write to --out" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        run.main(TINY + ["--out", str(tmp_path / "empty"), "--resume"])
    assert e.value.code == 2 and "no run in" in capsys.readouterr().err


def test_resume_matches_an_uninterrupted_run(tmp_path):
    straight, split = tmp_path / "straight", tmp_path / "split"
    assert run.main(TINY + ["--steps", "9", "--seed", "3", "--out", str(straight)]) == 0
    assert run.main(TINY + ["--steps", "3", "--seed", "3", "--out", str(split)]) == 0  # "interrupted"
    with pytest.raises(SystemExit):  # a second start in the same directory must say --resume
        run.main(TINY + ["--steps", "9", "--seed", "3", "--out", str(split)])
    assert run.main(TINY + ["--steps", "9", "--out", str(split), "--resume"]) == 0
    a, b = (json.loads((d / "summary.json").read_text()) for d in (straight, split))
    assert a == b
    assert (straight / "metrics.csv").read_text() == (split / "metrics.csv").read_text()
    import orbax.checkpoint as ocp

    args = ocp.args.Composite(state=ocp.args.StandardRestore())
    restore = lambda d: ocp.CheckpointManager(d.resolve() / "checkpoints").restore(9, args=args)["state"]
    for x, y in zip(jax.tree.leaves(restore(straight)), jax.tree.leaves(restore(split))):
        np.testing.assert_array_equal(x, y)


def test_cli_smoke_with_ppo_fitness(tmp_path):
    out = tmp_path / "smoke"
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    env.setdefault("JAX_COMPILATION_CACHE_DIR", os.path.expanduser("~/.cache/evojax_morph/jax"))
    cmd = [sys.executable, "-m", "evojax_morph.run", "--space", "bad_walker", "--steps", "2", "--num-envs", "2",
           "--train-steps", "320", "--chunk", "1", "--out", str(out)]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "greedy trajectory from m0" in proc.stdout
    for name in ("config.json", "metrics.csv", "curve.png", "trajectory.png", "best.xml", "summary.json"):
        assert (out / name).stat().st_size > 0, name
    summary = json.loads((out / "summary.json").read_text())
    assert len(summary["greedy_trajectory"]) == 5 and np.isfinite(summary["best_fitness"])
    import mujoco

    mujoco.MjModel.from_xml_string((out / "best.xml").read_text())  # the export loads
    assert list((out / "tb").iterdir())  # TensorBoard events
