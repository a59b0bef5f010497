"""Figures: a run's learning curve, the morphologies of its greedy trajectory, its confirmed
bodies."""

from __future__ import annotations

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from evojax_morph.morphology import Morphology
from evojax_morph.spaces import Space


def _figure(**kwargs) -> Figure:
    """A figure drawn by Agg, outside pyplot: no window, and matplotlib's backend left as the
    importer set it."""
    fig = Figure(**kwargs)
    FigureCanvasAgg(fig)
    return fig


def median_filter(x: np.ndarray, width: int) -> np.ndarray:
    half = max(width // 2, 0)
    return np.array([np.median(x[max(0, i - half) : i + half + 1]) for i in range(len(x))])


def plot_curve(path, steps, median, q25, q75, width: int = 9, label: str = "reward") -> None:
    """The source's style: median-filtered per-step median with a .25-.75 quantile band."""
    fig = _figure(figsize=(6, 3.5))
    ax = fig.subplots()
    ax.fill_between(
        steps,
        median_filter(q25, width),
        median_filter(q75, width),
        alpha=0.3,
        label=".25-.75 quantiles",
    )
    ax.plot(steps, median_filter(median, width), label=f"median {label}")
    ax.set_xlabel("environment step")
    ax.set_ylabel(label)
    ax.legend(loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def draw_morphology(ax, space: Space, m: Morphology) -> None:
    """The body at rest in the x-z plane: capsules as thick segments, the floor as a line."""
    layout = space.host_layout(m)
    plan = space.plan
    xlim = (-1.6, 1.6)
    fig = ax.get_figure()
    points_per_m = ax.get_position().width * fig.get_figwidth() * 72 / (xlim[1] - xlim[0])
    origin = [np.zeros(3)]
    for k, parent in enumerate(plan.limb_parent):
        origin.append(origin[parent] + layout.limb_pos[k])
    root = layout.root_pos
    for g, body in enumerate(plan.geom_body):
        if not layout.geom_active[g]:
            continue
        a = root + origin[body] + layout.geom_from[g]
        b = root + origin[body] + layout.geom_to[g]
        width = 2 * layout.geom_radius[g] * points_per_m
        ax.plot(
            [a[0], b[0]],
            [a[2], b[2]],
            color=plan.geom_rgba[g][:3],
            lw=width,
            solid_capstyle="round",
        )
    for k in np.flatnonzero(layout.limb_active):
        hip = root + origin[k + 1]
        ax.plot(hip[0], hip[2], "o", color="k", ms=3)
    ax.axhline(0, color="0.5", lw=1)
    ax.set_aspect("equal")
    ax.set_xlim(*xlim)
    ax.set_ylim(-0.1, 1.0)
    ax.axis("off")


def plot_trajectory(
    path, space: Space, morphs: list[Morphology], fitness: list[float], actions: list[str]
) -> None:
    """Every morphology of a rollout with its fitness, left to right (the source's Figure 5)."""
    n = len(morphs)
    fig = _figure(figsize=(2.6 * n, 2.4))
    axes = fig.subplots(1, n, squeeze=False)
    fig.tight_layout()  # settle the axes' sizes before drawing in data units
    for i, (ax, m) in enumerate(zip(axes[0], morphs)):
        draw_morphology(ax, space, m)
        title = f"f = {fitness[i]:.3g}"
        if i:
            title = f"{actions[i - 1]}\n" + title
        ax.set_title(title, fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def plot_confirmed(path, confirmed: list[dict]) -> None:
    """The confirmed bodies, best at the top: each one's mean over its fresh evaluations with its
    95% interval, beside its mean in the run's body log (`summary.json`'s "confirmed")."""
    n = len(confirmed)
    fig = _figure(figsize=(7, 0.9 + 0.45 * n))
    ax = fig.subplots()
    y = np.arange(n)[::-1]
    mean = np.array([c["mean"] for c in confirmed])
    lo, hi = (np.array([c["ci95"][i] for c in confirmed]) for i in (0, 1))
    ax.errorbar(mean, y, xerr=[mean - lo, hi - mean], fmt="o", capsize=3,
                label=f"fresh: mean, 95% CI ({confirmed[0]['controllers']} controllers)")
    ax.plot([c["log_mean"] for c in confirmed], y, "x", color="grey", label="run: log mean")
    ax.set_yticks(y, [c["body"] for c in confirmed], fontsize=6)
    ax.set_xlabel("fitness")
    ax.legend(loc="best", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
