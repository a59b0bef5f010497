"""The actor-critic agent, the baselines and the bodies a space enumerates, with the predefined
fitness (fast);
and a smoke run of every experiment script at a tiny budget."""

import json
import runpy
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_spaces import reachable, reachable_batched

import evojax_morph as em
from evojax_morph import agents
from evojax_morph.agents import a2c, baselines
from evojax_morph.fitnesses import table as tb
from evojax_morph.morphology import signature
from evojax_morph.search.pipeline import RunConfig, build

ROOT = Path(__file__).resolve().parents[1]


def make(space_name, agent, num_envs, horizon, **run):
    """The run's pipeline with the predefined fitness."""
    return build(RunConfig(space=space_name, fitness="predefined", agent=agent, num_envs=num_envs,
                           horizon=horizon, **run))


def test_masked_entropy_by_hand():
    logits = jnp.array([[0.0, 5.0, 0.0, 0.0], [1.0, 2.0, 3.0, 4.0]])
    mask = jnp.array([[True, False, True, True], [False, False, False, True]])
    # row 0: uniform over 3 valid actions (the masked 5 must not count): log 3; row 1: one action: 0
    np.testing.assert_allclose(a2c.masked_entropy(logits, mask), [np.log(3.0), 0.0], atol=1e-6)


def a2c_learning(seeds) -> tuple[np.ndarray, np.ndarray]:
    """Per seed (one vmapped call): the mean episode return (f_8 - f_0) of each of 25 episodes
    (S, 25), and the fall of the policy's entropy from the first 8 steps to the last 8 (S,), for
    the actor-critic on Constructor with the predefined fitness (rewards / fitness_scale, the
    run's update schedule: one update per step)."""
    init, chunk, _ = make("constructor", "a2c", 16, 8, hidden=32).agent
    keys = jax.vmap(jax.random.PRNGKey)(jnp.asarray(seeds))
    _, metrics = jax.jit(jax.vmap(lambda s: chunk(s, 200)))(jax.jit(jax.vmap(init))(keys))
    assert np.isfinite(metrics["loss"]).all()
    reward = np.asarray(metrics["reward"])  # (S, 200, 16)
    entropy = np.asarray(metrics["entropy"])  # (S, 200)
    returns = reward.reshape(len(reward), 25, 8, 16).sum(2).mean(2)  # (S, episodes)
    return returns, entropy[:, :8].mean(1) - entropy[:, -8:].mean(1)


def a2c_bad_walker(seeds) -> np.ndarray:
    """Per seed (one vmapped call): the mean episode return (f_5 - f_0, best possible 1.33) of
    the last 5 of 80 episodes of the actor-critic on Bad Walker with the predefined fitness,
    16 parallel evolutions, the run's settings (a 64-wide GNN, one update per step)."""
    init, chunk, _ = make("bad_walker", "a2c", 16, 5).agent
    keys = jax.vmap(jax.random.PRNGKey)(jnp.asarray(seeds))
    _, metrics = jax.jit(jax.vmap(lambda s: chunk(s, 400)))(jax.jit(jax.vmap(init))(keys))
    assert np.isfinite(metrics["loss"]).all()
    reward = np.asarray(metrics["reward"])  # (S, 400, 16)
    returns = reward.reshape(len(reward), 80, 5, 16).sum(2).mean(2)  # (S, episodes)
    return returns[:, -5:].mean(1)


@pytest.mark.learning
def test_actor_critic_learns_constructor():
    """Episode returns rise from random play towards the space's best, and the entropy falls."""
    returns, fall = a2c_learning(range(12))
    final = returns[:, -5:].mean(1)  # the last 5 episodes
    rise = final - returns[:, 0]  # from the first episode, nearly random play
    # Measured on 2 CPU cores (jax 0.10.2) over seeds 100-123 with one update per step
    # (`python -m experiments.learning_margins --measure a2c --seeds 24`): final 800 of 800 in
    # all 24; rise from the first episode median 1000 (range 762-1250; 12-seed medians' 1%
    # bootstrap quantile 894); entropy fall median 2.88 (range 2.71-3.02). The rise is measured
    # from the first episode: the first 5 (the old baseline) now hold 40 updates and already
    # climb most of the way.
    assert np.median(final) > 700, final
    assert np.median(rise) > 700, rise
    assert np.median(fall) > 2.0, fall


