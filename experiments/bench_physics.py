"""Physics steps/s of the padded template under vmap, against the unpadded model of one body.

For each space, at B morphologies x E envs (B*E worlds), this times:
  unpadded   the exported MJCF of one morphology m, put on the device, shared by all B*E worlds;
  padded     the template specialised to that same m, shared by all B*E worlds;
  batched    the template specialised to B different random morphologies, E worlds each.
`padded / unpadded` is the cost of padding itself; `batched` is how the fitness step uses it.
Each figure steps every world `--steps` times inside one jitted `lax.scan`, after a warm-up
call that compiles it, and takes the median of `--repeats` timed calls.

  python -m experiments.bench_physics                       # CPU-sized defaults
  python -m experiments.bench_physics --batch 1024 --envs 64  # the GPU target
  python -m experiments.bench_physics --spaces constructor constructor:leg_depth=1,leg_edges=0
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

import evojax_morph as em
from evojax_morph.physics import mjx


def make_rollout(steps: int, batched_models: bool):
    """jit(fn(models, data) -> data): `steps` physics steps of every world, sinusoidal controls."""

    def step_world(model, data, t):
        phase = jnp.arange(data.ctrl.shape[-1]) + data.qpos[0]  # differs per world after a step
        return mjx.step(model, data.replace(ctrl=jnp.sin(8.0 * t * model.opt.timestep + phase)))

    per_env = jax.vmap(step_world, (None, 0, None))  # E worlds of one model
    per_model = jax.vmap(per_env, (0 if batched_models else None, 0, None))

    @jax.jit
    def rollout(models, data):
        def body(data, t):
            return per_model(models, data, t), None

        return jax.lax.scan(body, data, jnp.arange(steps))[0]

    return rollout


def time_rollout(rollout, models, data, repeats: int) -> float:
    jax.block_until_ready(rollout(models, data))  # compile and warm up
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(rollout(models, data))
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def broadcast_data(model, batch: int, envs: int):
    data = mjx.make_data(model)
    return jax.tree.map(lambda x: jnp.broadcast_to(x, (batch, envs) + x.shape), data)


def make_space(spec: str):
    """A space from `name` or `name:key=value,...` (integer options): `constructor:knees=1`."""
    name, _, options = spec.partition(":")
    kwargs = dict(kv.split("=") for kv in options.split(",")) if options else {}
    return em.make_space(name, **{k: int(v) for k, v in kwargs.items()})


def bench_space(spec: str, batch: int, envs: int, steps: int, repeats: int, seed: int) -> dict:
    space = make_space(spec)
    name = space.name
    keys = jax.random.split(jax.random.PRNGKey(seed), batch)
    walk = space.default_horizon
    morphs = jax.jit(jax.vmap(space.random_morphology, (0, None)), static_argnums=1)(keys, walk)
    m = space.optimum() if name == "bad_walker" else jax.tree.map(lambda x: x[0], morphs)
    worlds = batch * envs
    shared = make_rollout(steps, batched_models=False)

    unpadded = mjx.put_model(mujoco.MjModel.from_xml_string(space.to_mjcf(m)))
    t_unpadded = time_rollout(shared, unpadded, broadcast_data(unpadded, batch, envs), repeats)

    padded = jax.jit(space.mjx_model)(m)
    t_padded = time_rollout(shared, padded, broadcast_data(padded, batch, envs), repeats)

    models = jax.jit(jax.vmap(space.mjx_model))(morphs)
    data = jax.vmap(lambda model: broadcast_data(model, 1, envs)[0])(models)
    t_batched = time_rollout(make_rollout(steps, batched_models=True), models, data, repeats)

    tmpl = space.template
    rate = lambda t: worlds * steps / t
    return {
        "space": spec,
        "template": f"nbody {tmpl.nbody}, nv {tmpl.nv}, ngeom {tmpl.ngeom}",
        "device": jax.devices()[0].device_kind,
        "batch": batch,
        "envs": envs,
        "steps": steps,
        "body": space.format(m).replace("\n", " | "),
        "unpadded_sps": rate(t_unpadded),
        "padded_sps": rate(t_padded),
        "batched_sps": rate(t_batched),
        "padding_cost": 1 - t_unpadded / t_padded,
    }


def main():
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--spaces",
        nargs="+",
        default=em.list_spaces(),
        help="names, or name:key=value,... with integer options (constructor:knees=1,leg_edges=1)",
    )
    parser.add_argument("--batch", type=int, default=8, help="B, morphologies")
    parser.add_argument("--envs", type=int, default=8, help="E, worlds per morphology")
    parser.add_argument("--steps", type=int, default=100, help="physics steps per timed call")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    jax.config.update("jax_default_matmul_precision", "highest")

    rows = [
        bench_space(s, args.batch, args.envs, args.steps, args.repeats, args.seed)
        for s in args.spaces
    ]
    for row in rows:
        print(json.dumps(row))
    print(
        f"\n{'space':<34} {'B x E':>12} {'unpadded/s':>12} {'padded/s':>12} {'batched/s':>12} "
        f"{'padding':>8}"
    )
    for r in rows:
        print(
            f"{r['space']:<34} {r['batch']:>5} x {r['envs']:<4} {r['unpadded_sps']:>12.4g} "
            f"{r['padded_sps']:>12.4g} {r['batched_sps']:>12.4g} {r['padding_cost']:>7.0%}"
        )


if __name__ == "__main__":
    main()
