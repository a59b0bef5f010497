"""TAME's pre-training: its evolutionary loop grows a genealogy and trains the classifier on it.

`pretrain` returns a `Pretrained` classifier, saved as an Orbax checkpoint plus tame.json and
loaded back by the "tame" fitness (`evojax_morph.fitnesses.tame`).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm.auto import tqdm

from evojax_morph.morphology import Morphology, stack
from evojax_morph.spaces import Space, make_space
from evojax_morph.tame.classifier import log_likelihood, node_log_likelihood
from evojax_morph.tame.fitness import Rollouts, Tame, TameConfig, fitness_from, init_classifier


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
        meta = {
            "space": self.space,
            "config": dataclasses.asdict(self.config),
            "history": self.history,
            "train_bodies": self.train_bodies,
            "held_out_bodies": self.held_out_bodies,
        }
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
        abstract = jax.eval_shape(
            functools.partial(init_classifier, space, cfg), jax.random.PRNGKey(0)
        )
        with ocp.StandardCheckpointer() as ckpt:
            params = ckpt.restore(path / "params", abstract)
        return cls(
            meta["space"],
            cfg,
            params,
            meta["history"],
            meta["train_bodies"],
            meta["held_out_bodies"],
        )


def pick_held_out(num_bodies: int, fraction: float, seed: int) -> list[int]:
    """Sorted indices of round(fraction x (num_bodies - 1)) bodies drawn at random from 1 ..
    num_bodies - 1 of an `enumerate_bodies` list (index 0 is m0, which starts every genealogy)."""
    pick = np.random.default_rng(seed).permutation(num_bodies - 1)[
        : round(fraction * (num_bodies - 1))
    ]
    return sorted(int(i) + 1 for i in pick)


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

    `held_out` bodies (and any body of the same shape, `Space.canonical`) never enter the
    genealogy: a mutation that would make one is drawn again (up to 20 times; then the parent is
    copied). Their own rollouts, drawn once, measure the classifier every generation.
    """
    tame = Tame(space, cfg)
    held_keys = {space.canonical(m) for m in held_out}
    if space.canonical(jax.device_get(space.initial())) in held_keys:
        raise ValueError("m0 cannot be held out: every genealogy starts from it")
    rollouts = _make_rollouts(tame, population)
    child_of = _make_child_of(space, held_keys)

    # The genealogy: every body in order of birth, its rollouts in a buffer of fixed capacity
    # (so that training and scoring compile once); `count` bodies are filled.
    key, k_init, k_held, k_roll = jax.random.split(key, 4)
    bodies = _first_bodies(space, k_init, 2 * population, walk_length, child_of)
    capacity = (generations + 1) * population
    buffer, morphs = _genealogy(rollouts(k_roll, bodies), stack(bodies), capacity)
    held = (stack(list(held_out)), rollouts(k_held, held_out)) if held_out else None

    params = init_classifier(space, cfg, jax.random.fold_in(key, 1))
    opt = optax.adam(learning_rate)
    opt_state = opt.init(params)
    train = _make_train(tame.classifier, cfg, opt, batch_size)
    measure = _make_measure(tame.classifier, cfg)

    history = []
    bar = tqdm(range(generations), desc=f"TAME {space.name}", disable=not progress)
    for gen in bar:
        count = len(bodies)
        steps = epochs * max(1, math.ceil(count * cfg.episodes / batch_size))
        key, k_train, k_mut, k_roll = jax.random.split(key, 4)
        params, opt_state, loss = train(params, opt_state, morphs, buffer, count, steps, k_train)
        seen, fit = measure(params, morphs, buffer, count)
        row = _history_row(space, cfg, gen, bodies, loss, seen, fit)
        if held is not None:
            unseen, _ = measure(params, *held, len(held_out))
            row.update(held_out_loglik=unseen["loglik"], held_out_accuracy=unseen["accuracy"])
        history.append(row)
        bar.set_postfix(
            train_acc=f"{row['train_accuracy']:.2f}",
            held_out_acc=f"{row.get('held_out_accuracy', np.nan):.2f}",
        )
        if gen + 1 == generations:
            break
        children = _children(child_of, bodies, fit, population, k_mut)
        new = rollouts(k_roll, children), stack(children)
        buffer, morphs = _put(count, (buffer, morphs), new)
        bodies += children

    # Fresh rollouts of the genealogy's bodies tell overfitting to rollouts from overfitting to
    # bodies.
    fresh = rollouts(jax.random.fold_in(key, 2), bodies)
    seen_fresh, _ = measure(params, morphs, fresh, len(bodies))
    history[-1].update(
        train_fresh_loglik=seen_fresh["loglik"], train_fresh_accuracy=seen_fresh["accuracy"]
    )
    train_keys = sorted({space.canonical(m) for m in bodies})
    assert not held_keys & set(train_keys), "a held-out body entered the genealogy"
    return Pretrained(
        space.name, cfg, jax.device_get(params), history, train_keys, sorted(held_keys)
    )


def _make_rollouts(tame: Tame, population: int):
    """`rollouts(key, bodies) -> Rollouts` of a list of bodies, `population` at a time: one
    compiled shape."""
    rollout_batch = jax.jit(jax.vmap(tame.rollout))

    def rollouts(key, bodies) -> Rollouts:
        bodies = list(jax.tree.map(np.asarray, b) for b in bodies)
        n = len(bodies)
        bodies += [bodies[0]] * (-n % population)
        keys = jax.random.split(key, len(bodies))
        parts = [
            rollout_batch(keys[i : i + population], stack(bodies[i : i + population]))
            for i in range(0, len(bodies), population)
        ]
        return jax.tree.map(lambda *x: jnp.concatenate(x)[:n], *parts)

    return rollouts


