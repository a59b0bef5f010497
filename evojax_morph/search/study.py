"""A study as one batched program: every method and every seed of a comparison stepping together.

A step of the study proposes each method's children (its agent's `AskTell.ask`, vmapped over
its seeds), evaluates every method's and seed's children in ONE call of the fitness on one flat
batch of sum_m S x N_m bodies, and gives each method its results back (`AskTell.tell`, vmapped
over its seeds). The start (m0's evaluation) is one call in the same way. Nothing but the batch
is shared: a method's seeds run exactly as `from_policy`'s agent runs them alone with the same
keys (tests/test_study.py, on the table fitness, bit for bit), and the methods see nothing of
each other. The fitness sees one flat world axis, never a vmap inside a vmap (MuJoCo Warp's
call needs that), and a GPU gets calls as full as the study is wide.

`make_study` gives the jitted `init(keys)` and `chunk(states, num_steps)` (one `lax.scan`);
`run_study` steps it in the host's loop of every search (`loop.chunks`, a run's too), each
chunk followed by a save as a run's checkpoints (`records.checkpoints`), resumed from them.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from evojax_morph import agents
from evojax_morph.agents.base import Policy, make_ask_tell
from evojax_morph.mdp import EvolutionEnv, EvoState
from evojax_morph.morphology import canonical, signature
from evojax_morph.records.bodylog import ranked
from evojax_morph.records.checkpoints import (
    checkpoint_manager,
    restore_checked,
    restore_newest,
    save_args,
)
from evojax_morph.search.loop import chunks
from evojax_morph.search.pipeline import Pipeline, RunConfig, agent_config, build
from evojax_morph.sharding import jit_replicated, to_host

_signatures = jax.jit(jax.vmap(jax.vmap(signature)))  # (S, N, ...) bodies -> (S, N, 2)


class Method(NamedTuple):
    """One method of a study: an agent's policy on its env (N_m parallel evolutions a seed)."""

    name: str
    env: EvolutionEnv  # every method's env has the study's space and fitness
    policy: Policy


class Study(NamedTuple):
    """init(keys (S,)) -> states, {method: AgentState (S, ...)}: seed s of every method starts
    from keys[s], as `from_policy`'s `init(keys[s])` would alone. chunk(states, num_steps) ->
    (states, metrics): {method: its agent's metrics (num_steps, S, ...), "bodies" left out,
    with "signature" (num_steps, S, N_m, 2) uint32: each child's `morphology.signature`, and "morph"
    (num_steps, S, N_m, ...): each child, to recover a body from its signature
    (`best_mean_bodies`)}. evaluations: bodies a study step evaluates (one fitness call):
    sum_m S x N_m."""

    init: Callable
    chunk: Callable
    methods: tuple[str, ...]
    seeds: int
    evaluations: int


def methods_from(cfg: RunConfig, names: Sequence[str], mesh=None,
                 overrides: dict | None = None) -> tuple[list[Method], Pipeline]:
    """(methods, pipeline): each agent of `names` as `run` builds it under `cfg` (its
    settings from `cfg`, `pipeline.agent_config`, then `overrides`' {name: {field: value}}),
    all on the env of cfg.num_envs evolutions of the pipeline `build` makes of `cfg` with the
    first agent (its space, fitness config and batched fitness, split across `mesh`)."""
    p = build(dataclasses.replace(cfg, agent=names[0]), mesh)
    methods = [Method(name, p.env, agents.make_policy(
        name, p.env, settings_of(cfg, name, p.env, overrides))) for name in names]
    return methods, p


def settings_of(cfg: RunConfig, name: str, env: EvolutionEnv, overrides: dict | None = None):
    """Agent `name`'s config as `run` builds it under `cfg`, then `overrides`' fields for it
    (None for an agent without settings)."""
    settings = agent_config(dataclasses.replace(cfg, agent=name), env)
    mine = (overrides or {}).get(name, {})
    return dataclasses.replace(settings, **mine) if mine else settings


def evaluate_together(fitness_fn: Callable, batches: Sequence[tuple]) -> list:
    """The `FitnessResult`s of several (keys, morphs, params) batches of leading shape
    (S, N_m), from one call of `fitness_fn` on their concatenation, flat: (sum_m S x N_m,)."""
    shapes = [b[0].shape[:2] for b in batches]
    sizes = [s * n for s, n in shapes]
    flat = [jax.tree.map(lambda x, k=k: x.reshape((k, *x.shape[2:])), b)
            for b, k in zip(batches, sizes)]
    out = fitness_fn(*jax.tree.map(lambda *xs: jnp.concatenate(xs), *flat))
    ends = np.cumsum(sizes).tolist()
    return [jax.tree.map(lambda x, a=end - k, b=end, sh=sh: x[a:b].reshape((*sh, *x.shape[1:])),
                         out) for k, end, sh in zip(sizes, ends, shapes)]


