"""Predictor-guided evolution: a GNN ensemble learns the fitness of a body from every evaluation
so far and chooses which child each parent gets (BANANAS's idea, White et al. 2021).

Parents are chosen as regularized evolution chooses them (an aging population, tournaments by
the members' draws: `baselines.make_regularized_evolution`, its first population included);
what is learned is the child. Each step, for each of the N parents, `candidates` children are
drawn: each a walk of 1 to `reach` mutations whose first mutation is distinct among the
parent's candidates (uniform over the valid ones) and whose others are uniformly random valid
mutations. They are scored by an ensemble of `ensemble` graph networks, each trained on its
own minibatches of the evaluations so far (the body log's data: body -> fitness), and the
child of the highest acquisition is evaluated: independent Thompson sampling ("its": the
ensemble's mean plus its spread times a standard normal draw per child, BANANAS's choice) or
an upper confidence bound ("ucb": mean plus `kappa` spreads). A body among a parent's
candidates more than once (two mutations that make the same body, two walks that meet) is
scored once: with a Thompson draw for each copy it would win by its number of draws (on the
Length Walker walking table that bias alone doubled the first design's regret, 155 against
315: docs/results.md). A child evaluated before (its
`morphology.signature` in the data) is chosen only when every candidate was (`unseen_first`,
BANANAS's removal of duplicates): a greedy predictor otherwise sends a parent to the same
best-predicted child again and again, and the aging population fills with copies of a few
bodies (48 distinct bodies in 10,000 evaluations on the Length Walker walking table without
it; docs/results.md).

`reach` > 1 looks past a parent's neighbours: a child may be several mutations away, so the
search can cross bodies it predicts worse on its way to one it predicts better, as regularized
evolution's random mutations do by chance. The walk's last mutation is the step's action; the
body before it stands in the step as the parent (the body log's "parent"; it is not
evaluated). `prior` > 0 adds to each member a fixed, untrained network of its own times
`prior` (randomized prior functions, Osband et al. 2018): the members disagree where no data
reach, however alike their training makes them, so Thompson sampling keeps exploring there.

Before `learning_starts` evaluations are stored it mutates at random, as regularized evolution
does. Only the evaluated children count against a run's budget; the predictor's own compute
(training and scoring, both in the step's selection, `next_evo`) is in the agent's step, on
the clock of every comparison.

With a predictor that knows nothing the choice is a random valid mutation, so the agent is
regularized evolution plus what the predictor learned: what it adds is measured against that.

`transfer` starts the ensemble (and its prior networks) from one trained elsewhere, saved by
`save_ensemble` from another run's final state (another seed, another table or task of a space
with the same kinds, sites and attributes): a policy that carries what it learned to a new
problem. It goes on learning from the new run's evaluations; with `learning_starts` 0 it
chooses from the first step.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from evojax_morph.agents import baselines
from evojax_morph.agents.base import Policy, RunOptions
from evojax_morph.agents.gnn import TreeGNN, node_features
from evojax_morph.mdp import NEG, EvolutionEnv, EvoState, Observation, random_valid_actions
from evojax_morph.morphology import Morphology, signature, tree_select


@dataclasses.dataclass(frozen=True)
class PredictorConfig:
    """Predictor-guided evolution's settings; its parents' are regularized evolution's. `reach`
    and `prior` are the tuning's choice (experiments/frozen_settings.json, four settings on
    the Bad Walker's distance table); reach 1 and prior 0 are the first design's."""

    hidden: int = 32  # GNN width
    layers: int = 2  # graph convolution rounds
    ensemble: int = 5  # networks, each initialised and trained on minibatches of its own
    candidates: int = 16  # children of each parent scored per step
    reach: int = 3  # mutations a child may be from its parent (1 to reach, uniform)
    prior: float = 1.0  # the scale of each member's fixed random prior network (0: none)
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
    transfer: str = ""  # an ensemble saved by `save_ensemble` to start from ("": fresh networks)

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
        if self.ensemble < 2 or self.candidates < 1 or self.reach < 1 or self.prior < 0:
            raise ValueError("predictor: an ensemble of at least 2, at least 1 candidate, a "
                             "reach of at least 1 and a prior of at least 0")

    @classmethod
    def for_run(cls, env: EvolutionEnv, run: RunOptions) -> PredictorConfig:
        """A run's --population and --tournament; its --learning-starts."""
        cfg = cls(population=run.population, tournament=run.tournament,
                  learning_starts=run.learning_starts)
        cfg.check(env.num_envs)
        return cfg


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
    prior: dict  # (E, ...) each member's fixed prior network (scaled by `prior`; 0: unused)
    opt_state: optax.OptState  # (E, ...)
    data: Data
    pop: baselines.Population  # regularized evolution's members
    action: jax.Array  # (N,) int32: the last mutation of each parent's chosen walk
    chose: jax.Array  # () bool: `action` was chosen by the predictor (else: act at random)
    metrics: dict  # the last selection's "loss" and "spread"


