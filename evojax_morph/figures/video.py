"""Watch a saved controller walk its body: one evaluation episode, as a GIF and an MP4.

`replay(saved, key)` rolls out the controller's deterministic policy on its body in MJX, as the
PPO fitness's evaluation episodes do (`tasks.rollout`, the episode loop they share), and records
the positions; `draw_frames` turns them into pictures with MuJoCo's renderer where OpenGL works
(`evojax_morph.physics.opengl.choose_gl`: `MUJOCO_GL` if set, else the display's GL, else EGL,
else OSMesa, each tried in a subprocess first) and otherwise with a matplotlib drawing of the
capsules, which needs no GL; `write_video` encodes them.
`render_saved(saved, out)` does all three, and `render(run_dir, body)` for a body of a run
directory (`python -m evojax_morph.render`).
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from evojax_morph.physics.opengl import choose_gl
from evojax_morph.ppo.networks import make_deterministic_policy, make_init, make_networks
from evojax_morph.records import saved_controllers
from evojax_morph.records.saved_controllers import SavedController
from evojax_morph.tasks import Locomotion, rollout

BACKENDS = ("auto", "mujoco", "matplotlib")


class Replay(NamedTuple):
    """One episode of a controller on its body, until it ended (fell over or timed out)."""

    qpos: np.ndarray  # (T + 1, nq) positions of the padded template, the reset state first
    reward: np.ndarray  # (T,) reward of each control step
    dt: float  # seconds per control step
    fell: bool = False  # the episode ended by a fall (or a diverged simulation), not its length

    @property
    def distance(self) -> np.ndarray:
        """(T + 1,) metres the trunk moved forward since the reset."""
        return self.qpos[:, 0] - self.qpos[0, 0]

    @property
    def episode_return(self) -> float:
        return float(self.reward.sum())


class Rendered(NamedTuple):
    paths: list[Path]  # the files written (the GIF, and the MP4 if it could be encoded)
    backend: str  # who drew the frames: "mujoco (egl)" (MuJoCo, and its GL) or "matplotlib"
    replay: Replay
    notes: list[str]  # what could not be done, and why


_EPISODE_FNS: dict = {}


def _episode_fn(space, fitness):
    """(jit(episode(key, morph, params)) -> (qpos (L, nq), reward (L,), done (L,), terminated
    (L,), qpos0), the control step's seconds, init(key) -> one controller's parameters), one
    per space and fitness config, compiled once however often the space is made again."""
    cache_key = (space.name, space.max_nodes, fitness)
    if cache_key not in _EPISODE_FNS:
        _EPISODE_FNS[cache_key] = _make_episode_fn(space, fitness)
    return _EPISODE_FNS[cache_key]


def _make_episode_fn(space, fitness):
    env = Locomotion(space, fitness.task)
    networks = make_networks(env, fitness.ppo)
    policy = make_deterministic_policy(networks)

    @jax.jit
    def episode(key, morph, params):
        model = space.mjx_model(morph)
        first = env.reset(key, model)
        _, _, out = rollout(
            lambda state, action: env.step(model, state, action),
            lambda state, _: policy(params, state.obs),
            first,
            fitness.task.episode_length,
            lambda _, s: (None, (s.data.qpos, s.reward, s.done, s.terminated)),
        )
        return out + (first.data.qpos,)

    return episode, env.dt, make_init(env, networks, fitness.with_controllers(1).ppo)


def replay(saved: SavedController, key: jax.Array | None = None, controller: int = 0) -> Replay:
    """One evaluation episode of the saved controller on its body.

    Args:
      saved: a body and its controller (`controllers.load`).
      key: the episode's reset key (its small random perturbation); default: from the run's seed.
      controller: which of the K controllers acts, 0 <= controller < K.
    Returns:
      A `Replay` up to the step the episode ended (fell over, diverged or reached its length).
    """
    k = saved.fitness.ppo.controllers
    if not 0 <= controller < k:
        raise ValueError(f"controller {controller} out of range: this body has {k} controller(s)")
    params = jax.device_get(saved.params)  # on the host, placed as `lower_replay` compiles for
    if k > 1:
        params = jax.tree.map(lambda x: x[controller], params)
    key = jax.random.PRNGKey(saved.seed) if key is None else key
    episode, dt, _ = _episode_fn(saved.space, saved.fitness)
    qpos, reward, done, terminated, qpos0 = jax.device_get(episode(key, saved.morph, params))
    ended = np.flatnonzero(done)
    length = int(ended[0]) + 1 if len(ended) else len(done)
    qpos = np.concatenate([qpos0[None], qpos[:length]])
    return Replay(np.asarray(qpos, np.float64), np.asarray(reward[:length], np.float64), dt,
                  bool(terminated[length - 1]))


def lower_replay(space, fitness):
    """The program `replay` compiles for a controller of the `fitness` config on `space`,
    lowered for compiling ahead (`compile_ahead`)."""
    episode, _, init = _episode_fn(space, fitness)
    key = jax.ShapeDtypeStruct((2,), jnp.uint32)
    strong = lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype)  # noqa: E731 (as read from disk)
    params = jax.tree.map(strong, jax.eval_shape(init, key))
    return episode.lower(key, jax.eval_shape(space.initial), params)


# --- pictures ---------------------------------------------------------------------------


class _Scene:
    """The unpadded MuJoCo model of a body, posed from the padded template's positions."""

    def __init__(self, saved: SavedController, visual: bool = False):
        xml = saved.space.to_mjcf(saved.morph)
        if visual:  # a checkered floor shows the motion; an offscreen buffer for any size
            xml = xml.replace(
                "<worldbody>",
                '<visual><global offwidth="1920" offheight="1080"/><headlight ambient=".45 .45 '
                '.45" diffuse=".5 .5 .5" specular="0 0 0"/></visual>\n  <asset><texture '
                'type="skybox" builtin="gradient" rgb1=".93 .95 .98" rgb2=".7 .78 .88" '
                'width="64" height="64"/><texture name="grid" type="2d" builtin="checker" '
                'rgb1=".85 .87 .9" rgb2=".7 .73 .78" width="64" height="64"/><material '
                'name="grid" texture="grid" texrepeat="4 4" texuniform="true"/></asset>\n'
                '  <worldbody>',
            ).replace('rgba="0.8 0.85 0.9 1"/>', 'material="grid"/>', 1)
        self.model = mujoco.MjModel.from_xml_string(xml)
        self.data = mujoco.MjData(self.model)
        template = saved.space.template
        width = {int(mujoco.mjtJoint.mjJNT_FREE): 7, int(mujoco.mjtJoint.mjJNT_BALL): 4}
        to, source = [], []  # every qpos of every joint of the export, and the template's
        for j in range(self.model.njnt):
            n = width.get(int(self.model.jnt_type[j]), 1)
            to += range(self.model.jnt_qposadr[j], self.model.jnt_qposadr[j] + n)
            start = template.jnt_qposadr[template.joint(self.model.joint(j).name).id]
            source += range(start, start + n)
        self._to, self._from = np.array(to), np.array(source)

    def pose(self, qpos: np.ndarray) -> mujoco.MjData:
        self.data.qpos[self._to] = qpos[self._from]
        mujoco.mj_kinematics(self.model, self.data)
        return self.data

    def capsules(self, qpos: np.ndarray):
        """(G, 2, 3) end points, (G,) radii and (G, 3) colours of the body's capsules."""
        data = self.pose(qpos)
        caps = self.model.geom_type == mujoco.mjtGeom.mjGEOM_CAPSULE
        axis = data.geom_xmat[caps][:, [2, 5, 8]] * self.model.geom_size[caps, 1:2]
        ends = np.stack([data.geom_xpos[caps] - axis, data.geom_xpos[caps] + axis], 1)
        return ends, self.model.geom_size[caps, 0], self.model.geom_rgba[caps, :3]


