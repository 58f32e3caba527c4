"""The models against equations written out by hand, sharing no code with the library.

Everything here is plain NumPy/SciPy: the mass matrix, the constraint one-forms ``omega(q)`` and
their time derivative are typed in from the Lagrangians and the no-slip conditions (docs/mathematics.md
sections 5 and 6), the index-reduced Lagrange-d'Alembert system

    [[M, -omega^T], [omega, 0]] (qddot, lambda) = (F, -omegadot qdot)

is solved with ``numpy.linalg.solve`` and integrated with SciPy's DOP853. Random parameters (not
the ones the other tests use) and random maneuvers; ``lj.reference`` and RDP must agree with it.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import simulate_ns
from scipy.integrate import solve_ivp

import ldap_jax as lj


def _sinusoids(ctl):
    a, w, p = (np.asarray(x) for x in (ctl.amplitude, ctl.frequency, ctl.phase))
    value = lambda t: np.sum(a * np.sin(w * t + p), axis=1)  # noqa: E731
    rate = lambda t: np.sum(a * w * np.cos(w * t + p), axis=1)  # noqa: E731
    return value, rate


def snakeboard_field(m, l, inertia, jj, ctl):
    """q = (x, y, theta, psi, phi); L = (I psid^2 + 2 I psid thd + 2 J phid^2 + m l^2 thd^2
    + m (xd^2 + yd^2)) / 2; wheels at -l (angle theta + phi) and +l (angle theta - phi)."""
    value, _ = _sinusoids(ctl)
    mass = np.zeros((5, 5))
    mass[0, 0] = mass[1, 1] = m
    mass[2, 2] = m * l * l
    mass[2, 3] = mass[3, 2] = mass[3, 3] = inertia
    mass[4, 4] = 2 * jj

    def field(t, y):
        q, qd = y[:5], y[5:]
        th, phi, thd, phid = q[2], q[4], qd[2], qd[4]
        tp, tm = th + phi, th - phi
        omega = np.array(
            [
                [-np.sin(tp), np.cos(tp), -l * np.cos(phi), 0, 0],
                [-np.sin(tm), np.cos(tm), l * np.cos(phi), 0, 0],
            ]
        )
        omega_dot = np.array(
            [
                [-np.cos(tp) * (thd + phid), -np.sin(tp) * (thd + phid), l * np.sin(phi) * phid, 0, 0],
                [-np.cos(tm) * (thd - phid), -np.sin(tm) * (thd - phid), -l * np.sin(phi) * phid, 0, 0],
            ]
        )
        f = value(t)
        force = np.array([0.0, 0.0, 0.0, f[0], f[1]])
        kkt = np.block([[mass, -omega.T], [omega, np.zeros((2, 2))]])
        sol = np.linalg.solve(kkt, np.concatenate([force, -omega_dot @ qd]))
        return np.concatenate([qd, sol[:5]])

    return field


def car_field(m, inertia, kk, rho, l, ctl):
    """q = (x, y, theta, psi, sigma); L = (I psid^2 + K thd^2 + m (xd^2 + yd^2)) / 2;
    xd = rho cos(th) psid, yd = rho sin(th) psid, thd = (rho / l) sigma psid, sigmad = u_sigma(t)."""
    value, rate = _sinusoids(ctl)
    mass = np.diag([m, m, kk, inertia, 1.0])  # the sigma row is pinned by its constraint

    def field(t, y):
        q, qd = y[:5], y[5:]
        th, sg, thd, sgd = q[2], q[4], qd[2], qd[4]
        omega = np.array(
            [
                [1, 0, 0, -rho * np.cos(th), 0],
                [0, 1, 0, -rho * np.sin(th), 0],
                [0, 0, 1, -rho * sg / l, 0],
                [0, 0, 0, 0, 1.0],
            ]
        )
        omega_dot = np.zeros((4, 5))
        omega_dot[0, 3] = rho * np.sin(th) * thd
        omega_dot[1, 3] = -rho * np.cos(th) * thd
        omega_dot[2, 3] = -rho * sgd / l
        force = np.array([0.0, 0.0, 0.0, value(t)[0], 0.0])
        rhs_c = -omega_dot @ qd + np.array([0.0, 0.0, 0.0, rate(t)[1]])  # sigma_ddot = d u_sigma / dt
        kkt = np.block([[mass, -omega.T], [omega, np.zeros((4, 4))]])
        sol = np.linalg.solve(kkt, np.concatenate([force, rhs_c]))
        return np.concatenate([qd, sol[:5]])

    return field


def _case(name, seed):
    rng = np.random.default_rng(seed)
    if name == "snakeboard":
        m, l = rng.uniform(0.5, 3.0), rng.uniform(0.2, 1.0)
        inertia, jj = rng.uniform(0.1, 0.8) * m * l * l, rng.uniform(0.005, 0.1)
        system = lj.Snakeboard(m=m, l=l, I=inertia, J=jj)
        make = lambda ctl: snakeboard_field(m, l, inertia, jj, ctl)  # noqa: E731
    else:
        m, inertia, kk = rng.uniform(0.5, 3.0), rng.uniform(0.01, 0.5), rng.uniform(0.05, 1.0)
        rho, l = rng.uniform(0.05, 0.5), rng.uniform(0.3, 2.0)
        system = lj.Car(m=m, I=inertia, K=kk, rho=rho, l=l)
        make = lambda ctl: car_field(m, inertia, kk, rho, l, ctl)  # noqa: E731
    q0, qdot0, ctl = system.sample_maneuver(jax.random.PRNGKey(seed))
    return system, q0, qdot0, ctl, make(ctl)


def _solve(field, q0, qdot0, ts):
    y0 = np.concatenate([np.asarray(q0), np.asarray(qdot0)])
    sol = solve_ivp(field, (0.0, ts[-1]), y0, method="DOP853", rtol=1e-13, atol=1e-13, t_eval=ts)
    assert sol.success
    return sol.y[:5].T, sol.y[5:].T


@pytest.mark.parametrize("seed", [101, 202])
@pytest.mark.parametrize("name", ["car", "snakeboard"])
def test_reference_equals_hand_written_lagrange_dalembert(name, seed):
    """``lj.reference`` (the library's minimal equations, diffrax) equals the hand-written KKT
    system integrated by SciPy, configuration and velocity, over 6 s."""
    system, q0, qdot0, ctl, field = _case(name, seed)
    ts = np.linspace(0.0, 6.0, 31)
    q, qd = _solve(field, q0, qdot0, ts)
    ref = lj.reference(system, q0, qdot0, ctl, jnp.asarray(ts), rtol=1e-12, atol=1e-12)
    assert ref.result == lj.RESULTS.successful
    np.testing.assert_allclose(np.asarray(ref.q), q, atol=1e-9, rtol=0)
    np.testing.assert_allclose(np.asarray(ref.qdot), qd, atol=1e-9, rtol=0)


@pytest.mark.parametrize("name", ["car", "snakeboard"])
def test_rdp_and_rk4_converge_to_hand_written_solution(name):
    """RDP (alpha = 1/2, both retractions) converges at order 2 and RK4 at order 4 to the
    hand-written solution, with step h = 6 s / N, N = 300, 600, 1200 (RK4: 60, 120, 240)."""
    system, q0, qdot0, ctl, field = _case(name, 303)
    ts = np.linspace(0.0, 6.0, 61)
    q_true, _ = _solve(field, q0, qdot0, ts)
    batch = jax.tree_util.tree_map(lambda x: x[None], (q0, qdot0, ctl))
    for integrator, order, ns in (
        (lj.RDP(alpha=0.5, retraction="exp"), 2, (300, 600, 1200)),
        (lj.RDP(alpha=0.5, retraction="cayley"), 2, (300, 600, 1200)),
        (lj.RK4(), 4, (60, 120, 240)),
    ):
        runs = simulate_ns(system, integrator, batch, 6.0, ns, diagnostics=False)  # q alone is read
        errs = []
        for n in ns:
            assert not bool(np.any(runs[n].failed))
            errs.append(np.max(np.abs(runs[n].q[0, :: n // 60] - q_true)))
        observed = np.log2(np.asarray(errs[:-1]) / np.asarray(errs[1:]))
        assert np.all(np.abs(observed - order) < 0.15), (integrator, errs, observed)