def _make_child_of(space: Space, held_keys: set):
    """`child_of(key, parent) -> Morphology`: a random mutation of `parent` whose shape is not in
    `held_keys`, drawn up to 20 times; then `parent` itself."""
    mutate = jax.jit(space.random_mutation)

    def child_of(key, parent) -> Morphology:
        for attempt in jax.random.split(key, 20):
            child = jax.device_get(mutate(attempt, parent))
            if space.canonical(child) not in held_keys:
                return child
        return parent

    return child_of


def _first_bodies(space: Space, key, num: int, walk_length: int, child_of) -> list[Morphology]:
    """`num` walks of 0..`walk_length` mutations (`child_of`) from m0, one key each."""
    m0 = jax.device_get(space.initial())
    bodies = []
    for k in jax.random.split(key, num):
        k_len, k_walk = jax.random.split(k)
        m = m0
        for k_step in jax.random.split(
            k_walk, int(jax.random.randint(k_len, (), 0, walk_length + 1))
        ):
            m = child_of(k_step, m)
        bodies.append(m)
    return bodies


def _children(child_of, bodies, fit, population: int, key) -> list[Morphology]:
    """One mutation (`child_of`) of each of the `population` fittest `bodies` by `fit`."""
    parents = np.argsort(-fit, kind="stable")[:population]
    return [child_of(k, bodies[i]) for i, k in zip(parents, jax.random.split(key, len(parents)))]


def _put(count: int, trees, new):
    """`trees` with rows count .. count + len(`new`) - 1 of every leaf set to `new`'s."""
    n = len(jax.tree.leaves(new)[0])
    return jax.tree.map(lambda a, b: a.at[count : count + n].set(b), trees, new)


def _genealogy(rollouts: Rollouts, morphs: Morphology, capacity: int):
    """The buffer of `capacity` bodies' rollouts and their morphologies, filled with the first
    `len(rollouts)` (the rest: zero rollouts, copies of the first body)."""
    n = len(jax.tree.leaves(morphs)[0])
    buffer = jax.tree.map(
        lambda x: jnp.zeros((capacity, *x.shape[1:]), x.dtype).at[:n].set(x), rollouts
    )
    morphs = jax.tree.map(lambda x: jnp.repeat(x[:1], capacity, 0).at[:n].set(x), morphs)
    return buffer, morphs


def _make_train(classifier, cfg: TameConfig, opt, batch_size: int):
    """The jitted `train(params, opt_state, morphs, buffer, count, steps, key) -> (params,
    opt_state, mean loss)`."""

    def loss_fn(params, m, states, labels, labelled):
        """Minus the mean over samples of log q per labelled motor."""
        loglik, _ = jax.vmap(lambda *a: node_log_likelihood(classifier, params, *a))(
            m, states, labels, labelled
        )
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
            states = buffer.states[b, e] + cfg.state_noise * jax.random.normal(
                k_n, (batch_size, *buffer.states.shape[2:])
            )
            m = jax.tree.map(lambda x: x[b], morphs)
            loss, grads = jax.value_and_grad(loss_fn)(
                params, m, states, buffer.labels[b, e], buffer.labelled[b]
            )
            updates, opt_state = opt.update(grads, opt_state)
            return optax.apply_updates(params, updates), opt_state, total + loss

        params, opt_state, total = jax.lax.fori_loop(0, steps, step, (params, opt_state, 0.0))
        return params, opt_state, total / steps

    return train


def _make_measure(classifier, cfg: TameConfig):
    """`measure(params, morphs, rollouts, count) -> ({"loglik", "accuracy"}, F per body)` over
    the first `count` bodies, the means weighted to bodies with motors."""

    @jax.jit
    def score(params, morphs, rollouts):
        """Per body: F, mean log-likelihood per labelled motor, accuracy, and whether it has
        motors."""

        def one(m, r):
            loglik, acc = log_likelihood(classifier, params, m, r)
            return (
                fitness_from(cfg, loglik, r),
                loglik.mean() / jnp.maximum(r.labelled.sum(), 1),
                acc.mean(),
                r.labelled.any(),
            )

        return jax.vmap(one)(morphs, rollouts)

    def measure(params, morphs, rollouts, count) -> tuple[dict, np.ndarray]:
        f, loglik, acc, motors = (
            x[:count] for x in jax.device_get(score(params, morphs, rollouts))
        )
        w = motors / max(motors.sum(), 1)  # bodies without motors have nothing to predict
        return {"loglik": float(np.sum(loglik * w)), "accuracy": float(np.sum(acc * w))}, f

    return measure


def _history_row(space: Space, cfg: TameConfig, gen, bodies, loss, seen, fit) -> dict:
    """One generation's row of `Pretrained.history` (the held-out columns are added after)."""
    return {
        "generation": gen,
        "bodies": len(bodies),
        "distinct_bodies": len({space.canonical(m) for m in bodies}),
        "loss": float(loss),
        "train_loglik": seen["loglik"],
        "train_accuracy": seen["accuracy"],
        "chance_loglik": -math.log(cfg.num_primitives),
        "chance_accuracy": 1 / cfg.num_primitives,
        "best_fitness": float(fit.max()),
    }
