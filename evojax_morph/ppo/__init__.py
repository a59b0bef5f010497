"""The inner PPO: one pure function trains the controllers of a batch of different bodies.

`make_train(space, task_cfg, ppo_cfg, physics)` returns `init(key) -> Params` and `train(keys,
morphs, params) -> FitnessResult` (`evojax_morph.fitness_result`: the PPO fitness kind returns
it as it is), batched over bodies at its top: `jax.jit(train)` trains B bodies, each with
`controllers` x `worlds_per_controller` worlds, in one compiled call. Policies, values and
updates are vmapped over the B x K controllers; the physics of a control step is ONE step of all
B x K x `worlds_per_controller` worlds on the engine `physics` names (`physics.engines`): the
flat batch MuJoCo Warp needs, and on the JAX engine a vmap over bodies around their worlds. With
`controllers` K > 1 every body trains K independent controllers side by side (parameters with a
leading (K,) axis, all inherited by a child) and its fitness is their mean: one PPO run is a
noisy measure of a body, since a controller either finds a gait or does not (docs/benchmarks.md,
"Reliability of the PPO fitness"). It is built from brax's PPO parts (networks, GAE, running
observation statistics); the log-probability and entropy are our own
(`evojax_morph.ppo.networks`, with the parameters and the loss; re-exported here), masked to the
motors a body has, since brax's sum over every action dimension of the padded template.
Parameter shapes are the same for every body of a space, so a child can start from its parent's
controller (policy inheritance).

The pieces, one factory each in `evojax_morph.ppo.train`, as purejaxrl's scans nest: `make_train`
(K controllers per body) > `make_train_learners` (the update scan) > `make_collect` (COLLECT
TRAJECTORIES, the env-step scan) and `make_learn` (GAE, then epochs > minibatches of
`make_loss`); then `make_evaluate_learners` scores the trained controllers in episodes of
`tasks.rollout`. Their calls run in named scopes ("reset", "collect", "learn", "evaluate"), to
which xprof's trace viewer attributes the device's time (`python -m experiments.bench_fitness
--trace DIR`); they change no computation.
"""

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
from evojax_morph.ppo.train import (
    Episodes,
    env_steps_per_morphology,
    make_evaluate_learners,
    make_learn,
    make_policy,
    make_train,
)

__all__ = [
    "Episodes",
    "PPOConfig",
    "Params",
    "Transition",
    "env_steps_per_morphology",
    "make_deterministic_policy",
    "make_evaluate_learners",
    "make_init",
    "make_learn",
    "make_loss",
    "make_networks",
    "make_policy",
    "make_train",
    "masked_log_prob",
]
