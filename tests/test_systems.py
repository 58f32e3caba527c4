"""The model equations: reduced form == full Lagrange-d'Alembert form, and the reduced view."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import compiled_programs, systems

import ldap_jax as lj
from ldap_jax.systems import body_velocity

rng = np.random.default_rng(1)
SYSTEMS = systems()


def _random_state(system):
    q = rng.normal(size=5)
    if isinstance(system, lj.Snakeboard):
        q[4] = rng.uniform(-1.3, 1.3)  # on the host (op by op, JAX compiles each operation)
    q = jnp.asarray(q)
    v = jnp.asarray(rng.normal(size=system.n_velocities))
    c = jnp.asarray(rng.normal(size=2))
    cdot = jnp.asarray(rng.normal(size=2))
    return q, v, c, cdot


@pytest.mark.parametrize("name", SYSTEMS)
def test_reduced_equations_equal_full_lagrange_dalembert(name):
    """M(q) qddot = dL/dq - ... + F + omega^T lambda, omega qdot = 0, solved by autodiff."""
    system = SYSTEMS[name]

    @eqx.filter_jit  # one program, not op by op
    def reduced_and_full(system, q, v, c, cdot):
        f, u_kin = system.inputs(c)
        _, u_kin_dot = system.inputs(cdot)
        qdot = system.qdot_from_velocities(q, v, u_kin)
        vdot = system.velocity_dynamics(q, v, f, u_kin)
        _, qddot_reduced = jax.jvp(system.qdot_from_velocities, (q, v, u_kin), (qdot, vdot, u_kin_dot))
        qddot_full, _ = system.full_acceleration(q, qdot, f, u_kin_dot)
        residual, v_back = system.constraint_residual(q, qdot), system.velocities_from_qdot(q, qdot)
        return qddot_reduced, qddot_full, residual, v_back

    for _ in range(20):
        q, v, c, cdot = _random_state(system)
        qddot_reduced, qddot_full, residual, v_back = reduced_and_full(system, q, v, c, cdot)
        np.testing.assert_allclose(qddot_reduced, qddot_full, atol=1e-12 * (1 + np.abs(qddot_full).max()))
        assert float(residual) < 1e-14
        np.testing.assert_allclose(v_back, v, atol=1e-13)


@pytest.mark.parametrize("name", SYSTEMS)
def test_reduced_view_is_consistent_with_constraints(name):
    """xi + A(r) rdot lies in span e(r) exactly for velocities on the distribution, and
    ``l(r, rdot, xi) = L(q, qdot)``."""
    system = SYSTEMS[name]

    @eqx.filter_jit  # one program, not op by op
    def reduced_view(system, q, v, c):
        qdot = system.qdot_from_velocities(q, v, system.inputs(c)[1])
        xi = body_velocity(q, qdot)
        omega = xi + system.connection(q[3:]) @ qdot[3:]
        e = system.symmetry_basis(q[3:])
        if e.shape[1]:
            w = jnp.linalg.lstsq(e, omega)[0]
            omega = omega - e @ w
        # the inverse of the reduced Legendre transform: the velocity read back from the momenta
        # (d_u l, d_xi l) is (rdot, xi) (the kinematic entries from the controls)
        r, rdot = q[3:], qdot[3:]
        pu, mu = jax.grad(system.reduced_lagrangian, argnums=(1, 2))(r, rdot, xi)
        u_back, xi_back = system.velocity_from_momenta(r, pu, mu, system.inputs(c)[1])
        momenta = (
            system.momentum(q, qdot),
            system.symmetry_basis(r).T @ mu,
            system.reduced_momentum(r, rdot, xi),
        )
        energies = (system.reduced_energy(r, rdot, xi), system.energy(q, qdot))
        return omega, (u_back, rdot), (xi_back, xi), momenta, energies

    for _ in range(10):
        q, v, c, _ = _random_state(system)
        omega, (u_back, rdot), (xi_back, xi), momenta, energies = reduced_view(system, q, v, c)
        np.testing.assert_allclose(omega, 0.0, atol=1e-14)
        np.testing.assert_allclose(u_back, rdot, atol=1e-13)
        np.testing.assert_allclose(xi_back, xi, atol=1e-13)
        # the nonholonomic momentum is e(r)^T d_xi l, however it is computed
        np.testing.assert_allclose(momenta[0], momenta[1], atol=1e-14)
        np.testing.assert_allclose(momenta[2], momenta[0], atol=0)
        np.testing.assert_allclose(energies[0], energies[1], atol=0)


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

    @eqx.filter_jit  # one program, not op by op
    def rate_and_power(system, q, v, c, cdot):
        f, u_kin = system.inputs(c)
        qdot = system.qdot_from_velocities(q, v, u_kin)
        vdot = system.velocity_dynamics(q, v, f, u_kin)
        _, u_dot = system.inputs(cdot)

        def energy(qq, vv, uu):
            return system.energy(qq, system.qdot_from_velocities(qq, vv, uu))

        edot = jax.jvp(energy, (q, v, u_kin), (qdot, vdot, u_dot))[1]
        return edot, system.power(f, qdot[3:])

    for _ in range(10):
        q, v, c, _ = _random_state(system)
        edot, power = rate_and_power(system, q, v, c, jnp.asarray(rng.normal(size=2)))
        np.testing.assert_allclose(edot, power, rtol=1e-11, atol=1e-12)


def test_car_effective_inertia_sign():
    """(25) as printed (+A) would give I - m rho^2; the corrected sign gives I + m rho^2 + ..."""
    car = SYSTEMS["car"]
    q = jnp.array([0.0, 0.0, 0.0, 0.0, 0.3])
    acc = car.velocity_dynamics(q, jnp.array([0.0]), jnp.array([1.0, 0.0]), jnp.zeros(2))
    inertia, m, rho, k, l = (np.asarray(x) for x in (car.I, car.m, car.rho, car.K, car.l))  # host copies
    np.testing.assert_allclose(np.asarray(acc)[0], 1.0 / (inertia + m * rho**2 + k * (rho * 0.3 / l) ** 2))


@pytest.mark.parametrize(
    "cls, bad",
    [
        (lj.Car, "m"),
        (lj.Car, "rho"),
        (lj.Car, "K"),
        (lj.Snakeboard, "J"),
        (lj.Snakeboard, "l"),
    ],
)
def test_non_positive_parameters_are_named(cls, bad):
    """The message names the parameter and lists the values the model got, as plain numbers."""
    for value in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match=f"'{bad}'") as err:
            cls(**{bad: value})
        assert f" {bad}={value:g}" in str(err.value) and "Array(" not in str(err.value), str(err.value)


def test_snakeboard_rotor_inertia_bound():
    with pytest.raises(ValueError, match="'I'.*I < m l\\^2"):
        lj.Snakeboard(I=0.3)


def test_default_parameters():
    car, sb = lj.Car(), lj.Snakeboard()
    assert (float(car.m), float(car.I), float(car.K), float(car.rho), float(car.l)) == (
        1.0,
        0.1,
        0.2,
        0.1,
        0.5,
    )
    assert (float(sb.m), float(sb.l), float(sb.I), float(sb.J)) == (1.0, 0.5, 0.05, 0.02)
    with pytest.raises(TypeError, match="physical parameter"):
        lj.Car(m="heavy")


def test_models_are_pytrees_and_differentiable():
    sb = SYSTEMS["snakeboard"]
    leaves = jax.tree_util.tree_leaves(sb)
    assert len(leaves) == 4 and all(x.dtype == jnp.float64 for x in leaves)
    q, v, c, _ = _random_state(sb)
    g = jax.grad(lambda s: s.velocity_dynamics(q, v, c, jnp.zeros(2))[2])(sb)
    assert np.isfinite(float(g.m)) and abs(float(g.I)) > 0


@pytest.mark.parametrize("name", ["snakeboard", "racer"])
def test_diagnostics_on_values_are_one_program_each(name):
    """``energy``, ``momentum`` and ``constraint_residual`` called on values (a notebook's first
    ``sb.energy(q, qdot)``) each run as one compiled program, not operation by operation (measured
    before: 31 programs and 0.73 s for the snakeboard's energy; now 1 and 0.06 s), also for a
    user's ``lj.System`` (its callables are static), and give the values traced inline into a
    caller's ``jit``."""
    # a racer of its own, not helpers.RACER: its programs cannot have been compiled by another test
    system = SYSTEMS["snakeboard"] if name == "snakeboard" else lj.roller_racer()
    q = jnp.asarray(rng.normal(size=system.n_config))
    qdot = jnp.asarray(rng.normal(size=system.n_config))
    methods = ("energy", "momentum", "constraint_residual")
    lj.compiler_options()  # its first call probes XLA's options with two small programs
    with compiled_programs() as names:
        eager = [getattr(system, m)(q, qdot) for m in methods]
    assert set(names) <= {f"jit({m})" for m in methods}, names
    inline = jax.jit(lambda q, qdot: [getattr(system, m)(q, qdot) for m in methods])(q, qdot)
    for m, a, b in zip(methods, eager, inline):
        np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-15, err_msg=m)


