"""The inner PPO: one pure function trains the controllers of a batch of different bodies.

`make_train(space, task_cfg, ppo_cfg, physics)` returns `init(key) -> Params` and
`train(keys, morphs, params) -> TrainResult`, batched over bodies at its top: `jax.jit(train)`
trains B bodies, each with `controllers` x `num_envs` worlds, in one compiled call. Policies,
values and updates are vmapped over the B x K controllers; the physics of a control step is ONE
step of all B x K x num_envs worlds on the engine `physics` names (`evojax_morph.engines`): the
flat batch MuJoCo Warp needs, and on the JAX engine a vmap over bodies around their worlds. With
`controllers` K > 1 every body trains K independent controllers side by side (parameters with a
leading (K,) axis, all inherited by a child) and its fitness is their mean: one PPO run is a
noisy measure of a body, since a controller either finds a gait or does not
(docs/benchmarks.md, "Reliability of the PPO fitness"). It is built from brax's PPO
parts (networks, GAE, running observation statistics); the log-probability and entropy are our
own, masked to the motors a body has, since brax's sum over every action dimension of the
padded template. Parameter shapes are the same for every body of a space, so a child can start
from its parent's controller (policy inheritance).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax
from brax.training import distribution
from brax.training.acme import running_statistics
from brax.training.agents.ppo import losses as ppo_losses
from brax.training.agents.ppo import networks as ppo_networks
from flax import struct

from evojax_morph.engines import get_engine, repeat_worlds
from evojax_morph.locomotion import Locomotion, TaskConfig
from evojax_morph.morphology import Morphology, tree_select
from evojax_morph.spaces import Space


@dataclasses.dataclass(frozen=True)
class PPOConfig:
    """Inner PPO settings; budgets are per morphology."""

    train_steps: int = 100_000  # control steps of training, over all envs
    num_envs: int = 32  # parallel worlds per morphology
    unroll_length: int = 20  # control steps per env between updates
    num_minibatches: int = 4
    update_epochs: int = 8
    learning_rate: float = 1e-3
    discount: float = 0.97
    gae_lambda: float = 0.95
    clip_eps: float = 0.3
    entropy_cost: float = 1e-2
    vf_coef: float = 0.5
    max_grad_norm: float = 1.0
    reward_scaling: float = 1.0
    normalize_observations: bool = True
    policy_hidden: tuple[int, ...] = (32, 32)
    value_hidden: tuple[int, ...] = (64, 64)
    eval_episodes: int = 4  # deterministic episodes of episode_length after training
    controllers: int = 1  # K independent controllers per body; the fitness is their mean

    @property
    def num_updates(self) -> int:
        return max(1, self.train_steps // (self.num_envs * self.unroll_length))

    def validate(self) -> None:
        batch = self.num_envs * self.unroll_length
        if self.train_steps < 0 or self.num_envs < 1 or self.unroll_length < 1:
            raise ValueError("train_steps must be >= 0, num_envs and unroll_length >= 1")
        if batch % self.num_minibatches:
            raise ValueError(f"num_envs x unroll_length ({batch}) must divide into {self.num_minibatches} minibatches")
        if self.eval_episodes < 1 or self.controllers < 1:
            raise ValueError("eval_episodes and controllers must be at least 1")


class Params(NamedTuple):
    """A controller: what a child inherits from its parent."""

    normalizer: running_statistics.RunningStatisticsState
    policy: dict
    value: dict


class Transition(NamedTuple):
    obs: jax.Array  # (T, E, obs_size)
    raw_action: jax.Array  # (T, E, A) pre-tanh
    log_prob: jax.Array  # (T, E)
    reward: jax.Array  # (T, E)
    terminated: jax.Array  # (T, E) float
    truncated: jax.Array  # (T, E) float
    diverged: jax.Array  # (T, E) bool


@struct.dataclass
class TrainResult:
    params: Params  # the trained controller; with K > 1 controllers, a leading (K,) axis
    fitness: jax.Array  # (): mean return of the deterministic evaluation episodes (of all K)
    fitness_std: jax.Array  # (): standard deviation of the K controllers' mean returns (K > 1),
    # else of the evaluation episodes' returns
    diverged: jax.Array  # () bool: some simulation diverged (its reward was zeroed)
    train_return: jax.Array  # (): mean over envs of each env's last finished training episode
    entropy: jax.Array  # (): policy entropy per active motor at the end of training


def masked_log_prob(dist: distribution.NormalTanhDistribution, logits, raw_action, mask):
    """log pi(a) summed over the active action dimensions only.

    Args:
      dist: brax's tanh-normal action distribution.
      logits: (..., 2A) policy output.
      raw_action: (..., A) pre-tanh action.
      mask: (A,) bool, the motors the body has.
    Returns:
      (...,) log-probability of tanh(raw_action).
    """
    per_dim = dist.create_dist(logits).log_prob(raw_action)
    per_dim -= distribution.TanhBijector().forward_log_det_jacobian(raw_action)
    return jnp.sum(jnp.where(mask, per_dim, 0.0), axis=-1)


def masked_entropy(dist: distribution.NormalTanhDistribution, logits, key, mask):
    """Entropy of the tanh-normal over active dimensions, estimated with one sample as brax does."""
    normal = dist.create_dist(logits)
    per_dim = normal.entropy() + distribution.TanhBijector().forward_log_det_jacobian(normal.sample(key))
    return jnp.sum(jnp.where(mask, per_dim, 0.0), axis=-1)


def _networks(env: Locomotion, cfg: PPOConfig):
    return ppo_networks.make_ppo_networks(
        env.obs_size,
        env.action_size,
        preprocess_observations_fn=running_statistics.normalize
        if cfg.normalize_observations
        else (lambda obs, _: obs),
        policy_hidden_layer_sizes=cfg.policy_hidden,
        value_hidden_layer_sizes=cfg.value_hidden,
    )


def make_policy(space: Space, task_cfg: TaskConfig = TaskConfig(), cfg: PPOConfig = PPOConfig()):
    """`policy(params, obs) -> action`: the deterministic actions (..., A) of one controller
    (no leading K axis) for (..., obs_size) observations, as the evaluation episodes act."""
    networks = _networks(Locomotion(space, task_cfg), cfg)

    def policy(params: Params, obs: jax.Array) -> jax.Array:
        logits = networks.policy_network.apply(params.normalizer, params.policy, obs)
        return networks.parametric_action_distribution.mode(logits)

    return policy


def make_evaluate(space: Space, task_cfg: TaskConfig = TaskConfig(), cfg: PPOConfig = PPOConfig()):
    """`evaluate(key, model, params) -> (returns, diverged)`, both (eval_episodes,): one
    controller's deterministic policy (`make_policy`) for `eval_episodes` episodes from resets
    with the keys `split(key, eval_episodes)`, as the fitness scores a trained controller."""
    env = Locomotion(space, task_cfg)
    policy = make_policy(space, task_cfg, cfg)

    def evaluate(key, model, params: Params):
        state = jax.vmap(env.reset, (0, None))(jax.random.split(key, cfg.eval_episodes), model)
        step = jax.vmap(env.step, (None, 0, 0))

        def body(carry, _):
            state, returns, alive, diverged = carry
            state = step(model, state, policy(params, state.obs))
            returns = returns + jnp.where(alive, state.reward, 0.0)
            diverged = diverged | (alive & state.diverged)
            return (state, returns, alive & ~state.done, diverged), None

        zeros = jnp.zeros(cfg.eval_episodes, state.reward.dtype)
        alive = jnp.ones(cfg.eval_episodes, bool)
        (_, returns, _, diverged), _ = jax.lax.scan(
            body, (state, zeros, alive, ~alive), length=task_cfg.episode_length
        )
        return returns, diverged

    return evaluate


def make_train(
    space: Space,
    task_cfg: TaskConfig = TaskConfig(),
    cfg: PPOConfig = PPOConfig(),
    physics: str = "jax",
):
    """Returns `(init, train)` for the space's locomotion task on the engine `physics`.

    init(key) -> Params: one body's controllers (K stacked along a leading axis if K > 1).
    train(keys (B,), morphs (B, ...), params (B, ...)) -> TrainResult of (B,) arrays: each body
      trains its K controllers from `params`, every world of every body (B x K x num_envs) in
      one flat physics batch (`evojax_morph.engines`), then scores them (`eval_episodes`
      deterministic episodes each, B x K x eval_episodes worlds).
    """
    cfg.validate()
    engine = get_engine(physics)
    env = Locomotion(space, task_cfg)
    networks = _networks(env, cfg)
    dist = networks.parametric_action_distribution
    policy_apply = networks.policy_network.apply
    value_apply = networks.value_network.apply
    optimizer = optax.chain(optax.clip_by_global_norm(cfg.max_grad_norm), optax.adam(cfg.learning_rate))
    num_envs, horizon, episodes = cfg.num_envs, cfg.unroll_length, cfg.eval_episodes
    policy = make_policy(space, task_cfg, cfg)
    minibatch = num_envs * horizon // cfg.num_minibatches
    split2 = jax.vmap(jax.random.split)  # (L,) keys -> (L, 2) keys

    def init(key: jax.Array) -> Params:
        """Fresh parameters: one controller, or K stacked along a leading axis."""
        if cfg.controllers == 1:
            return init_one(key)
        return jax.vmap(init_one)(jax.random.split(key, cfg.controllers))

    def init_one(key: jax.Array) -> Params:
        key_policy, key_value = jax.random.split(key)
        obs_spec = jax.ShapeDtypeStruct((env.obs_size,), jnp.zeros(()).dtype)
        return Params(
            normalizer=running_statistics.init_state(obs_spec),
            policy=networks.policy_network.init(key_policy),
            value=networks.value_network.init(key_value),
        )

    def loss_fn(net, normalizer, batch, advantages, targets, mask, key):
        logits = policy_apply(normalizer, net["policy"], batch.obs)
        log_prob = masked_log_prob(dist, logits, batch.raw_action, mask)
        ratio = jnp.exp(log_prob - batch.log_prob)
        advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
        clipped = jnp.clip(ratio, 1 - cfg.clip_eps, 1 + cfg.clip_eps)
        policy_loss = -jnp.mean(jnp.minimum(ratio * advantages, clipped * advantages))
        value = value_apply(normalizer, net["value"], batch.obs)
        value_loss = jnp.mean((targets - value) ** 2)
        entropy = jnp.mean(masked_entropy(dist, logits, key, mask))
        loss = policy_loss + cfg.vf_coef * value_loss - cfg.entropy_cost * entropy
        return loss, entropy

    def train(keys: jax.Array, morphs: Morphology, params: Params) -> TrainResult:
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
            return TrainResult(
                params=out.params,
                fitness=out.fitness.mean(1),
                fitness_std=out.fitness.std(1),
                diverged=out.diverged.any(1),
                train_return=out.train_return.mean(1),
                entropy=out.entropy.mean(1),
            )

    def train_learners(keys: jax.Array, models, params: Params) -> TrainResult:
        """L = B x K learners (controllers), each on its body's model with num_envs worlds."""
        learners, bodies = keys.shape[0], models.body_mass.shape[0]
        per_body = learners // bodies
        worlds = engine.prepare(space, models, per_body * num_envs)
        body = jax.vmap(env.body)(models)
        world_bodies = repeat_worlds(body, per_body * num_envs)  # (L x E,)
        mask = repeat_worlds(body.motors, per_body)  # (L, A)
        num_active = jnp.maximum(mask.sum(-1), 1)
        by_learner = lambda x: x.reshape((learners, num_envs) + x.shape[1:])
        flat = lambda x: x.reshape((learners * num_envs,) + x.shape[2:])

        keys, key_reset = jnp.moveaxis(split2(keys), 1, 0)
        reset_keys = jax.vmap(lambda key: jax.random.split(key, num_envs))(key_reset)
        first = env.reset_worlds(engine, worlds, world_bodies, flat(reset_keys))
        net = {"policy": params.policy, "value": params.value}
        opt_state = jax.vmap(optimizer.init)(net)

        def update(carry, _):
            normalizer, net, opt_state, state, episode_return, last_return, keys = carry

            # COLLECT TRAJECTORIES: every learner acts, then every world steps in one batch
            def env_step(carry, _):
                state, episode_return, last_return, keys = carry
                keys, key_act = jnp.moveaxis(split2(keys), 1, 0)
                obs = by_learner(state.obs)
                logits = jax.vmap(policy_apply)(normalizer, net["policy"], obs)
                raw = jax.vmap(dist.sample_no_postprocessing)(logits, key_act)
                nxt = env.step_worlds(engine, worlds, world_bodies, state, flat(dist.postprocess(raw)))
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
                return (nxt, episode_return, last_return, keys), transition

            (state, episode_return, last_return, keys), traj = jax.lax.scan(
                env_step, (state, episode_return, last_return, keys), length=horizon
            )
            traj = jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1), traj)  # (L, T, E, ...)
            normalizer, net, opt_state, keys, entropy = jax.vmap(learn)(
                normalizer, net, opt_state, traj, by_learner(state.obs), mask, keys
            )
            metrics = {
                "return": last_return.mean(-1),
                "entropy": entropy / num_active,
                "diverged": traj.diverged.any((1, 2)),
            }
            return (normalizer, net, opt_state, state, episode_return, last_return, keys), metrics

        def learn(normalizer, net, opt_state, traj, last_obs, mask, key):
            """One learner's PPO update from its (T, E) trajectory."""
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
            flat_samples = lambda x: x.reshape((num_envs * horizon,) + x.shape[2:])
            samples = jax.tree.map(flat_samples, (traj, advantages, targets))

            def epoch(carry, key):
                net, opt_state = carry
                key_perm, key_loss = jax.random.split(key)
                perm = jax.random.permutation(key_perm, num_envs * horizon)
                shuffled = jax.tree.map(lambda x: x[perm].reshape((cfg.num_minibatches, minibatch) + x.shape[1:]), samples)

                def sgd(carry, batch):
                    net, opt_state = carry
                    (transition, adv, tgt), key = batch
                    grads, entropy = jax.grad(loss_fn, has_aux=True)(net, normalizer, transition, adv, tgt, mask, key)
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

        zeros = jnp.zeros((learners, num_envs), first.reward.dtype)
        carry = (params.normalizer, net, opt_state, first, zeros, zeros, keys)
        steps = cfg.num_updates if cfg.train_steps else 0
        (normalizer, net, _, _, _, _, keys), metrics = jax.lax.scan(update, carry, length=steps)
        params = Params(normalizer=normalizer, policy=net["policy"], value=net["value"])

        # EVALUATE: deterministic policy, eval_episodes episodes from fresh resets
        returns, eval_diverged = evaluate(keys, models, params)
        diverged = eval_diverged.any(-1) | (metrics["diverged"].any(0) if steps else False)
        last = lambda name: metrics[name][-1] if steps else jnp.zeros(learners)
        return TrainResult(
            params=params,
            fitness=jnp.nan_to_num(returns.mean(-1)),
            fitness_std=jnp.nan_to_num(returns.std(-1)),
            diverged=diverged,
            train_return=last("return"),
            entropy=last("entropy"),
        )

    def evaluate(keys: jax.Array, models, params: Params):
        """(L, eval_episodes) returns and diverged flags of L learners' deterministic policies,
        the episodes of learner l reset with `split(keys[l], eval_episodes)`, as `make_evaluate`
        scores one controller."""
        learners, bodies = keys.shape[0], models.body_mass.shape[0]
        per_body = learners // bodies * episodes
        worlds = engine.prepare(space, models, per_body)
        world_bodies = repeat_worlds(jax.vmap(env.body)(models), per_body)
        reset_keys = jax.vmap(lambda key: jax.random.split(key, episodes))(keys)
        state = env.reset_worlds(engine, worlds, world_bodies, reset_keys.reshape((-1,) + keys.shape[1:]))
        by_learner = lambda x: x.reshape((learners, episodes) + x.shape[1:])

        def body(carry, _):
            state, returns, alive, diverged = carry
            action = jax.vmap(policy)(params, by_learner(state.obs))
            state = env.step_worlds(engine, worlds, world_bodies, state, action.reshape(-1, env.action_size))
            returns = returns + jnp.where(alive, by_learner(state.reward), 0.0)
            diverged = diverged | (alive & by_learner(state.diverged))
            return (state, returns, alive & ~by_learner(state.done), diverged), None

        zeros = jnp.zeros((learners, episodes), state.reward.dtype)
        alive = jnp.ones((learners, episodes), bool)
        (_, returns, _, diverged), _ = jax.lax.scan(
            body, (state, zeros, alive, ~alive), length=task_cfg.episode_length
        )
        return returns, diverged

    return init, train


def env_steps_per_morphology(task_cfg: TaskConfig, cfg: PPOConfig) -> int:
    """Control steps one `train` call takes per morphology: training plus evaluation."""
    train = cfg.num_updates * cfg.num_envs * cfg.unroll_length if cfg.train_steps else 0
    return cfg.controllers * (train + cfg.eval_episodes * task_cfg.episode_length)
