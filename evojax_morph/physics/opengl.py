"""Which OpenGL MuJoCo's renderer draws with in this process, tried before it is loaded.

`choose_gl` keeps `MUJOCO_GL` if set; otherwise it takes the first of GLFW (with a display),
EGL and OSMesa that draws a picture in a subprocess (`probe_gl`). `evojax_morph.figures.video` draws
its frames on the GL chosen, and with matplotlib where there is none.
"""

from __future__ import annotations

import importlib
import os
import subprocess
import sys
import warnings

import mujoco

# MuJoCo's Python bindings pick their GL (`mujoco.GLContext`) from MUJOCO_GL when `mujoco` is
# first imported; unset, that is GLFW, which needs a display. EGL and OSMesa each fix PyOpenGL's
# platform for the whole process once loaded, so a failed try of one would rule out the other:
# each is tried in a subprocess, and only the one that drew there is loaded here.
GL_FALLBACKS = ("egl", "osmesa")
_PROBE = """
import mujoco, numpy as np
m = mujoco.MjModel.from_xml_string(
    '<mujoco><worldbody><geom type="sphere" size=".1"/></worldbody></mujoco>')
d = mujoco.MjData(m)
mujoco.mj_forward(m, d)
r = mujoco.Renderer(m, 16, 16)
r.update_scene(d)
ok = r.render().std() > 0
r.close()
print("GL_DREW" if ok else "GL_BLANK")
"""
_GL_CHOICE: list = []  # [(name, GLContext class or None, notes)], chosen once per process


def probe_gl(name: str, timeout: float = 120.0) -> str | None:
    """Whether MuJoCo renders under MUJOCO_GL=`name`, tried in a fresh Python process.

    Returns:
      None if it drew a picture, else why not (the probe's last line of error).
    """
    env = dict(os.environ, MUJOCO_GL=name)
    try:
        with warnings.catch_warnings():  # JAX warns of any fork; this one execs at once
            warnings.filterwarnings("ignore", "os.fork", RuntimeWarning)
            proc = subprocess.run(
                [sys.executable, "-c", _PROBE],
                capture_output=True,
                text=True,
                env=env,
                timeout=timeout,
            )
    except subprocess.TimeoutExpired:
        return f"no picture within {timeout:.0f} s"
    if "GL_DREW" in proc.stdout:
        return None
    if "GL_BLANK" in proc.stdout:
        return "it drew a blank picture"
    lines = [line for line in proc.stderr.strip().splitlines() if line.strip()]
    return lines[-1].strip()[:200] if lines else f"exit code {proc.returncode}"


def choose_gl(probe=probe_gl) -> tuple[str | None, type | None, list[str]]:
    """The GL for MuJoCo's renderer in this process, chosen once (later calls return the same).

    `MUJOCO_GL`, if set, is MuJoCo's own choice and is kept. Unset, the first of GLFW (only
    where there is a display: `DISPLAY` or `WAYLAND_DISPLAY`), EGL and OSMesa whose subprocess
    `probe` draws a picture.

    Returns:
      (its name, e.g. "egl", or None if none works; its `GLContext(width, height)` class;
      notes on what was tried and failed).
    """
    if _GL_CHOICE:
        return _GL_CHOICE[0]
    name = os.environ.get("MUJOCO_GL", "").strip().lower()
    notes = []
    if name:
        context = getattr(mujoco, "GLContext", None)  # what `import mujoco` chose from MUJOCO_GL
        if context is None:
            notes.append(f"MUJOCO_GL={name} gives MuJoCo no GL context")
            name = None
    else:
        name = context = None
        display = os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
        for candidate in ("glfw",) * bool(display) + GL_FALLBACKS:
            why = probe(candidate)
            if why is None:
                try:
                    context = importlib.import_module(f"mujoco.{candidate}").GLContext
                except Exception as e:  # another library loaded PyOpenGL on another platform
                    why = f"{type(e).__name__}: {e}"
                else:
                    name = candidate
                    break
            notes.append(f"{candidate}: {why}")
        if not display:
            notes.append("glfw: no display")
    _GL_CHOICE.append((name, context, notes))
    return _GL_CHOICE[0]
