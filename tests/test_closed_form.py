"""The closed-form RDP kernels equal the general Newton step, and a new closed-form system needs
nothing but its own file.

Systems with a closed form (:class:`lj.systems.AbstractClosedFormSystem`: the car and the
snakeboard) run an explicit kernel under ``lj.RDP()`` (``dtau_order=1``, ``solver="auto"``); the
general step ``lj.RDP(solver="newton")`` solves the same equations (21), (23) by Newton's method.
They must give the same trajectory, diagnostics, failure reports and gradients to round-off: in
float64 a small multiple of eps per step; in float32 no further from the Newton run than that
run's own float32 round-off (its distance to the float64 run) allows.

The Newton runs are batched over alpha (a traced ``RDP.alpha``: one program for the three values);
the kernels take alpha as a Python float, as users write it (the snakeboard kernel has branches
for alpha in {0, 1}).
"""

from __future__ import annotations

import functools
from typing import ClassVar, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import (
    SLEIGH,
    SYSTEMS,
    code,
    maneuvers,
    simulate_batch,
    simulate_over_alphas,
    sleigh_batch,
    sleigh_newton_run,
    stack,
)

import ldap_jax as lj
from ldap_jax import lie
from ldap_jax._numerics import sincos
from ldap_jax.systems import body_velocity, spatial_velocity

T_FINAL, N_STEPS, BATCH, SEED = 10.0, 500, 3, 3
ALPHAS = (0.0, 0.5, 1.0)
FIELDS = ("q", "qdot", "energy", "work", "momentum")


def _cast(tree, dtype):
    return jax.tree_util.tree_map(lambda x: x.astype(dtype) if eqx.is_inexact_array(x) else x, tree)


# two snakeboard maneuvers from rest (controls padded to the random maneuvers' two terms): a rotor
# torque only, and a constant steering torque that drives phi through pi/2 (RESULTS.singular)
FAILURE_BATCH = (
    jnp.zeros((2, 5)),
    jnp.zeros((2, 5)),
    lj.Sinusoids(
        amplitude=jnp.array([[[0.05, 0.0], [0.0, 0.0]], [[0.05, 0.0], [0.02, 0.0]]]),
        frequency=jnp.array([[[1.0, 1.0], [0.0, 1.0]], [[1.0, 1.0], [0.0, 1.0]]]),
        phase=jnp.array([[[0.0, 0.0], [0.0, 0.0]], [[0.0, 0.0], [np.pi / 2, 0.0]]]),
    ),
)


def _batch(name):
    """BATCH random maneuvers; for the snakeboard followed by the two of FAILURE_BATCH."""
    batch = maneuvers(SYSTEMS[name], BATCH, seed=SEED)
    return stack(batch, FAILURE_BATCH) if name == "snakeboard" else batch


@functools.cache
def _kernel_run(name: str, retraction: str, dtype: str, alpha: float):
    """The kernel's trajectories at one alpha (a Python float: one program per alpha), per worker."""
    dt = jnp.dtype(dtype)
    system, batch = _cast(SYSTEMS[name], dt), _cast(_batch(name), dt)
    return simulate_batch(system, lj.RDP(alpha=alpha, retraction=retraction), batch, T_FINAL, N_STEPS)


@functools.cache
def _newton_runs(name: str, retraction: str, dtype: str):
    """Newton's trajectories at every alpha of ALPHAS (one program), per worker."""
    dt = jnp.dtype(dtype)
    system, batch = _cast(SYSTEMS[name], dt), _cast(_batch(name), dt)
    return simulate_over_alphas(
        system, batch, ALPHAS, T_FINAL, N_STEPS, retraction=retraction, solver="newton"
    )


def _members(traj, sel):
    """Host copies of the members ``sel`` (NumPy: no program compiled per field and shape)."""
    return jax.tree_util.tree_map(lambda x: np.asarray(x)[sel] if eqx.is_array(x) and x.ndim else x, traj)


def _maxdiff(a, b):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.max(np.abs(a - b))) if a.size else 0.0


def _scale(a):
    a = np.asarray(a, np.float64)
    return 1.0 + (float(np.max(np.abs(a))) if a.size else 0.0)


