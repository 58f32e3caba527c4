"""Monte Carlo accuracy/runtime studies (paper Figs. 4 and 5), sharded over devices.

The study: for a model, a batch of random sinusoidal maneuvers, a duration (10 s, 10 min), a set
of integrators and resolutions (total number of steps N), measure the position error against a
high-accuracy reference (final and max over time), the runtime per trajectory (batched, after
compilation, median of repeats) and the failure rate (non-finite values, singular
configuration, solver not converged, or blow-up: a finite run far off the reference). The batch
axis is sharded over every JAX device
(``jax.sharding.Mesh`` + ``NamedSharding``), so the same code uses all GPUs of a node, or all
hosts once ``jax.distributed.initialize()`` has run.

Rollouts here are :func:`rollout`, a lean twin of :func:`ldap_jax.simulate` (same steps, same
failure codes, checked equal in the tests) that keeps only ``n_out + 1`` evenly spaced nodes and
takes ``N`` and the duration as traced values, so one compilation per (model, method) serves
every resolution and duration. RDP on the car and the snakeboard runs, as in ``simulate``, the
closed-form kernel (one compilation per ``N``): the study times what a user's call would run.

Example:
    >>> rows = run_study(StudyConfig(models=("snakeboard",), durations=(10.0,), runs=8,
    ...                              methods=("rdp", "rk2"), resolutions=(100, 200)))
    >>> write_csv(rows, "results/sweep.csv")
"""

from __future__ import annotations

import csv
import dataclasses
import math
import os
import time
from collections.abc import Callable, Iterable, Sequence
from functools import reduce

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from jaxtyping import Array

from ._compilation_cache import trim_compilation_cache
from ._controls import AbstractControls, Sinusoids
from .integrators import DLA, GNI, RDP, RK2, RK4, AbstractIntegrator, _fast
from .systems import AbstractSystem, Car, Snakeboard

__all__ = [
    "METHODS",
    "MODELS",
    "CSV_COLUMNS",
    "StudyConfig",
    "make_integrator",
    "sample_maneuvers",
    "rollout",
    "device_mesh",
    "shard_batch",
    "batch_rollout",
    "reference_batch",
    "position_errors",
    "run_study",
    "runtime_ratios",
    "write_csv",
    "read_csv",
    "plot_study",
    "format_table",
]

#: Integrators of the study, by the name used in the CSV's ``method`` column.
METHODS: dict[str, Callable[[], AbstractIntegrator]] = {
    "rdp": lambda: RDP(alpha=0.5, retraction="exp"),
    "rdp_a0": lambda: RDP(alpha=0.0, retraction="exp"),
    "rdp_a1": lambda: RDP(alpha=1.0, retraction="exp"),
    "rdp_cayley": lambda: RDP(alpha=0.5, retraction="cayley"),
    "rdp_a0_cayley": lambda: RDP(alpha=0.0, retraction="cayley"),
    "rdp_a1_cayley": lambda: RDP(alpha=1.0, retraction="cayley"),
    "gni": lambda: GNI(),
    "gni_folded": lambda: GNI(variant="folded"),
    "dla": lambda: DLA(),
    "rk2": lambda: RK2(),
    "rk4": lambda: RK4(),
}

#: The paper's models with the parameters of the tests and notebooks.
MODELS: dict[str, Callable[[], AbstractSystem]] = {
    "snakeboard": lambda: Snakeboard(m=1.0, l=0.5, I=0.05, J=0.02),
    "car": lambda: Car(m=1.0, I=0.1, K=0.2, rho=0.1, l=0.5),
}

#: Columns of the study's CSV, one row per model x duration x method x N.
CSV_COLUMNS = (
    "model",
    "duration",
    "method",
    "n_steps",
    "h",
    "runs",
    "failures",
    "failure_rate",
    "nonfinite",
    "singular",
    "not_converged",
    "blowup",
    "final_error_mean",
    "final_error_median",
    "final_error_max",
    "max_error_mean",
    "max_error_median",
    "max_error_max",
    "runtime_us",
    "reference_error",
)


