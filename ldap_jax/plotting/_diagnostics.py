"""Diagnostics over time: energy and work, the work-energy balance, the nonholonomic momentum."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from .._compilation_cache import compiler_options
from ..systems import AbstractSystem
from ._common import (
    REFERENCE_STYLE,
    check_one,
    finite_positive,
    labelled,
    needs_nodes,
    reference_nodes,
    root_figure,
    running_max,
    starts_run,
    styles_for,
    warn_if_failed,
)

__all__ = ["plot_diagnostics", "plot_energy_error"]


def _needs_diagnostics(label: str, traj: Any) -> None:
    if getattr(traj, "energy", None) is None or getattr(traj, "work", None) is None:
        raise ValueError(
            f"{label!r}: needs a Trajectory with diagnostics (lj.simulate(..., diagnostics=True))"
        )


def _groups(trajectories: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """``{system: {label: traj}}`` from a nested mapping or a flat one (a single group)."""
    example = "{'RDP': traj} or {'car': {'RDP': traj}}"
    trajectories = labelled(trajectories, "trajectories", example)
    values = list(trajectories.values())
    if values and all(isinstance(v, Mapping) for v in values):
        return {k: labelled(v, "trajectories", example) for k, v in trajectories.items()}
    return {"": trajectories}


def _check_reference(name: str, value: Any) -> tuple[AbstractSystem, Any]:
    """A reference entry ``(system, Solution)``; a ``TypeError`` naming ``'references'`` otherwise."""
    ok = (
        isinstance(value, tuple)
        and len(value) == 2
        and isinstance(value[0], AbstractSystem)
        and all(hasattr(value[1], f) for f in ("t", "q", "qdot"))
    )
    if not ok:
        where = "'references'" if not name else f"'references' {name!r}"
        raise TypeError(
            f"{where} must be (system, Solution), e.g. (car, lj.reference(car, q0, qdot0, ctl, traj.t)), "
            f"or {{system name: (system, Solution)}}, got {type(value).__name__}"
            + (f" of {[type(v).__name__ for v in value]}" if isinstance(value, tuple) else "")
        )
    return value


def _checked(label: str, traj: Any, name: str) -> None:
    """One trajectory with diagnostics and at least two saved nodes."""
    check_one(label, traj, name)
    _needs_diagnostics(label, traj)
    needs_nodes(label, np.shape(traj.t)[0], name, "a curve over time")


def _reference_values(system: Any, reference: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Times (s), energy (J) and momenta of the reference at all its nodes."""
    import jax

    q, qdot = np.asarray(reference.q), np.asarray(reference.qdot)
    ok = np.all(np.isfinite(q), axis=1) & np.all(np.isfinite(qdot), axis=1)
    values = jax.jit(
        jax.vmap(lambda a, b: (system.energy(a, b), system.momentum(a, b))),
        compiler_options=compiler_options(),
    )
    energy, momentum = (
        np.asarray(v) for v in values(np.where(ok[:, None], q, 0.0), np.where(ok[:, None], qdot, 0.0))
    )
    energy = np.where(ok, energy, np.nan)
    momentum = np.where(ok[:, None], momentum, np.nan)
    return np.asarray(reference.t, float), energy, momentum


