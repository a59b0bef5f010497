"""The flat world batch (JAX impl) and MuJoCo Warp behind MJX against the nested JAX batch.

The Warp tests are skipped where MuJoCo Warp is not installed (CI); here they run on the CPU,
through MJX's Warp implementation, at 3 bodies x 2 envs per space.
"""

import dataclasses
import functools
import json
import os
import re
import subprocess
import sys
import types

import chex
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from conftest import float64
from mujoco.mjx import warp as mjx_warp

import evojax_morph as em
from evojax_morph.physics import templates, warp_models
from evojax_morph.physics import warp as ew
from evojax_morph.physics.templates import mjx
from evojax_morph.spaces import crawler as cr

BODIES, ENVS, STEPS = 3, 2, 5
WARP_OK, WARP_REASON = ew.available()
requires_warp = pytest.mark.skipif(not WARP_OK, reason=f"MuJoCo Warp: {WARP_REASON}")
# Warp (float32) vs the JAX impl (float32), max |qpos difference| over the first 5 steps of
# these 3 bodies x 2 envs, measured on this CPU: 7.3e-8 (Bad Walker), 9.7e-8 (Constructor),
# 2.5e-8 (Length Walker), qpos up to 0.09; 30x the largest here. A world stepping another
# body (the nested-vmap bug) moves by at least 1.9e-2 (2.1e-2 on an H100). On an H100
# (2026-11-26) the JAX impl's float32 differs more: 8.4e-5 (Constructor), under 3e-6 (the
# others); 12x that there.
WARP_TOL = 3e-6 if jax.default_backend() == "cpu" else 1e-3
# The tests that step Warp also step the 3D Crawler (they are skipped where MuJoCo Warp is
# missing, as in CI, so it costs the default set nothing).
warp_spaces = pytest.mark.parametrize(
    "space", ["bad_walker", "constructor", "length_walker", "crawler"], indirect=True)


class _ConvergedCrawler(cr.Crawler):
    """The Crawler with its contact solves run to convergence. These tests start every body at
    the template's qpos0, where the Crawler's legs reach into the floor (the task starts each
    at its own height); at the shipped 4 Newton iterations the two engines' solves of that
    start part at once: the JAX impl's joint angles are 0.15 rad from 50 iterations' after one
    step, Warp's 0.005 (CPU, these 3 bodies x 2 envs, 2026-11-27). Converged, they agree to
    2.1e-4 over 5 steps (CPU)."""

    @functools.cached_property
    def plan(self):
        return dataclasses.replace(super().plan, iterations=50, ls_iterations=50)


@functools.cache  # the tests of a space share its bodies and their one specialisation program
def _morphs(space):
    keys = jax.random.split(jax.random.PRNGKey(0), BODIES)
    return jax.vmap(space.random_morphology, (0, None))(keys, space.default_horizon)


@functools.cache
def _bodies(space):
    models = jax.jit(jax.vmap(space.mjx_model))(_morphs(space))
    # Random walks may meet: make sure the bodies differ, or the isolation check proves nothing.
    shape = np.concatenate([models.body_mass, models.body_pos.reshape(BODIES, -1)], 1)
    assert all(not np.allclose(shape[i], shape[i - 1]) for i in range(BODIES)), shape
    return models


def _controls(space):
    """(STEPS, B, E, nu): random, the same for every body, so that bodies alone differ."""
    shape = (STEPS, 1, ENVS, space.template.nu)
    ctrl = jax.random.uniform(jax.random.PRNGKey(1), shape, minval=-1.0, maxval=1.0)
    return jnp.broadcast_to(ctrl, (STEPS, BODIES, ENVS, space.template.nu))


def _nested_jax(space, models, ctrl):
    """(STEPS, B, E, nq) qpos of today's batch: a vmap over bodies around a vmap over envs."""
    make = lambda _: mjx.make_data(space.mjx_template())
    data = jax.vmap(jax.vmap(make))(jnp.zeros((BODIES, ENVS)))
    step = jax.vmap(jax.vmap(mjx.step, (None, 0)))

    def body(data, c):
        data = step(models, data.replace(ctrl=c))
        return data, data.qpos

    return jax.jit(lambda d, c: jax.lax.scan(body, d, c)[1])(data, ctrl)