def make_integrator(name: str) -> AbstractIntegrator:
    """The integrator named ``name`` (a key of :data:`METHODS`)."""
    if name not in METHODS:
        raise ValueError(f"'method' must be one of {sorted(METHODS)}, got {name!r}")
    return METHODS[name]()


@dataclasses.dataclass(frozen=True)
class StudyConfig:
    """Settings of a study (defaults: the paper's full study).

    Attributes:
        models: keys of :data:`MODELS`.
        durations: trajectory lengths in seconds (paper: 10 s, Fig. 4; 600 s, Fig. 5).
        methods: keys of :data:`METHODS`.
        resolutions: total numbers of steps N; each must be a multiple of ``n_out``.
        runs: maneuvers per model.
        seed: seed of the maneuvers.
        n_out: evenly spaced nodes (besides t = 0) at which errors are measured; default the
            greatest common divisor of the resolutions, capped at 500.
        reference_step: largest step of the RK4 reference (a converged fine-step run, also at
            least 4 times finer than the finest resolution; its own error is estimated by
            halving the step on ``reference_check`` maneuvers).
        reference_check: maneuvers on which the reference error is estimated.
        repeats: timed repeats (after compilation) per method and N; the median is reported.
        timing_runs: batch size of the timed calls (the first ``timing_runs`` maneuvers; errors
            and failures always use all ``runs``).
        blowup_factor: a finite run whose max position error exceeds ``blowup_factor`` x
            (1 + the reference path's extent from its start) counts as a failure (blow-up).
        zero_steer_rate: snakeboard maneuvers start with ``phidot(0) = 0`` (see
            :func:`sample_maneuvers`).
    """

    models: tuple[str, ...] = ("snakeboard", "car")
    durations: tuple[float, ...] = (10.0, 600.0)
    methods: tuple[str, ...] = tuple(METHODS)
    resolutions: tuple[int, ...] = (500, 1000, 2000, 4000, 8000)
    runs: int = 1000
    seed: int = 0
    n_out: int | None = None
    reference_step: float = 5e-3
    reference_check: int = 16
    repeats: int = 3
    timing_runs: int = 200
    blowup_factor: float = 10.0
    zero_steer_rate: bool = True

    def __post_init__(self):
        for name in self.models:
            if name not in MODELS:
                raise ValueError(f"'models' must be among {sorted(MODELS)}, got {name!r}")
        for name in self.methods:
            if name not in METHODS:
                raise ValueError(f"'methods' must be among {sorted(METHODS)}, got {name!r}")
        if not self.resolutions or any(int(n) < 1 for n in self.resolutions):
            raise ValueError(f"'resolutions' must be positive integers, got {self.resolutions}")
        if not self.durations or any(not float(t) > 0 for t in self.durations):
            raise ValueError(f"'durations' must be positive, got {self.durations}")
        if self.runs < 1:
            raise ValueError(f"'runs' must be a positive integer, got {self.runs}")
        if self.timing_runs < 1:
            raise ValueError(f"'timing_runs' must be a positive integer, got {self.timing_runs}")
        if self.repeats < 1:
            raise ValueError(f"'repeats' must be a positive integer, got {self.repeats}")
        if not self.reference_step > 0:
            raise ValueError(f"'reference_step' must be positive, got {self.reference_step}")
        n_out = self.output_nodes
        bad = [n for n in self.resolutions if n % n_out]
        if bad:
            raise ValueError(f"'resolutions' {bad} are not multiples of n_out={n_out}")

    @property
    def output_nodes(self) -> int:
        if self.n_out is not None:
            if self.n_out < 1:
                raise ValueError(f"'n_out' must be a positive integer, got {self.n_out}")
            return int(self.n_out)
        g = reduce(math.gcd, (int(n) for n in self.resolutions))
        # largest divisor of g not above 500
        return max(d for d in range(1, min(g, 500) + 1) if g % d == 0)


