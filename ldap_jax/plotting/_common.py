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
    "failure_name",
    "tracks",
    "labelled",
    "check_one",
    "needs_nodes",
    "starts_run",
    "check_scale",
    "is_failed",
    "style_for",
    "styles_for",
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
    if not isinstance(label, str):
        raise TypeError(f"labels must be strings, got {label!r} ({type(label).__name__})")
    low = label.lower()
    fallback = {"color": _CYCLE[index % len(_CYCLE)], "ls": "-", "marker": "o"}
    matched, style = next(((p, s) for p, s in _STYLES if re.search(p, low)), (None, fallback))
    out = dict(style)
    if "cayley" in low and matched != "cayley":  # e.g. "RDP6 cayley": RDP6's colour, dash-dot
        out.update(ls="-.", marker="v")
    if not markers:
        out.pop("marker", None)
    return out


# variants for curves whose labels would share a style: line styles and markers by repeat
_VARIANT_LS: tuple[Any, ...] = ("--", "-.", ":", (0, (5, 1)), (0, (3, 1, 1, 1)), "-")
_VARIANT_MARKERS = ("s", "^", "D", "v", "P", "X", "*", "o")


def _shade(color: Any, repeat: int) -> tuple[float, float, float]:
    """``color`` darker (odd ``repeat``) or lighter (even), more so for later repeats."""
    from matplotlib.colors import to_rgb

    rgb = np.asarray(to_rgb(color))
    amount = min(0.25 * ((repeat + 1) // 2), 0.6)
    target = 0.0 if repeat % 2 else 1.0
    return tuple(float(c) for c in rgb + amount * (target - rgb))  # type: ignore[return-value]


def styles_for(labels: Any, *, markers: bool = False) -> dict[str, dict[str, Any]]:
    """Line styles for the curves of one figure: :func:`style_for` of each label, except that a
    label whose style an earlier label already has (e.g. ``"RDP h=0.1"`` and ``"RDP h=0.05"``, both
    RDP blue) gets a darker or lighter shade, another line style and another marker, so that every
    curve of the figure can be told apart.

    Args:
        labels: the curves' labels, in drawing order.
        markers: keep the markers (for curves through a few points).

    Returns:
        label -> keyword arguments for ``Axes.plot``.
    """
    labels = list(labels)
    out: dict[str, dict[str, Any]] = {}
    used: set[tuple[str, str, Any]] = set()

    def key(s: dict[str, Any]) -> tuple[str, str, Any]:
        from matplotlib.colors import to_hex

        return (to_hex(s["color"]), str(s["ls"]), s.get("marker") if markers else None)

    for i, label in enumerate(labels):
        base = style_for(label, i, markers=True)
        style, repeat = dict(base), 0
        while key(style) in used and repeat < 64:
            repeat += 1
            style = dict(
                base, color=_shade(base["color"], repeat), ls=_VARIANT_LS[(repeat - 1) % len(_VARIANT_LS)]
            )
            style["marker"] = _VARIANT_MARKERS[(repeat - 1) % len(_VARIANT_MARKERS)]
        used.add(key(style))
        if not markers:
            style.pop("marker", None)
        out[label] = style
    return out


def is_reference(label: str) -> bool:
    """True for labels that name a reference solution."""
    return re.search(_REFERENCE_PATTERN, label.lower()) is not None


_PICK = "pick one member with jax.tree_util.tree_map(lambda x: x[i], traj)"


def _n_axes(expected: str) -> int:
    """The number of axes of a shape written ``"(M,)"`` or ``"(M, d)"``."""
    return len([a for a in expected.strip("()").split(",") if a.strip()])


def _shape_message(name: str, label: str | None, field: str, shape: tuple, expected: str) -> str:
    where = f"{name!r}" if label is None else f"{name!r} {label!r}"
    msg = f"{where}: {field} has shape {shape}, expected {expected} (one trajectory)"
    n_axes = _n_axes(expected)
    if len(shape) > n_axes:
        msg += f"; this looks like a batch (e.g. from jax.vmap), which is not drawn as one: {_PICK}"
    return msg


def as_tq(
    obj: Any, t: Any = None, *, label: str | None = None, name: str = "trajectory"
) -> tuple[np.ndarray | None, np.ndarray]:
    """``(t, q)`` as NumPy arrays from a :class:`~ldap_jax.Trajectory`, a
    :class:`~ldap_jax.Solution` (anything with ``.q`` and ``.t``) or an array of configurations.

    Args:
        obj: trajectory-like object or array (M, d).
        t: times (M,) overriding ``obj.t`` (s); ``None`` keeps ``obj.t`` (or none for an array).
        label: the trajectory's label, for the messages.
        name: the argument it came from, for the messages.

    Raises:
        ValueError: ``q`` not 2-d (e.g. a vmapped batch), or ``t`` not 1-d or of the wrong length.
    """
    if hasattr(obj, "q"):
        q = np.asarray(obj.q, dtype=float)
        t_obj = getattr(obj, "t", None)
        t = t_obj if t is None else t
    else:
        q = np.asarray(obj, dtype=float)
    if q.ndim != 2:
        raise ValueError(_shape_message(name, label, "the configurations q", q.shape, "(M, d)"))
    if t is not None:
        t = np.asarray(t, dtype=float)
        if t.ndim != 1:
            raise ValueError(_shape_message(name, label, "the times t", t.shape, "(M,)"))
        if t.shape[0] != q.shape[0]:
            where = f"{name!r}" if label is None else f"{name!r} {label!r}"
            raise ValueError(
                f"{where}: times have {t.shape[0]} entries but there are {q.shape[0]} configurations"
            )
    return t, q


def check_one(label: str | None, obj: Any, name: str) -> None:
    """ValueError (naming the argument ``name`` and ``label``) unless ``obj`` holds one trajectory:
    ``t`` (M,), ``q`` and ``qdot`` (M, d), ``energy`` and ``work`` (M,), ``momentum`` (M, c)."""
    for field, expected in (
        ("t", "(M,)"),
        ("q", "(M, d)"),
        ("qdot", "(M, d)"),
        ("energy", "(M,)"),
        ("work", "(M,)"),
        ("momentum", "(M, c)"),
    ):
        value = getattr(obj, field, None)
        if value is not None and np.ndim(value) != _n_axes(expected):
            raise ValueError(_shape_message(name, label, field, np.shape(value), expected))


def needs_nodes(label: str | None, n_nodes: int, name: str, what: str) -> None:
    """ValueError unless a trajectory has at least two saved nodes (curves over time need them)."""
    if n_nodes < 2:
        where = f"{name!r}" if label is None else f"{name!r} {label!r}"
        raise ValueError(
            f"{where}: {what} needs at least two saved nodes, got {n_nodes} (a run with "
            "save='final' keeps only the last node; use save='all' or a stride)"
        )


def labelled(obj: Any, name: str, example: str = "{'RDP': traj}") -> dict[str, Any]:
    """``obj``, a mapping label -> value with string labels, as a dict; a ``TypeError`` naming the
    argument ``name`` otherwise (e.g. a bare trajectory where a mapping is expected)."""
    if not isinstance(obj, Mapping):
        raise TypeError(
            f"{name!r} must be a mapping label -> value, e.g. {example}, got {type(obj).__name__}"
        )
    for label in obj:
        if not isinstance(label, str):
            raise TypeError(f"{name!r}: labels must be strings, got {label!r} ({type(label).__name__})")
    return dict(obj)


def check_scale(scale: Any) -> float | str:
    """A vehicle drawing scale: ``"auto"`` or a positive finite number; ValueError otherwise."""
    if isinstance(scale, str):
        if scale != "auto":
            raise ValueError(f"'scale' must be a positive number or 'auto', got {scale!r}")
        return scale
    if isinstance(scale, bool) or not isinstance(scale, (int, float, np.integer, np.floating)):
        raise ValueError(f"'scale' must be a positive number or 'auto', got {scale!r}")
    if not (np.isfinite(scale) and scale > 0):
        raise ValueError(f"'scale' must be a positive number or 'auto', got {scale!r}")
    return float(scale)


def starts_run(obj: Any, t: np.ndarray | None, t_start: float | None = None) -> bool:
    """Whether the first saved node of ``obj`` is the run's start (node 0), so that it may be marked
    "start": not with a single node (``save="final"``), nor when the control work at that node is
    nonzero (the work counts from the start), nor when its time is after ``t_start`` (s), the
    earliest start of the trajectories drawn with it."""
    q = getattr(obj, "q", obj)
    if np.shape(q)[0] < 2:
        return False
    work = getattr(obj, "work", None)
    if work is not None and np.ndim(work) == 1:
        w0 = float(np.asarray(work, float)[0])
        if np.isfinite(w0) and w0 != 0.0:
            return False
    if t is not None and t_start is not None:
        return bool(t[0] <= t_start + time_tolerance(t, getattr(obj, "t", t)))
    return True


def time_tolerance(t: np.ndarray, *raw: Any) -> float:
    """Tolerance (s) for matching the times ``t``: 8 ulp of the coarsest dtype among ``raw`` (the
    times as given: float32 runs round their node times to float32) at ``max(1, |t|)``, and no less
    than ``1e-9 max(1, |t|)`` (float64 times computed in different ways)."""
    eps = max(
        (
            float(np.finfo(np.asarray(r).dtype).eps)
            for r in raw
            if np.issubdtype(np.asarray(r).dtype, np.floating)
        ),
        default=float(np.finfo(float).eps),
    )
    scale = max(1.0, float(np.max(np.abs(t)))) if np.size(t) else 1.0
    return max(8.0 * eps, 1e-9) * scale


def warn_if_failed(label: str, obj: Any) -> None:
    """A ``UserWarning`` when ``obj`` is a trajectory that failed (its ``result``; the nodes after
    the failure are NaN and not drawn) or has no finite configuration to draw."""
    if is_failed(obj):
        from .._results import RESULTS

        warnings.warn(
            f"plotting {label!r}, a trajectory that failed ({RESULTS[obj.result]}): the nodes after the "
            "failure are NaN and are not drawn",
            stacklevel=3,
        )
    elif not np.any(np.isfinite(np.asarray(getattr(obj, "q", obj), dtype=float))):
        warnings.warn(f"plotting {label!r}: no finite configuration to draw", stacklevel=3)


def is_failed(obj: Any) -> bool:
    """True for a (single) trajectory or solution whose ``failed`` is True."""
    failed = getattr(obj, "failed", None)
    return failed is not None and np.ndim(failed) == 0 and bool(failed)


def failure_name(obj: Any) -> str:
    """The name of a failed trajectory's result (``"singular"``, ``"diverged"``, ...)."""
    result = getattr(obj, "result", None)
    names = getattr(getattr(result, "_enumeration", None), "_name_to_item", None) or {}
    value = getattr(result, "_value", None)
    for name, item in names.items():
        if value is not None and int(np.asarray(item._value)) == int(np.asarray(value)):
            return name
    return "failed"


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
    """Running maximum over the finite entries, NaN until the first finite entry and from the first
    non-finite entry after it on (a failed run's nodes after the failure: the envelope stops there
    instead of being carried on flat)."""
    x = np.asarray(x, dtype=float)
    finite = np.isfinite(x)
    filled = np.where(finite, x, -np.inf)
    out = np.maximum.accumulate(filled)
    stopped = np.cumsum(~finite & (np.cumsum(finite) > 0)) > 0
    return np.where(np.isfinite(out) & ~stopped, out, np.nan)


def root_figure(ax: Any) -> Any:
    """The top-level figure of ``ax`` (not a subfigure)."""
    fig = ax.figure
    while getattr(fig, "figure", fig) is not fig:
        fig = fig.figure
    return fig


def reference_nodes(t_ref: np.ndarray, t: np.ndarray, label: str, *raw: Any) -> np.ndarray:
    """Indices of the reference nodes at the times ``t`` (s), matched to 8 ulp of the coarsest
    dtype of the times as given (``raw``: the trajectory's and the reference's ``t``; float64 when
    none is given); ValueError if some are missing."""
    idx = np.clip(np.searchsorted(t_ref, t), 0, len(t_ref) - 1)
    lower = np.clip(idx - 1, 0, len(t_ref) - 1)
    idx = np.where(np.abs(t_ref[lower] - t) < np.abs(t_ref[idx] - t), lower, idx)
    tol = time_tolerance(t_ref, *raw)
    if np.any(np.abs(t_ref[idx] - t) > tol):
        raise ValueError(
            f"{label!r}: its times are not among the reference's; sample the reference at the trajectory's "
            "nodes (e.g. lj.reference(..., ts=traj.t))"
        )
    return idx
