"""evojax_morph: robot morphology design as a Markov Decision Process, on JAX and MJX."""

from evojax_morph import physics  # noqa: F401  (first: it imports mjx quietly)
from evojax_morph.determinism import cpu_scheduler_workaround, deterministic_gpu
from evojax_morph.fitness import evaluate, init_params
from evojax_morph.fitnesses import FitnessConfig, FitnessResult, list_fitnesses, standard_ppo
from evojax_morph.locomotion import Locomotion, TaskConfig
from evojax_morph.morphology import Morphology, format_tree, stack, unstack
from evojax_morph.ppo import Params, PPOConfig, make_train
from evojax_morph.sharding import batch_mesh, init_distributed
from evojax_morph.spaces import Space, list_spaces, make_space

cpu_scheduler_workaround()  # before any JAX backend starts: see evojax_morph/determinism.py

__all__ = [
    "FitnessConfig",
    "FitnessResult",
    "Locomotion",
    "Morphology",
    "PPOConfig",
    "Params",
    "Space",
    "TaskConfig",
    "batch_mesh",
    "cpu_scheduler_workaround",
    "deterministic_gpu",
    "evaluate",
    "format_tree",
    "init_distributed",
    "init_params",
    "list_fitnesses",
    "list_spaces",
    "make_space",
    "make_train",
    "stack",
    "standard_ppo",
    "unstack",
]
__version__ = "0.1.0"
