"""The inner PPO's program: `make_train` and the factories it nests (`evojax_morph.ppo`
describes them); its networks, parameters and loss are in `evojax_morph.ppo.networks`."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax
from brax.training.acme import running_statistics
from brax.training.agents.ppo import losses as ppo_losses

from evojax_morph.fitness_result import FitnessResult
from evojax_morph.morphology import Morphology, tree_select
from evojax_morph.physics.engines import Engine, get_engine, repeat_worlds
from evojax_morph.ppo.networks import (
    Params,
    PPOConfig,
    Transition,
    make_deterministic_policy,
    make_init,
    make_loss,
    make_networks,
    masked_log_prob,
)
from evojax_morph.spaces import Space
from evojax_morph.tasks import EnvState, Locomotion, TaskConfig, rollout


class Rollout(NamedTuple):
    """What carries over from one trajectory to the next, per world of L learners x E envs."""

    state: EnvState  # (L x E,) the worlds, flat
    episode_return: jax.Array  # (L, E) return of each world's episode so far
    last_return: jax.Array  # (L, E) return of each world's last finished episode
    keys: jax.Array  # (L,) the learners' keys


def make_policy(space: Space, task_cfg: TaskConfig = TaskConfig(), cfg: PPOConfig = PPOConfig()):
    """`policy(params, obs) -> action`: the deterministic actions (..., A) of one controller
    (no leading K axis) for (..., obs_size) observations, as the evaluation episodes act."""
    return make_deterministic_policy(make_networks(Locomotion(space, task_cfg), cfg))


def make_train(
    space: Space,
    task_cfg: TaskConfig = TaskConfig(),
    cfg: PPOConfig = PPOConfig(),
    physics: str = "jax",
    layout: tuple | None = None,
):
    """Returns `(init, train)` for the space's locomotion task on the engine `physics`; with
    `layout` (limbs, full space) on a size class's template in the full one's layout
    (`Locomotion`).

    init(key) -> Params: one body's controllers (K stacked along a leading axis if K > 1).
    train(keys (B,), morphs (B, ...), params (B, ...)) -> FitnessResult of (B,) arrays: each body
      trains its K controllers from `params`, every world of every body (B x K x
      `worlds_per_controller`) in one flat physics batch (`evojax_morph.physics.engines`),
      then scores them (`eval_episodes` deterministic episodes each, B x K x eval_episodes
      worlds).
    """
    cfg.validate()
    env = Locomotion(space, task_cfg) if layout is None else Locomotion(
        space, task_cfg, layout[0], Locomotion(layout[1], task_cfg))
    networks = make_networks(env, cfg)
    train_learners = make_train_learners(space, env, get_engine(physics), networks, cfg)

    def train(keys: jax.Array, morphs: Morphology, params: Params) -> FitnessResult:
        # Full float32 matmuls wherever train is traced (em.evaluate, the agents' loops): TF32 on
        # GPUs perturbs physics and PPO more than RL tolerates.
        with jax.default_matmul_precision("highest"):
            models = jax.vmap(space.mjx_model)(morphs)
            k, bodies = cfg.controllers, keys.shape[0]
            if k == 1:
                return train_learners(keys, models, params)
            # The K controllers of body b are learners b * K ... b * K + K - 1.
            keys = jax.vmap(lambda key: jax.random.split(key, k))(keys)
            merge = lambda x: x.reshape((bodies * k,) + x.shape[2:])
            out = train_learners(merge(keys), models, jax.tree.map(merge, params))
            out = jax.tree.map(lambda x: x.reshape((bodies, k) + x.shape[1:]), out)
            return FitnessResult(
                params=out.params,
                fitness=out.fitness.mean(1),
                fitness_std=out.fitness.std(1),
                diverged=out.diverged.any(1),
                train_return=out.train_return.mean(1),
                entropy=out.entropy.mean(1),
                distance=out.distance.mean(1),
                upright=out.upright.mean(1),
                env_steps=env_steps_per_morphology(task_cfg, cfg),
            )

    return make_init(env, networks, cfg), train


_split2 = jax.vmap(jax.random.split)  # (L,) keys -> (L, 2) keys


def make_train_learners(space: Space, env: Locomotion, engine: Engine, networks, cfg: PPOConfig):
    """`train_learners(keys (L,), models (B,), params (L, ...)) -> FitnessResult of (L,) arrays`:
    L = B x K learners (controllers), learner l on body l // K with E = `worlds_per_controller`
    worlds, all L x E worlds stepped as one flat batch; PPO updates, then `eval_episodes`
    deterministic episodes per learner (`env_steps`: one learner's)."""
    optimizer = optax.chain(
        optax.clip_by_global_norm(cfg.max_grad_norm), optax.adam(cfg.learning_rate)
    )
    collect = make_collect(env, engine, networks, cfg)
    learn = jax.vmap(make_learn(networks, optimizer, cfg))
    evaluate = make_evaluate_learners(space, env, engine, cfg)
    per_learner = cfg.worlds_per_controller
    by_learner = lambda x: x.reshape((-1, per_learner) + x.shape[1:])
    learner_steps = env_steps_per_morphology(env.cfg, cfg) // cfg.controllers

    def train_learners(keys: jax.Array, models, params: Params) -> FitnessResult:
        learners = keys.shape[0]
        keys, key_reset = jnp.moveaxis(_split2(keys), 1, 0)
        with jax.named_scope("reset"):
            worlds, world_bodies, first = reset_learners(
                space, env, engine, key_reset, models, per_learner
            )  # (L x E,)
        mask = world_bodies.motors[::per_learner]  # (L, A)
        num_active = jnp.maximum(mask.sum(-1), 1)
        net = {"policy": params.policy, "value": params.value}
        opt_state = jax.vmap(optimizer.init)(net)

        def update(carry, _):
            normalizer, net, opt_state, rollout = carry
            with jax.named_scope("collect"):
                rollout, traj = collect(
                    worlds, world_bodies, first, mask, normalizer, net["policy"], rollout
                )
            traj = jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1), traj)  # (L, T, E, ...)
            state, _, last_return, keys = rollout
            with jax.named_scope("learn"):
                normalizer, net, opt_state, keys, entropy = learn(
                    normalizer, net, opt_state, traj, by_learner(state.obs), mask, keys
                )
            metrics = {
                "return": last_return.mean(-1),
                "entropy": entropy / num_active,
                "diverged": traj.diverged.any((1, 2)),
            }
            return (normalizer, net, opt_state, rollout._replace(keys=keys)), metrics

        zeros = jnp.zeros((learners, per_learner), first.reward.dtype)
        carry = (params.normalizer, net, opt_state, Rollout(first, zeros, zeros, keys))
        steps = cfg.num_updates if cfg.train_steps else 0
        (normalizer, net, _, rollout), metrics = jax.lax.scan(update, carry, length=steps)
        params = Params(normalizer=normalizer, policy=net["policy"], value=net["value"])

        # EVALUATE: deterministic policy, eval_episodes episodes from fresh resets
        with jax.named_scope("evaluate"):
            episodes = evaluate(rollout.keys, models, params)
        diverged = episodes.diverged.any(-1) | (metrics["diverged"].any(0) if steps else False)
        returns = episodes.returns
        last = lambda name: metrics[name][-1] if steps else jnp.zeros(learners)
        return FitnessResult(
            params=params,
            fitness=jnp.nan_to_num(returns.mean(-1)),
            fitness_std=jnp.nan_to_num(returns.std(-1)),
            diverged=diverged,
            train_return=last("return"),
            entropy=last("entropy"),
            distance=episodes.distance.mean(-1),
            upright=episodes.upright.mean(-1),
            env_steps=learner_steps,
        )

    return train_learners


