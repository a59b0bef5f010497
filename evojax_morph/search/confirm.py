"""Confirming a search's best bodies: fresh evaluations of a few candidates, with an interval.

With a noisy fitness the highest single draw of a search is more often a lucky draw than the
best body (docs/benchmarks.md: two evaluations of the 20 best Bad Walker bodies rank them with
a Spearman correlation of 0.10), and with inheritance a body's fitness in a run also carries the
training its lineage gave it. `confirm` evaluates each candidate again from scratch: C
independent evaluations (controllers trained from fresh initialisations, no inheritance; on the
table fitness C fresh draws), all in one batched fitness call, and reports each body's mean
with a 95% t-interval.

A run's confirm, which its confirm stage (`run.stages.Confirm`) calls: `confirm_record` confirms
the bodies of the highest mean in its body log, the greedy trajectory's bodies in the same call
(or says why nothing is confirmed: `confirm_skipped`), `reported_best` chooses the body the run
reports as its best, and `save_controllers` gives the controllers a run keeps of it and of the
greedy trajectory.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import scipy.stats

from evojax_morph.fitnesses import FitnessConfig, get_fitness
from evojax_morph.fitnesses.batched import evaluate
from evojax_morph.morphology import Morphology
from evojax_morph.ppo import Params
from evojax_morph.records import saved_controllers
from evojax_morph.search.pipeline import Greedy, Pipeline, RunConfig
from evojax_morph.sharding import to_host
from evojax_morph.spaces import Space


@dataclasses.dataclass(frozen=True)
class Confirmed:
    """One body's fresh evaluations.

    Attributes:
      body: its canonical name (`Space.canonical`)
      morph: the body, host-side
      values: (C,) float: the fitness of each fresh evaluation (one controller each)
      diverged: (C,) bool: that evaluation's simulation diverged
      params: (C, ...) the C trained controllers (ppo), else None
      distance: (C,) metres forward in each evaluation's episodes (NaN: none ran)
      upright: (C,) the fraction of each evaluation's episodes before a fall
    """

    body: str
    morph: Morphology
    values: np.ndarray  # (C,) float
    diverged: np.ndarray  # (C,) bool
    params: Params | None  # (C, ...)
    distance: np.ndarray  # (C,) float
    upright: np.ndarray  # (C,) float

    @property
    def upright_whole(self) -> float:
        """The fraction of the evaluations upright for the whole of every episode."""
        return float(np.mean(self.upright >= 1.0))

    @property
    def mean(self) -> float:
        """The body's confirmed fitness: the mean of its C values."""
        return float(np.mean(self.values, dtype=np.float64))

    @property
    def ci95(self) -> tuple[float, float]:
        """The 95% Student-t interval of that mean over the C values."""
        return t_interval(self.values)


def t_interval(values: np.ndarray, level: float = 0.95) -> tuple[float, float]:
    """The Student-t interval of the mean of `values` (C >= 2 independent draws): mean -/+
    t_{(1 + level) / 2, C - 1} x sd / sqrt(C), sd with C - 1 degrees of freedom."""
    values = np.asarray(values, np.float64)
    if len(values) < 2:
        raise ValueError("an interval needs at least 2 values")
    half = scipy.stats.t.ppf((1 + level) / 2, len(values) - 1) * values.std(ddof=1)
    half /= np.sqrt(len(values))
    return float(values.mean() - half), float(values.mean() + half)


def confirm(
    space: Space,
    morphs: Morphology,
    key: jax.Array,
    cfg: FitnessConfig,
    controllers: int,
    mesh=None,
    ranked: bool = True,
) -> list[Confirmed]:
    """Each body evaluated `controllers` times afresh, in one batched fitness call.

    The batch holds every body `controllers` times, each copy one evaluation of `cfg` with one
    controller (`cfg.ppo.controllers` is set to 1), its own key and a fresh controller: so the C
    results of a body are independent draws of its fitness, whatever its fitness was in a run.
    On the table fitness each copy draws one stored result (so a body's C draws are with
    replacement); on the PPO fitness each trains one controller, as C controllers of a body
    would (the same B x C learners in one physics batch).

    Args:
      space: the space the bodies belong to.
      morphs: N candidate bodies (`em.stack`), arrays of shape (N, max_nodes, ...).
      key: one PRNG key; evaluation c of body n uses its (n * C + c)-th split. Take one no
        other evaluation used (`run` folds a constant into its seed).
      cfg: the fitness.
      controllers: C >= 2 evaluations per body.
      mesh: the devices to split the N x C batch across (default: all).
      ranked: sort the results by mean; False: in the order of `morphs`.
    Returns:
      N `Confirmed`, best mean first (equal means in the order of `morphs`), or in the order
      of `morphs`.
    """
    if controllers < 2:
        raise ValueError(f"confirm needs at least 2 controllers per body, got {controllers}")
    n = morphs.active.shape[0]
    one = cfg.with_controllers(1)
    copies = jax.tree.map(lambda x: jnp.repeat(jnp.asarray(x), controllers, axis=0), morphs)
    res = evaluate(space, copies, key, one, mesh=mesh)
    res = to_host(res)
    per_body = lambda x: np.asarray(x).reshape((n, controllers) + x.shape[1:])  # noqa: E731
    values, diverged = per_body(res.fitness), per_body(res.diverged)
    distance, upright = per_body(res.distance), per_body(res.upright)
    params = None if res.params is None else jax.tree.map(per_body, res.params)
    host = jax.device_get(morphs)  # the caller's, the same on every process
    found = []
    for i in range(n):
        morph = jax.tree.map(lambda x, i=i: np.asarray(x[i]), host)
        found.append(Confirmed(
            body=space.canonical(morph),
            morph=morph,
            values=values[i],
            diverged=diverged[i],
            params=None if params is None else jax.tree.map(lambda x, i=i: x[i], params),
            distance=distance[i],
            upright=upright[i],
        ))
    return rank(found) if ranked else found