def _assert_equal_to_roundoff(kern, newt, n_steps, label):
    eps = float(jnp.finfo(jnp.float64).eps)
    # round-off accumulates at most linearly in the number of steps
    tol = 10 * eps * n_steps
    assert not np.any(code(newt.result) != 0), (label, code(newt.result))
    for field in FIELDS:
        a, b = getattr(kern, field), getattr(newt, field)
        assert a.shape == b.shape and a.dtype == b.dtype, (label, field)
        assert _maxdiff(a, b) <= tol * _scale(b), (label, field, _maxdiff(a, b), tol * _scale(b))
    # residual-type outputs are round-off themselves: both tiny relative to the velocities
    vel = _scale(newt.qdot)
    for field in ("constraint_residual", "step_residual"):
        assert float(np.max(np.asarray(getattr(kern, field)))) <= 100 * eps * vel, (label, field)
        assert float(np.max(np.asarray(getattr(newt, field)))) <= 100 * eps * vel, (label, field)
    assert bool(np.all(np.asarray(newt.converged))) and bool(np.all(np.asarray(kern.converged)))
    np.testing.assert_array_equal(code(kern.result), code(newt.result))
    np.testing.assert_array_equal(kern.failure_index, newt.failure_index)
    np.testing.assert_array_equal(kern.t, newt.t)


@pytest.mark.parametrize("retraction", ["exp", "cayley"])
@pytest.mark.parametrize("name", list(SYSTEMS))
def test_kernel_equals_newton_float64(name, retraction):
    """Every alpha in {0, 1/2, 1}: the closed form and Newton agree to round-off over 500 steps,
    and report a failure (the snakeboard's singularity) at the same step, NaN after it."""
    system = SYSTEMS[name]
    newton = _newton_runs(name, retraction, "float64")
    for alpha, newt in zip(ALPHAS, newton):
        kern = _kernel_run(name, retraction, "float64", alpha)
        assert lj.RDP(alpha=alpha, retraction=retraction).uses_kernel(system)
        random = slice(0, BATCH)
        _assert_equal_to_roundoff(
            _members(kern, random), _members(newt, random), N_STEPS, (name, retraction, alpha)
        )
        if name == "snakeboard":
            _assert_same_failures(_members(kern, slice(BATCH, None)), _members(newt, slice(BATCH, None)))


def _assert_same_failures(kern, newt):
    """FAILURE_BATCH: the first run succeeds, the second is singular at the same step."""
    np.testing.assert_array_equal(code(kern.result), [0, lj.RESULTS.singular._value])
    np.testing.assert_array_equal(code(kern.result), code(newt.result))
    np.testing.assert_array_equal(kern.failure_index, newt.failure_index)
    assert int(kern.failure_index[0]) == N_STEPS
    for field in ("q", "qdot", "energy", "work", "momentum", "constraint_residual"):
        a, b = np.asarray(getattr(kern, field)), np.asarray(getattr(newt, field))
        np.testing.assert_array_equal(np.isnan(a), np.isnan(b), err_msg=field)
    k = int(kern.failure_index[1])
    assert 0 < k < N_STEPS and np.all(np.isfinite(np.asarray(kern.q[1, : k + 1])))
    assert np.all(np.isnan(np.asarray(kern.q[1, k + 1 :])))
    np.testing.assert_allclose(kern.q[:, : k + 1], newt.q[:, : k + 1], rtol=0, atol=1e-10)


@pytest.mark.parametrize("name", list(SYSTEMS))
def test_kernel_equals_newton_order_4(name):
    """The composition (5 substeps, two of them backwards) runs the kernel per substep."""
    system = SYSTEMS[name]
    batch = maneuvers(system, BATCH, seed=SEED)
    n = N_STEPS // 5
    kern = simulate_batch(system, lj.RDP(order=4), batch, T_FINAL, n)
    newt = simulate_batch(system, lj.RDP(order=4, solver="newton"), batch, T_FINAL, n)
    _assert_equal_to_roundoff(kern, newt, 5 * n, (name, "order 4"))


# every alpha and both retractions appear for each model, and the default RDP() (each case compiles a
# float32 kernel; the float32 Newton runs cover every alpha of a retraction at once)
F32_CASES = [
    ("car", 0.0, "cayley"),
    ("car", 0.5, "exp"),
    ("car", 1.0, "exp"),
    ("snakeboard", 0.0, "exp"),
    ("snakeboard", 0.5, "exp"),
    ("snakeboard", 0.5, "cayley"),
    ("snakeboard", 1.0, "cayley"),
]


# The car's kernel solves (23) for the wheel rate in ratio form, then takes one Newton correction on
# the residual in difference form (as the Newton step writes it). Without the correction the ratio
# form's rounding biased the wheel rate by ~eps per step: in float32 psi ended 10x further from float64
# than under Newton over these 500 steps (this test found it).


