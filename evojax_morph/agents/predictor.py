"""Predictor-guided evolution: a GNN ensemble learns the fitness of a body from every evaluation
so far and chooses which mutation each parent gets (BANANAS's idea, White et al. 2021).

Parents are chosen as regularized evolution chooses them (an aging population, tournaments by
the members' draws: `baselines.make_regularized_evolution`, its first population included);
what is learned is the mutation. Each step, for each of the N parents, `candidates` valid
mutations are drawn uniformly and the children they make are scored by an ensemble of
`ensemble` graph networks, each trained on its own minibatches of the evaluations so far (the
body log's data: body -> fitness); the child of the highest acquisition is evaluated:
independent Thompson sampling ("its": the ensemble's mean plus its spread times a standard
normal draw per child, BANANAS's choice) or an upper confidence bound ("ucb": mean plus
`kappa` spreads). A child evaluated before (its `morphology.signature` in the data) is chosen
only when every candidate was (`unseen_first`, BANANAS's removal of duplicates): a greedy
predictor otherwise sends a parent to the same best-predicted child again and again, and the
aging population fills with copies of a few bodies (48 distinct bodies in 10,000 evaluations
on the Length Walker walking table without it; docs/results.md). Before `learning_starts`
evaluations are stored it mutates at random, as regularized evolution does. Only the evaluated
children count against a run's budget; the predictor's own compute (training and scoring) is in
the agent's step, on the clock of every comparison.

With a predictor that knows nothing the choice is a random valid mutation, so the agent is
regularized evolution plus what the predictor learned: what it adds is measured against that.
"""

from __future__ import annotations

import dataclasses

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax
from flax import struct

from evojax_morph.agents import baselines
from evojax_morph.agents.base import Policy, RunOptions
from evojax_morph.agents.gnn import TreeGNN, node_features
from evojax_morph.mdp import NEG, EvolutionEnv, Observation, random_valid_actions
from evojax_morph.morphology import Morphology, signature


@dataclasses.dataclass(frozen=True)
class PredictorConfig:
    """Predictor-guided evolution's settings; its parents' are regularized evolution's."""

    hidden: int = 32  # GNN width
    layers: int = 2  # graph convolution rounds
    ensemble: int = 5  # networks, each initialised and trained on minibatches of its own
    candidates: int = 16  # valid mutations of each parent scored per step
    acquisition: str = "its"  # "its" (Thompson, per child) or "ucb" (mean + kappa spreads)
    kappa: float = 1.0  # ucb only
    unseen_first: bool = True  # a child evaluated before only when every candidate was
    buffer_size: int = 16_384  # evaluations kept to learn from (a ring)
    batch_size: int = 64
    updates_per_step: int = 4
    learning_rate: float = 3e-3
    learning_starts: int = 64  # evaluations stored before the predictor chooses
    population: int = 0  # regularized evolution's P (0: 2 N)
    tournament: int = 0  # its S (0: P // 8)
    first: str = "walks"  # its first population ("walks" or "m0")

    def parents(self) -> baselines.RegularizedEvolutionConfig:
        """The parent selection's settings."""
        return baselines.RegularizedEvolutionConfig(self.population, self.tournament,
                                                    self.first)

    def check(self, num_envs: int) -> None:
        """ValueError where these settings cannot run `num_envs` evolutions."""
        self.parents().sizes(num_envs)
        if self.acquisition not in ("its", "ucb"):
            raise ValueError(f"predictor: acquisition must be 'its' or 'ucb', got "
                             f"{self.acquisition!r}")
        if self.ensemble < 2 or self.candidates < 1:
            raise ValueError("predictor: an ensemble of at least 2 and at least 1 candidate")

    @classmethod
    def for_run(cls, env: EvolutionEnv, run: RunOptions) -> PredictorConfig:
        """A run's --population and --tournament; its --learning-starts."""
        cfg = cls(population=run.population, tournament=run.tournament,
                  learning_starts=run.learning_starts)
        cfg.check(env.num_envs)
        return cfg


def check(num_envs: int, population: int = 0, tournament: int = 0) -> None:
    PredictorConfig(population=population, tournament=tournament).check(num_envs)


