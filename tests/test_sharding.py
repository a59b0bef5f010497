"""Several devices: the same fitness as one device, and checkpoints that move between counts.

JAX fixes the device count at start-up, so the 4-device side runs in a subprocess with
XLA_FLAGS=--xla_force_host_platform_device_count=4; this process has one CPU device.
"""

import json
import os
import sqlite3
import subprocess
import sys

import numpy as np

from evojax_morph import run

FOUR_DEVICES = r"""
import json, sys
import jax
import numpy as np
import evojax_morph as em
from evojax_morph import run
from evojax_morph.sharding import batch_mesh

assert jax.device_count() == 4
# float64 so that only rounding (reduction order differs between the programs) separates them
jax.config.update("jax_enable_x64", True)
space = em.make_space("bad_walker")
cfg = em.FitnessConfig(ppo=em.PPOConfig(train_steps=320, num_envs=8, num_minibatches=2,
                                        update_epochs=2, eval_episodes=1))
keys = jax.random.split(jax.random.PRNGKey(0), 6)  # 6 bodies on 4 devices: padded to 8
morphs = jax.vmap(space.random_morphology, (0, None))(keys, 3)
four = em.evaluate(space, morphs, keys, cfg)
one = em.evaluate(space, morphs, keys, cfg, mesh=batch_mesh(jax.devices()[:1]))
devices = {d.id for d in four.params.policy["params"]["hidden_0"]["kernel"].sharding.device_set}
jax.config.update("jax_enable_x64", False)

# a run saved on 4 devices, resumed by the caller on 1
assert run.main(sys.argv[1:]) == 0
print("RESULT", json.dumps({"four": np.asarray(four.fitness).tolist(),
                            "one": np.asarray(one.fitness).tolist(), "devices": len(devices)}))
"""


def test_four_devices_give_one_devices_fitness_and_checkpoints_move(tmp_path):
    out = tmp_path / "run"
    env = dict(
        os.environ, JAX_PLATFORMS="cpu", XLA_FLAGS="--xla_force_host_platform_device_count=4"
    )
    env.setdefault("JAX_COMPILATION_CACHE_DIR", os.path.expanduser("~/.cache/evojax_morph/jax"))
    cli = [
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
        "--out",
        str(out),
    ]
    proc = subprocess.run(
        [sys.executable, "-c", FOUR_DEVICES, *cli],
        capture_output=True,
        text=True,
        env=env,
        timeout=900,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "on 4 cpu device(s)" in proc.stdout
    got = json.loads(proc.stdout.split("RESULT ")[1])
    assert got["devices"] == 4  # the trained controllers really were spread over the devices
    np.testing.assert_allclose(got["four"], got["one"], rtol=1e-5, atol=1e-5)
    assert np.ptp(got["one"]) > 1.0  # different bodies, different fitness: a mix-up would show

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
    assert run.main(["--out", str(out), "--resume", "--steps", "3", "--no-gif"]) == 0
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