def test_specialise_writes_only_the_listed_fields(space):
    models = _bodies(space)
    template = space.mjx_template()
    paths, leaves = zip(*jax.tree_util.tree_leaves_with_path(models))
    changed = {
        jax.tree_util.keystr(path)
        for path, leaf, orig in zip(paths, leaves, jax.tree.leaves(template))
        if not np.array_equal(np.asarray(leaf), np.broadcast_to(orig, leaf.shape))
    }
    listed = {f".{name}" for name in templates.SPECIALISED_FIELDS} | {".stat.meaninertia"}
    assert changed <= listed, changed - listed


def test_capsule_boxes_match_mujocos(space):
    """The broadphase boxes `to_warp` writes are those MuJoCo compiles for the unpadded body."""
    m = jax.tree.map(lambda x: x[0], _morphs(space))
    export = mujoco.MjModel.from_xml_string(space.to_mjcf(m))
    sizes = _bodies(space).geom_size[0]
    boxes = np.asarray(warp_models._capsule_aabb(space.template, sizes))
    for g in range(export.ngeom):
        name = export.geom(g).name
        expected = export.geom_aabb[g].reshape(2, 3)
        np.testing.assert_allclose(boxes[space.template.geom(name).id], expected, atol=1e-6)


@pytest.mark.slow  # 46 s cold; test_fitness checks the flat world batch in the default set
def test_flat_jax_batch_equals_nested():
    """One space suffices: the layout of worlds is the same for every space (and each space's
    compile costs 20-30 s of the suite)."""
    space = em.make_space("length_walker")
    models = _bodies(space)
    ctrl = _controls(space)
    expected = _nested_jax(space, models, ctrl)

    flat, axes = templates.flat_models(models, ENVS)
    data = jax.vmap(lambda _: mjx.make_data(space.mjx_template()))(jnp.arange(BODIES * ENVS))
    step = jax.vmap(mjx.step, (axes, 0))

    def body(data, c):
        data = step(flat, data.replace(ctrl=c.reshape(BODIES * ENVS, -1)))
        return data, data.qpos.reshape(BODIES, ENVS, -1)

    got = jax.jit(lambda d, c: jax.lax.scan(body, d, c)[1])(data, ctrl)
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-6)


def test_unavailable_warp_is_a_clear_error(monkeypatch):
    space = em.make_space("bad_walker")
    with float64():  # float64 on: Warp cannot run, whether installed or not
        ok, reason = ew.available()
        assert not ok and reason
        with pytest.raises(RuntimeError, match="the Warp physics cannot run: " + re.escape(reason)):
            ew.to_warp(space, None, ENVS)
    monkeypatch.setattr(mjx_warp, "WARP_INSTALLED", False)  # as in CI
    ok, reason = ew.available()
    assert not ok and "pip install 'evojax_morph[warp]'" in reason
    with pytest.raises(RuntimeError, match="warp-lang is not installed"):
        ew.put_model(space.template)


@requires_warp
@warp_spaces
def test_warp_flat_batch_agrees_with_jax_per_world(space):
    tol = WARP_TOL
    if space.name == "crawler":  # 5x the CPU's 2.1e-4 (above)
        space, tol = _ConvergedCrawler(), 1e-3
    models = _bodies(space)
    ctrl = _controls(space)
    expected = np.asarray(_nested_jax(space, models, ctrl))  # (STEPS, B, E, nq)

    model, data = ew.to_warp(space, models, ENVS)
    assert data.qpos.shape == (BODIES * ENVS, space.template.nq)

    def body(data, c):
        data = ew.step_worlds(model, data, c.reshape(BODIES * ENVS, -1))
        return data, data.qpos.reshape(BODIES, ENVS, -1)

    got = np.asarray(jax.jit(lambda d, c: jax.lax.scan(body, d, c)[1])(data, ctrl))
    error = np.abs(got - expected).max()
    assert error < tol, error

    # Each world reads its own body: had world w = b * E + e read body w % B (the nested-vmap
    # bug), it would follow that body's trajectory (same start, same controls), which is far
    # outside the tolerance.
    wrong_body = np.arange(BODIES * ENVS).reshape(BODIES, ENVS) % BODIES
    buggy = expected[:, wrong_body, np.arange(ENVS)[None, :]]
    moved = np.abs(buggy - expected).max(axis=(0, 3))  # (B, E)
    assert (moved[wrong_body != np.arange(BODIES)[:, None]] > 10 * tol).all(), moved