@pytest.mark.parametrize(
    "name,alpha,retraction",
    F32_CASES,
)
def test_kernel_equals_newton_float32(name, alpha, retraction):
    i = ALPHAS.index(alpha)
    kern32 = _kernel_run(name, retraction, "float32", alpha)
    newt32 = _newton_runs(name, retraction, "float32")[i]
    ref = _newton_runs(name, retraction, "float64")[i]
    for traj in (kern32, newt32):
        for field in FIELDS + ("t", "constraint_residual", "step_residual"):
            assert getattr(traj, field).dtype == jnp.float32, field
    np.testing.assert_array_equal(code(kern32.result), code(ref.result))
    random = slice(0, BATCH)
    kern32, newt32, ref = (_members(x, random) for x in (kern32, newt32, ref))
    eps32 = float(jnp.finfo(jnp.float32).eps)
    for field in FIELDS:
        a, b, c = getattr(kern32, field), getattr(newt32, field), getattr(ref, field)
        own_roundoff = _maxdiff(b, c)  # the Newton step's float32 error
        assert _maxdiff(a, b) <= 4 * own_roundoff + 10 * eps32 * _scale(c), (
            field,
            _maxdiff(a, b),
            own_roundoff,
        )
    np.testing.assert_array_equal(code(kern32.result), code(newt32.result))


@pytest.mark.parametrize("name", list(SYSTEMS))
def test_gradients_match(name):
    """Reverse-mode gradients of a cost on a middle and the final node, in the parameters, the
    initial states and the controls: through the kernel and through Newton (implicit function
    theorem) they agree; for the car, every rematerialisation policy gives the same gradient: per
    step and chunks of 7 steps (which do not divide N: the padded chunk loop) on the kernel path,
    nested sqrt(N) chunks (18 steps, also padded) on the Newton path. (The policies belong to the
    rollout loop, which is the same for every system; the car's gradient programs compile in
    about 2.3 s against the snakeboard's 3.6 s.)"""
    system = SYSTEMS[name]
    # one maneuver, without vmap: batching adds nothing to what is compared, only tracing time
    q0, qdot0, ctl = jax.tree_util.tree_map(lambda x: x[0], maneuvers(system, 2, seed=5))
    grad = eqx.filter_jit(jax.grad(_gradient_loss, argnums=(0, 1, 2)))
    policies = {"auto": (False, True, 7), "newton": (False, "sqrt")} if name == "car" else {}
    g = {
        (solver, policy): grad(system, q0, qdot0, ctl, lj.RDP(solver=solver), policy)
        for solver in ("auto", "newton")
        for policy in policies.get(solver, (False,))
    }
    plain = g["newton", False]
    assert max(float(np.max(np.abs(np.asarray(x)))) for x in jax.tree_util.tree_leaves(plain)) > 1e-6
    for (solver, policy), gi in g.items():
        for a, b, c in zip(*(jax.tree_util.tree_leaves(x) for x in (gi, g[solver, False], plain))):
            assert np.all(np.isfinite(np.asarray(a))), (solver, policy)
            np.testing.assert_allclose(a, b, rtol=1e-11, atol=1e-12, err_msg=str((solver, policy)))
            np.testing.assert_allclose(a, c, rtol=1e-9, atol=1e-9 * _scale(c), err_msg=str((solver, policy)))


def _gradient_loss(system, q0, qdot0, ctl, integrator, checkpoint):
    traj = lj.simulate(
        system, q0, qdot0, ctl, t_final=5.0, n_steps=300, integrator=integrator, checkpoint=checkpoint
    )
    return jnp.sum(traj.q[-1, :3] ** 2) + traj.energy[-1] + jnp.sum(traj.q[150] ** 2)


def test_sincos_accuracy_and_derivative():
    rng = np.random.default_rng(0)
    for dtype, lim, ulps in ((np.float64, 1e4, 2.0), (np.float32, 1e3, 2.0)):
        x = np.concatenate([rng.uniform(-4, 4, 20000), rng.uniform(-lim, lim, 20000)]).astype(dtype)
        s, c = jax.jit(sincos)(x)
        assert s.dtype == dtype
        x64 = x.astype(np.float64)
        # absolute error in units of eps: the reduction's error is absolute, ~ |n| eps_pio2
        err_s = np.abs(np.asarray(s, np.float64) - np.sin(x64)) / np.finfo(dtype).eps
        err_c = np.abs(np.asarray(c, np.float64) - np.cos(x64)) / np.finfo(dtype).eps
        assert err_s.max() <= ulps and err_c.max() <= ulps, (dtype, err_s.max(), err_c.max())
    t = jnp.linspace(-3, 3, 7)
    ds = jax.vmap(jax.grad(lambda t: sincos(t)[0]))(t)
    dc = jax.vmap(jax.grad(lambda t: sincos(t)[1]))(t)
    np.testing.assert_allclose(ds, np.cos(np.linspace(-3, 3, 7)), rtol=1e-15, atol=1e-15)
    np.testing.assert_allclose(dc, -np.sin(np.linspace(-3, 3, 7)), rtol=1e-15, atol=1e-15)


