"""The 3D Crawler space: its mutations, its count of bodies, and its task on a free trunk."""

import json
from pathlib import Path

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import float64

import evojax_morph as em
from evojax_morph.spaces import crawler as cr
from evojax_morph.tasks import Body, Locomotion, make_task


@pytest.fixture(scope="module")
def space():
    return em.make_space("crawler")


def by_polynomial(horizon):
    """Bodies first reached after 0..horizon mutations, counted another way: a limb is 1
    mutation, 2 (its length or its axis changed) or 3 (both), in 1, 3 and 2 ways; a site holds
    0 to 3 limbs; the 6 sites are independent. The coefficients of (sum_k p^k)^6."""
    limb = np.array([0, 1, 3, 2])
    site, power = np.array([1]), np.array([1])
    for _ in range(cr.DEPTH):
        power = np.convolve(power, limb)
        site = np.pad(site, (0, len(power) - len(site))) + power
    body = np.array([1])
    for _ in range(cr.NUM_SITES):
        body = np.convolve(body, site)
    return body[: horizon + 1].tolist()


def test_reachable_counts_are_the_canonical_names(space):
    """`reachable_counts` (a numpy BFS over coded bodies) against `enumerate_bodies` (BFS over
    `mutate` by `canonical` name) to depth 3, and against the polynomial to depth 6."""
    _, depths = space.enumerate_bodies(3)
    assert cr.reachable_counts(3) == np.bincount(depths).tolist() == [1, 6, 39, 194]
    assert cr.reachable_counts(6) == by_polynomial(6)


@pytest.mark.slow
def test_a_million_bodies_within_the_horizon():
    """The README's count: 2,754,725 distinct bodies within 10 mutations (12 s)."""
    counts = cr.reachable_counts(10)
    assert counts == by_polynomial(10) and sum(counts) == 2_754_725


