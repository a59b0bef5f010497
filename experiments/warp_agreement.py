"""Short trajectories of MuJoCo Warp against MJX's JAX impl, with float64 as the scale of chaos.

For each space, B bodies (m* and B - 1 random ones where the space defines m*, the Bad and
Length Walkers; else B random ones) start at the template's qpos0 at rest, E envs each, and
take the same random controls (uniform in [-1, 1], one draw per physics step and world) under
three physics:
  jax32   the JAX impl in float32, today's nested vmap over bodies and envs;
  warp    MuJoCo Warp behind MJX (float32), one flat batch (`evojax_morph.warp`);
  jax64   the JAX impl in float64.
It prints, per space and body, max |qpos difference| over the body's envs at each checkpoint
step, for warp vs jax32 and for jax32 vs jax64: the second is what float32 rounding alone,
grown by the dynamics, amounts to, the yardstick for the first.

Measured on the CPU (B = 5, E = 2, 2026-11-23): to step 10 Warp is within 5.1e-7 of jax32
for 14 of 15 bodies, as float32 rounding is (jax32 vs jax64: up to 2.8e-7); by step 50 6 bodies
part by 2e-3 to 0.24 while jax32 and jax64 stay within 1.3e-6. The parting traced (Length
Walker m*) starts on one contact step where the 4-iteration Newton solver stops unconverged
(Warp's solver_niter = 4): MuJoCo Warp's line search differs from MJX's and C's, so the
unconverged answers differ (C, run on the export, agrees with jax32). With `--iterations 100`
every body stays within 9e-6 of jax32 over the 50 steps (jax32 vs jax64: up to 9e-6).

  python -m experiments.warp_agreement                         # B = 5, E = 4, steps 1 10 50
  python -m experiments.warp_agreement --envs 1 --spaces bad_walker   # CPU smoke
"""

from __future__ import annotations

import argparse
import json

import jax
import jax.numpy as jnp
import numpy as np

import evojax_morph as em
from evojax_morph import warp as ew
from evojax_morph.physics import mjx


def bodies(space, batch: int, seed: int):
    """B morphologies: m* first where the space has one, then random walks (default horizon)."""
    keys = jax.random.split(jax.random.PRNGKey(seed), batch)
    morphs = jax.vmap(space.random_morphology, (0, None))(keys, space.default_horizon)
    if hasattr(space, "optimum"):
        best = space.optimum()
        morphs = jax.tree.map(lambda b, x: x.at[0].set(b), best, morphs)
    return morphs


def jax_qpos(space, morphs, ctrl: np.ndarray, checkpoints) -> np.ndarray:
    """(C, B, E, nq) qpos at the checkpoint steps, JAX impl in the current default float."""
    models = jax.jit(jax.vmap(space.mjx_model))(morphs)
    batch, envs = ctrl.shape[1:3]
    make = lambda _: mjx.make_data(space.mjx_template())
    data = jax.vmap(jax.vmap(make))(jnp.zeros((batch, envs)))
    step = jax.vmap(jax.vmap(mjx.step, (None, 0)))

    def body(data, c):
        data = step(models, data.replace(ctrl=c.astype(data.ctrl.dtype)))
        return data, data.qpos

    qpos = jax.jit(lambda d, c: jax.lax.scan(body, d, c)[1])(data, jnp.asarray(ctrl))
    return np.asarray(qpos, np.float64)[np.asarray(checkpoints) - 1]


def warp_qpos(space, morphs, ctrl: np.ndarray, checkpoints, graph_mode=None) -> np.ndarray:
    """(C, B, E, nq) qpos at the checkpoint steps, MuJoCo Warp, one flat batch."""
    models = jax.jit(jax.vmap(space.mjx_model))(morphs)
    steps, batch, envs, nu = ctrl.shape
    model, data = ew.to_warp(space, models, envs, graph_mode=graph_mode)

    def body(data, c):
        data = ew.step_worlds(model, data, c.reshape(batch * envs, nu))
        return data, data.qpos.reshape(batch, envs, -1)

    qpos = jax.jit(lambda d, c: jax.lax.scan(body, d, c)[1])(data, jnp.asarray(ctrl))
    return np.asarray(qpos, np.float64)[np.asarray(checkpoints) - 1]