class FitnessNet(nn.Module):
    """A body's predicted fitness: the sum over its active nodes of a per-node output of the
    tree GNN (each node's row sees the whole body through the GNN's pooled context)."""

    hidden: int
    layers: int

    @nn.compact
    def __call__(self, m: Morphology, nodes: jax.Array) -> jax.Array:
        out, _ = TreeGNN(hidden=self.hidden, layers=self.layers, out_size=1,
                         head=(self.hidden,))(m, nodes)
        return jnp.sum(out[:, 0] * m.active)


@struct.dataclass
class Data:
    """Every evaluation so far (a ring of `buffer_size`): the predictor's training set."""

    morph: Morphology  # (C, ...)
    fitness: jax.Array  # (C,)
    signature: jax.Array  # (C, 2) uint32: each body's `morphology.signature`
    pos: jax.Array  # () int32: the next slot
    size: jax.Array  # () int32: slots filled


@struct.dataclass
class PredictorLearner:
    params: dict  # (E, ...) the ensemble
    opt_state: optax.OptState  # (E, ...)
    data: Data
    pop: baselines.Population  # regularized evolution's members


def make_predictor(space, cfg: PredictorConfig):
    """(init, predict): init(key, morph) -> (E, ...) params from one body; predict(params,
    morphs (..., max_nodes)) -> (E, ...) each member's predicted (normalised) fitness."""
    net = FitnessNet(cfg.hidden, cfg.layers)
    num_kinds, num_sites = len(space.kind_names), len(space.site_names)
    feats = lambda m: node_features(m, jnp.zeros(()), num_kinds, num_sites)  # noqa: E731

    def init(key, morph):
        return jax.vmap(lambda k: net.init(k, morph, feats(morph)))(
            jax.random.split(key, cfg.ensemble))

    def one(params, morphs):
        lead = morphs.active.shape[:-1]
        flat = jax.tree.map(lambda x: x.reshape((-1,) + x.shape[len(lead):]), morphs)
        out = jax.vmap(lambda m: net.apply(params, m, feats(m)))(flat)
        return out.reshape(lead)

    return init, jax.vmap(one, (0, None))