def _caption(rep: Replay, i: int) -> str:
    return f"distance {rep.distance[i]:+.2f} m   t = {i * rep.dt:.1f} s"


def _mujoco_frames(scene: _Scene, rep: Replay, index, width: int, height: int,
                   context_cls) -> list:
    """MuJoCo's pictures through its low-level API on a GL context of our choice (`Renderer`
    would take the one `import mujoco` chose)."""
    from PIL import Image, ImageDraw

    model = scene.model
    if width > model.vis.global_.offwidth or height > model.vis.global_.offheight:
        raise ValueError(f"{width} x {height} exceeds the offscreen buffer "
                         f"{model.vis.global_.offwidth} x {model.vis.global_.offheight}")
    context = context_cls(width, height)
    mjr = None
    try:
        context.make_current()
        mjv = mujoco.MjvScene(model, maxgeom=1000)
        option = mujoco.MjvOption()
        mjr = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_150)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, mjr)
        rect = mujoco.MjrRect(0, 0, width, height)
        rgb = np.zeros((height, width, 3), np.uint8)
        camera = mujoco.MjvCamera()
        camera.type = mujoco.mjtCamera.mjCAMERA_FREE
        camera.distance, camera.azimuth, camera.elevation = 2.8, 90.0, -8.0
        frames = []
        for i in index:
            data = scene.pose(rep.qpos[i])
            camera.lookat[:] = (data.xpos[1, 0], 0.0, 0.35)
            mujoco.mjv_updateScene(model, data, option, None, camera,
                                   mujoco.mjtCatBit.mjCAT_ALL, mjv)
            mujoco.mjr_render(rect, mjv, mjr)
            mujoco.mjr_readPixels(rgb, None, rect, mjr)
            image = Image.fromarray(np.flipud(rgb))  # GL's rows run bottom-up
            ImageDraw.Draw(image).text((8, 6), _caption(rep, i), fill=(20, 20, 20))
            frames.append(np.asarray(image))
        return frames
    finally:
        if mjr is not None:
            mjr.free()
        context.free()