def make_study(methods: Sequence[Method], seeds: int, fitness_fn: Callable | None = None,
               mesh=None) -> Study:
    """The study of `methods` x `seeds`, jitted, its states replicated on `mesh` (default:
    every device; the fitness splits its one batch a step across them).

    Args:
      methods: distinct names; their envs share one space and fitness.
      seeds: S runs of each method.
      fitness_fn: the one batched fitness (default: the first method's env's).
    """
    names = tuple(m.name for m in methods)
    if len(set(names)) != len(names):
        raise ValueError(f"a study's methods need distinct names, got {names}")
    fitness_fn = fitness_fn or methods[0].env.fitness_fn
    steps = [make_ask_tell(m.env, m.policy) for m in methods]
    args = lambda b: (b.keys, b.morphs, b.params)  # noqa: E731

    def init(keys: jax.Array) -> dict:
        starts = [jax.vmap(s.ask_first)(keys) for s in steps]
        outs = evaluate_together(fitness_fn, [args(b) for b in starts])
        return {m.name: jax.vmap(s.tell_first)(b, out)
                for m, s, b, out in zip(methods, steps, starts, outs)}

    def step(states: dict, _):
        # ASK: every method's seeds act and mutate
        props = [jax.vmap(s.ask)(states[m.name]) for m, s in zip(methods, steps)]
        # EVALUATE every child of the study in one fitness call
        outs = evaluate_together(fitness_fn, [args(p) for p in props])
        # TELL: each method's seeds learn from their own children
        new, metrics = {}, {}
        for m, s, p, out in zip(methods, steps, props, outs):
            new[m.name], mm = jax.vmap(s.tell)(states[m.name], p, out)
            mm = {k: v for k, v in mm.items() if k != "bodies"}
            mm["signature"] = _signatures(p.morphs)
            mm["morph"] = p.morphs
            metrics[m.name] = mm
        return new, metrics

    def chunk(states: dict, num_steps: int):
        """`num_steps` study steps in one `lax.scan`; metrics stacked along a leading axis
        (each method's children among them: their "signature" and "morph")."""
        return jax.lax.scan(step, states, length=num_steps)

    init, chunk = jit_replicated(init, chunk, mesh)
    evaluations = seeds * sum(m.env.num_envs for m in methods)
    return Study(init, chunk, names, seeds, evaluations)


def run_study(study: Study, keys: jax.Array, num_steps: int, chunk: int,
              resume: Path | None = None, deadline: float | None = None,
              since: float | None = None, log: Callable | None = None,
              preload: Callable | None = None) -> dict | None:
    """The study's host loop from the seeds' `keys` (S,): `num_steps` steps in chunks of
    `chunk`, resumable.

    With `resume` (a folder), the states and metrics so far are saved there after the start
    and after every chunk as a run's checkpoints are (`records.checkpoints`: Orbax, beside
    them the SHA-256 of every array, the newest two kept) and picked up by the next call from
    the newest that reads, a damaged newer one moved aside (`checkpoints.restore_newest`,
    which raises `ResumeError` where none reads); past `deadline` (time.time()) it returns
    None after the chunk in progress, to be called again. since: when this call's work began
    (time.time(), e.g. before building the study; default: now). log: called with a line of
    progress after every chunk (e.g. `print`), and with a line for each damaged save skipped
    (that one printed where `log` is None).
    preload: None, or a function starting the engine's preload (`Engine.preload`) and
    returning its Future: started before this call's first program compiles, waited for
    before that program runs.

    Returns:
      {"metrics": {method: {name: (num_steps, S, ...)}}, "states": the final states (host),
      "chunk_seconds": [the wall clock of each compiled chunk call, until its metrics reached
      the host], "chunk_steps": [the steps of each],
      "evaluations_per_second": the study's evaluations over those seconds, "init_seconds":
      the start's call, compile included, "seconds": every call's wall clock from its
      `since`, compiles included}.
    """
    called = time.time() if since is None else since
    loading = [preload()] if preload is not None else []

    def loaded(program):  # the preload waited for, before the call's first program runs
        while loading:
            loading.pop().result()
        return program

    found = None if resume is None else _newest_save(study, keys, resume, log or print)
    if found is None:
        start = time.perf_counter()
        states = jax.block_until_ready(loaded(study.init.lower(keys).compile())(keys))
        so_far = {"metrics": [], "chunk_seconds": [], "chunk_steps": [], "done": 0,
                  "seconds": 0.0, "init_seconds": time.perf_counter() - start}
    else:
        states, so_far = found
    manager = None if resume is None else checkpoint_manager(resume)[1]  # after the moves aside
    if manager is not None and found is None:  # a fresh start (a resumed one is saved already)
        _save(manager, states, so_far, called)
    compiled = {}

    def program(n):  # compiled before the clock starts: a call is timed alone
        if n not in compiled:
            compiled[n] = loaded(study.chunk.lower(states, n).compile())
        return compiled[n]

    for done in chunks(program, states, so_far["done"], num_steps, chunk, deadline):
        states = done.state
        so_far["chunk_seconds"].append(done.seconds)
        so_far["chunk_steps"].append(done.n)
        so_far["metrics"].append(done.metrics)
        so_far["done"] = done.step
        if manager is not None:
            _save(manager, states, so_far, called)
        if log is not None:
            log(f"study step {done.step} of {num_steps}: {done.seconds:.1f} s for {done.n} "
                f"({study.evaluations * done.n / done.seconds:.1f} evaluations/s)")
    if manager is not None:
        manager.wait_until_finished()
    if so_far["done"] < num_steps:  # past the deadline
        return None
    cat = jax.tree.map(lambda *xs: np.concatenate(xs), *so_far["metrics"])
    timed = float(np.sum(so_far["chunk_seconds"]))
    return {
        "metrics": cat,
        "states": to_host(states),
        "chunk_seconds": so_far["chunk_seconds"],
        "chunk_steps": so_far["chunk_steps"],
        "evaluations_per_second": study.evaluations * sum(so_far["chunk_steps"]) / timed,
        "init_seconds": so_far["init_seconds"],
        "seconds": so_far["seconds"] + time.time() - called,
    }