def plot_diagnostics(
    trajectories: Mapping[str, Any],
    *,
    references: Mapping[str, tuple[AbstractSystem, Any]] | tuple[AbstractSystem, Any] | None = None,
    momentum_units: str = "kg m$^2$/s",
    figsize: tuple[float, float] | None = None,
) -> Figure:
    """Diagnostics over time, one row per system (each with its own axes and units).

    Panels of a row:

    * with a reference: the energy error ``|E - E_ref|`` (J) per integrator, log scale (the
      integrator's accuracy in energy); without one: the energy ``E(t)`` (J) of the first
      trajectory with ``E_0 + W(t)``, its initial energy plus the control work;
    * the work-energy balance ``|E - E_0 - W|`` (J) per integrator, log scale (thin: the value;
      thick: its running maximum). It needs no reference, but ``W`` is the trapezoidal rule on
      the nodes (:attr:`~ldap_jax.Trajectory.work`), second order: on forced runs its
      quadrature error is a floor that hides the accuracy of higher-order methods;
    * the nonholonomic momentum ``mu_1 = <dl/dxi, e_1(r)>`` per integrator (and the reference's)
      for systems with constrained symmetries (the snakeboard; the car has none).

    Args:
        trajectories: ``{system name: {integrator label: Trajectory}}`` (one row per system), or
            ``{label: Trajectory}`` (one row). Trajectories need ``diagnostics=True``.
        references: ``{system name: (system, Solution)}`` (a :class:`~ldap_jax.Solution` from
            :func:`~ldap_jax.reference` sampled at the trajectories' node times), or one
            ``(system, Solution)`` for a single row; rows without one show energy and work.
        momentum_units: units of ``mu`` (the snakeboard's and the roller racer's: kg m^2/s).
        figsize: figure size (inches); default 13 wide, 3.4 per row.

    Returns:
        The figure.

    Raises:
        TypeError: ``trajectories`` not a mapping with string labels (e.g. a bare trajectory),
            ``references`` neither ``(system, Solution)`` nor a mapping of them.
        ValueError: a trajectory without diagnostics, with fewer than two saved nodes or batched
            (pick one member), a reference not sampled at its nodes, or ``references`` naming a
            row that ``trajectories`` does not have.
    """
    groups = _groups(trajectories)
    if not trajectories:
        raise ValueError("'trajectories' is empty")
    for trajs in groups.values():
        for label, traj in trajs.items():
            _checked(label, traj, "trajectories")
    for trajs in groups.values():
        for label, traj in trajs.items():
            warn_if_failed(label, traj)
    if isinstance(references, tuple) or (references is not None and not isinstance(references, Mapping)):
        references = {next(iter(groups)): _check_reference("", references)}
    references = {name: _check_reference(name, ref) for name, ref in (references or {}).items()}
    unknown = [name for name in references if name not in groups]
    if unknown:
        rows = [name for name in groups if name] or "one unnamed row (a flat mapping)"
        raise ValueError(
            f"'references' has {unknown}, not rows of 'trajectories' ({rows}); for a flat mapping "
            "label -> trajectory pass references=(system, Solution)"
        )
    n_rows = len(groups)
    fig = plt.figure(figsize=figsize or (13.0, 3.4 * n_rows), layout="constrained")
    subfigs = np.atleast_1d(fig.subfigures(n_rows, 1))
    for sub, (system_name, trajs) in zip(subfigs, groups.items()):
        curve_styles = styles_for(trajs)
        has_mu = any(
            getattr(tr, "momentum", None) is not None and np.asarray(tr.momentum).shape[-1] > 0
            for tr in trajs.values()
        )
        axes = sub.subplots(1, 3 if has_mu else 2)
        prefix = f"{system_name}: " if system_name else ""
        first_label, first = next(iter(trajs.items()))
        energy = np.asarray(first.energy)
        e_range = f"E from {np.nanmin(energy):.2g} to {np.nanmax(energy):.2g} J"
        ref = references.get(system_name)
        ref_mu = {}
        ax = axes[0]
        if ref is not None:
            t_ref, e_all, mu_all = _reference_values(*ref)
            for label, traj in trajs.items():
                t = np.asarray(traj.t, float)
                idx = reference_nodes(t_ref, t, label, traj.t, ref[1].t)
                e_ref = e_all[idx]
                ref_mu[label] = (t, mu_all[idx])
                kw = {"lw": 1.4, **curve_styles[label]}
                err = finite_positive(np.abs(np.asarray(traj.energy) - e_ref))
                first = 1 if starts_run(traj, t) else 0  # node 0 is exact
                ax.semilogy(t[first:], err[first:], label=label, **kw)
            ax.set_title(f"{prefix}energy error against the reference\n({e_range})", fontsize=10)
            ax.set_ylabel("$|E - E_{ref}|$ [J]")
        else:
            t = np.asarray(first.t)
            ax.plot(t, energy, color="k", lw=1.5, label="energy $E(t)$")
            ax.plot(
                t,
                energy[0] + np.asarray(first.work),
                color="tab:green",
                ls="--",
                lw=1.5,
                label="$E_0 + W(t)$",
            )
            ax.set_title(f"{prefix}energy and control work W\n({first_label})", fontsize=10)
            ax.set_ylabel("energy [J]")
        ax.legend(fontsize=7, loc="best")
        plot_energy_error(
            trajs,
            ax=axes[1],
            title=f"{prefix}work-energy balance $|E - E_0 - W|$\n(W: trapezoidal rule, 2nd order)",
        )
        if has_mu:
            ax = axes[2]
            if ref_mu:
                t, mu_ref = next(iter(ref_mu.values()))
                ax.plot(t, mu_ref[:, 0], label="reference", **{**REFERENCE_STYLE, "lw": 4.0})
            for label, traj in trajs.items():
                mu = getattr(traj, "momentum", None)
                if mu is None or np.asarray(mu).shape[-1] == 0:
                    continue
                kw = {"lw": 1.3, **curve_styles[label]}
                ax.plot(np.asarray(traj.t), np.asarray(mu)[:, 0], label=label, **kw)
            ax.set_title(
                rf"{prefix}nonholonomic momentum $\mu_1$" + "\n(constrained-symmetry direction $e_1$)",
                fontsize=10,
            )
            ax.set_ylabel(rf"$\mu_1$ [{momentum_units}]")
            ax.legend(fontsize=7, loc="best")
        for ax in axes:
            ax.set_xlabel("t [s]")
            ax.grid(True, alpha=0.3)
    return fig