@pytest.mark.learning
def test_actor_critic_learns_bad_walker():
    """Bad Walker: the actor-critic learns to remove the long foot (+1; no body that keeps it
    returns more than 0.33) although removing a short foot costs 1.33, instead of settling for
    no-ops or short feet moved out."""
    final = a2c_bad_walker(range(12))
    # Measured on 2 CPU cores (jax 0.10.2) over seeds 100-123
    # (`python -m experiments.learning_margins --measure a2c --seeds 24`): median 1.15 of 1.33;
    # 19 seeds at 1.06-1.23 (the long foot removed), 5 at -0.03-0.24
    # (the short feet moved out, the long foot still on: 0.33 at best). 0.5 lies above every
    # body that keeps the long foot, so the median falls below it only if 7 of 12 seeds stall,
    # about 1 in 200 at the measured 5 in 24 (Binomial); 12-seed medians' 1% quantile 0.65.
    assert np.median(final) > 0.5, final


def evolution_search(seeds):
    """Per seed (one vmapped call): best fitness per step (S, 24) and the final population's
    fitness (S, 8) of (mu + lambda) evolution on Bad Walker with the predefined fitness."""
    init, chunk, scores = make("bad_walker", "evolution", 8, 4).agent
    assert scores is None
    keys = jax.vmap(jax.random.PRNGKey)(jnp.asarray(seeds))
    states, metrics = jax.jit(jax.vmap(lambda s: chunk(s, 24)))(jax.jit(jax.vmap(init))(keys))
    return np.asarray(metrics["best_fitness"]), np.asarray(states.evo.fitness)


@pytest.mark.learning
def test_evolution_is_elitist_and_finds_the_optimum():
    space = em.make_space("bad_walker")
    best, population = evolution_search(range(12))
    # Elitism, in every seed: the best never falls, and with a deterministic fitness no survivor
    # is worse than the m0 they all began as.
    assert (np.diff(best, axis=1) >= 0).all()
    assert population.min() >= float(space.predefined_fitness(space.initial()))
    # 192 evaluations find Bad Walker's best body in nearly every seed (half of them measure
    # the survivors again, which a deterministic fitness does not need). Measured on 2 CPU
    # cores (jax 0.10.2, `evolution_search(range(100, 148))`): 47 of seeds 100-147 (one ends
    # at 1.0); at 96 evaluations 33 of 48. 9 of 12 fail only if 4 of 12 miss: about 1 in 10^4
    # at 1 in 48.
    optimum = max(float(space.predefined_fitness(m)) for m in reachable(space))
    found = np.abs(best[:, -1] - optimum) < 1e-6
    assert found.mean() >= 0.75, best[:, -1]


def on_table(agent, num_envs, **run):
    """The run's pipeline with Bad Walker's packaged table fitness (one draw a body)."""
    return build(RunConfig(space="bad_walker", fitness="table", agent=agent, num_envs=num_envs,
                           **run))


def test_evolution_ranks_its_survivors_by_the_mean_of_their_draws():
    """Step by step against numpy, from each step's evaluated bodies: the first half are the
    survivors, evaluated again unchanged; a survivor's fitness becomes the mean of all its
    draws, a child's is its one draw; the best half of them by that mean survive (ties: the
    lower slot), each followed by a copy to mutate."""
    n, mu = 6, 3
    agent = on_table("evolution", n).agent
    state = agent.init(jax.random.PRNGKey(3))
    np.testing.assert_array_equal(state.learner, np.ones(n))  # m0's N draws, one each
    for _ in range(4):
        new, m = agent.chunk(state, 1)
        log = jax.tree.map(lambda x: np.asarray(x[0]), m["bodies"])
        for a, b in zip(jax.tree.leaves(log["parent"]), jax.tree.leaves(log["morph"])):
            np.testing.assert_array_equal(a[:mu], b[:mu])  # the survivors: the same bodies
        draws = np.asarray(state.learner, np.float32)
        mean = np.where(np.arange(n) < mu, (np.asarray(state.evo.fitness) * draws
                                            + log["fitness"]) / (draws + 1), log["fitness"])
        count = np.where(np.arange(n) < mu, draws + 1, 1)
        keep = np.argsort(-mean, kind="stable")[:mu][np.arange(n) % mu]
        np.testing.assert_allclose(new.evo.fitness, mean[keep], rtol=1e-6)
        np.testing.assert_array_equal(new.learner, count[keep])
        state = new
    assert int(np.max(state.learner)) > 2  # some survivor was measured again and again


