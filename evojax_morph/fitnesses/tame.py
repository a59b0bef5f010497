"""The TAME fitness (task-agnostic), with a classifier trained by `python -m evojax_morph.tame`.

F(m) from fresh random-primitive rollouts of each body, scored by the saved classifier
(`evojax_morph.tame`); nothing is trained per body.
"""

from __future__ import annotations

import functools

import jax

from evojax_morph.fitnesses.base import Fitness, FitnessConfig, FitnessResult, untrained_result
from evojax_morph.spaces import Space, make_space
from evojax_morph.tame import Pretrained, Tame, over_bodies


def validate(cfg: FitnessConfig) -> None:
    if cfg.physics != "jax":
        raise ValueError(f"the tame fitness runs on the JAX engine only, not {cfg.physics!r}")
    if not cfg.classifier:
        raise ValueError(
            "the tame fitness needs classifier= the directory of a trained TAME classifier "
            "(train one with `python -m evojax_morph.tame --space SPACE --out DIR`)"
        )


@functools.lru_cache(maxsize=4)
def load(path: str):
    """(space name, TameConfig, fitness(keys (B,), morphs (B, ...)) -> (fitness (B,), diverged
    (B,))) of a saved classifier, mapped over bodies; cached per path."""
    pre = Pretrained.load(path)
    tame = Tame(make_space(pre.space), pre.config)
    params = pre.params
    fitness = over_bodies(lambda key, m: tame.fitness(params, key, m), pre.config.episodes)
    return pre.space, pre.config, fitness


def make(space: Space, cfg: FitnessConfig):
    trained_on, tame_cfg, fitness = load(str(cfg.classifier))
    if trained_on != space.name:
        raise ValueError(
            f"the TAME classifier in {cfg.classifier!r} was trained on {trained_on}, "
            f"not {space.name}"
        )
    env_steps = tame_cfg.episodes * tame_cfg.episode_length

    def evaluate(keys: jax.Array, morphs, params) -> FitnessResult:
        f, diverged = fitness(keys, morphs)
        return untrained_result(f, diverged, params, env_steps)

    return None, evaluate


FITNESS = Fitness(name="tame", validate=validate, scale=lambda space: 1.0, make=make)
