"""The study loop and its runtime ratios."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence

import jax
import numpy as np
from jax.sharding import Mesh

from .._compilation_cache import trim_compilation_cache
from ._batch import batch_rollout, device_mesh, reference_batch
from ._config import MODELS, StudyConfig, make_integrator
from ._maneuvers import sample_maneuvers

__all__ = ["run_study", "position_errors", "runtime_ratios"]


def position_errors(q: np.ndarray, q_ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Euclidean ``(x, y)`` errors: ``(final (B,), max over the output nodes (B,))``."""
    err = np.linalg.norm(np.asarray(q)[..., :2] - np.asarray(q_ref)[..., :2], axis=-1)
    return err[:, -1], np.max(err, axis=-1)


def _stats(x: np.ndarray) -> tuple[float, float, float]:
    x = x[np.isfinite(x)]
    if x.size == 0:
        return (float("nan"),) * 3
    return float(np.mean(x)), float(np.median(x)), float(np.max(x))


def _tasks(config: StudyConfig) -> list[tuple[str, float, str, int]]:
    return [
        (model, float(dur), method, int(n))
        for model in config.models
        for dur in config.durations
        for method in config.methods
        for n in config.resolutions
    ]


def run_study(
    config: StudyConfig,
    *,
    mesh: Mesh | None = None,
    progress: Callable[[Iterable], Iterable] | None = None,
    log: Callable[[str], None] | None = None,
) -> list[dict]:
    """Run the study of ``config``: one row per model x duration x method x N (see
    :data:`CSV_COLUMNS`).

    Args:
        mesh: devices to shard the batch over (default: all).
        progress: wraps the task list (e.g. ``tqdm.tqdm``) for a progress bar.
        log: receives one-line messages (reference error, timings).

    Returns:
        The rows, as dicts keyed by :data:`CSV_COLUMNS`.
    """
    mesh = device_mesh() if mesh is None else mesh
    log = log or (lambda s: None)
    n_out = config.output_nodes
    tasks = _tasks(config)
    iterator = progress(tasks) if progress is not None else tasks
    cache: dict = {}
    rows = []
    for model, dur, method, n in iterator:
        key = (model, dur)
        if key not in cache:
            system = MODELS[model]()
            man = sample_maneuvers(
                system,
                config.runs,
                config.seed + 1000 * list(MODELS).index(model),
                zero_steer_rate=config.zero_steer_rate,
            )
            ref_step = min(config.reference_step, dur / max(config.resolutions) / 4)
            q_ref, ref_code = reference_batch(system, man, dur, n_out=n_out, step=ref_step, mesh=mesh)
            m = min(config.reference_check, config.runs)
            sub = jax.tree_util.tree_map(lambda x: x[:m], man)
            q_half, _ = reference_batch(system, sub, dur, n_out=n_out, step=ref_step / 2, mesh=mesh)
            ref_err = float(np.nanmax(position_errors(q_ref[:m], q_half)[1]))
            log(
                f"{model} {dur:g} s: reference (RK4, h <= {ref_step:.3g}) error estimate {ref_err:.2e} "
                f"(vs h/2, {m} maneuvers); reference failures {int(np.sum(ref_code != 0))}"
            )
            cache = {key: (system, man, q_ref, ref_code, ref_err)}
        system, man, q_ref, ref_code, ref_err = cache[key]
        integrator = make_integrator(method)
        trim_compilation_cache()  # a full study compiles enough programs to exhaust vm.max_map_count
        n_time = min(config.timing_runs, config.runs)
        if n_time < config.runs:
            q, code, _ = batch_rollout(system, integrator, man, dur, n, n_out=n_out, mesh=mesh)
            sub = jax.tree_util.tree_map(lambda x: x[:n_time], man)
            _, _, seconds = batch_rollout(
                system, integrator, sub, dur, n, n_out=n_out, mesh=mesh, repeats=config.repeats
            )
        else:
            q, code, seconds = batch_rollout(
                system, integrator, man, dur, n, n_out=n_out, mesh=mesh, repeats=config.repeats
            )
        final, worst = position_errors(q, q_ref)
        # blow-up: finite, but the position error exceeds 10 x (1 + the reference's extent)
        extent = np.max(np.linalg.norm(q_ref[..., :2] - q_ref[:, :1, :2], axis=-1), axis=-1)
        blowup = (code == 0) & ~(worst <= config.blowup_factor * (1.0 + extent))
        ok = (code == 0) & ~blowup & (ref_code == 0)
        final, worst = np.where(ok, final, np.nan), np.where(ok, worst, np.nan)
        fm, fmed, fmax = _stats(final)
        wm, wmed, wmax = _stats(worst)
        failures = int(np.sum(code != 0) + np.sum(blowup))
        rows.append(
            dict(
                model=model,
                duration=dur,
                method=method,
                n_steps=n,
                h=dur / n,
                runs=config.runs,
                failures=failures,
                failure_rate=failures / config.runs,
                nonfinite=int(np.sum(code == 1)),
                singular=int(np.sum(code == 2)),
                not_converged=int(np.sum(code == 3)),
                blowup=int(np.sum(blowup)),
                final_error_mean=fm,
                final_error_median=fmed,
                final_error_max=fmax,
                max_error_mean=wm,
                max_error_median=wmed,
                max_error_max=wmax,
                runtime_us=1e6 * seconds / n_time,
                reference_error=ref_err,
            )
        )
    return rows


