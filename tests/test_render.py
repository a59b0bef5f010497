"""Saved controllers, their replay and its video (matplotlib fallback), the render command, and
the console scripts. The PPO trainings here (slow set) are 1-update `em.evaluate`s of two bodies
x two controllers, and `em.confirm`'s of two bodies x two controllers in the confirm stage's
test; the default set's controllers are fresh ones."""

import dataclasses
import json
import logging
import os
import pickle
import shutil
import subprocess
import sys
import tomllib
from importlib import import_module
from pathlib import Path
from types import SimpleNamespace

import chex
import jax
import numpy as np
import pytest
from conftest import DAMAGES, data_files
from PIL import Image

import evojax_morph as em
from evojax_morph import ppo, render
from evojax_morph.figures import video
from evojax_morph.physics import opengl
from evojax_morph.physics.engines import get_engine
from evojax_morph.records import bodylog, saved_controllers
from evojax_morph.records.checkpoints import Damaged
from evojax_morph.run.recorder import Recorder
from evojax_morph.search import confirm as confirming
from evojax_morph.search.pipeline import Greedy, RunConfig, build
from evojax_morph.tasks import Locomotion
from experiments import controller_engines, crawler_study

ROOT = Path(__file__).resolve().parents[1]
TINY_VIDEO = dict(backend="matplotlib", width=64, height=48, stride=50)


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    """A run directory as the driver leaves it for the PPO fitness, K = 2 controllers per body:
    best = m*, greedy trajectory m0 -> m*. The controllers are fresh ones and the fitness
    values made up: what the tests read of them is their shapes and values, not a gait (the
    trained run below is the slow set's). Episodes of 1 s (the run's default is 5 s): the same
    replay program, a fifth of the steps."""
    p = build(RunConfig(fitness="ppo", train_steps=320, controllers=2))
    p = p._replace(fitness=dataclasses.replace(p.fitness, task=em.TaskConfig(episode_length=50)))
    space = p.space
    fresh = jax.device_get(em.init_params(space, jax.random.split(jax.random.PRNGKey(0), 2),
                                          p.fitness))
    params = [jax.tree.map(lambda x, i=i: x[i], fresh) for i in range(2)]
    fitness = [12.5, 40.25]
    out = tmp_path_factory.mktemp("run")
    greedy = Greedy([space.initial(), space.optimum()], fitness, ["..."], params)
    saved = confirming.save_controllers(p, 7, space.optimum(), fitness[1], params[1], greedy)
    assert list(saved) == ["best", "step0", "step1"]
    Recorder(out, lead=True).controllers(saved)
    return out, p, params, fitness


@pytest.mark.slow  # the PPO training program: 90 s cold on 2 cores (test_fitness checks an update)
def test_one_ppo_update_moves_every_controller(run_dir):
    """The PPO fitness trains: one update (16 envs x 20 steps) of each of the 2 x 2 controllers
    of `run_dir` moves a weight of every layer of its policy and value networks, and its
    observation statistics; the fitness is finite and no world diverged."""
    _, p, params, _ = run_dir
    space = p.space
    fresh = jax.tree.map(lambda *x: np.stack(x), *params)
    res = jax.device_get(em.evaluate(space, em.stack([space.initial(), space.optimum()]),
                                     jax.random.PRNGKey(1), p.fitness, init_params=fresh))
    moved = lambda a, b: (a != b).reshape(4, -1).any(-1).all()  # each of the 2 x 2 controllers
    for name in ("policy", "value"):
        chex.assert_trees_all_equal_shapes(getattr(fresh, name), getattr(res.params, name))
        assert all(jax.tree.leaves(jax.tree.map(moved, getattr(fresh, name),
                                                getattr(res.params, name)))), name
    for name in ("mean", "summed_variance"):
        assert moved(getattr(fresh.normalizer, name), getattr(res.params.normalizer, name))
    assert np.isfinite(res.fitness).all() and not res.diverged.any()


