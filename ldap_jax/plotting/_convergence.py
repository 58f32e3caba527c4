"""Convergence (error against step) and work-precision (error against runtime) diagrams."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.ticker import NullFormatter

from ._common import labelled, root_figure, styles_for

__all__ = ["plot_convergence", "plot_work_precision", "study_curves", "fitted_order"]


def _xy(value: Any, label: str, x_name: str = "steps") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(x, y, order)``, sorted by x, from two sequences ``(xs, ys)`` (a tuple of two sequences) or
    a sequence of ``(x, y)`` pairs (a list of two pairs is pairs); ``order`` sorts the input.

    Raises:
        TypeError: ``label`` not a string.
        ValueError: neither form, or the ambiguous 2 x 2 forms: a tuple of two 2-tuples, a 2 x 2
            array.
    """
    if not isinstance(label, str):
        raise TypeError(f"labels must be strings, got {label!r} ({type(label).__name__})")
    forms = (
        f"pass the {x_name} and errors as a tuple of two lists ([x1, x2, ...], [e1, e2, ...]) or a "
        "list of (x, error) pairs [(x1, e1), (x2, e2), ...]"
    )
    if isinstance(value, tuple) and len(value) == 2 and all(_is_sequence(v) for v in value):
        if all(isinstance(v, tuple) and len(v) == 2 for v in value):
            raise ValueError(
                f"{label!r}: a tuple of two 2-tuples is ambiguous (two pairs or (xs, ys)?): {forms}"
            )
        x, y = (np.asarray(v, dtype=float) for v in value)
        if x.ndim != 1 or x.shape != y.shape:
            raise ValueError(
                f"{label!r}: (xs, ys) must be two 1-d sequences of one length, got {x.shape}, {y.shape}"
            )
    else:
        try:
            arr = np.asarray(value, dtype=float)
        except (TypeError, ValueError) as err:
            raise ValueError(f"{label!r}: expected (xs, ys) or a sequence of (x, y) pairs: {forms}") from err
        if arr.ndim != 2 or 2 not in arr.shape:
            raise ValueError(
                f"{label!r}: expected (xs, ys) or a sequence of (x, y) pairs, got shape {arr.shape}"
            )
        if arr.shape == (2, 2) and not isinstance(value, (list, tuple)):
            raise ValueError(f"{label!r}: a 2 x 2 array is ambiguous (two pairs or (xs, ys)?): {forms}")
        as_pairs = arr.shape[1] == 2 and (isinstance(value, (list, tuple)) or arr.shape[0] != 2)
        x, y = (arr[:, 0], arr[:, 1]) if as_pairs else (arr[0], arr[1])
    order = np.argsort(x, kind="stable")
    return x[order], y[order], order


def _is_sequence(v: Any) -> bool:
    """A 1-d sequence of values (a list, tuple or array), not a scalar nor a string."""
    if isinstance(v, (str, bytes)):
        return False
    try:
        return np.ndim(v) == 1
    except ValueError:  # ragged
        return False


def fitted_order(h: Sequence[float], err: Sequence[float], *, floor: float = 0.0) -> float:
    """Least-squares slope of ``log err`` against ``log h`` over the points with a finite error
    above ``floor`` (NaN with fewer than two such points)."""
    h, err = np.asarray(h, float), np.asarray(err, float)
    if h.ndim != 1 or h.shape != err.shape:
        raise ValueError(
            f"fitted_order: 'h' and 'err' must be 1-d of one length, got {h.shape} and {err.shape}"
        )
    ok = np.isfinite(err) & (err > floor) & np.isfinite(h) & (h > 0)
    if ok.sum() < 2:
        return float("nan")
    return float(np.polyfit(np.log(h[ok]), np.log(err[ok]), 1)[0])


