"""The study's outputs: CSV, markdown tables and figures."""

from __future__ import annotations

import csv
import os

import numpy as np

from ._config import CSV_COLUMNS

__all__ = ["write_csv", "read_csv", "plot_study", "format_table"]


def write_csv(rows: list[dict], path: str | os.PathLike) -> None:
    """Write the study's rows (columns :data:`CSV_COLUMNS`), every number to its full precision
    (the shortest text that reads back to the same float: :func:`read_csv` returns the rows)."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0].keys()) if rows else list(CSV_COLUMNS))
        writer.writeheader()
        for r in rows:
            writer.writerow({k: (repr(float(v)) if isinstance(v, float) else v) for k, v in r.items()})


def read_csv(path: str | os.PathLike) -> list[dict]:
    """Read a study CSV back (numbers as floats, ``n_steps`` etc. as ints)."""
    ints = {"n_steps", "runs", "failures", "nonfinite", "singular", "not_converged", "blowup"}
    with open(path, newline="") as fh:
        reader = csv.DictReader(fh)
        rows = list(reader)
        missing = [c for c in ("model", "method", "n_steps") if c not in (reader.fieldnames or ())]
    if missing:
        raise ValueError(
            f"{os.fspath(path)!r} is not a study CSV: no column {missing} (its columns: {reader.fieldnames})"
        )
    out = []
    for r in rows:
        conv = {}
        for k, v in r.items():
            if k in ("model", "method", "ratio"):
                conv[k] = v
            elif k in ints:
                conv[k] = int(v)
            else:
                conv[k] = float(v)
        out.append(conv)
    return out


def _duration_label(dur: float) -> str:
    return f"{dur / 60:g} min" if dur >= 60 else f"{dur:g} s"


#: One distinct style per method (colour by family, line style and marker by variant).
STYLES = {
    "rdp": ("tab:blue", "-", "o"),
    "rdp4": ("tab:purple", "-", "s"),
    "rdp6": ("tab:pink", "-", "D"),
    "rdp8": ("indigo", "-", "*"),
    "rdp_cayley": ("tab:blue", "--", "v"),
    "rdp_a0": ("tab:cyan", ":", "<"),
    "rdp_a1": ("tab:cyan", "-.", ">"),
    "rdp_a0_cayley": ("tab:olive", ":", "<"),
    "rdp_a1_cayley": ("tab:olive", "-.", ">"),
    "gni": ("tab:green", "-", "^"),
    "gni_folded": ("tab:green", "--", "x"),
    "dla": ("tab:brown", "-", "P"),
    "rk2": ("tab:orange", "--", "o"),
    "rk4": ("tab:red", "--", "s"),
}


def plot_study(
    rows: list[dict], out_dir: str | os.PathLike, *, error: str = "final_error_median"
) -> list[str]:
    """Figures in the style of the paper's Figs. 4 and 5, one per model and duration, three panels
    against the resolution N: the position error (``error``, default the median final error, as
    in the tables; failed runs excluded), the runtime per trajectory, and the failure rate.
    Returns the file paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    os.makedirs(out_dir, exist_ok=True)
    paths = []
    for model, dur in sorted({(r["model"], r["duration"]) for r in rows}):
        sel = [r for r in rows if r["model"] == model and r["duration"] == dur]
        fig, (ax_e, ax_t, ax_f) = plt.subplots(
            1, 3, figsize=(15, 4.6), gridspec_kw={"width_ratios": [1.25, 1, 0.8]}
        )
        for method in dict.fromkeys(r["method"] for r in sel):
            pts = sorted((r for r in sel if r["method"] == method), key=lambda r: r["n_steps"])
            ns = np.array([r["n_steps"] for r in pts])
            color, ls, marker = STYLES.get(method, ("k", "-", "o"))
            kw = dict(color=color, linestyle=ls, marker=marker, ms=4, label=method)
            ax_e.loglog(ns, [r[error] for r in pts], **kw)
            ax_t.loglog(ns, [r["runtime_us"] for r in pts], **kw)
            ax_f.semilogx(ns, [100 * r["failure_rate"] for r in pts], **kw)
        ns_all = sorted({int(r["n_steps"]) for r in sel})
        for ax in (ax_e, ax_t, ax_f):
            ax.set_xticks(ns_all, [str(n) for n in ns_all])
            ax.minorticks_off()
            ax.set_xlabel("resolution N (steps; macro steps for rdp4, rdp6, rdp8)")
            ax.grid(True, which="both", alpha=0.3)
        label = {"final_error_median": "median final", "final_error_mean": "mean final"}.get(error, error)
        ax_e.set_ylabel(f"position error, {label} [m]")
        ax_t.set_ylabel("runtime per trajectory [us]")
        ax_f.set_ylabel("failed runs [%]")
        ax_f.set_ylim(-3, 103)
        ax_e.legend(fontsize=7, ncol=2, loc="lower left")
        fig.suptitle(
            f"{model}, {_duration_label(dur)} trajectories, {sel[0]['runs']} random maneuvers "
            "(errors over the runs that did not fail)"
        )
        fig.tight_layout()
        path = os.path.join(out_dir, f"sweep_{model}_{int(round(dur))}s.png")
        fig.savefig(path, dpi=120)
        plt.close(fig)
        paths.append(path)
    return paths


def format_table(rows: list[dict], *, error: str = "final_error_median") -> str:
    """A markdown table of the study: per model and duration, one line per method, with the
    error (``error``), runtime per trajectory and failure rate at each resolution."""
    lines = []
    for model, dur in sorted({(r["model"], r["duration"]) for r in rows}):
        sel = [r for r in rows if r["model"] == model and r["duration"] == dur]
        ns = sorted({int(r["n_steps"]) for r in sel})
        lines.append(
            f"\n**{model}, {_duration_label(dur)}** ({sel[0]['runs']} maneuvers; "
            f"{error.replace('_', ' ')} [m] / runtime per trajectory [us] / failures)\n"
        )
        lines.append("| method | " + " | ".join(f"N={n}" for n in ns) + " |")
        lines.append("|---" * (len(ns) + 1) + "|")
        for method in dict.fromkeys(r["method"] for r in sel):
            cells = []
            for n in ns:
                r = next((x for x in sel if x["method"] == method and int(x["n_steps"]) == n), None)
                if r is None:
                    cells.append("")
                    continue
                fail = f" / {100 * r['failure_rate']:.1f}%" if r["failures"] else ""
                cells.append(f"{r[error]:.2e} / {r['runtime_us']:.3g}{fail}")
            lines.append(f"| {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
