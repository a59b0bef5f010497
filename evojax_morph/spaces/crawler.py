"""Crawler: a 3D space of legged bodies grown limb by limb on a torso free in 3D."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from evojax_morph.morphology import Morphology
from evojax_morph.physics import templates
from evojax_morph.spaces.base import SizeClass, Space

TORSO_HALF, TORSO_RADIUS, LIMB_RADIUS = 0.2, 0.08, 0.04  # m
LENGTHS = (0.2, 0.3, 0.4)  # m: the lengths a limb may take; a new limb takes the middle one
DEPTH = 3  # limbs in a chain from the torso to a foot, at most
CLEARANCE = 0.005  # m between the lowest point and the floor at reset
SITE_X = (TORSO_HALF, 0.0, -TORSO_HALF)  # front, middle, back, on each side
SPLAY = (0.5, 0.0, -0.5)  # the x part of a chain's heading: front legs reach forward
DROP = (0.5, 1.2, 1.45)  # rad below the horizontal of a limb at depth 1, 2, 3
SWING, LIFT = 0, 1  # a hinge's axis: swings its limb forward and back, or lifts it
TORSO, LIMB = 0, 1  # node kinds
NUM_SITES = 6
ADD = tuple(range(NUM_SITES))  # mutations 0..5: a limb at torso site s
EXTEND, REMOVE, SHORTER, LONGER, FLIP, NOOP = range(NUM_SITES, NUM_SITES + 6)


def _slots():
    """Static geometry of the 18 limb slots: slot 1 + 3 s + d - 1 is the limb at depth d of the
    chain from torso site s, so a body's tree is the template's, slot for slot."""
    site, depth, start, direction, swing, lift = [], [], [], [], [], []
    for s in range(NUM_SITES):
        row, side = s % 3, 1.0 if s < 3 else -1.0  # sites 0-2 on the left (+y), 3-5 right
        heading = np.array([SPLAY[row], side, 0.0]) / np.hypot(SPLAY[row], 1.0)
        lift_axis = np.cross(heading, [0.0, 0.0, 1.0])  # horizontal, across the heading
        for d in range(DEPTH):
            dirn = np.cos(DROP[d]) * heading - np.sin(DROP[d]) * np.array([0.0, 0.0, 1.0])
            site.append(s)
            depth.append(d + 1)
            start.append([SITE_X[row], side * TORSO_RADIUS, 0.0] if d == 0 else [0.0] * 3)
            direction.append(dirn)
            lift.append(lift_axis)
            swing.append(np.cross(lift_axis, dirn))  # in the limb's vertical plane
    return (np.array(site), np.array(depth), np.array(start), np.array(direction),
            np.array(swing), np.array(lift))


SLOT_SITE, SLOT_DEPTH, SLOT_START, SLOT_DIR, SLOT_SWING, SLOT_LIFT = _slots()
MAX_NODES = 1 + NUM_SITES * DEPTH
# the parent of each slot: the torso for a chain's first limb, else the limb above it
SLOT_PARENT = np.array([0 if d == 1 else 1 + k - 1 for k, d in enumerate(SLOT_DEPTH)])
DEFAULT_AXIS = np.where(SLOT_DEPTH == 1, SWING, LIFT)  # a hip swings, a knee lifts
# each node's child slot (the limb on its tip), and whether it has one (not the torso, not a
# limb at the greatest depth)
CHILD = np.r_[0, np.minimum(np.arange(2, MAX_NODES + 1), MAX_NODES - 1)]
HAS_CHILD_SLOT = np.r_[False, SLOT_DEPTH < DEPTH]


class Crawler(Space):
    """A torso free in 3D (a capsule along x) with 6 limb sites, and chains of up to 3 limbs.

    Sites: front, middle and back of the torso, on its left (+y) and right (-y). A chain's
    first limb leaves its site outward (front legs splayed forward, back legs backward) and
    0.5 rad down; a second limb hangs from its tip 1.2 rad down, a third 1.45 rad down. Every
    limb is a capsule (radius 4 cm) of length 0.2, 0.3 or 0.4 m with one actuated hinge at its
    start, whose axis either swings the limb forward and back (in the limb's vertical plane, the
    default for a first limb) or lifts it (across its heading, the default deeper down).

    Mutations (12), on node n: `add_<site>` (the torso only: a limb at an empty site),
    `extend` (a limb at the tip of limb n, up to `depth`: 3), `remove` (a limb with nothing on
    its tip), `shorter` and `longer` (limb n's length one step), `flip_axis` (limb n's hinge
    between swing and lift), `noop` (the torso only). Node slots are fixed (slot 1 + 3 s + d - 1
    is the limb at depth d of site s's chain), so the template's tree is every body's.

    Bodies within the default horizon of 10 mutations: 2,754,725 distinct (`reachable_counts`).
    Observation (of the evolution MDP): the morphology, its action mask (19 x 12), progress.
    Predefined fitness: 100 per pair of mirrored sites both holding a chain, plus 10 per limb:
    a body standing on both sides scores (max 400 within 10 mutations).
    """

    name = "crawler"
    kind_names = ("torso", "limb")
    site_names = ("front_left", "middle_left", "back_left", "front_right", "middle_right",
                  "back_right", "tip")
    mutation_names = tuple(f"add_{s}" for s in site_names[:NUM_SITES]) + (
        "extend", "remove", "shorter", "longer", "flip_axis", "noop")
    attr_names = ("length", "axis")
    fitness_scale = 100.0
    max_nodes = MAX_NODES

    # Size classes (`evojax_morph.physics.classes`): chains of one limb, then of two, then the full
    # template (7, 13 and 19 bodies; 12, 18 and 24 dofs). Of 20,000 random 10-mutation bodies
    # (a horizon's end: the deepest mix) 38.6% fit the first, 49.0% the second (and not the
    # first), 12.4% only the full template; with these shares a batch of 256 to 4,096 such
    # bodies overflowed none of 400 draws (64: 6, 16: 55, which then train on the full
    # template). Per world the classes cost about 0.83 of the full template's dofs.
    SHARES = (0.4, 0.5, 0.25)

    def __init__(self, horizon: int = 10, depth: int = DEPTH):
        """depth < 3: chains of at most `depth` limbs (`extend` masked below), on a template of
        those slots alone, nodes numbered as in the full space: a size class's space."""
        if horizon < 1:
            raise ValueError(f"horizon must be at least 1, got {horizon}")
        if not 1 <= depth <= DEPTH:
            raise ValueError(f"depth must be 1 to {DEPTH}, got {depth}")
        self.default_horizon = horizon
        self.depth = depth
        self._limbs = np.flatnonzero(SLOT_DEPTH <= depth)  # the template's limb slots

    @functools.cache  # noqa: B019  (spaces live as long as the process)
    def size_classes(self) -> tuple[tuple[SizeClass, float], ...]:
        found = []
        for depth, share in zip(range(1, self.depth), self.SHARES):
            deeper = jnp.asarray(np.r_[False, SLOT_DEPTH > depth])
            small = Crawler(self.default_horizon, depth)
            found.append((SizeClass(f"depth={depth}", small, small._limbs,
                                    lambda m, deeper=deeper: ~jnp.any(m.active & deeper)), share))
        return tuple(found)

    def initial(self) -> Morphology:
        n = self.max_nodes
        return Morphology(
            active=jnp.zeros(n, bool).at[0].set(True),
            parent=jnp.full(n, -1, jnp.int32),
            kind=jnp.zeros(n, jnp.int32),
            site=jnp.zeros(n, jnp.int32),
            attrs=jnp.zeros((n, 2), jnp.float32).at[0, 0].set(2 * TORSO_HALF),
        )

    def action_mask(self, m: Morphology) -> jax.Array:
        limb = m.active.at[0].set(False)
        leaf = limb & ~(m.active[CHILD] & HAS_CHILD_SLOT)
        can_extend = leaf & HAS_CHILD_SLOT & (np.r_[0, SLOT_DEPTH] < self.depth)
        length = m.attrs[:, 0]
        mask = jnp.zeros((MAX_NODES, self.num_mutations), bool)
        first = 1 + 3 * np.arange(NUM_SITES)
        mask = mask.at[0, :NUM_SITES].set(~m.active[first])
        mask = mask.at[:, EXTEND].set(can_extend)
        mask = mask.at[:, REMOVE].set(leaf)
        mask = mask.at[:, SHORTER].set(limb & (length > LENGTHS[0] + 1e-6))
        mask = mask.at[:, LONGER].set(limb & (length < LENGTHS[-1] - 1e-6))
        mask = mask.at[:, FLIP].set(limb)
        return mask.at[0, NOOP].set(True)

    def _apply(self, m: Morphology, node, mutation) -> Morphology:
        dtype = m.attrs.dtype
        is_add = mutation < NUM_SITES
        new = jnp.where(is_add, 1 + 3 * jnp.minimum(mutation, NUM_SITES - 1), node + 1)
        new = jnp.minimum(new, MAX_NODES - 1)
        slot_axis = jnp.asarray(np.r_[0, DEFAULT_AXIS], dtype)
        grown = Morphology(
            active=m.active.at[new].set(True),
            parent=m.parent.at[new].set(jnp.where(is_add, 0, node).astype(jnp.int32)),
            kind=m.kind.at[new].set(LIMB),
            site=m.site.at[new].set(jnp.where(is_add, mutation, NUM_SITES).astype(jnp.int32)),
            attrs=m.attrs.at[new].set(jnp.stack([jnp.asarray(LENGTHS[1], dtype),
                                                  slot_axis[new]])),
        )
        removed = Morphology(
            active=m.active.at[node].set(False), parent=m.parent.at[node].set(-1),
            kind=m.kind.at[node].set(0), site=m.site.at[node].set(0),
            attrs=m.attrs.at[node].set(0.0),
        )
        step = jnp.where(mutation == SHORTER, -1, 1)
        lengths = jnp.asarray(LENGTHS, dtype)
        index = jnp.argmin(jnp.abs(lengths - m.attrs[node, 0]))
        resized = m.replace(attrs=m.attrs.at[node, 0].set(lengths[jnp.clip(index + step, 0, 2)]))
        flipped = m.replace(attrs=m.attrs.at[node, 1].set(1 - m.attrs[node, 1]))
        choice = jnp.select(
            [is_add | (mutation == EXTEND), mutation == REMOVE,
             (mutation == SHORTER) | (mutation == LONGER), mutation == FLIP],
            [0, 1, 2, 3], 4)
        return jax.tree.map(lambda *x: jnp.stack(x)[choice], grown, removed, resized, flipped, m)

    def predefined_fitness(self, m: Morphology) -> jax.Array:
        chains = m.active[1 + 3 * np.arange(NUM_SITES)]
        pairs = jnp.sum(chains[:3] & chains[3:])
        limbs = jnp.sum(m.active) - 1
        return (100.0 * pairs + 10.0 * limbs).astype(jnp.float32)

    @functools.cached_property
    def plan(self) -> templates.BodyPlan:
        torso, limb = (0.3, 0.45, 0.7, 1.0), (0.85, 0.5, 0.2, 1.0)
        nodes = self._limbs + 1  # the template's body k + 1 is the morphology's node nodes[k]
        body_of = {0: 0, **{int(n): k + 1 for k, n in enumerate(nodes)}}
        return templates.BodyPlan(
            geom_names=("geom0",) + tuple(f"geom{i}" for i in nodes),
            geom_body=tuple(range(len(nodes) + 1)),
            geom_rgba=(torso,) + (limb,) * len(nodes),
            limb_nodes=tuple(int(n) for n in nodes),
            limb_parent=tuple(body_of[int(p)] for p in SLOT_PARENT[self._limbs]),
            joint_range=(-1.0, 1.0),
            gear=30.0,
            root="free",
            cone="elliptic",
        )

    def layout(self, m: Morphology) -> templates.Layout:
        limb = m.active[1:]
        length = jnp.where(limb, m.attrs[1:, 0], LENGTHS[1])  # inactive slots: a valid limb
        vector = length[:, None] * SLOT_DIR  # (18, 3): each limb from its hinge to its tip
        # a first limb's hinge is at its site on the torso, a deeper one's at its parent's tip
        limb_pos = jnp.where((SLOT_DEPTH == 1)[:, None], SLOT_START,
                             vector[np.maximum(SLOT_PARENT - 1, 0)])
        axis = jnp.where(limb, m.attrs[1:, 1], DEFAULT_AXIS)
        torso_from = jnp.array([[-TORSO_HALF, 0.0, 0.0]])
        limbs, geoms = self._limbs, np.r_[0, self._limbs + 1]  # the template's slots
        layout = templates.Layout(
            root_pos=jnp.zeros(3),
            limb_active=limb[limbs],
            limb_pos=limb_pos[limbs],
            geom_active=m.active[geoms],
            geom_from=jnp.concatenate([torso_from, jnp.zeros((MAX_NODES - 1, 3))])[geoms],
            geom_to=jnp.concatenate([-torso_from, vector])[geoms],
            geom_radius=jnp.full(MAX_NODES, LIMB_RADIUS).at[0].set(TORSO_RADIUS)[geoms],
            limb_axis=jnp.where((axis == LIFT)[:, None], SLOT_LIFT, SLOT_SWING)[limbs],
        )
        height = CLEARANCE - templates.lowest_point(self.plan, layout)
        return layout.replace(root_pos=jnp.zeros(3).at[2].set(height))


def distance_from_m0(m: Morphology) -> jax.Array:
    """() int32: the fewest mutations that grow `m` from m0: per limb one to add it, one per
    length step from the middle length, one if its hinge is not its slot's default. No mutation
    but `remove` raises this by more than one, and `remove` lowers it, so no shorter path exists."""
    length = jnp.argmin(jnp.abs(m.attrs[1:, :1] - jnp.asarray(LENGTHS)), axis=1)
    flipped = m.attrs[1:, 1] != DEFAULT_AXIS
    cost = 1 + jnp.abs(length - 1) + flipped
    return jnp.sum(jnp.where(m.active[1:], cost, 0)).astype(jnp.int32)


class CrawlerNear(Crawler):
    """The Crawler's bodies within `REACH` (4) mutations of m0: 1,137 bodies, few enough for a
    landscape table (`experiments.build_tables --space crawler_near`).

    The Crawler's physics, mutations and m0; a mutation is valid only where the child stays
    within reach (`distance_from_m0`), so every body an agent meets is one of the 1,137
    (`reachable_counts(4)`: 1, 6, 39, 194 and 897 at 0 to 4 mutations).
    """

    name = "crawler_near"
    REACH = 4

    def action_mask(self, m: Morphology) -> jax.Array:
        mask = super().action_mask(m)
        distance = distance_from_m0(m)
        length = jnp.argmin(jnp.abs(m.attrs[:, :1] - jnp.asarray(LENGTHS)), axis=1)
        # the change of the distance per (node, mutation): + 1 to grow, a step away from the
        # middle length or off the default hinge, - 1 back; remove and noop never leave
        off_default = m.attrs[:, 1] != np.r_[0, DEFAULT_AXIS]
        change = jnp.zeros((MAX_NODES, self.num_mutations), jnp.int32)
        change = change.at[:, : NUM_SITES].set(1).at[:, EXTEND].set(1)
        change = change.at[:, SHORTER].set(jnp.where(length <= 1, 1, -1))
        change = change.at[:, LONGER].set(jnp.where(length >= 1, 1, -1))
        change = change.at[:, FLIP].set(jnp.where(off_default, -1, 1))
        return mask & (distance + change <= self.REACH)


def reachable_counts(horizon: int) -> list[int]:
    """Distinct Crawler bodies first reached after 0, 1, ..., `horizon` mutations from m0.

    Breadth first over every body, by a code that names a body exactly as `Space.canonical`
    does (tests/test_crawler.py checks both against `enumerate_bodies`): a body is its 6
    chains, a chain its limbs' (length, axis) from the torso down, coded as one digit of base
    259 (no limb, or 1 to 3 limbs of 6 kinds each).
    """
    kinds = 2 * len(LENGTHS)  # a limb's (length, axis): length index x 2 + axis
    chains = [()] + [c for n in range(1, DEPTH + 1) for c in np.ndindex(*(kinds,) * n)]
    code = {c: i for i, c in enumerate(chains)}
    neighbours = []  # neighbours[i]: the chains one mutation from chain i
    for c in chains:
        out = set()
        if len(c) < DEPTH:  # add (the empty chain) or extend (a chain's last limb)
            default_axis = SWING if not c else LIFT
            out.add(code[c + (2 * 1 + default_axis,)])
        if c:
            out.add(code[c[:-1]])  # remove the leaf
        for k, kind in enumerate(c):
            size, axis = divmod(kind, 2)
            for new in (size - 1, size + 1):
                if 0 <= new < len(LENGTHS):
                    out.add(code[c[:k] + (2 * new + axis,) + c[k + 1:]])
            out.add(code[c[:k] + (2 * size + 1 - axis,) + c[k + 1:]])
        neighbours.append(sorted(out))
    base = len(chains)
    seen = frontier = np.zeros(1, np.int64)
    counts = [1]
    for _ in range(horizon):
        digits = (frontier[:, None] // base ** np.arange(NUM_SITES)) % base  # (F, 6)
        children = []
        for s in range(NUM_SITES):
            for d in range(max(map(len, neighbours))):
                new = np.array([n[d] if d < len(n) else -1 for n in neighbours])[digits[:, s]]
                ok = new >= 0
                children.append(frontier[ok] + (new[ok] - digits[ok, s]) * base**s)
        frontier = np.setdiff1d(np.concatenate(children), seen)  # sorted, each once
        seen = np.union1d(seen, frontier)
        counts.append(len(frontier))
    return counts
