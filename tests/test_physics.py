"""The padded MJX template against MuJoCo C on the unpadded export: physics and constants."""

from typing import NamedTuple

import chex
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from conftest import float64

import evojax_morph as em
from evojax_morph.physics.templates import mjx
from evojax_morph.spaces import bad_walker as bw

# The documented equivalence: 50 bodies x 300 steps per space (slow: minutes of float64
# stepping on 2 cores); the default set checks a sample of the Constructor's, 12 bodies x 100
# steps (the slow set samples every space too).
NUM_MORPHS, STEPS = 50, 300
SAMPLE_MORPHS, SAMPLE_STEPS = 12, 100
# Documented tolerance of the equivalence in float64 (observed: below 2e-9 over 300 steps).
QPOS_ATOL = 1e-6
# Both engines run the Newton solver to convergence here. Their stopping rules differ (MJX
# scales the improvement by trace M(q), MuJoCo C by meaninertia x nv), so with the library's
# budget of 4 iterations they can stop after different counts at a step where the solve has
# not converged, and part by the solver's residual (~1e-5: once in 50 x 300 length_walker
# steps, a trunk grazing the floor). Converged, both give the same constraint forces.
SOLVER = {"iterations": 50, "ls_iterations": 50, "tolerance": 1e-10}
# The Crawler's elliptic cones converge slower: at SOLVER its 50 bodies x 300 steps part from
# MuJoCo C by up to 1.8e-5 (the two solvers stop apart), at this budget by 1.7e-7 (CPU).
SOLVER_ELLIPTIC = {"iterations": 200, "ls_iterations": 100, "tolerance": 1e-15}


