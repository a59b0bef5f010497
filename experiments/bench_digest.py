"""What a checkpoint's digest costs (issue 62): the SHA-256 of every array of the agent state at
a save (`checkpoints.save_args`) and its check at a restore (`checkpoints.restore_checked`),
beside Orbax's save of the same state, for the CPU default run (Bad Walker, PPO fitness, 4
evolutions, 1 controller) and a GPU run's state (256 evolutions x 8 controllers, Warp's
default; built here on the CPU). The state has the run's shapes and dtypes, its floats drawn
at random (as incompressible as trained weights: Orbax compresses), its integers zero; hashing
and the finiteness check take the same time whatever the values. One JSON line per config.

    python -m experiments.bench_digest --repeats 5
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp

from evojax_morph import checkpoints
from evojax_morph.pipeline import RunConfig, build
from evojax_morph.run import gpu_controllers, gpu_defaults
from evojax_morph.sharding import to_host

CONFIGS = {
    "cpu_default": RunConfig(),
    "gpu_256": RunConfig(**gpu_defaults(), controllers=gpu_controllers("warp")),
}


def seconds(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def measure(name: str, cfg: RunConfig, repeats: int) -> dict:
    abstract = jax.eval_shape(build(cfg).agent.init, jax.random.PRNGKey(0))
    rng = np.random.default_rng(0)
    fill = lambda s: jnp.asarray(  # noqa: E731
        rng.standard_normal(s.shape).astype(s.dtype) if jnp.issubdtype(s.dtype, jnp.floating)
        else np.zeros(s.shape, s.dtype))
    state = jax.tree.map(fill, abstract)
    leaves = jax.tree.leaves(state)
    digest = checkpoints.digests(to_host(state))
    row = {"config": name, "num_envs": cfg.num_envs, "controllers": cfg.controllers,
           "arrays": len(leaves), "mbytes": round(sum(x.nbytes for x in leaves) / 1e6, 2),
           "digest_at_save_s": seconds(lambda: checkpoints.digests(to_host(state)), repeats),
           "check_at_restore_s": seconds(lambda: checkpoints.check(
               to_host(state), digest, checkpoints.FINITE), repeats)}
    with tempfile.TemporaryDirectory() as tmp:
        options = ocp.CheckpointManagerOptions(max_to_keep=1, create=True)
        manager = ocp.CheckpointManager(Path(tmp).resolve(), options=options)
        step = iter(range(10**6))

        def save(args_fn):
            manager.save(next(step), args=args_fn(state))
            manager.wait_until_finished()

        plain = lambda s: ocp.args.Composite(state=ocp.args.StandardSave(s))  # noqa: E731
        save(plain)  # the first save sets Orbax up
        row["orbax_save_s"] = seconds(lambda: save(plain), repeats)
        row["orbax_save_with_digest_s"] = seconds(lambda: save(checkpoints.save_args), repeats)
        manager.close()
    return {k: round(v, 4) if isinstance(v, float) else v for k, v in row.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    device = f"{jax.devices()[0].device_kind} ({jax.default_backend()}, jax {jax.__version__})"
    for name, cfg in CONFIGS.items():
        row = measure(name, cfg, args.repeats) | {"device": device}
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