def _same(space, got, want, name):
    """Bit for bit; but on a GPU, Warp orders contacts by thread timing, and the Crawler's legs
    touch the floor from the first step here (the planar bodies start in the air): 1.2e-7
    apart there on an H100, so within WARP_TOL."""
    if jax.default_backend() == "cpu" or space.name != "crawler":
        np.testing.assert_array_equal(got, want, err_msg=name)
    else:
        np.testing.assert_allclose(got, want, atol=WARP_TOL, err_msg=name)


def _step_n(model, data, ctrl):
    """`data` after len(ctrl) steps of `ctrl` (steps, N, nu), and each step's data."""
    def body(data, c):
        data = ew.step_worlds(model, data, c)
        return data, data
    return jax.jit(lambda d, c: jax.lax.scan(body, d, c))(data, ctrl)


@requires_warp
@warp_spaces
def test_steps_in_one_warp_call_equal_one_call_a_step(space, monkeypatch):
    """`steps(model, data, 4)` runs the 4 physics steps in one call into Warp (one shim, its own
    Warp callable) and lands on the same state, bit for bit, as 4 calls of one step; the
    benchmark switch EVOJAX_MORPH_WARP_FUSE=0, and an MJX laid out otherwise, make 4 calls."""
    model, data = ew.to_warp(space, _bodies(space), ENVS)
    ctrl = _controls(space)[0].reshape(BODIES * ENVS, -1)
    data = data.replace(ctrl=ctrl)

    def calls(fn):  # (Warp calls written, whether in a loop)
        text = str(jax.make_jaxpr(fn)(model, data))
        return text.count("ffi_call"), "while" in text or "scan" in text

    fused = lambda m, d: ew.steps(m, d, 4)
    single = lambda m, d: ew.step_worlds(m, d, d.ctrl)
    got = jax.jit(fused)(model, data)
    want = data
    for _ in range(4):
        want = jax.jit(single)(model, want)
    for name in ("qpos", "qvel", "qacc_warmstart", "time"):
        _same(space, getattr(got, name), getattr(want, name), name)
    assert np.abs(np.asarray(got.qpos) - np.asarray(data.qpos)).max() > 1e-4  # it moved
    assert calls(fused) == calls(single) == (1, False)
    monkeypatch.setenv("EVOJAX_MORPH_WARP_FUSE", "0")
    assert calls(lambda m, d: ew.steps(m, d, 4)) == (1, True)  # a new function: jit caches
    # An MJX without the functions the copy is made of: a warning, and one call a step.
    monkeypatch.delenv("EVOJAX_MORPH_WARP_FUSE")
    from mujoco.mjx.warp import forward

    monkeypatch.setattr(mjx_warp, "forward", types.SimpleNamespace(step=forward.step))
    monkeypatch.setattr(ew, "_fused_step", functools.cache(ew._fused_step.__wrapped__))
    with pytest.warns(UserWarning, match="one call into Warp per physics step"):
        assert calls(lambda m, d: ew.steps(m, d, 3)) == (1, True)


@requires_warp
@warp_spaces
def test_plain_solver_loop_steps_as_mjxs_conditional(space, monkeypatch):
    """`put_model` runs the solver's iterations as a plain loop, not MJX's CUDA graph
    conditional that stops once every world has converged (3-7% faster on an H100): a world
    that has converged skips the remaining passes either way, so the worlds step alike."""
    models, ctrl = _bodies(space), _controls(space).reshape(STEPS, BODIES * ENVS, -1)
    model, data = ew.to_warp(space, models, ENVS)
    assert not model.opt._impl.graph_conditional
    plain, _ = _step_n(model, data, ctrl)
    monkeypatch.setenv("EVOJAX_MORPH_WARP_CONDITIONAL", "1")
    model, data = ew.to_warp(space, models, ENVS)
    assert model.opt._impl.graph_conditional
    conditional, _ = _step_n(model, data, ctrl)
    if jax.default_backend() == "cpu":
        np.testing.assert_array_equal(plain.qpos, conditional.qpos)
    else:  # Warp on a GPU orders contacts by thread timing
        np.testing.assert_allclose(plain.qpos, conditional.qpos, atol=WARP_TOL)