def plot_energy_error(
    trajs: Mapping[str, Any],
    *,
    ax: Axes | None = None,
    relative: bool = False,
    envelope: bool = True,
    logx: bool = False,
    title: str | None = None,
    styles: Mapping[str, dict] | None = None,
) -> Figure:
    """The energy-balance error ``|E_k - E_0 - W_k|`` over time, one curve per trajectory, on a
    log scale: the structure-preservation picture of long runs (bounded for RDP, drifting for
    Runge-Kutta methods). ``W`` is the control work, so the picture also applies to forced runs;
    for unforced or work-free runs it is the energy error.

    Args:
        trajs: label -> :class:`~ldap_jax.Trajectory` (``diagnostics=True``).
        ax: axes to draw into (default: a new figure).
        relative: divide by ``|E_0|`` (dimensionless) instead of joules (undefined, and refused,
            for ``E_0 = 0``, e.g. a run from rest).
        envelope: draw the running maximum ``max_{j <= k} |E_j - E_0 - W_j|`` (thick) over the
            oscillating value (thin, light), up to a failed run's failure; False draws the value
            only.
        logx: logarithmic time axis: a drift growing like ``t^p`` is then a line of slope ``p``.
            (Node 0, where the error is zero by construction, is never drawn.)
        title: axes title.
        styles: label -> keyword arguments for ``Axes.plot``.

    Returns:
        The figure.

    Raises:
        TypeError: ``trajs`` not a mapping with string labels (e.g. a bare trajectory).
        ValueError: a trajectory without diagnostics, with fewer than two saved nodes or batched
            (pick one member); ``relative=True`` with ``E_0 = 0``.
    """
    trajs = labelled(trajs, "trajs")
    styles = styles or {}
    for label, traj in trajs.items():
        _checked(label, traj, "trajs")
    e0 = {label: float(np.asarray(traj.energy, float)[0]) for label, traj in trajs.items()}
    if relative:
        for label, e in e0.items():
            if not (np.isfinite(e) and e != 0.0):
                raise ValueError(
                    f"'trajs' {label!r}: the relative error |E - E0 - W| / |E0| is undefined at E0 = {e:g} "
                    "(e.g. a run from rest); use relative=False (joules)"
                )
    if ax is None:
        fig, ax = plt.subplots(figsize=(6.4, 4.0), layout="constrained")
    curve_styles = styles_for(trajs)
    for label, traj in trajs.items():
        warn_if_failed(label, traj)
        t = np.asarray(traj.t, float)
        err = np.abs(np.asarray(traj.energy_balance, float))
        if relative:
            err = err / abs(e0[label])
        keep = t > t[0]  # node 0: zero by construction
        kw = {"lw": 1.6, **curve_styles[label], **styles.get(label, {})}
        if envelope:
            ax.plot(t[keep], finite_positive(err)[keep], color=kw["color"], lw=0.6, alpha=0.3)
            ax.plot(t[keep], finite_positive(running_max(err))[keep], label=label, **kw)
        else:
            ax.plot(t[keep], finite_positive(err)[keep], label=label, **kw)
    ax.set_yscale("log")
    if logx:
        ax.set_xscale("log")
    ax.set_xlabel("t [s]")
    what = "running max of " if envelope else ""
    ax.set_ylabel(f"{what}$|E - E_0 - W|$" + (" / $|E_0|$" if relative else " [J]"))
    if title is not None:
        ax.set_title(title, fontsize=10)
    ax.grid(True, which="major", alpha=0.3)
    if trajs:
        note = "thick: running max, thin: value" if envelope else None
        ax.legend(fontsize=7, loc="best", title=note, title_fontsize=7)
    return root_figure(ax)