def test_saved_controllers_round_trip(run_dir):
    out, p, params, fitness = run_dir
    best = em.load_controller(saved_controllers.body_dir(out, "best"))
    assert best.label == "best" and best.seed == 7 and best.fitness == p.fitness
    assert best.value == pytest.approx(fitness[1]) and best.space.name == "bad_walker"
    assert best.space.canonical(best.morph) == p.space.canonical(p.space.optimum())
    leaves = jax.tree.leaves(best.params)
    assert leaves[0].shape[0] == 2  # both controllers
    for saved, original in zip(leaves, jax.tree.leaves(params[1])):
        np.testing.assert_array_equal(saved, original)
    assert saved_controllers.body_dir(out, "final") == saved_controllers.body_dir(out, "step 1")
    m0 = em.load_controller(saved_controllers.body_dir(out, "step 0"))
    assert m0.space.canonical(m0.morph) == p.space.canonical(p.space.initial())
    with pytest.raises(ValueError, match="unknown body"):
        saved_controllers.body_dir(out, "worst")
    with pytest.raises(FileNotFoundError, match="saved steps: 0, 1"):
        saved_controllers.body_dir(out, "step 5")


def test_a_controller_saved_on_a_gpu_reads_here():
    """The Crawler study's kept controller was saved on an H200 (Orbax records its device,
    "cuda:0"); it reads on this machine's device, its digests checked, the body the one its
    best.pkl names; its PPO settings, saved when `worlds_per_controller` was `num_envs`, read
    under the new name."""
    kept = ROOT / "docs/figures/crawler_study"
    assert "cuda:0" in (kept / "best_controller/params/_sharding").read_text()
    saved = em.load_controller(kept / "best_controller")
    best = pickle.loads((kept / "best.pkl").read_bytes())
    assert saved.space.name == "crawler" and saved.label.startswith("the study's best body")
    assert saved.space.canonical(saved.morph) == best["entry"]["body"]
    assert '"num_envs": 16' in (kept / "best_controller/meta/metadata").read_text()
    assert saved.fitness.ppo.worlds_per_controller == 16
    assert all(x.devices() == {jax.local_devices()[0]} for x in jax.tree.leaves(saved.params))


def test_a_damaged_controller_is_an_error(run_dir, tmp_path, capsys):
    """Each data file of a saved controller (its arrays' and its metadata's), one at a time,
    with bytes inverted in place, cut to half, then deleted: `em.load_controller` either raises
    `Damaged`, naming the controller and the check, and `render` exits 2 with that message, or
    loads the controller saved, bit for bit. A controller saved without digests (before they
    were kept) or holding a NaN is damaged too."""
    out, p, *_ = run_dir
    saved = em.load_controller(out / saved_controllers.DIR / "step0")
    caught = []
    for i, f in enumerate(data_files(out / saved_controllers.DIR / "step0")):
        for damage in DAMAGES:
            run = tmp_path / f"{i}{damage.__name__}"
            step0 = Path(saved_controllers.DIR, "step0")
            shutil.copytree(out / step0, run / step0)
            damage(run / f.relative_to(out))
            said = f"saved controller {run / saved_controllers.DIR / 'step0'} "
            try:
                loaded = em.load_controller(run / saved_controllers.DIR / "step0")
            except Damaged as e:  # (which array fails first may differ from one read to the next)
                assert str(e).startswith(said)
                with pytest.raises(SystemExit) as code:
                    render.main([str(run), "--body", "step", "0", "--no-mp4"])
                assert code.value.code == 2 and f"error: {said}" in capsys.readouterr().err
                caught.append(str(e))
                continue
            chex.assert_trees_all_equal(loaded.params, saved.params)
            assert loaded.space.canonical(loaded.morph) == saved.space.canonical(saved.morph)
    assert len(caught) >= len(DAMAGES) * 2, caught
    assert [c for c in caught if c.endswith(": its SHA-256 is not the saved one")], caught

    meta = tmp_path / "old" / "meta" / "metadata"  # saved before controllers had digests
    shutil.copytree(out / saved_controllers.DIR / "step0", tmp_path / "old")
    meta.write_text(json.dumps({k: v for k, v in json.loads(meta.read_text()).items()
                                if k not in ("sha256", "params")}))
    with pytest.raises(Damaged, match="is damaged: metadata: no digest saved"):
        em.load_controller(tmp_path / "old")
    nan = jax.tree.map(lambda x: x * np.nan, saved.params)
    saved_controllers.save(tmp_path / "nan", dataclasses.replace(saved, params=nan))
    with pytest.raises(Damaged, match=r"is damaged: \.normalizer\.mean: non-finite values where"):
        em.load_controller(tmp_path / "nan")


