"""Shared test fixtures, and the runs that several tests share.

Compiling a rollout costs seconds (XLA), running the small ones here milliseconds, so the suite is
organised around compiled programs and their results:

* :func:`simulate_batch` is one module-level ``jit(vmap(simulate))``: every test that runs the same
  system, integrator, number of steps, batch size and options reuses one program (parametrize over
  data, not over shapes);
* :func:`simulate_ns` runs a convergence study over several step counts in one program (below);
* the results that several tests or modules read (reference solutions, convergence runs) are cached
  per worker by name with ``functools.cache``; they survive ``lj.trim_compilation_cache``.
"""

from __future__ import annotations

import contextlib
import functools
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import ldap_jax as lj

# ----------------------------------------------------------------------------------- fixtures
SYSTEMS = {"car": lj.Car(), "snakeboard": lj.Snakeboard()}


#: The library's example systems, built once: their functions are static leaves of the compiled
#: programs, so a new instance would compile anew.
SLEIGH = lj.chaplygin_sleigh()
RACER = lj.roller_racer()


def sleigh_batch():
    """Two unforced sleigh maneuvers (pose (x, y, theta), velocities (omega, v_x))."""
    q0 = jnp.array([[0.0, 0.0, 0.4], [1.0, -2.0, -2.5]])
    v0 = jnp.array([[1.5, 0.5], [-2.0, 0.8]])
    qdot0 = jax.jit(jax.vmap(lambda q, v: SLEIGH.qdot_from_velocities(q, v, jnp.zeros(0))))(q0, v0)
    return q0, qdot0, lj.Constant(jnp.zeros((2, 0)))


@functools.cache
def sleigh_newton_run(retraction: str) -> lj.Trajectory:
    """10^4 general (Newton) RDP steps of the library's sleigh over 200 s."""
    return simulate_batch(
        SLEIGH, lj.RDP(retraction=retraction, solver="newton"), sleigh_batch(), 200.0, 10_000
    )


def systems():
    """The paper's models with the library's default parameters."""
    return dict(SYSTEMS)


#: name -> (integrator, expected order)
INTEGRATORS = {
    "rdp_exp": (lj.RDP(alpha=0.5, retraction="exp"), 2),
    "rdp_cayley": (lj.RDP(alpha=0.5, retraction="cayley"), 2),
    "rdp_exact_dexp": (lj.RDP(alpha=0.5, dtau_order=None), 2),
    "rdp_alpha0": (lj.RDP(alpha=0.0), 1),
    "rdp_alpha1": (lj.RDP(alpha=1.0), 1),
    "rdp_alpha1_cayley": (lj.RDP(alpha=1.0, retraction="cayley"), 1),
    "rk2": (lj.RK2(), 2),
    "rk4": (lj.RK4(), 4),
    "dla": (lj.DLA(), 2),
    "dla_alpha0": (lj.DLA(alpha=0.0), 1),
    "gni": (lj.GNI(), 2),
    "gni_folded": (lj.GNI(variant="folded"), 2),
}


def integrators():
    """(name, integrator, expected order) of the RDP variants and the RK baselines."""
    names = (
        "rdp_exp",
        "rdp_cayley",
        "rdp_exact_dexp",
        "rdp_alpha0",
        "rdp_alpha1",
        "rdp_alpha1_cayley",
        "rk2",
        "rk4",
    )
    return [(n, *INTEGRATORS[n]) for n in names]


def maneuvers(system, n, seed=0):
    """A batch of ``n`` random maneuvers ``(q0, qdot0, controls)`` (leading batch axis): the
    study's sampler, without its snakeboard steering-rate adjustment."""
    from ldap_jax import study

    return study.sample_maneuvers(system, n, seed, zero_steer_rate=False)


@eqx.filter_jit  # one program, not op by op
def discrete_momenta(system, q, hs, alpha):
    """The discrete momenta rebuilt from configurations alone (steps ``hs``, quadrature point
    ``alpha``, exp retraction): ``u_k = (r_{k+1} - r_k) / h_k``, ``xi_k = log(g_k^-1 g_{k+1}) / h_k``,
    ``(dl_du, mu)_k`` at ``(r_k + alpha h_k u_k, u_k, xi_k)``, and the jumps at the interior nodes
    ``dtau^-1(h_k xi_k)^T mu_k - dtau^-1(-h_{k-1} xi_{k-1})^T mu_{k-1}`` of (21) and (23)."""
    from ldap_jax import lie

    rel = jax.vmap(lambda g0, g1: lie.compose(lie.inverse(g0), g1))(q[:-1, :3], q[1:, :3])
    xi = jax.vmap(lie.log)(rel) / hs[:, None]
    u = (q[1:, 3:] - q[:-1, 3:]) / hs[:, None]
    r_a = q[:-1, 3:] + alpha * hs[:, None] * u
    dl_du, mu = jax.vmap(jax.grad(system.reduced_lagrangian, argnums=(1, 2)))(r_a, u, xi)
    out = jax.vmap(lambda v, m: lie.dtau_inv(v, "exp", 1).T @ m)(hs[:, None] * xi, mu)
    inc = jax.vmap(lambda v, m: lie.dtau_inv(-v, "exp", 1).T @ m)(hs[:, None] * xi, mu)
    return dl_du, mu, out[1:] - inc[:-1]


