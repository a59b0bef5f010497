"""The TAME fitness of a body: random-primitive rollouts, scored by a classifier.

F(m) = sum_j (log K + E[log q(a_j | s_T, m)]) + coverage x 1/2 log det(I + Cov[dx, dz] / sigma^2);
the package docstring (`evojax_morph.tame`) derives it. Every function here is pure and vmaps
over bodies.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from evojax_morph import tasks
from evojax_morph.morphology import Morphology
from evojax_morph.spaces import Space
from evojax_morph.tame.classifier import STATE_SIZE, Classifier, log_likelihood
from evojax_morph.tasks import Locomotion, TaskConfig

# On the CPU backend (jaxlib 0.10.2, 2 cores) a vmapped MJX rollout of 2,784 or more worlds in one
# call never returns (2,752 runs); batches of bodies are split so that a call holds fewer.
CPU_MAX_WORLDS = 2048


@dataclasses.dataclass(frozen=True)
class TameConfig:
    """Rollouts, classifier and fitness settings (TAME's defaults where it had them)."""

    episodes: int = 32  # rollouts per body (TAME: 32)
    episode_length: int = 100  # control steps of 20 ms: 2 s
    period: int = 50  # control steps per cycle of the slowest primitive (1 s)
    num_freqs: int = 2
    num_phases: int = 2
    state_noise: float = 0.05  # sigma: added to final states while training; coverage's unit
    coverage: float = 1.0  # weight of the coverage term in F(m)
    hidden: int = 64  # classifier width
    layers: int = 3  # classifier graph convolutions

    @property
    def num_primitives(self) -> int:
        return self.num_freqs * self.num_phases


@struct.dataclass
class Rollouts:
    """`episodes` random-primitive rollouts of one body (a leading batch axis when stacked)."""

    states: jax.Array  # (E, N, STATE_SIZE) final state per node
    labels: jax.Array  # (E, N) int32: the primitive that drove each node's motor
    labelled: jax.Array  # (N,) bool: the node has an active motor
    diverged: jax.Array  # (E,) bool: the simulation blew up (its final state is zeroed)


def make_classifier(space: Space, cfg: TameConfig) -> Classifier:
    return Classifier(len(space.kind_names), len(space.site_names), cfg.num_primitives, cfg.hidden,
                      cfg.layers)


def init_classifier(space: Space, cfg: TameConfig, key: jax.Array):
    """Fresh parameters of the space's classifier."""
    m = space.initial()
    return make_classifier(space, cfg).init(key, m, jnp.zeros((space.max_nodes, STATE_SIZE)))


def fitness_terms(cfg: TameConfig, loglik: jax.Array, r: Rollouts) -> tuple[jax.Array, jax.Array]:
    """The two terms of F(m) (the module docstring) from the (E,) log-likelihoods of one body's
    rollouts: control = sum_j (log K + E[log q]) and coverage = 1/2 log det(I + Cov / sigma^2)."""
    control = r.labelled.sum() * math.log(cfg.num_primitives) + loglik.mean()
    moved = r.states[:, 0, :2] - r.states[:, 0, :2].mean(0)  # trunk displacement, centred
    cov = moved.T @ moved / r.states.shape[0]
    return control, 0.5 * jnp.linalg.slogdet(jnp.eye(2) + cov / cfg.state_noise**2)[1]


def fitness_from(cfg: TameConfig, loglik: jax.Array, r: Rollouts) -> jax.Array:
    """F(m) = control + cfg.coverage x coverage."""
    control, coverage = fitness_terms(cfg, loglik, r)
    return control + cfg.coverage * coverage


def refused(space: Space) -> str | None:
    """Why TAME cannot run on `space`, or None: it labels a body's motors by the morphology's
    nodes, so each limb of the space's template must be one node."""
    if max(space.plan.limb_nodes, default=0) >= space.max_nodes:
        return (f"TAME labels a body's motors by its nodes, and the {space.name} space's limbs "
                f"are not its nodes (its template has {len(space.plan.limb_nodes)} limbs, a "
                f"body at most {space.max_nodes} nodes)")
    return None


class Tame:
    """Rollouts and the fitness of one space; every method is pure and vmaps over bodies."""

    def __init__(self, space: Space, cfg: TameConfig = TameConfig()):
        if refused(space):
            raise ValueError(refused(space))
        self.space, self.cfg = space, cfg
        self.task = Locomotion(space, TaskConfig(episode_length=cfg.episode_length))
        self.classifier = make_classifier(space, cfg)
        t, plan = space.template, space.plan
        node_body = np.full(space.max_nodes, t.body(plan.body_names[0]).id)
        node_body[list(plan.limb_nodes)] = [t.body(name).id for name in plan.body_names[1:]]
        self._node_body = node_body
        self._motor_node = np.asarray(plan.limb_nodes)
        freqs = 2 * np.pi / cfg.period * np.arange(1, cfg.num_freqs + 1)
        phases = 2 * np.pi / cfg.num_phases * np.arange(cfg.num_phases)
        self._freq, self._phase = (
            jnp.asarray(a, jnp.float32).reshape(-1)
            for a in np.meshgrid(freqs, phases, indexing="ij")
        )

    def _node_states(self, data) -> jax.Array:
        xmat = data.xmat[self._node_body]
        pos = data.xpos[self._node_body][:, [0, 2]]
        return jnp.concatenate([pos, xmat[:, 0, 0:1], xmat[:, 0, 2:3]], -1)  # rotation about y

    def rollout(self, key: jax.Array, m: Morphology) -> Rollouts:
        """`episodes` rollouts of `m`, one random primitive per motor in each."""
        cfg, task, space = self.cfg, self.task, self.space
        model = space.mjx_model(m)

        def episode(key):
            k_reset, k_label = jax.random.split(key)
            motor_labels = jax.random.randint(k_label, (task.action_size,), 0, cfg.num_primitives)
            freq, phase = self._freq[motor_labels], self._phase[motor_labels]
            start = task.reset(k_reset, model)
            end, diverged, _ = tasks.rollout(
                lambda state, action: task.step(model, state, action),
                lambda _, t: jnp.cos(freq * t + phase),
                start,
                cfg.episode_length,
                lambda diverged, state: (diverged | state.diverged, None),
                start.diverged,
            )
            first, last = self._node_states(start.data), self._node_states(end.data)
            states = jnp.concatenate([last[:, :2] - first[:, :2], last[:, 2:]], -1)
            states = jnp.where(diverged | ~jnp.isfinite(states), 0.0, states)
            labels = jnp.zeros(space.max_nodes, jnp.int32).at[self._motor_node].set(motor_labels)
            return states, labels, diverged

        states, labels, diverged = jax.vmap(episode)(jax.random.split(key, cfg.episodes))
        motors = task.action_mask(model)
        labelled = jnp.zeros(space.max_nodes, bool).at[self._motor_node].set(motors) & m.active
        return Rollouts(states.astype(jnp.float32), labels, labelled, diverged)

    def fitness(self, params, key: jax.Array, m: Morphology) -> tuple[jax.Array, jax.Array]:
        """F(m) with the classifier `params` from fresh rollouts drawn with `key`; and diverged."""
        r = self.rollout(key, m)
        loglik, _ = log_likelihood(self.classifier, params, m, r)
        return fitness_from(self.cfg, loglik, r), r.diverged.any()


def over_bodies(fn, episodes: int):
    """`fn(key, m)` mapped over (B,) keys and bodies: one vmap, or on the CPU a `lax.map` over
    vmapped groups of at most CPU_MAX_WORLDS worlds (see there)."""
    if jax.default_backend() != "cpu":
        return jax.vmap(fn)
    group = max(1, CPU_MAX_WORLDS // episodes)
    return lambda keys, morphs: jax.lax.map(lambda a: fn(*a), (keys, morphs), batch_size=group)
