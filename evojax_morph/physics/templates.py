"""Capsule bodies, planar or free in 3D: one padded MuJoCo template per space, specialised per
morphology in JAX.

A space describes its bodies in two parts:

* a static `BodyPlan`: every geom and limb slot that any morphology of the space may use, with
  the body each geom hangs on and the parent of each limb. This fixes the MuJoCo tree, joint
  types and contact pairs, which MJX requires to be identical across a vmapped batch;
* a dynamic `Layout`, computed from a morphology with jittable JAX ops: which slots are active
  and where their capsules lie.

`mjcf.write_mjcf` turns a plan and a layout into MJCF: with every slot (the padded
template) or with the active slots alone (the export, which MuJoCo compiles by itself and so
serves as the independent reference). `specialise` turns the template `mjx.Model` into the
model of one morphology by overwriting numeric fields only (the capsules' frames, masses and
inertias from `capsules`), and recomputes every derived constant that the MuJoCo
compiler would have computed for the unpadded body.

How an inactive slot is made inert:
  * its geoms get zero mass and a contact margin of -1e3: MJX adds the margins of both geoms and
    activates a contact only when `dist < margin`, so a floor contact never activates;
  * its limb body gets zero mass and inertia, its actuator zero gear and its dof an armature of
    1, which keeps the mass matrix positive definite. With zero inertia the dof is decoupled
    from every other dof (the mass matrix is block diagonal) and feels no force, so the joint
    stays at rest and the active dofs move exactly as in the unpadded model.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
from typing import Any, Protocol

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct

from evojax_morph.physics import capsules


def _mujoco_warp_package() -> str:
    """With EVOJAX_MORPH_MUJOCO_WARP=package, MJX's Warp implementation runs the mujoco-warp
    package instead of its vendored copy.

    MJX 3.17 steps `mujoco.mjx.third_party.mujoco_warp`, which lacks `Option.deterministic`; the
    mujoco-warp package of the same release has it, and the same Model, Data and Option fields
    but for `Option.deterministic` and three sensor addresses (unused here: no sensors). So its
    modules are registered under the vendored names before MJX imports them, where the package's
    version is mujoco's. Not the default: the option did not make the fitness reproducible and
    cost 12.5x (docs/benchmarks.md, "A reproducible Warp"), and the package runs no faster.

    Returns:
      "package" or "vendored": the copy MJX's Warp implementation runs.
    """
    import importlib
    import importlib.metadata as metadata
    import os
    import pkgutil
    import sys

    if os.environ.get("EVOJAX_MORPH_MUJOCO_WARP", "vendored") != "package":
        return "vendored"
    if "mujoco.mjx" in sys.modules:  # too late: MJX holds the vendored modules already
        return "vendored"
    try:
        if metadata.version("mujoco-warp") != mujoco.__version__:
            return "vendored"
        with contextlib.redirect_stdout(io.StringIO()):
            src = importlib.import_module("mujoco_warp._src")
            for mod in pkgutil.iter_modules(src.__path__):
                if not mod.name.endswith("_test"):
                    importlib.import_module(f"mujoco_warp._src.{mod.name}")
    except Exception:  # not installed, or no Warp to run it: MJX says why when asked
        return "vendored"
    for name in [n for n in sys.modules if n.split(".")[0] == "mujoco_warp"]:
        sys.modules["mujoco.mjx.third_party." + name] = sys.modules[name]
    return "package"


MUJOCO_WARP = _mujoco_warp_package()  # before mjx imports its Warp implementation
with contextlib.redirect_stdout(io.StringIO()):  # mjx prints when the optional warp is missing
    from mujoco import mjx

INACTIVE_MARGIN = -1e3  # m: contacts of an inactive geom never activate
INACTIVE_ARMATURE = 1.0  # kg m^2: keeps the mass matrix of a massless slot positive definite
ROOT_JOINTS = ("rootx", "rootz", "rooty")  # a planar root: slides along x and z, hinge about y
FREE_ROOT = "root"  # a free root's joint: 7 qpos (position, quaternion), 6 dofs


class SpaceLike(Protocol):
    """What the engines, MuJoCo Warp and the size classes read of a space; every
    `evojax_morph.spaces.Space` is one (the spaces build on this package, so it names them by
    what it reads)."""

    name: str
    max_nodes: int
    template: mujoco.MjModel  # the padded template
    plan: BodyPlan

    def mjx_model(self, m: Any) -> Any: ...  # one body's specialised MJX model

    def initial(self) -> Any: ...  # m0

    @property
    def full_share(self) -> float: ...

    def size_classes(self) -> tuple: ...


@dataclasses.dataclass(frozen=True)
class BodyPlan:
    """The static slots of a space's padded template.

    Body 0 is the root (the trunk); bodies 1..L are limbs, each with one actuated hinge at its
    body origin. `root` "planar": the trunk moves in the x-z plane through `ROOT_JOINTS` and
    every hinge turns about y. "free": the trunk is free in 3D (`FREE_ROOT`) and each limb's
    hinge turns about its own axis (`Layout.limb_axis`); every body frame stays aligned with
    the trunk's at rest.
    """

    geom_names: tuple[str, ...]  # (G,)
    geom_body: tuple[int, ...]  # (G,): 0 for the root, k for limb k
    geom_rgba: tuple[tuple[float, float, float, float], ...]  # (G,)
    limb_nodes: tuple[int, ...]  # (L,): the morphology node of limb k+1, naming its parts
    limb_parent: tuple[int, ...]  # (L,): parent body of limb k+1 (0 root, or an earlier limb)
    joint_range: tuple[float, float] = (-1.0, 1.0)  # rad, for every limb hinge
    joint_damping: float = 0.1
    joint_armature: float = 0.01
    gear: float = 30.0  # N m per unit of control, controls in [-1, 1]
    timestep: float = 0.005
    friction: float = 1.0
    # Newton solver budget: MJX runs the largest count of a vmapped batch, so keep it small.
    iterations: int = 4
    ls_iterations: int = 8
    root: str = "planar"  # "planar" or "free"
    # Friction cone. MJX and MuJoCo Warp align a capsule's pyramidal cone with its axis only
    # when the axis is within 60 degrees of the floor, MuJoCo C always: a steep limb heading
    # neither along x nor y then slips differently in each. An elliptic cone is the same in
    # every frame (and in every engine).
    cone: str = "pyramidal"

    def __post_init__(self):
        if self.root not in ("planar", "free"):
            raise ValueError(f"root must be 'planar' or 'free', got {self.root!r}")
        if self.cone not in ("pyramidal", "elliptic"):
            raise ValueError(f"cone must be 'pyramidal' or 'elliptic', got {self.cone!r}")
        if not len(self.geom_names) == len(self.geom_body) == len(self.geom_rgba):
            raise ValueError("geom_names, geom_body and geom_rgba differ in length")
        for k, p in enumerate(self.limb_parent):
            if not 0 <= p <= k:
                raise ValueError(f"limb {k + 1} has parent {p}: parents must come first")

    @property
    def num_limbs(self) -> int:
        return len(self.limb_nodes)

    @property
    def root_joints(self) -> tuple[str, ...]:
        return ROOT_JOINTS if self.root == "planar" else (FREE_ROOT,)

    @property
    def specialised_fields(self) -> tuple[str, ...]:
        """The Model fields `specialise` writes for this plan (with `stat.meaninertia`)."""
        return SPECIALISED_FIELDS + (("jnt_axis", "qpos0", "qpos_spring") if self.root == "free"
                                     else ())

    @property
    def body_names(self) -> tuple[str, ...]:
        return ("node0",) + tuple(f"node{i}" for i in self.limb_nodes)

    @property
    def joint_names(self) -> tuple[str, ...]:
        return tuple(f"joint{i}" for i in self.limb_nodes)

    @property
    def actuator_names(self) -> tuple[str, ...]:
        return tuple(f"act{i}" for i in self.limb_nodes)


@struct.dataclass
class Layout:
    """Where the active capsules of one morphology lie; every frame is a body frame."""

    root_pos: jax.Array  # (3,): root body position in the world at rest
    limb_active: jax.Array  # (L,) bool
    limb_pos: jax.Array  # (L, 3): hinge anchor (= limb body origin) in its parent's frame
    geom_active: jax.Array  # (G,) bool
    geom_from: jax.Array  # (G, 3): capsule segment start in its body's frame
    geom_to: jax.Array  # (G, 3): capsule segment end in its body's frame
    geom_radius: jax.Array  # (G,)
    limb_axis: jax.Array | None = None  # (L, 3): each hinge's axis (a free root); None: y


@dataclasses.dataclass(frozen=True)
class TemplateIndex:
    """Ids of the plan's slots in the compiled template."""

    body: np.ndarray  # (1 + L,) body ids, root first
    geom: np.ndarray  # (G,)
    limb_dof: np.ndarray  # (L,)
    actuator: np.ndarray  # (L,)
    limb_joint: np.ndarray  # (L,) joint ids
    free_dof: int | None  # the free root's first dof; None for a planar root
    free_qpos: int | None  # the free root's first qpos (its position, then its quaternion)

    @classmethod
    def build(cls, plan: BodyPlan, model: mujoco.MjModel) -> TemplateIndex:
        ids = lambda kind, names: np.array([model.__getattribute__(kind)(n).id for n in names])
        joints = ids("joint", plan.joint_names).astype(int)
        return cls(
            body=ids("body", plan.body_names),
            geom=ids("geom", plan.geom_names),
            limb_dof=model.jnt_dofadr[joints] if len(joints) else np.zeros(0, int),
            actuator=ids("actuator", plan.actuator_names),
            limb_joint=joints,
            free_dof=None if plan.root == "planar" else int(model.joint(FREE_ROOT).dofadr[0]),
            free_qpos=None if plan.root == "planar" else int(model.joint(FREE_ROOT).qposadr[0]),
        )


