
import chex
import jax
import numpy as np
import pytest

import evojax_morph as em
from evojax_morph.spaces import bad_walker as bw
from evojax_morph.spaces import constructor as cs
from evojax_morph.spaces import length_walker as lw


def reachable(space, max_depth=10):
    """Every morphology reachable from m0, by breadth-first search over valid actions (one
    body and one action at a time, jitted: eagerly, Bad Walker's 150 took half a minute)."""
    action_mask, mutate = jax.jit(space.action_mask), jax.jit(space.mutate)
    seen = {space.to_json(space.initial()): space.initial()}
    frontier = [space.initial()]
    for _ in range(max_depth):
        nxt = []
        for m in frontier:
            mask = np.asarray(action_mask(m))
            for node, mutation in zip(*np.nonzero(mask)):
                child = jax.device_get(mutate(m, node, mutation))
                key = space.to_json(child)
                if key not in seen:
                    seen[key] = child
                    nxt.append(child)
        frontier = nxt
    return list(seen.values())


def test_registry():
    assert em.list_spaces() == ["bad_walker", "constructor", "crawler", "crawler_near",
                               "length_walker"]
    with pytest.raises(ValueError, match="unknown space 'nope'.*bad_walker"):
        em.make_space("nope")


def test_random_morphologies_are_valid_trees(space):
    for seed in range(10):
        m = space.random_morphology(jax.random.PRNGKey(seed), 6)
        active, parent = np.asarray(m.active), np.asarray(m.parent)
        assert active[0] and parent[0] == -1
        for i in np.flatnonzero(active)[1:]:
            assert 0 <= parent[i] < i and active[parent[i]]
        assert np.all(parent[~active] == -1)


def test_masked_and_out_of_range_actions(space):
    m = space.initial()
    if np.asarray(space.action_mask(m)).all():  # Bad Walker: remove a foot to mask its row
        m = space.mutate(m, 1, space.num_mutations - 1)
    node, mutation = map(int, np.argwhere(~np.asarray(space.action_mask(m)))[0])
    with pytest.raises(ValueError, match="not allowed"):
        space.mutate(m, node, mutation)
    with pytest.raises(ValueError, match="node 99 is outside"):
        space.mutate(m, 99, 0)
    with pytest.raises(ValueError, match="mutation -1 is outside"):
        space.mutate(m, 0, -1)
    # Inside jit the documented behaviour is a no-op.
    mutate = jax.jit(space.mutate)
    for n, u in [(node, mutation), (99, 0), (0, space.num_mutations)]:
        out = mutate(m, n, u)
        chex.assert_trees_all_equal(out, m)


def test_vmapped_mutate_matches_loop(space):
    keys = jax.random.split(jax.random.PRNGKey(0), 8)
    morphs = [space.random_morphology(k, 3) for k in keys]
    actions = []
    for i, m in enumerate(morphs):
        valid = np.argwhere(np.asarray(space.action_mask(m)))
        actions.append(valid[i % len(valid)])
    nodes, mutations = np.array(actions).T
    batched = jax.jit(jax.vmap(space.mutate))(em.stack(morphs), nodes, mutations)
    for i, m in enumerate(morphs):
        chex.assert_trees_all_equal(jax.tree.map(lambda x: x[i], batched), space.mutate(m, nodes[i], mutations[i]))


def reachable_batched(space, batch=256):
    """Every morphology reachable from m0 and its depth: breadth first, each level's every
    (body, action) pair mutated in one vmapped call (masked actions leave the body unchanged)."""
    nodes, mutations = np.divmod(np.arange(space.num_actions), space.num_mutations)
    mutate_all = jax.jit(jax.vmap(jax.vmap(space.mutate, (None, 0, 0)), (0, None, None)))
    key = lambda m: space.to_json(m)  # noqa: E731
    m0 = jax.device_get(space.initial())
    seen, frontier, depth = {key(m0): (m0, 0)}, [m0], 0
    while frontier:
        depth += 1
        new = []
        for start in range(0, len(frontier), batch):
            part = frontier[start : start + batch]
            children = jax.device_get(mutate_all(em.stack(part + [m0] * (batch - len(part))), nodes, mutations))
            for child in em.unstack(jax.tree.map(lambda x: x[: len(part)].reshape((-1,) + x.shape[2:]), children)):
                if key(child) not in seen:
                    seen[key(child)] = (child, depth)
                    new.append(child)
        frontier = new
    return list(seen.values())