def _matplotlib_frames(scene: _Scene, rep: Replay, index, width: int, height: int) -> list:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    dpi = 100
    fig = Figure(figsize=(width / dpi, height / dpi), dpi=dpi)  # outside pyplot: no window,
    FigureCanvasAgg(fig)  # nothing left open, and matplotlib's backend as the importer set it
    ax = fig.add_axes((0, 0, 1, 1))
    view_w = 3.2  # metres across the picture
    points_per_m = width / dpi * 72 / view_w
    _, radius, rgba = scene.capsules(rep.qpos[0])
    lines = [
        ax.plot([], [], color=c, lw=2 * r * points_per_m, solid_capstyle="round")[0]
        for r, c in zip(radius, rgba)
    ]
    x0 = rep.qpos[0, 0]
    ax.axvline(x0, color="0.6", lw=0.8, ls="--")  # where the trunk started
    ax.axhline(0.0, color="0.45", lw=1.5)
    lo, hi = x0 - view_w + rep.distance.min(), x0 + view_w + rep.distance.max()
    for x in np.arange(np.floor(lo * 2) / 2, hi, 0.5):  # ground marks: the motion shows
        ax.plot([x, x - 0.05], [0.0, -0.06], color="0.45", lw=1)
    text = ax.text(0.02, 0.95, "", transform=ax.transAxes, va="top", fontsize=8)
    ax.set_aspect("equal")
    ax.axis("off")
    frames = []
    for i in index:
        ends, _, _ = scene.capsules(rep.qpos[i])
        for line, (a, b) in zip(lines, ends):
            line.set_data([a[0], b[0]], [a[2], b[2]])
        centre = rep.qpos[i, 0]
        ax.set_xlim(centre - view_w / 2, centre + view_w / 2)
        ax.set_ylim(-0.15, -0.15 + view_w * height / width)
        text.set_text(_caption(rep, i))
        fig.canvas.draw()
        frames.append(np.asarray(fig.canvas.buffer_rgba())[..., :3].copy())
    return frames


