"""The GPU determinism switch: it must reach XLA before a backend starts, and say when it cannot."""

import json
import os
import subprocess
import sys

from conftest import FAST_COMPILE, xla_takes

PROBE = r"""
import os, sys
import jax
from evojax_morph.physics.determinism import FLAG, deterministic_gpu
if sys.argv[1] == "late":
    jax.devices()  # a backend is up: too late to change XLA's flags
ok = deterministic_gpu()
print(ok, FLAG in os.environ.get("XLA_FLAGS", ""), float(jax.numpy.ones(3).sum()))
"""


def probe(when: str) -> str:
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    env["JAX_PLATFORMS"] = "cpu"
    proc = subprocess.run(
        [sys.executable, "-c", PROBE, when], capture_output=True, text=True, env=env, timeout=300
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc.stdout.split()


def test_switch_before_the_backend_starts_and_refused_after():
    assert probe("early") == [
        "True",
        "True",
        "3.0",
    ]  # set, and the CPU backend accepts the GPU flag
    assert probe("late") == ["False", "False", "3.0"]  # nothing changed once a backend was up


def test_run_asks_for_deterministic_ops_unless_the_ppo_fitness_may_step_on_warp(
    tmp_path, monkeypatch
):
    from evojax_morph.physics import engines
    from evojax_morph.run import cli

    asked = []
    monkeypatch.setattr(cli, "deterministic_gpu", lambda: asked.append(True))
    monkeypatch.setattr(engines, "warp_imports", lambda: True)

    def asks(*argv) -> bool:
        asked.clear()
        cli.start(list(argv))
        return bool(asked)

    assert asks("--physics", "jax")
    assert not asks("--physics", "warp")
    assert not asks()  # auto, where Warp imports
    assert not asks("--physics", "warp", "--fast-gpu")
    assert asks("--physics", "warp", "--fitness", "table")  # no physics: reproducible
    assert asks("--fitness", "tame")  # tame runs on the JAX engine
    monkeypatch.setattr(engines, "warp_imports", lambda: False)
    assert asks()  # auto without Warp: the JAX engine
    assert not asks("--fast-gpu")
    # a --resume follows the run's saved config, not the defaults
    (tmp_path / "config.json").write_text(json.dumps({"physics": "warp", "fitness": "ppo"}))
    assert not asks("--resume", "--out", str(tmp_path), "--physics", "jax")
    (tmp_path / "config.json").write_text(json.dumps({"physics": "jax", "fitness": "ppo"}))
    assert asks("--resume", "--out", str(tmp_path))


IMPORT = r"""
import json, os, sys
import matplotlib
matplotlib.use(sys.argv[1])  # the importer's choice, which evojax_morph must keep
b = matplotlib.get_backend(); f = os.environ.get("XLA_FLAGS")
import evojax_morph
from evojax_morph.figures import plots  # every figure's module, and one figure drawn
from evojax_morph.run import report
plots.plot_curve(sys.argv[2], [0, 1, 2], [1, 2, 3], [0, 1, 2], [2, 3, 4])
print(json.dumps([b, matplotlib.get_backend(), f, os.environ.get("XLA_FLAGS")]))
"""


def test_import_leaves_matplotlib_and_xla_flags_as_they_were(tmp_path):
    """`import evojax_morph` (and a figure drawn) keeps the importer's matplotlib backend, and
    XLA_FLAGS as they were but for the CPU scheduler and all-reduce flags
    (`cpu_scheduler_workaround`, `all_reduce_workaround`, said in evojax_morph/__init__.py), each
    appended only where XLA_FLAGS does not set it."""
    from evojax_morph.physics.determinism import ALL_REDUCE_FLAG, CPU_FLAG

    def imported(xla_flags: str | None) -> list:
        env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "MPLBACKEND")}
        env["JAX_PLATFORMS"] = "cpu"
        if xla_flags is not None:
            env["XLA_FLAGS"] = xla_flags
        proc = subprocess.run([sys.executable, "-c", IMPORT, "svg", str(tmp_path / "c.png")],
                              capture_output=True, text=True, env=env, timeout=300)
        assert proc.returncode == 0, proc.stderr[-2000:]
        return json.loads(proc.stdout.splitlines()[-1])

    own = ("--xla_cpu_enable_concurrency_optimized_scheduler=true "
           "--xla_gpu_unsupported_use_all_reduce_one_shot_kernel=true")
    assert imported(own) == ["svg", "svg", own, own]
    assert imported(None) == ["svg", "svg", None, f"{CPU_FLAG} {ALL_REDUCE_FLAG}"]
    assert imported("--xla_cpu_use_thunk_runtime=true") == [
        "svg", "svg", "--xla_cpu_use_thunk_runtime=true",
        f"--xla_cpu_use_thunk_runtime=true {CPU_FLAG} {ALL_REDUCE_FLAG}"]
    assert (tmp_path / "c.png").read_bytes()[:4] == b"\x89PNG"


def test_the_default_set_adds_a_flag_only_where_xla_takes_it():
    """XLA aborts the process on a flag its jaxlib does not know (jaxlib 0.12 has no
    --xla_cpu_use_fusion_emitters, which the default set adds on older ones): the default set
    adds a flag only where a Python of its own starts with it (`conftest.xla_takes`)."""
    assert xla_takes(FAST_COMPILE)
    assert not xla_takes(f"{FAST_COMPILE} --xla_no_such_flag=1")
