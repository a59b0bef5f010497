"""Does a predictor that starts from what another run learned find better bodies at equal new
evaluations? (issue 77, "a policy that transfers")

Reads three `compare_table` data files of the same target table, seeds and keys: the predictor
started from a saved ensemble (--transfer, its settings file names the source), the same
predictor from fresh networks on the same machine (--control), and the held-out file (--heldout,
for regularized evolution's runs and the predictor's on another device, as references). For
each K both hold and each budget (10,000 evaluations: the confirmed rule; 2,000: the confirmed
rule taken early), the mean regret of the returned bodies with a bootstrap 95% interval over
seeds, and transfer minus control (and minus regularized evolution) in mean true fitness with
`table_stats.effect`'s intervals (over seeds and the table's results), Holm over every
difference at once. The figure: the regret of each run's best-so-far body (the draw rule) against
evaluations, median and quartiles over seeds, per K.

  python -m experiments.transfer   # the defaults: the Length Walker's walking table's files
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from evojax_morph.fitnesses import FitnessConfig
from evojax_morph.fitnesses import table as table_fitness
from evojax_morph.spaces import make_space
from experiments.common import band, holm, plt, save
from experiments.table_stats import effect, resampled_means, returned_rows

RULES = {"10000": "confirmed", "2000": "confirmed_early"}  # evaluations a run: the rule


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    for name, path in (("transfer", "transfer/compare_table_length_walker_walk_transfer"),
                       ("control", "transfer/compare_table_length_walker_walk_transfer_control"),
                       ("heldout", "heldout/compare_table_length_walker_walk_heldout")):
        parser.add_argument(f"--{name}", type=Path, default=Path(f"docs/figures/{path}.json"))
    parser.add_argument("--out", type=Path, default=Path("docs/figures/transfer"))
    args = parser.parse_args(argv)
    files = {n: json.loads(getattr(args, n).read_text()) for n in ("transfer", "control",
                                                                    "heldout")}
    s = files["transfer"]["settings"]
    space = make_space(s["space"])
    table, _ = table_fitness.load(space, FitnessConfig(kind="table", table=s["table"]))
    true = np.nanmean(table.fitness, 1)
    rng = np.random.default_rng(0)
    table_means = resampled_means(table.fitness, rng)
    runs = {"transfer": ("transfer", "predictor"), "control": ("control", "predictor"),
            "predictor_heldout": ("heldout", "predictor"),
            "regularized_evolution": ("heldout", "regularized_evolution")}
    ks = [k for k in files["transfer"]["results"] if k in files["control"]["results"]]
    summary = {"question": __doc__.splitlines()[0], "table": s["table"], "space": s["space"],
               "seeds": s["seeds"], "source": files["transfer"]["tuning"].get("transfer"),
               "settings": {n: files[f]["results"][ks[0]][m]["agent_settings"]
                            for n, (f, m) in runs.items()},
               "devices": {n: files[f]["results"][ks[0]][m].get("device", files[f].get("device"))
                           for n, (f, m) in runs.items()},
               "regret": {}, "effects": {}}
    effects = {}
    for k in ks:
        for budget, rule in RULES.items():
            rows = {n: np.asarray(returned_rows(files[f]["results"][k][m], rule))
                    for n, (f, m) in runs.items()}
            summary["regret"][f"K={k}, {budget}"] = {
                n: [float(np.mean(true.max() - true[r])),
                    *np.quantile(rng.choice(true.max() - true[r], (10_000, len(r))).mean(1),
                                 [0.025, 0.975]).tolist(), int(np.sum(true[r] == true.max()))]
                for n, r in rows.items()}
            for other in ("control", "regularized_evolution"):
                effects[f"K={k}, {budget}: transfer-{other}"] = effect(
                    rows["transfer"], rows[other], true, table_means, rng)
    holm(effects)
    summary["effects"] = effects
    summary["regret_columns"] = "mean regret, its 95% bootstrap interval over seeds, seeds tied"
    fig, axes = plt.subplots(1, len(ks), figsize=(5 * len(ks), 3.6), squeeze=False)
    for ax, k in zip(axes[0], ks):
        for n in ("transfer", "control"):
            r = files[n]["results"][k]["predictor"]
            curve = true.max() - np.asarray(r["curve"])  # (chunks, seeds)
            x = np.arange(1, len(curve) + 1) * s["num_envs"] * s["chunk"]
            band(ax, x, curve, {"transfer": "predictor, transferred ensemble",
                                "control": "predictor, fresh networks"}[n])
        ax.set(title=f"K = {k}", xlabel="evaluations", ylabel="regret of the best draw's body")
        ax.legend()
    save(fig, args.out, f"transfer_{s['space']}_walk", summary)
    for key, by in summary["regret"].items():
        print(key, {n: round(v[0], 1) for n, v in by.items()})
    for key, e in effects.items():
        print(key, f"{e['diff']:.1f} [{e['ci_with_table'][0]:.1f}, {e['ci_with_table'][1]:.1f}], "
              f"Holm p {e['p_holm']:.3f}")


if __name__ == "__main__":
    main()
