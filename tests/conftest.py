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


def pytest_collection_modifyitems(config, items):
    """The longest file first: with two workers taking a file each (pyproject's addopts), the
    4-device run (3 to 5 minutes) then overlaps the rest instead of ending the suite alone."""
    items.sort(key=lambda item: item.path.name != "test_sharding.py")