def test_sincos_quadrant_beyond_the_int32_range():
    """The quadrant ``round(2x/pi) mod 4`` is taken in floating point: an int32 cast wrapped once
    ``2x/pi`` passed 2^31 (|x| > 3.37e9: controls timed from Unix time at 2 rad/s), turning sin and
    cos by a quarter turn with no error reported."""
    x = np.array([3.3e9, 3.374e9, 3.4e9, -5e9, 1e10, 2.0**40, 1.75e9 * 2])
    s, c = jax.jit(sincos)(x)
    np.testing.assert_allclose(np.asarray(s), np.sin(x), atol=1e-6)
    np.testing.assert_allclose(np.asarray(c), np.cos(x), atol=1e-6)


def test_dispatch():
    """RDP runs the kernel of every closed-form system (subclasses included) with dtau_order=1 and
    solver="auto"; anything else takes the Newton step."""
    sb, car = SYSTEMS["snakeboard"], SYSTEMS["car"]

    class MySnakeboard(lj.Snakeboard):
        pass

    assert lj.RDP().uses_kernel(sb)
    assert lj.RDP(alpha=1.0, retraction="cayley").uses_kernel(car)
    assert lj.RDP(order=6).uses_kernel(sb)
    assert lj.RDP().uses_kernel(MySnakeboard())
    assert lj.RDP().uses_kernel(ClosedFormSleigh())
    assert not lj.RDP(dtau_order=None).uses_kernel(sb)
    assert not lj.RDP(dtau_order=2).uses_kernel(car)
    assert not lj.RDP(solver="newton").uses_kernel(sb)
    assert not lj.RDP().uses_kernel(lj.chaplygin_sleigh())
    assert not lj.RDP().implicit and lj.RDP(solver="newton").implicit and lj.RDP(dtau_order=None).implicit


# ------------------------------------------------------------------- a new closed-form system
class SleighState(NamedTuple):
    """Pose ``(x, y, theta)`` and incoming momentum ``mu = (dtau^-1_{-h xi})^* d_xi l`` (3,)."""

    q: jax.Array
    mu: jax.Array


def _monotone_cubic_root(c3, c1, nu):
    """The real root of ``c3 w^3 + c1 w = nu`` for ``c3 >= 0``, ``c1 > 0`` (the cubic is increasing).

    Cardano's formula for the one real root of ``w^3 + p w + q = 0`` with ``p = c1/c3 > 0``, in its
    hyperbolic form ``w = -2 sqrt(p/3) sinh(asinh((3 q / (2 p)) sqrt(3/p)) / 3)`` (the algebraic form
    cancels catastrophically for a small step, where ``w ~ nu / c1``), written with ``c1, c3`` so
    that ``c3 -> 0`` is benign; ``c3 = 0`` is the linear case ``w = nu / c1``.
    """
    cubic = c3 > 0
    c3s = jnp.where(cubic, c3, jnp.ones_like(c3))
    x = -(1.5 * nu / c1) * jnp.sqrt(3 * c3s / c1)
    w = -2 * jnp.sqrt(c1 / (3 * c3s)) * jnp.sinh(jnp.arcsinh(x) / 3)
    return jnp.where(cubic, w, nu / c1)


