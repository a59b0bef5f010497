"""MJCF of a space's bodies: the padded template and the standalone export.

`write_mjcf` turns a `physics.BodyPlan` and a `physics.Layout` into MJCF: with every slot (the
padded template, which `compile_template` compiles once per space) or with the active slots
alone (the export, which MuJoCo compiles by itself and so serves as the independent reference
for the padded MJX model that `physics.specialise` makes).
"""

from __future__ import annotations

import jax
import mujoco
import numpy as np

from evojax_morph.physics.capsules import DENSITY
from evojax_morph.physics.templates import FREE_ROOT, ROOT_JOINTS, BodyPlan, Layout


def write_mjcf(plan: BodyPlan, layout: Layout, name: str, padded: bool) -> str:
    """MJCF of a layout: every slot if `padded` (the template), else the active slots only."""
    lay = jax.tree.map(np.asarray, layout)
    fmt = lambda v: " ".join(f"{float(x):.17g}" for x in v)

    def geoms(body: int, indent: str) -> list[str]:
        lines = []
        for g, b in enumerate(plan.geom_body):
            if b != body or not (padded or lay.geom_active[g]):
                continue
            fromto = fmt(np.concatenate([lay.geom_from[g], lay.geom_to[g]]))
            lines.append(
                f'{indent}<geom name="{plan.geom_names[g]}" type="capsule" fromto="{fromto}" '
                f'size="{float(lay.geom_radius[g]):.17g}" rgba="{fmt(plan.geom_rgba[g])}"/>'
            )
        return lines

    def limbs(parent: int, indent: str) -> list[str]:
        lines = []
        for k, p in enumerate(plan.limb_parent):
            if p != parent or not (padded or lay.limb_active[k]):
                continue
            i = plan.limb_nodes[k]
            axis = "" if lay.limb_axis is None else f' axis="{fmt(lay.limb_axis[k])}"'
            lines.append(f'{indent}<body name="node{i}" pos="{fmt(lay.limb_pos[k])}">')
            lines.append(f'{indent}  <joint name="joint{i}"{axis}/>')
            lines += geoms(k + 1, indent + "  ")
            lines += limbs(k + 1, indent + "  ")
            lines.append(f"{indent}</body>")
        return lines

    motors = [
        f'    <motor name="act{i}" joint="joint{i}" gear="{plan.gear:.17g}"/>'
        for k, i in enumerate(plan.limb_nodes)
        if padded or lay.limb_active[k]
    ]
    lo, hi = plan.joint_range
    planar = [
        f'      <joint name="{name}" type="{kind}" axis="{axis}" limited="false" damping="0" '
        'armature="0"/>'
        for name, kind, axis in zip(ROOT_JOINTS, ("slide", "slide", "hinge"),
                                    ("1 0 0", "0 0 1", "0 1 0"))
    ]
    body = (
        [f'    <body name="node0" pos="{fmt(lay.root_pos)}">']
        + (planar if plan.root == "planar" else [f'      <freejoint name="{FREE_ROOT}"/>'])
        + geoms(0, "      ")
        + limbs(0, "      ")
        + ["    </body>"]
    )
    return "\n".join(
        [
            f'<mujoco model="{name}">',
            '  <compiler angle="radian" autolimits="true"/>',
            f'  <option timestep="{plan.timestep:.17g}" iterations="{plan.iterations}" '
            f'ls_iterations="{plan.ls_iterations}"'
            + ("" if plan.cone == "pyramidal" else f' cone="{plan.cone}"') + "/>",
            "  <default>",
            f'    <joint type="hinge" axis="0 1 0" range="{lo:.17g} {hi:.17g}" '
            f'damping="{plan.joint_damping:.17g}" armature="{plan.joint_armature:.17g}"/>',
            f'    <geom contype="1" conaffinity="0" condim="3" friction="{plan.friction:.17g} '
            f'0.1 0.1" density="{DENSITY:.17g}"/>',
            '    <motor ctrlrange="-1 1"/>',
            "  </default>",
            "  <worldbody>",
            '    <light name="sun" pos="0 0 4" dir="0 0 -1" directional="true"/>',
            '    <geom name="floor" type="plane" size="0 0 0.05" conaffinity="1" '
            'rgba="0.8 0.85 0.9 1"/>',
        ]
        + body
        + ["  </worldbody>", "  <actuator>"]
        + motors
        + ["  </actuator>", "</mujoco>", ""]
    )


def compile_template(plan: BodyPlan, layout: Layout, name: str) -> mujoco.MjModel:
    """Compiles the padded template; `layout` only needs to be a valid placement of every slot."""
    model = mujoco.MjModel.from_xml_string(write_mjcf(plan, layout, name, padded=True))
    # Frames vary per morphology, so no body or geom frame may be assumed to coincide with
    # another: MuJoCo's renderer and C engine read these flags (MJX's JAX engine ignores them).
    model.body_sameframe[:] = 0
    model.geom_sameframe[:] = 0
    return model
