"""Constructor: grow a planar body from a stick by adding static edges and actuated legs."""

from __future__ import annotations

import functools

import jax.numpy as jnp
import numpy as np

from evojax_morph import physics
from evojax_morph.morphology import Morphology
from evojax_morph.spaces.base import Space

STICK_LENGTH, EDGE_LENGTH, LEG_LENGTH = 1.0, 0.5, 0.4  # m
STICK_RADIUS, EDGE_RADIUS, LEG_RADIUS = 0.05, 0.05, 0.04
LEG_INCLINE = 0.2  # rad: a leg's foot sits behind its hip, which helps it push forward
CLEARANCE = 0.005  # m between the lowest point and the floor at reset
STICK, EDGE, LEG = 0, 1, 2  # node kinds
# Mutation m adds a child in slot m of the node: (kind, attachment point, x direction).
# Attachment 0 is the node's start point, 1 its end point; direction only matters for edges.
SLOT_KIND = np.array([EDGE, EDGE, EDGE, EDGE, LEG, LEG])
SLOT_END = np.array([0, 0, 1, 1, 0, 1])
SLOT_DIR = np.array([-1.0, 1.0, -1.0, 1.0, 0.0, 0.0])
DEFAULT_HORIZON = 8


class Constructor(Space):
    """Start from a stick (node 0) and add one limb per mutation.

    Every node offers 6 mutations, each filling one child slot of the node: a static horizontal
    edge (length 0.5) from its start or end point, pointing backward or forward (4 slots), or
    an actuated leg (length 0.4, inclined by 0.2 rad) hanging from its start or end point
    (2 slots). A slot takes one child. Edges are welded to the trunk (geoms of the root body);
    a leg is a body with a hinge and a motor, and a leaf: its own 6 mutations are masked, since
    a limb on a limb needs a kinematic chain whose shape would vary per morphology, and MJX
    needs one fixed body tree for a batch. The capacity is 1 + horizon nodes, so a run of
    `horizon` mutations never runs out of room; once full, every action is masked.

    Predefined fitness: 100 x (number of legs - number of edges).
    """

    name = "constructor"
    kind_names = ("stick", "edge", "leg")
    site_names = ("start_back", "start_fwd", "end_back", "end_fwd", "leg_start", "leg_end")
    mutation_names = tuple(f"add_{s}" for s in ("edge_start_back", "edge_start_fwd",
                                                "edge_end_back", "edge_end_fwd",
                                                "leg_start", "leg_end"))
    attr_names = ("length",)
    fitness_scale = 100.0  # typical magnitude of the predefined fitness

    def __init__(self, horizon: int = DEFAULT_HORIZON):
        if horizon < 1:
            raise ValueError(f"horizon must be at least 1, got {horizon}")
        self.horizon = self.default_horizon = horizon
        self.max_nodes = 1 + horizon

    def initial(self) -> Morphology:
        n = self.max_nodes
        return Morphology(
            active=jnp.zeros(n, bool).at[0].set(True),
            parent=jnp.full(n, -1, jnp.int32),
            kind=jnp.zeros(n, jnp.int32),
            site=jnp.zeros(n, jnp.int32),
            attrs=jnp.zeros((n, 1), jnp.float32).at[0, 0].set(STICK_LENGTH),
        )

    def action_mask(self, m: Morphology) -> jnp.ndarray:
        # occupied[i, s]: node i already has a child in slot s
        child = m.active[:, None] & (m.parent[:, None] == jnp.arange(self.max_nodes)[None])
        occupied = jnp.einsum("ji,js->is", child, m.site[:, None] == jnp.arange(6)[None]) > 0
        can_grow = m.active & (m.kind != LEG) & (m.num_nodes < self.max_nodes)
        return can_grow[:, None] & ~occupied

    def _apply(self, m: Morphology, node, mutation) -> Morphology:
        new = m.num_nodes  # slots fill in order: nodes are never removed
        kind = jnp.asarray(SLOT_KIND, jnp.int32)[mutation]
        length = jnp.where(kind == LEG, LEG_LENGTH, EDGE_LENGTH).astype(m.attrs.dtype)
        return Morphology(
            active=m.active.at[new].set(True),
            parent=m.parent.at[new].set(node.astype(jnp.int32)),
            kind=m.kind.at[new].set(kind),
            site=m.site.at[new].set(mutation),
            attrs=m.attrs.at[new, 0].set(length),
        )

    def predefined_fitness(self, m: Morphology) -> jnp.ndarray:
        legs = jnp.sum(m.active & (m.kind == LEG))
        edges = jnp.sum(m.active & (m.kind == EDGE))
        return 100.0 * (legs - edges).astype(jnp.float32)

    @functools.cached_property
    def plan(self) -> physics.BodyPlan:
        nodes = range(1, self.max_nodes)
        edge, leg, stick = (0.35, 0.55, 0.8, 1.0), (0.85, 0.5, 0.2, 1.0), (0.3, 0.45, 0.7, 1.0)
        return physics.BodyPlan(
            # geoms: the stick, then one welded edge per slot (on the root), then one leg per slot
            geom_names=("geom0",) + tuple(f"geom{i}_welded" for i in nodes)
            + tuple(f"geom{i}" for i in nodes),
            geom_body=(0,) * self.max_nodes + tuple(range(1, self.max_nodes)),
            geom_rgba=(stick,) + (edge,) * self.horizon + (leg,) * self.horizon,
            limb_nodes=tuple(nodes),
            limb_parent=(0,) * self.horizon,
            joint_range=(-1.0, 1.0),
            gear=30.0,
        )

    def layout(self, m: Morphology) -> physics.Layout:
        n = self.max_nodes
        kind = jnp.where(m.active, m.kind, EDGE)  # inactive slots get valid edge geometry...
        default = jnp.where(kind == LEG, LEG_LENGTH, EDGE_LENGTH)
        length = jnp.where(m.active, m.attrs[:, 0], default)  # ...of a valid length
        end_slot = jnp.asarray(SLOT_END)[m.site]
        direction = jnp.asarray(SLOT_DIR)[m.site]
        leg_dir = jnp.array([-jnp.sin(LEG_INCLINE), 0.0, -jnp.cos(LEG_INCLINE)])

        # END POINTS IN THE ROOT FRAME, parents first
        start = jnp.zeros((n, 3)).at[0, 0].set(-length[0] / 2)
        end = jnp.zeros((n, 3)).at[0, 0].set(length[0] / 2)
        for i in range(1, n):
            p = jnp.maximum(m.parent[i], 0)
            attach = jnp.where(end_slot[i] == 1, end[p], start[p])
            step = jnp.where(
                kind[i] == LEG, length[i] * leg_dir, jnp.array([1.0, 0.0, 0.0]) * direction[i] * length[i]
            )
            start, end = start.at[i].set(attach), end.at[i].set(attach + step)

        is_edge = m.active[1:] & (kind[1:] == EDGE)
        is_leg = m.active[1:] & (kind[1:] == LEG)
        leg_to = length[1:, None] * leg_dir
        welded_to = jnp.where((kind[1:] == EDGE)[:, None], end[1:], start[1:] + EDGE_LENGTH * jnp.array([1.0, 0, 0]))
        layout = physics.Layout(
            root_pos=jnp.zeros(3),
            limb_active=is_leg,
            limb_pos=start[1:],
            geom_active=jnp.concatenate([jnp.ones(1, bool), is_edge, is_leg]),
            geom_from=jnp.concatenate([start[:1], start[1:], jnp.zeros((n - 1, 3))]),
            geom_to=jnp.concatenate([end[:1], welded_to, leg_to]),
            geom_radius=jnp.concatenate(
                [jnp.full(1, STICK_RADIUS), jnp.full(n - 1, EDGE_RADIUS), jnp.full(n - 1, LEG_RADIUS)]
            ),
        )
        height = CLEARANCE - physics.lowest_point(self.plan, layout)
        return layout.replace(root_pos=jnp.zeros(3).at[2].set(height))