def make_predictor(space, cfg: PredictorConfig):
    """(init, predict): init(key, morph) -> (E, ...) params from one body; predict(params,
    prior, morphs (..., max_nodes)) -> (E, ...) each member's predicted (normalised) fitness,
    its trained network plus `cfg.prior` times its fixed prior network (`prior`: init's params
    of another key)."""
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

    def predict(params, prior, morphs):
        out = jax.vmap(one, (0, None))(params, morphs)
        return out + cfg.prior * jax.vmap(one, (0, None))(prior, morphs) if cfg.prior else out

    return init, predict


def save_ensemble(path, learner: PredictorLearner) -> None:
    """The trained ensemble of one run's `learner` (no seed axis) and its prior networks, as an
    .npz that `PredictorConfig.transfer` starts another run from."""
    flat = {}
    for part in ("params", "prior"):
        for key, x in jax.tree_util.tree_flatten_with_path(getattr(learner, part))[0]:
            flat[part + jax.tree_util.keystr(key)] = np.asarray(x)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **flat)


def load_ensemble(path: str, template: dict, part: str) -> dict:
    """The `part` ("params" or "prior") of the ensemble saved at `path`, in the shapes of
    `template` (an ensemble `make_predictor`'s init makes). Raises ValueError where the file's
    arrays do not fit them (another space's features, another width, depth or ensemble size)."""
    with np.load(path) as saved:
        flat = dict(saved)

    def take(key, x):
        name = part + jax.tree_util.keystr(key)
        if name not in flat or flat[name].shape != x.shape:
            raise ValueError(f"predictor: the ensemble in {path!r} does not fit this space and "
                             f"these settings ({name}: saved "
                             f"{flat[name].shape if name in flat else 'none'}, here {x.shape})")
        return jnp.asarray(flat[name], x.dtype)

    return jax.tree_util.tree_map_with_path(take, template)


def normaliser(cfg: PredictorConfig, data: Data):
    """(mean, scale) of the fitness stored: the ensemble learns (fitness - mean) / scale."""
    filled = jnp.arange(cfg.buffer_size) < data.size
    count = jnp.maximum(data.size, 1)
    mean = jnp.sum(jnp.where(filled, data.fitness, 0.0)) / count
    var = jnp.sum(jnp.where(filled, (data.fitness - mean) ** 2, 0.0)) / count
    return mean, jnp.sqrt(var) + 1e-6


def store(cfg: PredictorConfig, data: Data, children: EvoState) -> Data:
    """`data` with the N children's evaluations written over its oldest (a ring)."""
    n = children.fitness.shape[0]
    idx = (data.pos + jnp.arange(n)) % cfg.buffer_size
    return Data(jax.tree.map(lambda s, x: s.at[idx].set(x), data.morph, children.morph),
                data.fitness.at[idx].set(children.fitness),
                data.signature.at[idx].set(jax.vmap(signature)(children.morph)),
                (data.pos + n) % cfg.buffer_size, jnp.minimum(data.size + n, cfg.buffer_size))


