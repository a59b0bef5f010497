"""The tutorial runs to its end as a user runs it (a subprocess, its own output folder), so it
cannot rot: 2 min 24 s on 2 cores, most of it compiling, so in the slow set."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.slow
def test_the_tutorial_runs_to_its_end(tmp_path):
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    proc = subprocess.run(
        [sys.executable, str(ROOT / "examples" / "tutorial.py"), str(tmp_path)],
        capture_output=True, text=True, env=env, cwd=tmp_path, timeout=900,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    for name in ("bodies.png", "m0.xml", "run/summary.json", "run/bodies.sqlite", "best.gif"):
        assert (tmp_path / name).stat().st_size > 0, name
    assert "done in" in proc.stdout
