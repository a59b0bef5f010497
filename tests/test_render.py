"""Saved controllers, their replay and its video (matplotlib fallback), the render command, and
the console scripts. The one PPO training here is a 1-update `em.evaluate` of two bodies."""

import dataclasses
import os
import subprocess
import sys
import tomllib
from importlib import import_module
from pathlib import Path

import jax
import numpy as np
import pytest
from PIL import Image

import evojax_morph as em
from evojax_morph import controllers, driver, ppo, render
from evojax_morph.pipeline import Greedy, RunConfig, build

ROOT = Path(__file__).resolve().parents[1]
TINY_VIDEO = dict(backend="matplotlib", width=64, height=48, stride=50)


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    """A run directory as the driver leaves it, with K = 2 controllers per body trained 1 PPO
    update: best = m*, greedy trajectory m0 -> m*."""
    p = build(RunConfig(fitness="ppo", train_steps=320, controllers=2))
    space = p.space
    morphs = em.stack([space.initial(), space.optimum()])
    res = jax.device_get(em.evaluate(space, morphs, jax.random.PRNGKey(0), p.fitness))
    params = [jax.tree.map(lambda x, i=i: x[i], res.params) for i in range(2)]
    fitness = [float(f) for f in res.fitness]
    out = tmp_path_factory.mktemp("run")
    greedy = Greedy([space.initial(), space.optimum()], fitness, ["..."], params)
    saved = driver.save_controllers(out, p, 7, space.optimum(), fitness[1], params[1], greedy)
    assert saved == ["best", "step0", "step1"]
    return out, p, params, fitness


def test_saved_controllers_round_trip(run_dir):
    out, p, params, fitness = run_dir
    best = em.load_controller(controllers.body_dir(out, "best"))
    assert best.label == "best" and best.seed == 7 and best.fitness == p.fitness
    assert best.value == pytest.approx(fitness[1]) and best.space.name == "bad_walker"
    assert best.space.canonical(best.morph) == p.space.canonical(p.space.optimum())
    leaves = jax.tree.leaves(best.params)
    assert leaves[0].shape[0] == 2  # both controllers
    for saved, original in zip(leaves, jax.tree.leaves(params[1])):
        np.testing.assert_array_equal(saved, original)
    assert controllers.body_dir(out, "final") == controllers.body_dir(out, "step 1")
    m0 = em.load_controller(controllers.body_dir(out, "step 0"))
    assert m0.space.canonical(m0.morph) == p.space.canonical(p.space.initial())
    with pytest.raises(ValueError, match="unknown body"):
        controllers.body_dir(out, "worst")
    with pytest.raises(FileNotFoundError, match="saved steps: 0, 1"):
        controllers.body_dir(out, "step 5")


def test_replay_is_the_fitness_evaluation_episode(run_dir):
    """The replay of controller k from reset key r returns what the PPO fitness's evaluation
    (`ppo.make_evaluate`, which scores every trained controller) returns for the same key."""
    out, p, _, _ = run_dir
    saved = em.load_controller(controllers.body_dir(out, "best"))
    cfg = dataclasses.replace(saved.fitness.ppo, eval_episodes=1)
    evaluate = jax.jit(ppo.make_evaluate(saved.space, saved.fitness.task, cfg))
    model = saved.space.mjx_model(saved.morph)
    key = jax.random.PRNGKey(3)
    replays = []
    for k in range(2):
        one = jax.tree.map(lambda x, k=k: x[k], saved.params)
        returns, _ = evaluate(key, model, one)
        rep = em.replay(saved, jax.random.split(key, 1)[0], controller=k)
        np.testing.assert_allclose(rep.episode_return, float(returns[0]), rtol=1e-5, atol=1e-5)
        assert rep.qpos.shape == (len(rep.reward) + 1, saved.space.template.nq)
        replays.append(rep)
    assert not np.allclose(replays[0].qpos[-1], replays[1].qpos[-1])  # two controllers
    with pytest.raises(ValueError, match="out of range"):
        em.replay(saved, controller=2)


