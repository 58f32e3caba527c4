"""A gait at a glance: the loop in shape space, the nonholonomic momentum, and the path."""

from __future__ import annotations

from typing import Any, Literal

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.axes import Axes
from matplotlib.collections import LineCollection
from matplotlib.colors import Normalize
from matplotlib.figure import Figure

from ..systems import AbstractSystem
from ._common import check_one, failure_name, is_failed, needs_nodes, shape_label, starts_run, warn_if_failed
from ._paths import auto_scale
from ._vehicles import Drawer, VehicleArtists, vehicle_parts

__all__ = ["plot_shape_loop"]


def _coloured_line(
    ax: Axes, x: np.ndarray, y: np.ndarray, t: np.ndarray, norm: Normalize, cmap: str
) -> LineCollection:
    pts = np.stack([x, y], axis=1)
    ok = np.all(np.isfinite(pts), axis=1)
    seg = np.stack([pts[:-1], pts[1:]], axis=1)[ok[:-1] & ok[1:]]
    tm = 0.5 * (t[:-1] + t[1:])[ok[:-1] & ok[1:]]
    lc = LineCollection(seg, cmap=cmap, norm=norm, lw=2.0)
    lc.set_array(tm)
    ax.add_collection(lc)
    ax.autoscale_view()
    return lc


