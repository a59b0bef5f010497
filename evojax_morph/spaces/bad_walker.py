"""Bad Walker: a planar trunk that starts on a long middle foot and two short feet."""

from __future__ import annotations

import functools

import jax.numpy as jnp
import numpy as np

from evojax_morph.morphology import Morphology
from evojax_morph.physics import templates
from evojax_morph.spaces.base import Space

TRUNK_LENGTH = 1.0
LONG_FOOT, SHORT_FOOT = 0.5, 0.2  # foot lengths, m
TRUNK_RADIUS, FOOT_RADIUS = 0.05, 0.04
CLEARANCE = 0.005  # m between the lowest point and the floor at reset
# Attachment x on the trunk: the 4 locations a mutation can pick (ends included), then the
# middle, which only the long foot of m0 occupies.
SITE_X = np.array([-1.0, -1.0 / 3.0, 1.0 / 3.0, 1.0, 0.0]) * TRUNK_LENGTH / 2
MIDDLE = 4
REMOVE = 4  # the mutation that removes a foot
LONG, BACK, FRONT = 1, 2, 3  # node ids of the feet
# Predefined fitness weights.
W_LONG_REMOVED, W_SHORT_REMOVED, W_CLOSE = 1.0, 1.0, 0.5


class BadWalker(Space):
    """A planar trunk (node 0) with three feet: long (node 1), back short (2), front short (3).

    Mutations of a foot move it to one of the 4 trunk locations or remove it for good; every
    mutation of the root is a valid no-op, as is moving a foot where it already is. m0 balances
    on the long middle foot with both short feet off the ground; m* (long foot removed, short
    feet at the two ends) walks.

    Predefined fitness: +1 if the long foot is removed, -1 per removed short foot, plus 0.5 x
    closeness (1 - distance / trunk length) of each short foot to its own end of the trunk.
    m* scores 2, the unique maximum.

    Episodes last `default_horizon` = 5 mutations: m* is 3 mutations from m0, so an agent that
    reaches it has 2 steps left in which holding it (a no-op: any root mutation, or moving a foot
    where it is) is the best it can do, as in the source's account of Bad Walker.
    """

    name = "bad_walker"
    kind_names = ("trunk", "long_foot", "short_foot")
    site_names = ("back_end", "back_inner", "front_inner", "front_end", "middle")
    mutation_names = ("to_back_end", "to_back_inner", "to_front_inner", "to_front_end", "remove")
    attr_names = ("length",)
    fitness_scale = 1.0  # typical magnitude of the predefined fitness
    max_nodes = 4
    default_horizon = 5  # m* is 3 mutations away: 2 more steps show whether it is held

    def initial(self) -> Morphology:
        return Morphology(
            active=jnp.ones(4, bool),
            parent=jnp.array([-1, 0, 0, 0], jnp.int32),
            kind=jnp.array([0, 1, 2, 2], jnp.int32),
            site=jnp.array([0, MIDDLE, 1, 2], jnp.int32),
            attrs=jnp.array([[TRUNK_LENGTH], [LONG_FOOT], [SHORT_FOOT], [SHORT_FOOT]], jnp.float32),
        )

    def optimum(self) -> Morphology:
        """m*: long foot removed, short feet at the two ends of the trunk."""
        m = self.initial()
        m = self.mutate(m, LONG, REMOVE)
        m = self.mutate(m, BACK, 0)
        return self.mutate(m, FRONT, 3)

    def action_mask(self, m: Morphology) -> jnp.ndarray:
        rows = m.active.at[0].set(True)  # the root's mutations are no-ops, always allowed
        return jnp.broadcast_to(rows[:, None], (self.max_nodes, self.num_mutations))

    def _apply(self, m: Morphology, node, mutation) -> Morphology:
        is_foot = node > 0
        remove = is_foot & (mutation == REMOVE)
        move = is_foot & (mutation < REMOVE)
        return Morphology(
            active=m.active.at[node].set(m.active[node] & ~remove),
            parent=m.parent.at[node].set(jnp.where(remove, -1, m.parent[node])),
            kind=m.kind.at[node].set(jnp.where(remove, 0, m.kind[node])),
            site=m.site.at[node].set(jnp.where(move, mutation, jnp.where(remove, 0, m.site[node]))),
            attrs=m.attrs.at[node].set(jnp.where(remove, 0.0, m.attrs[node])),
        )

    def predefined_fitness(self, m: Morphology) -> jnp.ndarray:
        x = jnp.asarray(SITE_X, jnp.float32)[m.site]
        back_close = 1.0 - jnp.abs(x[BACK] - SITE_X[0]) / TRUNK_LENGTH
        front_close = 1.0 - jnp.abs(x[FRONT] - SITE_X[3]) / TRUNK_LENGTH
        return (
            W_LONG_REMOVED * (~m.active[LONG])
            - W_SHORT_REMOVED * ((~m.active[BACK]).astype(jnp.float32) + ~m.active[FRONT])
            + W_CLOSE * (m.active[BACK] * back_close + m.active[FRONT] * front_close)
        )

    @functools.cached_property
    def plan(self) -> templates.BodyPlan:
        trunk, foot = (0.35, 0.55, 0.8, 1.0), (0.85, 0.5, 0.2, 1.0)
        return templates.BodyPlan(
            geom_names=("geom0", "geom1", "geom2", "geom3"),
            geom_body=(0, 1, 2, 3),
            geom_rgba=(trunk, foot, foot, foot),
            limb_nodes=(1, 2, 3),
            limb_parent=(0, 0, 0),
            joint_range=(-1.0, 1.0),
            gear=30.0,
        )

    def layout(self, m: Morphology) -> templates.Layout:
        length = m.attrs[:, 0]
        x = jnp.asarray(SITE_X)[m.site[1:]]
        zeros = jnp.zeros(3)
        feet_to = jnp.stack([jnp.zeros(3), jnp.zeros(3), -length[1:]], -1)
        half = TRUNK_LENGTH / 2
        layout = templates.Layout(
            root_pos=zeros,
            limb_active=m.active[1:],
            limb_pos=jnp.stack([x, jnp.zeros(3), jnp.zeros(3)], -1),
            geom_active=m.active,
            geom_from=jnp.zeros((4, 3)).at[0, 0].set(-half),
            geom_to=jnp.concatenate([jnp.array([[half, 0.0, 0.0]]), feet_to]),
            geom_radius=jnp.array([TRUNK_RADIUS, FOOT_RADIUS, FOOT_RADIUS, FOOT_RADIUS]),
        )
        height = CLEARANCE - templates.lowest_point(self.plan, layout)
        return layout.replace(root_pos=zeros.at[2].set(height))
