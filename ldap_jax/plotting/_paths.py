"""Paths in the plane with the vehicle drawn small along one of them, and position errors over
time against a reference."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Literal

import numpy as np
from matplotlib.axes import Axes
from matplotlib.lines import Line2D

from ..systems import AbstractSystem
from ._common import (
    as_tq,
    check_scale,
    failure_name,
    finite_positive,
    is_failed,
    is_reference,
    labelled,
    needs_nodes,
    reference_nodes,
    starts_run,
    styles_for,
    warn_if_failed,
)
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
        scale: drawing scale of the vehicle (a positive number, 1: true size), or ``"auto"``: the
            vehicle's length is 12% of the paths' extent (at most true size).
        times: times (s) of the ``draw`` path's nodes (default: from the trajectory, if any).
        markers: mark the start (circle: the first node of the ``draw`` path, or else of another
            path, when it is the run's start; not for ``save="final"`` or a later first node) and
            every path's end (square), or its failure (a cross at the last finite node of a failed
            trajectory, "failed (<result>)" in the legend).
        vehicle: custom drawing ``q -> parts`` (see :func:`~ldap_jax.plotting.vehicle_parts`).
        legend: ``True``: a legend of the paths and the markers; ``"markers"``: of the vehicle,
            start and end markers only (for a figure-level legend of the paths); ``False``: none.
        legend_loc: legend location (matplotlib's ``loc``).

    Returns:
        ``ax``.

    Raises:
        TypeError: ``paths`` not a mapping with string labels.
        ValueError: empty ``paths``, a batch of trajectories (pick one member), a bad ``draw`` or
            ``scale``.
    """
    paths = labelled(paths, "paths")
    if not paths:
        raise ValueError("'paths' is empty")
    scale = check_scale(scale)
    styles = styles or {}
    for label, value in paths.items():
        warn_if_failed(label, value)
    data = {label: as_tq(value, label=label, name="paths") for label, value in paths.items()}
    draw = draw if draw is not None else next(iter(paths))
    if draw not in data:
        raise ValueError(f"'draw' must be one of {list(paths)}, got {draw!r}")
    curve_styles = styles_for(data)
    failures: dict[str, str] = {}  # result name -> colour of the first path that failed so
    n_failed = 0
    for label, (_, q) in data.items():
        kw = {"lw": 1.4, **curve_styles[label], **styles.get(label, {})}
        (line,) = ax.plot(q[:, 0], q[:, 1], label=label, **kw)
        if markers:
            good = np.flatnonzero(np.all(np.isfinite(q[:, :2]), axis=1))
            if good.size:
                end = q[good[-1]]
                if is_failed(paths[label]):  # the failure at the last finite node, not an end
                    failures.setdefault(failure_name(paths[label]), line.get_color())
                    n_failed += 1
                    ax.plot(end[0], end[1], "x", ms=8, color=line.get_color(), mew=2.0, zorder=6)
                else:
                    ax.plot(end[0], end[1], "s", ms=5, mfc="none", mec=line.get_color(), mew=1.3, zorder=6)
    t_draw, q_draw = data[draw]
    t_draw = np.asarray(times, float) if times is not None else t_draw
    start = None
    if markers:
        # the start of the run: the first saved node of the 'draw' path (else of another path)
        # when it is the run's node 0; not for save="final" or a later first node
        t_first = [t[0] for t, q in data.values() if t is not None and q.shape[0]]
        t_start = min(t_first) if t_first else None
        for label in [draw] + [lab for lab in data if lab != draw]:
            t_lab, q_lab = data[label]
            if starts_run(paths[label], t_lab, t_start) and np.all(np.isfinite(q_lab[0, :2])):
                start = q_lab[0]
                break
        if start is not None:
            ax.plot(start[0], start[1], "o", ms=8, mfc="white", mec="k", mew=1.5, zorder=7)
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
        if start is not None:
            handles.append(
                Line2D([], [], ls="none", marker="o", ms=7, mfc="white", mec="k", mew=1.5, label="start")
            )
        if n_failed < len(data):
            handles.append(
                Line2D([], [], ls="none", marker="s", ms=5, mfc="none", mec="0.3", mew=1.3, label="end")
            )
        for name, color in failures.items():
            handles.append(
                Line2D([], [], ls="none", marker="x", ms=7, color=color, mew=2.0, label=f"failed ({name})")
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
        TypeError: ``trajectories`` not a mapping with string labels (e.g. a bare trajectory).
        ValueError: a trajectory's node times are not among the reference's (matched to a few ulp
            of the times' dtype), a trajectory with fewer than two saved nodes, a batch.
    """
    trajectories = labelled(trajectories, "trajectories")
    styles = styles or {}
    t_ref, q_ref = as_tq(reference, name="reference")
    if t_ref is None:
        raise ValueError("'reference' needs times (a Solution or Trajectory)")
    curve_styles = styles_for(trajectories)
    for label, traj in trajectories.items():
        t, q = as_tq(traj, label=label, name="trajectories")
        if t is None:
            raise ValueError(f"{label!r} needs times (a Trajectory)")
        needs_nodes(label, q.shape[0], "trajectories", "the position error over time")
        idx = reference_nodes(t_ref, t, label, traj.t, reference.t)
        err = np.linalg.norm(q[:, :2] - q_ref[idx, :2], axis=1)
        kw = {"lw": 1.4, **curve_styles[label], **styles.get(label, {})}
        if is_reference(label):
            continue
        first = 1 if starts_run(traj, t) else 0  # node 0: no error
        ax.semilogy(t[first:], finite_positive(err)[first:], label=label, **kw)
    ax.set_xlabel("t [s]")
    ax.set_ylabel("position error [m]")
    ax.grid(True, which="major", alpha=0.3)
    if legend:
        ax.legend(fontsize=7, loc="best")
    return ax