def agreement(
    spec: str, batch: int, envs: int, checkpoints, seed: int, graph_mode, iterations=None
) -> dict:
    space = em.make_space(spec)
    if iterations is not None:  # before the template reaches any device
        space.template.opt.iterations = iterations
    morphs = bodies(space, batch, seed)
    steps = max(checkpoints)
    shape = (steps, batch, envs, space.template.nu)
    rng = np.random.default_rng(seed)
    ctrl = rng.uniform(-1.0, 1.0, shape).astype(np.float32)

    jax32 = jax_qpos(space, morphs, ctrl, checkpoints)
    warp = warp_qpos(space, morphs, ctrl, checkpoints, graph_mode)
    with jax.enable_x64(True):
        jax64 = jax_qpos(space, morphs, ctrl.astype(np.float64), checkpoints)

    gap = lambda a, b: np.abs(a - b).max(axis=(2, 3)).T  # (B, C): max over envs and dofs
    return {
        "space": spec,
        "device": jax.devices()[0].device_kind,
        "graph_mode": str(graph_mode),
        "iterations": int(space.template.opt.iterations),
        "envs": envs,
        "steps": list(checkpoints),
        "bodies": [space.format(m).replace("\n", " | ") for m in em.unstack(morphs)],
        "warp_vs_jax32": gap(warp, jax32).tolist(),
        "jax32_vs_jax64": gap(jax32, jax64).tolist(),
        "qpos_scale": np.abs(jax64).max(axis=(2, 3)).T.tolist(),
        "finite": bool(np.isfinite(warp).all() and np.isfinite(jax32).all()),
    }


def main():
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--spaces", nargs="+", default=em.list_spaces())
    parser.add_argument("--batch", type=int, default=5, help="B, bodies per space")
    parser.add_argument("--envs", type=int, default=4, help="E, worlds per body")
    parser.add_argument("--checkpoints", type=int, nargs="+", default=[1, 10, 50])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--iterations", type=int, default=None, help="Newton iterations (default the space's, 4)"
    )
    parser.add_argument(
        "--graph-mode",
        choices=("NONE", "JAX", "WARP", "WARP_STAGED", "WARP_STAGED_EX"),
        default=None,
        help="Warp's CUDA graph mode (warp.JaxCallableGraphMode); default MJX's (WARP on a GPU)",
    )
    args = parser.parse_args()
    jax.config.update("jax_default_matmul_precision", "highest")
    ok, reason = ew.available()
    if not ok:
        raise SystemExit(f"the Warp physics cannot run: {reason}")
    import warp

    warp.config.log_level = warp.LOG_WARNING  # no line per kernel module loaded
    graph_mode = None
    if args.graph_mode is not None:
        graph_mode = getattr(warp.JaxCallableGraphMode, args.graph_mode)

    rows = []
    for spec in args.spaces:
        checkpoints = sorted(args.checkpoints)
        row = agreement(
            spec, args.batch, args.envs, checkpoints, args.seed, graph_mode, args.iterations
        )
        print(json.dumps(row), flush=True)
        rows.append(row)

    steps = sorted(args.checkpoints)
    head = " ".join(f"{f'warp {s}':>10}" for s in steps) + " "
    head += " ".join(f"{f'f64 {s}':>10}" for s in steps)
    print("\nmax |qpos difference| at step: warp vs jax float32, jax float32 vs float64")
    print(f"{'space':<16} {'body':>4} {head}")
    for r in rows:
        for b, (w, x) in enumerate(zip(r["warp_vs_jax32"], r["jax32_vs_jax64"])):
            cells = " ".join(f"{v:>10.2e}" for v in w + x)
            print(f"{r['space']:<16} {b:>4} {cells}")


if __name__ == "__main__":
    main()
