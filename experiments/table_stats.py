"""The statistics of `compare_table`'s runs on a landscape table: regret and rank per (K, rule,
method), pairwise effects with bootstrap intervals (over seeds, and over seeds and the table's
results), and the lines `compare_table` prints (also used by `transfer`)."""

from __future__ import annotations

import numpy as np

from evojax_morph.agents import list_agents
from experiments.common import holm

RL = ("ddqn", "dqn", "qrdqn", "bootdqn", "a2c", "predictor")  # the learned designs
RULES = ("draw", "confirmed", "confirmed_early")  # what a run returns: the module's docstring
BASELINES = ("regularized_evolution", "evolution", "random")
BOOT = 10_000  # bootstrap resamples


def returned_rows(r: dict, rule: str) -> list | None:
    """The table rows of the bodies a method's runs returned under `rule` (None: not kept)."""
    if rule == "draw":
        return r["best_rows"]
    if rule == "confirmed":
        return r.get("confirmed_rows")
    return (r.get("confirmed_early") or {}).get("rows")


def bootstrap(x: np.ndarray, stat, rng, boot: int = BOOT) -> list[float]:
    """[stat, 2.5%, 97.5%] of `stat` over seeds resampled with replacement."""
    idx = rng.integers(0, len(x), (boot, len(x)))
    values = stat(x[idx], axis=1)
    return [float(stat(x)), *np.quantile(values, [0.025, 0.975]).tolist()]


def effect(a, b, true, table_means, rng) -> dict:
    """True fitness of the bodies returned, method a against method b.

    Args:
      a, b: (seeds,) int, the table rows of the bodies each run of a and b returned.
      true: (T,) the table's means; table_means: (BOOT, T) the same with each body's S results
        resampled with replacement.
    Returns:
      mean(true[a]) - mean(true[b]) with two 95% bootstrap intervals, over seeds (the table's
      means taken as exact) and over seeds and the table's results at once (the means are
      estimates too), and P(a seed of a beats one of b), ties half.
    """
    ia = rng.integers(0, len(a), (len(table_means), len(a)))
    ib = rng.integers(0, len(b), (len(table_means), len(b)))
    d = true[a[ia]].mean(1) - true[b[ib]].mean(1)
    lo, hi = np.quantile(d, [0.025, 0.975])
    d_table = np.take_along_axis(table_means, a[ia], 1).mean(1) - np.take_along_axis(
        table_means, b[ib], 1).mean(1)
    tlo, thi = np.quantile(d_table, [0.025, 0.975])
    fa, fb = true[a][:, None], true[b][None]
    beats = np.mean((fa > fb) + 0.5 * (fa == fb))
    # two-sided bootstrap p of the difference, over seeds and the table's results
    p = min(1.0, 2 * min(np.mean(d_table <= 0), np.mean(d_table >= 0)) + 1 / len(d_table))
    return {"diff": float(true[a].mean() - true[b].mean()), "ci": [float(lo), float(hi)],
            "significant": bool(lo > 0 or hi < 0), "ci_with_table": [float(tlo), float(thi)],
            "significant_with_table": bool(tlo > 0 or thi < 0), "p_beats": float(beats),
            "p": float(p)}


def pairs(methods) -> list[tuple[str, str]]:
    """The comparisons: every RL agent against every baseline (plain and bootstrapped DQN also
    against Double-DQN), and the baselines against each other, in that order."""
    out = [(a, b) for a in RL
           for b in (*BASELINES, *(("ddqn",) if a in ("dqn", "bootdqn") else ()))]
    out += [(a, b) for i, a in enumerate(BASELINES) for b in BASELINES[i + 1:]]
    return [(a, b) for a, b in out if a in methods and b in methods]


def resampled_means(fitness: np.ndarray, rng, boot: int = BOOT) -> np.ndarray:
    """(boot, T) each body's mean over its measured results resampled with replacement (a row
    holds its results first, NaN after: the deep rows hold more)."""
    counts = (~np.isnan(fitness)).sum(1)
    out = np.empty((boot, len(fitness)))
    for r, n in enumerate(counts):
        out[:, r] = fitness[r, rng.integers(0, n, (boot, n))].mean(1)
    return out


