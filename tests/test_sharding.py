"""Several devices: the same fitness as one device (a run that moves between device counts:
test_sharding_run.py, a file of its own so that the two 4-device subprocesses, the suite's
longest steps, run on both pytest-xdist workers at once).

JAX fixes the device count at start-up, so the 4-device side runs in a subprocess with
XLA_FLAGS=--xla_force_host_platform_device_count=4; this process has one CPU device.
"""

import json

import numpy as np
import pytest
from conftest import on_four_devices

FITNESS_ON_FOUR = r"""
import json
import jax
import numpy as np
import evojax_morph as em
from evojax_morph.sharding import batch_mesh

assert jax.device_count() == 4
# float64 so that only rounding (reduction order differs between the programs) separates them
jax.config.update("jax_enable_x64", True)
space = em.make_space("bad_walker")
cfg = em.FitnessConfig(ppo=em.PPOConfig(train_steps=320, worlds_per_controller=8, num_minibatches=2,
                                        update_epochs=2, eval_episodes=1))
keys = jax.random.split(jax.random.PRNGKey(0), 6)  # 6 bodies on 4 devices: padded to 8
morphs = jax.vmap(space.random_morphology, (0, None))(keys, 3)
four = em.evaluate(space, morphs, keys, cfg)
one = em.evaluate(space, morphs, keys, cfg, mesh=batch_mesh(jax.devices()[:1]))
devices = {d.id for d in four.params.policy["params"]["hidden_0"]["kernel"].sharding.device_set}
# the two ways to split: each device sees the whole padded batch (XLA partitions the program)
# or its own quarter (shard_map, for Warp's foreign call)
from evojax_morph.sharding import shard_batch
seen = lambda x: jax.numpy.full_like(x, x.shape[0])
split = {m: np.asarray(jax.jit(shard_batch(seen, manual=m))(jax.numpy.arange(6.0))).tolist()
         for m in (False, True)}
print("RESULT", json.dumps({"four": np.asarray(four.fitness).tolist(),
                            "one": np.asarray(one.fitness).tolist(), "devices": len(devices),
                            "split": split}))
"""


@pytest.mark.slow  # a new Python compiling two float64 PPO programs: minutes on 2 cores
def test_four_devices_give_one_devices_fitness():
    got = json.loads(on_four_devices(FITNESS_ON_FOUR).stdout.split("RESULT ")[1])
    assert got["devices"] == 4  # the trained controllers really were spread over the devices
    assert got["split"] == {"false": [8.0] * 6, "true": [2.0] * 6}  # 6 padded to 8
    np.testing.assert_allclose(got["four"], got["one"], rtol=1e-5, atol=1e-5)
    assert np.ptp(got["one"]) > 1.0  # different bodies, different fitness: a mix-up would show


BROADCAST = r"""
import sys
import jax
jax.config.update("jax_cpu_collectives_implementation", "gloo")
jax.distributed.initialize(coordinator_address=sys.argv[1], num_processes=2,
                           process_id=int(sys.argv[2]))
from evojax_morph.sharding import broadcast_json
lead = {"candidates": [[{"body": "0@0[1]()", "mean": 1.5}, '{"kind": [1]}']], "log": None}
print("RESULT", json.dumps(broadcast_json(lead if jax.process_index() == 0 else None)))
"""


@pytest.mark.slow  # two new Pythons starting JAX's distributed runtime: 10 to 40 s on 2 cores
def test_two_processes_get_the_leads_value():
    """`broadcast_json` (the body log's best, handed by the lead process to the confirm stage of
    every process) between two processes of one run, each of one CPU device."""
    import os
    import socket
    import subprocess
    import sys

    with socket.socket() as s:  # a free port for the coordinator
        s.bind(("127.0.0.1", 0))
        address = f"127.0.0.1:{s.getsockname()[1]}"
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    script = "import json\n" + BROADCAST
    procs = [subprocess.Popen([sys.executable, "-c", script, address, str(i)], env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for i in range(2)]
    outs = [p.communicate(timeout=120) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], [err[-2000:] for _, err in outs]
    got = [json.loads(out.split("RESULT ")[1]) for out, _ in outs]
    lead = {"candidates": [[{"body": "0@0[1]()", "mean": 1.5}, '{"kind": [1]}']], "log": None}
    assert got == [lead, lead]