def plot_convergence(
    results: Mapping[str, Any],
    *,
    ax: Axes | None = None,
    slopes: Sequence[int] = (2, 4, 6),
    floor: float = 1e-11,
    floor_label: str = "below: not fitted (reference accuracy)",
    xlabel: str = "step h [s]",
    ylabel: str = "final position error [m]",
    title: str | None = None,
    styles: Mapping[str, dict] | None = None,
) -> Figure:
    """Log-log error against step size, one curve per method, with reference slopes.

    Each legend entry gives the least-squares order fitted over the points above ``floor`` (the
    reference's own accuracy: points below it are drawn but not fitted). The reference lines
    ``C h^p`` (grey, for each ``p`` in ``slopes``) run a factor 3 below the curve whose fitted
    order is ``p`` (through the geometric mean of all errors when no curve has that order).

    Args:
        results: label -> ``(steps, errors)`` (a tuple of two sequences) or a list of
            ``(h, error)`` pairs (a list of two pairs is two points); NaN errors (failed runs) are
            skipped. A tuple of two 2-tuples or a 2 x 2 array is ambiguous and refused.
        ax: axes to draw into (default: a new figure).
        slopes: orders of the reference lines.
        floor: errors at or below it are excluded from the fitted orders (units of the errors).
        floor_label: note on the floor line (drawn when some error is below it).
        xlabel: x label (with units).
        ylabel: y label (with units).
        title: axes title.
        styles: label -> keyword arguments for ``Axes.plot``.

    Returns:
        The figure.

    Raises:
        TypeError: ``results`` not a mapping, or a label not a string.
        ValueError: a curve in neither form, or in an ambiguous one.
    """
    results = labelled(results, "results", "{'RDP': (steps, errors)}")
    styles = styles or {}
    data = {label: _xy(v, label)[:2] for label, v in results.items()}
    if ax is None:
        _, ax = plt.subplots(figsize=(6.4, 4.6), layout="constrained")
    curve_styles = styles_for(data, markers=True)
    for label, (h, err) in data.items():
        p = fitted_order(h, err, floor=floor)
        name = f"{label} (fitted order {p:.1f})" if np.isfinite(p) else label
        kw = {"lw": 1.5, "ms": 5, **curve_styles[label], **styles.get(label, {})}
        ok = np.isfinite(err) & (err > 0)
        ax.loglog(h[ok], err[ok], label=name, **kw)
    all_h = np.concatenate([h for h, _ in data.values()]) if data else np.array([])
    all_e = np.concatenate([e for _, e in data.values()]) if data else np.array([])
    good = np.isfinite(all_e) & (all_e > 0)
    if good.any():
        ylim = (all_e[good].min() / 3, all_e[good].max() * 3)
        h_lo, h_hi = all_h[good].min(), all_h[good].max()
        hs = np.geomspace(h_lo, h_hi, 20)
        orders = {label: fitted_order(h, e, floor=floor) for label, (h, e) in data.items()}
        for p, ls in zip(slopes, ("--", "-.", ":", (0, (5, 1)))):
            # anchor a third below the largest-step error of the curve of that order, if any
            match = [lab for lab, o in orders.items() if np.isfinite(o) and abs(o - p) < 0.5]
            if match:
                h, e = data[match[0]]
                ok = np.isfinite(e) & (e > floor)
                anchor_h, anchor_e = h[ok][-1], e[ok][-1] / 3
            else:
                anchor_h, anchor_e = h_hi, float(np.exp(np.mean(np.log(all_e[good]))))
            ax.loglog(
                hs,
                anchor_e * (hs / anchor_h) ** p,
                color="0.45",
                ls=ls,
                lw=1.0,
                label=f"slope {p}: $\\propto h^{p}$",
            )
        ax.set_ylim(*ylim)
        steps = np.unique(all_h[good])
        if steps.size <= 8:
            ax.set_xticks(steps, [f"{x:g}" for x in steps])
            ax.xaxis.set_minor_formatter(NullFormatter())
        if floor > 0 and all_e[good].min() < floor:
            ax.axhline(floor, color="0.6", lw=0.8, ls=(0, (1, 2)))
            ax.annotate(
                floor_label,
                (0.01, floor),
                xycoords=("axes fraction", "data"),
                ha="left",
                va="top",
                fontsize=7,
                color="0.4",
            )
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if title is not None:
        ax.set_title(title, fontsize=10)
    ax.grid(True, which="both", alpha=0.25)
    if data:
        ax.legend(fontsize=7, loc="best")
    return root_figure(ax)


def study_curves(
    rows: Sequence[Mapping[str, Any]], error: str = "final_error_median"
) -> tuple[dict[str, list[tuple[float, float]]], dict[str, list[str]]]:
    """Work-precision curves from rows of :func:`ldap_jax.study.run_study` (or of a ``sweep.csv``
    read back by :func:`ldap_jax.study.read_csv`): one curve per method, of ``(seconds, error)``
    pairs, with the runtime converted from the rows' microseconds (``runtime_us``) to seconds.

    Args:
        rows: study rows (``model``, ``duration``, ``method``, ``n_steps``, ``runtime_us`` and
            the ``error`` column).
        error: the error column to plot (m), e.g. ``"final_error_median"`` or ``"max_error_median"``.

    Returns:
        ``(curves, annotations)`` for :func:`plot_work_precision`: label -> pairs, and label ->
        ``"N=..."`` per point. The label is the method, prefixed by the model and the duration
        when the rows hold more than one of them.

    Raises:
        ValueError: a row without one of those columns.
    """
    needed = ("model", "duration", "method", "n_steps", "runtime_us", error)
    for row in rows:
        missing = [k for k in needed if k not in row]
        if missing:
            raise ValueError(f"'rows': a study row lacks {missing} (got keys {sorted(row)})")
    cases = {(r["model"], float(r["duration"])) for r in rows}
    curves: dict[str, list[tuple[float, float]]] = {}
    notes: dict[str, list[str]] = {}
    for r in sorted(rows, key=lambda r: (r["model"], float(r["duration"]), r["method"], int(r["n_steps"]))):
        label = r["method"] if len(cases) == 1 else f"{r['model']}, {float(r['duration']):g} s: {r['method']}"
        curves.setdefault(label, []).append((1e-6 * float(r["runtime_us"]), float(r[error])))
        notes.setdefault(label, []).append(f"N={int(r['n_steps'])}")
    return curves, notes


