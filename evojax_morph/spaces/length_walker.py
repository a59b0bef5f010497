"""Length Walker: a trunk on two feet whose mutations move a foot or change its length in steps.

The worked example of adding a space (README, "Adding a space"): one module defining the
initial body, the action mask, the mutation, the predefined fitness, the static `BodyPlan` of
the padded template and the per-morphology `Layout`, registered by name in `spaces/__init__.py`.
"""

from __future__ import annotations

import functools

import jax.numpy as jnp
import numpy as np

from evojax_morph.morphology import Morphology
from evojax_morph.physics import templates
from evojax_morph.spaces.base import Space

TRUNK_LENGTH = 1.0  # m
TRUNK_RADIUS, FOOT_RADIUS = 0.05, 0.04
CLEARANCE = 0.005  # m between the lowest point and the floor at reset
# The 4 trunk locations a foot can move to, back end to front end.
SITE_X = np.array([-1.0, -1.0 / 3.0, 1.0 / 3.0, 1.0]) * TRUNK_LENGTH / 2
# The foot lengths a foot can take: a lengthen or shorten mutation moves one step along them.
LENGTHS = np.array([0.1, 0.2, 0.3, 0.4], np.float32)  # m
START_LENGTH, BEST_LENGTH = 3, 1  # indices into LENGTHS: m0's feet, m*'s feet
BACK, FRONT = 1, 2  # node ids of the feet
LENGTHEN, SHORTEN = 4, 5  # mutation ids; 0..3 move a foot to SITE_X[mutation]
# Predefined fitness weights.
W_CLOSE, W_LENGTH = 0.5, 0.25


