"""Matplotlib figures: paths with the vehicle drawn, and diagnostics over time.

Imported only where used (``import ldap_jax.plotting``), so the core imports without matplotlib.
"""

from __future__ import annotations

from collections.abc import Mapping

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.patches import Polygon

from .systems import AbstractSystem, Car, Snakeboard

__all__ = ["draw_vehicle", "plot_paths", "plot_diagnostics"]


def _rect(cx, cy, heading, length, width):
    c, s = np.cos(heading), np.sin(heading)
    pts = np.array(
        [
            [length / 2, width / 2],
            [-length / 2, width / 2],
            [-length / 2, -width / 2],
            [length / 2, -width / 2],
        ]
    )
    return pts @ np.array([[c, s], [-s, c]]) + np.array([cx, cy])


def draw_vehicle(ax, system: AbstractSystem, q, *, color="k", alpha=1.0, scale=1.0):
    """Draw the vehicle at configuration ``q = (x, y, theta, r1, r2)``.

    Car: body from the rear axle (x, y) forward by ``l``, front wheels steered by
    ``atan(sigma)``. Snakeboard: the board of length ``2 l``, wheel sets at ``-l`` steered by
    ``+phi`` and at ``+l`` steered by ``-phi`` (the constraints' geometry).
    """
    x, y, th = float(q[0]), float(q[1]), float(q[2])
    c, s = np.cos(th), np.sin(th)
    if isinstance(system, Car):
        ell = float(system.l) * scale
        width, wheel = 0.5 * ell, 0.25 * ell
        body = _rect(x + c * ell / 2, y + s * ell / 2, th, 1.3 * ell, width)
        ax.add_patch(Polygon(body, closed=True, fill=False, ec=color, alpha=alpha, lw=1.2))
        steer = np.arctan(float(q[4]))
        for side in (-1, 1):
            rx, ry = x - s * side * width / 2, y + c * side * width / 2
            ax.add_patch(Polygon(_rect(rx, ry, th, wheel, wheel / 3), closed=True, color=color, alpha=alpha))
            fx, fy = rx + c * ell, ry + s * ell
            ax.add_patch(
                Polygon(_rect(fx, fy, th + steer, wheel, wheel / 3), closed=True, color=color, alpha=alpha)
            )
    elif isinstance(system, Snakeboard):
        ell = float(system.l) * scale
        phi = float(q[4])
        ax.plot([x - c * ell, x + c * ell], [y - s * ell, y + s * ell], color=color, alpha=alpha, lw=2.5)
        wheel = 0.45 * ell
        for pos, steer in ((-ell, phi), (ell, -phi)):
            ax.add_patch(
                Polygon(
                    _rect(x + c * pos, y + s * pos, th + steer, wheel, wheel / 4),
                    closed=True,
                    color=color,
                    alpha=alpha,
                )
            )
        ax.plot([x], [y], "o", color=color, alpha=alpha, ms=3)
    else:
        ax.plot([x], [y], "o", color=color, alpha=alpha)
        ax.arrow(x, y, 0.1 * c, 0.1 * s, color=color, alpha=alpha, width=0.005)


def plot_paths(
    ax,
    system: AbstractSystem,
    paths: Mapping[str, np.ndarray],
    *,
    draw: str | None = None,
    n_draw: int = 6,
    styles: Mapping[str, dict] | None = None,
):
    """Plot the (x, y) paths of several trajectories, drawing the vehicle along ``paths[draw]``.

    Args:
        ax: matplotlib axes.
        system: the system (for drawing).
        paths: label -> configurations (N+1, d).
        draw: which path gets the vehicle drawn (default: the first).
        n_draw: how many vehicle poses to draw.
        styles: label -> keyword arguments for ``ax.plot``.
    """
    styles = styles or {}
    for i, (label, q) in enumerate(paths.items()):
        q = np.asarray(q)
        ax.plot(q[:, 0], q[:, 1], label=label, **{"lw": 1.5 if i == 0 else 1.0, **styles.get(label, {})})
    draw = draw or next(iter(paths))
    q = np.asarray(paths[draw])
    valid = np.flatnonzero(np.all(np.isfinite(q), axis=1))
    for j, k in enumerate(np.linspace(valid[0], valid[-1], n_draw).astype(int)):
        draw_vehicle(ax, system, q[k], alpha=0.25 + 0.75 * j / max(n_draw - 1, 1))
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.legend(loc="best", fontsize=8)
    return ax


def plot_diagnostics(trajectories: Mapping[str, object], *, axes=None):
    """Energy balance ``E - E0 - W``, nonholonomic momentum and constraint residual over time."""
    has_momentum = any(np.asarray(t.momentum).shape[-1] > 0 for t in trajectories.values())
    n = 3 if has_momentum else 2
    if axes is None:
        _, axes = plt.subplots(1, n, figsize=(4.2 * n, 3.2))
    for label, traj in trajectories.items():
        t = np.asarray(traj.t)
        axes[0].plot(t, np.asarray(traj.energy_balance), label=label)
        axes[1].semilogy(t, np.maximum(np.asarray(traj.constraint_residual), 1e-18), label=label)
        if np.asarray(traj.momentum).shape[-1] > 0:
            axes[2].plot(t, np.asarray(traj.momentum)[:, 0], label=label)
    axes[0].set_title("work-energy balance $E - E_0 - W$")
    axes[1].set_title(r"constraint residual $|\omega(q)\dot q|$")
    if has_momentum:
        axes[2].set_title(r"momentum $\mu_1$")
    for ax in axes:
        ax.set_xlabel("t [s]")
        ax.legend(fontsize=7)
    return axes