def make_collect(env: Locomotion, engine: Engine, networks, cfg: PPOConfig):
    """`collect(worlds, bodies, first, mask, normalizer, policy, rollout) -> (rollout, traj)`:
    `unroll_length` control steps of L learners' stochastic policies (normalizer and policy
    with a leading (L,) axis, mask (L, A)), every world of the flat batch (`bodies` and each
    world's reset state `first`, (L x E,)) stepped at once; a world that is done restarts from
    its `first`. traj: a `Transition` of (T, L, E, ...) arrays."""
    dist = networks.parametric_action_distribution
    policy_apply = jax.vmap(networks.policy_network.apply)
    by_learner = lambda x: x.reshape((-1, cfg.worlds_per_controller) + x.shape[1:])
    flat = lambda x: x.reshape((-1,) + x.shape[2:])

    def collect(worlds, bodies, first: EnvState, mask, normalizer, policy, rollout: Rollout):
        def env_step(rollout: Rollout, _):
            state, episode_return, last_return, keys = rollout
            keys, key_act = jnp.moveaxis(_split2(keys), 1, 0)
            obs = by_learner(state.obs)
            logits = policy_apply(normalizer, policy, obs)
            raw = jax.vmap(dist.sample_no_postprocessing)(logits, key_act)
            nxt = env.step_worlds(engine, worlds, bodies, state, flat(dist.postprocess(raw)))
            reward, done = by_learner(nxt.reward), by_learner(nxt.done)
            episode_return = episode_return + reward
            transition = Transition(
                obs=obs,
                raw_action=raw,
                log_prob=masked_log_prob(dist, logits, raw, mask[:, None]),
                reward=reward,
                terminated=by_learner(nxt.terminated).astype(reward.dtype),
                truncated=by_learner(nxt.truncated).astype(reward.dtype),
                diverged=by_learner(nxt.diverged),
            )
            last_return = jnp.where(done, episode_return, last_return)
            # AUTO-RESET to each world's own first state
            nxt = tree_select(nxt.done, first.replace(data=None), nxt.replace(data=None)).replace(
                data=engine.where(nxt.done, first.data, nxt.data)
            )
            episode_return = jnp.where(by_learner(nxt.steps) == 0, 0.0, episode_return)
            return Rollout(nxt, episode_return, last_return, keys), transition

        return jax.lax.scan(env_step, rollout, length=cfg.unroll_length)

    return collect