@pytest.mark.parametrize("name", [*SYSTEMS, "roller racer"])
def test_shape_mobility_is_the_impulse_response_at_rest(name):
    """``A = shape_mobility(r)`` (the leading block of the Newton Jacobian's inverse) equals the
    derivative of ``velocity_from_momenta`` with respect to the shape momenta at rest, is
    symmetric, and ``1/2 P^T A P`` is the kinetic energy of the velocity an impulse ``P`` gives
    (the energy less that at rest: the racer's hinge has a potential)."""
    system = SYSTEMS[name] if name in SYSTEMS else lj.systems.roller_racer()
    r = jnp.asarray(rng.uniform(-1.0, 1.0, size=system.n_shape))
    p = jnp.asarray(rng.normal(size=system.n_shape))

    @eqx.filter_jit
    def both(system, r, p):
        zero, zero3 = jnp.zeros_like(r), jnp.zeros(3, r.dtype)
        a = system.shape_mobility(r)
        by_ad = jax.jacfwd(lambda pp: system.velocity_from_momenta(r, pp, zero3, zero)[0])(zero)
        u, xi = system.velocity_from_momenta(r, p, zero3, zero)
        rest = system.reduced_energy(r, zero, zero3)
        return a, by_ad, system.reduced_energy(r, u, xi) - rest

    a, by_ad, energy = (np.asarray(x) for x in both(system, r, p))
    scale = np.max(np.abs(by_ad))
    assert scale > 0
    np.testing.assert_allclose(a, by_ad, rtol=0, atol=1e-13 * scale)
    np.testing.assert_allclose(a, a.T, rtol=0, atol=1e-13 * scale)
    p = np.asarray(p)
    np.testing.assert_allclose(0.5 * p @ a @ p, energy, rtol=1e-12)