_COMPILE_EVENTS = {
    "compile": "/jax/core/compile/backend_compile_duration",
    "trace": "/jax/core/compile/jaxpr_trace_duration",
}


@contextlib.contextmanager
def eager_operations():
    """Yield a list that collects the names of the primitives run eagerly inside the block (each
    one a compiled program of its own in a new process)."""
    from jax._src import core

    names: list[str] = []
    run = core.EvalTrace.process_primitive

    def counted(self, primitive, args, params):
        names.append(primitive.name)
        return run(self, primitive, args, params)

    core.EvalTrace.process_primitive = counted
    try:
        yield names
    finally:
        core.EvalTrace.process_primitive = run


@contextlib.contextmanager
def compiled_programs(stage: str = "compile"):
    """Yield a list that collects the names of the programs XLA compiles inside the block
    (e.g. ``"jit(_run)"``); ``stage="trace"``: of the functions JAX traces for ``jit`` (e.g.
    ``"_run"``), which a hit in the persistent compilation cache does not skip."""
    from jax._src import monitoring

    names: list[str] = []
    wanted = _COMPILE_EVENTS[stage]

    def listen(event, duration, **kwargs):
        if event == wanted:
            names.append(kwargs.get("fun_name"))

    monitoring.register_event_duration_secs_listener(listen)
    try:
        yield names
    finally:
        monitoring.unregister_event_duration_listener(listen)


def _on_host(fn):
    """``fn`` applied to host copies of concrete leaves (no compiled program per operation and
    shape, as an eager ``jnp`` operation would be), to the leaves themselves under a trace. The
    result goes back by ``jax.device_put``: ``jnp.asarray`` of a host array compiles an identity
    program (``jit(stage)``) per shape and dtype in this JAX."""

    def apply(*xs):
        if any(isinstance(x, jax.core.Tracer) for x in xs):
            return fn(*xs)
        return jax.device_put(fn(*(np.asarray(x) for x in xs)))

    return apply


def index(tree, i):
    return jax.tree_util.tree_map(_on_host(lambda x: x[i]), tree)


def stack(*trees):
    """Concatenate batches (pytrees with a leading batch axis) along that axis."""
    return jax.tree_util.tree_map(_on_host(lambda *xs: np.concatenate(xs)), *trees)


def fitted_order(hs, errs):
    """Least-squares slope of log(err) against log(h)."""
    return float(np.polyfit(np.log(np.asarray(hs)), np.log(np.asarray(errs)), 1)[0])


def pose_error(q, q_ref):
    """Max over the batch of the Euclidean error in (x, y, theta)."""
    q, q_ref = np.asarray(q), np.asarray(q_ref)
    return float(np.max(np.linalg.norm(q[..., :3] - q_ref[..., :3], axis=-1)))


def code(result) -> np.ndarray:
    """Integer result codes of a (batched) ``lj.RESULTS`` item."""
    return np.asarray(result._value)


# ------------------------------------------------------------------------------ shared programs
@eqx.filter_jit
def _simulate_batch(system, integrator, q0, qdot0, controls, t_final, n_steps, options):
    def one(a, b, c, tf):
        return lj.simulate(
            system, a, b, c, t_final=tf, n_steps=n_steps, integrator=integrator, **dict(options)
        )

    return jax.vmap(one)(q0, qdot0, controls, t_final)


def simulate_batch(system, integrator, batch, t_final, n_steps, **options) -> lj.Trajectory:
    """``vmap(simulate)`` over a batch ``(q0, qdot0, controls)`` in one compiled program, shared by
    every call with the same system type, integrator, ``n_steps``, batch size and options (the
    values of the system's parameters, the maneuvers and ``t_final`` are data). ``t_final`` is a
    scalar or one value per member."""
    q0, qdot0, ctl = batch
    tf = jnp.broadcast_to(jnp.asarray(t_final, q0.dtype), q0.shape[:1])
    return _simulate_batch(
        system, integrator, q0, qdot0, ctl, tf, int(n_steps), tuple(sorted(options.items()))
    )


