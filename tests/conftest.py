"""Shared test set-up: CPU backend, a persistent compilation cache, and small helpers."""

import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax
import pytest

# Compiled programs survive between runs (CI reuses the machine's cache directory).
jax.config.update(
    "jax_compilation_cache_dir",
    os.environ.get("EVOJAX_MORPH_JAX_CACHE", os.path.expanduser("~/.cache/evojax_morph/jax")),
)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)

import evojax_morph as em


@pytest.fixture(scope="session", params=["bad_walker", "constructor", "length_walker"])
def space(request):
    return em.make_space(request.param)
