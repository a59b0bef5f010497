"""Shared test set-up: CPU backend, a persistent compilation cache, and small helpers."""

import contextlib
import json
import os
import re
import subprocess
import sys
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax
import pytest

import evojax_morph as em

# Compiled programs survive between runs (CI reuses the machine's cache directory).
CACHE = em.persistent_cache()


# The default set (pyproject's -m) compiles at LLVM's lowest optimisation and with XLA's
# older CPU code emitters (`--xla_cpu_use_fusion_emitters=false`): its time is mostly compiling
# small programs, among them some 3,400 of under 0.2 s, most of those the eager ops between the
# tests' jitted calls (28 ms each with the fusion emitters at -O0, 20 ms without). The cold set
# took 7 min 58 s at -O0 against 10 min 20 s, and 4 min 18 s to 4 min 38 s without the fusion
# emitters against 5 min 31 s to 5 min 54 s with them, on one machine (docs/benchmarks.md, "The
# test suite"). The learning and slow sets mostly run, and keep XLA's default; so does a run of
# the library.
DEFAULT_SET = "not learning and not slow"
FAST_COMPILE = "--xla_backend_optimization_level=0"
OLD_EMITTERS = "--xla_cpu_use_fusion_emitters=false"


def xla_takes(flags: str) -> bool:
    """Whether this jaxlib's XLA starts with `flags` as its XLA_FLAGS, asked of a Python of
    its own (about 2 s): XLA aborts the process on a flag it does not know, and a later XLA
    drops flags (jaxlib 0.12 has no --xla_cpu_use_fusion_emitters, though its name is still in
    the library, a reserved field of XLA's options)."""
    env = dict(os.environ, XLA_FLAGS=flags, JAX_PLATFORMS="cpu")
    probe = [sys.executable, "-c", "import jax; jax.devices()"]
    return subprocess.run(probe, env=env, capture_output=True).returncode == 0


def pytest_configure(config):
    """The default set's XLA flags, set before any test starts JAX's backend (which reads it)."""
    flags = os.environ.get("XLA_FLAGS", "")
    if config.getoption("markexpr") == DEFAULT_SET and "optimization_level" not in flags:
        flags = f"{flags} {FAST_COMPILE}"
        if "fusion_emitters" not in flags and xla_takes(f"{flags} {OLD_EMITTERS}"):
            flags = f"{flags} {OLD_EMITTERS}"
        os.environ["XLA_FLAGS"] = flags.strip()


@pytest.fixture(scope="session", params=["bad_walker", "constructor", "length_walker"])
def space(request):
    return em.make_space(request.param)


# The longest files first, in this order (pyproject's --no-loadscope-reorder keeps it: xdist
# would otherwise start the files with the most tests first and the longest last, ending the
# suite alone), as measured cold (docs/benchmarks.md, "The test suite"). In the slow set the
# two 4-device subprocesses, one test a file, start together on both workers, then the toy
# reproduce run, the full MuJoCo C equivalence and the experiment smokes (test_search.py).
FIRST = ("test_sharding.py", "test_sharding_run.py", "test_reproduce.py", "test_physics.py",
         "test_agent.py", "test_fitness.py", "test_crawler.py", "test_search.py", "test_tame.py",
         "test_spaces.py", "test_table.py", "test_render.py", "test_warp.py", "test_cli.py",
         "test_tasks.py", "test_classes.py", "test_confirm.py")


def pytest_collection_modifyitems(config, items):
    """Files in the order of FIRST, then the rest; two workers take a file each."""
    rank = lambda item: FIRST.index(item.path.name) if item.path.name in FIRST else len(FIRST)
    items.sort(key=rank)


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


@contextlib.contextmanager
def float64():
    """`jax.enable_x64` for a block, with JAX's caches cleared on entry and exit. jax 0.10
    keeps a numpy constant traced under one setting in that setting's dtype. A later program
    under the other setting then fails: an f64 buffer reaches an f32 parameter
    (RuntimeProgramInputMismatch), or the lowering fails to verify. Without the clears, one
    float64 test broke the next float32 test on its pytest-xdist worker."""
    jax.clear_caches()
    try:
        with jax.enable_x64(True):
            yield
    finally:
        jax.clear_caches()


def flip(f: Path) -> None:
    """64 bytes of the file `f` inverted in place, at offset 100 (the middle of a smaller one)."""
    data = bytearray(f.read_bytes())
    at = min(100, len(data) // 2)
    data[at:at + 64] = bytes(b ^ 0xFF for b in data[at:at + 64])
    f.write_bytes(bytes(data))


def truncate(f: Path) -> None:
    """The file `f` cut to half its length."""
    f.write_bytes(f.read_bytes()[: f.stat().st_size // 2])


DAMAGES = (flip, truncate, Path.unlink)  # what a disk error or a cut-short copy does to a file


def data_files(checkpoint: Path) -> list[Path]:
    """The files of an Orbax checkpoint that hold data: its arrays' (under d/) and its JSON
    items' (a run's checkpoint: the digest and its record; a saved controller: its metadata)."""
    files = [f for f in sorted(checkpoint.rglob("*")) if f.is_file() and f.parent.name == "d"]
    json_item = [checkpoint / d / "metadata" for d in ("digest", "record", "meta")
                 if (checkpoint / d).is_dir()]
    assert files and json_item, f"not a checkpoint of a run or a controller: {checkpoint}"
    return files + json_item


def run_shape(out: Path, printed: str) -> dict:
    """What a run leaves and prints, less what its numbers decide: the files by name, the keys
    and types of its JSON files (timing.json's keys), metrics.csv's columns and the printed
    lines, each number a #, each body BODY and each mutation MUTATION, a table's rows as one,
    a body's drawing, the progress bar and what OpenGL there is left out. Comparable across
    CPUs, which round a run's numbers differently, and machines."""

    def skeleton(x):
        if isinstance(x, dict):
            return {k: skeleton(v) for k, v in x.items()}
        if isinstance(x, list):
            return [skeleton(x[0])] if x else []
        return type(x).__name__

    number = re.compile(r"-?\d+(\.\d+)?(e[-+]?\d+)?")
    lines = []
    for line in printed.replace(str(out), "OUT").replace("\r", "\n").splitlines():
        line = " ".join(number.sub("#", line).split())
        line = re.sub(r"#@\S*(?: #@\S*)*", "BODY", line)  # a body's canonical name
        line = re.sub(r"node #: \S+( \(no-op\))?", "node #: MUTATION", line)
        line = re.sub(r"drawn by [^:]*:", "drawn by GL:", line)  # the machine's OpenGL
        line = re.sub(r"^confirmed best \w+", "confirmed best GAIT", line)  # walks or moves
        if line and not line.startswith(("├", "└", "│", "#: ", "time: ", "best.gif: ")) \
                and "|" not in line and line != (lines or [None])[-1]:  # a table's rows as one
            lines.append(line)
    files = sorted(p.name + "/" * p.is_dir() for p in out.iterdir())
    shape = {"files": files, "printed": lines,
             "metrics.csv": (out / "metrics.csv").read_text().splitlines()[0]}
    for name in ("config.json", "summary.json", "confirmed.json"):
        if (out / name).exists():
            shape[name] = skeleton(json.loads((out / name).read_text()))
    shape["timing.json"] = sorted(json.loads((out / "timing.json").read_text()))
    return shape