def runtime_ratios(
    rows: list[dict],
    pairs: Sequence[tuple[str, str]] = (
        ("rdp", "rk2"),
        ("rdp", "rk4"),
        ("rdp4", "rk4"),
        ("rdp6", "rk4"),
        ("gni", "rdp"),
        ("dla", "rdp"),
    ),
    *,
    error: str = "final_error_median",
) -> list[dict]:
    """Runtime ratios ``a / b`` per model and duration: at equal N (geometric mean over the
    common resolutions) and at equal accuracy (runtime interpolated log-log at the error levels
    both methods reach; geometric mean over those levels; ``nan`` when their ranges do not
    overlap or failures leave too few points)."""
    out = []
    keys = sorted({(r["model"], r["duration"]) for r in rows})
    for model, dur in keys:
        sel = [r for r in rows if r["model"] == model and r["duration"] == dur]
        by = {}
        for r in sel:
            by.setdefault(r["method"], {})[int(r["n_steps"])] = r
        for a, b in pairs:
            if a not in by or b not in by:
                continue
            common = sorted(set(by[a]) & set(by[b]))
            eq_n = [by[a][n]["runtime_us"] / by[b][n]["runtime_us"] for n in common]
            eq_n = [x for x in eq_n if np.isfinite(x) and x > 0]
            ratio_n = float(np.exp(np.mean(np.log(eq_n)))) if eq_n else float("nan")
            ratio_acc = _equal_accuracy(by[a], by[b], error)
            out.append(
                dict(model=model, duration=dur, ratio=f"{a}/{b}", equal_n=ratio_n, equal_accuracy=ratio_acc)
            )
    return out


def _curve(points: dict, error: str):
    ns = sorted(points)
    e = np.array([points[n][error] for n in ns], float)
    t = np.array([points[n]["runtime_us"] for n in ns], float)
    good = np.isfinite(e) & (e > 0) & np.isfinite(t) & (t > 0)
    return np.log(e[good]), np.log(t[good])


def _equal_accuracy(pa: dict, pb: dict, error: str) -> float:
    ea, ta = _curve(pa, error)
    eb, tb = _curve(pb, error)
    if ea.size < 2 or eb.size < 2:
        return float("nan")
    lo, hi = max(ea.min(), eb.min()), min(ea.max(), eb.max())
    if not lo < hi:
        return float("nan")
    levels = np.linspace(lo, hi, 9)

    def interp(e, t, x):  # runtime at error level x (errors decrease with N)
        order = np.argsort(e)
        return np.interp(x, e[order], t[order])

    return float(np.exp(np.mean(interp(ea, ta, levels) - interp(eb, tb, levels))))
