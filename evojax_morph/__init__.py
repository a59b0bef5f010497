"""evojax_morph: robot morphology design as a Markov Decision Process, on JAX and MJX."""

import evojax_morph.physics.templates  # noqa: F401  (first: it imports mjx quietly)
from evojax_morph.agents import AskTell, ask_tell, list_agents
from evojax_morph.figures.video import render as render_video
from evojax_morph.figures.video import replay
from evojax_morph.fitnesses import FitnessConfig, FitnessResult, list_fitnesses, standard_ppo
from evojax_morph.fitnesses.batched import evaluate, init_params, make_env
from evojax_morph.mdp import EvolutionEnv
from evojax_morph.morphology import Morphology, format_tree, stack, unstack
from evojax_morph.physics.determinism import (
    all_reduce_workaround,
    cpu_scheduler_workaround,
    deterministic_gpu,
    persistent_cache,
)
from evojax_morph.physics.engines import list_engines
from evojax_morph.ppo import Params, PPOConfig, make_train
from evojax_morph.records.bodylog import best_bodies
from evojax_morph.records.saved_controllers import SavedController
from evojax_morph.records.saved_controllers import load as load_controller
from evojax_morph.search.confirm import Confirmed, confirm
from evojax_morph.sharding import batch_mesh, init_distributed
from evojax_morph.spaces import Space, list_spaces, make_space
from evojax_morph.tasks import Locomotion, TaskConfig, list_tasks, make_task

# The one side effect of importing evojax_morph, and it must stay here: two XLA flags. XLA's
# CPU runtime of jaxlib 0.10.2 can deadlock running a large vmapped MJX program (the
# Constructor's template, 50 bodies), and XLA's one-shot all-reduce failed on 2 GPUs with jax
# 0.12.0 (determinism.py says both). XLA reads XLA_FLAGS once, when the first backend starts, so
# the flags must be in before any user code runs JAX. It only appends `determinism.CPU_FLAG` and
# `ALL_REDUCE_FLAG`, each where XLA_FLAGS does not set it already and no backend is up
# (tests/test_determinism.py). Matplotlib's backend is left alone: the figures draw with Agg
# canvases of their own (`plots`, `video`).
cpu_scheduler_workaround()
all_reduce_workaround()

__all__ = [
    "AskTell",
    "Confirmed",
    "EvolutionEnv",
    "FitnessConfig",
    "FitnessResult",
    "Locomotion",
    "Morphology",
    "PPOConfig",
    "Params",
    "SavedController",
    "Space",
    "TaskConfig",
    "all_reduce_workaround",
    "ask_tell",
    "batch_mesh",
    "best_bodies",
    "confirm",
    "cpu_scheduler_workaround",
    "deterministic_gpu",
    "evaluate",
    "format_tree",
    "init_distributed",
    "init_params",
    "list_agents",
    "list_engines",
    "list_fitnesses",
    "list_spaces",
    "list_tasks",
    "load_controller",
    "make_env",
    "make_space",
    "make_task",
    "make_train",
    "persistent_cache",
    "render_video",
    "replay",
    "stack",
    "standard_ppo",
    "unstack",
]
__version__ = "0.1.0"


def __getattr__(name: str):
    """`GymEvolutionEnv` and `SB3EvolutionEnv` on first use: they need the optional gymnasium
    (the `gym` extra) and stable-baselines3 (the `sb3` extra), so they are left out of
    `__all__`."""
    if name == "GymEvolutionEnv":
        from evojax_morph.envs.gym_env import GymEvolutionEnv

        return GymEvolutionEnv
    if name == "SB3EvolutionEnv":
        from evojax_morph.envs.sb3_env import SB3EvolutionEnv

        return SB3EvolutionEnv
    raise AttributeError(f"module 'evojax_morph' has no attribute {name!r}")
