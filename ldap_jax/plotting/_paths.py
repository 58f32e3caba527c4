"""Paths in the plane with the vehicle drawn small along one of them, and position errors over
time against a reference."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Literal

import numpy as np
from matplotlib.axes import Axes
from matplotlib.lines import Line2D

from ..systems import AbstractSystem
from ._common import as_tq, finite_positive, is_reference, reference_nodes, style_for, warn_if_failed
from ._vehicles import Drawer, VehicleArtists, vehicle_parts, vehicle_size

__all__ = ["plot_paths", "plot_position_error", "auto_scale"]


def auto_scale(system: AbstractSystem, positions: np.ndarray, fraction: float = 0.12) -> float:
    """Drawing scale (at most 1, true size) at which the vehicle's length is ``fraction`` of the
    diagonal of the paths' bounding box ``positions`` (M, 2) (m)."""
    pts = positions[np.all(np.isfinite(positions), axis=1)]
    if pts.size == 0:
        return 1.0
    diag = float(np.hypot(*(pts.max(axis=0) - pts.min(axis=0))))
    if diag <= 0.0:
        return 1.0
    return min(1.0, fraction * diag / vehicle_size(system))


def plot_paths(
    ax: Axes,
    system: AbstractSystem,
    paths: Mapping[str, Any],
    *,
    draw: str | None = None,
    n_draw: int = 4,
    styles: Mapping[str, dict] | None = None,
    scale: float | str = "auto",
    times: Any = None,
    markers: bool = True,
    vehicle: Drawer | None = None,
    legend: bool | Literal["markers"] = True,
    legend_loc: str = "best",
) -> Axes:
    """Plot the ``(x, y)`` paths of several trajectories, with the vehicle drawn small and sparse
    along one of them, a start marker and an end marker per path.

    The vehicle poses are drawn at ``n_draw`` evenly spaced nodes, each labelled with its time
    (when known), fainter at earlier times; the legend says which path carries them and at what
    drawing scale. Reference curves (labels with "reference") are drawn thick and light under
    the others.

    Args:
        ax: matplotlib axes.
        system: the system (for drawing the vehicle).
        paths: label -> configurations (M, d) (m, rad), or a :class:`~ldap_jax.Trajectory` /
            :class:`~ldap_jax.Solution` (then its times label the drawn poses).
        draw: the path that carries the drawn vehicle (default: the first).
        n_draw: number of vehicle poses (0: none).
        styles: label -> keyword arguments for ``Axes.plot`` (override the defaults).
        scale: drawing scale of the vehicle (1: true size), or ``"auto"``: the vehicle's length is
            12% of the paths' extent (at most true size).
        times: times (s) of the ``draw`` path's nodes (default: from the trajectory, if any).
        markers: mark the start (circle) and every path's end (square).
        vehicle: custom drawing ``q -> parts`` (see :func:`~ldap_jax.plotting.vehicle_parts`).
        legend: ``True``: a legend of the paths and the markers; ``"markers"``: of the vehicle,
            start and end markers only (for a figure-level legend of the paths); ``False``: none.
        legend_loc: legend location (matplotlib's ``loc``).

    Returns:
        ``ax``.
    """
    if not isinstance(paths, Mapping):
        raise TypeError(
            f"'paths' must be a mapping label -> trajectory, e.g. {{'RDP': traj}}, got {type(paths)}"
        )
    if not paths:
        raise ValueError("'paths' is empty")
    styles = styles or {}
    for label, value in paths.items():
        warn_if_failed(label, value)
    data = {label: as_tq(value) for label, value in paths.items()}
    draw = draw if draw is not None else next(iter(paths))
    if draw not in data:
        raise ValueError(f"'draw' must be one of {list(paths)}, got {draw!r}")
    for i, (label, (_, q)) in enumerate(data.items()):
        kw = {"lw": 1.4, **style_for(label, i), **styles.get(label, {})}
        (line,) = ax.plot(q[:, 0], q[:, 1], label=label, **kw)
        if markers:
            good = np.flatnonzero(np.all(np.isfinite(q[:, :2]), axis=1))
            if good.size:
                end = q[good[-1]]
                ax.plot(end[0], end[1], "s", ms=5, mfc="none", mec=line.get_color(), mew=1.3, zorder=6)
    t_draw, q_draw = data[draw]
    t_draw = np.asarray(times, float) if times is not None else t_draw
    if markers:
        ax.plot(q_draw[0, 0], q_draw[0, 1], "o", ms=8, mfc="white", mec="k", mew=1.5, zorder=7)
    all_xy = np.concatenate([q[:, :2] for _, q in data.values()])
    if scale == "auto":
        scale = auto_scale(system, all_xy)
    valid = np.flatnonzero(np.all(np.isfinite(q_draw), axis=1))
    handles = []
    if n_draw > 0 and valid.size:
        nodes = np.unique(np.linspace(valid[0], valid[-1], n_draw).round().astype(int))
        for j, k in enumerate(nodes):
            alpha = 0.35 + 0.65 * j / max(len(nodes) - 1, 1)
            parts = vehicle_parts(system, q_draw[k], scale=float(scale), vehicle=vehicle)
            VehicleArtists(ax, parts, color="k", alpha=alpha, lw=0.9, zorder=5)
            if t_draw is not None:
                ax.annotate(
                    f"{t_draw[k]:.3g} s",
                    (q_draw[k, 0], q_draw[k, 1]),
                    xytext=(9, -12),
                    textcoords="offset points",
                    fontsize=7,
                    color="0.2",
                    zorder=8,
                    bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none", "alpha": 0.75},
                )
        what = "at the labelled times" if t_draw is not None else f"at {len(nodes)} nodes"
        size = (
            "true size"
            if vehicle is not None or np.isclose(scale, 1.0)
            else f"drawn at {float(scale):.2g}x size"
        )
        handles.append(
            Line2D(
                [], [], color="k", lw=0.9, label=f"vehicle on {draw!r} {what}\n(fainter = earlier; {size})"
            )
        )
    if markers:
        handles.append(
            Line2D([], [], ls="none", marker="o", ms=7, mfc="white", mec="k", mew=1.5, label="start")
        )
        handles.append(
            Line2D([], [], ls="none", marker="s", ms=5, mfc="none", mec="0.3", mew=1.3, label="end")
        )
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.grid(True, alpha=0.25)
    if legend:
        line_handles = ax.get_legend_handles_labels()[0] if legend is True else []
        ax.legend(handles=line_handles + handles, loc=legend_loc, fontsize=7, framealpha=0.85)
    return ax


