"""The TAME fitness (task-agnostic), with a classifier trained by `python -m evojax_morph.tame`.

F(m) from fresh random-primitive rollouts of each body, scored by the saved classifier
(`evojax_morph.tame`); nothing is trained per body.
"""

from __future__ import annotations

import functools
import json
from pathlib import Path

import jax

from evojax_morph.fitnesses.base import (
    Fitness,
    FitnessConfig,
    FitnessResult,
    Inputs,
    untrained_result,
)
from evojax_morph.spaces import Space, make_space
from evojax_morph.tame import Pretrained, Tame, over_bodies


def validate(cfg: FitnessConfig) -> None:
    if not cfg.classifier:
        raise ValueError(
            "the tame fitness needs classifier= the directory of a trained TAME classifier "
            "(train one with `python -m evojax_morph.tame --space SPACE --out DIR`)"
        )


def _other_space(classifier: str, trained_on: str, space: str) -> str:
    return (f"the TAME classifier in {classifier!r} was trained on {trained_on}, another space "
            f"than {space}")


def check(inputs: Inputs) -> None:
    """A classifier in `inputs.classifier`, trained on the space."""
    meta = Path(inputs.classifier) / "tame.json"
    if not inputs.classifier or not meta.exists():
        raise ValueError(
            "--fitness tame needs --classifier DIR, a classifier trained by "
            f"`python -m evojax_morph.tame --space {inputs.space} --out DIR`"
        )
    train = f"train it again with `python -m evojax_morph.tame --space {inputs.space} --out DIR`"
    try:
        trained_on = json.loads(meta.read_text())["space"]
    except (ValueError, KeyError, TypeError) as e:  # not JSON, or not a classifier's
        raise ValueError(f"{str(meta)!r} is not a TAME classifier's record ({type(e).__name__}: "
                         f"{e}); {train}") from None
    if not (meta.parent / "params").is_dir():
        raise ValueError(f"the TAME classifier in {inputs.classifier!r} has tame.json but no "
                         f"params/ (its weights); {train}")
    if trained_on != inputs.space:
        raise ValueError(_other_space(inputs.classifier, trained_on, inputs.space))


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
        raise ValueError(_other_space(cfg.classifier, trained_on, space.name))
    env_steps = tame_cfg.episodes * tame_cfg.episode_length

    def evaluate(keys: jax.Array, morphs, params) -> FitnessResult:
        f, diverged = fitness(keys, morphs)
        return untrained_result(f, diverged, params, env_steps)

    return None, evaluate


FITNESS = Fitness(name="tame", validate=validate, scale=lambda space: 1.0, make=make,
                  engines=("jax",), check=check)