@requires_warp
def test_stream_registrations_are_counted(monkeypatch):
    """warp-lang erases an external CUDA stream's entry when any one of its `wp.Stream`s dies,
    which failed a later Warp call's graph capture on an H100 ("unknown stream"); counted, the
    entry goes with the last."""
    import warp as wp

    wp.init()
    core, calls = wp._src.context.runtime.core, []
    monkeypatch.setattr(core, "wp_cuda_stream_register", lambda c, s: calls.append(("in", s)))
    monkeypatch.setattr(core, "wp_cuda_stream_unregister", lambda c, s: calls.append(("out", s)))
    ew.count_stream_registrations()
    ew.count_stream_registrations()  # once only
    for stream in (7, 7, 8):
        core.wp_cuda_stream_register(None, stream)
    core.wp_cuda_stream_unregister(None, 7)
    assert calls == [("in", 7), ("in", 8)]
    core.wp_cuda_stream_unregister(None, 7)
    core.wp_cuda_stream_register(None, 7)
    assert calls[2:] == [("out", 7), ("in", 7)]


def _every_crawler_limb(space, key):
    """The Crawler with all 18 limbs, then 20 random length and axis changes."""
    m = space.initial()
    for site in range(cr.NUM_SITES):
        m = space.mutate(m, 0, cr.ADD[site])
        for depth in (1, 2):  # node 3 s + d: the limb at depth d of the chain at site s
            m = space.mutate(m, 3 * site + depth, cr.EXTEND)
    nodes, kinds = jax.random.split(key)
    changes = (cr.SHORTER, cr.LONGER, cr.FLIP)
    for node, kind in zip(jax.random.randint(nodes, (20,), 1, space.max_nodes),
                          jax.random.randint(kinds, (20,), 0, len(changes))):
        m = space.mutate(m, node, jnp.asarray(changes)[kind])
    return m


@requires_warp
@warp_spaces
def test_buffers_hold_what_the_largest_bodies_need(space):
    """`buffers(space)` bounds contacts and constraint rows per world: random bodies of the
    space's full size (its most active capsules), stepped with 4x the room and dropped onto
    the floor, never need more; and with the bounds as given they step exactly alike."""
    keys = jax.random.split(jax.random.PRNGKey(3), 16)
    if space.name == "crawler":  # random walks stay far from its 18 limbs: grow them all
        morphs = jax.vmap(lambda k: _every_crawler_limb(space, k))(keys)
    else:
        morphs = jax.vmap(space.random_morphology, (0, None))(keys, 4 * space.default_horizon)
    capsules = np.asarray(jax.vmap(space.layout)(morphs).geom_active).sum(1)
    assert capsules.max() <= space.max_nodes and capsules.max() >= space.max_nodes - 1, capsules
    models = jax.jit(jax.vmap(space.mjx_model))(morphs)
    contacts, rows = ew.buffers(space)
    n, steps = models.body_mass.shape[0], 40  # 0.2 s: every body lands and settles its feet
    ctrl = jax.random.uniform(jax.random.PRNGKey(4), (steps, n, space.template.nu), minval=-1)
    model, data = ew.to_warp(space, models, 1, naconmax_per_world=4 * contacts, njmax=4 * rows)
    roomy, trace = _step_n(model, data, ctrl)
    # The worlds share one contact pool (n x contacts); rows are per world.
    nacon, used_rows = np.asarray(trace._impl.nacon[:, 0]), np.asarray(trace._impl.nefc).max()
    assert 0 < nacon.max() <= n * contacts and 0 < used_rows <= rows, (nacon, used_rows)
    if jax.default_backend() == "cpu":
        # Contacts per world. On an H100 the pool's per-contact fields came back as zeros (world
        # 0, geoms 0, 0) from MJX's GPU step, though its count and the rows were right.
        per_world = [np.bincount(np.asarray(w)[:k], minlength=n).max()
                     for w, k in zip(trace._impl.contact__worldid, nacon)]
        assert 0 < max(per_world) <= contacts, per_world
    model, data = ew.to_warp(space, models, 1)
    tight, _ = _step_n(model, data, ctrl)
    if jax.default_backend() == "cpu":
        np.testing.assert_array_equal(tight.qpos, roomy.qpos)
    else:  # Warp on a GPU orders contacts by thread timing: 1.2e-7 apart on an H100
        np.testing.assert_allclose(tight.qpos, roomy.qpos, atol=WARP_TOL)