# ------------------------------------------------------------------------------------ maneuvers
def _zero_steer_rate(system: Snakeboard, q0: Array, qdot0: Array, ctl: Sinusoids):
    """Re-phase a snakeboard maneuver's steering so that ``phidot(0) = 0``.

    ``sample_maneuver`` steers with ``phi(t) = phi_c + b sin(w t + p)`` from the torque
    ``f_phi = -2 J b w^2 sin(w t + p)``. Any second-order scheme's discrete steering rate then
    carries a mean bias ``~ h^2 f_phi'(0) / J`` (from the first step's quadrature), a linear drift
    of phi proportional to ``b w^3 cos(p) h^2 t`` that on 10-minute runs at coarse steps drives
    phi into the singularity ``cos(phi) = 0``. With ``p = +-pi/2`` (``phidot(0) = 0``,
    ``f_phi'(0) = 0``) the leading bias vanishes; ``phi_c``, ``b``, ``w`` stay random.
    """
    b = -ctl.amplitude[1, 0] / (2 * system.J * ctl.frequency[1, 0] ** 2)
    phi_c = q0[4] - b * jnp.sin(ctl.phase[1, 0])
    p_new = jnp.where(jnp.cos(ctl.phase[1, 0]) >= 0, 0.5 * jnp.pi, -0.5 * jnp.pi).astype(q0.dtype)
    ctl = eqx.tree_at(lambda c: c.phase, ctl, ctl.phase.at[1, 0].set(p_new))
    q0_new = q0.at[4].set(phi_c + b * jnp.sin(p_new))
    v = system.velocities_from_qdot(q0, qdot0)
    v = v.at[1].set(jnp.zeros((), q0.dtype))
    qdot0_new = system.qdot_from_velocities(q0_new, v, jnp.zeros(2, q0.dtype))
    return q0_new, qdot0_new, ctl


def sample_maneuvers(
    system: AbstractSystem, n: int, seed: int, *, zero_steer_rate: bool = True
) -> tuple[Array, Array, AbstractControls]:
    """A reproducible batch of ``n`` random maneuvers ``(q0, qdot0, controls)`` (leading axis n).

    Uses the model's ``sample_maneuver`` (random sinusoidal controls producing parallel
    parking, sharp turns and winding; initial states on the constraints). For the snakeboard
    with ``zero_steer_rate`` the steering phase is set so that ``phidot(0) = 0`` (see
    :func:`_zero_steer_rate`): this keeps long coarse runs off the singularity ``cos(phi) = 0``.
    """
    if n < 1:
        raise ValueError(f"'n' must be a positive integer, got {n}")
    keys = jax.random.split(jax.random.PRNGKey(seed), n)
    man = jax.vmap(system.sample_maneuver)(keys)
    if zero_steer_rate and isinstance(system, Snakeboard):
        man = jax.vmap(lambda a, b, c: _zero_steer_rate(system, a, b, c))(*man)
    return man