class ClosedFormSleigh(lj.systems.AbstractClosedFormSystem):
    r"""The Chaplygin sleigh of ``lj.chaplygin_sleigh`` with a closed-form RDP step.

    ``Q = SE(2)``, no shape, ``l = (m v_x^2 + m (v_y + a omega)^2 + I omega^2) / 2``, constraint
    ``v_y = 0``, ``e = [(1, 0, 0), (0, 1, 0)]``. With ``xi = (omega, v, 0)`` and
    ``d_xi l = (J omega, m v, m a omega)``, ``J = I + m a^2``, the vertical equations (21) with
    ``dtau^-1 = I - ad/2``, ``e^T (dtau^-1_{h xi}^T d_xi l - mu_in) = 0``, read
    ``J omega + h m a v omega / 2 = nu_1`` and ``m v - h m a omega^2 / 2 = nu_2`` (``nu = e^T mu_in``),
    i.e. ``v = nu_2 / m + h a omega^2 / 2`` and the cubic
    ``(J + h a nu_2 / 2) omega + (h^2 m a^2 / 4) omega^3 = nu_1``, solved in closed form.
    """

    m: jax.Array = eqx.field(converter=lambda x: jnp.asarray(x, float), default=1.0)
    I: jax.Array = eqx.field(converter=lambda x: jnp.asarray(x, float), default=0.2)  # noqa: E741
    a: jax.Array = eqx.field(converter=lambda x: jnp.asarray(x, float), default=0.3)

    shape_names: ClassVar[tuple[str, ...]] = ()
    control_names: ClassVar[tuple[str, ...]] = ()
    kinematic: ClassVar[tuple[bool, ...]] = ()
    n_velocities: ClassVar[int] = 2

    def parameter_checks(self):
        return tuple((f"parameter {n!r} must be positive", getattr(self, n) > 0) for n in ("m", "I", "a"))

    # reduced view
    def reduced_lagrangian(self, r, u, xi):
        return 0.5 * (self.m * xi[1] ** 2 + self.m * (xi[2] + self.a * xi[0]) ** 2 + self.I * xi[0] ** 2)

    def connection(self, r):
        return jnp.zeros((3, 0), r.dtype)

    def symmetry_basis(self, r):
        return jnp.eye(3, 2, dtype=r.dtype)

    def inputs(self, controls):
        return controls, controls  # no channels

    def body_constraints(self, r):
        return jnp.array([[0.0, 0.0, 1.0]], dtype=r.dtype)

    # minimal continuous form, v = (omega, v_x)
    def qdot_from_velocities(self, q, v, u_kin):
        return spatial_velocity(q, jnp.stack([v[0], v[1], jnp.zeros_like(v[0])]))

    def velocities_from_qdot(self, q, qdot):
        return body_velocity(q, qdot)[:2]

    def velocity_dynamics(self, q, v, f, u_kin):
        omega, vx = v
        inertia = self.I + self.m * self.a**2
        return jnp.stack([-self.m * self.a * vx * omega / inertia, self.a * omega**2])

    # the closed-form RDP step
    def kernel_init(self, q, pu, mu):
        return SleighState(q=q, mu=mu)

    def kernel_momenta(self, state):
        return state.q, jnp.zeros((0,), state.q.dtype), state.mu

    def kernel_step(self, alpha, h, retraction, state, c0, c1):
        m, a = self.m, self.a
        inertia = self.I + m * a**2
        nu1, nu2 = state.mu[0], state.mu[1]
        c1_ = inertia + 0.5 * h * a * nu2
        omega = _monotone_cubic_root(0.25 * h**2 * m * a**2, c1_, nu1)
        v = nu2 / m + 0.5 * h * a * omega**2
        p = jnp.stack([inertia * omega, m * v, m * a * omega])  # d_xi l
        hw, hv = h * omega, h * v
        ad_t_p = jnp.stack([-hv * p[2], hw * p[2], -hw * p[1]])  # ad_{h xi}^T d_xi l
        jump = p - 0.5 * ad_t_p - state.mu  # dtau^-1_{h xi}^T d_xi l - mu_in
        residual = jnp.linalg.norm(jump[:2]) / (1.0 + jnp.linalg.norm(state.mu))
        xi = jnp.stack([omega, v, jnp.zeros_like(v)])
        new = SleighState(q=lie.compose(state.q, lie.retract(h * xi, retraction)), mu=p + 0.5 * ad_t_p)
        # the cubic is monotone (one real root) for J + h a nu_2 / 2 > 0: beyond, a fold
        return new, residual, ~(c1_ > 0)

    def kernel_observe(self, state, c):
        inertia = self.I + self.m * self.a**2
        omega, v = state.mu[0] / inertia, state.mu[1] / self.m
        xi = jnp.stack([omega, v, jnp.zeros_like(v)])
        return self.observation(state.q, jnp.zeros((0,), omega.dtype), xi, c)