@requires_warp
@warp_spaces
def test_where_worlds_selects_all_a_step_reads(space):
    """Worlds reset with `where_worlds` (the state fields alone) step exactly as worlds whose
    every per-world field was selected: the next step recomputes the rest."""
    from mujoco.mjx._src.types import tree_path_to_attr_str
    from mujoco.mjx.warp import types as warp_types

    models = _bodies(space)
    model, data = ew.to_warp(space, models, ENVS)
    ctrl = _controls(space).reshape(STEPS, BODIES * ENVS, -1)
    first = jax.jit(jax.vmap(mjx.forward, (None, 0)))(model, data)
    moved, _ = _step_n(model, first, ctrl)
    done = jnp.arange(BODIES * ENVS) % 2 == 0
    per_world = warp_types._BATCH_DIM["Data"]

    def every_field(path, a, b):
        if not per_world.get(tree_path_to_attr_str(path), True):
            return b
        return jnp.where(done.reshape((-1,) + (1,) * (a.ndim - 1)), a, b)

    full = jax.tree_util.tree_map_with_path(every_field, first, moved)
    slim = ew.where_worlds(done, first, moved)
    assert not np.array_equal(slim.xpos, full.xpos)  # the slim reset leaves derived fields stale
    full, _ = _step_n(model, full, ctrl)
    slim, _ = _step_n(model, slim, ctrl)
    for name in ew.STATE_FIELDS:
        _same(space, getattr(slim, name), getattr(full, name), name)


@requires_warp
@pytest.mark.slow  # three PPO programs (JAX, Warp, Warp trained) to compile: minutes on 2 cores
def test_ppo_fitness_on_warp():
    """The PPO fitness with physics="warp": 3 bodies x 2 controllers x 4 envs in one flat Warp
    batch. Untrained controllers score as on the JAX engine over short episodes (the engines
    part only after many contact steps: docs/benchmarks.md compares trained fitness in
    distribution, on a GPU); training runs and hands back controllers of the init's shapes."""
    space = em.make_space("bad_walker")
    third = jax.tree.map(lambda x: x[0], _morphs(space))
    morphs = em.stack([space.initial(), space.optimum(), third])
    keys = jax.random.split(jax.random.PRNGKey(2), 3)
    ppo_cfg = em.PPOConfig(train_steps=0, worlds_per_controller=4, unroll_length=4,
                           num_minibatches=2, update_epochs=1, controllers=2, eval_episodes=2)
    task = em.TaskConfig(episode_length=5)
    untrained = {
        p: em.evaluate(space, morphs, keys, em.FitnessConfig(task=task, ppo=ppo_cfg, physics=p))
        for p in ("jax", "warp")
    }
    # Measured on this CPU: Warp - JAX = 3e-6, 6.5e-4 (m*, whose feet meet the floor first)
    # and 0 for fitness -0.022, 0.359, -0.007. The bodies' fitness differ by 0.015 and more, so
    # a world stepping another body's model would fail.
    np.testing.assert_allclose(untrained["warp"].fitness, untrained["jax"].fitness, atol=5e-3)
    assert np.diff(np.sort(np.asarray(untrained["jax"].fitness))).min() > 0.01

    trained_cfg = em.FitnessConfig(
        task=task, ppo=dataclasses.replace(ppo_cfg, train_steps=32), physics="warp"
    )
    out = em.evaluate(space, morphs, keys, trained_cfg, init_params=untrained["warp"].params)
    assert np.isfinite(np.asarray(out.fitness)).all() and not np.asarray(out.diverged).any()
    chex.assert_trees_all_equal_shapes(out.params, untrained["warp"].params)
    changed = jax.tree.map(lambda a, b: not np.array_equal(a, b), out.params.policy,
                           untrained["warp"].params.policy)
    assert all(jax.tree.leaves(changed))  # two updates moved every policy weight


