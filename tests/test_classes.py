"""Size classes: each class's template holds its bodies as the full template does, and the
fitness grouped by class is the single template's."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

import evojax_morph as em
from evojax_morph.fitnesses import FitnessConfig, standard_ppo
from evojax_morph.physics import classes
from evojax_morph.tasks import make_task

# Bodies of 8 mutations of the default Constructor: 25% fit its smallest class (docs: SHARES).
NUM_BODIES, STEPS = 16, 100


@pytest.fixture(scope="module")
def constructor_bodies():
    space = em.make_space("constructor")
    keys = jax.random.split(jax.random.PRNGKey(0), NUM_BODIES)
    morphs = jax.jit(jax.vmap(space.random_morphology, (0, None)), static_argnums=1)(keys, 8)
    return space, em.unstack(morphs), morphs


def c_qpos(xml: str, ctrl_by_name: dict, steps: int) -> dict:
    """MuJoCo C: joint name -> (steps,) its qpos, each actuator driven by its named control."""
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    names = [model.joint(j).name for j in range(model.njnt)]
    out = {n: np.zeros(steps) for n in names}
    for t in range(steps):
        for a in range(model.nu):
            data.ctrl[a] = ctrl_by_name[model.actuator(a).name][t]
        mujoco.mj_step(model, data)
        for j, n in enumerate(names):
            out[n][t] = data.qpos[model.jnt_qposadr[j]]
    return out


def test_a_class_holds_its_bodies_on_the_full_templates_limbs(constructor_bodies):
    """A body that fits a class exports (unpadded) to the same MuJoCo C body from the class's
    template and from the full one, the class's limb slot j being the full one's `limbs[j]`:
    the same controls by that map give the same motion, to float64 rounding. Bodies the class
    cannot hold do not fit, and the classes split the sample."""
    space, bodies, morphs = constructor_bodies
    full_names = space.plan.actuator_names
    rng = np.random.default_rng(0)
    counts = []
    for size_class, _ in space.size_classes():
        fits = np.asarray(jax.vmap(size_class.fits)(morphs))
        counts.append(int(fits.sum()))
        small = size_class.space
        small_names = small.plan.actuator_names
        for m in [b for b, ok in zip(bodies, fits) if ok]:
            ctrl = rng.uniform(-1, 1, (len(full_names), STEPS))
            by_full = dict(zip(full_names, ctrl))
            by_small = {small_names[j]: ctrl[size_class.limbs[j]] for j in range(len(small_names))}
            got = c_qpos(small.to_mjcf(m), by_small, STEPS)
            want = c_qpos(space.to_mjcf(m), by_full, STEPS)
            small_joints = small.plan.joint_names
            rename = {small_joints[j]: space.plan.joint_names[size_class.limbs[j]]
                      for j in range(len(small_joints))}
            assert {rename.get(n, n) for n in got} == set(want)
            for n, q in got.items():
                np.testing.assert_allclose(q, want[rename.get(n, n)], atol=1e-9)
            assert np.abs(want["rootx"]).max() > 0.01 or np.abs(want["rootz"]).max() > 0.01
        # a walk inside the class's own space always fits it
        inside = jax.vmap(small.random_morphology, (0, None))(
            jax.random.split(jax.random.PRNGKey(1), 8), 8)
        assert bool(jax.vmap(size_class.fits)(inside).all())
    assert 0 < counts[0] < counts[1] <= NUM_BODIES, counts


def test_assign_places_each_body_in_the_smallest_class_with_room():
    need = jnp.array([0, 0, 0, 1, 2, 1, 0])
    places, ok = classes.assign(need, [2, 3, 2])
    assert bool(ok)
    assert [np.asarray(p).tolist() for p in places] == [[0, 1], [2, 3, 5], [4, 6]]
    _, ok = classes.assign(jnp.array([2, 2, 2, 0]), [2, 3, 2])
    assert not bool(ok)  # three bodies need the full template, which has two places


@pytest.mark.slow
@pytest.mark.parametrize("name", ["constructor", "crawler"])
def test_fitness_by_class_is_the_single_templates(name):
    """Given controllers (no training), the fitness grouped by class equals the one template's
    body by body, to float32 rounding: the class's template steps the same body, and resets
    and observations keep the full layout. 8 bodies of a horizon-3 space, a mix that fits the
    capacities (some in the small class, the rest on larger templates)."""
    space = em.make_space(name, horizon=3)
    size_class = space.size_classes()[0][0]
    keys = jax.random.split(jax.random.PRNGKey(0), 8)
    morphs = jax.vmap(space.random_morphology, (0, None))(keys, 3)
    fits = np.asarray(jax.vmap(size_class.fits)(morphs))
    assert 0 < fits.sum() < 8
    assert bool(classes.places(space, morphs)[2])  # the classes train it, not the fallback
    params = em.init_params(space, jax.random.split(jax.random.PRNGKey(2), 8))
    fitness = {}
    for by_class in (False, True):
        cfg = FitnessConfig(task=make_task("walk"), ppo=standard_ppo(0), classes=by_class)
        fitness[by_class] = np.asarray(
            em.evaluate(space, morphs, jax.random.PRNGKey(1), cfg, init_params=params).fitness)
    np.testing.assert_allclose(fitness[True], fitness[False], rtol=1e-4, atol=1e-3)
    assert np.ptp(fitness[False]) > 1.0  # the bodies differ: not all standing still