def test_closed_form_sleigh_matches_its_description():
    """The hand-written sleigh is the library's: same reduced view and continuous equations."""
    rng = np.random.default_rng(0)

    @eqx.filter_jit  # one program, not op by op
    def views(system, q, v, xi):
        r = jnp.zeros(0)
        qdot = system.qdot_from_velocities(q, v, r)
        return (
            system.reduced_lagrangian(r, r, xi),
            qdot,
            system.velocities_from_qdot(q, ClosedFormSleigh().qdot_from_velocities(q, v, r)),
            system.velocity_dynamics(q, v, r, r),
            system.constraint_forms(q),
        )

    for _ in range(5):
        q, v, xi = (rng.normal(size=k) for k in (3, 2, 3))  # traced by filter_jit as arrays
        mine, lib = views(ClosedFormSleigh(), q, v, xi), views(SLEIGH, q, v, xi)
        np.testing.assert_allclose(mine[0], lib[0], rtol=1e-15)  # the reduced Lagrangian
        np.testing.assert_allclose(mine[1], lib[1], atol=1e-15)  # qdot from the velocities
        np.testing.assert_allclose(mine[2], lib[2], atol=1e-15)  # the velocities read back
        np.testing.assert_allclose(mine[3], lib[3], rtol=1e-14, atol=1e-15)  # velocity dynamics
        np.testing.assert_allclose(mine[4], lib[4], atol=0)  # the constraint forms
    # the cubic's closed-form root solves it, from h = 0 up, to round-off
    c3 = jnp.asarray([0.0, 1e-12, 1e-6, 1e-3, 1.0, 1e3])
    w = _monotone_cubic_root(c3, jnp.asarray(0.29), jnp.asarray(-0.7))
    np.testing.assert_allclose(c3 * w**3 + 0.29 * w, -0.7, rtol=4e-16 * 8)


@pytest.mark.parametrize("retraction", ["exp", "cayley"])
def test_closed_form_sleigh_equals_newton_on_the_library_sleigh(retraction):
    """A closed-form system written outside the library: RDP() runs its kernel, and 10^4 steps
    reproduce lj.chaplygin_sleigh() under RDP(solver="newton") to round-off."""
    mine = ClosedFormSleigh()
    assert lj.RDP().uses_kernel(mine) and not lj.RDP().uses_kernel(SLEIGH)
    n = 10_000
    kern = simulate_batch(mine, lj.RDP(retraction=retraction), sleigh_batch(), 200.0, n)
    newt = sleigh_newton_run(retraction)
    _assert_equal_to_roundoff(kern, newt, n, ("sleigh", retraction))
    # it moved, and its energy (conserved by the flow) stays bounded over the run
    heading = np.asarray(kern.q)[:, :, 2]
    assert float(np.min(np.abs(heading[:, -1] - heading[:, 0]))) > 1.0
    e = np.asarray(kern.energy)
    assert np.abs(e - e[:, :1]).max() < 1e-6 * e[:, 0].min()


# ------------------------------------------------------------- the snakeboard step's hand-written VJP
class _AutodiffSnakeboard(lj.Snakeboard):
    """The snakeboard with JAX's own derivative of its kernel step (no hand-written VJP)."""

    def kernel_step_reverse(self, alpha, h, retraction, state, c0, c1):
        return self.kernel_step(alpha, h, retraction, state, c0, c1)


class _AutodiffSinusoids(lj.Sinusoids):
    """Sinusoids with JAX's own derivative of the sampler (no hand-written VJP)."""

    def sampler(self, h, fractions, *, reverse_only=False):
        return super().sampler(h, fractions)


def _autodiff_controls(ctl):
    return _AutodiffSinusoids(amplitude=ctl.amplitude, frequency=ctl.frequency, phase=ctl.phase)


@pytest.mark.parametrize("order", [2, 4])
def test_sinusoid_sampler_vjp_equals_autodiff(order):
    """The sampler's hand-written VJP (per term) equals JAX's VJP of the same sampler, in the
    coefficients, the step and the time, at the fractions of order 2 (0, 1) and of order 4's
    composition, under ``vmap``, at random coefficients and cotangents; the values are the same."""
    rng = np.random.default_rng(3)
    n = 8
    ctl = lj.Sinusoids(
        amplitude=jnp.asarray(rng.normal(size=(n, 2, 3))),
        frequency=jnp.asarray(rng.uniform(-3, 3, size=(n, 2, 3))),
        phase=jnp.asarray(rng.uniform(0, 6, size=(n, 2, 3))),
    )
    fractions = jnp.asarray(lj.RDP(order=order).control_nodes)
    t = jnp.asarray(rng.uniform(0, 20, size=n))
    h = jnp.asarray(rng.uniform(0.001, 0.3, size=n))

    def vjp(reverse_only, ct):
        def one(ctl, h, t, ct):
            def f(c, h, t):
                return c.sampler(h, fractions, reverse_only=reverse_only)(t)

            out, pull = jax.vjp(f, ctl, h, t)
            return out, pull(ct)

        return jax.jit(jax.vmap(one))(ctl, h, t, ct)

    ct = jnp.asarray(rng.normal(size=(n, fractions.shape[0], 2)))
    (o1, g1), (o2, g2) = vjp(False, ct), vjp(True, ct)
    np.testing.assert_allclose(o2, o1, rtol=1e-15, atol=1e-15)
    _leaves_close(g2, g1, f"order {order}")