def test_regularized_evolution_ages_out_its_oldest():
    """P = 8 members, N = 4 children a step, tournaments of S = P (every member sampled): the
    population is a ring of the last two steps' children, the first step's aged out at the
    third, and every parent is the fittest member."""
    agent = on_table("regularized_evolution", 4, population=8, tournament=8).agent
    state, draws = agent.init(jax.random.PRNGKey(5)), []
    for step in range(3):
        state, m = agent.chunk(state, 1)
        draws.append(np.asarray(m["bodies"]["fitness"][0]))
        pop = state.learner
        assert int(pop.size) == min(4 * (step + 1), 8) and int(pop.next) == 4 * (step + 1) % 8
        members = np.asarray(pop.evo.fitness)[: int(pop.size)]
        np.testing.assert_array_equal(members[:4], draws[-1] if step != 1 else draws[0])
        np.testing.assert_array_equal(state.evo.fitness, np.full(4, members.max()))
    np.testing.assert_array_equal(np.asarray(pop.evo.fitness)[4:], draws[1])  # step 2's children


def test_regularized_evolution_first_population_of_walks():
    """first="walks": until the population is full, the parents are random walks of 0 to
    walk - 1 mutations from m0, so the first P children lie at most `walk` mutations away (a
    no-op is a mutation), some beyond one; once full, the parents are tournament winners
    again (S = P: the fittest)."""
    n, p = 16, 32
    env = on_table("random", n).env
    cfg = baselines.RegularizedEvolutionConfig(p, p, first="walks", walk=3)
    agent = agents.from_policy(env, baselines.make_regularized_evolution(env, cfg))
    bodies, depths = env.space.enumerate_bodies()
    depth = {env.space.canonical(m): d for m, d in zip(bodies, depths)}
    state, far = agent.init(jax.random.PRNGKey(2)), []
    for _ in range(3):
        state, m = agent.chunk(state, 1)
        kids = jax.device_get(m["bodies"]["morph"])
        far.append([depth[env.space.canonical(jax.tree.map(lambda x, i=i: x[0, i], kids))]
                    for i in range(n)])
    assert max(far[0]) <= 1 and 2 <= max(far[1]) <= 3
    members = np.asarray(state.learner.evo.fitness)
    np.testing.assert_array_equal(state.evo.fitness, np.full(n, members.max()))


