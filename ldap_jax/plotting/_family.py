"""A gait family's trade-off: displacement per cycle and efficiency against a swept target."""

from __future__ import annotations

import re

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.figure import Figure

__all__ = ["plot_gait_family"]

#: The unit of :func:`ldap_jax.control.effort_cost`: ``int |u / scale|^2 dt``, the controls
#: divided by their scale (in the controls' units), squared, times seconds.
EFFORT_UNIT = "(scaled controls)$^2$ s"
EFFORT_LABEL = f"effort per cycle [{EFFORT_UNIT}]"


def plot_gait_family(
    target: np.ndarray,
    displacement: np.ndarray,
    effort: np.ndarray,
    *,
    target_label: str = "torque bound [N m]",
    displacement_label: str = "displacement per cycle [m]",
    effort_label: str = EFFORT_LABEL,
    efficiency_label: str | None = None,
    converged: np.ndarray | None = None,
    title: str | None = None,
    figsize: tuple[float, float] = (11.0, 3.8),
) -> Figure:
    """A family of gaits solved over a swept target (a torque bound, a period, a prescribed
    displacement), in two panels: the displacement per cycle against the effort per cycle
    ``int |u / scale|^2 dt`` (the trade-off curve, coloured by the target), and the efficiency
    (displacement per unit effort) against the target.

    The effort is :func:`ldap_jax.control.effort_cost`: the integral over the cycle of the squared
    controls divided by their scale (``task.parameterization.scale``, in the controls' units), so
    it is in (scaled controls)^2 s, i.e. seconds times the square of a dimensionless control.

    Args:
        target: the swept values (B,).
        displacement: displacement (or rotation) per cycle of each member (B,).
        effort: effort per cycle of each member (B,) ((scaled controls)^2 s).
        target_label, displacement_label: axis labels with units.
        effort_label: the effort axis' label with units.
        efficiency_label: the efficiency axis' label (default: "displacement per unit effort" in
            the unit of ``displacement_label``, e.g. m, per (scaled controls)^2 s).
        converged: (B,) booleans; members that did not converge are drawn as crosses.
        title: figure title.
        figsize: figure size (inches).

    Returns:
        The figure.

    Raises:
        ValueError: ``target``, ``displacement``, ``effort`` and ``converged`` not 1-d of one
            length.
    """
    arrays = {"target": target, "displacement": displacement, "effort": effort}
    if converged is not None:
        arrays["converged"] = converged
    shapes = {name: np.shape(x) for name, x in arrays.items()}
    n = shapes["target"][0] if len(shapes["target"]) == 1 else None
    if n is None or any(shape != (n,) for shape in shapes.values()):
        raise ValueError(
            f"'target', 'displacement', 'effort' and 'converged' must be 1-d of one length, got {shapes}"
        )
    target, displacement, effort = (np.asarray(x, float) for x in (target, displacement, effort))
    ok = np.ones(target.shape, bool) if converged is None else np.asarray(converged, bool)
    if efficiency_label is None:
        unit = re.search(r"\[([^\]]*)\]\s*$", displacement_label)
        efficiency_label = (
            f"displacement per unit effort [{unit.group(1) if unit else 'm'} / ({EFFORT_UNIT})]"
        )
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=figsize)
    sc = ax0.scatter(effort[ok], displacement[ok], c=target[ok], cmap="viridis", s=18)
    ax0.plot(effort[ok], displacement[ok], color="0.6", lw=0.8, zorder=0)
    if np.any(~ok):
        ax0.scatter(effort[~ok], displacement[~ok], marker="x", color="r", label="not converged")
        ax0.legend(fontsize=8)
    fig.colorbar(sc, ax=ax0, label=target_label)
    ax0.set(xlabel=effort_label, ylabel=displacement_label, title="trade-off")
    with np.errstate(divide="ignore", invalid="ignore"):
        eff = displacement / effort
    ax1.plot(target[ok], eff[ok], "o-", ms=3)
    ax1.set(xlabel=target_label, ylabel=efficiency_label, title="efficiency")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return fig