def rank(found: list[Confirmed]) -> list[Confirmed]:
    """`found` sorted by mean, best first; stable: equal means keep their order."""
    return sorted(found, key=lambda c: -c.mean)


CONFIRM_SALT = 0x636F6E66  # a run's confirm key: fold_in(PRNGKey(seed), CONFIRM_SALT)


def confirm_skipped(cfg) -> str | None:
    """Why the confirm stage evaluates nothing (confirmed.json's note), None where it does: the
    one place this is decided."""
    if cfg.confirm == 0:
        return "not run (--confirm 0): the best body is the highest single draw, a noisy maximum"
    if get_fitness(cfg.fitness).deterministic:
        return (f"not run: the {cfg.fitness} fitness is deterministic, so an evaluation again "
                "gives the same values; the best body is the highest single draw")
    return None


def kept_greedy(record: dict, greedy: Greedy, space) -> Greedy | None:
    """`greedy` with the results confirmed.json's `record` kept for its bodies (a --resume of
    a finished run, which then evaluates them again no more than the rest: its summary and
    trajectory stay the first finish's, and controllers/stepT as saved then), or None where the
    record holds none for these bodies."""
    entries = record.get("greedy") or []
    if [e["body"] for e in entries] != [space.canonical(m) for m in greedy.morphs]:
        return None
    return greedy._replace(fitness=[e["mean"] for e in entries], params=None,
                           controllers=record["controllers"], confirmed=True)


def greedy_bodies(p: Pipeline) -> int:
    """The bodies of the greedy trajectory, m0 first; 0 for a baseline (no policy to roll out)."""
    return 0 if p.agent.scores is None else p.greedy_env.horizon + 1


def confirm_record(p: Pipeline, cfg: RunConfig, step: int, candidates: list,
                   greedy: list | None = None, kept: dict | None = None, stale: bool = False,
                   log=print):
    """The bodies of a run's log confirmed, the greedy trajectory's `greedy` in the same call;
    every process calls it.

    The `cfg.confirm` distinct bodies of the highest mean in the body log (`candidates`:
    (`bodylog.best_bodies` entry, shape JSON) pairs, best first: ties to the body evaluated
    more often, then to the one seen first), then the bodies `greedy`, are each evaluated
    `cfg.confirm_controllers` times from scratch, in one fitness call (`confirm`): fresh
    controllers, no inheritance, keys from `fold_in(PRNGKey(seed), CONFIRM_SALT)`, which no
    other part of the run uses. The greedy bodies only ride along (one call's latency instead
    of two, issue 61): they enter neither the record nor the choice of the best. Skipped, with a
    note saying why (`confirm_skipped`); not done again where confirmed.json's record `kept`
    was kept from the run's finish at this step with these settings and this log (a --resume
    of a finished run, `run.resume.Start.kept`); `stale`: a confirmed.json that is not is
    there (it is written again).

    Returns:
      (record, top, joined): record is what confirmed.json keeps (env_steps, bodies,
      controllers, "confirmed": summary entries best first, "confirm_note"); top is the best
      `Confirmed` when it was evaluated now, else None; joined the `Confirmed` of each body of
      `greedy`, in its order, when evaluated now, else None.
    """
    n, c = cfg.confirm, cfg.confirm_controllers
    record = {"env_steps": step, "bodies": n, "controllers": c, "confirmed": []}
    if kept is not None:
        log("confirm: done when the run finished, kept (confirmed.json)")
        return kept, None, None
    if stale:
        log("confirm: confirmed.json is not of this body log at this step with these settings, "
            "so the bodies are confirmed again")
    record["confirm_note"] = confirm_skipped(cfg)
    if record["confirm_note"]:
        if n:  # --confirm 0 said so itself
            log(f"confirm: {record['confirm_note']}")
        return record, None, None
    ranked = [entry for entry, _ in candidates]
    also = "" if not greedy else f", with the greedy trajectory's {len(greedy)} bodies"
    log(f"confirm: the {len(ranked)} bodies of the highest mean{also}, {c} fresh evaluations "
        "each...")
    key = jax.random.fold_in(jax.random.PRNGKey(cfg.seed), CONFIRM_SALT)
    bodies = [p.space.from_json(shape) for _, shape in candidates] + list(greedy or [])
    morphs = jax.tree.map(lambda *x: np.stack(x), *bodies)
    every = confirm(p.space, morphs, key, p.fitness, c, ranked=False)
    found, joined = rank(every[:len(ranked)]), every[len(ranked):]
    in_log = {b["body"]: b for b in ranked}
    record["confirmed"] = [confirmed_entry(f, in_log[f.body]) for f in found]
    record["confirm_note"] = (
        f"the {len(found)} bodies of the highest mean in the body log, each evaluated again {c} "
        "times from scratch (fresh keys and controllers, no inheritance) in one fitness call; "
        f"mean and 95% Student-t interval over the {c}"
    )
    if greedy:  # the greedy trajectory's, for a --resume to keep (`kept_greedy`)
        record["greedy"] = [{"body": f.body, "mean": f.mean,
                             "values": [float(v) for v in f.values]} for f in joined]
    return record, found[0], None if greedy is None else joined