@pytest.mark.parametrize("contrast", [False, pytest.param(True, marks=pytest.mark.slow)])
def test_predictor_stores_its_evaluations_and_revisits_only_when_every_child_was_seen(contrast):
    """The predictor's data set holds each step's child, its draw and its signature, in order;
    its scores rank only valid actions (masked ones at the floor). Scoring every valid
    mutation of its parent (reach 1), it picks a child evaluated before only when all of the
    parent's children were, and every parent was evaluated. `contrast` (the slow set: two
    more programs, 22 s cold) checks that these can fail: without the rule
    (`unseen_first=False`) the greedy picks go back to bodies already seen while new ones were
    on offer; with reach 3 some children are a walk away, the body their last mutation was
    applied to (the step's parent) never evaluated."""
    env = on_table("random", 1).env
    space, nm, steps, starts = env.space, env.space.num_mutations, 40, 8

    def run(unseen_first, reach=1):
        agent = agents.make_agent("predictor", env, learning_starts=starts, candidates=1024,
                                  ensemble=2, unseen_first=unseen_first, reach=reach, first="m0")
        return agent, *agent.chunk(agent.init(jax.random.PRNGKey(0)), steps)

    def unevaluated_parents(m):
        sig = lambda key: np.asarray(jax.vmap(signature)(  # noqa: E731
            jax.tree.map(lambda x: x[:, 0], m["bodies"][key])))
        parents, evaluated = sig("parent"), {tuple(x) for x in sig("morph")}
        evaluated.add(tuple(np.asarray(signature(space.initial()))))
        return sum(tuple(p) not in evaluated for p in parents[starts:])

    @jax.jit
    def offered(parents):  # (T, A) each valid child's signature and the mask
        every = jnp.arange(space.max_nodes * nm)
        kids = jax.vmap(lambda p: jax.vmap(lambda a: signature(space.mutate(
            p, a // nm, a % nm)))(every))(parents)
        return kids, jax.vmap(lambda p: space.action_mask(p).reshape(-1))(parents)

    def avoidable_revisits(m):
        body = lambda x: x[:, 0]  # noqa: E731
        sig = np.asarray(jax.vmap(signature)(jax.tree.map(body, m["bodies"]["morph"])))
        kids, mask = map(np.asarray, offered(jax.tree.map(body, m["bodies"]["parent"])))
        count = 0
        for t in range(starts, steps):
            seen = {tuple(x) for x in sig[:t]}
            unseen_offered = any(tuple(k) not in seen for k in kids[t][mask[t]])
            count += tuple(sig[t]) in seen and unseen_offered
        return count, sig

    agent, state, m = run(True)
    data = state.learner.data
    count, sig = avoidable_revisits(m)
    assert int(data.size) == steps and count == 0
    np.testing.assert_array_equal(np.asarray(data.fitness)[:steps],
                                  np.asarray(m["fitness"]).reshape(-1))
    np.testing.assert_array_equal(np.asarray(data.signature)[:steps], sig)
    obs = env.observe(state.evo)
    scores, mask = np.asarray(agent.scores(state.learner, obs)), np.asarray(obs.mask)
    assert (scores[~mask] <= -1e8).all() and np.isfinite(scores[mask]).all()
    assert (scores[mask] > -1e8).all() and unevaluated_parents(m) == 0
    if contrast:
        assert avoidable_revisits(run(False)[2])[0] > 0
        assert unevaluated_parents(run(True, reach=3)[2]) > 0


def test_a_predictor_starts_from_a_transferred_ensemble(tmp_path):
    """`save_ensemble` keeps a run's ensemble and prior networks; a predictor with `transfer`
    starts from exactly them (not from its own key's networks); an ensemble of another shape
    (here another width) is refused with the array named."""
    from evojax_morph.agents import predictor

    env = on_table("random", 2).env
    make = lambda **kw: agents.make_agent("predictor", env, ensemble=2, first="m0", **kw)  # noqa: E731
    source = make().init(jax.random.PRNGKey(0)).learner
    path = tmp_path / "ensemble.npz"
    predictor.save_ensemble(path, source)
    moved = make(transfer=str(path)).init(jax.random.PRNGKey(1)).learner
    fresh = make().init(jax.random.PRNGKey(1)).learner
    for part in ("params", "prior"):
        for x, y in zip(jax.tree.leaves(getattr(source, part)),
                        jax.tree.leaves(getattr(moved, part)), strict=True):
            np.testing.assert_array_equal(x, y)
        assert any(not np.array_equal(x, z) for x, z in zip(
            jax.tree.leaves(getattr(source, part)), jax.tree.leaves(getattr(fresh, part))))
    with pytest.raises(ValueError, match=r"does not fit this space and these settings \(params"):
        make(transfer=str(path), hidden=16).init(jax.random.PRNGKey(1))


@pytest.mark.learning
def test_predictor_learns_the_table():
    """After 60 steps of 8 evaluations on the Bad Walker table, the ensemble's mean prediction
    (each member's prior network included) ranks the table's 90 bodies by their true means
    (Spearman), where the same networks untrained do not."""
    from scipy.stats import spearmanr

    from evojax_morph.agents import predictor

    env = on_table("random", 8).env
    cfg = predictor.PredictorConfig(learning_starts=32)
    agent = agents.from_policy(env, predictor.make_policy(env, cfg))
    table, _ = tb.load(env.space, em.FitnessConfig(kind="table"))
    _, predict = predictor.make_predictor(env.space, cfg)
    bodies = jax.tree.map(jnp.asarray, table.bodies)
    mean = lambda lr: predict(lr.params, lr.prior, bodies).mean(0)  # noqa: E731

    def run(key):
        start = agent.init(key)
        state, _ = agent.chunk(start, 60)
        return mean(start.learner), mean(state.learner)

    before, after = jax.jit(jax.vmap(run))(jax.vmap(jax.random.PRNGKey)(jnp.arange(12)))
    rho = lambda x: np.array([spearmanr(row, table.mean())[0] for row in np.asarray(x)])  # noqa: E731
    # Measured on 2 CPU cores (jax 0.10.2), seeds 100-111, at the defaults of 2026-12-02's
    # third round (reach 3, prior 1; the mean prediction includes the prior networks):
    # trained mean 0.82 (min 0.66, sd 0.07, every seed above its untrained networks), the
    # same to 0.01 under --xla_cpu_max_isa=AVX2 and AVX; untrained mean 0.00 (-0.38 to
    # 0.36). The bound on the trained mean sits 20 standard errors (0.020) under it.
    assert rho(after).mean() >= 0.4 and abs(rho(before).mean()) <= 0.2, (rho(after), rho(before))
    assert (rho(after) > rho(before)).mean() >= 10 / 12


def lucky_draw_table(path):
    """A Bad Walker table (32 results a body) where every body but one has a lucky draw: one
    result in 32 is 800 above its mean (0 to 100), the others a little below; the best body,
    3 mutations from m0, has a mean of 200 in noisy draws (100 or 300) and no lucky one.
    Returns the best body."""
    space = em.make_space("bad_walker")
    bodies, _ = space.enumerate_bodies()
    names = [space.canonical(m) for m in bodies]
    depth = {space.canonical(m): d for m, d in reachable_batched(space)}
    b = next(i for i, name in enumerate(names) if depth.get(name) == 3)  # the first of 65
    rng = np.random.default_rng(0)
    mean = rng.uniform(0, 100, len(names))
    fitness = mean[:, None] + rng.normal(0, 10, (len(names), 32))
    fitness[:, 0] += 800
    fitness[:, 1:] -= 800 / 31
    fitness[b] = np.where(np.arange(32) % 2, 100.0, 300.0)
    tb.Table(space.name, names, tb.stacked(list(bodies)), fitness.astype(np.float32),
             np.zeros(fitness.shape, bool), {"env_steps_per_result": 1}).save(path)
    return bodies[b]


@pytest.mark.learning
def test_measuring_again_or_aging_escapes_lucky_draws(tmp_path):
    """On a table of lucky draws, the single-draw (mu + lambda) rule fills its population with
    them and stays; evolution measuring its survivors again and regularized evolution end
    their runs on the best body: per seed, over 100 steps of 8 evaluations, whether more than
    a tenth of the last 25 steps' evaluations are the best body."""
    best = jnp.asarray(tb.signature(lucky_draw_table(tmp_path / "t.npz")))
    env = build(RunConfig(space="bad_walker", fitness="table", table=str(tmp_path / "t.npz"),
                          agent="random", num_envs=8)).env
    keys = jax.vmap(jax.random.PRNGKey)(jnp.arange(24))

    def ends_on_best(policy):
        agent = agents.from_policy(env, policy)

        def run(key):
            state, m = agent.chunk(agent.init(key), 100)
            on_best = (jax.vmap(jax.vmap(tb.signature))(m["bodies"]["morph"]) == best).all(-1)
            return on_best[-25:].mean() > 0.1, (state.evo.fitness > 400).mean()

        return map(np.asarray, jax.jit(jax.vmap(run))(keys))

    ended, lucky = ends_on_best(single_draw_evolution(env))
    # Measured on 2 CPU cores (jax 0.10.2) over seeds 100-147: the single-draw rule's final
    # population all lucky draws in every seed, no seed ending on the best body; evolution 29
    # of 48 seeds (60%), regularized evolution 27 (56%). At 56%, 8 of 24 or fewer (the bound
    # below) is about 1 in 300 (Binomial); 3 of 24 at the measured 0 in 48 under 1 in 100.
    assert lucky.mean() >= 0.9 and ended.mean() <= 0.1, (lucky, ended)
    measured = baselines.RegularizedEvolutionConfig(population=32, tournament=8)  # as measured
    for policy in (baselines.make_evolution(env),
                   baselines.make_regularized_evolution(env, measured)):
        ended, _ = ends_on_best(policy)
        assert ended.mean() >= 0.375, ended


def test_random_walks_restart():
    space = em.make_space("bad_walker")
    init, chunk, _ = make("bad_walker", "random", 8, 4).agent
    state, metrics = chunk(init(jax.random.PRNGKey(1)), 8)  # two episodes: restarts at m0
    assert np.isfinite(np.asarray(metrics["fitness"])).all() and (state.evo.steps == 0).all()
    np.testing.assert_array_equal(state.evo.morph.site, state.first.morph.site)  # back at m0
    np.testing.assert_allclose(
        state.evo.fitness, jax.vmap(space.predefined_fitness)(state.evo.morph)
    )


def test_enumerated_bodies_are_told_apart_by_shape():
    """`enumerate_bodies` lists every body reachable from m0 once, by `canonical` name (slot
    numbers and sibling order ignored), m0 first; the predefined fitness's best is m*."""
    space = em.make_space("bad_walker")
    # back foot to front_end (site 3) and front foot to back_end (site 0), or the other way
    swapped = space.mutate(space.mutate(space.initial(), 2, 3), 3, 0)
    same = space.mutate(space.mutate(space.initial(), 2, 0), 3, 3)
    assert space.canonical(swapped) == space.canonical(same)  # identical short feet
    assert space.canonical(swapped) != space.canonical(space.initial())

    bodies, depths = space.enumerate_bodies()
    slots = reachable(space)  # an independent BFS, telling bodies apart by slot
    distinct = {space.canonical(m) for m in slots}
    names = [space.canonical(m) for m in bodies]
    assert len(slots) == 150 and len(set(names)) == len(names) == len(distinct) == 90
    assert set(names) == distinct and depths[0] == 0
    assert names[0] == space.canonical(space.initial())
    fitness = np.asarray(jax.vmap(space.predefined_fitness)(em.stack(bodies)))
    assert names[int(fitness.argmax())] == space.canonical(space.optimum())


@pytest.mark.parametrize(
    "script, args, output",
    [
        (
            "fig4_predefined",
            ["--steps", "8", "--chunk", "8", "--num-envs", "4", "--seeds", "2"],
            "fig4_predefined",
        ),
    ],
)
@pytest.mark.slow  # the script compiles its agents: minutes
def test_experiment_scripts_run_at_a_tiny_budget(script, args, output, tmp_path, monkeypatch):
    """`python -m experiments.SCRIPT ...` from the project root, in this process."""
    monkeypatch.syspath_prepend(str(ROOT))
    monkeypatch.setattr(sys, "argv", [script, *args, "--out", str(tmp_path)])
    runpy.run_module(f"experiments.{script}", run_name="__main__")
    assert (tmp_path / f"{output}.png").stat().st_size > 0
    summary = json.loads((tmp_path / f"{output}.json").read_text())
    assert summary


def single_draw_evolution(env) -> baselines.Policy:
    """The (mu + lambda) rule of the results before issue 60, kept here to show its trap: every
    body mutated, the fittest N of parents and children by the one draw each was evaluated
    at, never measured again, so a lucky draw survives for ever."""

    def next_evo(env, learner, keys, parents, children, first, done):
        del keys, first, done
        pool = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), parents, children)
        _, keep = jax.lax.top_k(pool.fitness, env.num_envs)
        survivors = jax.tree.map(lambda x: x[keep], pool)
        return learner, survivors.replace(steps=jnp.zeros(env.num_envs, jnp.int32))

    return baselines.make_random(env)._replace(next_evo=next_evo)