PRELOAD_CHECK = """
import jax
import evojax_morph as em
from mujoco.mjx import warp as mjx_warp
from warp._src.context import user_modules
from evojax_morph.physics import warp_kernels
space = em.make_space("crawler")
warp_kernels.preload(jax.local_devices(), space).result()
package = mjx_warp.mujoco_warp.__name__ + "._src."
names = [package + n for n in warp_kernels.FIXED_MODULES] + ["mujoco.mjx.warp.ffi"]
preloaded = {n: set(m.execs) for n, m in user_modules.items() if m.execs}
assert all(preloaded.get(n) for n in names), preloaded
made = [n for n in preloaded if "." not in n]  # modules of one kernel, made from the model
keys = jax.random.split(jax.random.PRNGKey(0), 2)
morphs = jax.vmap(space.random_morphology, (0, None))(keys, 3)
ppo = em.PPOConfig(train_steps=32, worlds_per_controller=4, unroll_length=4, num_minibatches=2,
                   update_epochs=1, controllers=1, eval_episodes=1)
cfg = em.FitnessConfig(task=em.TaskConfig(episode_length=5), ppo=ppo, physics="warp")
jax.block_until_ready(em.evaluate(space, morphs, keys, cfg).fitness)
loaded = {n: set(m.execs) for n, m in user_modules.items() if m.execs}
named = {n for n in loaded if n.startswith("mujoco.")}
assert named <= set(names), sorted(named - set(names))
new = sorted(n for n in loaded if loaded[n] != preloaded.get(n, set()))
assert all(n.startswith("_nxn_broadphase") for n in new), new
print("MODULES", len(named), "MADE", len(made), "NEW", len(new), new)
"""