@pytest.mark.slow  # its own PPO program (C = 2 at 320 steps): over 2 minutes cold on 2 cores
def test_confirmed_best_keeps_its_fresh_controllers(run_dir, tmp_path):
    """The confirm stage on the PPO fitness (one PPO update per controller here): C = 2
    controllers trained afresh on each body of the log; the best body's are saved, best first,
    and read back when a finished run is resumed."""
    _, p, _, _ = run_dir
    space = p.space
    log = bodylog.BodyLog(tmp_path / "bodies.sqlite", space)
    log.add(0, em.stack([space.initial(), space.optimum()]), [1.0, 2.0], [0.0, 0.0], [0, 0])
    log.commit()
    log.close()
    cfg = RunConfig(fitness="ppo", train_steps=320, controllers=2, confirm=2,
                    confirm_controllers=2)
    path = tmp_path / "bodies.sqlite"
    ranked = bodylog.best_bodies(path, 2)
    shapes = bodylog.shapes(path, space, [b["body"] for b in ranked])
    candidates = [(b, space.to_json(shapes[b["body"]])) for b in ranked]
    record, top, _ = confirming.confirm_record(p, cfg, 0, candidates)
    confirmed = record["confirmed"]
    assert [c["log_mean"] for c in confirmed] in ([2.0, 1.0], [1.0, 2.0])
    assert top.body == confirmed[0]["body"] and top.mean == confirmed[0]["mean"]
    assert [c["controllers"] for c in confirmed] == [2, 2]
    best, fitness, params, best_cfg = confirming.reported_best(p, record, top, None)
    assert best_cfg.ppo.controllers == 2 and fitness == top.mean
    Recorder(tmp_path, lead=True).controllers(
        confirming.save_controllers(p, 7, best, fitness, params, None, best_cfg))
    kept = em.load_controller(saved_controllers.body_dir(tmp_path, "best"))
    assert kept.fitness.ppo.controllers == 2 and kept.value == top.mean
    order = np.argsort(-top.values, kind="stable")  # controller 0 the best, for best.gif
    for saved, trained in zip(jax.tree.leaves(kept.params), jax.tree.leaves(top.params)):
        np.testing.assert_array_equal(saved, trained[order])
    record["best_morphology"] = best.to_dict()  # as confirmed.json keeps it
    again = confirming.reported_best(
        p, record, None, None, (em.Morphology.from_dict(record["best_morphology"]), kept))
    assert space.canonical(again[0]) == top.body and again[3] == best_cfg
    for x, y in zip(jax.tree.leaves(again[2]), jax.tree.leaves(kept.params)):
        np.testing.assert_array_equal(x, y)


def test_the_studys_best_body_keeps_its_typical_controller_and_its_video(run_dir, tmp_path,
                                                                          monkeypatch):
    """`crawler_study.confirm_best` on the PPO fitness: the best candidate of the runs is
    confirmed, its controller of median return kept and drawn; the next call reuses both, and
    confirms again when the controller is gone. `em.confirm` answers with fresh controllers and
    made-up returns (test_confirmed_best_keeps_its_fresh_controllers confirms for real)."""
    _, p, _, _ = run_dir
    space, calls = p.space, []
    fresh = jax.device_get(em.init_params(space, jax.random.split(jax.random.PRNGKey(1), 4),
                                          p.fitness))
    values = np.array([30.0, 10.0, 20.0, 50.0])  # the lower median, 20, is controller 2

    def confirm(space_, morphs, key, cfg, controllers):
        calls.append(controllers)
        morph = jax.tree.map(lambda x: np.asarray(x[0]), morphs)
        return [em.Confirmed(space.canonical(morph), morph, values, np.zeros(4, bool), fresh,
                             np.ones(4), np.ones(4))]

    monkeypatch.setattr(crawler_study.em, "confirm", confirm)
    render = video.render_saved  # small and on matplotlib, whatever size the study asks
    monkeypatch.setattr(crawler_study.video, "render_saved",
                        lambda saved, stem, **_: render(saved, stem, mp4=False, **TINY_VIDEO))
    runs = [{"method": "a2c", "seed": 3, "candidates": [(m, x, space.canonical(x)) for m, x in
                                                        ((5.0, space.initial()),
                                                         (9.0, space.optimum()))]}]
    args = SimpleNamespace(data=tmp_path, best_controllers=4)
    best = crawler_study.confirm_best(space, p.fitness, runs, args, tmp_path / "best")
    assert calls == [4] and best["entry"]["body"] == space.canonical(space.optimum())
    assert (best["entry"]["method"], best["entry"]["seed"], best["video"]["controller"]) == \
        ("a2c", 3, 2)
    kept = em.load_controller(tmp_path / "best_controller")
    assert kept.value == 20.0 and kept.seed == 3
    for saved, trained in zip(jax.tree.leaves(kept.params), jax.tree.leaves(fresh)):
        np.testing.assert_array_equal(saved, trained[2])
    assert best["video"]["file"] == "best.gif" and (tmp_path / "best.gif").stat().st_size > 0
    assert crawler_study.confirm_best(space, p.fitness, runs, args, tmp_path / "best") == best
    assert calls == [4]
    shutil.rmtree(tmp_path / "best_controller")
    crawler_study.confirm_best(space, p.fitness, runs, args, tmp_path / "best")
    assert calls == [4, 4] and (tmp_path / "best_controller").exists()


