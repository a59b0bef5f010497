"""Shared test set-up: CPU backend, a persistent compilation cache, and small helpers."""

import os
import subprocess
import sys

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax
import pytest

# Compiled programs survive between runs (CI reuses the machine's cache directory).
CACHE = os.environ.get("EVOJAX_MORPH_JAX_CACHE", os.path.expanduser("~/.cache/evojax_morph/jax"))
jax.config.update("jax_compilation_cache_dir", CACHE)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)

import evojax_morph as em


@pytest.fixture(scope="session", params=["bad_walker", "constructor", "length_walker"])
def space(request):
    return em.make_space(request.param)


def pytest_collection_modifyitems(config, items):
    """The longest files first: with two workers taking a file each (pyproject's addopts), the
    two 4-device subprocesses (test_sharding*.py) start at once, one per worker, and overlap
    the rest instead of ending the suite alone."""
    items.sort(key=lambda item: not item.path.name.startswith("test_sharding"))


def on_four_devices(script: str, *args: str) -> subprocess.CompletedProcess:
    """Runs `script` with `args` in a Python of 4 CPU devices (JAX fixes the count at start)."""
    env = dict(
        os.environ, JAX_PLATFORMS="cpu", XLA_FLAGS="--xla_force_host_platform_device_count=4"
    )
    env.setdefault("JAX_COMPILATION_CACHE_DIR", CACHE)
    proc = subprocess.run(
        [sys.executable, "-c", script, *args], capture_output=True, text=True, env=env, timeout=900
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc
