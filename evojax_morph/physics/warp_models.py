"""Warp models and data of a flat batch of B bodies x E envs: the bodies' fields repeated per
world (`to_warp`, `world_model`), the template shared (`put_model`), and the data of every world
with its contacts and constraint rows sized ahead (`make_worlds`, `buffers`).

Contacts and constraint rows are allocated per world for the largest body of the space
(`buffers`): Warp's solver kernels run over every allocated row of every world, used or not. The
solver's iterations run as a plain loop, not a CUDA graph conditional (`put_model`). Float32
only. The derived constants are computed by `specialise` in the JAX impl and copied; `dof_M0`
and `stat.meaninertia` are not read by Warp. `geom_aabb` (the broadphase's boxes) is recomputed
from the capsule sizes.
"""

from __future__ import annotations

import os

import jax
import jax.numpy as jnp
import mujoco

from evojax_morph.physics.templates import SpaceLike, flat_models, mjx
from evojax_morph.physics.warp_runtime import (
    apply_determinism,
    callback_lock,
    count_stream_registrations,
    graph_conditional,
    require,
)

# Fields `specialise` writes that Warp does not read.
_NOT_IN_WARP = ("dof_M0",)


def _capsule_aabb(template: mujoco.MjModel, geom_size: jax.Array) -> jax.Array:
    """(..., ngeom, 2, 3) geom_aabb (centre, half sizes in the geom frame) for `geom_size`.

    A capsule's box is centred with half sizes (r, r, r + half length); every other geom keeps
    the template's box.
    """
    aabb = jnp.asarray(template.geom_aabb.reshape(-1, 2, 3), jnp.float32)
    aabb = jnp.broadcast_to(aabb, geom_size.shape[:-2] + aabb.shape)
    r, half = geom_size[..., 0], geom_size[..., 1]
    capsule = jnp.stack([jnp.zeros_like(r)] * 3 + [r, r, r + half], -1).reshape(aabb.shape)
    is_capsule = template.geom_type == mujoco.mjtGeom.mjGEOM_CAPSULE
    return jnp.where(is_capsule[:, None, None], capsule, aabb)


def to_warp(
    space: SpaceLike,
    models: mjx.Model,
    envs: int,
    naconmax_per_world: int | None = None,
    njmax: int | None = None,
    graph_mode=None,
) -> tuple[mjx.Model, mjx.Data]:
    """A Warp model and initial data of N = B x E worlds for B specialised bodies.

    Args:
      space: the space whose padded template (`space.template`) the bodies specialise.
      models: B bodies from `space.mjx_model` (JAX impl, float32 or float64), every leaf with a
        leading (B,) axis.
      envs: E, worlds per body; world `w = b * E + e` is env e of body b.
      naconmax_per_world: contacts allocated per world (Warp's pool holds N times this);
        None for `make_worlds`'s default.
      njmax: constraint rows per world; None for `make_worlds`'s default.
      graph_mode: a `warp.JaxCallableGraphMode`; None is MJX's default (WARP on a GPU, JAX on
        the CPU).

    Returns:
      `(model, data)`: a Warp-impl `mjx.Model` whose `plan.specialised_fields` (but `dof_M0`) and
      `geom_aabb` have a leading (N,) float32 axis, the rest the template's; and `mjx.Data` of
      the template at qpos0 with a leading (N,) axis on its per-world fields.

    Raises:
      RuntimeError: when MJX's Warp implementation cannot run here (the reason is given).
    """
    require()
    model = world_model(space, models, envs, graph_mode)
    worlds = models.body_mass.shape[0] * envs
    return model, make_worlds(space, worlds, naconmax_per_world, njmax)


def world_model(space: SpaceLike, models: mjx.Model, envs: int, graph_mode=None) -> mjx.Model:
    """The Warp model of `to_warp` alone: B bodies' `plan.specialised_fields` (but `dof_M0`) and
    `geom_aabb` repeated per world, a leading (B x envs,) axis on each; jittable."""
    require()
    template = space.template
    base = put_model(template, graph_mode)
    flat, _ = flat_models(models, envs, space.plan.specialised_fields)  # one per world
    fields = {n: jnp.asarray(getattr(flat, n), jnp.float32) for n in written(space)}
    fields["geom_aabb"] = _capsule_aabb(template, fields["geom_size"])
    return base.replace(**fields)


