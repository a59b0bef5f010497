"""Fitness kinds, registered by name; `evojax_morph.fitnesses.batched` evaluates any of them.

To add a kind: write a module of this package defining its `make(space, cfg) -> (init,
evaluate)`, its settings check and its typical scale as a `Fitness`, with its rules (the
engines it steps on, its default task, its check of the files it reads), and list it below. Its
own settings, if any, are a frozen dataclass with defaults, its `Fitness.params`: `make` reads
them from `cfg.params`, and each field becomes the run command's `--fitness.FIELD`.
"""

from evojax_morph.fitnesses import ppo, predefined, table, tame
from evojax_morph.fitnesses.base import (
    Fitness,
    FitnessConfig,
    FitnessResult,
    Inputs,
    fitness_params,
    get_fitness,
    list_fitnesses,
    register,
    resolve_physics,
)
from evojax_morph.fitnesses.ppo import standard_ppo

register(ppo.FITNESS, predefined.FITNESS, tame.FITNESS, table.FITNESS)

__all__ = ["Fitness", "FitnessConfig", "FitnessResult", "Inputs", "fitness_params", "get_fitness",
           "list_fitnesses", "register", "resolve_physics", "standard_ppo"]
