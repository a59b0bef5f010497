"""Batched NGE fitness: learning, inheritance, batching, and the masked PPO pieces."""

import dataclasses
import json
from typing import NamedTuple

import chex
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from brax.training import distribution
from brax.training.agents.ppo import losses as ppo_losses

import evojax_morph as em
from evojax_morph import ppo
from evojax_morph.spaces import bad_walker as bw

# One small budget for every test that trains, so the suite compiles PPO once, and one that only
# evaluates the controller it is given.
CFG = em.FitnessConfig(ppo=em.standard_ppo(40_000))
EVAL_ONLY = em.FitnessConfig(ppo=dataclasses.replace(CFG.ppo, train_steps=0))
# The default set's checks of batching, the one-world path and K controllers: untrained
# controllers, K = 2 a body, over 1 s episodes (the same programs as at 5 s, a fifth of the
# stepping). Fresh controllers of m* score from -6 to 10 there, so mix-ups show.
CHECK = em.FitnessConfig(task=em.TaskConfig(episode_length=50),
                         ppo=dataclasses.replace(EVAL_ONLY.ppo, controllers=2))
# Seeds of every learning statistic below: one PPO run is a coin with a bias (a gait is found or
# not), so the tests assert medians over seeds, with margins measured over 20 other seeds by
# `python -m experiments.learning_margins --seeds 20` (2 CPU cores, jax 0.10.2).
SEEDS = 12


@pytest.fixture(scope="module")
def walker():
    return em.make_space("bad_walker")


def footless(space):
    m = space.initial()
    for foot in (bw.LONG, bw.BACK, bw.FRONT):
        m = space.mutate(m, foot, bw.REMOVE)
    return m


@pytest.fixture(scope="module")
def bodies(walker):
    """SEEDS copies of m*, a body with no motor and SEEDS - 1 children of m* (`gen1`), a key and
    a fresh controller for each, and the evaluation-only `train`, vmapped and traced once for
    every batch of 2 x SEEDS bodies below (jit-once check)."""
    chex.clear_trace_counter()
    _, evaluate = ppo.make_train(walker, EVAL_ONLY.task, EVAL_ONLY.ppo)
    evaluate = jax.jit(chex.assert_max_traces(evaluate, n=1))
    child = walker.mutate(walker.optimum(), bw.FRONT, 2)  # front foot one site inward
    keys = jax.random.split(jax.random.PRNGKey(0), 2 * SEEDS)
    init, _ = ppo.make_train(walker, CFG.task, CFG.ppo)
    fresh = jax.jit(jax.vmap(init))(keys)
    gen1 = em.stack([walker.optimum()] * SEEDS + [footless(walker)] + [child] * (SEEDS - 1))
    return gen1, keys, fresh, child, evaluate


def train_first(walker, bodies, cfg):
    """The first SEEDS + 2 bodies of `gen1` (SEEDS m*, the motorless one, a child) trained from
    their fresh controllers in one jitted, vmapped `train` call at `cfg`'s budget."""
    gen1, keys, fresh, _, _ = bodies
    _, train = ppo.make_train(walker, cfg.task, cfg.ppo)
    first = lambda tree: jax.tree.map(lambda x: x[: SEEDS + 2], tree)  # noqa: E731
    return jax.jit(train)(keys[: SEEDS + 2], first(gen1), first(fresh))


@pytest.fixture(scope="module")
def trained(walker, bodies):
    """`bodies` with the first SEEDS + 2 trained at the learning tests' budget (CFG)."""
    gen1, keys, fresh, child, evaluate = bodies
    return gen1, keys, train_first(walker, bodies, CFG), fresh, child, evaluate


class Checked(NamedTuple):
    """SEEDS bodies scored at CHECK in one batch, K = 2 fresh controllers each."""

    morphs: em.Morphology  # (SEEDS, ...): SEEDS / 2 m*, the motorless one, SEEDS / 2 - 1 children
    keys: jax.Array  # (SEEDS,) one key a body
    params: ppo.Params  # (SEEDS, 2, ...) `gen1`'s 2 x SEEDS fresh controllers, in pairs
    result: em.FitnessResult  # (SEEDS,) em.evaluate's


MOTORLESS = SEEDS // 2  # the motorless body's place in `checked`