def written(space: SpaceLike) -> list[str]:
    """The fields `specialise` writes that Warp reads: a run holds one of each per world."""
    return [n for n in space.plan.specialised_fields if n not in _NOT_IN_WARP]


def put_model(mj_model: mujoco.MjModel, graph_mode=None) -> mjx.Model:
    """`mj_model` as one Warp-impl model shared by every world (no per-world fields).

    graph_mode None is EVOJAX_MORPH_WARP_GRAPH's `GraphMode` if set (`jax`, `warp`, `none`, ...;
    for benchmarks), else MJX's default: WARP (Warp's own CUDA graph per call) on a GPU."""
    require()
    apply_determinism()
    count_stream_registrations()
    if graph_mode is None and os.environ.get("EVOJAX_MORPH_WARP_GRAPH"):
        from mujoco.mjx.warp.types import GraphMode

        graph_mode = GraphMode[os.environ["EVOJAX_MORPH_WARP_GRAPH"].upper()]
    with callback_lock():
        model = mjx.put_model(mj_model, impl="warp", graph_mode=graph_mode)
    # Warp prints a warning for each step whose solver hits its iteration budget: ours is small
    # on purpose (BodyPlan.iterations), so these would flood the output.
    # The solver's iterations as a plain loop of `iterations` passes, not a CUDA graph
    # conditional that stops once every world has converged: the same kernels, and a world that
    # has converged skips each pass (bit-identical on the CPU, tests/test_warp.py), but on an
    # H100 3-7% faster (docs/benchmarks.md). EVOJAX_MORPH_WARP_CONDITIONAL=1 keeps MJX's
    # conditional (for benchmarks).
    impl = model.opt._impl.replace(warn_overflow=0, graph_conditional=graph_conditional())
    return model.replace(opt=model.opt.replace(_impl=impl))


def buffers(space: SpaceLike) -> tuple[int, int]:
    """`(contacts, rows)` per world: what the largest body of `space` can need at once.

    MuJoCo Warp sizes its contact pool and constraint rows ahead, and launches many solver
    kernels over every row of every world, used or not; an overflow drops contacts or rows
    silently (`put_model` turns the warning off). Only capsule-floor pairs collide, a capsule on
    a plane touches it at 2 points at most, an inactive capsule never does (its margin, see
    `physics`), and a body has at most one active capsule per node: so 2 x max_nodes contacts.
    Each takes 4 rows (pyramidal cone, condim 3; 3 in an elliptic cone); each limited joint 1
    more. Other constraint kinds are refused rather than counted.
    """
    t = space.template
    if (
        set(t.geom_condim.tolist()) != {3}
        or t.neq
        or t.npair
        or t.ntendon
        or (t.dof_frictionloss > 0).any()
        or (t.geom_conaffinity[t.geom_type == mujoco.mjtGeom.mjGEOM_CAPSULE] != 0).any()
    ):
        raise ValueError(f"{space.name}: buffers() counts capsule-floor contacts and limits only")
    capsules = int((t.geom_type == mujoco.mjtGeom.mjGEOM_CAPSULE).sum())
    contacts = 2 * min(space.max_nodes, capsules)
    per_contact = 4 if t.opt.cone == mujoco.mjtCone.mjCONE_PYRAMIDAL else 3  # elliptic: 3
    return contacts, per_contact * contacts + int(t.jnt_limited.sum())


def make_worlds(
    space: SpaceLike,
    worlds: int,
    naconmax_per_world: int | None = None,
    njmax: int | None = None,
    mj_model: mujoco.MjModel | None = None,
) -> mjx.Data:
    """Warp-impl data of the space's template (or `mj_model`) at qpos0 for `worlds` worlds, the
    contact pool shared; contacts and rows per world default to `buffers(space)`."""
    require()
    contacts, rows = buffers(space)
    naconmax_per_world = contacts if naconmax_per_world is None else naconmax_per_world
    njmax = rows if njmax is None else njmax
    mj_model = space.template if mj_model is None else mj_model
    with callback_lock():
        data = mjx.make_data(mj_model, impl="warp", naconmax=naconmax_per_world * worlds,
                             njmax=njmax)
    # Data's own vmap rule batches the per-world fields and keeps the contact pool shared.
    return jax.vmap(lambda _: data)(jnp.arange(worlds))