def stats(results: dict, fitness: np.ndarray) -> dict:
    """Per (K, rule, method): regret and rank summaries; per (K, rule): the pairwise effects.
    `fitness`: the table's (T, S) results, NaN where a row has fewer."""
    rng = np.random.default_rng(0)
    true = np.nanmean(fitness, 1)
    table_means = resampled_means(fitness, rng)  # (BOOT, T)
    order = np.argsort(-true)
    gap = table_means[:, order[0]] - table_means[:, order[1]]
    behind = table_means[:, order[0], None] - table_means  # (BOOT, T): the best minus each
    tied = np.quantile(behind, 0.025, axis=0) <= 0  # 95% interval of the difference holds 0
    out = {"table_top2_gap": {"diff": float(true[order[0]] - true[order[1]]),
                              "ci": np.quantile(gap, [0.025, 0.975]).tolist(),
                              "p_first_better": float(np.mean(gap > 0)),
                              "results": [int(n) for n in (~np.isnan(fitness[order[:2]])).sum(1)]},
           "indistinguishable_from_best": [int(r) for r in order if tied[r]]}
    best = float(true.max())
    ranked = np.sort(true)[::-1]
    for k, by_method in results.items():
        out[k] = {}
        for rule in RULES:
            rows = {m: np.asarray(rw) for m, r in by_method.items()
                    if (rw := returned_rows(r, rule)) is not None}
            by = out[k][rule] = {}
            for m, rw in rows.items():
                f, r = true[rw], by_method[m]
                regret = best - f
                by[m] = {
                    "median_regret": bootstrap(regret, np.median, rng),
                    "mean_regret": bootstrap(regret, np.mean, rng),
                    "ranks": [int(np.searchsorted(-ranked, -x, "left")) + 1 for x in f],
                    "found_optimum": int(np.sum(f == best)),
                    "indistinguishable": int(tied[rw].sum()),  # returned a body tied with the best
                    "median_best_visited_regret": float(np.median(best - np.asarray(
                        r["best_visited"]))),
                    "median_distinct_bodies": float(np.median(r["distinct_bodies"])),
                    "seconds_per_run": r["seconds"] / len(f),
                }
            effects = {f"{a}-{b}": effect(rows[a], rows[b], true, table_means, rng)
                       for a, b in pairs(rows)}
            holm(effects)
            by.update(effects)
    return out


def table_lines(summary: dict) -> list[str]:
    st = summary["stats"]
    gap = st["table_top2_gap"]
    lines = [f"the table's best body minus its second: {gap['diff']:.1f} "
             f"[{gap['ci'][0]:.1f}, {gap['ci'][1]:.1f}], P(first better) "
             f"{gap['p_first_better']:.2f} ({gap['results']} results; each body's resampled); "
             f"{len(st['indistinguishable_from_best'])} bodies indistinguishable from the best",
             "K  rule            method                median regret [95% CI]    "
             "mean regret [95% CI]      median rank  optimum  tied  s/run"]
    for k in sorted(summary["results"], key=int):
        for rule in RULES:
            by = st[k][rule]
            for m in list_agents():
                if m not in by:
                    continue
                r = by[m]
                med, mean = r["median_regret"], r["mean_regret"]
                lines.append(
                    f"{k:<2} {rule:<15} {m:<21} {med[0]:6.1f} [{med[1]:6.1f}, {med[2]:6.1f}]     "
                    f"{mean[0]:6.1f} [{mean[1]:6.1f}, {mean[2]:6.1f}]     "
                    f"{np.median(r['ranks']):5.1f}     {r['found_optimum']:2d}/{len(r['ranks'])}"
                    f"  {r['indistinguishable']:2d}  {r['seconds_per_run']:6.2f}"
                )
            for pair, e in by.items():
                if "-" in pair:
                    star = "*" if e["significant_holm"] else " "
                    lines.append(
                        f"{k:<2} {rule:<15} {pair:<34} diff {e['diff']:6.1f} "
                        f"[{e['ci'][0]:6.1f}, {e['ci'][1]:6.1f}] with the table's noise "
                        f"[{e['ci_with_table'][0]:6.1f}, {e['ci_with_table'][1]:6.1f}] "
                        f"p {e['p']:.4f}, Holm {e['p_holm']:.4f}{star} "
                        f"P(beats) {e['p_beats']:.2f}")
    return lines