def test_fallback_video_is_small_and_complete(run_dir, tmp_path, monkeypatch):
    out, *_ = run_dir
    shown = em.render_video(out, "best", tmp_path / "walk", **TINY_VIDEO)
    assert shown.backend == "matplotlib"
    gif = Image.open(tmp_path / "walk.gif")
    steps = len(shown.replay.qpos)  # every 50th position and the last
    assert gif.size == (64, 48) and 2 <= gif.n_frames <= len(set(range(0, steps, 50)) | {steps - 1})
    first = np.asarray(gif.convert("RGB"))
    gif.seek(gif.n_frames - 1)
    assert not np.array_equal(first, np.asarray(gif.convert("RGB")))  # the body moved
    try:
        import imageio_ffmpeg  # noqa: F401
    except ImportError:
        assert any("no MP4" in n for n in shown.notes)
    else:
        assert (tmp_path / "walk.mp4").stat().st_size > 0

    # Without imageio: the GIF alone, said so, and no partial file left behind.
    monkeypatch.setitem(sys.modules, "imageio", None)
    shown = em.render_video(out, "step 0", tmp_path / "gif_only", **TINY_VIDEO)
    assert [p.name for p in shown.paths] == ["gif_only.gif"]
    assert any("no MP4" in n for n in shown.notes)
    assert not (tmp_path / "gif_only.mp4").exists()
    assert not [p for p in tmp_path.iterdir() if "partial" in p.name]


def test_render_command_and_its_bad_input(run_dir, tmp_path, capsys):
    out, *_ = run_dir
    small = ["--backend", "matplotlib", "--width", "64", "--height", "48", "--stride", "50"]
    assert render.main(["--body", "step", "1", str(out), "--no-mp4", *small]) == 0
    assert (out / "step1.gif").stat().st_size > 0 and not (out / "step1.mp4").exists()
    assert "walked" in capsys.readouterr().out

    empty = tmp_path / "predefined_run"
    empty.mkdir()
    (empty / "config.json").write_text("{}")
    for args, message in [
        ([str(empty)], "no saved controller"),
        ([str(out), "--body", "worst"], "unknown body 'worst'"),
        ([str(out), "--body", "step", "9"], "no controller of greedy step 9"),
        ([str(out), "--controller", "2"], "--controller 2 out of range"),
        ([str(tmp_path / "nowhere")], "no run directory"),
    ]:
        with pytest.raises(SystemExit) as e:
            render.main(args + small)
        assert e.value.code == 2 and message in capsys.readouterr().err, args
    assert list(empty.iterdir()) == [empty / "config.json"]  # nothing written
    assert not (out / "best.gif").exists()


def test_mujoco_renderer_where_gl_works():
    """MuJoCo's own pictures under MUJOCO_GL=egl (skipped where EGL gives no context)."""
    code = (
        "import numpy as np, evojax_morph as em\n"
        "from evojax_morph import video\n"
        "s = em.make_space('bad_walker')\n"
        "saved = em.SavedController(s, None, 0, s.optimum(), None, 0.0, 'best')\n"
        "rep = video.Replay(np.tile(s.template.qpos0, (2, 1)), np.zeros(1), 0.02)\n"
        "frames, by, _ = video.draw_frames(saved, rep, 'mujoco', 64, 48, 1)\n"
        "print('DRAWN', by, len(frames), frames[0].shape, frames[0].std() > 0)\n"
    )
    env = dict(os.environ, MUJOCO_GL="egl", JAX_PLATFORMS="cpu")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                          timeout=300, cwd=ROOT)
    if "DRAWN" not in proc.stdout:
        pytest.skip(f"no EGL context here: {proc.stderr.strip().splitlines()[-1:]}")
    assert "DRAWN mujoco 2 (48, 64, 3) True" in proc.stdout


def test_console_scripts_point_at_the_commands():
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    assert set(scripts) == {"evojax-morph", "evojax-morph-tame", "evojax-morph-render"}
    for target in scripts.values():
        module, name = target.split(":")
        assert callable(getattr(import_module(module), name)), target
    assert scripts["evojax-morph-render"] == "evojax_morph.render:main"