def _put(array: jax.Array, index, value) -> jax.Array:
    """`array.at[index].set(value)`, keeping the dtype of `array`."""
    return array.at[index].set(jnp.asarray(value).astype(array.dtype))


def specialise(
    template: mjx.Model, plan: BodyPlan, index: TemplateIndex, layout: Layout
) -> mjx.Model:
    """The template specialised to one layout, with MuJoCo's derived constants recomputed.

    Pure JAX on numeric fields only: jit- and vmap-friendly, one compile for every morphology.
    """
    dtype = template.body_mass.dtype
    layout = jax.tree.map(
        lambda x: x.astype(dtype) if jnp.issubdtype(x.dtype, jnp.floating) else x, layout
    )
    geom_on = layout.geom_active.astype(dtype)
    limb_on = layout.limb_active.astype(dtype)

    # GEOMS
    free = plan.root == "free"
    frame = capsules.frame_3d if free else capsules.frame_xz
    centre, half, quat, rot = frame(layout.geom_from, layout.geom_to)
    mass_g, inertia_g = capsules.inertia(layout.geom_radius, half)
    mass_g = mass_g * geom_on
    inertia_g = inertia_g * geom_on[:, None]
    g = index.geom
    size = _put(_put(template.geom_size, (g, 0), layout.geom_radius), (g, 1), half)
    rgba = _put(template.geom_rgba, (g, 3), template.geom_rgba[g, 3] * geom_on)
    margin = jnp.where(layout.geom_active, template.geom_margin[g], INACTIVE_MARGIN)
    margin = _put(template.geom_margin, g, margin)

    # BODIES
    owner = np.zeros((1 + plan.num_limbs, len(plan.geom_body)))  # 1 where geom g is on body b
    owner[np.array(plan.geom_body), np.arange(len(plan.geom_body))] = 1.0
    inertial = capsules.bodies_3d if free else capsules.bodies_xz
    mass, com, principal, iquat = inertial(owner, mass_g, inertia_g, centre, rot)
    b = index.body
    body_pos = _put(_put(template.body_pos, b[0], layout.root_pos), b[1:], layout.limb_pos)
    subtree = mass
    for k in reversed(range(plan.num_limbs)):  # limbs come after their parents
        subtree = subtree.at[plan.limb_parent[k]].add(subtree[k + 1])

    # LIMB JOINTS AND ACTUATORS
    armature = jnp.where(layout.limb_active, plan.joint_armature, INACTIVE_ARMATURE)
    armature = _put(template.dof_armature, index.limb_dof, armature)
    gear = _put(template.actuator_gear, (index.actuator, 0), plan.gear * limb_on)

    model = template.replace(
        geom_pos=_put(template.geom_pos, g, centre),
        geom_quat=_put(template.geom_quat, g, quat),
        geom_size=size,
        geom_rbound=_put(template.geom_rbound, g, layout.geom_radius + half),
        geom_rgba=rgba,
        geom_margin=margin,
        body_pos=body_pos,
        body_mass=_put(template.body_mass, b, mass),
        body_subtreemass=_put(template.body_subtreemass, b, subtree),
        body_ipos=_put(template.body_ipos, b, com),
        body_iquat=_put(template.body_iquat, b, iquat),
        body_inertia=_put(template.body_inertia, b, principal),
        dof_armature=armature,
        actuator_gear=gear,
    )
    if free:  # each hinge's axis; a free joint's qpos0 is where its body starts (the compiler's)
        axis = layout.limb_axis / jnp.linalg.norm(layout.limb_axis, axis=-1, keepdims=True)
        start = np.arange(index.free_qpos, index.free_qpos + 3)
        model = model.replace(
            jnt_axis=_put(template.jnt_axis, index.limb_joint, axis),
            qpos0=_put(template.qpos0, start, layout.root_pos),
            qpos_spring=_put(template.qpos_spring, start, layout.root_pos),
        )
    return _set_constants(model, index, limb_on)