@pytest.mark.parametrize("integrator", ["rk4", "rdp4"])
def test_reverse_over_reverse_through_the_sampler_equals_forward_over_reverse(integrator):
    """A gradient of a gradient through the sampler's hand-written VJP (``jax.jacrev`` of
    ``jax.grad``) equals ``jax.hessian`` (forward over reverse, which JAX differentiates itself)
    in a sinusoid's frequency and in ``t_final``. The VJP used to read ``(sin, cos)(w f h)`` as
    constants: the second pass missed their dependence on ``w`` and ``h``, 6% off in the
    frequency and 14% in ``t_final`` for RK4 (car, 20 steps)."""
    car = lj.Car()
    q0, qdot0, ctl = car.sample_maneuver(jax.random.PRNGKey(1))
    integ = lj.RK4() if integrator == "rk4" else lj.RDP(order=4)

    def f(x):  # x = (the torque's first frequency, t_final)
        c = lj.Sinusoids(ctl.amplitude, ctl.frequency.at[0, 0].set(x[0]), ctl.phase)
        return lj.simulate(car, q0, qdot0, c, t_final=x[1], n_steps=20, integrator=integ).q[-1, 0]

    x = jnp.array([float(ctl.frequency[0, 0]), 3.0])
    rev_rev = jax.jit(jax.jacrev(jax.grad(f)))(x)
    fwd_rev = jax.jit(jax.hessian(f))(x)
    assert float(jnp.max(jnp.abs(fwd_rev))) > 0.01
    np.testing.assert_allclose(np.asarray(rev_rev), np.asarray(fwd_rev), rtol=1e-12, atol=1e-13)


def _leaves_close(a, b, what):
    """Every leaf of ``a`` equals ``b``'s to 1e-12 of the largest entry of ``b`` (a cotangent that
    is exactly zero in one is exactly zero in the other)."""
    la, lb = jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)
    assert len(la) == len(lb)
    scale = max(float(np.max(np.abs(np.asarray(x)))) for x in lb)
    assert scale > 0, what
    for x, y in zip(la, lb):
        assert np.all(np.isfinite(np.asarray(x))), what
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-12, atol=1e-12 * scale, err_msg=what)


def _plain_step(system, h, st, a, b):
    return system.kernel_step(0.5, h, "exp", st, a, b)[0]


def _symmetric(system, h, st, a, b):
    from ldap_jax.systems._snakeboard import _symmetric_step

    return _symmetric_step(system, h, st, a, b)[0]


@eqx.filter_jit  # the model, the steps and the states traced: one program for every h
def _batched_step(system, hs, state, c0, c1):
    return jax.vmap(lambda *x: _plain_step(system, *x))(hs, state, c0, c1)


@eqx.filter_jit
def _batched_step_vjp(f, system, hs, state, c0, c1, ct):
    """``f``'s values and VJP (in the model, the step, the state and both control values) per member."""

    def one(h, st, a, b, ct):
        out, pull = jax.vjp(f, system, h, st, a, b)
        return out, pull(ct)

    return jax.vmap(one)(hs, state, c0, c1, ct)


@pytest.mark.parametrize("h", [0.01, -0.03, 0.4, 2e-9])
def test_snakeboard_step_vjp_equals_autodiff(h):
    """The symmetric step's hand-written VJP equals JAX's VJP of the same step, for every input
    (model parameters, step, state, both control values) at random states and cotangents, under
    ``vmap``; ``h = 2e-9`` puts the rotation ``h xi_1`` in the exponential map's Taylor branch
    (and 0.4 puts the steering angle's rotation well away from small). The values are the
    step's to round-off (the same operations; XLA compiles the two programs apart: 1 ulp)."""
    sb = lj.Snakeboard(m=1.3, l=0.45, I=0.06, J=0.025)
    rng = np.random.default_rng(7)
    n = 16
    q = rng.normal(size=(n, 5))
    q[:, 4] = rng.uniform(-1.2, 1.2, n)
    pu, mu = rng.normal(size=(n, 2)) * 0.3, rng.normal(size=(n, 3))
    state = jax.vmap(sb.kernel_init)(jnp.asarray(q), jnp.asarray(pu), jnp.asarray(mu))
    c0, c1 = jnp.asarray(rng.normal(size=(n, 2))), jnp.asarray(rng.normal(size=(n, 2)))
    hs = jnp.full((n,), h)

    out = _batched_step(sb, hs, state, c0, c1)
    ct = jax.tree_util.tree_map(lambda x: jnp.asarray(rng.normal(size=x.shape)), out)
    (o1, g1), (o2, g2) = (_batched_step_vjp(f, sb, hs, state, c0, c1, ct) for f in (_plain_step, _symmetric))
    for x, y in zip(jax.tree_util.tree_leaves(o1), jax.tree_util.tree_leaves(o2)):
        np.testing.assert_allclose(x, y, rtol=1e-15, atol=1e-15)
    _leaves_close(g2, g1, f"h={h}")
    if h == 2e-9:  # the Taylor branch was taken
        # the step's rotation angle h xi^1 is the heading's change (the exponential map turns by it)
        turn = o1.pose.theta - state.pose.theta
        assert float(jnp.max(jnp.abs(turn))) < float(jnp.finfo(jnp.float64).eps) ** 0.25