# --- Bad Walker ---------------------------------------------------------------------------


def test_bad_walker_semantics():
    space = em.make_space("bad_walker")
    m0 = space.initial()
    assert space.format(m0).count("foot") == 3
    # Every mutation of the root is allowed and changes nothing.
    for u in range(space.num_mutations):
        chex.assert_trees_all_equal(space.mutate(m0, 0, u), m0)
    # Moving a foot sets its site; removing it frees the slot for good.
    moved = space.mutate(m0, bw.BACK, 0)
    assert int(moved.site[bw.BACK]) == 0 and bool(moved.active[bw.BACK])
    removed = space.mutate(moved, bw.LONG, bw.REMOVE)
    assert not bool(removed.active[bw.LONG]) and int(removed.parent[bw.LONG]) == -1
    assert not np.asarray(space.action_mask(removed))[bw.LONG].any()
    assert np.asarray(space.action_mask(removed))[[0, bw.BACK, bw.FRONT]].all()


def test_bad_walker_predefined_fitness_peaks_at_m_star():
    space = em.make_space("bad_walker")
    morphs = reachable(space)
    # long foot: middle, removed or one of 4 sites (6); each short foot: removed or 4 sites (5)
    assert len(morphs) == 6 * 5 * 5
    fitness = np.array(jax.vmap(space.predefined_fitness)(em.stack(morphs)))
    best = morphs[int(np.argmax(fitness))]
    chex.assert_trees_all_equal(best, space.optimum())
    assert np.sum(fitness == fitness.max()) == 1
    assert fitness.max() > float(space.predefined_fitness(space.initial()))


def test_bad_walker_horizon_leaves_room_to_hold_m_star():
    """m* is 3 mutations from m0 and an episode leaves at least 2 more (the source's no-ops)."""
    space = em.make_space("bad_walker")
    star = space.to_json(space.optimum())
    assert star not in {space.to_json(m) for m in reachable(space, max_depth=2)}
    assert star in {space.to_json(m) for m in reachable(space, max_depth=3)}
    assert space.default_horizon >= 3 + 2


# --- Constructor --------------------------------------------------------------------------


def test_constructor_semantics():
    space = em.make_space("constructor", horizon=6, knees=2, leg_edges=2)
    m = space.initial()
    assert int(m.num_nodes) == 1 and np.asarray(space.action_mask(m))[0].all()
    m = space.mutate(m, 0, 4)  # leg at the stick's start (node 1)
    m = space.mutate(m, 0, 4)  # a second leg at the same place (node 2)
    assert int(m.kind[2]) == cs.LEG and int(m.site[1]) == int(m.site[2]) == 4
    assert np.asarray(space.action_mask(m))[1].all()  # a leg takes all 6 mutations
    m = space.mutate(m, 1, 5)  # knee: a leg at leg 1's foot (node 3)
    m = space.mutate(m, 1, 3)  # an edge welded to leg 1, forward from its foot (node 4)
    m = space.mutate(m, 4, 5)  # a leg at that edge's end: leg 1's second knee (node 5)
    mask = np.asarray(space.action_mask(m))
    assert not mask[[1, 4], 4:].any() and mask[[1, 4], :4].all()  # leg 1: knees full, edge slot left
    assert not mask[[3, 5], 4:].any()  # knees take no legs (leg_depth 2)
    assert mask[0].all() and mask[2].all()
    # Each limb joins the template body it hangs from: knees under leg 1, the edge welded to it.
    body, geom, _, _ = space._assign(m)
    parent = space.body_parent
    assert parent[body[1]] == 0 and parent[body[2]] == 0 and body[1] != body[2]
    assert parent[body[3]] == body[1] and parent[body[5]] == body[1] and body[4] == body[1]
    assert space.plan.geom_body[int(geom[4])] == body[1]
    m = space.mutate(m, 5, 1)  # an edge on a knee (node 6): full
    assert int(m.num_nodes) == 7 == space.max_nodes
    assert not np.asarray(space.action_mask(m)).any()
    assert float(space.predefined_fitness(m)) == 100.0 * (4 - 2)


