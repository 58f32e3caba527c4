"""Every integrator converges to the diffrax reference with its order, on random maneuvers."""

import jax
import jax.numpy as jnp
import pytest
from helpers import fitted_order, integrators, maneuvers, systems

import ldap_jax as lj

T = 2.0
N_MANEUVERS = 3
SYSTEMS = systems()


def _reference_batch(system, man, ts):
    q0, qdot0, ctl = man
    return jax.vmap(lambda a, b, c: lj.reference(system, a, b, c, ts, rtol=1e-12, atol=1e-12))(q0, qdot0, ctl)


def _errors(system, integrator, man, ns, ts_ref, ref):
    q0, qdot0, ctl = man
    n0 = ns[0]
    pos, vel = [], []
    for n in ns:
        traj = jax.vmap(
            lambda a, b, c, n=n: lj.simulate(system, a, b, c, t_final=T, n_steps=n, integrator=integrator)
        )(q0, qdot0, ctl)
        assert not bool(jnp.any(traj.failed))
        stride = n // n0
        q = traj.q[:, ::stride]
        qdot = traj.qdot[:, ::stride]
        pos.append(float(jnp.max(jnp.linalg.norm(q[..., :3] - ref.q[..., :3], axis=-1))))
        vel.append(float(jnp.max(jnp.linalg.norm(qdot - ref.qdot, axis=-1))))
    return pos, vel


@pytest.mark.parametrize("sys_name", list(SYSTEMS))
@pytest.mark.parametrize("int_name, integrator, order", integrators(), ids=[i[0] for i in integrators()])
def test_observed_order(sys_name, int_name, integrator, order):
    system = SYSTEMS[sys_name]
    man = maneuvers(system, N_MANEUVERS, seed=11)
    ns = (20, 40, 80) if order == 4 else (40, 80, 160)
    ts = jnp.linspace(0.0, T, ns[0] + 1)
    ref = _reference_batch(system, man, ts)
    assert not bool(jnp.any(ref.failed))
    pos, vel = _errors(system, integrator, man, ns, ts, ref)
    hs = [T / n for n in ns]
    p_pos, p_vel = fitted_order(hs, pos), fitted_order(hs, vel)
    print(f"{sys_name} {int_name}: position errors {pos} order {p_pos:.3f}; velocity order {p_vel:.3f}")
    assert p_pos > order - 0.15, (pos, p_pos)
    assert p_vel > min(order, 2) - 0.2, (vel, p_vel)
    assert pos[-1] < 0.05