def plot_position_error(
    ax: Axes,
    reference: Any,
    trajectories: Mapping[str, Any],
    *,
    styles: Mapping[str, dict] | None = None,
    legend: bool = True,
) -> Axes:
    """Position error ``|(x, y) - (x, y)_ref|`` (m) over time, one curve per trajectory, log scale.

    Args:
        ax: matplotlib axes.
        reference: the reference (a :class:`~ldap_jax.Solution` or anything with ``.t``, ``.q``)
            sampled at (a superset of) every trajectory's node times.
        trajectories: label -> :class:`~ldap_jax.Trajectory` (with ``.t``, ``.q``).
        styles: label -> keyword arguments for ``Axes.plot``.
        legend: draw the legend.

    Returns:
        ``ax``.

    Raises:
        ValueError: a trajectory's node times are not among the reference's.
    """
    styles = styles or {}
    t_ref, q_ref = as_tq(reference)
    if t_ref is None:
        raise ValueError("'reference' needs times (a Solution or Trajectory)")
    for i, (label, traj) in enumerate(trajectories.items()):
        t, q = as_tq(traj)
        if t is None:
            raise ValueError(f"{label!r} needs times (a Trajectory)")
        idx = reference_nodes(t_ref, t, label)
        err = np.linalg.norm(q[:, :2] - q_ref[idx, :2], axis=1)
        kw = {"lw": 1.4, **style_for(label, i), **styles.get(label, {})}
        if is_reference(label):
            continue
        ax.semilogy(t[1:], finite_positive(err)[1:], label=label, **kw)  # node 0: no error
    ax.set_xlabel("t [s]")
    ax.set_ylabel("position error [m]")
    ax.grid(True, which="major", alpha=0.3)
    if legend:
        ax.legend(fontsize=7, loc="best")
    return ax