# ------------------------------------------------------------------------------------- rollout
def rollout(
    system: AbstractSystem,
    integrator: AbstractIntegrator,
    q0: Array,
    qdot0: Array,
    controls: AbstractControls,
    t_final: Array,
    n_steps: Array,
    *,
    n_out: int,
) -> tuple[Array, Array]:
    """Integrate one trajectory with ``n_steps`` steps over ``[0, t_final]``, keeping ``n_out + 1``
    evenly spaced nodes.

    The same steps and failure codes as :func:`ldap_jax.simulate` (0 success, 1 non-finite,
    2 singular, 3 not converged; NaN after the first failure), but ``t_final`` and ``n_steps``
    may be traced (``n_steps`` must be a multiple of ``n_out``): an outer ``lax.scan`` over the
    ``n_out`` output intervals, an inner ``fori_loop`` over the steps of each. Not differentiable
    in reverse mode (dynamic trip count); for gradients use :func:`ldap_jax.simulate`.

    Returns:
        ``(q_out, result)``: configurations at ``t_j = j t_final / n_out``, (n_out + 1, d), and
        the result code.
    """
    dtype = jnp.result_type(q0, qdot0)
    q0, qdot0 = jnp.asarray(q0, dtype), jnp.asarray(qdot0, dtype)
    t_final = jnp.asarray(t_final, dtype)
    n_steps = jnp.asarray(n_steps, jnp.int32)
    h = t_final / n_steps.astype(dtype)
    stride = n_steps // n_out
    fractions = jnp.asarray(integrator.control_nodes, dtype)

    def cvals(k):
        t = k.astype(dtype) * h + h * fractions
        return jax.vmap(controls)(t)

    zero = jnp.zeros((), jnp.int32)
    qdot0 = system.consistent_qdot(q0, qdot0, controls(jnp.zeros((), dtype)))
    state0 = integrator.init(system, h, q0, qdot0, cvals(zero))

    def one_step(k, carry):
        state, code = carry
        new_state, _, info = integrator.step(system, h, state, cvals(k))
        q_prev, q_next = integrator.configuration(state), integrator.configuration(new_state)
        finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in jax.tree_util.tree_leaves(new_state)]))
        step_code = jnp.where(
            ~finite, 1, jnp.where(system.singular(q_next, q_prev), 2, jnp.where(info.converged, 0, 3))
        )
        new_code = jnp.where(code == 0, step_code, code)
        keep = new_code == 0
        state = jax.tree_util.tree_map(lambda a, b: jnp.where(keep, a, b), new_state, state)
        return state, new_code

    def interval(carry, j):
        carry = jax.lax.fori_loop(j * stride, (j + 1) * stride, one_step, carry)
        state, code = carry
        q = jnp.where(code == 0, integrator.configuration(state), jnp.nan)
        return carry, q

    (_, code), q_out = jax.lax.scan(interval, (state0, zero), jnp.arange(n_out, dtype=jnp.int32))
    return jnp.concatenate([q0[None], q_out]), code


# ------------------------------------------------------------------------------------ sharding
def device_mesh(devices: Sequence[jax.Device] | None = None) -> Mesh:
    """A one-axis mesh ``("batch",)`` over ``devices`` (default: all of ``jax.devices()``, i.e.
    every GPU of the node, or of every host after ``jax.distributed.initialize()``)."""
    devices = jax.devices() if devices is None else list(devices)
    return Mesh(np.asarray(devices), ("batch",))


def shard_batch(tree, mesh: Mesh):
    """Pad the leading (batch) axis of every array leaf to a multiple of the mesh size (repeating
    the last member) and place it with ``NamedSharding(mesh, P("batch"))``.

    Returns:
        ``(sharded_tree, n)`` with ``n`` the original batch size.
    """
    leaves = jax.tree_util.tree_leaves(tree)
    n = leaves[0].shape[0]
    n_dev = mesh.devices.size
    pad = (-n) % n_dev
    sharding = NamedSharding(mesh, PartitionSpec("batch"))

    def place(x):
        x = np.asarray(x)
        if pad:
            x = np.concatenate([x, np.repeat(x[-1:], pad, axis=0)])
        return jax.device_put(x, sharding)

    return jax.tree_util.tree_map(place, tree), n


def _gather(x) -> np.ndarray:
    if jax.process_count() > 1 and not x.is_fully_addressable:  # pragma: no cover (multi-host)
        from jax.experimental import multihost_utils

        return np.asarray(multihost_utils.process_allgather(x, tiled=True))
    return np.asarray(x)


@eqx.filter_jit
def _batched(system, integrator, q0, qdot0, controls, t_final, n_steps, n_out):
    run = lambda a, b, c: rollout(system, integrator, a, b, c, t_final, n_steps, n_out=n_out)  # noqa: E731
    return jax.vmap(run)(q0, qdot0, controls)