# Every Model field `specialise` writes (with `stat.meaninertia`); every other field of a
# specialised model is the template's, whatever the body.
SPECIALISED_FIELDS = (
    "geom_pos",
    "geom_quat",
    "geom_size",
    "geom_rbound",
    "geom_rgba",
    "geom_margin",
    "body_pos",
    "body_mass",
    "body_subtreemass",
    "body_ipos",
    "body_iquat",
    "body_inertia",
    "body_invweight0",
    "dof_armature",
    "dof_invweight0",
    "dof_M0",
    "actuator_gear",
    "actuator_acc0",
)


def flat_models(
    models: mjx.Model, envs: int, fields: tuple[str, ...] = SPECIALISED_FIELDS
) -> tuple[mjx.Model, mjx.Model]:
    """B specialised models as one model per world of a flat batch of B x E worlds.

    World `w = b * envs + e` is env e of body b. Only the fields `specialise` writes are
    repeated per world; the rest are body 0's, shared. Step the flat batch with
    `jax.vmap(mjx.step, (in_axes, 0))(model, data)`, data with a leading (B * E,) axis.

    Args:
      models: a batch of `specialise`d models (JAX impl), every leaf with a leading (B,) axis.
      envs: E, worlds per body.
      fields: the fields `specialise` wrote (`BodyPlan.specialised_fields`).

    Returns:
      `(model, in_axes)`: the model, `fields` and `stat.meaninertia`
      with a leading (B * E,) axis and the rest unbatched, and the matching `in_axes` tree
      (0 for the repeated leaves, None for the shared ones).
    """
    repeat = lambda x: jnp.repeat(x, envs, axis=0)
    shared = jax.tree.map(lambda x: x[0], models)
    flat = shared.replace(
        **{name: repeat(getattr(models, name)) for name in fields},
        stat=shared.stat.replace(meaninertia=repeat(models.stat.meaninertia)),
    )
    axes = jax.tree.map(lambda _: None, shared)
    axes = axes.replace(
        **{name: 0 for name in fields}, stat=axes.stat.replace(meaninertia=0)
    )
    return flat, axes


