"""Friction: a Rayleigh dissipation function ``R(r, u, xi)`` on an ``lj.System`` (the roller racer's
rolling resistance, ``lj.roller_racer(drag=...)``). Its forces ``-d_u R`` on the shape and
``-d_xi R`` on the group enter the reduced equations as they enter the full Lagrange-d'Alembert
(KKT) equations; the RDP steps keep their orders with them; the energy falls when nothing drives
the system; the integrators that cannot take them say so."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import simulate_ns

import ldap_jax as lj

RACER = lj.roller_racer(drag=0.3)
T = 4.0
TORQUE = lj.Sinusoids(amplitude=[[0.5]], frequency=[[2.0]], phase=[[0.3]])
Q0 = np.array([0.0, 0.0, 0.0, 0.2])


def _start(system):
    return np.asarray(system.qdot_from_velocities(Q0, jnp.array([0.5, 0.4]), jnp.zeros(1)))


def test_reduced_equations_with_friction_equal_the_full_kkt_equations():
    """``velocity_dynamics`` (the reduced equations with the friction's shape force and its group
    covector projected on the constraint distribution) against the time derivative of the minimal
    velocities along the full KKT accelerations with the friction as a generalised force, at random
    states and torques (1e-12); and the friction changes the accelerations (it is not zero)."""
    frictionless = lj.roller_racer()

    @jax.jit
    @jax.vmap
    def accelerations(q, v, f):
        qdot = RACER.qdot_from_velocities(q, v, jnp.zeros(1))
        reduced = RACER.velocity_dynamics(q, v, f, jnp.zeros(1))
        qddot, _ = RACER.full_acceleration(q, qdot, f, jnp.zeros(1))
        full = jax.jvp(RACER.velocities_from_qdot, (q, qdot), (qdot, qddot))[1]
        return reduced, full, frictionless.velocity_dynamics(q, v, f, jnp.zeros(1))

    rng = np.random.default_rng(0)
    q = np.c_[rng.normal(size=(16, 3)), rng.uniform(-1, 1, 16)]
    reduced, full, free = accelerations(q, rng.normal(size=(16, 2)), rng.normal(size=(16, 1)))
    np.testing.assert_allclose(reduced, full, rtol=1e-12, atol=1e-12)
    assert np.min(np.max(np.abs(np.asarray(free) - np.asarray(reduced)), axis=1)) > 1e-3


@functools.cache
def _reference() -> np.ndarray:
    return np.asarray(lj.reference(RACER, Q0, _start(RACER), TORQUE, np.array([T])).q)[-1]


@pytest.mark.parametrize(
    ("integrator", "order", "steps"),
    [
        (lj.RDP(), 2, (40, 80)),
        (lj.RDP(order=4), 4, (40, 80)),
        # the 11-stage default's asymptotic range starts after T/10 (4.9 from T/10, 6.0 from T/20)
        (lj.RDP(order=6), 6, (20, 40)),
        (lj.RK4(), 4, (320, 640)),  # RK4 reaches its asymptotic range later (4.3 at T/80)
    ],
    ids=["rdp2", "rdp4", "rdp6", "rk4"],
)
def test_integrators_keep_their_order_with_friction(integrator, order, steps):
    """The final configuration of the racer with friction under a sinusoidal torque against
    ``lj.reference`` (the reduced equations with friction, rtol 1e-11): halving the step divides
    the error by ``2^order`` (measured order within 0.15 of the nominal one)."""
    ref = _reference()
    # both step counts from one program (helpers.simulate_ns: the same steps bit for bit as two
    # calls of simulate), without the diagnostics nothing here reads
    batch = jax.tree_util.tree_map(lambda x: np.asarray(x)[None], (Q0, _start(RACER), TORQUE))
    runs = simulate_ns(RACER, integrator, batch, T, steps, diagnostics=False)
    errors = []
    for n in steps:
        assert int(runs[n].result[0]) == lj.RESULTS.successful._value
        errors.append(np.max(np.abs(runs[n].q[0, n] - ref)))
    measured = np.log2(errors[0] / errors[1])
    assert abs(measured - order) < 0.15, (errors, measured)


def test_energy_falls_under_friction_and_is_kept_without():
    """Unforced, from a moving start: with friction the energy at the nodes falls at every step
    (the dissipated power ``<d_u R, u> + <d_xi R, xi> = 2 R > 0``), by more than 30 % over 4 s;
    without it the energy stays within 1e-6 of its start (RDP order 4, T/200)."""
    zero = lj.Sinusoids(amplitude=[[0.0]], frequency=[[1.0]], phase=[[0.0]])
    kw = dict(t_final=T, n_steps=200, integrator=lj.RDP(order=4))
    e = np.asarray(lj.simulate(RACER, Q0, _start(RACER), zero, **kw).energy)
    assert np.all(np.diff(e) < 0) and e[-1] < 0.7 * e[0], e[::40]
    free = lj.roller_racer()
    e0 = np.asarray(lj.simulate(free, Q0, _start(free), zero, **kw).energy)
    assert np.max(np.abs(e0 - e0[0])) < 1e-6 * e0[0]


def test_friction_bad_input_and_integrators_that_do_not_take_it():
    with pytest.raises(ValueError, match="DLA"):
        lj.simulate(RACER, Q0, _start(RACER), TORQUE, t_final=1.0, n_steps=10, integrator=lj.DLA())
    with pytest.raises(ValueError, match="GNI"):
        lj.simulate(RACER, Q0, _start(RACER), TORQUE, t_final=1.0, n_steps=10, integrator=lj.GNI())
    with pytest.raises(ValueError, match="'drag'"):
        lj.roller_racer(drag=-1.0)
    with pytest.raises(ValueError, match="dissipation"):
        lj.System(
            1,
            lambda r, u, xi: 0.5 * (u @ u + xi @ xi),
            lambda r: jnp.zeros((3, 1)),
            dissipation=lambda r, u, xi: xi,  # not a scalar
        )
    with pytest.raises(TypeError, match="dissipation"):
        lj.System(1, lambda r, u, xi: 0.5 * (u @ u + xi @ xi), lambda r: jnp.zeros((3, 1)), dissipation=1.0)


def test_a_long_forced_run_with_friction_is_not_diverged():
    """The divergence test balances E - E0 against the controls' work and, with friction, the
    friction's: without the latter, the energy friction dissipates (which grows without bound in
    a forced steady state) passed the test's bound and a healthy roller racer pumping against
    drag was reported diverged at t = 450 s. The balance now closes to the scheme's error."""
    racer = lj.roller_racer(drag=0.3)
    ctl = lj.Sinusoids(amplitude=[[0.4]], frequency=[[2.5]], phase=[[0.0]])
    traj = lj.simulate(racer, jnp.zeros(4), jnp.zeros(4), ctl, t_final=900.0, n_steps=9000, save=10)
    assert traj.result == lj.RESULTS.successful, lj.RESULTS[traj.result]
    # the controls' work alone does not balance the energy: friction took most of it
    assert float(traj.work[-1]) > 10 * float(jnp.max(jnp.abs(traj.energy)))
