"""A run on 4 devices (a subprocess, as in test_sharding.py) resumed on one: its outputs,
checkpoints, controllers and body log."""

import json
import sqlite3

import numpy as np
import pytest
from conftest import on_four_devices

from evojax_morph.run import cli

RUN_ON_FOUR = r"""
import sys
import jax
from evojax_morph.run import cli

assert jax.device_count() == 4
# the greedy walk, and its bodies' call apart from the confirm stage's, compile for one device
# (the rollout split, one body a call, hung on 2 GPUs)
from evojax_morph.search.pipeline import RunConfig, build, make_greedy_evaluation, make_greedy_walk
from evojax_morph.sharding import batch_mesh, replicated
p = build(RunConfig(space="bad_walker", fitness="predefined", num_envs=4, horizon=2))
everywhere = lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=replicated(batch_mesh()))
state = jax.tree.map(everywhere, jax.eval_shape(p.agent.init, jax.random.PRNGKey(0)))  # as run's
key = jax.random.PRNGKey(1)
for lowered in (make_greedy_walk(p).lower(state.learner, state.first, key),
                make_greedy_evaluation(p).lower(key)):
    placed = jax.tree.leaves(lowered.compile().input_shardings)
    assert {d for s in placed for d in s.device_set} == {jax.local_devices()[0]}, placed
assert cli.main(sys.argv[1:]) == 0  # a run saved on 4 devices, resumed by the caller on 1
"""


# A new Python compiling a whole PPO run on 4 devices, then its resume on one: minutes on 2 cores.
@pytest.mark.slow
def test_a_run_on_four_devices_resumes_on_one(tmp_path):
    out = tmp_path / "run"
    argv = [
        "--space",
        "bad_walker",
        "--steps",
        "2",
        "--num-envs",
        "6",
        "--train-steps",
        "320",
        "--controllers",  # two controllers per body, inherited through the run and the resume
        "2",
        "--chunk",
        "1",
        "--horizon",  # a greedy rollout of 2 evaluations, not Bad Walker's 5
        "2",
        "--no-gif",  # tests/test_render.py draws a run's best.gif; here it would cost a minute
        "--confirm",  # and tests its confirm stage on the PPO fitness: here it would compile
        "0",  # twice more (4 devices, then 1)
        "--out",
        str(out),
    ]
    assert "on 4 cpu device(s)" in on_four_devices(RUN_ON_FOUR, *argv).stdout

    # The 4-device run's outputs, then its checkpoint resumed here, on one device.
    for name in (
        "config.json",
        "metrics.csv",
        "curve.png",
        "trajectory.png",
        "best.xml",
        "summary.json",
    ):
        assert (out / name).stat().st_size > 0, name
    assert list((out / "tb").iterdir())  # TensorBoard events
    import mujoco

    mujoco.MjModel.from_xml_string((out / "best.xml").read_text())  # the export loads
    assert not (out / "best.gif").exists()  # --no-gif
    before = (out / "metrics.csv").read_text().splitlines()
    assert cli.main(["--out", str(out), "--resume", "--steps", "3", "--no-gif"]) == 0
    after = (out / "metrics.csv").read_text().splitlines()
    assert after[:3] == before and len(after) == 4  # steps 1-2 kept, step 3 added
    summary = json.loads((out / "summary.json").read_text())
    assert summary["env_steps"] == 3 and np.isfinite(summary["best_fitness"])
    assert len(summary["greedy_trajectory"]) == 3  # m0 and 2 mutations (--horizon 2)
    # the trained controllers of the best body and the greedy trajectory's
    saved = sorted(d.name for d in (out / "controllers").iterdir())
    assert saved == ["best"] + [f"step{t}" for t in range(3)] == summary["controllers"]
    db = sqlite3.connect(out / "bodies.sqlite")
    assert db.execute("SELECT COUNT(*), MAX(step) FROM bodies").fetchone() == (6 * 4, 3)
    db.close()