@pytest.mark.slow  # its replay program: a minute cold on 2 cores
def test_replay_is_the_fitness_evaluation_episode(run_dir):
    """The replay of controller k from reset key r returns what the PPO fitness's evaluation
    (`ppo.make_evaluate_learners`, which scores every trained controller) returns for it."""
    out, p, _, _ = run_dir
    saved = em.load_controller(saved_controllers.body_dir(out, "best"))
    cfg = dataclasses.replace(saved.fitness.ppo, eval_episodes=1)
    env = Locomotion(saved.space, saved.fitness.task)
    evaluate = jax.jit(ppo.make_evaluate_learners(saved.space, env, get_engine("jax"), cfg))
    models = jax.tree.map(lambda x: x[None], saved.space.mjx_model(saved.morph))  # B = 1
    key = jax.random.PRNGKey(3)
    replays = []
    for k in range(2):
        one = jax.tree.map(lambda x, k=k: x[k : k + 1], saved.params)  # L = 1
        episodes = evaluate(key[None], models, one)
        rep = em.replay(saved, jax.random.split(key, 1)[0], controller=k)
        np.testing.assert_allclose(rep.episode_return, float(episodes.returns[0, 0]),
                                   rtol=1e-5, atol=1e-5)
        assert rep.qpos.shape == (len(rep.reward) + 1, saved.space.template.nq)
        replays.append(rep)
    assert not np.allclose(replays[0].qpos[-1], replays[1].qpos[-1])  # two controllers
    with pytest.raises(ValueError, match="out of range"):
        em.replay(saved, controller=2)


@pytest.mark.slow  # its evaluation program and the replay's: about a minute cold on 2 cores
def test_the_engines_check_scores_the_replays_episodes(run_dir):
    """`experiments.controller_engines` scores controller 0 in the episodes `replay` draws from
    the same reset keys (split(key)), on the engine it is asked for."""
    out, _, _, _ = run_dir
    saved = em.load_controller(saved_controllers.body_dir(out, "best"))
    key = jax.random.PRNGKey(5)
    got = controller_engines.scores(saved, "jax", 2, key)
    replays = [em.replay(saved, k, controller=0).episode_return for k in jax.random.split(key, 2)]
    np.testing.assert_allclose(got["returns"], replays, rtol=1e-4, atol=1e-2)
    assert got["engine"] == "jax" and got["mean"] == pytest.approx(np.mean(replays), abs=1e-2)


def test_replay_compiles_ahead(run_dir, monkeypatch, caplog):
    """`video.lower_replay` of the config a run knows before its end (its own) compiles the
    program that `replay` of the saved controller then calls: the replay compiles no other."""
    out, p, _, _ = run_dir
    monkeypatch.setattr(video, "_EPISODE_FNS", {})  # as in a new process
    with jax.log_compiles(True), caplog.at_level(logging.WARNING, logger="jax"):
        video.lower_replay(p.space, p.fitness).compile()
        ahead = len(caplog.records)
        em.replay(em.load_controller(saved_controllers.body_dir(out, "best")), controller=1)
    episode = [i for i, r in enumerate(caplog.records)
               if r.getMessage().startswith("Compiling jit(episode)")]
    assert len(episode) == 1 and episode[0] < ahead


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
        err = capsys.readouterr().err.strip().splitlines()  # the reason and --help, no usage
        assert e.value.code == 2 and len(err) == 2 and message in err[0], (args, err)
    assert list(empty.iterdir()) == [empty / "config.json"]  # nothing written
    assert not (out / "best.gif").exists()