def plot_work_precision(
    curves: Mapping[str, Any] | Sequence[Mapping[str, Any]],
    *,
    ax: Axes | None = None,
    annotations: Mapping[str, Sequence[str]] | None = None,
    error: str = "final_error_median",
    xlabel: str = "runtime per trajectory [s]",
    ylabel: str | None = None,
    title: str | None = None,
    styles: Mapping[str, dict] | None = None,
) -> Figure:
    """Work-precision diagram: error against runtime, log-log, one curve per method (lower left
    is better: less error for less time).

    Args:
        curves: label -> a list of ``(seconds, error)`` pairs (a list of two pairs is two points)
            or a tuple of two sequences ``(seconds_list, errors)``; or the rows of a study
            (:func:`ldap_jax.study.run_study`), plotted as they are: one curve per method,
            runtimes in seconds, each point annotated with its ``N`` (:func:`study_curves`).
            Non-finite points are skipped.
        ax: axes to draw into (default: a new figure).
        annotations: label -> one text per point (in the given order, e.g. ``"N=100"``).
        error: with study rows, the error column to plot (default the median final error).
        xlabel: x label (with units: the runtimes are in seconds).
        ylabel: y label (with units; default ``"position error [m]"``, or the study's error
            column).
        title: axes title.
        styles: label -> keyword arguments for ``Axes.plot``.

    Returns:
        The figure.

    Raises:
        TypeError: a label not a string.
        ValueError: a curve that is neither pairs nor two sequences (or an ambiguous tuple of two
            2-tuples or 2 x 2 array); annotations whose count is not the curve's; a study row
            without the columns it needs.

    Example:
        >>> from ldap_jax import study
        >>> rows = study.run_study(study.StudyConfig(models=("snakeboard",), durations=(10.0,),
        ...     methods=("rdp", "rk2"), resolutions=(250, 1000), runs=8))
        >>> fig = plot_work_precision(rows, title="snakeboard, 10 s")
    """
    if not isinstance(curves, Mapping):
        curves, notes = study_curves(curves, error)
        annotations = notes if annotations is None else annotations
        ylabel = ylabel or f"{error.replace('_', ' ')} [m]"
    curves = labelled(curves, "curves", "{'RDP': [(seconds, error), ...]}")
    styles = styles or {}
    annotations = annotations or {}
    data = {label: _xy(value, label, "runtimes") for label, value in curves.items()}
    for label, texts in annotations.items():
        if label in data and len(texts) != len(data[label][0]):
            raise ValueError(
                f"'annotations' {label!r}: {len(texts)} texts for {len(data[label][0])} points "
                "(one text per point)"
            )
    if ax is None:
        _, ax = plt.subplots(figsize=(6.4, 4.6), layout="constrained")
    curve_styles = styles_for(data, markers=True)
    for label, (secs, errs, order) in data.items():
        ok = np.isfinite(secs) & np.isfinite(errs) & (secs > 0) & (errs > 0)
        kw = {"lw": 1.5, "ms": 5, **curve_styles[label], **styles.get(label, {})}
        ax.loglog(secs[ok], errs[ok], label=label, **kw)
        texts = annotations.get(label)
        if texts is not None:
            texts = [texts[j] for j in order]
            for s, e, txt, keep in zip(secs, errs, texts, ok):
                if keep:
                    ax.annotate(
                        txt, (s, e), xytext=(4, 3), textcoords="offset points", fontsize=6, color="0.3"
                    )
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel or "position error [m]")
    if title is not None:
        ax.set_title(title, fontsize=10)
    ax.grid(True, which="both", alpha=0.25)
    if curves:
        ax.legend(fontsize=7, loc="best")
    return root_figure(ax)
