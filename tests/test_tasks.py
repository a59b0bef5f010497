"""Tasks by name, what each pays for, and the gait numbers a task measures."""


import jax
import jax.numpy as jnp
import numpy as np
import pytest

import evojax_morph as em
from evojax_morph.physics.templates import mjx


def test_tasks_are_registered_by_name():
    assert em.list_tasks() == ["distance", "walk"]
    assert em.make_task("distance") == em.TaskConfig()  # the source's: all tables and figures
    walk = em.make_task("walk", episode_length=50)
    assert walk.name == "walk" and walk.episode_length == 50 and walk.healthy_reward > 0
    assert em.FitnessConfig.from_dict(em.FitnessConfig(task=walk).to_dict()).task == walk
    with pytest.raises(ValueError, match="unknown task 'run'; known tasks: distance, walk"):
        em.make_task("run")
    with pytest.raises(ValueError, match=r"unknown task settings \['speed'\]"):
        em.make_task("walk", speed=1.0)


SPACE = em.make_space("bad_walker")
MODEL = jax.jit(SPACE.mjx_model)(SPACE.optimum())  # m*
BODY = em.Locomotion(SPACE).body(MODEL)  # its motors and height


def episode_return(task: em.TaskConfig, xs: np.ndarray, fall_at: int | None = None) -> float:
    """The return of an episode whose trunk is at x = xs[t] after control step t (upright,
    still controls), falling (pitched past max_tilt) at step `fall_at`, as the task scores it
    step by step (`Locomotion._outcome`, on positions and velocities)."""
    env = em.Locomotion(SPACE, task)
    body = jax.tree.map(jnp.asarray, BODY)
    qpos = jnp.zeros(SPACE.template.nq)
    x, _, pitch = env._root_qpos
    t = np.arange(task.episode_length)
    after = jnp.zeros((len(t), len(qpos))).at[:, x].set(xs)
    after = after.at[:, pitch].set(jnp.where(t == fall_at, 2 * task.max_tilt, 0.0))
    before = jnp.concatenate([qpos[None], after[:-1]])
    outcome = jax.jit(jax.vmap(env._outcome, (None, 0, 0, None, 0, None)))
    out = outcome(body, before, jnp.asarray(t, jnp.int32), jnp.zeros(env.action_size), after,
                  jnp.zeros(SPACE.template.nv))
    ends = np.flatnonzero(np.asarray(out.done))  # the step that fell or reached the length
    return float(np.asarray(out.reward)[: ends[0] + 1].sum())


def test_walking_pays_more_than_falling_forward_or_standing_still():
    """On the walking task 2 m in 5 s upright pays most, then standing still, then a lunge of
    1 m that falls after 1 s; on the source's task a lunge of 2.5 m beats walking 2 m, and
    standing still pays nothing (the reason the walking task exists)."""
    steps = 250
    walk2m = np.linspace(2 / steps, 2, steps)
    stand = np.zeros(steps)
    lunge = lambda m: np.minimum(np.linspace(m / 50, m * steps / 50, steps), m)  # noqa: E731
    walk, distance = em.make_task("walk"), em.make_task("distance")
    walked, stood = episode_return(walk, walk2m), episode_return(walk, stand)
    lunged = episode_return(walk, lunge(1.0), fall_at=49)
    assert walked > stood > lunged, (walked, stood, lunged)
    np.testing.assert_allclose([walked, stood, lunged], [225, 125, 75], rtol=1e-4)
    assert episode_return(distance, lunge(2.5), fall_at=49) > episode_return(distance, walk2m)
    assert episode_return(distance, stand) == 0.0


def test_a_body_pushed_forward_moves_the_distance_it_should():
    """m* lifted off the floor with gravity off and pushed forward at 1.5 m/s (its trunk's
    forward velocity set by hand, every other velocity 0, controls 0): nothing acts on it, so
    after 10 control steps of 20 ms its trunk has moved 0.3 m, each step's `forward` is 0.03 m
    and each step of the walking task pays 1.5 m/s + the healthy reward; it stays upright."""
    model = MODEL.replace(opt=MODEL.opt.replace(gravity=jnp.zeros(3)))
    task = em.make_task("walk")
    env = em.Locomotion(SPACE, task)
    x, z, _ = env._root_qpos
    data = mjx.make_data(model)
    qpos = data.qpos.at[z].add(1.0)  # lifted 1 m: no contact
    qvel = jnp.zeros_like(data.qvel).at[env._root_dof[0]].set(1.5)
    state = env._first(BODY, qpos, qvel).replace(data=data.replace(qpos=qpos, qvel=qvel))
    step = jax.jit(env.step)
    forward = []
    for _ in range(10):
        state = step(model, state, jnp.zeros(env.action_size))
        forward.append(float(state.forward))
        assert not state.done
        np.testing.assert_allclose(state.reward, 1.5 + task.healthy_reward, rtol=1e-4)
    np.testing.assert_allclose(forward, 0.03, rtol=1e-4)
    np.testing.assert_allclose(state.data.qpos[x] - qpos[x], 0.3, rtol=1e-4)
