"""The tutorial runs to its end as a user runs it (a subprocess, its own output folder), so it
cannot rot: 2 min 24 s on 2 cores, most of it compiling, so in the slow set. What it printed is
stored beside it (examples/tutorial_output.txt, shown on the site's tutorial page) with the
SHA-256 of the script it came from: an edited tutorial fails here until its output is stored
again (`EVOJAX_MORPH_TUTORIAL_OUTPUT=1 pytest tests/test_tutorial.py -m slow`)."""

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SCRIPT, OUTPUT = ROOT / "examples" / "tutorial.py", ROOT / "examples" / "tutorial_output.txt"


def header() -> str:
    """The stored output's first line: which script printed it."""
    digest = hashlib.sha256(SCRIPT.read_bytes()).hexdigest()
    return f"# printed by examples/tutorial.py, sha256 {digest}"


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
    if os.environ.get("EVOJAX_MORPH_TUTORIAL_OUTPUT") == "1":
        OUTPUT.write_text(f"{header()}\n{proc.stdout.replace(str(tmp_path), 'tutorial_out')}")
    stored = OUTPUT.read_text().splitlines()
    assert stored[0] == header(), "examples/tutorial.py changed: store its output again"
    assert len(stored) - 1 == len(proc.stdout.splitlines())  # the same prints, line for line