class LengthWalker(Space):
    """A planar trunk (node 0, 1 m) with a back foot (node 1) and a front foot (node 2).

    Mutations of a foot: move it to one of 4 trunk locations (both ends included), lengthen it
    or shorten it by one step of 0.1 m within 0.1 to 0.4 m (a length change at a bound is
    masked). Every mutation of the root is a valid no-op, as is moving a foot where it is.
    m0 stands on two 0.4 m feet at the inner locations; m* has 0.2 m feet at the two ends.
    Capacity 3 nodes; every body has both feet (nothing is ever removed), so the template has
    no inactive slot: only numeric fields (foot positions and lengths) vary.

    Observation (of the evolution MDP): the morphology, its action mask (3 x 6) and progress.
    Action: (node, mutation), mutation in to_back_end, to_back_inner, to_front_inner,
      to_front_end, lengthen, shorten.
    Reward: the change in fitness. Episodes last `default_horizon` = 8 mutations: m* is 6 from
      m0 (two moves, two shortenings of each foot), leaving 2 steps in which to hold it.

    Predefined fitness: for each foot, 0.5 x closeness (1 - distance / trunk length) to its own
    end of the trunk (the back foot's is the back end), minus 0.25 per length step away from
    0.2 m. m* scores 1, the unique maximum over the 256 bodies (4 sites x 4 lengths per foot),
    since each foot's term peaks at its own end and 0.2 m alone; m0 scores -1/3.
    """

    name = "length_walker"
    kind_names = ("trunk", "back_foot", "front_foot")
    site_names = ("back_end", "back_inner", "front_inner", "front_end")
    mutation_names = (
        "to_back_end", "to_back_inner", "to_front_inner", "to_front_end", "lengthen", "shorten"
    )
    attr_names = ("length",)
    fitness_scale = 1.0  # typical magnitude of the predefined fitness
    max_nodes = 3
    default_horizon = 8

    def initial(self) -> Morphology:
        foot = float(LENGTHS[START_LENGTH])
        return Morphology(
            active=jnp.ones(3, bool),
            parent=jnp.array([-1, 0, 0], jnp.int32),
            kind=jnp.array([0, 1, 2], jnp.int32),
            site=jnp.array([0, 1, 2], jnp.int32),
            attrs=jnp.array([[TRUNK_LENGTH], [foot], [foot]], jnp.float32),
        )

    def optimum(self) -> Morphology:
        """m*: 0.2 m feet at the two ends of the trunk."""
        m = self.mutate(self.mutate(self.initial(), BACK, 0), FRONT, 3)
        for _ in range(START_LENGTH - BEST_LENGTH):
            m = self.mutate(self.mutate(m, BACK, SHORTEN), FRONT, SHORTEN)
        return m

    def _length_index(self, m: Morphology) -> jnp.ndarray:
        """(max_nodes,) int32: each node's step in LENGTHS (meaningless for the trunk)."""
        return jnp.argmin(jnp.abs(m.attrs[:, :1] - jnp.asarray(LENGTHS)[None]), -1)

    def action_mask(self, m: Morphology) -> jnp.ndarray:
        step = self._length_index(m)
        foot = jnp.arange(self.max_nodes) > 0
        mask = jnp.ones((self.max_nodes, self.num_mutations), bool)
        mask = mask.at[:, LENGTHEN].set(~foot | (step < len(LENGTHS) - 1))
        return mask.at[:, SHORTEN].set(~foot | (step > 0))

    def _apply(self, m: Morphology, node, mutation) -> Morphology:
        is_foot = node > 0
        move = is_foot & (mutation < LENGTHEN)
        change = jnp.where(mutation == LENGTHEN, 1, jnp.where(mutation == SHORTEN, -1, 0)) * is_foot
        step = jnp.clip(self._length_index(m)[node] + change, 0, len(LENGTHS) - 1)
        length = jnp.where(is_foot, jnp.asarray(LENGTHS)[step], m.attrs[node, 0])
        return m.replace(
            site=m.site.at[node].set(jnp.where(move, mutation, m.site[node])),
            attrs=m.attrs.at[node, 0].set(length),
        )

    def predefined_fitness(self, m: Morphology) -> jnp.ndarray:
        x = jnp.asarray(SITE_X, jnp.float32)[m.site]
        own_end = jnp.asarray([0.0, SITE_X[0], SITE_X[-1]], jnp.float32)
        close = 1.0 - jnp.abs(x - own_end) / TRUNK_LENGTH
        off = jnp.abs(self._length_index(m) - BEST_LENGTH).astype(jnp.float32)
        return jnp.sum((W_CLOSE * close - W_LENGTH * off)[1:])

    @functools.cached_property
    def plan(self) -> templates.BodyPlan:
        trunk, foot = (0.35, 0.55, 0.8, 1.0), (0.85, 0.5, 0.2, 1.0)
        return templates.BodyPlan(
            geom_names=("geom0", "geom1", "geom2"),
            geom_body=(0, 1, 2),
            geom_rgba=(trunk, foot, foot),
            limb_nodes=(1, 2),
            limb_parent=(0, 0),
        )

    def layout(self, m: Morphology) -> templates.Layout:
        length = m.attrs[1:, 0]
        x = jnp.asarray(SITE_X)[m.site[1:]]
        zeros2 = jnp.zeros(2)
        half = TRUNK_LENGTH / 2
        layout = templates.Layout(
            root_pos=jnp.zeros(3),
            limb_active=m.active[1:],
            limb_pos=jnp.stack([x, zeros2, zeros2], -1),  # a foot's hinge sits on the trunk's axis
            geom_active=m.active,
            geom_from=jnp.zeros((3, 3)).at[0, 0].set(-half),
            geom_to=jnp.concatenate(
                [jnp.array([[half, 0.0, 0.0]]), jnp.stack([zeros2, zeros2, -length], -1)]
            ),
            geom_radius=jnp.array([TRUNK_RADIUS, FOOT_RADIUS, FOOT_RADIUS]),
        )
        height = CLEARANCE - templates.lowest_point(self.plan, layout)
        return layout.replace(root_pos=jnp.zeros(3).at[2].set(height))