@eqx.filter_jit
def _batched_fast(system, integrator, q0, qdot0, controls, t_final, n_steps: int, n_out: int):
    """The closed-form RDP kernel that :func:`ldap_jax.simulate` runs for the car and the
    snakeboard (``n_steps`` static), keeping every ``n_steps // n_out``-th node."""

    def run(q0, qdot0, ctl):
        zero = jnp.zeros((), q0.dtype)
        qdot0 = system.consistent_qdot(q0, qdot0, ctl(zero))
        out = _fast.rdp_rollout(system, integrator, q0, qdot0, ctl, zero, t_final / n_steps, n_steps)
        return out.q[:: n_steps // n_out], out.result

    return jax.vmap(run)(q0, qdot0, controls)


def batch_rollout(
    system: AbstractSystem,
    integrator: AbstractIntegrator,
    maneuvers,
    t_final: float,
    n_steps: int,
    *,
    n_out: int,
    mesh: Mesh | None = None,
    repeats: int = 0,
    fast_path: bool = True,
) -> tuple[np.ndarray, np.ndarray, float]:
    """:func:`rollout` over a batch of maneuvers ``(q0, qdot0, controls)``, its batch axis sharded
    over ``mesh`` (default: all devices).

    Args:
        repeats: if positive, compile ahead of time, then time ``repeats`` calls (the first
            call's results are returned).
        fast_path: as in :func:`ldap_jax.simulate`: RDP on the car and the snakeboard runs the
            closed-form kernel (compiled once per ``n_steps``) instead of the per-step
            :class:`~ldap_jax.RDP` step (same numbers to round-off, several times faster).

    Returns:
        ``(q_out (B, n_out + 1, d), result (B,), seconds)`` with ``seconds`` the median
        wall time of the timed calls for the whole batch (``nan`` when ``repeats == 0``).
    """
    if int(n_steps) % n_out:
        raise ValueError(f"'n_steps' ({n_steps}) must be a multiple of n_out ({n_out})")
    mesh = device_mesh() if mesh is None else mesh
    (q0, qdot0, ctl), n = shard_batch(maneuvers, mesh)
    dtype = q0.dtype
    t = jnp.asarray(t_final, dtype)
    ns = jnp.asarray(n_steps, jnp.int32)
    system = jax.tree_util.tree_map(
        lambda x: x.astype(dtype) if eqx.is_array(x) and jnp.issubdtype(x.dtype, jnp.floating) else x, system
    )
    if fast_path and _fast.supports(system, integrator):
        batched, args = _batched_fast, (system, integrator, q0, qdot0, ctl, t, int(n_steps), n_out)
    else:
        batched, args = _batched, (system, integrator, q0, qdot0, ctl, t, ns, n_out)
    if repeats:
        run = batched.lower(*args).compile()  # compile first: every timed call is a measurement
    else:
        run = batched
    times = []
    q_out = code = None
    for _ in range(max(repeats, 1)):
        start = time.perf_counter()
        q_out, code = jax.block_until_ready(run(*args))
        times.append(time.perf_counter() - start)
    times = times if repeats else []
    seconds = float(np.median(times)) if times else float("nan")
    return _gather(q_out)[:n], _gather(code)[:n], seconds


def reference_batch(
    system: AbstractSystem,
    maneuvers,
    t_final: float,
    *,
    n_out: int,
    step: float = 5e-3,
    mesh: Mesh | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """High-accuracy reference: RK4 on the continuous equations with a fine step (at most
    ``step``, a multiple of ``n_out`` steps), sampled at the ``n_out + 1`` output nodes.

    A converged fine-step run instead of diffrax's adaptive Dopri8, which costs too much over
    10 minutes for 1000 maneuvers; :func:`run_study` estimates its error by halving the step.

    Returns:
        ``(q_ref (B, n_out + 1, d), result (B,))``.
    """
    n_ref = n_out * max(1, math.ceil(t_final / (step * n_out)))
    q, code, _ = batch_rollout(system, RK4(), maneuvers, t_final, n_ref, n_out=n_out, mesh=mesh)
    return q, code


def position_errors(q: np.ndarray, q_ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Euclidean ``(x, y)`` errors: ``(final (B,), max over the output nodes (B,))``."""
    err = np.linalg.norm(np.asarray(q)[..., :2] - np.asarray(q_ref)[..., :2], axis=-1)
    return err[:, -1], np.max(err, axis=-1)


# ---------------------------------------------------------------------------------------- study
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
    pairs: Sequence[tuple[str, str]] = (("rdp", "rk2"), ("rdp", "rk4"), ("gni", "rdp"), ("dla", "rdp")),
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


# ------------------------------------------------------------------------------------ output
def write_csv(rows: list[dict], path: str | os.PathLike) -> None:
    """Write the study's rows (columns :data:`CSV_COLUMNS`)."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0].keys()) if rows else list(CSV_COLUMNS))
        writer.writeheader()
        for r in rows:
            writer.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})


def read_csv(path: str | os.PathLike) -> list[dict]:
    """Read a study CSV back (numbers as floats, ``n_steps`` etc. as ints)."""
    ints = {"n_steps", "runs", "failures", "nonfinite", "singular", "not_converged", "blowup"}
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
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


def plot_study(rows: list[dict], out_dir: str | os.PathLike, *, error: str = "final_error_mean") -> list[str]:
    """Figures in the style of the paper's Figs. 4 and 5, one per model and duration: position
    error vs N (log-log) and runtime per trajectory vs N, one curve per method; failed runs are
    excluded from the errors and their rate is annotated. Returns the file paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    os.makedirs(out_dir, exist_ok=True)
    paths = []
    for model, dur in sorted({(r["model"], r["duration"]) for r in rows}):
        sel = [r for r in rows if r["model"] == model and r["duration"] == dur]
        fig, (ax_e, ax_t) = plt.subplots(1, 2, figsize=(11, 4.2))
        for method in dict.fromkeys(r["method"] for r in sel):
            pts = sorted((r for r in sel if r["method"] == method), key=lambda r: r["n_steps"])
            ns = np.array([r["n_steps"] for r in pts])
            e = np.array([r[error] for r in pts], float)
            t = np.array([r["runtime_us"] for r in pts], float)
            fail = np.array([r["failure_rate"] for r in pts], float)
            style = "--" if method.startswith("rk") else "-"
            (line,) = ax_e.loglog(ns, e, style, marker="o", ms=3, label=method)
            for ni, ei, fi in zip(ns, e, fail):
                if fi > 0 and np.isfinite(ei):
                    ax_e.annotate(f"{100 * fi:.0f}%", (ni, ei), fontsize=6, color=line.get_color())
            ax_t.loglog(ns, t, style, marker="o", ms=3, color=line.get_color(), label=method)
        ns_all = sorted({int(r["n_steps"]) for r in sel})
        for ax in (ax_e, ax_t):
            ax.set_xticks(ns_all, [str(n) for n in ns_all])
            ax.minorticks_off()
        ax_e.set_xlabel("resolution N (total steps)")
        ax_e.set_ylabel(f"position error ({error.replace('_', ' ')}) [m]")
        ax_t.set_xlabel("resolution N (total steps)")
        ax_t.set_ylabel("runtime per trajectory [us]")
        runs = sel[0]["runs"]
        fig.suptitle(
            f"{model}, {_duration_label(dur)} trajectories, {runs} random maneuvers (labels: failure rate)"
        )
        ax_e.grid(True, which="both", alpha=0.3)
        ax_t.grid(True, which="both", alpha=0.3)
        ax_t.legend(fontsize=7, ncol=2)
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