def plot_shape_loop(
    traj: Any,
    system: AbstractSystem,
    *,
    shape: Literal["config", "phase"] = "config",
    cmap: str = "viridis",
    title: str | None = None,
    momentum_units: str = "kg m$^2$/s",
    vehicle: Drawer | None = None,
    figsize: tuple[float, float] = (13.0, 4.0),
) -> Figure:
    """A gait in three panels, coloured by time: the loop in shape space, the nonholonomic
    momentum, and the path of the body.

    The first node is marked "start" when it is the run's start (node 0; else "first saved node");
    a failed trajectory's last finite node is marked with a cross, "failed (<result>)", instead of
    "end".

    A periodic shape motion (a closed loop in shape space) that encloses area generally moves the
    body: for the snakeboard, the rotor angle ``psi`` against the steering angle ``phi``; its
    net displacement per cycle is the loop's geometric phase (plus the momentum's drift).

    Args:
        traj: a :class:`~ldap_jax.Trajectory` (``momentum`` needs ``diagnostics=True``; without it
            the middle panel shows the shape velocities).
        system: the system (names of the shape coordinates; drawing).
        shape: ``"config"``: the first two shape coordinates ``(r_1, r_2)`` (e.g. ``(psi, phi)``);
            ``"phase"``: the last one against its rate (e.g. ``(phi, phidot)``). Systems with one
            shape coordinate always use ``"phase"``.
        cmap: colour map of time.
        title: figure title.
        momentum_units: units of ``mu``.
        vehicle: custom drawing ``q -> parts`` for the path panel.
        figsize: figure size (inches).

    Returns:
        The figure.

    Raises:
        TypeError: ``traj`` not a trajectory (e.g. a :class:`~ldap_jax.control.Solution`: roll it
            out with ``task.rollout(sol.params)``).
        ValueError: a system without shape coordinates, a bad ``shape``, a trajectory with fewer
            than two saved nodes (``save="final"``) or batched (pick one member).
    """
    if shape not in ("config", "phase"):
        raise ValueError(f"'shape' must be 'config' or 'phase', got {shape!r}")
    n = system.n_shape
    if n < 1:
        raise ValueError("plot_shape_loop needs a system with shape coordinates (n_shape >= 1)")
    if not all(hasattr(traj, f) for f in ("t", "q", "qdot")):
        hint = (
            "; for a control solution roll out its parameters: task.rollout(sol.params)"
            if hasattr(traj, "params")
            else ""
        )
        raise TypeError(
            f"'traj' must be a Trajectory (lj.simulate) with t, q and qdot, got {type(traj).__name__}{hint}"
        )
    check_one(None, traj, "traj")
    needs_nodes(None, np.shape(traj.t)[0], "traj", "a loop over time")
    warn_if_failed("traj", traj)
    t = np.asarray(traj.t, float)
    q = np.asarray(traj.q, float)
    qdot = np.asarray(traj.qdot, float)
    # the first node is the start only when it is the run's node 0 (not for a later first node)
    first = "start" if starts_run(traj, t) else f"first saved node (t = {t[0]:.3g} s)"
    failed = failure_name(traj) if is_failed(traj) else None
    names = tuple(system.shape_names)
    norm = Normalize(float(t[0]), float(t[-1]))
    fig, axes = plt.subplots(1, 3, figsize=figsize, layout="constrained")

    ax = axes[0]
    if shape == "config" and n >= 2:
        x, y = q[:, 3], q[:, 4]
        ax.set_xlabel(shape_label(names[0]))
        ax.set_ylabel(shape_label(names[1]))
        ax.set_title("gait loop in shape space", fontsize=10)
    else:
        x, y = q[:, 3 + n - 1], qdot[:, 3 + n - 1]
        ax.set_xlabel(shape_label(names[-1]))
        ax.set_ylabel(shape_label(names[-1], rate=True))
        ax.set_title(f"gait loop in the phase plane of ${names[-1]}$", fontsize=10)
    lc = _coloured_line(ax, x, y, t, norm, cmap)
    ax.plot(x[0], y[0], "o", ms=7, mfc="white", mec="k", zorder=5, label=first)
    ax.legend(fontsize=7, loc="best")
    ax.grid(True, alpha=0.3)

    ax = axes[1]
    mu = getattr(traj, "momentum", None)
    if mu is not None and np.asarray(mu).shape[-1] > 0:
        mu = np.asarray(mu)
        _coloured_line(ax, t, mu[:, 0], t, norm, cmap)
        ax.set_ylabel(rf"$\mu_1$ [{momentum_units}]")
        ax.set_title(
            r"nonholonomic momentum $\mu_1 = \langle \partial\ell/\partial\xi, e_1(r)\rangle$", fontsize=10
        )
    else:
        for i, name in enumerate(names):
            ax.plot(t, qdot[:, 3 + i], lw=1.3, label=shape_label(name, rate=True))
        ax.set_ylabel("shape velocity [rad/s or 1/s]")
        ax.set_title("shape velocities", fontsize=10)
        ax.legend(fontsize=7, loc="best")
    ax.set_xlabel("t [s]")
    ax.grid(True, alpha=0.3)

    ax = axes[2]
    _coloured_line(ax, q[:, 0], q[:, 1], t, norm, cmap)
    good = np.flatnonzero(np.all(np.isfinite(q), axis=1))
    scale = auto_scale(system, q[:, :2], fraction=0.12)
    if good.size:
        for k, alpha in ((good[0], 0.45), (good[-1], 1.0)):
            VehicleArtists(
                ax, vehicle_parts(system, q[k], scale=scale, vehicle=vehicle), color="k", alpha=alpha, lw=0.9
            )
        ax.plot(q[good[0], 0], q[good[0], 1], "o", ms=7, mfc="white", mec="k", zorder=6, label=first)
        if failed is None:
            ax.plot(q[good[-1], 0], q[good[-1], 1], "s", ms=6, mfc="none", mec="k", zorder=6, label="end")
        else:  # the failure at the last finite node, not an end
            end = q[good[-1]]
            ax.plot(end[0], end[1], "x", ms=8, color="tab:red", mew=2.0, zorder=6, label=f"failed ({failed})")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    size = "true size" if vehicle is not None or np.isclose(scale, 1.0) else f"{scale:.2g}x size"
    ends = (
        "start" if first == "start" else "first saved node",
        "end" if failed is None else "last node before the failure",
    )
    ax.set_title(f"path (vehicle at {ends[0]} and {ends[1]}, {size})", fontsize=10)
    ax.legend(fontsize=7, loc="best")
    ax.grid(True, alpha=0.3)
    fig.colorbar(lc, ax=axes, label="t [s]", shrink=0.9, pad=0.01)
    if title is not None:
        fig.suptitle(title)
    return fig
