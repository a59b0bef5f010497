"""Constructor: grow a planar body from a stick by adding static edges and actuated legs."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from evojax_morph.morphology import Morphology
from evojax_morph.physics import templates
from evojax_morph.spaces.base import SizeClass, Space

STICK_LENGTH, EDGE_LENGTH, LEG_LENGTH = 1.0, 0.5, 0.4  # m
STICK_RADIUS, EDGE_RADIUS, LEG_RADIUS = 0.05, 0.05, 0.04
LEG_INCLINE = 0.2  # rad: a leg's foot sits behind its hip, which helps it push forward
CLEARANCE = 0.005  # m between the lowest point and the floor at reset
STICK, EDGE, LEG = 0, 1, 2  # node kinds
# Mutation m adds a child at slot m of the node: (kind, attachment point, x direction).
# Attachment 0 is the node's start point, 1 its end point; direction only matters for edges.
SLOT_KIND = np.array([EDGE, EDGE, EDGE, EDGE, LEG, LEG])
SLOT_END = np.array([0, 0, 1, 1, 0, 1])
SLOT_DIR = np.array([-1.0, 1.0, -1.0, 1.0, 0.0, 0.0])
DEFAULT_HORIZON = 8


class Constructor(Space):
    """Start from a stick (node 0) and add one limb per mutation, to any node.

    Every node, legs included, offers the same 6 mutations, each adding a child at one of its
    slots: a static horizontal edge (0.5 m) from its start or end point, pointing backward or
    forward (4 slots), or an actuated leg (0.4 m, inclined by 0.2 rad, a hinge and a motor at its
    hip) hanging from its start or end point (2 slots). A slot takes any number of children, so
    several legs or edges can sit at one place. A node's start and end points are, for the
    stick and an edge, its two ends, and for a leg, its hip and its foot.

    Rigid parts: an edge is welded to the body of the node it hangs from (the trunk, or a leg:
    an edge on a leg swings with it); a leg on a leg (or on an edge welded to a leg) is a knee:
    a body with its own hinge inside its parent leg's body. MJX needs one body tree for a whole
    batch, so the padded template fixes the tree: the trunk holds `horizon` leg slots and
    `horizon` edge slots; a leg of depth d < `leg_depth` holds `knees` leg slots, and every leg
    holds `leg_edges` edge slots. A new limb takes the next free slot of the body it joins; a
    mutation that would need a slot the template lacks is masked. The capacity is 1 + horizon
    nodes; once full, every action is masked.

    Bodies of the source that remain unreachable (with the defaults leg_depth=2, knees=1,
    leg_edges=1): a leg on a knee (legs more than `leg_depth` deep); a second knee or a second
    edge on one leg (more than `knees` legs or `leg_edges` edges on a leg); and any body of more
    than 1 + horizon limbs. Each extra slot is in every leg of the template, and every slot
    costs physics time on every body of a batch, active or not. Measured on the CPU
    (docs/benchmarks.md, "Physics"): a batch of bodies steps 2.4x slower on this default
    template (17 bodies, 41 capsules) than on leaf legs (`leg_depth=1, leg_edges=0`: 9 bodies,
    17 capsules, the cheapest), and 4.9x slower with `knees=2, leg_edges=2` (25 bodies, 81
    capsules). Stacked legs, which the source's agent builds (its Figure 7), need no extra
    slots: the trunk has one for every step.

    Observation (of the evolution MDP): the morphology, its action mask (max_nodes x 6), progress.
    Action: (node, mutation). Reward: the change in fitness.
    Predefined fitness: 100 x (number of legs - number of edges). Its maximum after the
    `horizon` mutations of an episode is 100 x horizon (800 by default): a leg at every step,
    reached by many bodies (legs stacked at one place, knees, or spread out).
    """

    name = "constructor"
    kind_names = ("stick", "edge", "leg")
    site_names = ("start_back", "start_fwd", "end_back", "end_fwd", "leg_start", "leg_end")
    mutation_names = tuple(
        f"add_{s}"
        for s in (
            "edge_start_back",
            "edge_start_fwd",
            "edge_end_back",
            "edge_end_fwd",
            "leg_start",
            "leg_end",
        )
    )
    attr_names = ("length",)
    fitness_scale = 100.0  # typical magnitude of the predefined fitness

    @classmethod
    def gpu_defaults(cls) -> dict:
        """On the walking task (docs/results.md, "Bodies that walk", and docs/benchmarks.md,
        "The walking budget on the Constructor"): at 100,000 PPO steps 2.1% of random
        8-mutation bodies' evaluations walk 2 m upright (0.8% at 50,000, none at 10,000), at
        twice 50,000's cost; 128 evolutions x 1 controller (`gpu_controllers`) keep a step at
        ~6 s on an H100 (200,000 walks more, 3.8%, but doubles the greedy rollout's 8 one-body
        calls too)."""
        return {
            "num_envs": 128,
            "train_steps": 100_000,
            "steps": 60,
            "chunk": 5,
            "checkpoint_every": 1,
            "confirm": 8,
            "confirm_controllers": 32,
        }

    @classmethod
    def gpu_controllers(cls, engine) -> int:
        """1 on every engine: the Constructor's budget goes to PPO steps and evolutions."""
        return 1

    def __init__(
        self, horizon: int = DEFAULT_HORIZON, leg_depth: int = 2, knees: int = 1,
        leg_edges: int = 1, trunk_legs: int | None = None, trunk_edges: int | None = None,
    ):
        if horizon < 1:
            raise ValueError(f"horizon must be at least 1, got {horizon}")
        if leg_depth < 1 or knees < 0 or leg_edges < 0 or min(trunk_legs or 0,
                                                               trunk_edges or 0) < 0:
            raise ValueError(
                "need leg_depth >= 1, knees, leg_edges, trunk_legs, trunk_edges >= 0; "
                f"got {leg_depth}, {knees}, {leg_edges}, {trunk_legs}, {trunk_edges}"
            )
        self.horizon = self.default_horizon = horizon
        self.max_nodes = 1 + horizon
        self.leg_depth, self.knees, self.leg_edges = leg_depth, knees, leg_edges
        # the trunk's leg and edge slots: by default one for each mutation of an episode
        self.trunk_legs = horizon if trunk_legs is None else trunk_legs
        self.trunk_edges = horizon if trunk_edges is None else trunk_edges

        # THE STATIC BODY TREE: body 0 the trunk, then leg slots breadth first (parents first)
        body_parent, body_depth = [-1], [0]
        child_legs = [[]]  # child_legs[b]: the leg slots of body b, in the order they fill
        frontier = [0]
        while frontier:
            nxt = []
            for b in frontier:
                count = self.trunk_legs if b == 0 else (knees if body_depth[b] < leg_depth else 0)
                for _ in range(count):
                    body_parent.append(b)
                    body_depth.append(body_depth[b] + 1)
                    child_legs.append([])
                    child_legs[b].append(len(body_parent) - 1)
                    nxt.append(len(body_parent) - 1)
            frontier = nxt
        self.body_parent = np.array(body_parent)  # (B,)
        num_bodies = len(body_parent)
        width = max(len(c) for c in child_legs)
        # int32 (as the morphologies), under x64 too
        self.leg_slots = np.full((num_bodies, max(width, 1)), -1, np.int32)  # (B, K): body ids
        for b, c in enumerate(child_legs):
            self.leg_slots[b, : len(c)] = c
        self.num_leg_slots = np.array([len(c) for c in child_legs])  # (B,)
        # GEOMS: the stick; the trunk's edges; then each leg's capsule and its edges
        edges = [self.trunk_edges] + [leg_edges] * (num_bodies - 1)
        self.edge_slots = np.full((num_bodies, max(max(edges), 1)), -1, np.int32)  # (B, E): geoms
        geom_body, geom_names = [0], ["geom0"]
        self.leg_geom = np.zeros(num_bodies, np.int32)  # (B,): each leg body's capsule (0: trunk)
        for b in range(num_bodies):
            if b > 0:
                self.leg_geom[b] = len(geom_body)
                geom_body.append(b)
                geom_names.append(f"leg{b}")
            for k in range(edges[b]):
                self.edge_slots[b, k] = len(geom_body)
                geom_body.append(b)
                geom_names.append(f"edge{b}_{k}")
        self.num_edge_slots = np.array(edges)  # (B,)
        self.geom_body = np.array(geom_body)  # (G,)
        self.geom_names = tuple(geom_names)

    # Size classes (`physics.classes`): legs on the trunk only, then one knee and one edge
    # per leg, both with at most 4 legs on the trunk, then the full template. Of 20,000 random
    # 8-mutation bodies of the default space 25.4% fit the first, 73.8% the second (and not the
    # first), 0.8% only the full template; with these shares a batch of 64 to 1,024 such bodies
    # overflowed none of 400 draws (16 bodies: 1.8%, which then train on the full template).
    # A class whose template is the full one's is left out, and its share goes to the full one.
    SHARES = (0.3, 0.8, 0.1)

    @functools.cache  # noqa: B019  (spaces live as long as the process)
    def size_classes(self) -> tuple[tuple[SizeClass, float], ...]:
        trunk = min(4, self.trunk_legs), self.trunk_edges
        shapes = [(1, 0, 0, *trunk),
                  (min(2, self.leg_depth), min(1, self.knees), min(1, self.leg_edges), *trunk)]
        full = (self.leg_depth, self.knees, self.leg_edges, self.trunk_legs, self.trunk_edges)
        return tuple((self.size_class(*shape), share) for shape, share
                     in zip(shapes, self.SHARES) if shape != full)

    def size_class(self, leg_depth: int, knees: int, leg_edges: int, trunk_legs: int,
                   trunk_edges: int) -> SizeClass:
        """The bodies this space's template holds that also fit the smaller template of
        `Constructor(horizon, leg_depth, knees, leg_edges, trunk_legs, trunk_edges)`.


        The smaller template's tree is a subtree of this one's: its body b is this one's
        `body_map[b]` (the k-th leg slot of a body is the k-th leg slot of its image), and slots
        fill in node order in both, so a body that fits lands on the same limbs in both."""
        small = Constructor(self.horizon, leg_depth, knees, leg_edges, trunk_legs, trunk_edges)
        body_map = np.zeros(len(small.body_parent), int)
        for b in range(len(small.body_parent)):  # parents first
            if small.num_leg_slots[b] > self.num_leg_slots[body_map[b]]:
                raise ValueError(f"{small} is not a subtree of {self}")
            for k in range(small.num_leg_slots[b]):
                body_map[small.leg_slots[b, k]] = self.leg_slots[body_map[b], k]
        legs, edges = np.zeros((2, len(self.body_parent)), int)
        legs[body_map], edges[body_map] = small.num_leg_slots, small.num_edge_slots
        if (edges > self.num_edge_slots).any():
            raise ValueError(f"{small} is not a subtree of {self}")

        def fits(m: Morphology) -> jax.Array:
            _, _, used_legs, used_edges = self._assign(m)
            return jnp.all(used_legs <= legs) & jnp.all(used_edges <= edges)

        name = (f"leg_depth={leg_depth},knees={knees},leg_edges={leg_edges},"
                f"trunk_legs={trunk_legs},trunk_edges={trunk_edges}")
        return SizeClass(name, small, body_map[1:] - 1, fits)

    def initial(self) -> Morphology:
        n = self.max_nodes
        return Morphology(
            active=jnp.zeros(n, bool).at[0].set(True),
            parent=jnp.full(n, -1, jnp.int32),
            kind=jnp.zeros(n, jnp.int32),
            site=jnp.zeros(n, jnp.int32),
            attrs=jnp.zeros((n, 1), jnp.float32).at[0, 0].set(STICK_LENGTH),
        )

    def _assign(self, m: Morphology):
        """Where each node sits in the template, filling slots in node order.

        Returns:
          body: (max_nodes,) int32: the template body each node is part of (0 for the stick and
            the trunk's edges, its own slot for a leg, its leg's for an edge on a leg).
          geom: (max_nodes,) int32: the geom slot of each node's capsule (0 if inactive).
          legs: (B,) int32 leg slots filled in each body; edges: (B,) int32 edge slots filled.
        """
        leg_slots, edge_slots = jnp.asarray(self.leg_slots), jnp.asarray(self.edge_slots)
        num_bodies = len(self.body_parent)
        body = jnp.zeros(self.max_nodes, jnp.int32)
        geom = jnp.zeros(self.max_nodes, jnp.int32)
        legs = jnp.zeros(num_bodies, jnp.int32)
        edges = jnp.zeros(num_bodies, jnp.int32)
        for i in range(1, self.max_nodes):  # parents come first
            on = m.active[i]
            host = body[jnp.maximum(m.parent[i], 0)]
            is_leg = m.kind[i] == LEG
            slot = jnp.where(is_leg, legs[host], edges[host])
            leg_body = leg_slots[host, jnp.minimum(slot, leg_slots.shape[1] - 1)]
            edge_geom = edge_slots[host, jnp.minimum(slot, edge_slots.shape[1] - 1)]
            body = body.at[i].set(jnp.where(on, jnp.where(is_leg, leg_body, host), 0))
            leg_geom = jnp.asarray(self.leg_geom)[jnp.maximum(leg_body, 0)]
            geom = geom.at[i].set(jnp.where(on, jnp.where(is_leg, leg_geom, edge_geom), 0))
            legs = legs.at[host].add(on & is_leg)
            edges = edges.at[host].add(on & ~is_leg)
        return body, geom, legs, edges

    def action_mask(self, m: Morphology) -> jnp.ndarray:
        body, _, legs, edges = self._assign(m)
        leg_room = legs < jnp.asarray(self.num_leg_slots)  # (B,)
        edge_room = edges < jnp.asarray(self.num_edge_slots)
        room = jnp.where(
            jnp.asarray(SLOT_KIND)[None] == LEG, leg_room[body][:, None], edge_room[body][:, None]
        )
        return m.active[:, None] & (m.num_nodes < self.max_nodes) & room

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
    def plan(self) -> templates.BodyPlan:
        edge, leg, stick = (0.35, 0.55, 0.8, 1.0), (0.85, 0.5, 0.2, 1.0), (0.3, 0.45, 0.7, 1.0)
        is_leg = np.zeros(len(self.geom_body), bool)
        is_leg[self.leg_geom[1:]] = True
        return templates.BodyPlan(
            geom_names=self.geom_names,
            geom_body=tuple(int(b) for b in self.geom_body),
            geom_rgba=tuple(
                stick if g == 0 else (leg if is_leg[g] else edge)
                for g in range(len(self.geom_body))
            ),
            limb_nodes=tuple(
                range(1, len(self.body_parent))
            ),  # template slots, not morphology nodes
            limb_parent=tuple(int(p) for p in self.body_parent[1:]),
            joint_range=(-1.0, 1.0),
            gear=30.0,
        )

    def layout(self, m: Morphology) -> templates.Layout:
        n, num_bodies, num_geoms = self.max_nodes, len(self.body_parent), len(self.geom_body)
        body, geom, _, _ = self._assign(m)
        kind = jnp.where(m.active, m.kind, EDGE)
        length = jnp.where(m.active, m.attrs[:, 0], EDGE_LENGTH)
        end_slot = jnp.asarray(SLOT_END)[m.site]
        direction = jnp.asarray(SLOT_DIR)[m.site]
        leg_dir = jnp.array([-jnp.sin(LEG_INCLINE), 0.0, -jnp.cos(LEG_INCLINE)])
        x_axis = jnp.array([1.0, 0.0, 0.0])

        # END POINTS OF EVERY NODE IN THE TRUNK FRAME AT REST, parents first
        start = jnp.zeros((n, 3)).at[0, 0].set(-length[0] / 2)
        end = jnp.zeros((n, 3)).at[0, 0].set(length[0] / 2)
        for i in range(1, n):
            p = jnp.maximum(m.parent[i], 0)
            attach = jnp.where(end_slot[i] == 1, end[p], start[p])
            step = jnp.where(kind[i] == LEG, length[i] * leg_dir, x_axis * direction[i] * length[i])
            start, end = start.at[i].set(attach), end.at[i].set(attach + step)

        # BODY ORIGINS (a leg's at its hip) AND GEOMS, scattered from nodes to template slots
        is_leg = m.active & (kind == LEG)
        leg_body = jnp.where(is_leg, body, num_bodies)  # num_bodies: dropped by the scatter
        origin = jnp.zeros((num_bodies, 3)).at[leg_body].set(start, mode="drop")
        limb_active = jnp.zeros(num_bodies, bool).at[leg_body].set(True, mode="drop")
        # inactive geoms keep a valid capsule: a leg's own shape, or an edge along x
        rest_to = jnp.where(
            jnp.asarray(np.isin(np.arange(num_geoms), self.leg_geom[1:]))[:, None],
            LEG_LENGTH * leg_dir,
            EDGE_LENGTH * x_axis,
        )
        slot = jnp.where(m.active, geom, num_geoms)  # the stick is geom 0
        host_origin = origin[body]  # (n, 3): the origin of each node's body
        geom_active = jnp.zeros(num_geoms, bool).at[slot].set(True, mode="drop")
        geom_from = jnp.zeros((num_geoms, 3)).at[slot].set(start - host_origin, mode="drop")
        geom_to = rest_to.at[slot].set(end - host_origin, mode="drop")
        radius = jnp.where(
            kind == LEG, LEG_RADIUS, jnp.where(kind == STICK, STICK_RADIUS, EDGE_RADIUS)
        )
        geom_radius = (
            jnp.full(num_geoms, EDGE_RADIUS).at[jnp.asarray(self.leg_geom[1:])].set(LEG_RADIUS)
        )
        geom_radius = geom_radius.at[slot].set(radius, mode="drop")
        parent_origin = origin[jnp.asarray(self.body_parent[1:])]
        layout = templates.Layout(
            root_pos=jnp.zeros(3),
            limb_active=limb_active[1:],
            limb_pos=jnp.where(limb_active[1:, None], origin[1:] - parent_origin, 0.0),
            geom_active=geom_active,
            geom_from=geom_from,
            geom_to=geom_to,
            geom_radius=geom_radius,
        )
        height = CLEARANCE - templates.lowest_point(self.plan, layout)
        return layout.replace(root_pos=jnp.zeros(3).at[2].set(height))