def test_constructor_leaf_legs_option():
    space = em.make_space("constructor", horizon=4, leg_depth=1, leg_edges=0)
    m = space.mutate(space.mutate(space.initial(), 0, 5), 0, 5)  # two legs at the stick's end
    mask = np.asarray(space.action_mask(m))
    assert not mask[1:3].any() and mask[0].all()  # legs are leaves
    assert space.template.nbody == 1 + 1 + 4  # world, trunk, 4 leg slots


def test_constructor_nodes_never_share_a_template_slot():
    """Random walks to full capacity: every leg has its own body slot, every limb its own geom."""
    space = em.make_space("constructor")
    keys = jax.random.split(jax.random.PRNGKey(0), 64)
    morphs = jax.vmap(space.random_morphology, (0, None))(keys, space.horizon)
    body, geom, _, _ = jax.vmap(space._assign)(morphs)
    kinds, parents = np.asarray(morphs.kind), np.asarray(morphs.parent)
    knees = 0
    for b, g, k, p in zip(np.asarray(body), np.asarray(geom), kinds, parents):
        legs = b[1:][k[1:] == cs.LEG]
        assert len(set(legs)) == len(legs) and (legs > 0).all()
        assert len(set(g[1:])) == space.horizon and (g[1:] > 0).all()
        for i in np.flatnonzero(k == cs.LEG):  # a leg's body hangs from its parent node's body
            assert space.body_parent[b[i]] == b[p[i]]
        knees += int((space.body_parent[legs] > 0).sum())
    assert knees > 0  # the walks did reach knees


def test_constructor_best_return_is_a_leg_every_step():
    """The predefined optimum after `horizon` mutations: 100 x horizon (legs stacked or kneed)."""
    space = em.make_space("constructor")
    m = space.initial()
    for node in (0, 0, 0, 0, 1, 2, 3, 4):  # 4 legs on the stick, a knee on each
        m = space.mutate(m, node, 4)
    assert float(space.predefined_fitness(m)) == 100.0 * space.horizon == 800.0
    assert not np.asarray(space.action_mask(m)).any()


def test_constructor_capacity_follows_horizon():
    for horizon in (1, 8):
        space = em.make_space("constructor", horizon=horizon)
        m = space.random_morphology(jax.random.PRNGKey(horizon), horizon)
        assert int(m.num_nodes) == space.max_nodes == horizon + 1
        assert not np.asarray(space.action_mask(m)).any()
    with pytest.raises(ValueError, match="horizon"):
        em.make_space("constructor", horizon=0)


def test_constructor_predefined_fitness_counts_limbs():
    space = em.make_space("constructor")
    for seed in range(5):
        m = space.random_morphology(jax.random.PRNGKey(seed), 8)
        kinds = np.asarray(m.kind)[np.asarray(m.active)]
        expected = 100.0 * (np.sum(kinds == cs.LEG) - np.sum(kinds == cs.EDGE))
        assert float(space.predefined_fitness(m)) == expected


def test_constructor_edges_chain_from_their_attachment_points():
    space = em.make_space("constructor")
    m = space.initial()
    m = space.mutate(m, 0, 3)  # edge forward from the stick's end: x 0.5 -> 1.0
    m = space.mutate(m, 1, 3)  # and again from that edge's end: x 1.0 -> 1.5
    m = space.mutate(m, 2, 5)  # leg at x 1.5
    m = space.mutate(m, 3, 3)  # an edge welded to that leg, from its foot forward
    layout = space.layout(m)
    body, geom, _, _ = space._assign(m)
    np.testing.assert_allclose(layout.geom_to[int(geom[2]), 0], 1.5, atol=1e-6)
    leg = int(body[3])
    np.testing.assert_allclose(layout.limb_pos[leg - 1], [1.5, 0, 0], atol=1e-6)  # the hip
    assert np.asarray(layout.limb_active).sum() == 1 and bool(layout.limb_active[leg - 1])
    # the leg's edge, in the leg's frame: from its foot, 0.5 m forward
    foot = cs.LEG_LENGTH * np.array([-np.sin(cs.LEG_INCLINE), 0, -np.cos(cs.LEG_INCLINE)])
    np.testing.assert_allclose(layout.geom_from[int(geom[4])], foot, atol=1e-6)
    np.testing.assert_allclose(layout.geom_to[int(geom[4])], foot + [0.5, 0, 0], atol=1e-6)
