"""The SB3 `VecEnv` over the Gymnasium adapter, and sb3-contrib's MaskablePPO learning Bad
Walker on the predefined fitness through it. Skipped where sb3-contrib is not installed (the
`sb3` extra pulls torch, so the `test` extra leaves it out): `pip install -e ".[sb3]"`, then
`pytest tests/test_sb3.py` and `pytest -m learning tests/test_sb3.py`."""

import numpy as np
import pytest

import evojax_morph as em

pytest.importorskip("gymnasium")
sb3_contrib = pytest.importorskip("sb3_contrib")
torch = pytest.importorskip("torch")

from sb3_contrib.common.maskable.utils import get_action_masks, is_masking_supported  # noqa: E402
from stable_baselines3.common.vec_env import VecEnv  # noqa: E402

N, HORIZON = 3, 2


def test_vec_env_is_the_gymnasium_adapter_in_sb3_form():
    """Same seed, same actions: the VecEnv's observations, rewards and ends are the Gymnasium
    adapter's; the terminal observation is its `final_obs`; the masks reach MaskablePPO per
    evolution."""
    gym_envs = em.GymEvolutionEnv("bad_walker", "predefined", num_envs=N, horizon=HORIZON)
    envs = em.SB3EvolutionEnv(em.GymEvolutionEnv("bad_walker", "predefined", num_envs=N,
                                                 horizon=HORIZON))
    assert isinstance(envs, VecEnv) and envs.num_envs == N
    assert envs.action_space == gym_envs.single_action_space
    assert is_masking_supported(envs)

    envs.seed(4)
    obs = envs.reset()
    ref, info = gym_envs.reset(seed=4)
    rng = np.random.default_rng(0)
    for t in range(2 * HORIZON):
        for k in ref:
            np.testing.assert_array_equal(obs[k], ref[k])
            assert obs[k].flags.writeable  # torch takes them as they are
        masks = get_action_masks(envs)  # how MaskablePPO asks: env_method("action_masks")
        np.testing.assert_array_equal(masks, gym_envs.action_masks())
        assert masks.shape == (N, envs.action_space.n)
        actions = np.array([rng.choice(np.flatnonzero(m)) for m in masks])
        obs, reward, dones, infos = envs.step(actions)
        ref, ref_reward, terminated, truncated, info = gym_envs.step(actions)
        np.testing.assert_array_equal(reward, ref_reward.astype(np.float32))
        np.testing.assert_array_equal(dones, terminated | truncated)
        assert dones.all() == ((t + 1) % HORIZON == 0) and dones.any() == dones.all()
        for i in range(N):
            np.testing.assert_allclose(infos[i]["fitness"], info["fitness"][i])
            assert infos[i]["action_valid"]
            if dones[i]:
                final = info["final_obs"][i]
                for k in final:
                    np.testing.assert_array_equal(infos[i]["terminal_observation"][k], final[k])
                assert infos[i]["TimeLimit.truncated"] is False
            else:
                assert "terminal_observation" not in infos[i]

    assert envs.get_attr("space", [0, 2]) == [envs.envs.space] * 2
    with pytest.raises(AttributeError, match="only 'action_masks'"):
        envs.env_method("render")
    with pytest.raises(ValueError, match="set an attribute for all"):
        envs.set_attr("render_mode", None, indices=[1])
    with pytest.raises(TypeError, match="wraps a GymEvolutionEnv"):
        em.SB3EvolutionEnv(gym_envs.env)


def _greedy_return(model, envs, horizon):
    """The return of the deterministic masked policy from m0 (every evolution acts alike)."""
    obs, total = envs.reset(), np.zeros(envs.num_envs)
    for _ in range(horizon):
        actions, _ = model.predict(obs, action_masks=envs.action_masks(), deterministic=True)
        obs, reward, _, _ = envs.step(actions)
        total += reward
    return total[0]


def _random_returns(envs, horizon, episodes, seed):
    rng, totals = np.random.default_rng(seed), []
    for _ in range(episodes // envs.num_envs):
        envs.reset()
        total = np.zeros(envs.num_envs)
        for _ in range(horizon):
            actions = np.array([rng.choice(np.flatnonzero(m)) for m in envs.action_masks()])
            total += envs.step(actions)[1]
        totals += list(total)
    return np.array(totals)


@pytest.mark.learning
def test_maskable_ppo_beats_random_mutations():
    """MaskablePPO, 4,096 steps over 8 evolutions (5 to 30 s a seed on 2 shared CPU cores),
    on Bad Walker's predefined fitness (horizon 5: m0 0.667, the optimum 2.0, so a return of at
    most 1.333). The greedy policy's return minus the mean return of random masked actions,
    median over 12 seeds, must exceed 1.0. Measured over 20 other seeds (100 to 119): every
    greedy return was 1.167 (a final fitness of 1.833), random actions' mean -0.504 over 512
    episodes (their 90th percentile 0.667): a difference of 1.67 for every seed, so the
    threshold 1.0 leaves 0.67 of margin."""
    torch.set_num_threads(1)
    envs = em.SB3EvolutionEnv(em.GymEvolutionEnv("bad_walker", "predefined", num_envs=8))
    horizon = envs.envs.env.horizon
    random_mean = _random_returns(envs, horizon, episodes=128, seed=0).mean()
    gains = []
    for seed in range(12):
        envs.seed(seed)
        model = sb3_contrib.MaskablePPO("MultiInputPolicy", envs, n_steps=32, batch_size=64,
                                        seed=seed, verbose=0)
        model.learn(4096)
        gains.append(_greedy_return(model, envs, horizon) - random_mean)
    assert np.median(gains) > 1.0, gains
