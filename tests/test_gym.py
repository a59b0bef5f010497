"""The Gymnasium adapter, driven by a masked random agent on the predefined fitness; rewards
are checked against the space's own mutation and fitness, computed here one body at a time.

sb3-contrib's MaskablePPO drives it through `em.SB3EvolutionEnv` in tests/test_sb3.py (skipped
without the `sb3` extra, which pulls torch)."""

import jax.numpy as jnp
import numpy as np
import pytest

import evojax_morph as em
from evojax_morph.morphology import Morphology

gym = pytest.importorskip("gymnasium")

N, HORIZON = 4, 3


def body(obs: dict, i: int) -> Morphology:
    return Morphology(
        active=jnp.asarray(obs["active"][i], bool),
        parent=jnp.asarray(obs["parent"][i]),
        kind=jnp.asarray(obs["kind"][i]),
        site=jnp.asarray(obs["site"][i]),
        attrs=jnp.asarray(obs["attrs"][i]),
    )


def same(a: Morphology, b: Morphology) -> bool:
    return all(np.array_equal(x, y) for x, y in zip(
        (a.active, a.parent, a.kind, a.site, a.attrs), (b.active, b.parent, b.kind, b.site, b.attrs)
    ))


def test_masked_random_agent_rewards_masks_and_autoreset():
    envs = em.GymEvolutionEnv("bad_walker", "predefined", num_envs=N, horizon=HORIZON)
    space = envs.space
    assert isinstance(envs, gym.vector.VectorEnv)
    assert envs.single_action_space.n == space.max_nodes * space.num_mutations
    assert envs.metadata["autoreset_mode"] == gym.vector.AutoresetMode.SAME_STEP
    f = lambda m: float(space.predefined_fitness(m))  # noqa: E731
    m0 = space.initial()

    obs, info = envs.reset(seed=0)
    assert envs.observation_space.contains(obs)
    np.testing.assert_allclose(info["fitness"], f(m0))
    rng = np.random.default_rng(0)
    for t in range(2 * HORIZON):
        masks = envs.action_masks()
        np.testing.assert_array_equal(masks, obs["action_mask"].astype(bool))
        parents = [body(obs, i) for i in range(N)]
        for i in range(N):  # the mask is the space's own
            own = np.asarray(space.action_mask(parents[i])).ravel()
            np.testing.assert_array_equal(masks[i], own)
        actions = np.array([rng.choice(np.flatnonzero(m)) for m in masks])
        nm = space.num_mutations
        # eager mutate raises on a masked action: the agent kept to the mask
        children = [space.mutate(parents[i], actions[i] // nm, actions[i] % nm) for i in range(N)]

        obs, reward, terminated, truncated, info = envs.step(actions)
        assert envs.observation_space.contains(obs)
        expected = [f(c) - f(p) for c, p in zip(children, parents)]
        np.testing.assert_allclose(reward, expected, atol=1e-6)
        np.testing.assert_allclose(info["fitness"], [f(c) for c in children], atol=1e-6)
        assert info["action_valid"].all() and not truncated.any()
        ended = (t + 1) % HORIZON == 0
        assert (terminated == ended).all()
        for i in range(N):
            if ended:  # same-step autoreset: m0 now, the child in final_obs
                assert same(body(obs, i), m0) and obs["progress"][i, 0] == 0
                assert same(_final(info, i), children[i])
            else:
                assert same(body(obs, i), children[i])
                assert obs["progress"][i, 0] == pytest.approx((t % HORIZON + 1) / HORIZON)
        assert ("final_obs" in info) == ended


def _final(info: dict, i: int) -> Morphology:
    final = info["final_obs"][i]
    assert info["_final_obs"][i]
    return body({k: v[None] for k, v in final.items()}, 0)


def test_masked_action_is_a_flagged_no_op_and_bad_actions_raise():
    envs = em.GymEvolutionEnv("bad_walker", "predefined", num_envs=N, horizon=HORIZON)
    space = envs.space
    remove_long = 1 * space.num_mutations + 4
    envs.reset(seed=1)
    obs, *_ = envs.step(np.full(N, remove_long))
    assert not envs.action_masks()[:, remove_long].any()
    before = body(obs, 0)
    obs, reward, _, _, info = envs.step(np.full(N, remove_long))  # now masked
    assert not info["action_valid"].any() and np.allclose(reward, 0.0)
    assert same(body(obs, 0), before)
    with pytest.raises(ValueError, match="lie in"):
        envs.step(np.full(N, space.num_actions))
    with pytest.raises(ValueError, match="integers"):
        envs.step(np.zeros(N + 1, int))
