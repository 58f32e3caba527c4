"""The study loop and its runtime ratios."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Sequence
from typing import NamedTuple

import jax
import numpy as np
from jax.sharding import Mesh

from .._compilation_cache import trim_compilation_cache
from ..integrators import RK4
from ..systems import AbstractSystem
from ._batch import device_mesh, reference_steps, rollout_nodes, timed
from ._chunks import ChunkStore
from ._config import CSV_COLUMNS, MODELS, StudyConfig, make_integrator
from ._maneuvers import global_maneuvers, sample_maneuvers
from ._summary import host_scalars, point_statistics, reference_statistics

__all__ = ["run_study", "position_errors", "runtime_ratios", "study_maneuvers"]


def position_errors(q: np.ndarray, q_ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Euclidean ``(x, y)`` errors: ``(final (B,), max over the output nodes (B,))``."""
    err = np.linalg.norm(np.asarray(q)[..., :2] - np.asarray(q_ref)[..., :2], axis=-1)
    return err[:, -1], np.max(err, axis=-1)


def _tasks(config: StudyConfig) -> list[tuple[str, float, str, int]]:
    return [
        (model, float(dur), method, int(n))
        for model in config.models
        for dur in config.durations
        for method in config.methods
        for n in config.resolutions
    ]


class _Reference(NamedTuple):
    """A model and duration's maneuvers and reference, as global arrays on the devices."""

    system: AbstractSystem
    sample: Callable[[int], tuple]  # the first n maneuvers, as global arrays
    maneuvers: tuple
    q: jax.Array
    code: jax.Array
    error: float


def _model_seed(config: StudyConfig, model: str) -> int:
    """The seed of ``model``'s maneuvers: ``config.seed + 1000 i``, ``i`` its index in :data:`MODELS`."""
    return config.seed + 1000 * list(MODELS).index(model)


def study_maneuvers(config: StudyConfig, model: str) -> tuple:
    """The ``config.runs`` maneuvers ``(q0, qdot0, controls)`` the study runs for ``model`` (one of
    ``config.models``), on the host: :func:`~ldap_jax.study.sample_maneuvers` of ``MODELS[model]()``
    with the seed ``config.seed + 1000 i`` (``i`` the model's index in :data:`MODELS`) and
    ``config.zero_steer_rate``. Member ``j`` is row ``j`` of every point of the model, up to the
    round-off of a batch of another size, so that a point can be checked maneuver by maneuver.

    Raises:
        ValueError: ``model`` not in ``config.models``.
    """
    if model not in config.models:
        raise ValueError(f"'model' must be one of the study's models {config.models}, got {model!r}")
    system = MODELS[model]()
    return sample_maneuvers(
        system, config.runs, _model_seed(config, model), zero_steer_rate=config.zero_steer_rate
    )


def _reference(config: StudyConfig, model: str, dur: float, mesh: Mesh, log) -> _Reference:
    """The maneuvers of ``model`` (each process samples its devices' members), the RK4 reference
    on them, and the reference's error estimated against half its step on a few of them."""
    system = MODELS[model]()
    seed = _model_seed(config, model)
    n_out = config.output_nodes

    def maneuvers(n: int):
        return global_maneuvers(system, n, seed, zero_steer_rate=config.zero_steer_rate, mesh=mesh)

    def reference(man, step: float):
        n_ref = reference_steps(dur, n_out, step)
        return rollout_nodes(system, RK4(), man, dur, n_ref, n_out=n_out, mesh=mesh)

    ref_step = min(config.reference_step, dur / max(config.resolutions) / 4)
    man = maneuvers(config.runs)
    q_ref, ref_code = reference(man, ref_step)
    m = min(config.reference_check, config.runs)
    q_half, _ = reference(maneuvers(m), ref_step / 2)
    stats = host_scalars(reference_statistics(q_ref, ref_code, q_half, config.runs, m))
    log(
        f"{model} {dur:g} s: reference (RK4, h <= {ref_step:.3g}) error estimate {stats['error']:.2e} "
        f"(vs h/2, {m} maneuvers); reference failures {stats['failures']}"
    )
    return _Reference(system, maneuvers, man, q_ref, ref_code, stats["error"])


