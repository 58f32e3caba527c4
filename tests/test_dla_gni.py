"""DLA and GNI: measured order against the diffrax reference on both models (positions, and node
velocities read from the carried momenta), DLA's failure reporting and gradients, and the GNI's
discrete structure (averaged constraint, exact energy, the parasitic period-2 mode, docs/integrators.md
section 5)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import (
    CONV_BATCH,
    CONV_NS,
    CONV_T,
    INTEGRATORS,
    SLEIGH,
    code,
    convergence_case,
    convergence_runs,
    fitted_order,
    index,
    maneuvers,
    simulate_batch,
    simulate_ns,
    systems,
)

import ldap_jax as lj

SYSTEMS = systems()
NAMES = ("dla", "gni", "gni_folded", "dla_alpha0")
NS = CONV_NS[2]


@pytest.mark.parametrize("sys_name", list(SYSTEMS))
@pytest.mark.parametrize("int_name", NAMES)
def test_observed_order(sys_name, int_name):
    integrator, order = INTEGRATORS[int_name]
    assert integrator.order == order
    _, ref = convergence_case(sys_name)
    runs = convergence_runs(sys_name, int_name)
    pos, vel = [], []
    for n in NS:
        run = runs[n]
        assert not bool(np.any(run.failed)), run.result
        q, qdot = run.q[:, :: n // NS[0]], run.qdot[:, :: n // NS[0]]
        pos.append(float(np.max(np.linalg.norm(q[..., :3] - ref.q[..., :3], axis=-1))))
        vel.append(float(np.max(np.linalg.norm(qdot - ref.qdot, axis=-1))))
        if isinstance(integrator, lj.DLA):
            assert bool(np.all(run.converged))
            assert float(np.max(run.step_residual)) < 1e-10
        # the node velocities (from the momenta, projected onto the distribution) lie on the constraints
        assert float(np.max(run.constraint_residual)) < 1e-10
    hs = [CONV_T / n for n in NS]
    p_pos, p_vel = fitted_order(hs, pos), fitted_order(hs, vel)
    print(f"{sys_name} {int_name}: errors {pos} order {p_pos:.3f}; velocity {vel} order {p_vel:.3f}")
    assert abs(p_pos - order) < 0.15, (pos, p_pos)
    # node velocities from the momenta: as accurate as the positions
    assert p_vel > order - 0.2, (vel, p_vel)
    assert pos[-1] < 0.05


def test_dla_agrees_with_rdp_at_midpoint():
    # Both are second order with the same force rule; at alpha = 1/2 their errors nearly
    # coincide (the paper's remark for short runs): their difference is far below either error.
    man, ref = convergence_case("snakeboard")
    sb = SYSTEMS["snakeboard"]
    q_dla = convergence_runs("snakeboard", "dla")[160].q
    # test_convergence's RDP runs (without diagnostics): not computed again
    q_rdp = convergence_runs("snakeboard", "rdp_exp", diagnostics=False)[160].q
    # the explicit (alpha = 0) predictor finds the same root as the Euler-type guess
    q_pred = simulate_batch(sb, lj.DLA(initial_guess="explicit"), man, CONV_T, 160).q
    np.testing.assert_allclose(q_pred, q_dla, rtol=0, atol=1e-11)
    err = float(np.max(np.abs(q_rdp[:, ::4, :3] - ref.q[..., :3])))
    assert float(np.max(np.abs(q_dla - q_rdp))) < 0.1 * err


def test_dla_reports_non_convergence():
    # h = 1.5 s on a spinning board: the physical root of the step folds away (docs/integrators.md
    # section 4) and Newton cannot converge. The failure must show as RESULTS.not_converged at the
    # failed step, with NaN after it; the same maneuver at h = 0.1875 converges everywhere.
    sb = SYSTEMS["snakeboard"]
    # three maneuvers at three step counts: the batch size and step count of the convergence runs,
    # whose compiled program this reuses; member 0 is the spinning one
    batch = index(maneuvers(sb, 8, seed=5), slice(3, 6))
    runs = simulate_ns(sb, lj.DLA(), batch, 30.0, (20, 40, 160))
    coarse, fine = runs[20], runs[160]
    assert int(coarse.result[0]) == lj.RESULTS.not_converged._value, coarse.result
    k = int(coarse.failure_index[0])
    assert k < 20
    assert not bool(coarse.converged[0, k + 1])  # node k + 1 reports the failed step k
    assert float(coarse.step_residual[0, k + 1]) > 1e-8
    assert bool(np.all(coarse.converged[0, : k + 1]))
    assert bool(np.all(np.isnan(coarse.q[0, k + 1 :])))
    assert bool(np.all(np.isfinite(coarse.q[0, : k + 1])))
    assert int(fine.result[0]) == 0 and bool(np.all(fine.converged))
    with pytest.raises(Exception, match="did not converge"):
        lj.simulate(sb, *index(batch, 0), t_final=30.0, n_steps=20, integrator=lj.DLA(), throw=True)


@pytest.mark.parametrize("sys_name", list(SYSTEMS))
def test_dla_gradient_matches_finite_differences(sys_name):
    man, _ = convergence_case(sys_name)
    system = SYSTEMS[sys_name]
    q0, qdot0, ctl = index(man, 0)

    def final_x(scale):
        c = eqx.tree_at(lambda c: c.amplitude, ctl, ctl.amplitude * scale)
        traj = lj.simulate(
            system, q0, qdot0, c, t_final=CONV_T, n_steps=40, integrator=lj.DLA(), diagnostics=False
        )
        return traj.q[-1, 0]

    value_and_grad = jax.jit(jax.value_and_grad(final_x))
    one = jnp.asarray(1.0)
    grad = float(value_and_grad(one)[1])
    eps = 1e-6
    fd = (float(value_and_grad(one + eps)[0]) - float(value_and_grad(one - eps)[0])) / (2 * eps)
    # central differences: truncation O(eps^2), roundoff ~1e-16 / eps = 1e-10
    assert abs(grad - fd) < 1e-7 * (1 + abs(fd)), (grad, fd)


@eqx.filter_jit  # one program, not op by op
def _gni_structure(system, q, qdot0, h):
    """The difference velocities ``v_0 .. v_{N-1}`` of the nodes ``q``, the averaged constraints
    ``omega(q_k) (v_k + v_{k-1})``, the constraints on ``v_k`` alone, and ``1/2 v^T M(q_0) v``
    along ``v_{-1} = qdot0, v_0, ...``."""
    v = jnp.diff(q, axis=0) / h
    v_all = jnp.concatenate([qdot0[None], v])
    omega = jax.vmap(system.constraint_forms)(q[:-1])
    avg = jnp.einsum("kij,kj->ki", omega, v_all[1:] + v_all[:-1])
    viol = jnp.einsum("kij,kj->ki", omega, v_all[1:])
    mass = jax.hessian(system.lagrangian, argnums=1)(q[0], qdot0)
    return v, avg, viol, 0.5 * jnp.einsum("ki,ij,kj->k", v_all, mass, v_all)


@pytest.mark.parametrize("sys_name", list(SYSTEMS))
def test_gni_discrete_structure(sys_name):
    """The faithful GNI's defining properties hold to rounding: the constraints on average,
    ``omega(q_k) (v_k + v_{k-1}) = 0``, and, unforced, exact conservation of ``1/2 v^T M v``."""
    man, _ = convergence_case(sys_name)
    system = SYSTEMS[sys_name]
    q0, qdot0, ctl = index(man, 1)
    zero = eqx.tree_at(lambda c: c.amplitude, ctl, jnp.zeros_like(ctl.amplitude))
    # forced, unforced, and the forced one again up to the batch size and step count of the
    # convergence runs (their compiled program is reused)
    h_n = max(NS)
    members = [(q0, qdot0, ctl), (q0, qdot0, zero)] + [(q0, qdot0, ctl)] * (CONV_BATCH * len(NS) - 2)
    batch = jax.tree_util.tree_map(lambda *x: np.stack(x), *members)
    h = CONV_T / h_n
    traj = simulate_batch(system, lj.GNI(), batch, CONV_T, h_n)
    q, residual = np.asarray(traj.q), np.asarray(traj.constraint_residual)  # host copies
    for i in range(2):  # forced, unforced
        v, avg, viol, ke = (np.asarray(x) for x in _gni_structure(system, q[i], qdot0, h))
        assert float(np.max(np.abs(avg))) < 1e-12 * (1 + float(np.max(np.abs(v)))), sys_name
        # the velocities themselves are not on the constraints (that is the method)
        assert float(np.max(np.abs(viol))) > 1e-8
        # ... but the node velocities read from the momenta are
        assert float(np.max(residual[i])) < 1e-12 * (1 + float(np.max(np.abs(v))))
    kin = np.asarray(system.kinematic_index)
    if kin.size == 0:  # with a prescribed (time-varying) steering rate the energy is not conserved
        assert float(np.max(np.abs(ke - ke[0]))) < 1e-12 * float(ke[0])


def test_gni_parasitic_mode_is_the_method():
    """The relative constraint violation |omega(q_k) v_k| / |v_k| of the faithful GNI grows on a
    time scale that does not shrink with h (a property of the two-step method, whose normal
    velocity obeys n_{k+1} = -n_k - (omega(q_{k+1}) - omega(q_k)) v_k exactly), while the folded
    variant keeps it O(h)."""
    sb = SYSTEMS["snakeboard"]
    batch = index(maneuvers(sb, 4, seed=3), slice(0, 1))
    t_final = 80.0
    ns = (1600, 6400)
    faithful = simulate_ns(sb, lj.GNI(max_violation=None), batch, t_final, ns)  # not stopped
    folded = simulate_ns(sb, lj.GNI(variant="folded"), batch, t_final, ns)
    late = {}
    for n in ns:
        res = faithful[n].step_residual[0]  # node k + 1 holds step k's violation
        assert not bool(faithful[n].failed[0]) and not bool(folded[n].failed[0])
        late[n] = float(np.max(res[n // 2 + 1 : n + 1]))
        early = float(np.max(res[1 : n // 8 + 1]))
        assert late[n] > 5 * early, (late[n], early)
        assert float(np.max(folded[n].step_residual[0, 1:])) < 0.2 * late[n]
    # 4x smaller steps do not shrink the late violation by anything like h^2 (16x)
    assert late[6400] > 0.25 * late[1600], late
    assert late[1600] > 0.1, late


def test_gni_parasitic_mode_ends_the_run_as_diverged():
    """A car with a 2 m wheel driven from 3 rad/s (its heading turns 45 rad in 4 s): the faithful
    GNI's parasitic mode takes the velocity off the constraints within the run at every step
    size, its heading 36-42 rad from the truth where the folded variant and RDP converge. With
    the default ``max_violation`` the run ends ``diverged``; without it (``None``) it reports
    success with that error, which is what the check is for."""
    car = lj.Car(m=1.0, I=0.1, K=0.2, rho=2.0, l=0.5)
    f0 = 0.1 + 1.0 * 2.0**2
    ctl = lj.Sinusoids(
        amplitude=jnp.array([[f0, 0.5 * f0], [0.5, 0.0]]),
        frequency=jnp.array([[1.0, 2.3], [1.0, 1.0]]),
        phase=jnp.array([[0.3, 1.0], [0.5, 0.0]]),
    )
    q0 = jnp.array([0.0, 0.0, 0.4, 0.0, 0.2])
    qdot0 = car.qdot_from_velocities(q0, jnp.array([3.0]), jnp.zeros(2))

    def final(integrator, n):
        traj = lj.simulate(
            car,
            q0,
            qdot0,
            ctl,
            t_final=4.0,
            n_steps=n,
            integrator=integrator,
            save="final",
            diagnostics=False,
        )
        return code(traj.result), np.asarray(traj.q[-1])

    _, truth = final(lj.RDP(order=4), 2560)  # 1.5e-12 from the Lagrange-d'Alembert solution
    for n in (160, 2560):
        assert final(lj.GNI(), n)[0] == code(lj.RESULTS.diverged), n
    result, q = final(lj.GNI(max_violation=None), 2560)
    assert result == code(lj.RESULTS.successful) and abs(q[2] - truth[2]) > 10.0
    result, q = final(lj.GNI(variant="folded"), 2560)
    assert result == code(lj.RESULTS.successful) and np.max(np.abs(q[:3] - truth[:3])) < 1e-2
    with pytest.raises(ValueError, match="'max_violation'"):
        lj.GNI(max_violation=0.0)


def test_gni_refuses_configuration_dependent_mass_matrix():
    # The explicit GNI is consistent only for a constant mass matrix; the Chaplygin sleigh with an
    # offset contact point has M(theta). DLA handles it (implicit in L_d), GNI must refuse.
    q0 = jnp.zeros(SLEIGH.n_config)
    qdot0 = SLEIGH.qdot_from_velocities(q0, jnp.full(SLEIGH.n_velocities, 0.5), jnp.zeros(SLEIGH.n_shape))
    with pytest.raises(Exception, match="mass matrix"):
        lj.simulate(SLEIGH, q0, qdot0, None, t_final=1.0, n_steps=10, integrator=lj.GNI())
    traj = lj.simulate(SLEIGH, q0, qdot0, None, t_final=1.0, n_steps=10, integrator=lj.DLA())
    assert traj.result == lj.RESULTS.successful
    assert code(traj.result) == 0
