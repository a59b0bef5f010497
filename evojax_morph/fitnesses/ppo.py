"""The PPO fitness (NGE-style): the return of a controller trained with PPO on the body.

Training starts from the controller it is given (a parent's: policy inheritance); the fitness is
the mean return of the deterministic evaluation episodes after training (`evojax_morph.ppo`).
Every world of a fitness call (bodies x controllers x envs) steps as one flat batch on the engine
`FitnessConfig.physics` names (`evojax_morph.physics.engines`).
"""

from __future__ import annotations

from evojax_morph import ppo
from evojax_morph.fitnesses.base import Fitness, FitnessConfig
from evojax_morph.physics import classes
from evojax_morph.spaces import Space


def standard_ppo(train_steps: int, controllers: int = 1) -> ppo.PPOConfig:
    """The inner PPO that runs, experiments and tests use, at a budget of `train_steps` per
    controller, with `controllers` independent controllers per body (the fitness is their mean;
    docs/benchmarks.md measures how each more controller cuts the noise, and what it costs)."""
    return ppo.PPOConfig(train_steps=train_steps, worlds_per_controller=16, unroll_length=20,
                         controllers=controllers)


def validate(cfg: FitnessConfig) -> None:
    cfg.ppo.validate()


def make(space: Space, cfg: FitnessConfig):
    init, train = ppo.make_train(space, cfg.task, cfg.ppo, cfg.physics)
    if cfg.classes and space.size_classes():
        train = classes.grouped(space, train, [
            ppo.make_train(c.space, cfg.task, cfg.ppo, cfg.physics, (c.limbs, space))[1]
            for c, _ in space.size_classes()])
    return init, train  # train returns the FitnessResult itself


FITNESS = Fitness(
    name="ppo", validate=validate, scale=lambda space: 100.0, make=make, trains_controllers=True
)
