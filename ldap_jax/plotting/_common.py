"""Shared helpers of the plotting package: input coercion, line styles, axis labels with units."""

from __future__ import annotations

import re
import warnings
from collections.abc import Mapping
from typing import Any

import numpy as np

__all__ = [
    "as_tq",
    "warn_if_failed",
    "tracks",
    "style_for",
    "shape_label",
    "finite_positive",
    "running_max",
    "is_reference",
    "reference_nodes",
    "root_figure",
    "REFERENCE_STYLE",
]

#: Style of a reference (ground-truth) curve: thick, light, underneath the methods.
REFERENCE_STYLE: dict[str, Any] = {"color": "0.2", "lw": 3.0, "alpha": 0.3, "ls": "-", "zorder": 1}

# (pattern on the lower-cased label, style); the first match wins. Colours follow
# ldap_jax.study's figures (RDP blue/purple/pink, RK orange/red, DLA brown, GNI green).
_REFERENCE_PATTERN = r"reference|diffrax|exact|ground truth"
_STYLES: tuple[tuple[str, dict[str, Any]], ...] = (
    (r"tsit5", {"color": "0.55", "ls": "-", "lw": 2.0, "marker": "x"}),  # diffrax peers, told apart
    (r"dopri", {"color": "0.25", "ls": "--", "lw": 2.0, "marker": "+"}),
    (_REFERENCE_PATTERN, REFERENCE_STYLE),
    (r"(rdp|order)[\s_=\-:(,]*8(?!\d)", {"color": "indigo", "ls": "-", "marker": "*"}),
    (r"(rdp|order)[\s_=\-:(,]*6(?!\d)", {"color": "tab:pink", "ls": "-", "marker": "D"}),
    (r"(rdp|order)[\s_=\-:(,]*4(?!\d)", {"color": "tab:purple", "ls": "-", "marker": "s"}),
    (r"cayley", {"color": "tab:cyan", "ls": "-.", "marker": "v"}),
    (r"rdp", {"color": "tab:blue", "ls": "-", "marker": "o"}),
    (r"rk\s*-?4", {"color": "tab:red", "ls": "--", "marker": "s"}),
    (r"rk\s*-?2", {"color": "tab:orange", "ls": "--", "marker": "o"}),
    (r"dla", {"color": "tab:brown", "ls": ":", "marker": "P"}),
    (r"gni", {"color": "tab:green", "ls": ":", "marker": "^"}),
)
_CYCLE = ("tab:gray", "tab:olive", "tab:cyan", "tab:brown", "tab:green", "k")


def style_for(label: str, index: int = 0, *, markers: bool = False) -> dict[str, Any]:
    """Line style for a curve labelled ``label``: reference curves thick and light, RDP in blues and
    purples (solid), Runge-Kutta in orange and red (dashed), others from a fixed cycle.

    Args:
        label: the curve's label (matched case-insensitively, e.g. ``"RDP order 4"``, ``"RK4"``).
        index: position of the curve, for labels that match nothing.
        markers: keep the marker (for curves through a few points, e.g. convergence).

    Returns:
        Keyword arguments for ``Axes.plot``.
    """
    low = label.lower()
    fallback = {"color": _CYCLE[index % len(_CYCLE)], "ls": "-", "marker": "o"}
    matched, style = next(((p, s) for p, s in _STYLES if re.search(p, low)), (None, fallback))
    out = dict(style)
    if "cayley" in low and matched != "cayley":  # e.g. "RDP6 cayley": RDP6's colour, dash-dot
        out.update(ls="-.", marker="v")
    if not markers:
        out.pop("marker", None)
    return out


def is_reference(label: str) -> bool:
    """True for labels that name a reference solution."""
    return re.search(_REFERENCE_PATTERN, label.lower()) is not None


def as_tq(obj: Any, t: Any = None) -> tuple[np.ndarray | None, np.ndarray]:
    """``(t, q)`` as NumPy arrays from a :class:`~ldap_jax.Trajectory`, a
    :class:`~ldap_jax.Solution` (anything with ``.q`` and ``.t``) or an array of configurations.

    Args:
        obj: trajectory-like object or array (M, d).
        t: times (M,) overriding ``obj.t`` (s); ``None`` keeps ``obj.t`` (or none for an array).

    Raises:
        ValueError: ``q`` not 2-d, or ``t`` of the wrong length.
    """
    if hasattr(obj, "q"):
        q = np.asarray(obj.q, dtype=float)
        t_obj = getattr(obj, "t", None)
        t = t_obj if t is None else t
    else:
        q = np.asarray(obj, dtype=float)
    if q.ndim != 2:
        raise ValueError(f"configurations must have shape (M, d) (one trajectory), got {q.shape}")
    if t is not None:
        t = np.asarray(t, dtype=float).reshape(-1)
        if t.shape[0] != q.shape[0]:
            raise ValueError(f"times have {t.shape[0]} entries but there are {q.shape[0]} configurations")
    return t, q