def _snakeboard_losses(system, q0, qdot0, ctl, t_final, mask):
    """A batched loss on the final and a middle node; ``mask``: failed members left out with a
    double ``where``."""

    def one(q0, qdot0, ctl):
        traj = lj.simulate(system, q0, qdot0, ctl, t_final=t_final, n_steps=200, check_constraints=False)
        loss = jnp.sum(traj.q[-1] ** 2) + jnp.sum(traj.qdot[100] ** 2)
        if mask:
            return jnp.where(traj.failed, 0.0, jnp.where(traj.failed, 0.0, loss))
        return loss

    return jnp.sum(jax.vmap(one)(q0, qdot0, ctl))


def test_snakeboard_rollout_gradient_with_the_hand_written_vjp():
    """Through ``simulate``: the rollout runs the step's hand-written VJP (the order-2 step reads
    the sinusoids at the ends of its steps, evaluated once per node and carried, without the
    sampler and its VJP), and its gradients in the model parameters, initial states, controls
    and ``t_final`` equal those of JAX's own derivative of the step (to 1e-12), for random
    maneuvers and, with a member that fails (``singular``) left out by a double ``where``, for
    the healthy members (finite); a loss that reads the failed member gets NaN in both. (Five
    random maneuvers, the batch size of the runs with the failing members: the same programs.)"""
    sb = lj.Snakeboard()
    ad = _AutodiffSnakeboard()
    q0, qdot0, ctl = maneuvers(sb, 5, seed=11)
    batch = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a[:3], b]), (q0, qdot0, ctl), FAILURE_BATCH)
    # the step's hand-written VJP is what the rollout runs (and the reference does not)
    jaxpr = str(jax.make_jaxpr(lambda c: _snakeboard_losses(sb, q0, qdot0, c, 4.0, False))(ctl))
    assert "_symmetric_step" in jaxpr and "_sinusoid_term" not in jaxpr
    jaxpr = str(
        jax.make_jaxpr(lambda c: _snakeboard_losses(ad, q0, qdot0, c, 4.0, False))(_autodiff_controls(ctl))
    )
    assert "_symmetric_step" not in jaxpr and "_sinusoid_term" not in jaxpr

    grad = eqx.filter_jit(jax.grad(_snakeboard_losses, argnums=(0, 1, 2, 3, 4)))

    def both(a, b, c, mask, t_final=6.0):
        mine = grad(sb, a, b, c, jnp.asarray(t_final), mask)
        ref = grad(ad, a, b, _autodiff_controls(c), jnp.asarray(t_final), mask)
        return mine, ref

    # per-step rotations h xi_0 up to 0.023 (the exponential map's series branch), then over 40 s
    # up to 0.26, 13% of them above the series' threshold (0.105): both branches of the VJP
    _leaves_close(*both(q0, qdot0, ctl, False), "random maneuvers")
    _leaves_close(*both(q0, qdot0, ctl, False, 40.0), "random maneuvers, coarse steps")
    traj = jax.vmap(lambda a, b, c: lj.simulate(sb, a, b, c, t_final=6.0, n_steps=200))(*batch)
    assert (code(traj.result)[:4] == code(lj.RESULTS.successful)).all()
    assert code(traj.result)[4] == code(lj.RESULTS.singular)
    # the failed member masked out: the healthy members' gradients (their own inputs) are finite and
    # equal; a loss reading the failed member: NaN where JAX's own derivative gives NaN
    for mask in (True, False):
        mine, ref = both(*batch, mask)
        if mask:
            healthy = jax.tree_util.tree_map(lambda x: x[:4], (mine[1:4], ref[1:4]))
            _leaves_close(*healthy, "masked")
        for x, y in zip(jax.tree_util.tree_leaves(mine), jax.tree_util.tree_leaves(ref)):
            np.testing.assert_array_equal(np.isnan(np.asarray(x)), np.isnan(np.asarray(y)))
    read = mine
    assert np.isnan(np.asarray(read[3].amplitude)[4]).all()