def _set_constants(model: mjx.Model, index: TemplateIndex, limb_on: jax.Array) -> mjx.Model:
    """Constants MuJoCo computes at qpos0 (engine_setconst.c), from the model's own mass matrix."""
    data = mjx.make_data(model)
    data = mjx.kinematics(model, data)
    data = mjx.com_pos(model, data)
    data = mjx.crb(model, data)
    mass_matrix = mjx.full_m(model, data)
    inv_m = jnp.linalg.inv(mass_matrix)

    # body_invweight0: mean diagonal of J M^-1 J' for the Jacobian of each body's centre of mass.
    def invweight(body_id):
        jacp, jacr = mjx.jac(model, data, data.xipos[body_id], body_id)
        jac = jnp.concatenate([jacp, jacr], 1).T  # (6, nv)
        a = jac @ inv_m @ jac.T
        return jnp.stack([jnp.trace(a[:3, :3]) / 3, jnp.trace(a[3:, 3:]) / 3])

    body_ids = np.arange(1, model.nbody)
    body_invweight0 = _put(model.body_invweight0, body_ids, jax.vmap(invweight)(body_ids))

    # dof_invweight0: diagonal of M^-1 for a hinge or slide; a free joint's translations share
    # the mean of their three, and its rotations theirs. dof_M0: diagonal of M.
    dof_invweight0 = jnp.diagonal(inv_m)
    if index.free_dof is not None:
        for first in (index.free_dof, index.free_dof + 3):
            part = slice(first, first + 3)
            dof_invweight0 = dof_invweight0.at[part].set(jnp.mean(dof_invweight0[part]))
    dof_m0 = jnp.diagonal(mass_matrix)

    # actuator_acc0: norm of M^-1 times the actuator's moment (its gear on its dof).
    acc0 = _put(
        model.actuator_acc0,
        index.actuator,
        jnp.abs(model.actuator_gear[index.actuator, 0])
        * jnp.linalg.norm(inv_m[:, index.limb_dof], axis=0),
    )

    # stat.meaninertia: mean diagonal of M over the dofs the unpadded model would have.
    dof_on = jnp.ones(model.nv, model.body_mass.dtype).at[index.limb_dof].set(limb_on)
    meaninertia = jnp.sum(dof_m0 * dof_on) / jnp.sum(dof_on)
    return model.replace(
        body_invweight0=body_invweight0,
        dof_invweight0=dof_invweight0,
        dof_M0=dof_m0,
        actuator_acc0=acc0,
        stat=model.stat.replace(meaninertia=meaninertia),
    )


def lowest_point(plan: BodyPlan, layout: Layout) -> jax.Array:
    """() height of the lowest active capsule surface below the root origin, at rest (<= 0).

    At rest every joint is at zero and every body frame is aligned with the root's, so a limb's
    origin is the sum of its ancestors' anchors.
    """
    origin = [jnp.zeros(3, layout.limb_pos.dtype)]
    for k, p in enumerate(plan.limb_parent):
        origin.append(origin[p] + layout.limb_pos[k])
    body_origin = jnp.stack(origin)[np.array(plan.geom_body)]  # (G, 3)
    bottom = jnp.minimum(layout.geom_from[:, 2], layout.geom_to[:, 2]) + body_origin[:, 2]
    bottom = bottom - layout.geom_radius
    return jnp.min(jnp.where(layout.geom_active, bottom, jnp.inf))