def warn_if_failed(label: str, obj: Any) -> None:
    """A ``UserWarning`` when ``obj`` is a trajectory that failed (its ``result``; the nodes after
    the failure are NaN and not drawn) or has no finite configuration to draw."""
    failed = getattr(obj, "failed", None)
    if failed is not None and np.ndim(failed) == 0 and bool(failed):
        from .._results import RESULTS

        warnings.warn(
            f"plotting {label!r}, a trajectory that failed ({RESULTS[obj.result]}): the nodes after the "
            "failure are NaN and are not drawn",
            stacklevel=3,
        )
    elif not np.any(np.isfinite(np.asarray(getattr(obj, "q", obj), dtype=float))):
        warnings.warn(f"plotting {label!r}: no finite configuration to draw", stacklevel=3)


def tracks(obj: Any, labels: Any = None) -> dict[str, Any]:
    """Normalise one trajectory, a mapping label -> trajectory, or a sequence of trajectories to a
    dict label -> trajectory (labels from ``labels``, else ``"1"``, ``"2"``, ...)."""
    if isinstance(obj, Mapping):
        return dict(obj)
    if isinstance(obj, (list, tuple)):
        names = list(labels) if labels is not None else [str(i + 1) for i in range(len(obj))]
        if len(names) != len(obj):
            raise ValueError(f"{len(names)} labels for {len(obj)} trajectories")
        return dict(zip(names, obj))
    name = labels if isinstance(labels, str) else (labels[0] if labels else "")
    return {name: obj}


_GREEK = {"psi", "phi", "theta", "sigma", "alpha", "beta", "gamma", "delta", "eta", "omega"}


def shape_label(name: str, *, rate: bool = False) -> str:
    """Axis label with units for a shape coordinate (``"psi"`` -> ``"$\\psi$ [rad]"``; the car's
    ``sigma = tan(steering angle)`` is dimensionless)."""
    sym = f"\\{name}" if name in _GREEK else name
    sym = f"\\dot{{{sym}}}" if rate else sym
    if name == "sigma":
        unit = "1/s" if rate else "-"
        return f"${sym}$ = tan(steering angle) [{unit}]" if not rate else f"${sym}$ [{unit}]"
    unit = "rad/s" if rate else "rad"
    return f"${sym}$ [{unit}]"


def finite_positive(x: np.ndarray) -> np.ndarray:
    """``x`` with non-positive and non-finite entries replaced by NaN (for log axes)."""
    x = np.asarray(x, dtype=float)
    return np.where(np.isfinite(x) & (x > 0), x, np.nan)


def running_max(x: np.ndarray) -> np.ndarray:
    """Running maximum ignoring NaN (NaN until the first finite entry)."""
    x = np.asarray(x, dtype=float)
    filled = np.where(np.isfinite(x), x, -np.inf)
    out = np.maximum.accumulate(filled)
    return np.where(np.isfinite(out), out, np.nan)


def root_figure(ax: Any) -> Any:
    """The top-level figure of ``ax`` (not a subfigure)."""
    fig = ax.figure
    while getattr(fig, "figure", fig) is not fig:
        fig = fig.figure
    return fig


def reference_nodes(t_ref: np.ndarray, t: np.ndarray, label: str) -> np.ndarray:
    """Indices of the reference nodes at the times ``t`` (s); ValueError if some are missing."""
    idx = np.clip(np.searchsorted(t_ref, t), 0, len(t_ref) - 1)
    lower = np.clip(idx - 1, 0, len(t_ref) - 1)
    idx = np.where(np.abs(t_ref[lower] - t) < np.abs(t_ref[idx] - t), lower, idx)
    tol = 1e-9 * max(1.0, float(np.max(np.abs(t_ref))))
    if np.any(np.abs(t_ref[idx] - t) > tol):
        raise ValueError(
            f"{label!r}: its times are not among the reference's; sample the reference at the trajectory's "
            "nodes (e.g. lj.reference(..., ts=traj.t))"
        )
    return idx
