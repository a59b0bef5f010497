import jax
import jax.numpy as jnp
import numpy as np
import pytest

import evojax_morph as em
from evojax_morph.morphology import Morphology


def assert_same(a: Morphology, b: Morphology):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_json_round_trip(space):
    for seed in range(5):
        m = space.random_morphology(jax.random.PRNGKey(seed), 4)
        back = space.from_json(space.to_json(m))
        assert_same(m, back)


def test_json_rejects_other_space_and_capacity():
    walker, constructor = em.make_space("bad_walker"), em.make_space("constructor")
    text = walker.to_json(walker.initial())
    with pytest.raises(ValueError, match="space 'bad_walker'"):
        constructor.from_json(text)
    bigger = em.make_space("constructor", horizon=10)
    with pytest.raises(ValueError, match="capacity"):
        bigger.from_json(constructor.to_json(constructor.initial()))


def test_from_dict_rejects_orphans():
    d = em.make_space("bad_walker").initial().to_dict()
    d["nodes"][2]["parent"] = 3  # a parent must come before its child
    with pytest.raises(ValueError, match="parent"):
        Morphology.from_dict(d)
    d = em.make_space("bad_walker").initial().to_dict()
    d["nodes"] = d["nodes"][1:]
    with pytest.raises(ValueError, match="root"):
        Morphology.from_dict(d)


def test_format_draws_every_active_node():
    space = em.make_space("constructor")
    m = space.initial()
    m = space.mutate(m, 0, 4)  # leg at the stick's start
    m = space.mutate(m, 0, 3)  # edge forward from the stick's end
    m = space.mutate(m, 2, 5)  # leg at that edge's end
    text = space.format(m)
    lines = text.splitlines()
    assert len(lines) == 4
    assert lines[0].startswith("0: stick")
    assert "3: leg @ leg_end" in lines[-1] and lines[-1].startswith("    └── ")  # under node 2


def test_stack_unstack_and_depth():
    space = em.make_space("constructor")
    morphs = [space.random_morphology(jax.random.PRNGKey(i), 3) for i in range(3)]
    batch = em.stack(morphs)
    assert batch.active.shape == (3, space.max_nodes)
    for a, b in zip(em.unstack(batch), morphs):
        assert_same(a, b)
    m = space.mutate(space.mutate(space.initial(), 0, 1), 1, 5)
    np.testing.assert_array_equal(m.depth(), [0, 1, 2] + [0] * (space.max_nodes - 3))
    assert int(m.num_nodes) == 3
    assert jnp.all(batch.num_nodes == 4)