def train(cfg: PredictorConfig, predict, optimizer, learner: PredictorLearner, data: Data, key):
    """(params, opt_state, mean loss): `cfg.updates_per_step` Adam steps of every member on a
    minibatch of its own from `data` (a bootstrap), none before `data` holds enough."""
    mean, scale = normaliser(cfg, data)

    def loss_fn(params, prior, idx):
        target = (data.fitness[idx] - mean) / scale
        morphs = jax.tree.map(lambda x: x[idx], data.morph)
        one = lambda p: jax.tree.map(lambda x: x[None], p)  # noqa: E731
        return jnp.mean((predict(one(params), one(prior), morphs)[0] - target) ** 2)

    def update(carry, key):
        params, opt_state = carry

        def member(params, prior, opt_state, key):  # its own minibatch: a bootstrap
            idx = jax.random.randint(key, (cfg.batch_size,), 0, jnp.maximum(data.size, 1))
            loss, grads = jax.value_and_grad(loss_fn)(params, prior, idx)
            updates, opt_state = optimizer.update(grads, opt_state, params)
            return optax.apply_updates(params, updates), opt_state, loss

        new_params, new_opt, loss = jax.vmap(member)(
            params, learner.prior, opt_state, jax.random.split(key, cfg.ensemble))
        ready = data.size >= min(cfg.learning_starts, cfg.batch_size)
        keep = lambda new, old: jnp.where(ready, new, old)  # noqa: E731
        return (jax.tree.map(keep, new_params, params),
                jax.tree.map(keep, new_opt, opt_state)), loss.mean()

    (params, opt_state), losses = jax.lax.scan(
        update, (learner.params, learner.opt_state),
        jax.random.split(key, cfg.updates_per_step))
    return params, opt_state, losses.mean()


def candidate_walks(env: EvolutionEnv, cfg: PredictorConfig, key, parents: EvoState):
    """(N * k) candidate walks from the N `parents`, k = min(candidates, actions): (the
    body before each walk's last mutation, that mutation, the child, valid). Valid
    mutations are the env's (`env.observe`'s mask: an env may allow fewer than its space)."""
    n, nm = env.num_envs, env.space.num_mutations
    mutate = jax.vmap(lambda m, a: env.space.mutate(m, a // nm, a % nm))  # over a flat batch
    key_first, key_len, *key_steps = jax.random.split(key, cfg.reach + 1)
    mask = env.observe(parents).mask  # (N, A)
    k = min(cfg.candidates, mask.shape[-1])

    def mask_of(body):  # (N * k, A): the env's mask of N x k bodies, k at a time
        by_slot = jax.tree.map(lambda x: x.reshape(n, k, *x.shape[1:]), body)
        masks = jax.vmap(lambda m: env.observe(parents.replace(morph=m)).mask, (0,))(
            jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1), by_slot))  # (k, N, A)
        return jnp.swapaxes(masks, 0, 1).reshape(n * k, -1)

    # the first mutations: distinct per parent (Gumbel top-k over its mask)
    score, action = jax.lax.top_k(jnp.where(mask, jax.random.gumbel(key_first, mask.shape),
                                            NEG), k)
    valid, action = (score > NEG / 2).reshape(-1), action.reshape(-1)
    body = jax.tree.map(lambda x: jnp.repeat(x, k, 0), parents.morph)  # (N * k, ...)
    length = jax.random.randint(key_len, (n * k,), 1, cfg.reach + 1)
    for i, key_step in enumerate(key_steps[: cfg.reach - 1], start=1):  # further ones
        walked = mutate(body, action)
        step_mask = mask_of(walked)
        nxt = random_valid_actions(key_step, step_mask)
        go = (i < length) & step_mask.any(-1)  # a walk with no valid step left ends here
        body, action = tree_select(go, walked, body), jnp.where(go, nxt, action)
    return body, action, mutate(body, action), valid



def choose(env: EvolutionEnv, cfg: PredictorConfig, predict, prior, params, data: Data, keys,
           parents: EvoState):
    """Each parent's chosen walk (the body before its last mutation, that mutation) and
    the ensemble's mean spread over the candidates: the acquisition over the ensemble's
    (`params`, `prior`) predictions of each parent's `candidate_walks`."""
    n = env.num_envs
    key_walks, key_its = keys
    body, action, kids, valid = candidate_walks(env, cfg, key_walks, parents)
    k = action.shape[0] // n
    pred = predict(params, prior, kids).reshape(-1, n, k)  # (E, N, k)
    mean, spread = pred.mean(0), pred.std(0)
    if cfg.acquisition == "its":
        value = mean + spread * jax.random.normal(key_its, mean.shape)
    else:
        value = mean + cfg.kappa * spread
    sig = jax.vmap(signature)(kids).reshape(n, k, 2)
    valid = valid.reshape(n, k)
    # A BODY ONCE: a candidate equal to an earlier one of its parent's is dropped
    same = (sig[:, :, None] == sig[:, None, :]).all(-1) & valid[:, None, :]
    valid &= ~jnp.any(jnp.tril(same, -1), -1)
    if cfg.unseen_first:  # SEEN: a candidate's signature among the evaluations stored
        filled = jnp.arange(cfg.buffer_size) < data.size
        seen = jnp.any((sig[:, :, None] == data.signature).all(-1) & filled, -1)  # (N, k)
        unseen = valid & ~seen
        valid = jnp.where(unseen.any(1, keepdims=True), unseen, valid)
    pick = jnp.arange(n) * k + jnp.argmax(jnp.where(valid, value, NEG), 1)
    return jax.tree.map(lambda x: x[pick], body), action[pick], jnp.mean(spread)