# --- Length Walker ------------------------------------------------------------------------


def test_length_walker_semantics():
    space = em.make_space("length_walker")
    m0 = space.initial()
    for u in range(space.num_mutations):  # the root's mutations are no-ops
        chex.assert_trees_all_equal(space.mutate(m0, 0, u), m0)
    mask = np.asarray(space.action_mask(m0))
    assert not mask[lw.BACK, lw.LENGTHEN] and not mask[lw.FRONT, lw.LENGTHEN]  # 0.4 m is the longest
    m = space.mutate(m0, lw.BACK, lw.SHORTEN)
    assert float(m.attrs[lw.BACK, 0]) == lw.LENGTHS[2] and float(m.attrs[lw.FRONT, 0]) == lw.LENGTHS[3]
    assert np.asarray(space.action_mask(m))[lw.BACK, lw.LENGTHEN]
    chex.assert_trees_all_equal(space.mutate(m, lw.BACK, lw.LENGTHEN), m0)  # steps land on the grid
    m = space.mutate(space.mutate(m, lw.BACK, lw.SHORTEN), lw.BACK, lw.SHORTEN)
    assert float(m.attrs[lw.BACK, 0]) == lw.LENGTHS[0] and not np.asarray(space.action_mask(m))[lw.BACK, lw.SHORTEN]
    m = space.mutate(m, lw.FRONT, 0)  # feet may share or swap places
    assert int(m.site[lw.FRONT]) == 0 and int(m.site[lw.BACK]) == 1
    # The capsule follows the attribute: the foot ends its length below its hinge.
    np.testing.assert_allclose(space.layout(m).geom_to[lw.BACK, 2], -lw.LENGTHS[0])


def test_length_walker_predefined_optimum_by_enumeration():
    """All 256 bodies (4 sites x 4 lengths per foot) are reachable; m* alone scores best."""
    space = em.make_space("length_walker")
    found = reachable_batched(space)
    morphs, depths = [m for m, _ in found], np.array([d for _, d in found])
    assert len(morphs) == (4 * 4) ** 2
    fitness = np.array(jax.jit(jax.vmap(space.predefined_fitness))(em.stack(morphs)))
    best = int(np.argmax(fitness))
    chex.assert_trees_all_equal(morphs[best], space.optimum())
    assert np.sum(fitness == fitness.max()) == 1 and fitness.max() == 1.0
    assert float(space.predefined_fitness(space.initial())) == pytest.approx(-1 / 3)
    # m* is 6 mutations from m0; an episode leaves 2 steps to hold it.
    assert depths[best] == 6 and space.default_horizon == depths[best] + 2


def test_a_mutation_that_changes_nothing_is_named_a_no_op():
    """The greedy trajectory's names (`pipeline.action_name`): the root's mutations and a move
    to where a foot already is say "(no-op)"; a move or a removal that changes the body does
    not."""
    from evojax_morph.search.pipeline import action_name

    space = em.make_space("bad_walker")
    m0, nm = space.initial(), space.num_mutations
    name = lambda node, u, m=m0: action_name(space, node * nm + u, m, space.mutate(m, node, u))
    assert name(0, bw.REMOVE) == "node 0: remove (no-op)"
    moved = space.mutate(m0, bw.BACK, 0)
    assert name(bw.BACK, 0) == f"node {bw.BACK}: to_back_end"
    assert name(bw.BACK, 0, moved) == f"node {bw.BACK}: to_back_end (no-op)"
    assert name(bw.LONG, bw.REMOVE) == f"node {bw.LONG}: remove"