@requires_warp
@pytest.mark.slow  # a PPO program compiled in a fresh process
def test_preload_holds_the_modules_a_step_loads():
    """`warp_kernels.preload` with a space compiles what a step would compile of MuJoCo Warp's named
    modules (and MJX's Warp call) and of the modules of one kernel it makes from the model, at
    the block sizes the step launches them at: in a fresh process, after it, a PPO evaluation
    (training, then episodes) loads no other module and no other variant of one, but the
    broadphase's, whose code holds the number of worlds. A new MJX that moves kernels into
    another module, or makes them from what `model_modules` does not set, fails here. The
    Crawler: its elliptic cones take solver paths the planar spaces do not."""
    backend = jax.default_backend()   # "gpu" names no platform: JAX_PLATFORMS takes "cuda"
    env = dict(os.environ, JAX_PLATFORMS="cuda" if backend == "gpu" else backend)
    proc = subprocess.run([sys.executable, "-c", PRELOAD_CHECK], env=env, capture_output=True,
                          text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "MODULES 7" in proc.stdout and "MADE 0" not in proc.stdout, proc.stdout[-500:]


DETERMINISM_CHECK = """
import jax, numpy as np
import evojax_morph as em
from evojax_morph.physics import templates
from evojax_morph.physics import warp as ew
from mujoco_warp._src import collision_driver
assert templates.MUJOCO_WARP == "package", templates.MUJOCO_WARP
sorts, sort = [], collision_driver._sort_contacts
collision_driver._sort_contacts = lambda m, d: sorts.append(1) or sort(m, d)
space = em.make_space("bad_walker")
keys = jax.random.split(jax.random.PRNGKey(0), 2)
models = jax.vmap(space.mjx_model)(jax.vmap(space.random_morphology, (0, None))(keys, 3))
ctrl = jax.random.uniform(jax.random.PRNGKey(1), (5, 4, space.template.nu), minval=-1, maxval=1)
qpos = {}
for on in (False, True):
    assert ew.set_deterministic(on) and ew.deterministic() == on
    model, data = ew.to_warp(space, models, 2)
    sorts.clear()
    step = lambda d, c, model=model: (d := ew.step_worlds(model, d, c), d.qpos)
    qpos[on] = np.asarray(jax.jit(lambda d, c, s=step: jax.lax.scan(s, d, c)[1])(data, ctrl))
    assert (len(sorts) > 0) == on, (on, len(sorts))
print("DIFF", np.abs(qpos[True] - qpos[False]).max())
"""


@requires_warp
def test_set_deterministic_reaches_mujoco_warp():
    """Under EVOJAX_MORPH_MUJOCO_WARP=package, `set_deterministic(True)` makes the mujoco-warp
    package behind MJX sort each world's contacts (its CONTACTS determinism), and off it does
    not; the worlds step alike either way (sorting reorders contacts, not their forces). In a
    subprocess: the package replaces the vendored copy only before MJX is first imported."""
    import warp

    if not warp.is_cpu_available():  # the subprocess runs on the CPU
        pytest.skip("warp-lang here cannot compile CPU kernels (no LLVM)")
    env = dict(os.environ, EVOJAX_MORPH_MUJOCO_WARP="package", JAX_PLATFORMS="cpu")
    proc = subprocess.run([sys.executable, "-c", DETERMINISM_CHECK], env=env,
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert float(proc.stdout.split("DIFF")[1]) < WARP_TOL
    if templates.MUJOCO_WARP == "vendored":  # the default: the option is refused, not ignored
        assert not ew.set_deterministic(True) and not ew.deterministic()


WARP_ON_FOUR = r"""
import json
import re
import jax
import numpy as np
import evojax_morph as em
from evojax_morph.sharding import batch_mesh

assert jax.device_count() == 4
space = em.make_space("bad_walker")
cfg = em.FitnessConfig(physics="warp", ppo=em.PPOConfig(
    train_steps=320, worlds_per_controller=8, num_minibatches=2, update_epochs=2, eval_episodes=1))
keys = jax.random.split(jax.random.PRNGKey(0), 6)  # 6 bodies on 4 devices: padded to 8
morphs = jax.vmap(space.random_morphology, (0, None))(keys, 3)
four = em.evaluate(space, morphs, keys, cfg)
one = em.evaluate(space, morphs, keys, cfg, mesh=batch_mesh(jax.devices()[:1]))
devices = {d.id for d in four.params.policy["params"]["hidden_0"]["kernel"].sharding.device_set}
# the leading axes of what Warp's calls return in the 4-device program: the worlds they step
from evojax_morph.fitnesses.batched import lower_evaluate
text = lower_evaluate(space, 6, cfg)[-1].as_text()
calls = [line.split("->")[-1] for line in text.splitlines() if "custom_call @jax_callable" in line]
worlds = sorted({int(n) for call in calls for n in re.findall(r"tensor<(\d+)x", call)})
# the agents' loop around it (m0, one Double-DQN step): GSPMD failed to compile it under jax
# 0.10, jax 0.11 hung it on 2 GPUs; it has to compile and run, not only `evaluate`
from evojax_morph.agents import dqn
from evojax_morph.search.pipeline import RunConfig, build
run = RunConfig(space="bad_walker", agent="ddqn", num_envs=4, horizon=2, train_steps=320,
                physics="warp")
init, chunk, _ = build(run, batch_mesh(), dqn.DQNConfig(learning_starts=0)).agent
_, metrics = chunk(jax.jit(init)(jax.random.PRNGKey(0)), 1)
print("RESULT", json.dumps({"four": np.asarray(four.fitness).tolist(),
                            "one": np.asarray(one.fitness).tolist(), "devices": len(devices),
                            "step": np.asarray(metrics["fitness"]).tolist(), "worlds": worlds}))
"""


@requires_warp
@pytest.mark.slow  # a Python of 4 devices compiling Warp's CPU kernels and two PPO programs
def test_warp_on_four_devices_gives_one_devices_fitness():
    """The Warp fitness split over 4 devices (`shard_map`, each device stepping its own worlds)
    gives one device's: float32, and the programs differ in batch (2 bodies a device against 6
    on one), so to rounding that 320 PPO steps amplify. Measured: 3e-7 relative on 2 CPU
    devices (2026-11-25), 1.4e-3 on 4 devices of CI's AMD EPYC (2026-11-28, the same package
    versions); the tolerance is 1e-2, below the gap between the two nearest bodies (-0.71 and
    -0.67: 5%), so a body given another's fitness still fails. And a step of the agents' loop
    around it compiles and runs."""
    import warp
    from conftest import on_four_devices

    if not warp.is_cpu_available():
        pytest.skip("warp-lang here cannot compile CPU kernels (no LLVM)")
    got = json.loads(on_four_devices(WARP_ON_FOUR).stdout.split("RESULT ")[1])
    assert got["devices"] == 4
    # each device's Warp calls step its own 2 bodies x 8 envs, not the padded batch's 8 x 8
    # (unsplit on jax 0.11 and 0.12 before 2026-11-28)
    assert 16 in got["worlds"] and 64 not in got["worlds"], got["worlds"]
    assert np.shape(got["step"]) == (1, 4)  # one step's fitness of each of the 4 evolutions
    assert np.isfinite(got["step"]).all()
    np.testing.assert_allclose(got["four"], got["one"], rtol=1e-2, atol=1e-3)
    one = np.asarray(got["one"])
    gaps = np.abs(one[:, None] - one[None, :]) + np.diag(np.full(6, np.inf))
    assert (gaps > 2 * (1e-3 + 1e-2 * np.abs(one))).all()  # the bodies lie further apart than
    # the tolerance, so a body given another's fitness fails