def sample_morphologies(space, n, seed=0):
    """n random walks from m0 of assorted lengths, so bodies of every size appear."""
    horizon = space.default_horizon
    lengths = (1, max(2, horizon // 2), horizon)
    morphs = []
    for j, length in enumerate(lengths):
        keys = jax.random.split(jax.random.PRNGKey(seed + j), -(-n // len(lengths)))
        batch = jax.jit(jax.vmap(space.random_morphology, (0, None)), static_argnums=1)(keys, length)
        morphs += em.unstack(batch)
    return morphs[:n]


def qpos_addresses(model, names, dofs=False):
    """Every qpos (or dof) of the joints `names` (a free joint has 7 qpos and 6 dofs), in order."""
    free, ball = int(mujoco.mjtJoint.mjJNT_FREE), int(mujoco.mjtJoint.mjJNT_BALL)
    width = {free: 6, ball: 3} if dofs else {free: 7, ball: 4}
    address = model.jnt_dofadr if dofs else model.jnt_qposadr
    return np.array([address[model.joint(n).id] + k for n in names
                     for k in range(width.get(int(model.joint(n).type[0]), 1))])


def joint_names(ref):
    return [ref.joint(j).name for j in range(ref.njnt)]


@pytest.fixture(scope="module", params=[
    pytest.param("bad_walker", marks=pytest.mark.slow), "constructor",
    pytest.param("length_walker", marks=pytest.mark.slow)])
def space(request):
    """The planar spaces; the default set checks the Constructor's (every joint kind, the most
    bodies), the slow set all three (each sample's float64 compile is 30 to 80 s on 2 cores)."""
    return em.make_space(request.param)


def rollout(models, ctrls):
    """(B, T, nq) qpos and qvel of B specialised models driven by (B, T, nu) controls."""

    def one(model, ctrl):
        def body(data, c):
            data = mjx.step(model, data.replace(ctrl=c))
            return data, (data.qpos, data.qvel)

        return jax.lax.scan(body, mjx.make_data(model), ctrl)[1]

    return jax.vmap(one)(models, ctrls)


def converged(models, solver):
    """The models with the solver run to convergence (`solver`), as the MuJoCo C references."""
    return models.replace(opt=models.opt.replace(
        iterations=solver["iterations"], ls_iterations=solver["ls_iterations"],
        tolerance=jnp.full_like(models.opt.tolerance, solver["tolerance"])))


def specialise_and_step(space, morphs, ctrls, batches, solver):
    """In float64, `morphs` specialised and stepped by `ctrls` (B, T, nu) in `batches` equal
    calls of one jitted function, traced once however the bodies differ (the sample's three
    calls: walks of one length each). Returns the batched models and qpos, qvel (B, T, nq|nv)."""
    chex.clear_trace_counter()

    @jax.jit
    @chex.assert_max_traces(n=1)
    def run(morphs, ctrls):
        models = jax.vmap(space.mjx_model)(morphs)
        return models, rollout(converged(models, solver), ctrls)

    size, rest = divmod(len(morphs), batches)
    assert not rest, (len(morphs), batches)
    parts = [run(em.stack(morphs[b * size : (b + 1) * size]), ctrls[b * size : (b + 1) * size])
             for b in range(batches)]
    models, (qpos, qvel) = jax.device_get(jax.tree.map(lambda *x: jnp.concatenate(x), *parts))
    return models, qpos, qvel


def c_rollout(ref, ctrl):
    data = mujoco.MjData(ref)
    out = np.zeros((len(ctrl), ref.nq))
    for t, c in enumerate(ctrl):
        data.ctrl[:] = c
        mujoco.mj_step(ref, data)
        out[t] = data.qpos
    return out


class Stepped(NamedTuple):
    """Bodies specialised and stepped in float64 (`stepped`), and their MuJoCo C exports."""

    morphs: list  # B bodies of assorted sizes
    ctrls: np.ndarray  # (B, T, nu) random controls in [-1, 1]
    models: mjx.Model  # the B specialised models, batched, float64
    qpos: np.ndarray  # (B, T, nq) after each step, converged solver
    qvel: np.ndarray  # (B, T, nv)
    refs: list  # B unpadded MuJoCo C models (float64 MJCF export), solver as the MJX ones


def stepped(space, num_morphs, steps, batches=1, solver=SOLVER) -> Stepped:
    """`num_morphs` random bodies of `space` (`sample_morphologies`) driven by random controls
    for `steps` steps (`specialise_and_step`, the solver's budget `solver`), and their
    exports."""
    with float64():
        morphs = sample_morphologies(space, num_morphs)
        ctrls = np.random.default_rng(0).uniform(-1, 1, (num_morphs, steps, space.template.nu))
        models, qpos, qvel = specialise_and_step(space, morphs, jnp.asarray(ctrls), batches, solver)
        # Exported in float64 too: a float32 layout would move the body by ~1e-8 m.
        refs = [mujoco.MjModel.from_xml_string(space.to_mjcf(m)) for m in morphs]
    for ref in refs:
        ref.opt.iterations, ref.opt.ls_iterations = solver["iterations"], solver["ls_iterations"]
        ref.opt.tolerance = solver["tolerance"]
    return Stepped(morphs, ctrls, models, qpos, qvel, refs)


@pytest.fixture(scope="module")
def sample(space):
    """The default set's sample: SAMPLE_MORPHS bodies x SAMPLE_STEPS, in 3 calls of one trace
    (4 walks of one length each), which the tests below share."""
    return stepped(space, SAMPLE_MORPHS, SAMPLE_STEPS, batches=3)


@pytest.mark.parametrize(
    "num_morphs, steps",
    [
        pytest.param(SAMPLE_MORPHS, SAMPLE_STEPS, id="sample"),
        pytest.param(NUM_MORPHS, STEPS, id="full", marks=pytest.mark.slow),
    ],
)
def test_padded_template_steps_like_mujoco_c(space, num_morphs, steps, request):
    """Random controls matched by actuator name, float64: same root and joints. The sample
    (12 bodies of every size x 100 steps: contacts, falls and every joint kind) catches a wrong
    field or a padded slot that moves; the full 50 x 300 is the documented tolerance's test
    (and checks the derived constants of its 50 bodies too)."""
    if num_morphs == SAMPLE_MORPHS:
        run = request.getfixturevalue("sample")
    else:
        run = stepped(space, num_morphs, steps)
        check_derived_constants(space, run)
    assert_steps_like_c(space, run)


@pytest.mark.parametrize(
    "num_morphs, steps",
    [pytest.param(6, 60, id="sample"), pytest.param(NUM_MORPHS, STEPS, id="full", marks=pytest.mark.slow)],
)
def test_crawler_steps_like_mujoco_c(num_morphs, steps):
    """The 3D space (a free trunk, hinges about any axis, capsules in any direction, elliptic
    cones): same root, joints and derived constants as MuJoCo C on the unpadded exports."""
    space = em.make_space("crawler")
    run = stepped(space, num_morphs, steps, solver=SOLVER_ELLIPTIC)
    check_derived_constants(space, run)
    assert_steps_like_c(space, run)


@pytest.mark.slow
@pytest.mark.parametrize("name, which", [("constructor", 0), ("constructor", 1), ("crawler", 0)],
                         ids=["small", "middle", "crawler_small"])
def test_size_class_templates_step_like_mujoco_c(name, which):
    """The size classes (`Space.size_classes`): each class's padded template, specialised to
    bodies of the class, steps as MuJoCo C does on their unpadded exports (slow: a float64
    compile each, 40 s on 2 cores; the default set checks the classes' exports against the full
    template's in tests/test_classes.py and tests/test_crawler.py)."""
    size_class = em.make_space(name).size_classes()[which][0]
    solver = SOLVER_ELLIPTIC if name == "crawler" else SOLVER
    assert_steps_like_c(size_class.space, stepped(size_class.space, 6, 50, 3, solver))


def assert_steps_like_c(space, run: "Stepped") -> None:
    tmpl = space.template
    worst = 0.0
    for i, ref in enumerate(run.refs):
        names = joint_names(ref)
        acts = [tmpl.actuator(ref.actuator(a).name).id for a in range(ref.nu)]
        expected = c_rollout(ref, run.ctrls[i][:, acts])
        got = run.qpos[i][:, qpos_addresses(tmpl, names)]
        worst = max(worst, np.abs(got - expected[:, qpos_addresses(ref, names)]).max())

        # Padded joints stay exactly at rest.
        padded = np.setdiff1d(np.arange(tmpl.nq), qpos_addresses(tmpl, names))
        padded_dofs = np.setdiff1d(np.arange(tmpl.nv), qpos_addresses(tmpl, names, dofs=True))
        assert np.all(run.qpos[i][:, padded] == 0) and np.all(run.qvel[i][:, padded_dofs] == 0)
    assert worst < QPOS_ATOL, worst
    # The bodies really moved: the test is not comparing two resting models.
    assert np.abs(run.qpos[:, -1] - run.qpos[:, 0]).max() > 0.1


def inertia_tensor(quat, principal):
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, quat)
    rot = rot.reshape(3, 3)
    return rot @ np.diag(principal) @ rot.T


def test_derived_constants_match_the_compiler(space, sample):
    """Masses, inertias, invweight0, acc0 and meaninertia as MuJoCo computes them unpadded, on
    the sample's bodies (the slow set's full test checks its 50 too)."""
    check_derived_constants(space, sample)


def check_derived_constants(space, run: Stepped):
    models, refs = run.models, run.refs
    tmpl = space.template
    for i, ref in enumerate(refs):
        got = jax.tree.map(lambda x: x[i], models)
        for b in range(1, ref.nbody):
            t = tmpl.body(ref.body(b).name).id
            np.testing.assert_allclose(got.body_mass[t], ref.body_mass[b], rtol=1e-10)
            np.testing.assert_allclose(got.body_subtreemass[t], ref.body_subtreemass[b], rtol=1e-10)
            np.testing.assert_allclose(got.body_pos[t], ref.body_pos[b], atol=1e-12)
            np.testing.assert_allclose(got.body_ipos[t], ref.body_ipos[b], atol=1e-10)
            np.testing.assert_allclose(
                inertia_tensor(got.body_iquat[t], got.body_inertia[t]),
                inertia_tensor(ref.body_iquat[b], ref.body_inertia[b]),
                atol=1e-10,
            )
            np.testing.assert_allclose(got.body_invweight0[t], ref.body_invweight0[b], rtol=1e-8)
        names = joint_names(ref)
        np.testing.assert_allclose(got.qpos0[qpos_addresses(tmpl, names)],
                                   ref.qpos0[qpos_addresses(ref, names)], atol=1e-12)
        for j in range(ref.njnt):
            t_jnt = tmpl.joint(ref.joint(j).name).id
            np.testing.assert_allclose(got.jnt_axis[t_jnt], ref.jnt_axis[j], atol=1e-12)
        t_dofs, r_dofs = qpos_addresses(tmpl, names, dofs=True), qpos_addresses(ref, names, dofs=True)
        np.testing.assert_allclose(got.dof_invweight0[t_dofs], ref.dof_invweight0[r_dofs], rtol=1e-8)
        np.testing.assert_allclose(got.dof_M0[t_dofs], ref.dof_M0[r_dofs], rtol=1e-8)
        for a in range(ref.nu):
            t = tmpl.actuator(ref.actuator(a).name).id
            np.testing.assert_allclose(got.actuator_acc0[t], ref.actuator_acc0[a], rtol=1e-8)
            np.testing.assert_allclose(got.actuator_gear[t], ref.actuator_gear[a])
        np.testing.assert_allclose(got.stat.meaninertia, ref.stat.meaninertia, rtol=1e-8)
        for g in range(1, ref.ngeom):  # skip the floor
            t = tmpl.geom(ref.geom(g).name).id
            np.testing.assert_allclose(got.geom_size[t, :2], ref.geom_size[g, :2], atol=1e-12)
            np.testing.assert_allclose(got.geom_pos[t], ref.geom_pos[g], atol=1e-12)
            axis_got, axis_ref = np.zeros(9), np.zeros(9)
            mujoco.mju_quat2Mat(axis_got, got.geom_quat[t])
            mujoco.mju_quat2Mat(axis_ref, ref.geom_quat[g])
            # A capsule is symmetric about its axis: compare the axis, up to direction.
            assert abs(abs(axis_got[2::3] @ axis_ref[2::3]) - 1) < 1e-10


def test_inactive_geoms_never_touch():
    """A removed foot buried in the floor makes no contact force: qacc equals the export's."""
    space = em.make_space("bad_walker")
    m = space.mutate(space.initial(), bw.LONG, bw.REMOVE)
    with float64():
        model = jax.jit(space.mjx_model)(m)
        ref = mujoco.MjModel.from_xml_string(space.to_mjcf(m))
        rootz = space.template.jnt_qposadr[space.template.joint("rootz").id]
        sink = -float(model.body_pos[1, 2]) - 0.03  # trunk 3 cm into the floor

        @jax.jit
        def forward(model, sink):
            data = mjx.make_data(model)
            return mjx.forward(model, data.replace(qpos=data.qpos.at[rootz].set(sink)))

        data = jax.device_get(forward(model, sink))
    contact = data._impl.contact
    geom1 = space.template.geom("geom1").id
    touching = (contact.geom1 == geom1) | (contact.geom2 == geom1)
    assert touching.any() and np.all(contact.dist[touching] < 0)  # the removed foot is in the floor
    assert np.all((contact.dist - contact.includemargin)[touching] > 0)  # but never active

    ref_data = mujoco.MjData(ref)
    ref_data.qpos[ref.jnt_qposadr[ref.joint("rootz").id]] = sink
    mujoco.mj_forward(ref, ref_data)
    assert ref_data.ncon > 0
    names = joint_names(ref)
    got = data.qacc[[space.template.jnt_dofadr[space.template.joint(n).id] for n in names]]
    np.testing.assert_allclose(got, ref_data.qacc[[ref.jnt_dofadr[ref.joint(n).id] for n in names]], atol=1e-8)


def test_to_mjcf_rejects_batches():
    space = em.make_space("bad_walker")
    with pytest.raises(ValueError, match="one morphology"):
        space.to_mjcf(em.stack([space.initial(), space.initial()]))
