"""DLA and GNI: measured order against the diffrax reference on both models, DLA's failure
reporting and gradients, and the GNI's discrete structure (averaged constraint, exact energy,
the parasitic period-2 mode of INTEGRATORS-NOTES.md 4.3)."""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import fitted_order, index, maneuvers, systems

import ldap_jax as lj

T = 2.0
NS = (40, 80, 160)
SYSTEMS = systems()
INTEGRATORS = {
    "dla": lj.DLA(),
    "gni": lj.GNI(),
    "gni_folded": lj.GNI(variant="folded"),
    "dla_alpha0": lj.DLA(alpha=0.0),
}


@functools.cache
def _case(sys_name):
    system = SYSTEMS[sys_name]
    man = maneuvers(system, 3, seed=11)
    ts = jnp.linspace(0.0, T, NS[0] + 1)
    ref = jax.vmap(lambda a, b, c: lj.reference(system, a, b, c, ts, rtol=1e-12, atol=1e-12))(*man)
    assert not bool(jnp.any(ref.failed))
    return system, man, ref


@pytest.mark.parametrize("sys_name", list(SYSTEMS))
@pytest.mark.parametrize("int_name", list(INTEGRATORS))
def test_observed_order(sys_name, int_name):
    integrator = INTEGRATORS[int_name]
    system, man, ref = _case(sys_name)
    pos = []
    for n in NS:
        traj = jax.vmap(
            lambda a, b, c, n=n: lj.simulate(system, a, b, c, t_final=T, n_steps=n, integrator=integrator)
        )(*man)
        assert not bool(jnp.any(traj.failed)), traj.result
        q = traj.q[:, :: n // NS[0]]
        pos.append(float(jnp.max(jnp.linalg.norm(q[..., :3] - ref.q[..., :3], axis=-1))))
        if isinstance(integrator, lj.DLA):
            assert bool(jnp.all(traj.converged))
            assert float(jnp.max(traj.step_residual)) < 1e-10
        # the node velocity estimates lie on the constraints
        assert float(jnp.max(traj.constraint_residual)) < 1e-10
    order = fitted_order([T / n for n in NS], pos)
    print(f"{sys_name} {int_name}: errors {pos}, order {order:.3f}")
    assert abs(order - integrator.order) < 0.15, (pos, order)
    assert pos[-1] < 0.05


def test_dla_agrees_with_rdp_at_midpoint():
    # Both are second order with the same force rule; at alpha = 1/2 their errors nearly
    # coincide (the paper's remark for short runs): their difference is far below either error.
    system, man, ref = _case("snakeboard")
    run = lambda integ: jax.vmap(  # noqa: E731
        lambda a, b, c: lj.simulate(system, a, b, c, t_final=T, n_steps=160, integrator=integ)
    )(*man)
    q_dla, q_rdp = run(lj.DLA()).q, run(lj.RDP()).q
    # the explicit (alpha = 0) predictor finds the same root as the Euler-type guess
    q_pred = run(lj.DLA(initial_guess="explicit")).q
    np.testing.assert_allclose(q_pred, q_dla, rtol=0, atol=1e-11)
    err = float(jnp.max(jnp.abs(q_rdp[:, ::4, :3] - ref.q[..., :3])))
    assert float(jnp.max(jnp.abs(q_dla - q_rdp))) < 0.1 * err


def _study_maneuver(i, seed=5):
    sb = SYSTEMS["snakeboard"]
    return sb, index(maneuvers(sb, 8, seed=seed), i)


def test_dla_reports_non_convergence():
    # h = 1.5 s on a spinning board: the physical root of the step folds away (INTEGRATORS-NOTES
    # 3.4) and Newton cannot converge. The failure must show as result code 3 at the failed step,
    # with NaN after it; the same maneuver at h = 0.1875 converges everywhere.
    sb, (q0, qdot0, ctl) = _study_maneuver(3)
    traj = lj.simulate(sb, q0, qdot0, ctl, t_final=30.0, n_steps=20, integrator=lj.DLA())
    assert int(traj.result) == 3, lj.RESULTS[int(traj.result)]
    k = int(traj.failure_index)
    assert not bool(traj.converged[k])
    assert float(traj.step_residual[k]) > 1e-8
    assert bool(jnp.all(traj.converged[:k]))
    assert bool(jnp.all(jnp.isnan(traj.q[k + 1 :])))
    assert bool(jnp.all(jnp.isfinite(traj.q[: k + 1])))
    with pytest.raises(Exception, match="integration failed"):
        lj.simulate(sb, q0, qdot0, ctl, t_final=30.0, n_steps=20, integrator=lj.DLA(), throw=True)
    fine = lj.simulate(sb, q0, qdot0, ctl, t_final=30.0, n_steps=160, integrator=lj.DLA())
    assert int(fine.result) == 0 and bool(jnp.all(fine.converged))


@pytest.mark.parametrize("sys_name", list(SYSTEMS))
def test_dla_gradient_matches_finite_differences(sys_name):
    system, man, _ = _case(sys_name)
    q0, qdot0, ctl = index(man, 0)

    def final_x(scale):
        c = eqx.tree_at(lambda c: c.amplitude, ctl, ctl.amplitude * scale)
        return lj.simulate(system, q0, qdot0, c, t_final=T, n_steps=40, integrator=lj.DLA()).q[-1, 0]

    one = jnp.asarray(1.0)
    grad = float(jax.grad(final_x)(one))
    eps = 1e-6
    fd = float((final_x(one + eps) - final_x(one - eps)) / (2 * eps))
    # central differences: truncation O(eps^2), roundoff ~1e-16 / eps = 1e-10
    assert abs(grad - fd) < 1e-7 * (1 + abs(fd)), (grad, fd)


@pytest.mark.parametrize("sys_name", list(SYSTEMS))
def test_gni_discrete_structure(sys_name):
    """The faithful GNI's defining properties hold to rounding: the constraints on average,
    ``omega(q_k) (v_k + v_{k-1}) = 0``, and, unforced, exact conservation of ``1/2 v^T M v``."""
    system, man, _ = _case(sys_name)
    q0, qdot0, ctl = index(man, 1)
    h_n = 200
    zero = eqx.tree_at(lambda c: c.amplitude, ctl, jnp.zeros_like(ctl.amplitude))
    for controls in (ctl, zero):
        traj = lj.simulate(system, q0, qdot0, controls, t_final=T, n_steps=h_n, integrator=lj.GNI())
        h = T / h_n
        v = jnp.diff(traj.q, axis=0) / h  # v_0 .. v_{N-1}
        v_all = jnp.concatenate([qdot0[None], v])  # v_{-1} = qdot0
        omega = jax.vmap(system.constraint_forms)(traj.q[:-1])
        avg = jnp.einsum("kij,kj->ki", omega, v_all[1:] + v_all[:-1])
        assert float(jnp.max(jnp.abs(avg))) < 1e-12 * (1 + float(jnp.max(jnp.abs(v)))), sys_name
        # the velocities themselves are not on the constraints (that is the method)
        viol = jnp.einsum("kij,kj->ki", omega, v_all[1:])
        assert float(jnp.max(jnp.abs(viol))) > 1e-8
    mass = jax.hessian(system.lagrangian, argnums=1)(q0, qdot0)
    ke = 0.5 * jnp.einsum("ki,ij,kj->k", v_all, mass, v_all)
    kin = np.asarray(system.kinematic_index)
    if kin.size == 0:  # with a prescribed (time-varying) steering rate the energy is not conserved
        assert float(jnp.max(jnp.abs(ke - ke[0]))) < 1e-12 * float(ke[0])


def test_gni_parasitic_mode_is_the_method():
    """The relative constraint violation |omega(q_k) v_k| / |v_k| of the faithful GNI grows on a
    time scale that does not shrink with h (a property of the two-step method, whose normal
    velocity obeys n_{k+1} = -n_k - (omega(q_{k+1}) - omega(q_k)) v_k exactly), while the folded
    variant keeps it O(h)."""
    sb = SYSTEMS["snakeboard"]
    q0, qdot0, ctl = index(maneuvers(sb, 4, seed=3), 0)
    t_final = 80.0
    late = {}
    for n in (1600, 6400):
        traj = lj.simulate(sb, q0, qdot0, ctl, t_final=t_final, n_steps=n, integrator=lj.GNI())
        late[n] = float(jnp.max(traj.step_residual[n // 2 : n]))
        early = float(jnp.max(traj.step_residual[: n // 8]))
        assert late[n] > 5 * early, (late[n], early)
        folded = lj.simulate(
            sb, q0, qdot0, ctl, t_final=t_final, n_steps=n, integrator=lj.GNI(variant="folded")
        )
        assert float(jnp.max(folded.step_residual)) < 0.2 * late[n]
    # 4x smaller steps do not shrink the late violation by anything like h^2 (16x)
    assert late[6400] > 0.25 * late[1600], late
    assert late[1600] > 0.1, late


def test_gni_refuses_configuration_dependent_mass_matrix():
    # The explicit GNI is consistent only for a constant mass matrix; the Chaplygin sleigh with an
    # offset contact point has M(theta). DLA handles it (implicit in L_d), GNI must refuse.
    sleigh = lj.chaplygin_sleigh()
    q0 = jnp.zeros(sleigh.n_config)
    qdot0 = sleigh.qdot_from_velocities(q0, jnp.full(sleigh.n_velocities, 0.5), jnp.zeros(sleigh.n_shape))
    shape = (sleigh.n_controls, 1)
    ctl = lj.Sinusoids(amplitude=jnp.full(shape, 0.1), frequency=jnp.ones(shape), phase=jnp.zeros(shape))
    with pytest.raises(Exception, match="mass matrix"):
        lj.simulate(sleigh, q0, qdot0, ctl, t_final=1.0, n_steps=10, integrator=lj.GNI())
    assert int(lj.simulate(sleigh, q0, qdot0, ctl, t_final=1.0, n_steps=10, integrator=lj.DLA()).result) == 0