_DRAW = (
    "import numpy as np, evojax_morph as em\n"
    "from evojax_morph.figures import video\n"
    "s = em.make_space('bad_walker')\n"
    "saved = em.SavedController(s, None, 0, s.optimum(), None, 0.0, 'best')\n"
    "rep = video.Replay(np.tile(s.template.qpos0, (2, 1)), np.zeros(1), 0.02)\n"
    "frames, by, notes = video.draw_frames(saved, rep, 'auto', 64, 48, 1)\n"
    "print('DRAWN', by, len(frames), frames[0].shape, frames[0].std() > 0)\n"
    "print('NOTES', notes)\n"
)
# MuJoCo's own Renderer, on the GL that `import mujoco` takes from MUJOCO_GL: the reference.
_MUJOCO_ALONE = (
    "import mujoco\n"
    "m = mujoco.MjModel.from_xml_string('<mujoco><worldbody><geom size=\"1\"/></worldbody>"
    "</mujoco>')\n"
    "r = mujoco.Renderer(m, 8, 8); d = mujoco.MjData(m); mujoco.mj_forward(m, d)\n"
    "r.update_scene(d); print('DREW' if r.render().std() > 0 else 'BLANK'); r.close()\n"
)


def _python(code, **env):
    base = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "DISPLAY",
                                                              "WAYLAND_DISPLAY")}
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env=dict(base, JAX_PLATFORMS="cpu", **env), timeout=300, cwd=ROOT)


def test_mujoco_gl_chosen_without_a_display():
    """With MUJOCO_GL unset and no display, `auto` draws with MuJoCo on the first of EGL and
    OSMesa that MuJoCo's own Renderer draws with here, and says which; with neither, matplotlib
    and why. MUJOCO_GL, when set, is kept."""
    works = [gl for gl in opengl.GL_FALLBACKS
             if "DREW" in _python(_MUJOCO_ALONE, MUJOCO_GL=gl).stdout]
    proc = _python(_DRAW)
    assert "DRAWN" in proc.stdout, proc.stderr[-2000:]
    if works:
        assert f"DRAWN mujoco ({works[0]}) 2 (48, 64, 3) True" in proc.stdout
        assert "Exception ignored" not in proc.stderr  # the GL context was freed before exit
        proc = _python(_DRAW, MUJOCO_GL=works[0])  # set by the user: no probe, same GL
        assert f"DRAWN mujoco ({works[0]}) 2 (48, 64, 3) True" in proc.stdout
    else:
        assert "DRAWN matplotlib 2 (48, 64, 3) True" in proc.stdout
        assert all(f"{gl}: " in proc.stdout for gl in opengl.GL_FALLBACKS)


def test_gl_fallbacks_in_order_then_matplotlib(run_dir, monkeypatch, tmp_path):
    """The GLs are probed in order (GLFW only with a display); when none draws, `auto` falls
    back to matplotlib saying why, and `mujoco` raises, writing nothing."""
    tried = []

    def probe(name):
        tried.append(name)
        return f"{name} failed here"

    for display, expected in [(None, ["egl", "osmesa"]), (":0", ["glfw", "egl", "osmesa"])]:
        tried.clear()
        monkeypatch.setattr(opengl, "_GL_CHOICE", [])
        monkeypatch.delenv("MUJOCO_GL", raising=False)
        monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
        if display:
            monkeypatch.setenv("DISPLAY", display)
        else:
            monkeypatch.delenv("DISPLAY", raising=False)
        name, context, notes = opengl.choose_gl(probe)
        assert (name, context) == (None, None) and tried == expected
        assert all(f"{gl}: {gl} failed here" in notes for gl in expected)
        assert opengl.choose_gl(probe)[2] == notes and tried == expected  # chosen once

    out, *_ = run_dir
    shown = em.render_video(out, "best", tmp_path / "walk", **dict(TINY_VIDEO, backend="auto"))
    assert shown.backend == "matplotlib"
    assert any("egl: egl failed here" in n for n in shown.notes)
    with pytest.raises(RuntimeError, match="osmesa failed here"):
        em.render_video(out, "best", tmp_path / "gl", **dict(TINY_VIDEO, backend="mujoco"))
    assert not (tmp_path / "gl.gif").exists()


def test_console_scripts_point_at_the_commands():
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    assert set(scripts) == {"evojax-morph", "evojax-morph-tame", "evojax-morph-render"}
    for target in scripts.values():
        module, name = target.split(":")
        assert callable(getattr(import_module(module), name)), target
    assert scripts["evojax-morph-render"] == "evojax_morph.render:main"