@pytest.fixture(scope="module")
def checked(walker, bodies):
    """Half of `gen1`'s bodies with all its fresh controllers, two a body, in one `em.evaluate`
    at CHECK (one compiled program for the three tests below)."""
    gen1, keys, fresh, _, _ = bodies
    rows = np.r_[: SEEDS // 2, SEEDS : SEEDS + SEEDS // 2]
    morphs = jax.tree.map(lambda x: x[rows], gen1)
    params = jax.tree.map(lambda x: x.reshape((SEEDS, 2) + x.shape[1:]), fresh)
    return Checked(morphs, keys[:SEEDS], params,
                   em.evaluate(walker, morphs, keys[:SEEDS], CHECK, params))


def zero_controller(params):
    """The same controllers with a zeroed policy: its mean action, tanh(0), is 0 everywhere."""
    return params._replace(policy=jax.tree.map(jnp.zeros_like, params.policy))


@pytest.mark.learning
def test_m_star_learns_to_walk(walker, trained):
    gen1, keys, out1, fresh, _, evaluate = trained
    zero = np.asarray(evaluate(keys, gen1, zero_controller(fresh)).fitness[:SEEDS])  # m* stands still
    learned = np.asarray(out1.fitness[:SEEDS])
    # 50 = 1 m further in 5 s than standing still. Measured over 20 other seeds: learned minus
    # zero-controller fitness has median 167 (range 21 to 330; a seed that finds no gait stays
    # near 30), and a 12-seed median falls below 104 once in 100 (bootstrap).
    assert np.median(learned - zero) > 50, (learned, zero)
    assert np.all(np.isfinite(np.asarray(out1.fitness))) and not np.asarray(out1.diverged).any()


def test_no_motor_no_fitness(checked):
    """A trunk alone cannot move itself: with no motor its controller acts on nothing, so its
    fitness is the same trained or not, and a reward that paid a body without motors shows
    with fresh controllers (m* in the same batch: -3 to 8)."""
    fitness = np.asarray(checked.result.fitness)
    assert abs(fitness[MOTORLESS]) < 1.0
    assert np.ptp(fitness[:MOTORLESS]) > 2.0  # m*, with motors, moves


@pytest.mark.learning
def test_inherited_controller_hands_over_a_gait(trained):
    """A child evaluated with its parent's trained controller, before any training of its own,
    walks further than with a fresh controller (the same keys).

    That a child trained further from the inherited controller beats the same child trained from
    scratch at the same budget is NOT asserted: over 20 seeds at this budget the difference had
    median +34 but ranged from -160 to +499, and a 12-seed median fell below -74 once in 100
    (experiments/learning_margins.py; on a GPU, docs/results.md, "Inheritance").
    """
    _, keys, out1, fresh, child, evaluate = trained
    children = em.stack([child] * (2 * SEEDS))
    parents = jax.tree.map(lambda x: x[:SEEDS], out1.params)
    params = jax.tree.map(lambda a, b: jnp.concatenate([a, b[SEEDS:]]), parents, fresh)
    child_keys = jnp.concatenate([keys[SEEDS:], keys[SEEDS:]])
    fitness = np.asarray(evaluate(child_keys, children, params).fitness)
    inherited, scratch = fitness[:SEEDS], fitness[SEEDS:]
    # Measured over 20 other seeds: the difference has median 43 and was positive in all 20 (9 to
    # 318); a 12-seed median falls below 13.8 once in 100 (bootstrap).
    assert np.median(inherited - scratch) > 5, (inherited, scratch)


def test_batch_equals_one_at_a_time(walker, checked):
    """Each body of a batch gets what it would get alone with the same key and controllers, and
    with K = 2 controllers its fitness is the mean of two single-controller runs, each with its
    share of the body's key: the fitness steps every world of every controller of every body
    as one flat batch, and scores as the replays of one controller on its body alone do
    (`em.replay`: one body, one controller, one world at a time), equal to rounding.

    Compared on evaluation of untrained controllers (physics, task and policy under vmap).
    Training and trained gaits amplify float rounding too much to compare: Adam's first steps
    move every weight by about the learning rate whatever the size of its gradient, so sign
    flips of near-zero gradients under a different reduction order become visible, and a
    walking gait can turn a 1e-7 difference into a fall.
    """
    result = checked.result

    def alone(b, c, key):  # body b's controller c on its own, with its share of b's key
        pick = lambda tree: jax.tree.map(lambda x: x[b], tree)  # noqa: E731
        saved = em.SavedController(walker, CHECK, 0, pick(checked.morphs), pick(checked.params),
                                   0.0, f"body {b}")
        eval_key = jax.random.split(key)[0]  # what train keeps for the evaluation
        reps = [em.replay(saved, k, controller=c)
                for k in jax.random.split(eval_key, CHECK.ppo.eval_episodes)]
        # the gait as the replay shows it: metres to its last frame, steps before a fall
        length = CHECK.task.episode_length
        upright = [(len(r.reward) - r.fell) / length for r in reps]
        return np.mean([[r.episode_return, r.distance[-1], u] for r, u in zip(reps, upright)], 0)

    singles = np.array([[alone(b, c, key) for c, key in enumerate(jax.random.split(k, 2))]
                        for b, k in enumerate(checked.keys)])  # (SEEDS, 2, 3)
    singles, gait = singles[..., 0], singles[..., 1:].mean(1)
    # Measured: the two paths differ by at most 1.2e-4 with jax 0.10.2; with jax 0.12.1 at the
    # default set's -O0, body 9 by 9.9e-3 and its distance by 0.2 mm with the same upright
    # fraction (1.3e-6 at XLA's default optimisation; read as contacts rounded apart), the
    # others by 4e-5.
    # Mixed-up bodies still show: the two closest in fitness here are 0.07 apart.
    np.testing.assert_allclose(result.fitness, singles.mean(1), rtol=1e-3, atol=2e-2)
    np.testing.assert_allclose(result.fitness_std, singles.std(1), rtol=1e-3, atol=2e-2)
    np.testing.assert_allclose(result.distance, gait[:, 0], rtol=1e-3, atol=5e-4)
    np.testing.assert_allclose(result.upright, gait[:, 1], rtol=1e-6)
    assert np.ptp(np.asarray(result.upright)) > 0.1  # fresh controllers fall at different times
    assert np.ptp(np.asarray(result.distance)) > 0.02  # bodies moved differently
    assert np.abs(np.diff(singles[:MOTORLESS])).max() > 1.0  # m*'s pairs differ: a mix-up shows
    assert len(set(np.round(np.asarray(result.fitness), 3))) > 2  # different bodies, different results


def test_k_controllers_come_back(walker, checked):
    """Both controllers of every body come back (for the children), unchanged by an evaluation,
    and a body's env steps are K single runs'."""
    result = checked.result
    chex.assert_trees_all_equal(result.params, checked.params)
    assert result.env_steps == 2 * ppo.env_steps_per_morphology(CHECK.task, EVAL_ONLY.ppo)
    assert not np.asarray(result.diverged).any()


def test_evaluate_api(walker):
    morphs = em.stack([walker.initial(), walker.optimum()])
    pre = em.evaluate(walker, morphs, jax.random.PRNGKey(0), em.FitnessConfig(kind="predefined"))
    np.testing.assert_allclose(pre.fitness, [walker.predefined_fitness(m) for m in em.unstack(morphs)])
    assert pre.params is None and not pre.diverged.any()
    with pytest.raises(ValueError, match="batch of shape"):
        em.evaluate(walker, walker.initial(), jax.random.PRNGKey(0), CFG)
    with pytest.raises(ValueError, match="2 keys for 3"):
        em.evaluate(walker, em.stack([walker.initial()] * 3), jax.random.split(jax.random.PRNGKey(0), 2), CFG)
    with pytest.raises(ValueError, match="unknown fitness"):
        em.FitnessConfig(kind="tame?")
    with pytest.raises(ValueError, match="minibatches"):
        em.PPOConfig(worlds_per_controller=3, unroll_length=3, num_minibatches=4).validate()


# --- masked PPO pieces against Python loops ------------------------------------------------


def test_masked_log_prob_matches_a_loop():
    rng = np.random.default_rng(0)
    dist = distribution.NormalTanhDistribution(event_size=4)
    logits = rng.normal(size=(5, 8)).astype(np.float32)
    raw = rng.normal(size=(5, 4)).astype(np.float32)
    mask = np.array([True, False, True, False])
    got = np.asarray(ppo.masked_log_prob(dist, jnp.asarray(logits), jnp.asarray(raw), jnp.asarray(mask)))
    for b in range(5):
        total = 0.0
        for a in range(4):
            if not mask[a]:
                continue
            loc, scale = logits[b, a], np.log1p(np.exp(logits[b, 4 + a])) + 0.001  # softplus + min_std
            normal = -0.5 * ((raw[b, a] - loc) / scale) ** 2 - np.log(scale) - 0.5 * np.log(2 * np.pi)
            total += normal - np.log(1 - np.tanh(raw[b, a]) ** 2)  # change of variables for tanh
        np.testing.assert_allclose(got[b], total, rtol=1e-4, atol=1e-4)
    # Masked dimensions do not matter at all.
    other = raw.copy()
    other[:, ~mask] += 5.0
    np.testing.assert_array_equal(got, ppo.masked_log_prob(dist, jnp.asarray(logits), jnp.asarray(other), jnp.asarray(mask)))


def test_one_update_moves_every_layer_but_a_masked_motors_outputs():
    """One PPO update (`ppo.make_learn`, 2 epochs x 2 minibatches) from a random trajectory of
    the current policy: every layer of the policy and value networks moves and the observation
    statistics too, all finite; the policy's outputs of a masked motor (its action's mean and
    scale) keep their weights to the bit: its log-probability and entropy are masked out.
    (The whole training program, collection included, is test_render's, in the slow set.)"""
    space = em.make_space("bad_walker")
    cfg = dataclasses.replace(CFG.ppo, worlds_per_controller=4, unroll_length=8, num_minibatches=2,
                              update_epochs=2)
    env = em.Locomotion(space, CFG.task)
    networks = ppo.make_networks(env, cfg)
    params = jax.jit(ppo.make_init(env, networks, cfg))(jax.random.PRNGKey(0))
    optimizer = optax.adam(cfg.learning_rate)
    learn = jax.jit(ppo.make_learn(networks, optimizer, cfg))
    a = env.action_size
    mask = jnp.arange(a) != 1  # motor 1 masked
    k_obs, k_act, k_rew = jax.random.split(jax.random.PRNGKey(1), 3)
    shape = (cfg.unroll_length, cfg.worlds_per_controller)
    obs = jax.random.normal(k_obs, shape + (env.obs_size,))
    dist = networks.parametric_action_distribution

    @jax.jit
    def trajectory(params):
        logits = networks.policy_network.apply(params.normalizer, params.policy, obs)
        raw = dist.sample_no_postprocessing(logits, k_act)
        zeros = jnp.zeros(shape)
        return ppo.Transition(obs, raw, ppo.masked_log_prob(dist, logits, raw, mask),
                              jax.random.normal(k_rew, shape), zeros, zeros, zeros.astype(bool))

    traj = trajectory(params)
    net = {"policy": params.policy, "value": params.value}
    normalizer, new, _, _, entropy = learn(params.normalizer, net, optimizer.init(net), traj,
                                           obs[-1], mask, jax.random.PRNGKey(2))
    changed = jax.tree.map(lambda x, y: bool((x != y).any()), net, new)
    assert all(jax.tree.leaves(changed)), changed
    assert all(np.isfinite(x).all() for x in jax.tree.leaves(new)) and np.isfinite(entropy)
    assert (normalizer.mean != params.normalizer.mean).all()

    def output_layer(policy):  # the last layer: a mean and a scale a motor
        (layer,) = [v for v in policy["params"].values() if v["bias"].shape == (2 * a,)]
        return layer

    before, after = output_layer(net["policy"]), output_layer(new["policy"])
    for col in (1, a + 1):  # motor 1's mean and scale
        np.testing.assert_array_equal(after["kernel"][:, col], before["kernel"][:, col])
        np.testing.assert_array_equal(after["bias"][col], before["bias"][col])
    assert (after["kernel"][:, 0] != before["kernel"][:, 0]).any()  # an active motor's move


def test_gae_with_termination_and_truncation_matches_a_loop():
    rng = np.random.default_rng(1)
    steps, envs, gamma, lam = 7, 3, 0.9, 0.8
    rewards = rng.normal(size=(steps, envs))
    values = rng.normal(size=(steps, envs))
    bootstrap = rng.normal(size=envs)
    terminated = np.zeros((steps, envs))
    truncated = np.zeros((steps, envs))
    terminated[2, 0] = terminated[5, 1] = 1
    truncated[3, 2] = 1
    targets, adv = ppo_losses.compute_gae(
        truncation=jnp.asarray(truncated), termination=jnp.asarray(terminated), rewards=jnp.asarray(rewards),
        values=jnp.asarray(values), bootstrap_value=jnp.asarray(bootstrap), lambda_=lam, discount=gamma,
    )
    expected = np.zeros((steps, envs))
    for e in range(envs):
        acc = 0.0
        for t in reversed(range(steps)):
            next_value = bootstrap[e] if t == steps - 1 else values[t + 1, e]
            if truncated[t, e]:  # the step that hit the time limit teaches nothing; restart the sum
                acc = 0.0
                continue
            delta = rewards[t, e] + gamma * (1 - terminated[t, e]) * next_value - values[t, e]
            acc = delta + gamma * lam * (1 - terminated[t, e]) * acc
            expected[t, e] = acc
    np.testing.assert_allclose(np.asarray(targets) - values, expected, rtol=1e-5, atol=1e-5)
    assert np.all(np.asarray(adv)[truncated == 1] == 0)


def test_a_fitness_config_rebuilds_from_its_dict():
    """`FitnessConfig.from_dict(c.to_dict()) == c`, every field away from its default (a saved
    controller's config: `classes` was once dropped, replaying on the wrong template)."""
    c = em.FitnessConfig(kind="ppo", task=em.make_task("walk"), ppo=em.standard_ppo(123, 3),
                         classifier="dir", physics="warp", table="t.npz", classes=True)
    assert em.FitnessConfig.from_dict(json.loads(json.dumps(c.to_dict()))) == c
