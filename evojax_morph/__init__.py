"""evojax_morph: robot morphology design as a Markov Decision Process, on JAX and MJX."""

from evojax_morph.morphology import Morphology, format_tree, stack, unstack
from evojax_morph.spaces import Space, list_spaces, make_space

__all__ = ["Morphology", "Space", "format_tree", "list_spaces", "make_space", "stack", "unstack"]
__version__ = "0.1.0"
