"""A gait family's trade-off: displacement per cycle and efficiency against a swept target."""

from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.figure import Figure

__all__ = ["plot_gait_family"]


def plot_gait_family(
    target: np.ndarray,
    displacement: np.ndarray,
    effort: np.ndarray,
    *,
    target_label: str = "torque bound [N m]",
    displacement_label: str = "displacement per cycle [m]",
    converged: np.ndarray | None = None,
    title: str | None = None,
    figsize: tuple[float, float] = (11.0, 3.8),
) -> Figure:
    """A family of gaits solved over a swept target (a torque bound, a period, a prescribed
    displacement), in two panels: the displacement per cycle against the effort per cycle
    ``int |u / scale|^2 dt`` (the trade-off curve, coloured by the target), and the efficiency
    (displacement per unit effort) against the target.

    Args:
        target: the swept values (B,).
        displacement: displacement (or rotation) per cycle of each member (B,).
        effort: effort per cycle of each member (B,).
        target_label, displacement_label: axis labels with units.
        converged: (B,) booleans; members that did not converge are drawn as crosses.
        title: figure title.
        figsize: figure size (inches).

    Returns:
        The figure.
    """
    target, displacement, effort = (np.asarray(x, float) for x in (target, displacement, effort))
    ok = np.ones(target.shape, bool) if converged is None else np.asarray(converged, bool)
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=figsize)
    sc = ax0.scatter(effort[ok], displacement[ok], c=target[ok], cmap="viridis", s=18)
    ax0.plot(effort[ok], displacement[ok], color="0.6", lw=0.8, zorder=0)
    if np.any(~ok):
        ax0.scatter(effort[~ok], displacement[~ok], marker="x", color="r", label="not converged")
        ax0.legend(fontsize=8)
    fig.colorbar(sc, ax=ax0, label=target_label)
    ax0.set(xlabel="effort per cycle", ylabel=displacement_label, title="trade-off")
    with np.errstate(divide="ignore", invalid="ignore"):
        eff = displacement / effort
    ax1.plot(target[ok], eff[ok], "o-", ms=3)
    ax1.set(xlabel=target_label, ylabel="displacement per unit effort", title="efficiency")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return fig