def make_policy(env: EvolutionEnv, cfg: PredictorConfig) -> Policy:
    """Acting: the best child of `cfg.candidates` random valid mutations by the acquisition;
    learning: the ensemble's minibatch steps on the evaluations so far; parents: regularized
    evolution's."""
    cfg.check(env.num_envs)
    space, n = env.space, env.num_envs
    nm = space.num_mutations
    init_net, predict = make_predictor(space, cfg)
    parents = baselines.make_regularized_evolution(env, cfg.parents())
    optimizer = optax.adam(cfg.learning_rate)

    def normaliser(data: Data):
        filled = jnp.arange(cfg.buffer_size) < data.size
        count = jnp.maximum(data.size, 1)
        mean = jnp.sum(jnp.where(filled, data.fitness, 0.0)) / count
        var = jnp.sum(jnp.where(filled, (data.fitness - mean) ** 2, 0.0)) / count
        return mean, jnp.sqrt(var) + 1e-6

    def init(keys, obs: Observation) -> PredictorLearner:
        one = jax.tree.map(lambda x: x[0], obs.morph)
        params = init_net(keys[0], one)
        data = Data(jax.tree.map(lambda x: jnp.zeros((cfg.buffer_size, *x.shape), x.dtype), one),
                    jnp.zeros(cfg.buffer_size), jnp.zeros((cfg.buffer_size, 2), jnp.uint32),
                    jnp.zeros((), jnp.int32), jnp.zeros((), jnp.int32))
        return PredictorLearner(params, jax.vmap(optimizer.init)(params), data,
                                parents.init(keys[1:], obs))

    def act(learner: PredictorLearner, keys, obs: Observation, step):
        del step
        key_cand, key_its, key_rand = keys
        # CANDIDATES: distinct valid mutations of each parent (Gumbel top-k over the mask)
        gumbel = jax.random.gumbel(key_cand, obs.mask.shape)
        k = min(cfg.candidates, obs.mask.shape[-1])
        score, cand = jax.lax.top_k(jnp.where(obs.mask, gumbel, NEG), k)  # (N, k)
        valid = score > NEG / 2
        kids = jax.vmap(lambda m, a: jax.vmap(lambda a: space.mutate(m, a // nm, a % nm))(a))(
            obs.morph, cand)
        # ACQUISITION over the ensemble's predictions
        pred = predict(learner.params, kids)  # (E, N, k)
        mean, spread = pred.mean(0), pred.std(0)
        if cfg.acquisition == "its":
            value = mean + spread * jax.random.normal(key_its, mean.shape)
        else:
            value = mean + cfg.kappa * spread
        if cfg.unseen_first:  # SEEN: a candidate's signature among the evaluations stored
            sig = jax.vmap(jax.vmap(signature))(kids)  # (N, k, 2)
            data = learner.data
            filled = jnp.arange(cfg.buffer_size) < data.size
            seen = jnp.any((sig[:, :, None] == data.signature).all(-1) & filled, -1)  # (N, k)
            unseen = valid & ~seen
            valid = jnp.where(unseen.any(1, keepdims=True), unseen, valid)
        pick = jnp.take_along_axis(cand, jnp.argmax(jnp.where(valid, value, NEG), 1)[:, None],
                                   1)[:, 0]
        ready = learner.data.size >= cfg.learning_starts
        action = jnp.where(ready, pick, random_valid_actions(key_rand, obs.mask))
        return action.astype(jnp.int32), {"spread": jnp.mean(spread)}

    def next_evo(env, learner: PredictorLearner, keys, parents_evo, children, first, done):
        # STORE every child's evaluation
        data = learner.data
        idx = (data.pos + jnp.arange(n)) % cfg.buffer_size
        data = Data(jax.tree.map(lambda s, x: s.at[idx].set(x), data.morph, children.morph),
                    data.fitness.at[idx].set(children.fitness),
                    data.signature.at[idx].set(jax.vmap(signature)(children.morph)),
                    (data.pos + n) % cfg.buffer_size, jnp.minimum(data.size + n, cfg.buffer_size))
        pop, evo = parents.next_evo(env, learner.pop, keys, parents_evo, children, first, done)
        return learner.replace(data=data, pop=pop), evo

    def learn(learner: PredictorLearner, keys, transition, step):
        del transition, step
        data = learner.data
        mean, scale = normaliser(data)

        def loss_fn(params, idx):
            target = (data.fitness[idx] - mean) / scale
            morphs = jax.tree.map(lambda x: x[idx], data.morph)
            out = predict(jax.tree.map(lambda x: x[None], params), morphs)[0]
            return jnp.mean((out - target) ** 2)

        def update(carry, key):
            params, opt_state = carry

            def member(params, opt_state, key):  # its own minibatch: a bootstrap of the data
                idx = jax.random.randint(key, (cfg.batch_size,), 0, jnp.maximum(data.size, 1))
                loss, grads = jax.value_and_grad(loss_fn)(params, idx)
                updates, opt_state = optimizer.update(grads, opt_state, params)
                return optax.apply_updates(params, updates), opt_state, loss

            new_params, new_opt, loss = jax.vmap(member)(
                params, opt_state, jax.random.split(key, cfg.ensemble))
            ready = data.size >= min(cfg.learning_starts, cfg.batch_size)
            keep = lambda new, old: jnp.where(ready, new, old)  # noqa: E731
            return (jax.tree.map(keep, new_params, params),
                    jax.tree.map(keep, new_opt, opt_state)), loss.mean()

        (params, opt_state), losses = jax.lax.scan(
            update, (learner.params, learner.opt_state),
            jax.random.split(keys[0], cfg.updates_per_step))
        return learner.replace(params=params, opt_state=opt_state), {"loss": losses.mean()}

    def scores(learner: PredictorLearner, obs: Observation) -> jax.Array:
        """(N, num_actions): the ensemble's mean prediction of each valid action's child."""
        actions = jnp.arange(obs.mask.shape[-1])
        kids = jax.vmap(lambda m: jax.vmap(lambda a: space.mutate(m, a // nm, a % nm))(
            actions))(obs.morph)
        return jnp.where(obs.mask, predict(learner.params, kids).mean(0), NEG)

    # keys: init (net, population), act (candidates, its, random), learn, next_evo (parents)
    return Policy(keys=(2, 3, 1, 1), init=init, act=act, learn=learn, scores=scores,
                  next_evo=next_evo)
