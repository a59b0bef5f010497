"""The run command: bad input and resume (its PPO smoke run is in test_sharding, on 4 devices)."""

import json

import jax
import numpy as np
import pytest

from evojax_morph import run

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
    assert (
        run.main(TINY + ["--steps", "3", "--seed", "3", "--out", str(split)]) == 0
    )  # "interrupted"
    with pytest.raises(SystemExit):  # a second start in the same directory must say --resume
        run.main(TINY + ["--steps", "9", "--seed", "3", "--out", str(split)])
    assert run.main(TINY + ["--steps", "9", "--out", str(split), "--resume"]) == 0
    a, b = (json.loads((d / "summary.json").read_text()) for d in (straight, split))
    assert a == b
    assert (straight / "metrics.csv").read_text() == (split / "metrics.csv").read_text()
    import orbax.checkpoint as ocp

    args = ocp.args.Composite(state=ocp.args.StandardRestore())
    restore = lambda d: ocp.CheckpointManager(d.resolve() / "checkpoints").restore(9, args=args)[
        "state"
    ]
    for x, y in zip(jax.tree.leaves(restore(straight)), jax.tree.leaves(restore(split))):
        np.testing.assert_array_equal(x, y)