class Run(NamedTuple):
    """A batch of trajectories restricted to nodes ``0..n`` (numpy arrays, leading batch axis).

    ``result`` and ``failure_index`` describe the first ``n`` steps: a failure at a later step (the
    run went on past ``t_final``, see :func:`simulate_ns`) does not count."""

    t: np.ndarray
    q: np.ndarray
    qdot: np.ndarray
    energy: Any
    work: Any
    momentum: Any
    constraint_residual: Any
    step_residual: Any
    converged: np.ndarray
    result: np.ndarray  # integer codes
    failure_index: np.ndarray

    @property
    def failed(self) -> np.ndarray:
        return self.result != 0

    @property
    def energy_balance(self) -> np.ndarray:
        return self.energy - self.energy[..., :1] - self.work


def simulate_ns(system, integrator, batch, t_final, ns, **options) -> dict[int, Run]:
    """Trajectories of ``batch`` over ``[0, t_final]`` with each number of steps in ``ns``, from
    one compiled program.

    Member ``(n, maneuver)`` runs ``max(ns)`` steps of size ``h = t_final / n`` (its ``t_final`` is
    ``t_final * max(ns) / n``), and its nodes ``0..n`` are returned. The ratios ``max(ns) / n`` are
    powers of two, so ``h`` and the node times are bit for bit those of
    ``simulate(..., t_final=t_final, n_steps=n)``: the first ``n`` steps are the same computation.
    What the members do after ``t_final`` (a failure, say) is not reported.
    """
    n_max = max(ns)
    for n in ns:
        ratio = n_max // n
        if n_max % n or ratio & (ratio - 1):
            raise ValueError(f"max(ns) / n must be a power of two, got {ns}")
    q0 = batch[0]
    b = q0.shape[0]
    k = len(ns)
    tiled = jax.tree_util.tree_map(_on_host(lambda x: np.concatenate([x] * k)), batch)
    scale = np.repeat(np.asarray([n_max // n for n in ns], float), b)
    traj = simulate_batch(system, integrator, tiled, jnp.asarray(t_final * scale, q0.dtype), n_max, **options)
    out = {}
    for j, n in enumerate(ns):
        sel = slice(j * b, (j + 1) * b)

        def nodes(x, sel=sel, n=n):
            return None if x is None else np.asarray(x)[sel, : n + 1]

        fi = np.asarray(traj.failure_index)[sel]
        codes = np.where(fi < n, code(traj.result)[sel], 0)
        out[n] = Run(
            t=nodes(traj.t),
            q=nodes(traj.q),
            qdot=nodes(traj.qdot),
            energy=nodes(traj.energy),
            work=nodes(traj.work),
            momentum=nodes(traj.momentum),
            constraint_residual=nodes(traj.constraint_residual),
            step_residual=nodes(traj.step_residual),
            converged=nodes(traj.converged),
            result=codes,
            failure_index=np.minimum(fi, n),
        )
    return out


@eqx.filter_jit
def _simulate_over_alphas(system, batch, alphas, t_final, n_steps, rdp_options, simulate_options):
    def one(alpha, q0, qdot0, ctl):
        integrator = lj.RDP(alpha=alpha, **dict(rdp_options))
        options = dict(simulate_options, t_final=t_final, n_steps=n_steps, integrator=integrator)
        return lj.simulate(system, q0, qdot0, ctl, **options)

    return jax.vmap(lambda a: jax.vmap(lambda q, qd, c: one(a, q, qd, c))(*batch))(alphas)


def simulate_over_alphas(
    system, batch, alphas, t_final, n_steps, simulate_options=None, **rdp_options
) -> list[lj.Trajectory]:
    """``lj.RDP(alpha, **rdp_options)`` on a batch for every alpha in ``alphas``, in one program:
    alpha is traced (one value per member), so the three values of a comparison over alpha share
    one compilation. A closed-form kernel then runs its general branch (no special case for a
    Python float alpha in {0, 1}). ``simulate_options``: more arguments of ``lj.simulate`` (e.g.
    ``{"diagnostics": False}``: a smaller program when nothing reads them). Returns one batched
    trajectory per alpha."""
    dtype = batch[0].dtype
    out = _simulate_over_alphas(
        system,
        batch,
        jnp.asarray(alphas, dtype),
        jnp.asarray(t_final, dtype),
        int(n_steps),
        tuple(sorted(rdp_options.items())),
        tuple(sorted((simulate_options or {}).items())),
    )
    return [index(out, i) for i in range(len(alphas))]


@eqx.filter_jit
def _reference_batch(system, q0, qdot0, controls, ts, rtol, atol):
    return jax.vmap(lambda a, b, c: lj.reference(system, a, b, c, ts, rtol=rtol, atol=atol))(
        q0, qdot0, controls
    )


def reference_batch(system, batch, ts, rtol=1e-11, atol=1e-11) -> lj.Solution:
    """``vmap(lj.reference)`` over a batch, one compiled program per system, batch size and
    number of samples."""
    return _reference_batch(system, *batch, jnp.asarray(ts), float(rtol), float(atol))


# ------------------------------------------------------------------------------- shared results
#: The convergence studies (test_convergence, test_dla_gni): 3 maneuvers over 2 s.
CONV_T, CONV_SEED, CONV_BATCH = 2.0, 11, 3
CONV_NS = {1: (40, 80, 160), 2: (40, 80, 160), 4: (20, 40, 80)}
CONV_GRID = 40  # errors measured at the 41 nodes of the coarsest second-order run


@functools.cache
def convergence_case(sys_name: str):
    """``(maneuvers, reference at CONV_GRID + 1 times)``, computed once per worker."""
    system = SYSTEMS[sys_name]
    man = maneuvers(system, CONV_BATCH, seed=CONV_SEED)
    ref = reference_batch(system, man, jnp.linspace(0.0, CONV_T, CONV_GRID + 1), rtol=1e-12, atol=1e-12)
    assert not bool(jnp.any(ref.failed))
    return man, jax.tree_util.tree_map(np.asarray, ref)


@functools.cache
def convergence_runs(sys_name: str, int_name: str, diagnostics: bool = True) -> dict[int, Run]:
    """The runs of ``INTEGRATORS[int_name]`` at the step counts of its order (``CONV_NS``), one
    program per system, integrator and ``diagnostics`` (without them: positions, velocities and
    the result only, a smaller program)."""
    integrator, order = INTEGRATORS[int_name]
    man, _ = convergence_case(sys_name)
    ns = CONV_NS[min(order, 4)]
    return simulate_ns(SYSTEMS[sys_name], integrator, man, CONV_T, ns, diagnostics=diagnostics)


def on_grid(run: Run, n: int, grid: int = CONV_GRID) -> Run:
    """The nodes of an ``n``-step run at the ``grid + 1`` times of the coarse grid."""
    stride = n // grid if n >= grid else None
    if stride is None:
        raise ValueError(f"n={n} is coarser than the grid {grid}")
    return run._replace(
        **{
            f: (None if getattr(run, f) is None else getattr(run, f)[:, ::stride])
            for f in (
                "t",
                "q",
                "qdot",
                "energy",
                "work",
                "momentum",
                "constraint_residual",
                "step_residual",
                "converged",
            )
        }
    )


#: the steered sleigh's length from the rear knife edge to its steerable front wheel (m)
STEERED_SLEIGH_LENGTH = 0.8


def steered_sleigh(basis: str = "regular", **options) -> lj.System:
    """A sleigh (rear knife edge, offset centre of mass) with a steerable front knife edge at
    ``(L, 0)`` whose wheel has inertia and a steering spring: shape ``phi``. ``basis="regular"``:
    ``e = (sin phi, L cos phi, 0)``; ``"tan"``: ``e = (tan(phi) / L, 1, 0)``, unbounded at
    ``cos(phi) = 0``. ``options`` go to :class:`lj.System` (``kinematic=``, ``singularity=``)."""
    m, inertia, a, b, mf, length, jf, k = 1.0, 0.15, 0.4, 0.05, 0.3, STEERED_SLEIGH_LENGTH, 0.04, 0.5

    def lagrangian(r, u, xi):
        om, vx, vy = xi
        kinetic = m * ((vx - om * b) ** 2 + (vy + om * a) ** 2) + inertia * om**2
        kinetic = kinetic + mf * (vx**2 + (vy + om * length) ** 2) + jf * (om + u[0]) ** 2
        return 0.5 * kinetic - 0.5 * k * r[0] ** 2

    bases = {
        "regular": lambda r: jnp.stack([jnp.sin(r[0]), length * jnp.cos(r[0]), 0.0 * r[0]])[:, None],
        "tan": lambda r: jnp.stack([jnp.tan(r[0]) / length, 1.0 + 0.0 * r[0], 0.0 * r[0]])[:, None],
    }
    return lj.System(
        1,
        lagrangian,
        lambda r: jnp.zeros((3, 1)),
        bases[basis],
        lambda r: jnp.array(
            [[0.0, 0.0, 1.0, 0.0], [length * jnp.cos(r[0]), -jnp.sin(r[0]), jnp.cos(r[0]), 0.0]]
        ),
        **options,
    )
