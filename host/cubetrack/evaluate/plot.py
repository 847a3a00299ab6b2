"""Paper-style figures (matplotlib, written to files; no window is ever opened).

- :func:`plot_xy`: trajectories in the xy plane against the ground truth (paper Fig. 5).
- :func:`plot_rmse_bars`: position RMSE bars per method and camera height (paper Figs. 6–7).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

from cubetrack.io.trajectory import Trajectory


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")  # files only; chosen at call time, not at import
    import matplotlib.pyplot as plt

    return plt


def plot_xy(estimates: Mapping[str, Trajectory], ground_truth: Trajectory | None, path: str | Path,
            title: str = "") -> Path:
    """Scatter each estimate's xy positions (metres) over the ground-truth line; returns the file."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6, 6))
    if ground_truth is not None:
        ax.plot(ground_truth.positions_m[:, 0], ground_truth.positions_m[:, 1], "k-", lw=1.5, label="ground truth")
    for label, traj in estimates.items():
        ax.plot(traj.positions_m[:, 0], traj.positions_m[:, 1], ".", ms=3, label=label)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    return _save(plt, fig, ax, title, path)


def plot_rmse_bars(rmse_m: Mapping[tuple[str, str], float], path: str | Path, title: str = "",
                   ylabel: str = "position RMSE [cm]", scale: float = 100.0) -> Path:
    """Grouped bars: ``rmse_m[(group, series)]`` (e.g. (height, method)) in metres, shown in cm."""
    plt = _pyplot()
    groups = list(dict.fromkeys(g for g, _ in rmse_m))
    series = list(dict.fromkeys(s for _, s in rmse_m))
    width = 0.8 / max(1, len(series))
    fig, ax = plt.subplots(figsize=(1.5 + 1.2 * len(groups) * max(1, len(series)) * 0.5, 4))
    for j, s in enumerate(series):
        xs = [i + (j - (len(series) - 1) / 2) * width for i in range(len(groups))]
        ys = [rmse_m.get((g, s), float("nan")) * scale for g in groups]
        ax.bar(xs, ys, width=width, label=s)
    ax.set_xticks(range(len(groups)), groups)
    ax.set_ylabel(ylabel)
    ax.grid(True, axis="y", alpha=0.3)
    return _save(plt, fig, ax, title, path)


def _save(plt, fig, ax, title: str, path: str | Path) -> Path:
    """Legend, title, layout; write the figure as PNG and close it."""
    ax.legend(loc="best", fontsize=8)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
