"""The reference solver against an independent integration of the full Lagrange-d'Alembert DAE."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import index, maneuvers, systems

import ldap_jax as lj

SYSTEMS = systems()


@pytest.mark.parametrize("name", list(SYSTEMS))
def test_reference_matches_full_kkt_integration(name):
    """Integrate (q, qdot) in R^10 with qddot from the KKT system M qddot = ... + omega^T lambda
    (index-reduced DAE, no use of the minimal equations) and compare with lj.reference."""
    system = SYSTEMS[name]
    q0, qdot0, ctl = index(maneuvers(system, 1, seed=21), 0)
    ts = jnp.linspace(0.0, 3.0, 7)

    def field(t, y, args):
        q, qdot = y
        f, _ = system.inputs(ctl(t))
        _, u_kin_dot = system.inputs(ctl.derivative(t))
        return qdot, system.full_acceleration(q, qdot, f, u_kin_dot)[0]

    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(field),
        diffrax.Dopri8(),
        0.0,
        3.0,
        None,
        (q0, qdot0),
        saveat=diffrax.SaveAt(ts=ts),
        stepsize_controller=diffrax.PIDController(rtol=1e-12, atol=1e-12),
        max_steps=100_000,
    )
    ref = lj.reference(system, q0, qdot0, ctl, ts)
    assert not bool(ref.failed)
    np.testing.assert_allclose(ref.q, sol.ys[0], atol=1e-9)
    np.testing.assert_allclose(ref.qdot, sol.ys[1], atol=1e-9)


def test_reference_is_converged():
    """Tightening the tolerance by 100x changes the answer by less than 1e-9 over 10 s."""
    sb = SYSTEMS["snakeboard"]
    q0, qdot0, ctl = index(maneuvers(sb, 1, seed=22), 0)
    ts = jnp.linspace(0.0, 10.0, 11)
    a = lj.reference(sb, q0, qdot0, ctl, ts)
    b = lj.reference(sb, q0, qdot0, ctl, ts, rtol=1e-13, atol=1e-13)
    assert float(jnp.max(jnp.abs(a.q - b.q))) < 1e-9


def test_reference_vmaps():
    car = SYSTEMS["car"]
    man = maneuvers(car, 3, seed=23)
    ts = jnp.linspace(0.0, 1.0, 5)
    batched = jax.vmap(lambda a, b, c: lj.reference(car, a, b, c, ts))(*man)
    single = lj.reference(car, *index(man, 2), ts)
    np.testing.assert_allclose(batched.q[2], single.q, atol=1e-12)