def make_learn(networks, optimizer: optax.GradientTransformation, cfg: PPOConfig):
    """`learn(normalizer, net, opt_state, traj, last_obs, mask, key) -> (normalizer, net,
    opt_state, key, entropy)`: one learner's PPO update from its (T, E) trajectory and the
    (E, obs_size) observations after it: `update_epochs` epochs of `num_minibatches`."""
    grad_fn = jax.grad(make_loss(networks, cfg), has_aux=True)
    value_apply = networks.value_network.apply
    samples = cfg.worlds_per_controller * cfg.unroll_length
    minibatch = samples // cfg.num_minibatches

    def learn(normalizer, net, opt_state, traj: Transition, last_obs, mask, key):
        # ADVANTAGES (brax's GAE: a step that hit the time limit is masked out, not bootstrapped)
        if cfg.normalize_observations:
            normalizer = running_statistics.update(normalizer, traj.obs)
        values = value_apply(normalizer, net["value"], traj.obs)
        bootstrap = value_apply(normalizer, net["value"], last_obs)
        targets, advantages = ppo_losses.compute_gae(
            truncation=traj.truncated,
            termination=traj.terminated,
            rewards=traj.reward * cfg.reward_scaling,
            values=values,
            bootstrap_value=bootstrap,
            lambda_=cfg.gae_lambda,
            discount=cfg.discount,
        )

        # UPDATE NETWORK: epochs x minibatches over the flattened (T x E) samples
        flat = jax.tree.map(
            lambda x: x.reshape((samples,) + x.shape[2:]), (traj, advantages, targets)
        )

        def epoch(carry, key):
            net, opt_state = carry
            key_perm, key_loss = jax.random.split(key)
            perm = jax.random.permutation(key_perm, samples)
            shuffled = jax.tree.map(
                lambda x: x[perm].reshape((cfg.num_minibatches, minibatch) + x.shape[1:]), flat
            )

            def sgd(carry, batch):
                net, opt_state = carry
                (transition, adv, tgt), key = batch
                grads, entropy = grad_fn(net, normalizer, transition, adv, tgt, mask, key)
                updates, opt_state = optimizer.update(grads, opt_state)
                return (optax.apply_updates(net, updates), opt_state), entropy

            keys = jax.random.split(key_loss, cfg.num_minibatches)
            (net, opt_state), entropy = jax.lax.scan(sgd, (net, opt_state), (shuffled, keys))
            return (net, opt_state), entropy.mean()

        key, key_epochs = jax.random.split(key)
        (net, opt_state), entropy = jax.lax.scan(
            epoch, (net, opt_state), jax.random.split(key_epochs, cfg.update_epochs)
        )
        return normalizer, net, opt_state, key, entropy.mean()

    return learn


