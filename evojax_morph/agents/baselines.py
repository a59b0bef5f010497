"""Baselines that learn nothing, at the agents' cost: N fitness evaluations per step.

random: N random mutation walks; each step applies a uniformly random valid mutation to every
  walk, episodes of `horizon` mutations restart from m0, as the agents' do.
evolution: NGE's (mu + lambda) evolution, survivors measured again (Wang et al. 2019,
  WilsonWangTHU/neural_graph_evolution, evolution/species_bank.py): a population of N // 2
  survivors; each step every survivor is evaluated again (its controller trained further with
  a fresh key; a fresh draw on the table fitness) and N - N // 2 children, a random valid
  mutation each of a survivor, are evaluated, in one fitness call of N; the N // 2 of the
  highest mean over their draws survive. A lucky draw is diluted by the next ones.
regularized_evolution: aging evolution as the NAS benchmarks run it (Real et al. 2019,
  google-research/nasbench; NAS-Bench-201's R_EA), batched: a population of P; each step makes
  N children, each a random valid mutation of the best of S members sampled without
  replacement, and each child replaces the oldest member. A lucky draw is aged out after P / N
  steps.

Children inherit their parent's controller, as the agents' do. Neither evolution restarts.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from flax import struct

from evojax_morph.agents.base import Policy, RunOptions
from evojax_morph.mdp import REMEASURE, EvolutionEnv, EvoState, random_valid_actions
from evojax_morph.morphology import Morphology, tree_select


def _random_act(learner, keys, obs, step):
    del learner, step
    return random_valid_actions(keys[0], obs.mask), {}


def _no_learning(learner, keys, transition, step):
    del keys, transition, step
    return learner, {}


def make_random(env: EvolutionEnv, cfg: None = None) -> Policy:
    """Random walks: uniformly random valid mutations, episodes restarting at m0."""
    del env, cfg  # nothing to set
    return Policy(keys=(0, 1, 0), init=lambda keys, obs: None, act=_random_act,
                  learn=_no_learning, scores=None)


def _take(tree, idx):
    return jax.tree.map(lambda x: x[idx], tree)


# EVOLUTION, SURVIVORS MEASURED AGAIN


def check_evolution(num_envs: int) -> None:
    if num_envs < 2:
        raise ValueError(f"evolution keeps num_envs // 2 survivors: it needs at least 2 "
                         f"parallel evolutions (--num-envs), got {num_envs}")


def make_evolution(env: EvolutionEnv, cfg: None = None) -> Policy:
    """(mu + lambda) evolution whose survivors are evaluated again every step (module doc).

    Slots [0, mu) of the bodies a step evaluates are the survivors (action `REMEASURE`), slots
    [mu, N) their children; the learner holds how many draws each survivor's fitness (kept as
    their mean in `EvoState.fitness`) averages.
    """
    del cfg  # nothing to set
    n = env.num_envs
    check_evolution(n)
    mu = n // 2
    surviving = jnp.arange(n) < mu

    def act(draws, keys, obs, step):
        del draws, step
        action = random_valid_actions(keys[0], obs.mask)
        return jnp.where(surviving, REMEASURE, action), {}

    def next_evo(env, draws, keys, parents, children, first, done):
        del env, keys, first, done
        # the survivors' new draw joins their mean; a child has its one draw
        mean = jnp.where(surviving, (parents.fitness * draws + children.fitness) / (draws + 1),
                         children.fitness)
        count = jnp.where(surviving, draws + 1, 1)
        _, keep = jax.lax.top_k(mean, mu)  # ties: the lower slot, a survivor before a child
        slots = keep[jnp.arange(n) % mu]  # each survivor, then a copy of it to mutate
        evo = _take(children.replace(fitness=mean), slots)
        return count[slots], evo.replace(steps=jnp.zeros(n, jnp.int32))

    return Policy(keys=(0, 1, 0), init=lambda keys, obs: jnp.ones(n, jnp.int32), act=act,
                  learn=_no_learning, scores=None, next_evo=next_evo)


# REGULARIZED (AGING) EVOLUTION


@dataclasses.dataclass(frozen=True)
class RegularizedEvolutionConfig:
    """Aging evolution's settings. Defaults tuned on the Length Walker's distance table (four
    settings x 20 seeds, as every method had there) after a sweep of 10 settings on the Bad
    Walker's distance table that no other method had (docs/figures/tuning_regularized_evolution/),
    and reported on every table, the tuning table among them (docs/results.md, "Searchers under
    noise"); the NAS benchmarks use P = 50 to 100, S = 10 to 25 with one child a step."""

    population: int = 0  # P, members; 0: 2 N
    tournament: int = 0  # S, members sampled per tournament; 0: P // 8
    # the first population: "walks", P random walks of 1 to `walk` mutations from m0 (the NAS
    # benchmarks' random first population); "m0", children of m0 and of the first members
    first: str = "m0"
    walk: int = 5  # "walks": the longest walk

    def sizes(self, num_envs: int) -> tuple[int, int]:
        """(P, S) for N = `num_envs` children a step; raises ValueError where they cannot work."""
        p = self.population or 2 * num_envs
        s = self.tournament or max(p // 8, 1)
        if p < 2:
            raise ValueError(f"regularized_evolution: the population must be at least 2, got {p}")
        if p < num_envs:
            raise ValueError(f"regularized_evolution: the population ({p}) must hold at least a "
                             f"step's {num_envs} children (--num-envs)")
        if not 1 <= s <= p:
            raise ValueError(f"regularized_evolution: the tournament must sample between 1 "
                             f"and the population ({p}) members, got {s}")
        if self.first not in ("m0", "walks") or self.walk < 1:
            raise ValueError(f"regularized_evolution: first must be 'm0' or 'walks' and walk "
                             f"at least 1, got {self.first!r}, {self.walk}")
        return p, s

    def check(self, num_envs: int) -> None:
        """ValueError where these settings cannot run `num_envs` evolutions (`sizes`)."""
        self.sizes(num_envs)

    @classmethod
    def for_run(cls, env: EvolutionEnv, run: RunOptions) -> RegularizedEvolutionConfig:
        """P and S of the run's --population and --tournament, defaults resolved; raises
        ValueError before anything compiles where they cannot work."""
        return cls(*cls(run.population, run.tournament).sizes(env.num_envs))


def random_walks(env: EvolutionEnv, key: jax.Array, first: EvoState, longest: int) -> Morphology:
    """(N, ...) bodies, each a walk from `first`'s bodies (m0) of 0 to `longest` uniformly random
    actions valid in `env` (its length uniform too)."""
    key_len, key_walk = jax.random.split(key)
    lengths = jax.random.randint(key_len, (env.num_envs,), 0, longest + 1)
    nm = env.space.num_mutations

    def step(morph, x):
        i, key = x
        action = random_valid_actions(key, env.observe(first.replace(morph=morph)).mask)
        child = jax.vmap(env.space.mutate)(morph, action // nm, action % nm)
        return tree_select(i < lengths, child, morph), None

    morph, _ = jax.lax.scan(step, first.morph,
                            (jnp.arange(longest), jax.random.split(key_walk, longest)))
    return morph


@struct.dataclass
class Population:
    """Aging evolution's members, a ring: the oldest is at `next`."""

    evo: EvoState  # (P, ...) members, valid in slots [0, size)
    size: jax.Array  # () int32: members so far (P once full)
    next: jax.Array  # () int32: the slot the next child takes (the oldest member once full)


def make_regularized_evolution(env: EvolutionEnv,
                               cfg: RegularizedEvolutionConfig | None = None) -> Policy:
    """Aging evolution (module doc). The population starts empty and is filled by the
    children, oldest first; until then tournaments sample the members there are. The first
    step mutates m0's N evaluations."""
    n = env.num_envs
    cfg = cfg or RegularizedEvolutionConfig()
    p, s = cfg.sizes(n)

    def init(keys, obs):
        del keys
        params = jax.eval_shape(env.init_fn, jax.random.PRNGKey(0))
        zeros = lambda shape, dtype=jnp.float32: jnp.zeros((p, *shape), dtype)  # noqa: E731
        evo = EvoState(jax.tree.map(lambda x: zeros(x.shape[1:], x.dtype), obs.morph),
                       jax.tree.map(lambda x: zeros(x.shape, x.dtype), params), zeros(()),
                       zeros(()), zeros((), bool), zeros(()), zeros(()), zeros((), jnp.int32))
        zero = jnp.zeros((), jnp.int32)
        return Population(evo, zero, zero)

    def next_evo(env, pop, keys, parents, children, first, done):
        del parents, done
        # AGE: the children replace the oldest members
        slots = (pop.next + jnp.arange(n)) % p
        evo = jax.tree.map(lambda m, c: m.at[slots].set(c), pop.evo, children)
        pop = Population(evo, jnp.minimum(pop.size + n, p), (pop.next + n) % p)
        # TOURNAMENTS: N samples of S distinct members; the fittest of each is a parent
        key_sample, key_walk = jax.random.split(keys[0])
        u = jax.random.uniform(key_sample, (n, p))
        member = jnp.arange(p) < pop.size
        _, sample = jax.lax.top_k(jnp.where(member, u, -1.0), s)  # (N, S), members first
        fit = jnp.where(member[sample], evo.fitness[sample], -jnp.inf)
        winners = jnp.take_along_axis(sample, jnp.argmax(fit, 1)[:, None], 1)[:, 0]
        parents = _take(evo, winners).replace(steps=jnp.zeros(n, jnp.int32))
        if cfg.first == "walks":  # until P members: walks of 0 to walk - 1, mutated once more
            walks = random_walks(env, key_walk, first, cfg.walk - 1)
            parents = tree_select(jnp.broadcast_to(pop.size < p, (n,)),
                                  first.replace(morph=walks), parents)
        return pop, parents

    return Policy(keys=(0, 1, 0, 1), init=init, act=_random_act, learn=_no_learning,
                  scores=None, next_evo=next_evo)