def draw_frames(
    saved: SavedController,
    rep: Replay,
    backend: str = "auto",
    width: int = 480,
    height: int = 270,
    stride: int = 2,
) -> tuple[list[np.ndarray], str, list[str]]:
    """Pictures of a replay, one every `stride` control steps (and the last).

    Args:
      backend: "mujoco" (MuJoCo's renderer on `choose_gl`'s GL; fails without one),
        "matplotlib" (a drawing of the capsules, needs no GL) or "auto" (MuJoCo's renderer if
        it draws, else matplotlib).
    Returns:
      (frames (height, width, 3) uint8, who drew them: "mujoco (GL)" or "matplotlib", notes on
      a fallback).
    """
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; choose one of {', '.join(BACKENDS)}")
    index = sorted(set(range(0, len(rep.qpos), stride)) | {len(rep.qpos) - 1})
    notes = []
    if backend in ("auto", "mujoco"):
        gl, context, tried = choose_gl()
        try:
            if context is None:
                raise RuntimeError("no GL context for MuJoCo's renderer: " + "; ".join(tried))
            with warnings.catch_warnings():  # glfw warns before it fails without a display
                warnings.simplefilter("ignore" if backend == "auto" else "default")
                scene = _Scene(saved, visual=True)
                frames = _mujoco_frames(scene, rep, index, width, height, context)
            return frames, f"mujoco ({gl})", []
        except Exception as e:  # no GL context: glfw without a display, no EGL or OSMesa
            if backend == "mujoco":
                raise
            why = "; ".join(tried) if context is None else f"{gl}: {type(e).__name__}"
            notes.append(
                f"no OpenGL for MuJoCo's renderer ({why}); drew the capsules with matplotlib"
            )
    return _matplotlib_frames(_Scene(saved), rep, index, width, height), "matplotlib", notes


# --- files ------------------------------------------------------------------------------


def _replace_atomically(path: Path, write) -> None:
    """`write(tmp)` then a rename onto `path`: a failure leaves no half-written file."""
    tmp = path.with_name(f".{path.stem}.partial{path.suffix}")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_video(stem: Path, frames: list[np.ndarray], fps: float, mp4: bool = True):
    """STEM.gif, and STEM.mp4 if `mp4` and imageio with its ffmpeg can encode it.

    Returns:
      (paths written, notes on what was skipped).
    """
    from PIL import Image

    stem = Path(stem)
    images = [Image.fromarray(f) for f in frames]
    gif = stem.with_suffix(".gif")
    duration = max(int(round(1000 / fps)), 20)  # GIF delays are in 10 ms, browsers floor at 20
    _replace_atomically(gif, lambda p: images[0].save(
        p, format="GIF", save_all=True, append_images=images[1:], duration=duration, loop=0
    ))
    paths, notes = [gif], []
    if mp4:
        try:
            import imageio
            import imageio_ffmpeg  # noqa: F401  (the ffmpeg binary imageio calls)
        except ImportError:
            notes.append("no MP4: it needs imageio and imageio-ffmpeg "
                         "(pip install 'evojax_morph[video]'); wrote the GIF only")
        else:
            out = stem.with_suffix(".mp4")
            # libx264 wants even sizes; macro_block_size=1 keeps the frames' own size
            even = [f[: f.shape[0] // 2 * 2, : f.shape[1] // 2 * 2] for f in frames]
            _replace_atomically(out, lambda p: imageio.mimwrite(
                p, even, format="FFMPEG", fps=fps, macro_block_size=1
            ))
            paths.append(out)
    return paths, notes


def render(run_dir: Path, body: str = "best", out: Path | None = None, **kwargs) -> Rendered:
    """Replays a body of a run with its saved controller and writes OUT.gif (and OUT.mp4).

    Args:
      run_dir: a run directory of the PPO fitness (it keeps `controllers/`).
      body: "best", "final" (the greedy trajectory's last body) or "step N".
      out: the files' path, its suffix replaced; default RUN_DIR/best, RUN_DIR/final,
        RUN_DIR/stepN.
      kwargs: as in `render_saved`.
    Raises:
      ValueError: an unknown `body`; FileNotFoundError: no controller saved for it.
    """
    saved = saved_controllers.load(saved_controllers.body_dir(run_dir, body))
    stem = Path(out) if out is not None else Path(run_dir) / body.replace(" ", "")
    return render_saved(saved, stem, **kwargs)


def render_saved(
    saved: SavedController,
    out: Path,
    backend: str = "auto",
    controller: int = 0,
    key: jax.Array | None = None,
    width: int = 480,
    height: int = 270,
    stride: int = 2,
    mp4: bool = True,
) -> Rendered:
    """OUT.gif (and OUT.mp4) of one evaluation episode of `saved`: backend, width, height and
    stride as in `draw_frames`, controller and key as in `replay`; mp4: also try the MP4."""
    rep = replay(saved, key, controller)
    frames, drawn_by, notes = draw_frames(saved, rep, backend, width, height, stride)
    paths, more = write_video(out, frames, fps=1.0 / (rep.dt * stride), mp4=mp4)
    return Rendered(paths, drawn_by, rep, notes + more)
