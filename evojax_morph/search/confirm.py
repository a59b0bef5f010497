"""Confirming a search's best bodies: fresh evaluations of a few candidates, with an interval.

With a noisy fitness the highest single draw of a search is more often a lucky draw than the
best body (docs/benchmarks.md: two evaluations of the 20 best Bad Walker bodies rank them with
a Spearman correlation of 0.10), and with inheritance a body's fitness in a run also carries the
training its lineage gave it. `confirm` evaluates each candidate again from scratch: C
independent evaluations (controllers trained from fresh initialisations, no inheritance; on the
table fitness C fresh draws), all in one batched fitness call, and reports each body's mean
with a 95% t-interval. A run's confirm stage (`run.confirm_stage`) ends with it, on the bodies of
the highest mean in its body log.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import scipy.stats

from evojax_morph.fitnesses import FitnessConfig
from evojax_morph.fitnesses.batched import evaluate
from evojax_morph.morphology import Morphology
from evojax_morph.ppo import Params
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
