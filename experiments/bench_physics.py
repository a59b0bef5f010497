"""Physics steps/s of the padded template under vmap, against the unpadded model of one body.

For each space, at B morphologies x E envs (N = B*E worlds), and each physics asked for
(`--physics jax|warp|both`), this times:
  unpadded   the exported MJCF of one morphology m, put on the device, shared by all N worlds;
  padded     the template specialised to that same m, shared by all N worlds;
  nested     (JAX only) B different random morphologies, E worlds each: a vmap over bodies
             around a vmap over envs, as the fitness steps them today;
  flat       the same B bodies as one flat batch of N worlds, the fields `specialise` writes
             repeated per world (`physics.flat_models`; for Warp `warp.to_warp`, whose
             worlds all read their own copy of those fields).
`padded / unpadded` is the cost of padding itself. Each figure steps every world `--steps`
times inside one jitted `lax.scan`, after a warm-up call that compiles it, and takes the median
of `--repeats` timed calls. Warp (MuJoCo Warp behind MJX, float32) runs on a CUDA GPU or, slowly,
on the CPU; `--graph-mode` picks its CUDA graph capture (MJX's default: WARP on a GPU).

  python -m experiments.bench_physics                       # CPU-sized defaults, JAX
  python -m experiments.bench_physics --batch 2 --envs 2 --steps 10 --physics both  # CPU smoke
  python -m experiments.bench_physics --batch 1024 --envs 64 --physics both  # the GPU target
  python -m experiments.bench_physics --spaces constructor constructor:leg_depth=1,leg_edges=0
  python -m experiments.bench_physics --spaces constructor --classes   # and by size class
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

import evojax_morph as em
from evojax_morph.physics import classes, templates
from evojax_morph.physics import warp as ew
from evojax_morph.physics.determinism import full_precision
from evojax_morph.physics.templates import mjx


def controls(data, t, timestep):
    """Sinusoidal controls of one world at step t; the phase differs per world after a step."""
    phase = jnp.arange(data.ctrl.shape[-1]) + data.qpos[0]
    return jnp.sin(8.0 * t * timestep + phase)


def step_world(model, data, t):
    return mjx.step(model, data.replace(ctrl=controls(data, t, model.opt.timestep)))


def _scan(steps: int, step_all):
    """jit(fn(models, data) -> data): `steps` calls of `step_all(models, data, t)`."""

    @jax.jit
    def rollout(models, data):
        def body(data, t):
            return step_all(models, data, t), None

        return jax.lax.scan(body, data, jnp.arange(steps))[0]

    return rollout


def make_rollout(steps: int, batched_models: bool):
    """jit(fn(models, data) -> data): `steps` physics steps of every world, sinusoidal controls.

    Data has a leading (B, E) axis; models a leading (B,) axis if `batched_models`."""
    per_env = jax.vmap(step_world, (None, 0, None))  # E worlds of one model
    return _scan(steps, jax.vmap(per_env, (0 if batched_models else None, 0, None)))


def make_flat_rollout(steps: int, in_axes):
    """jit(fn(model, data) -> data) over one flat batch: data (N,), model fields per `in_axes`."""
    return _scan(steps, jax.vmap(step_world, (in_axes, 0, None)))


def make_warp_rollout(steps: int, timestep: float):
    """jit(fn(model, data) -> data): `steps` flat Warp steps of every world (`warp.step_worlds`)."""

    @jax.jit
    def rollout(model, data):
        def body(data, t):
            ctrl = jax.vmap(controls, (0, None, None))(data, t, timestep)
            return ew.step_worlds(model, data, ctrl), None

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


def bench_space(spec: str, physics_kinds: list[str], batch: int, envs: int, steps: int,
                repeats: int, seed: int, graph_mode=None, naconmax: int | None = None,
                njmax: int | None = None, ideal_bodies: int = 0) -> list[dict]:
    """One row per physics kind of `physics_kinds` ("jax", "warp") for the space `spec`."""
    space = make_space(spec)
    name = space.name
    keys = jax.random.split(jax.random.PRNGKey(seed), batch)
    walk = space.default_horizon
    morphs = jax.jit(jax.vmap(space.random_morphology, (0, None)), static_argnums=1)(keys, walk)
    m = space.optimum() if name == "bad_walker" else jax.tree.map(lambda x: x[0], morphs)
    worlds = batch * envs
    unpadded_mj = mujoco.MjModel.from_xml_string(space.to_mjcf(m))
    models = jax.jit(jax.vmap(space.mjx_model))(morphs)
    tmpl = space.template
    rate = lambda t: None if t is None else worlds * steps / t
    rows = []

    for kind in physics_kinds:
        if kind == "jax":
            shared = make_rollout(steps, batched_models=False)
            unpadded = mjx.put_model(unpadded_mj)
            t_unpadded = time_rollout(
                shared, unpadded, broadcast_data(unpadded, batch, envs), repeats
            )
            padded = jax.jit(space.mjx_model)(m)
            t_padded = time_rollout(shared, padded, broadcast_data(padded, batch, envs), repeats)
            data = jax.vmap(lambda model: broadcast_data(model, 1, envs)[0])(models)
            nested = make_rollout(steps, batched_models=True)
            t_nested = time_rollout(nested, models, data, repeats)
            flat, axes = templates.flat_models(models, envs, space.plan.specialised_fields)
            flat_data = broadcast_data(padded, 1, worlds)[0]
            t_flat = time_rollout(make_flat_rollout(steps, axes), flat, flat_data, repeats)
        else:
            rollout = make_warp_rollout(steps, float(tmpl.opt.timestep))
            unpadded = ew.put_model(unpadded_mj, graph_mode)
            unpadded_data = ew.make_worlds(space, worlds, naconmax, njmax, mj_model=unpadded_mj)
            t_unpadded = time_rollout(rollout, unpadded, unpadded_data, repeats)
            # The body m specialised, its fields shared by every world (a leading axis of 1).
            one = jax.tree.map(lambda x: x[None], jax.jit(space.mjx_model)(m))
            padded, _ = ew.to_warp(space, one, 1, graph_mode=graph_mode)
            padded_data = ew.make_worlds(space, worlds, naconmax, njmax)
            t_padded = time_rollout(rollout, padded, padded_data, repeats)
            t_nested = None  # a nested vmap is wrong under Warp (see evojax_morph.physics.warp)
            flat, flat_data = ew.to_warp(space, models, envs, naconmax, njmax, graph_mode)
            t_flat = time_rollout(rollout, flat, flat_data, repeats)
        by_class = batch_padding(space, kind, morphs, envs, steps, repeats, graph_mode, naconmax,
                                 njmax, ideal_bodies) if ideal_bodies else {}
        rows.append(
            {
                "space": spec,
                "physics": kind,
                "graph_mode": str(graph_mode) if kind == "warp" else None,
                "naconmax_per_world": naconmax if kind == "warp" else None,
                "template": f"nbody {tmpl.nbody}, nv {tmpl.nv}, ngeom {tmpl.ngeom}",
                "device": jax.devices()[0].device_kind,
                "batch": batch,
                "envs": envs,
                "steps": steps,
                "body": space.format(m).replace("\n", " | "),
                "unpadded_sps": rate(t_unpadded),
                "padded_sps": rate(t_padded),
                "nested_sps": rate(t_nested),
                "flat_sps": rate(t_flat),
                "padding_cost": 1 - t_unpadded / t_padded,
                **by_class,
            }
        )
    return rows


def batch_padding(space, kind, morphs, envs, steps, repeats, graph_mode, naconmax, njmax,
                  ideal_bodies: int):
    """The padding cost of the batch `morphs` (B bodies x `envs` worlds, flat) on the full
    template and grouped by size class (`physics.classes`: each class's places, unused ones
    m0), against the mean time of each body's own unpadded model stepping the same B x E worlds
    (over the first `ideal_bodies`, a random sample: each unpadded body compiles anew):
    `batch_padding_cost` and `classes_padding_cost`, 1 - unpadded / padded."""
    batch = morphs.active.shape[0]
    worlds = batch * envs
    bodies = em.unstack(morphs)
    if kind == "jax":
        shared = make_rollout(steps, batched_models=False)

        def unpadded(m):
            model = mjx.put_model(mujoco.MjModel.from_xml_string(space.to_mjcf(m)))
            return time_rollout(shared, model, broadcast_data(model, batch, envs), repeats)

        def padded(sp, ms):
            flat, axes = templates.flat_models(jax.vmap(sp.mjx_model)(ms), envs,
                                             sp.plan.specialised_fields)
            data = broadcast_data(sp.mjx_template(), 1, ms.active.shape[0] * envs)[0]
            return time_rollout(make_flat_rollout(steps, axes), flat, data, repeats)
    else:
        rollout = make_warp_rollout(steps, float(space.template.opt.timestep))

        def unpadded(m):
            mj = mujoco.MjModel.from_xml_string(space.to_mjcf(m))
            data = ew.make_worlds(space, worlds, naconmax, njmax, mj_model=mj)
            return time_rollout(rollout, ew.put_model(mj, graph_mode), data, repeats)

        def padded(sp, ms):
            model, data = ew.to_warp(sp, jax.vmap(sp.mjx_model)(ms), envs, naconmax, njmax,
                                     graph_mode)
            return time_rollout(rollout, model, data, repeats)

    ideal = float(np.mean([unpadded(m) for m in bodies[:ideal_bodies]]))
    full = padded(space, morphs)
    size_classes = [c for c, _ in space.size_classes()]
    need, places, ok = classes.places(space, morphs)
    m0 = space.initial()
    grouped = 0.0
    for here, sp in zip(places, [c.space for c in size_classes] + [space]):
        ms = em.stack([bodies[i] if i < batch else m0 for i in np.asarray(here)])
        grouped += padded(sp, ms)
        print(f"{kind}: a class of {len(ms.active)} places, {grouped:.4f} s so far (one template "
              f"{full:.4f} s, unpadded {ideal:.4f} s)", file=sys.stderr, flush=True)
    return {
        "classes": [c.name for c in size_classes] + ["full"],
        "bodies_per_class": np.bincount(np.asarray(need), minlength=len(places)).tolist(),
        "places_per_class": [int(p.shape[0]) for p in places],
        "all_placed": bool(ok),
        "unpadded_bodies": min(batch, ideal_bodies),
        "batch_padding_cost": 1 - ideal / full,
        "classes_padding_cost": 1 - ideal / grouped if ok else None,
        "classes_speedup": full / grouped if ok else None,
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
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
    parser.add_argument("--physics", choices=("jax", "warp", "both"), default="jax")
    parser.add_argument(
        "--graph-mode",
        choices=("NONE", "JAX", "WARP", "WARP_STAGED", "WARP_STAGED_EX"),
        default=None,
        help="Warp's CUDA graph mode (warp.JaxCallableGraphMode); default MJX's (WARP on a GPU)",
    )
    parser.add_argument(
        "--naconmax", type=int, default=None, help="Warp contacts per world (default: buffers)"
    )
    parser.add_argument("--njmax", type=int, default=None,
                        help="Warp constraint rows per world (default warp.buffers(space))")
    parser.add_argument(
        "--classes", action="store_true",
        help="also the padding cost of the batch on one template and grouped by size class",
    )
    parser.add_argument("--ideal-bodies", type=int, default=8,
                        help="--classes: the bodies whose unpadded models set the ideal time")
    args = parser.parse_args()
    full_precision()  # as the run command
    kinds = ["jax", "warp"] if args.physics == "both" else [args.physics]
    graph_mode = None
    if "warp" in kinds:
        ok, reason = ew.available()
        if not ok:
            raise SystemExit(f"--physics {args.physics}: the Warp physics cannot run: {reason}")
        import warp

        warp.config.log_level = warp.LOG_WARNING  # no line per kernel module loaded
        if args.graph_mode is not None:
            graph_mode = getattr(warp.JaxCallableGraphMode, args.graph_mode)

    rows = []
    for spec in args.spaces:
        for row in bench_space(
            spec,
            kinds,
            args.batch,
            args.envs,
            args.steps,
            args.repeats,
            args.seed,
            graph_mode,
            args.naconmax,
            args.njmax,
            args.ideal_bodies if args.classes else 0,
        ):
            print(json.dumps(row), flush=True)
            rows.append(row)
    print(
        f"\n{'space':<34} {'physics':<7} {'B x E':>12} {'unpadded/s':>12} {'padded/s':>12} "
        f"{'nested/s':>12} {'flat/s':>12} {'padding':>8}"
    )
    for r in rows:
        sps = [r[k] for k in ("unpadded_sps", "padded_sps", "nested_sps", "flat_sps")]
        sps = " ".join(f"{'-':>12}" if x is None else f"{x:>12.4g}" for x in sps)
        print(
            f"{r['space']:<34} {r['physics']:<7} {r['batch']:>5} x {r['envs']:<4} {sps} "
            f"{r['padding_cost']:>7.0%}"
        )


if __name__ == "__main__":
    main()