def test_crawler_near_keeps_the_bodies_within_reach(space):
    """`distance_from_m0` is each body's breadth-first depth (the 240 bodies within 3
    mutations), and `crawler_near` allows exactly the Crawler's mutations whose child lies
    within 4: 1,137 bodies in all, as `reachable_counts` counts them."""
    bodies, depths = space.enumerate_bodies(max_depth=3)
    batch = em.stack(bodies)
    np.testing.assert_array_equal(jax.vmap(cr.distance_from_m0)(batch), depths)
    near = em.make_space("crawler_near")
    nm = space.num_mutations

    def allowed(m):
        kids = jax.vmap(lambda a: space.mutate(m, a // nm, a % nm))(jnp.arange(space.num_actions))
        within = jax.vmap(cr.distance_from_m0)(kids) <= near.REACH
        return space.action_mask(m).reshape(-1) & within, near.action_mask(m).reshape(-1)

    want, got = jax.jit(jax.vmap(allowed))(batch)
    np.testing.assert_array_equal(got, want)
    assert sum(cr.reachable_counts(near.REACH)) == 1137


def test_mutations(space):
    m = space.mutate(space.initial(), 0, 3)  # a limb at the front right: slot 10
    assert space.format(m).splitlines()[1] == "└── 10: limb @ front_right (length=0.3, axis=0)"
    m = space.mutate(space.mutate(m, 10, cr.EXTEND), 11, cr.EXTEND)  # a chain of 3
    assert np.asarray(m.active)[[10, 11, 12]].all()
    assert np.asarray(m.attrs)[11:13, 1].tolist() == [1, 1]  # a knee lifts
    mask = np.asarray(space.action_mask(m))
    assert not mask[12, cr.EXTEND] and not mask[10, cr.REMOVE] and mask[12, cr.REMOVE]
    assert mask[0, cr.NOOP] and not mask[10, cr.NOOP] and not mask[0, 3]
    with pytest.raises(ValueError, match="'remove' is not allowed on node 10"):
        space.mutate(m, 10, cr.REMOVE)
    short = space.mutate(m, 11, cr.SHORTER)
    assert float(short.attrs[11, 0]) == pytest.approx(0.2)
    assert not np.asarray(space.action_mask(short))[11, cr.SHORTER]
    flipped = space.mutate(m, 10, cr.FLIP)
    assert float(flipped.attrs[10, 1]) == 1.0
    chex.assert_trees_all_equal(space.mutate(m, 0, cr.NOOP), m)
    chex.assert_trees_all_equal(jax.jit(space.mutate)(m, 10, cr.REMOVE), m)  # masked: no-op
    # removing the chain leaf by leaf gives back m0, slot for slot
    gone = space.mutate(space.mutate(space.mutate(m, 12, cr.REMOVE), 11, cr.REMOVE), 10, cr.REMOVE)
    chex.assert_trees_all_equal(gone, space.initial())
    assert float(space.predefined_fitness(m)) == 30.0  # 3 limbs, no mirrored pair


def test_hinge_axes_are_across_their_limbs(space):
    """Each slot's swing and lift axes are unit vectors perpendicular to the limb and to each
    other; the layout gives every limb its own."""
    for axes in (cr.SLOT_SWING, cr.SLOT_LIFT):
        np.testing.assert_allclose(np.linalg.norm(axes, axis=1), 1.0, atol=1e-12)
        np.testing.assert_allclose(np.sum(axes * cr.SLOT_DIR, 1), 0.0, atol=1e-12)
    np.testing.assert_allclose(np.sum(cr.SLOT_SWING * cr.SLOT_LIFT, 1), 0.0, atol=1e-12)
    m = space.mutate(space.mutate(space.initial(), 0, 0), 1, cr.FLIP)
    np.testing.assert_allclose(space.layout(m).limb_axis[0], cr.SLOT_LIFT[0], atol=1e-6)


def test_the_3d_task_on_a_free_trunk(space):
    """A body starts upright at its own height, whatever qpos0 its batch was made from; the
    episode ends when the trunk's up axis tilts past max_tilt or it sinks."""
    task = Locomotion(space, make_task("walk"))
    assert task.obs_size == 11 + 2 * 18
    m = space.mutate(space.mutate(space.initial(), 0, 1), 0, 4)  # middle legs
    body = Body(motors=m.active[1:], height=space.layout(m).root_pos[2])  # task.body's, uncompiled
    template = space.template  # qpos0 of the template's tallest body, not this one's
    qpos, qvel = task._perturb(jax.random.PRNGKey(0), body, jnp.asarray(template.qpos0),
                               jnp.zeros(template.nv))
    np.testing.assert_allclose(qpos[:7], [0, 0, float(body.height), 1, 0, 0, 0], atol=1e-7)
    obs = task._obs(body, qpos, qvel)
    assert obs.shape == (task.obs_size,) and float(obs[0]) == pytest.approx(float(body.height))

    def ends(turn, height):
        quat = jnp.array([np.cos(turn / 2), np.sin(turn / 2), 0, 0])  # about x
        q = qpos.at[2].set(height).at[3:7].set(quat)
        return bool(task._outcome(body, qpos, 0, jnp.zeros(task.action_size), q, qvel).terminated)

    h = float(body.height)
    assert not ends(0.9, h) and ends(1.1, h)  # max_tilt 1 rad, about any horizontal axis
    assert not ends(0.0, 0.75 * h) and ends(0.0, 0.65 * h)  # min_height 0.7


def test_the_budget_studys_bodies_are_those_its_data_name(space):
    """experiments/crawler_budget.py grows its bodies by mutations from m0: they are the bodies
    its data file names, the first is the actor-critic's best returned body of the 20,000-step
    comparison, and each is within the horizon (one mutation a limb)."""
    from experiments import crawler_budget

    data = json.loads(Path("docs/figures/crawler_budget.json").read_text())
    bodies = [crawler_budget.body(space, sites, limbs) for _, sites, limbs in crawler_budget.BODIES]
    assert [space.canonical(m) for m in bodies] == [b["body"] for b in data["bodies"]]
    a2c = json.loads(Path("docs/figures/reproduce_crawler/compare_a2c.json").read_text())
    assert max(a2c["returned"], key=lambda r: r["mean"])["body"] == space.canonical(bodies[0])
    limbs = [int(np.sum(m.active)) - 1 for m in bodies]
    assert limbs == [4, 4, 6, 8] and max(limbs) <= space.default_horizon


def test_the_valleys_bodies_are_m0_and_every_body_one_mutation_away(space):
    """experiments/crawler_valley.py's data file names m0 and each of its 6 one-limb children
    (a limb on each torso site), the bodies the space's mutations make from m0; every child
    scored below m0's lowest draw."""
    from experiments import crawler_valley

    data = json.loads(Path("docs/figures/crawler_valley.json").read_text())
    near = crawler_valley.neighbourhood(space)
    assert [b["body"] for b in data["bodies"]] == list(near)
    assert [int(np.sum(m.active)) for _, m in near.values()] == [1] + [2] * 6
    m0, *children = data["bodies"]
    assert max(max(c["values"]) for c in children) < min(m0["values"])


def test_size_classes_hold_the_bodies_of_shallow_chains(space):
    """The classes' templates hold chains of 1 and 2 limbs: a body fits a class exactly when
    its deepest limb is no deeper; a fitting body exports to the same unpadded MJCF from the
    class and from the full template, and the class's template specialised to it has the full
    one's masses, inertias, frames and joint axes body by body (by name); the class's limb
    slot j is the full template's `limbs[j]`."""
    keys = jax.random.split(jax.random.PRNGKey(3), 24)
    morphs = jax.vmap(space.random_morphology, (0, None))(keys, 10)
    deepest = np.max(np.where(np.asarray(morphs.active[:, 1:]), cr.SLOT_DEPTH, 0), axis=1)
    full = jax.jit(space.mjx_model)
    fields = ("body_mass", "body_inertia", "body_ipos", "body_iquat", "body_pos", "body_quat")
    assert [c.name for c, _ in space.size_classes()] == ["depth=1", "depth=2"]
    for depth, (size_class, _) in enumerate(space.size_classes(), start=1):
        small = size_class.space
        fits = np.asarray(jax.vmap(size_class.fits)(morphs))
        np.testing.assert_array_equal(fits, deepest <= depth)
        assert [space.plan.actuator_names[j] for j in size_class.limbs] == list(
            small.plan.actuator_names)
        inside = jax.vmap(small.random_morphology, (0, None))(keys[:8], 10)  # walks of the
        assert bool(jax.vmap(size_class.fits)(inside).all())  # class's own space fit it
        m = em.unstack(morphs)[int(np.flatnonzero(fits & (deepest == depth))[0])]
        assert small.to_mjcf(m) == space.to_mjcf(m)
        got, want = jax.jit(small.mjx_model)(m), full(m)
        names = [small.template.body(b).name for b in range(small.template.nbody)]
        rows = [space.template.body(n).id for n in names]
        for f in fields:
            np.testing.assert_allclose(getattr(got, f), np.asarray(getattr(want, f))[rows],
                                       atol=1e-6, err_msg=f)
        np.testing.assert_allclose(got.jnt_axis, np.asarray(want.jnt_axis)[
            [space.template.joint(small.template.joint(j).name).id
             for j in range(small.template.njnt)]], atol=1e-6)


def test_a_float32_template_after_a_float64_block():
    """A body laid out in float64 (conftest's `float64`, as tests/test_physics.py exports it)
    leaves the next float32 work intact: a new space's template (laid out eagerly, with the same
    numpy slot constants) builds and lays out in float32. Without the cleared caches, jax 0.10
    failed here (RuntimeProgramInputMismatch: an f64 buffer for an f32 parameter)."""
    with float64():
        wide = em.make_space("crawler").host_layout(em.make_space("crawler").initial())
    fresh = em.make_space("crawler", horizon=3)
    assert fresh.template.nbody > 1
    assert wide.geom_to.dtype == np.float64
    assert fresh.layout(fresh.initial()).geom_to.dtype == jnp.float32