def make_policy(env: EvolutionEnv, cfg: PredictorConfig) -> Policy:
    """Selection (`next_evo`): store the children's evaluations, train the ensemble on them,
    choose the parents as regularized evolution does, then each parent's child by the
    acquisition over `cfg.candidates` walks; acting takes the walk's last mutation."""
    cfg.check(env.num_envs)
    space, n = env.space, env.num_envs
    nm = space.num_mutations
    init_net, predict = make_predictor(space, cfg)
    parents = baselines.make_regularized_evolution(env, cfg.parents())
    optimizer = optax.adam(cfg.learning_rate)

    def init(keys, obs: Observation) -> PredictorLearner:
        one = jax.tree.map(lambda x: x[0], obs.morph)
        key_net, key_prior = jax.random.split(keys[0])
        params, prior = init_net(key_net, one), init_net(key_prior, one)
        if cfg.transfer:  # what another run learned, in place of fresh networks
            params = load_ensemble(cfg.transfer, params, "params")
            prior = load_ensemble(cfg.transfer, prior, "prior")
        data = Data(jax.tree.map(lambda x: jnp.zeros((cfg.buffer_size, *x.shape), x.dtype), one),
                    jnp.zeros(cfg.buffer_size), jnp.zeros((cfg.buffer_size, 2), jnp.uint32),
                    jnp.zeros((), jnp.int32), jnp.zeros((), jnp.int32))
        return PredictorLearner(params, prior, jax.vmap(optimizer.init)(params), data,
                                parents.init(keys[1:], obs), jnp.zeros(n, jnp.int32),
                                jnp.zeros((), bool), {"loss": jnp.zeros(()),
                                                      "spread": jnp.zeros(())})

    def next_evo(env, learner: PredictorLearner, keys, parents_evo, children, first, done):
        key_pop, key_train, *key_choose = keys
        data = store(cfg, learner.data, children)  # STORE every child's evaluation
        params, opt_state, loss = train(cfg, predict, optimizer, learner, data,
                                        key_train)  # LEARN from them
        pop, evo = parents.next_evo(env, learner.pop, key_pop[None], parents_evo, children,
                                    first, done)  # the PARENTS: regularized evolution's
        body, action, spread = choose(env, cfg, predict, learner.prior, params, data, key_choose,
                                      evo)
        chose = data.size >= cfg.learning_starts  # the CHILD: the acquisition's best walk
        evo = evo.replace(morph=tree_select(jnp.broadcast_to(chose, (n,)), body, evo.morph))
        return learner.replace(params=params, opt_state=opt_state, data=data, pop=pop,
                               action=action, chose=chose,
                               metrics={"loss": loss, "spread": spread}), evo

    def act(learner: PredictorLearner, keys, obs: Observation, step):
        del step
        action = jnp.where(learner.chose, learner.action, random_valid_actions(keys[0], obs.mask))
        return action.astype(jnp.int32), {}

    def learn(learner: PredictorLearner, keys, transition, step):
        del keys, transition, step  # learning is in the selection, `next_evo`
        return learner, learner.metrics

    def scores(learner: PredictorLearner, obs: Observation) -> jax.Array:
        """(N, num_actions): the ensemble's mean prediction of each valid action's child."""
        actions = jnp.arange(obs.mask.shape[-1])
        kids = jax.vmap(lambda m: jax.vmap(lambda a: space.mutate(m, a // nm, a % nm))(
            actions))(obs.morph)
        return jnp.where(obs.mask, predict(learner.params, learner.prior, kids).mean(0), NEG)

    # keys: init (nets, population), act (random), learn (none), next_evo (parents, training,
    # walks, its)
    return Policy(keys=(2, 1, 0, 4), init=init, act=act, learn=learn, scores=scores,
                  next_evo=next_evo)