def reset_learners(space: Space, env: Locomotion, engine: Engine, keys, models, n: int):
    """n fresh worlds for each of L learners (keys (L,)), learner l's on body l // (L / B) of
    models (B,) and reset with `split(keys[l], n)`, as one flat batch of L x n worlds:
    `(worlds, bodies, state)`, `worlds` from `engine.prepare`, `bodies` and `state` (L x n,)."""
    per_body = keys.shape[0] // models.body_mass.shape[0] * n
    worlds = engine.prepare(space, models, per_body)
    bodies = repeat_worlds(jax.vmap(env.body)(models), per_body)
    reset_keys = jax.vmap(lambda key: jax.random.split(key, n))(keys)
    state = env.reset_worlds(engine, worlds, bodies, reset_keys.reshape((-1,) + keys.shape[1:]))
    return worlds, bodies, state


class Episodes(NamedTuple):
    """What the evaluation episodes of L learners measured, each (L, eval_episodes)."""

    returns: jax.Array  # the return, up to the end of the episode (a fall, or its length)
    diverged: jax.Array  # bool: a simulation diverged while the episode ran
    distance: jax.Array  # metres the trunk moved forward (+x) before the episode ended
    upright: jax.Array  # the fraction of episode_length before a fall: 1 for a whole episode


def make_evaluate_learners(space: Space, env: Locomotion, engine: Engine, cfg: PPOConfig):
    """`evaluate(keys (L,), models (B,), params (L, ...)) -> Episodes` of (L, eval_episodes)
    arrays: L learners' deterministic policies, the episodes of learner l reset with
    `split(keys[l], eval_episodes)`."""
    policy = jax.vmap(make_deterministic_policy(make_networks(env, cfg)))
    episodes = cfg.eval_episodes

    def evaluate(keys: jax.Array, models, params: Params) -> Episodes:
        learners = keys.shape[0]
        worlds, world_bodies, first = reset_learners(space, env, engine, keys, models, episodes)
        by_learner = lambda x: x.reshape((learners, episodes) + x.shape[1:])

        def observe(carry, state):  # what each world's episode adds up, until it ends
            out, alive = carry
            on = lambda x: jnp.where(alive, by_learner(x), 0.0)
            up = alive & ~by_learner(state.terminated)  # upright after this step
            out = Episodes(
                returns=out.returns + on(state.reward),
                diverged=out.diverged | (alive & by_learner(state.diverged)),
                distance=out.distance + on(state.forward),
                upright=out.upright + up,
            )
            return (out, alive & ~by_learner(state.done)), None

        zeros = jnp.zeros((learners, episodes), first.reward.dtype)
        alive = jnp.ones((learners, episodes), bool)
        length = env.cfg.episode_length
        _, (out, _), _ = rollout(
            lambda state, action: env.step_worlds(engine, worlds, world_bodies, state, action),
            lambda state, _: policy(params, by_learner(state.obs)).reshape(-1, env.action_size),
            first,
            length,
            observe,
            (Episodes(zeros, ~alive, zeros, zeros), alive),
        )
        return out._replace(upright=out.upright / length)

    return evaluate


def env_steps_per_morphology(task_cfg: TaskConfig, cfg: PPOConfig) -> int:
    """Control steps one `train` call takes per morphology: training plus evaluation."""
    per_update = cfg.worlds_per_controller * cfg.unroll_length
    train = cfg.num_updates * per_update if cfg.train_steps else 0
    return cfg.controllers * (train + cfg.eval_episodes * task_cfg.episode_length)