def greedy_confirmed(greedy: Greedy, joined: list[Confirmed]) -> Greedy:
    """The walked `greedy` with its bodies' results `joined` from the confirm stage's call: each
    body's fitness the mean over its C fresh controllers, its controllers best first."""
    return greedy._replace(fitness=[f.mean for f in joined],
                           params=[best_first(f) for f in joined],
                           controllers=len(joined[0].values), confirmed=True)


def best_first(found: Confirmed):
    """The C controllers of `found`, best first (best.gif replays the 0th; ties in their
    order); None where the fitness trains none."""
    if found.params is None:
        return None
    order = np.argsort(-found.values, kind="stable")
    return jax.tree.map(lambda x: x[order], found.params)


def confirmed_entry(found: Confirmed, logged: dict) -> dict:
    """confirmed.json's (and summary.json's) entry of a confirmed body, with its mean and count
    in the body log."""
    return {
        "body": found.body,
        "mean": found.mean,
        "ci95": list(found.ci95),
        "controllers": len(found.values),
        "values": [float(v) for v in found.values],
        "diverged": int(found.diverged.sum()),
        "log_mean": logged["mean_fitness"],
        "log_evaluations": logged["evaluations"],
        **gait_entry(found),
    }


def gait_entry(found: Confirmed) -> dict:
    """A confirmed body's gait over its fresh evaluations: mean distance (m) and upright (the
    fraction of an episode before a fall), the fraction of evaluations upright the whole
    episode, and each evaluation's; None where the fitness measures no gait."""
    if not np.isfinite(found.distance).all():
        return {"distance": None, "upright": None, "upright_whole": None}
    return {
        "distance": float(found.distance.mean()),
        "upright": float(found.upright.mean()),
        "upright_whole": found.upright_whole,
        "distances": [round(float(d), 4) for d in found.distance],
        "uprights": [round(float(u), 4) for u in found.upright],
    }


def reported_best(p: Pipeline, record: dict, top: Confirmed | None, draw: tuple,
                  kept_best=None):
    """The body a run reports as its best: (morph, fitness, controllers, their fitness config),
    chosen here alone.

    The confirmed best `top` with its C fresh controllers, best first (best.gif replays the
    0th); else the best of `record` confirmed when the run first finished, `kept_best` (its
    body and controllers read back: `Start.kept_best`); else, nothing confirmed, `draw`: the
    highest single draw's (morph, fitness, controllers).
    """
    if top is not None:
        params = best_first(top)
        cfg = p.fitness if params is None else p.fitness.with_controllers(len(top.values))
        return top.morph, top.mean, params, cfg
    if record["confirmed"]:
        morph, saved = kept_best
        if saved is None:  # a fitness that trains no controllers
            return morph, record["confirmed"][0]["mean"], None, p.fitness
        return morph, record["confirmed"][0]["mean"], saved.params, saved.fitness
    return (*draw, p.fitness)


def save_controllers(p: Pipeline, seed: int, best, best_fitness: float, best_params,
                     greedy: Greedy | None, best_cfg=None) -> dict:
    """The controllers of the best body ("best") and of the evaluated greedy trajectory's
    ("stepT"), for a fitness that trains controllers, by name; None for one kept from the
    first finish (`kept_greedy`). best_cfg: the fitness config the best body's controllers
    were trained under (default the run's; the confirm stage's has C controllers); the greedy
    bodies' has `greedy.controllers` (None: the run's)."""
    if not saved_controllers.has_controllers(p.fitness):
        return {}
    bodies = [("best", best, best_params, best_fitness, best_cfg or p.fitness)]
    if greedy is not None:
        k = greedy.controllers
        greedy_cfg = p.fitness if k is None else p.fitness.with_controllers(k)
        bodies += [(f"step{t}", m, params, f, greedy_cfg) for t, (m, params, f)
                   in enumerate(zip(greedy.morphs, greedy.params or [None] * len(greedy.morphs),
                                    greedy.fitness))]
    saved = {}
    for name, morph, params, fitness, fit_cfg in bodies:
        label = name if name == "best" else f"step {name[4:]}"
        saved[name] = None if params is None and name != "best" else (
            saved_controllers.SavedController(p.space, fit_cfg, seed, morph, params, fitness,
                                              label))
    return saved

