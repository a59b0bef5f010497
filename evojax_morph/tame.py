"""TAME: a task-agnostic fitness from random action primitives (Hejna, Abbeel and Pinto, 2021).

A body is fit when it can *cause* many different outcomes: drive each motor with one of K
random periodic primitives, let the body move, and see whether a classifier can tell from the
final state which primitive drove each motor. With A the primitives (one per motor) and S_T the
final state, TAME ranks bodies by the mutual information I(A; S_T | m), bounded below through a
classifier q(a | s_T, m) (Barber and Agakov):

    I(A; S_T | m) >= H(A) + E[log q(A | s_T, m)] = sum_j (log K + E[log q(a_j | s_T, m)])

for a classifier that factorises over the J motors. We add TAME's state-coverage term, the
entropy of where the body ends up, as a Gaussian estimate over the trunk's final displacement
measured against the state noise sigma (0 for a body that stays put):

    F(m) = sum_j (log K + E[log q(a_j | s_T, m)]) + coverage * 1/2 log det(I + Cov[dx, dz] / sigma^2)

The reference implementation (github.com/jhejna/morphology-opt) averages the log-likelihood over
motors and multiplies by (log J)^0.25, and gets coverage only implicitly, from noise added to
the final states while training; the sum is the bound itself and needs no such regulariser.

Primitives (TAME's cosine policy): motor j gets u_j(t) = cos(2 pi f t / period + phi), with f in
{1, 2, ...} (`num_freqs`) and phi in {0, 2 pi / num_phases, ...}: K = num_freqs x num_phases.
An episode is `episode_length` control steps of the locomotion task's physics (50 Hz, reset
noise on), with no reward and no termination. The final state of a node is its body's
displacement (dx, dz) since reset and its orientation (cos, sin of the pitch); a welded limb
(a Constructor edge) reads its slot's body, which rides on the trunk.

The classifier is a `gnn.TreeGNN` over the morphology tree (so it can score bodies it never
saw), fed each node's morphology features and final state, with one logit per primitive and
node. It is trained by TAME's own loop (`pretrain`): a population grows a genealogy of bodies,
each body's rollouts go into a buffer, the classifier trains on the buffer each generation,
and the fittest bodies are mutated. The source scored the classifier only on bodies it had
trained on; `pretrain` keeps a set of held-out bodies out of the genealogy and reports the
classifier's accuracy and log-likelihood on them every generation.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
from pathlib import Path

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct
from tqdm.auto import tqdm

from evojax_morph.gnn import TreeGNN, node_features
from evojax_morph.locomotion import Locomotion, TaskConfig
from evojax_morph.morphology import Morphology, stack
from evojax_morph.spaces import Space, make_space

STATE_SIZE = 4  # per node: dx, dz, cos(pitch), sin(pitch)
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


class Classifier(nn.Module):
    """q(a | s_T, m): per-node logits over the primitives, from the tree and its final state."""

    num_kinds: int
    num_sites: int
    num_primitives: int
    hidden: int = 64
    layers: int = 3

    @nn.compact
    def __call__(self, m: Morphology, states: jax.Array) -> jax.Array:
        feats = node_features(m, jnp.zeros(()), self.num_kinds, self.num_sites)
        nodes = jnp.concatenate([feats, states * m.active[:, None]], -1)
        gnn = TreeGNN(self.hidden, self.layers, self.num_primitives, head=(self.hidden,))
        return gnn(m, nodes)[0]


def make_classifier(space: Space, cfg: TameConfig) -> Classifier:
    return Classifier(len(space.kind_names), len(space.site_names), cfg.num_primitives, cfg.hidden, cfg.layers)


def node_log_likelihood(classifier: Classifier, params, m: Morphology, states, labels, labelled):
    """log q(a_j | s_T, m) summed over the labelled nodes of one rollout, and the count right."""
    logits = classifier.apply(params, m, states)  # (N, K)
    logp = jnp.take_along_axis(jax.nn.log_softmax(logits), labels[:, None], -1)[:, 0]
    right = jnp.argmax(logits, -1) == labels
    return jnp.sum(logp * labelled), jnp.sum(right * labelled)


def log_likelihood(classifier: Classifier, params, m: Morphology, r: Rollouts):
    """(E,) sum over labelled nodes of log q(a_j | s_T, m), and (E,) fraction of them right."""
    loglik, right = jax.vmap(lambda s, a: node_log_likelihood(classifier, params, m, s, a, r.labelled))(
        r.states, r.labels
    )
    return loglik, right / jnp.maximum(r.labelled.sum(), 1)


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


class Tame:
    """Rollouts and the fitness of one space; every method is pure and vmaps over bodies."""

    def __init__(self, space: Space, cfg: TameConfig = TameConfig()):
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
        self._freq, self._phase = (jnp.asarray(a, jnp.float32).reshape(-1) for a in np.meshgrid(freqs, phases, indexing="ij"))

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

            def step(state, t):
                return task.step(model, state, jnp.cos(freq * t + phase)), state.diverged

            end, diverged = jax.lax.scan(step, start, jnp.arange(cfg.episode_length, dtype=jnp.float32))
            diverged = diverged.any() | end.diverged
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


# --- pre-training: TAME's evolutionary loop on a growing genealogy ----------------------------


@dataclasses.dataclass
class Pretrained:
    """A trained classifier with how it was trained and what it was never trained on."""

    space: str
    config: TameConfig
    params: dict
    history: list[dict]  # one row per generation: train and held-out log-likelihood and accuracy
    train_bodies: list[str]  # canonical names of every body in the training genealogy
    held_out_bodies: list[str]  # canonical names of the bodies kept out of it

    def save(self, path) -> Path:
        """An Orbax checkpoint of the parameters in `path`/params, the rest in `path`/tame.json."""
        import orbax.checkpoint as ocp

        path = Path(path).resolve()
        path.mkdir(parents=True, exist_ok=True)
        with ocp.StandardCheckpointer() as ckpt:
            ckpt.save(path / "params", self.params, force=True)
        meta = {"space": self.space, "config": dataclasses.asdict(self.config), "history": self.history,
                "train_bodies": self.train_bodies, "held_out_bodies": self.held_out_bodies}
        (path / "tame.json").write_text(json.dumps(meta, indent=1))
        return path

    @classmethod
    def load(cls, path) -> Pretrained:
        import orbax.checkpoint as ocp

        path = Path(path).resolve()
        if not (path / "tame.json").exists():
            raise FileNotFoundError(
                f"no TAME classifier in {str(path)!r} (no tame.json); train one with "
                "`python -m evojax_morph.tame --space SPACE --out DIR`"
            )
        meta = json.loads((path / "tame.json").read_text())
        space, cfg = make_space(meta["space"]), TameConfig(**meta["config"])
        abstract = jax.eval_shape(functools.partial(_init_params, space, cfg), jax.random.PRNGKey(0))
        with ocp.StandardCheckpointer() as ckpt:
            params = ckpt.restore(path / "params", abstract)
        return cls(meta["space"], cfg, params, meta["history"], meta["train_bodies"], meta["held_out_bodies"])


def _init_params(space: Space, cfg: TameConfig, key: jax.Array):
    m = space.initial()
    return make_classifier(space, cfg).init(key, m, jnp.zeros((space.max_nodes, STATE_SIZE)))


def pick_held_out(num_bodies: int, fraction: float, seed: int) -> list[int]:
    """Sorted indices of round(fraction x (num_bodies - 1)) bodies drawn at random from 1 ..
    num_bodies - 1 of an `enumerate_bodies` list (index 0 is m0, which starts every genealogy)."""
    pick = np.random.default_rng(seed).permutation(num_bodies - 1)[: round(fraction * (num_bodies - 1))]
    return sorted(int(i) + 1 for i in pick)


def over_bodies(fn, episodes: int):
    """`fn(key, m)` mapped over (B,) keys and bodies: one vmap, or on the CPU a `lax.map` over
    vmapped groups of at most CPU_MAX_WORLDS worlds (see there)."""
    if jax.default_backend() != "cpu":
        return jax.vmap(fn)
    group = max(1, CPU_MAX_WORLDS // episodes)
    return lambda keys, morphs: jax.lax.map(lambda a: fn(*a), (keys, morphs), batch_size=group)


@functools.lru_cache(maxsize=4)
def load_fitness(path: str):
    """(space name, TameConfig, fitness(keys (B,), morphs (B, ...)) -> (fitness (B,), diverged
    (B,))) of a saved classifier, vmapped over bodies; cached per path."""
    pre = Pretrained.load(path)
    tame = Tame(make_space(pre.space), pre.config)
    params = pre.params
    return pre.space, pre.config, over_bodies(lambda key, m: tame.fitness(params, key, m), pre.config.episodes)


def pretrain(
    space: Space,
    key: jax.Array,
    cfg: TameConfig = TameConfig(),
    population: int = 16,
    generations: int = 20,
    held_out: list[Morphology] = (),
    epochs: int = 10,
    batch_size: int = 128,
    learning_rate: float = 1e-3,
    walk_length: int = 4,
    progress: bool = True,
) -> Pretrained:
    """TAME's loop: 2 x `population` random bodies (walks of 0..`walk_length` mutations from
    m0), then per generation: train the classifier on every rollout so far (`epochs` passes),
    score every body of the genealogy by F on its own rollouts (as TAME does), mutate the
    `population` fittest once each and roll the children out.

    `held_out` bodies (and any body of the same shape, `landscape.canonical`) never enter the
    genealogy: a mutation that would make one is drawn again (up to 20 times; then the parent is
    copied). Their own rollouts, drawn once, measure the classifier every generation.
    """
    from evojax_morph.landscape import canonical

    tame = Tame(space, cfg)
    classifier = tame.classifier
    held_keys = {canonical(m) for m in held_out}
    rollout_batch = jax.jit(jax.vmap(tame.rollout))

    def rollouts(key, bodies) -> Rollouts:
        """Rollouts of a list of bodies, `population` at a time: one compiled shape."""
        bodies = list(jax.tree.map(np.asarray, b) for b in bodies)
        n = len(bodies)
        bodies += [bodies[0]] * (-n % population)
        keys = jax.random.split(key, len(bodies))
        parts = [rollout_batch(keys[i : i + population], stack(bodies[i : i + population]))
                 for i in range(0, len(bodies), population)]
        return jax.tree.map(lambda *x: jnp.concatenate(x)[:n], *parts)

    mutate = jax.jit(space.random_mutation)

    def child_of(key, parent) -> Morphology:
        for attempt in jax.random.split(key, 20):
            child = jax.device_get(mutate(attempt, parent))
            if canonical(child) not in held_keys:
                return child
        return parent

    # The genealogy: every body in order of birth, its rollouts in a buffer of fixed capacity
    # (so that training and scoring compile once); `count` bodies are filled.
    key, k_init, k_held, k_roll = jax.random.split(key, 4)
    m0 = jax.device_get(space.initial())
    if canonical(m0) in held_keys:
        raise ValueError("m0 cannot be held out: every genealogy starts from it")
    bodies = []
    for k in jax.random.split(k_init, 2 * population):
        k_len, k_walk = jax.random.split(k)
        m = m0
        for k_step in jax.random.split(k_walk, int(jax.random.randint(k_len, (), 0, walk_length + 1))):
            m = child_of(k_step, m)
        bodies.append(m)
    capacity = (generations + 1) * population
    new = rollouts(k_roll, bodies)
    buffer = jax.tree.map(lambda x: jnp.zeros((capacity, *x.shape[1:]), x.dtype).at[: len(bodies)].set(x), new)
    morphs = jax.tree.map(lambda x: jnp.repeat(x[:1], capacity, 0).at[: len(bodies)].set(x), stack(bodies))
    held = rollouts(k_held, held_out) if held_out else None
    held_morphs = stack(list(held_out)) if held_out else None

    params = _init_params(space, cfg, jax.random.fold_in(key, 1))
    opt = optax.adam(learning_rate)
    opt_state = opt.init(params)

    def loss_fn(params, m, states, labels, labelled):
        """Minus the mean over samples of log q per labelled motor."""
        loglik, _ = jax.vmap(lambda *a: node_log_likelihood(classifier, params, *a))(m, states, labels, labelled)
        return -jnp.mean(loglik / jnp.maximum(labelled.sum(-1), 1))

    @jax.jit
    def train(params, opt_state, morphs, buffer, count, steps, key):
        """`steps` Adam steps on minibatches of (body, episode) pairs of the first `count` bodies,
        with noise of std `state_noise` on the final states (TAME's)."""

        def step(i, carry):
            params, opt_state, total = carry
            k_b, k_e, k_n = jax.random.split(jax.random.fold_in(key, i), 3)
            b = jax.random.randint(k_b, (batch_size,), 0, count)
            e = jax.random.randint(k_e, (batch_size,), 0, cfg.episodes)
            states = buffer.states[b, e] + cfg.state_noise * jax.random.normal(k_n, (batch_size, *buffer.states.shape[2:]))
            m = jax.tree.map(lambda x: x[b], morphs)
            loss, grads = jax.value_and_grad(loss_fn)(params, m, states, buffer.labels[b, e], buffer.labelled[b])
            updates, opt_state = opt.update(grads, opt_state)
            return optax.apply_updates(params, updates), opt_state, total + loss

        params, opt_state, total = jax.lax.fori_loop(0, steps, step, (params, opt_state, 0.0))
        return params, opt_state, total / steps

    @jax.jit
    def score(params, morphs, rollouts):
        """Per body: F, mean log-likelihood per labelled motor, accuracy, and whether it has motors."""

        def one(m, r):
            loglik, acc = log_likelihood(classifier, params, m, r)
            return fitness_from(cfg, loglik, r), loglik.mean() / jnp.maximum(r.labelled.sum(), 1), acc.mean(), r.labelled.any()

        return jax.vmap(one)(morphs, rollouts)

    def measure(params, morphs, rollouts, count) -> tuple[dict, np.ndarray]:
        f, loglik, acc, motors = (x[:count] for x in jax.device_get(score(params, morphs, rollouts)))
        w = motors / max(motors.sum(), 1)  # bodies without motors have nothing to predict
        return {"loglik": float(np.sum(loglik * w)), "accuracy": float(np.sum(acc * w))}, f

    history = []
    bar = tqdm(range(generations), desc=f"TAME {space.name}", disable=not progress)
    for gen in bar:
        count = len(bodies)
        steps = epochs * max(1, math.ceil(count * cfg.episodes / batch_size))
        key, k_train, k_mut, k_roll = jax.random.split(key, 4)
        params, opt_state, loss = train(params, opt_state, morphs, buffer, count, steps, k_train)
        seen, fit = measure(params, morphs, buffer, count)
        row = {"generation": gen, "bodies": count, "distinct_bodies": len({canonical(m) for m in bodies}),
               "loss": float(loss), "train_loglik": seen["loglik"], "train_accuracy": seen["accuracy"],
               "chance_loglik": -math.log(cfg.num_primitives), "chance_accuracy": 1 / cfg.num_primitives,
               "best_fitness": float(fit.max())}
        if held is not None:
            unseen, _ = measure(params, held_morphs, held, len(held_out))
            row.update(held_out_loglik=unseen["loglik"], held_out_accuracy=unseen["accuracy"])
        history.append(row)
        bar.set_postfix(train_acc=f"{row['train_accuracy']:.2f}", held_out_acc=f"{row.get('held_out_accuracy', np.nan):.2f}")
        if gen + 1 == generations:
            break
        parents = np.argsort(-fit, kind="stable")[:population]
        children = [child_of(k, bodies[i]) for i, k in zip(parents, jax.random.split(k_mut, len(parents)))]
        new = rollouts(k_roll, children)
        put = lambda a, b: a.at[count : count + len(children)].set(b)  # noqa: B023
        buffer, morphs = jax.tree.map(put, buffer, new), jax.tree.map(put, morphs, stack(children))
        bodies += children

    # Fresh rollouts of the genealogy's bodies tell overfitting to rollouts from overfitting to bodies.
    fresh = rollouts(jax.random.fold_in(key, 2), bodies)
    seen_fresh, _ = measure(params, morphs, fresh, len(bodies))
    history[-1].update(train_fresh_loglik=seen_fresh["loglik"], train_fresh_accuracy=seen_fresh["accuracy"])
    train_keys = sorted({canonical(m) for m in bodies})
    assert not held_keys & set(train_keys), "a held-out body entered the genealogy"
    return Pretrained(space.name, cfg, jax.device_get(params), history, train_keys, sorted(held_keys))


def main(argv: list[str] | None = None) -> int:
    """Train a TAME classifier on a space and save it for `--fitness tame --classifier DIR`."""
    import argparse

    from evojax_morph import plots
    from evojax_morph.landscape import enumerate_bodies

    parser = argparse.ArgumentParser(prog="python -m evojax_morph.tame", description=main.__doc__)
    add = parser.add_argument
    add("--space", default="bad_walker")
    add("--out", default=None, help="where to save the classifier (default: runs/tame-SPACE-seedS)")
    add("--seed", type=int, default=0)
    add("--population", type=int, default=16, help="bodies mutated per generation")
    add("--generations", type=int, default=20)
    add("--held-out", type=float, default=0.2,
        help="fraction of the bodies within --held-out-depth mutations of m0 (m0 excluded) kept out of training")
    add("--held-out-depth", type=int, default=3)
    add("--epochs", type=int, default=10, help="passes over the rollout buffer per generation")
    for f in dataclasses.fields(TameConfig):
        add("--" + f.name.replace("_", "-"), type=type(f.default), default=f.default, help=f"TameConfig.{f.name}")
    args = parser.parse_args(argv)
    if not 0 <= args.held_out < 1:
        parser.error(f"--held-out must be in [0, 1), got {args.held_out}")
    for name in ("population", "generations", "epochs", "episodes", "episode_length", "period", "num_freqs", "num_phases"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be positive")
    space = make_space(args.space)
    cfg = TameConfig(**{f.name: getattr(args, f.name) for f in dataclasses.fields(TameConfig)})
    out = Path(args.out or f"runs/tame-{args.space}-seed{args.seed}")

    bodies, _ = enumerate_bodies(space, args.held_out_depth)
    held_out = [bodies[i] for i in pick_held_out(len(bodies), args.held_out, args.seed)]
    print(f"TAME on {space.name}: {len(held_out)} of {len(bodies)} bodies within {args.held_out_depth} "
          f"mutations held out; {args.generations} generations of {args.population}")
    pre = pretrain(space, jax.random.PRNGKey(args.seed), cfg, args.population, args.generations, held_out,
                   args.epochs)
    pre.save(out)
    plots.plot_tame_history(out / "history.png", pre.history)
    last = pre.history[-1]
    print(f"{len(pre.train_bodies)} distinct bodies trained on; last generation: log q per motor "
          f"{last['train_loglik']:.3f} on them (fresh rollouts {last['train_fresh_loglik']:.3f}), "
          f"{last.get('held_out_loglik', float('nan')):.3f} held out (chance {last['chance_loglik']:.3f}); accuracy "
          f"{last['train_accuracy']:.2f} / {last['train_fresh_accuracy']:.2f} / {last.get('held_out_accuracy', float('nan')):.2f}")
    print(f"saved to {out} (use: --fitness tame --classifier {out})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