def _point(config: StudyConfig, ref: _Reference, task, mesh: Mesh) -> dict:
    """The row of one point: the method's rollouts of every maneuver, reduced on the devices,
    and its runtime per trajectory on the first ``timing_runs`` maneuvers."""
    model, dur, method, n = task
    integrator = make_integrator(method)
    n_out = config.output_nodes

    def run(man):  # timed: compiled as a user's jax.jit would compile it
        return lambda: rollout_nodes(
            ref.system, integrator, man, dur, n, n_out=n_out, mesh=mesh, xla_defaults=True
        )

    n_time = min(config.timing_runs, config.runs)
    if n_time < config.runs:
        q, code = run(ref.maneuvers)()
        _, seconds = timed(run(ref.sample(n_time)), config.repeats)
    else:
        (q, code), seconds = timed(run(ref.maneuvers), config.repeats)
    stats = host_scalars(point_statistics(q, code, ref.q, ref.code, config.runs, config.blowup_factor))
    values = dict(
        stats,
        model=model,
        duration=dur,
        method=method,
        n_steps=n,
        h=dur / n,
        runs=config.runs,
        failure_rate=stats["failures"] / config.runs,
        runtime_us=1e6 * seconds / n_time,
        reference_error=ref.error,
    )
    return {c: values[c] for c in CSV_COLUMNS}


def run_study(
    config: StudyConfig,
    *,
    mesh: Mesh | None = None,
    progress: Callable[[Iterable], Iterable] | None = None,
    log: Callable[[str], None] | None = None,
    chunks: str | os.PathLike | None = None,
    resume: bool = True,
) -> list[dict]:
    """Run the study of ``config``: one row per model x duration x method x N (see
    :data:`CSV_COLUMNS`).

    The maneuvers, rollouts and references are global arrays split over the devices of
    ``mesh``; each process samples and runs only its devices' members, and each point comes
    back as its row's numbers (:func:`~ldap_jax.study.point_statistics`). With several
    processes (``jax.distributed.initialize``), every process calls this with the same
    ``config`` and gets the same rows.

    Args:
        mesh: devices to shard the batch over (default: all devices of all processes).
        progress: wraps the task list (e.g. ``tqdm.tqdm``) for a progress bar.
        log: receives one-line messages (reference error, timings, resumed points).
        chunks: a folder in which process 0 keeps each point's row as soon as it is done
            (:class:`~ldap_jax.study.ChunkStore`).
        resume: take the rows already in ``chunks`` instead of computing their points again
            (and a model and duration's reference only if one of its points is left).

    Returns:
        The rows, as dicts keyed by :data:`CSV_COLUMNS`.
    """
    if not isinstance(config, StudyConfig):
        raise TypeError(f"'config' must be an lj.study.StudyConfig, got {type(config).__name__}")
    mesh = device_mesh() if mesh is None else mesh
    log = log or (lambda s: None)
    tasks = _tasks(config)
    store = None if chunks is None else ChunkStore(chunks, config)
    rows = store.load(tasks) if store is not None and resume else {}
    if rows:
        log(f"resumed {len(rows)} of {len(tasks)} points from {store.folder}")
    iterator = progress(tasks) if progress is not None else tasks
    ref = None
    for i, task in enumerate(iterator):
        if i in rows:
            continue
        if ref is None or ref[0] != task[:2]:
            ref = None  # frees the previous reference before the next is computed
            trim_compilation_cache()
            ref = (task[:2], _reference(config, task[0], task[1], mesh, log))
        trim_compilation_cache()  # a full study compiles enough programs to exhaust vm.max_map_count
        rows[i] = _point(config, ref[1], task, mesh)
        if store is not None:
            store.save(task, rows[i])
    return [rows[i] for i in range(len(tasks))]


#: The pairs :func:`runtime_ratios` compares by default (those whose methods the rows hold).
DEFAULT_PAIRS: tuple[tuple[str, str], ...] = (
    ("rdp", "rk2"),
    ("rdp", "rk4"),
    ("rdp4", "rk4"),
    ("rdp6", "rk4"),
    ("rdp8", "rk4"),
    ("gni", "rdp"),
    ("dla", "rdp"),
)


def runtime_ratios(
    rows: list[dict],
    pairs: Sequence[tuple[str, str]] = DEFAULT_PAIRS,
    *,
    error: str = "final_error_median",
) -> list[dict]:
    """Runtime ratios ``a / b`` per model and duration: at equal N (geometric mean over the
    common resolutions) and at equal accuracy (runtime interpolated log-log at the error levels
    both methods reach; geometric mean over those levels; ``nan`` when their ranges do not
    overlap or failures leave too few points). The default pairs are those of
    :data:`DEFAULT_PAIRS` whose methods the rows hold; pairs given by name must all be there."""
    if pairs is not DEFAULT_PAIRS:  # pairs asked for by name: each method must be in the rows
        have = {r["method"] for r in rows}
        missing = sorted({m for pair in pairs for m in pair} - have)
        if missing:
            raise ValueError(f"'pairs': no rows of the methods {missing}; the rows hold {sorted(have)}")
    if rows and error not in rows[0]:
        columns = sorted(k for k in rows[0] if "error" in k)
        raise ValueError(f"'error' must be one of the rows' error columns {columns}, got {error!r}")
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
