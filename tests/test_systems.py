"""The model equations: reduced form == full Lagrange-d'Alembert form, and the reduced view."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import systems

import ldap_jax as lj
from ldap_jax.systems import body_velocity

rng = np.random.default_rng(1)
SYSTEMS = systems()


def _random_state(system):
    q = jnp.asarray(rng.normal(size=5))
    if isinstance(system, lj.Snakeboard):
        q = q.at[4].set(rng.uniform(-1.3, 1.3))
    v = jnp.asarray(rng.normal(size=system.n_velocities))
    c = jnp.asarray(rng.normal(size=2))
    cdot = jnp.asarray(rng.normal(size=2))
    return q, v, c, cdot


@pytest.mark.parametrize("name", SYSTEMS)
def test_reduced_equations_equal_full_lagrange_dalembert(name):
    """M(q) qddot = dL/dq - ... + F + omega^T lambda, omega qdot = 0, solved by autodiff."""
    system = SYSTEMS[name]
    for _ in range(20):
        q, v, c, cdot = _random_state(system)
        f, u_kin = system.inputs(c)
        _, u_kin_dot = system.inputs(cdot)
        qdot = system.qdot_from_velocities(q, v, u_kin)
        vdot = system.velocity_dynamics(q, v, f, u_kin)
        _, qddot_reduced = jax.jvp(system.qdot_from_velocities, (q, v, u_kin), (qdot, vdot, u_kin_dot))
        qddot_full, _ = system.full_acceleration(q, qdot, f, u_kin_dot)
        np.testing.assert_allclose(qddot_reduced, qddot_full, atol=1e-12 * (1 + np.abs(qddot_full).max()))
        assert float(system.constraint_residual(q, qdot)) < 1e-14
        np.testing.assert_allclose(system.velocities_from_qdot(q, qdot), v, atol=1e-13)


@pytest.mark.parametrize("name", SYSTEMS)
def test_reduced_view_is_consistent_with_constraints(name):
    """xi + A(r) rdot lies in span e(r) exactly for velocities on the distribution, and
    ``l(r, rdot, xi) = L(q, qdot)``."""
    system = SYSTEMS[name]
    for _ in range(10):
        q, v, c, _ = _random_state(system)
        qdot = system.qdot_from_velocities(q, v, system.inputs(c)[1])
        xi = body_velocity(q, qdot)
        omega = xi + system.connection(q[3:]) @ qdot[3:]
        e = system.symmetry_basis(q[3:])
        if e.shape[1]:
            w = jnp.linalg.lstsq(e, omega)[0]
            omega = omega - e @ w
        np.testing.assert_allclose(omega, 0.0, atol=1e-14)
        # locked velocity from the momentum reproduces xi
        mom = system.momentum(q, qdot)
        np.testing.assert_allclose(system.locked_velocity(q[3:], qdot[3:], mom), xi, atol=1e-13)


def test_snakeboard_momentum_and_its_equation():
    """mu_1 = 2 m l^2 cos(phi) s + I sin(2 phi) psidot, and
    mu_1_dot = 2 I cos^2(phi) psidot phidot - mu_1 tan(phi) phidot (forces do not enter)."""
    sb = SYSTEMS["snakeboard"]
    m, l, inertia = sb.m, sb.l, sb.I
    for _ in range(10):
        q, v, c, _ = _random_state(sb)
        f = c
        psidot, phidot, s = v
        phi = q[4]
        qdot = sb.qdot_from_velocities(q, v, jnp.zeros(2))
        mu1 = sb.momentum(q, qdot)[0]
        np.testing.assert_allclose(
            mu1, 2 * m * l**2 * jnp.cos(phi) * s + inertia * jnp.sin(2 * phi) * psidot, rtol=1e-13
        )
        vdot = sb.velocity_dynamics(q, v, f, jnp.zeros(2))

        def mom(qq, vv):
            return sb.momentum(qq, sb.qdot_from_velocities(qq, vv, jnp.zeros(2)))[0]

        mu1_dot = jax.jvp(mom, (q, v), (qdot, vdot))[1]
        expected = 2 * inertia * jnp.cos(phi) ** 2 * psidot * phidot - mu1 * jnp.tan(phi) * phidot
        np.testing.assert_allclose(mu1_dot, expected, rtol=1e-11, atol=1e-12)


@pytest.mark.parametrize("name", SYSTEMS)
def test_energy_rate_equals_power(name):
    """dE/dt = <f, rdot> (the car's steering does no work)."""
    system = SYSTEMS[name]
    for _ in range(10):
        q, v, c, _ = _random_state(system)
        f, u_kin = system.inputs(c)
        qdot = system.qdot_from_velocities(q, v, u_kin)
        vdot = system.velocity_dynamics(q, v, f, u_kin)
        _, u_dot = system.inputs(jnp.asarray(rng.normal(size=2)))

        def energy(qq, vv, uu):
            return system.energy(qq, system.qdot_from_velocities(qq, vv, uu))

        edot = jax.jvp(energy, (q, v, u_kin), (qdot, vdot, u_dot))[1]
        np.testing.assert_allclose(edot, system.power(f, qdot), rtol=1e-11, atol=1e-12)


def test_car_effective_inertia_sign():
    """(25) as printed (+A) would give I - m rho^2; the corrected sign gives I + m rho^2 + ..."""
    car = SYSTEMS["car"]
    q = jnp.array([0.0, 0.0, 0.0, 0.0, 0.3])
    acc = car.velocity_dynamics(q, jnp.array([0.0]), jnp.array([1.0, 0.0]), jnp.zeros(2))
    np.testing.assert_allclose(
        acc[0], 1.0 / (car.I + car.m * car.rho**2 + car.K * (car.rho * 0.3 / car.l) ** 2)
    )


@pytest.mark.parametrize(
    "cls, kwargs, bad",
    [
        (lj.Car, dict(m=1.0, I=0.1, K=0.2, rho=0.1, l=0.5), "m"),
        (lj.Car, dict(m=1.0, I=0.1, K=0.2, rho=0.1, l=0.5), "rho"),
        (lj.Car, dict(m=1.0, I=0.1, K=0.2, rho=0.1, l=0.5), "K"),
        (lj.Snakeboard, dict(m=1.0, l=0.5, I=0.05, J=0.02), "J"),
        (lj.Snakeboard, dict(m=1.0, l=0.5, I=0.05, J=0.02), "l"),
    ],
)
def test_non_positive_parameters_are_named(cls, kwargs, bad):
    for value in (0.0, -1.0):
        with pytest.raises(ValueError, match=f"'{bad}'"):
            cls(**{**kwargs, bad: value})


def test_snakeboard_rotor_inertia_bound():
    with pytest.raises(ValueError, match="'I'.*I < m l\\^2"):
        lj.Snakeboard(m=1.0, l=0.5, I=0.3, J=0.02)


def test_models_are_pytrees_and_differentiable():
    sb = SYSTEMS["snakeboard"]
    leaves = jax.tree_util.tree_leaves(sb)
    assert len(leaves) == 4 and all(x.dtype == jnp.float64 for x in leaves)
    q, v, c, _ = _random_state(sb)
    g = jax.grad(lambda s: s.velocity_dynamics(q, v, c, jnp.zeros(2))[2])(sb)
    assert np.isfinite(float(g.m)) and float(jnp.abs(g.I)) > 0