def _newest_save(study: Study, keys: jax.Array, folder: Path, log: Callable):
    """(states, so far) of the newest of the study's saves in `folder` that reads, checked
    against its digests (`checkpoints.restore_newest`, which logs those skipped); None where
    there is none."""
    def restore(manager, step):  # the tree as saved, on the host
        states = jax.eval_shape(study.init, keys)
        saved = {"states": states}
        if step:  # the metrics of its `step` steps
            saved["metrics"] = jax.eval_shape(lambda s: study.chunk(s, step), states)[1]
        abstract = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), saved)
        return restore_checked(manager, step, abstract)

    found = restore_newest(folder, restore, log)[1]
    if found is None:
        return None
    saved, record = found  # record: {"step", "log": the rest of so far}
    return saved["states"], {**record["log"], "done": record["step"],
                             "metrics": [saved["metrics"]] if record["step"] else []}


def _save(manager, states, so_far: dict, since: float) -> None:
    """The study's `states` and `so_far` saved as its checkpoint of the steps done
    (`checkpoints.save_args`): the states and the metrics so far as arrays, the rest in its
    record, "seconds" counted up to now from `since`."""
    kept = {"states": to_host(states)}
    if so_far["metrics"]:
        kept["metrics"] = jax.tree.map(lambda *xs: np.concatenate(xs), *so_far["metrics"])
    rest = {k: v for k, v in so_far.items() if k not in ("metrics", "done")}
    rest["seconds"] = so_far["seconds"] + time.time() - since
    manager.save(so_far["done"], args=save_args(kept, so_far["done"], rest))


def best_mean_bodies(metrics: dict, upto_steps: int,
                     first: EvoState | None = None) -> list[dict]:
    """Each run's body of the highest mean fitness over its evaluations so far, by the rule of
    the run command's body log (`bodylog.ranked`). Bodies are told apart by their
    signature, the hash of their canonical name. Every draw counts at the fitness it got, a
    diverged simulation's too (its fitness is finite, its reward zeroed:
    `FitnessResult.diverged`), as the log keeps it; a NaN (which the log refuses) makes its
    body's mean NaN, ranked below every other.

    Args:
      metrics: one method's study metrics, host-side: "signature" (T, S, N, 2) uint32,
        "fitness" (T, S, N) and "morph" (T, S, N, ...).
      upto_steps: the steps [0, upto_steps) counted.
      first: the method's `AgentState.first` (S, N), host-side: m0 as the start evaluated it,
        counted before step 0 (the log's step 0); None: not counted. A run needs one draw.

    Returns:
      per seed {"morph": the body (host-side), "mean": its mean fitness, "draws": its
      evaluations, "signature": (2,) uint32}.
    """
    sig = np.asarray(metrics["signature"][:upto_steps])
    fit = np.asarray(metrics["fitness"][:upto_steps])
    morphs = jax.tree.map(lambda x: np.asarray(x[:upto_steps]), metrics["morph"])
    if first is not None:  # one step more, before the others
        sig = np.concatenate([np.asarray(_signatures(first.morph))[None], sig])
        fit = np.concatenate([np.asarray(first.fitness)[None], fit])
        morphs = jax.tree.map(lambda a, b: np.concatenate([np.asarray(a)[None], b]),
                              first.morph, morphs)
    found = []
    for s in range(sig.shape[1]):  # a seed's draws in the order they were made
        names, seen, which = np.unique(sig[:, s].reshape(-1, 2), axis=0, return_index=True,
                                       return_inverse=True)
        which = which.reshape(-1)
        draws = np.bincount(which)
        mean = np.bincount(which, weights=fit[:, s].reshape(-1).astype(np.float64)) / draws
        step, child = np.unravel_index(seen, (sig.shape[0], sig.shape[2]))  # first draws

        def body(i, s=s, step=step, child=child):
            return jax.tree.map(lambda x: x[step[i], s, child[i]], morphs)

        (b,) = ranked(mean, draws, step, lambda i, body=body: canonical(body(i)), 1)
        found.append({"morph": body(b), "mean": float(mean[b]), "draws": int(draws[b]),
                      "signature": names[b]})
    return found
