"""Periodic gaits as hard-constrained limit cycles: the built-in gaits solved from their default
guesses, periodicity and prescribed displacements on the model, the replay over several cycles
on the reference, the cycle map's monodromy and Floquet analysis, sensitivities of the optimum
by the implicit function theorem, the tracker, and bad input. The roller racer's gait and a user
path constraint are checked on the results of notebook 06 and of the control guide
(tests/test_docs.py), which compute them anyway."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ldap_jax as lj
from ldap_jax import control as lc

pytestmark = pytest.mark.xdist_group("gaits")  # one worker compiles the drive gait's programs


@pytest.fixture(scope="module")
def drive():
    task = lc.drive_gait()
    return task, lc.solve(task)


def test_drive_gait_is_a_periodic_orbit_that_holds_on_the_reference(drive):
    """From its default guess with default settings: converged with the model's constraints met to
    1e-9; one cycle of the model returns to its start's reduced state to 1e-9, with the prescribed
    zero net rotation met to 1e-9 and the bounds held at the nodes; replayed for 3 cycles on the
    reference, each cycle returns to within 1e-5 of the model's orbit and moves as the model's
    cycle does to 1e-6."""
    task, sol = drive
    assert bool(sol.converged), lc.SOLVER_RESULTS[sol.result]
    assert float(sol.max_violation) <= 1e-9
    rp = lc.replay_gait(task, sol, cycles=3)  # the Solution counts as its params
    assert rp["reference_result"] == lj.RESULTS.successful
    assert rp["model_return_error"] <= 1e-9
    assert abs(float(rp["model_displacement"][2])) <= 1e-9
    # the objective is the displacement along the start's heading, per cycle
    assert float(rp["model_displacement"][0]) == pytest.approx(-float(sol.cost), rel=1e-12)
    assert np.all(rp["return_error"] < 1e-5), rp["return_error"]
    assert np.all(rp["displacement_error"] < 1e-6), rp["displacement_error"]
    c = np.asarray(task.parameterization.values(sol.params.controls))
    assert np.max(np.abs(c)) <= 0.1 + 1e-12
    assert np.max(np.abs(np.asarray(rp["q_ref"])[:, 4])) <= 1.0 + 1e-6  # phi on the reference
    np.testing.assert_allclose(c[-1], c[0], atol=1e-9)  # u_N = u_0


def test_monodromy_matches_finite_differences_of_the_cycle_map(drive):
    """The Jacobian of the cycle map by autodiff against central differences of the map (the
    matrix, not its eigenvalues, which the Jordan blocks at 1 make sensitive)."""
    task, sol = drive
    z0, M = lc.monodromy(task, sol.params)
    P = lambda z: lc.cycle_map(task, sol.params, z)  # noqa: E731 (one compiled program)
    z0, M = np.asarray(z0), np.asarray(M)
    np.testing.assert_allclose(np.asarray(P(z0)), z0, atol=1e-9)  # a fixed point
    eps = 1e-6
    for i in range(z0.size):
        e = np.zeros_like(z0)
        e[i] = eps
        fd = (np.asarray(P(z0 + e)) - np.asarray(P(z0 - e))) / (2 * eps)
        np.testing.assert_allclose(M[:, i], fd, rtol=1e-6, atol=1e-7)


def test_floquet_analysis_names_the_jordan_structure():
    """Jordan blocks at 1 recovered from the ranks of (M - I)^j under a perturbation that splits
    their eigenvalues; stable and unstable matrices classified."""
    rng = np.random.default_rng(0)
    J = np.eye(4) + np.diag([1.0, 1.0, 0.0], k=1)  # blocks of size 3 and 1 at 1
    S = rng.normal(size=(4, 4)) + 3 * np.eye(4)
    M = S @ J @ np.linalg.inv(S) + 1e-12 * rng.normal(size=(4, 4))
    out = lc.floquet(M)
    assert out["jordan_blocks"] == [3, 1] and out["at_one"] == 4 and out["growth"] == 2
    assert out["stability"] == "neutrally stable"
    assert lc.floquet(np.diag([0.5, -0.9]))["stability"] == "asymptotically stable"
    assert lc.floquet(np.diag([1.1, 0.2]))["stability"] == "unstable"


def test_drive_gait_sensitivities_match_finite_differences_of_resolves(drive):
    """d(displacement per cycle)/d(torque bound, mass, period) by the implicit function theorem
    against central differences of re-solves (rtol 1e-5), in reverse mode and in forward mode
    (a ``jax.jvp`` with respect to the model or the period once raised: the solution's
    model-error diagnostic rolled out through the failure mask's custom VJP). The re-solves start
    from the Solution (a warm start with a small barrier) and stay at its optimum: from its
    params alone, at the gaits' default barrier, they ended at another one, 8.5e-5 m lower."""
    task, sol = drive
    p0 = sol

    def distance(bound, m, period):
        b = task.bounds
        t = eqx.tree_at(
            lambda t: (t.bounds.u_lower, t.bounds.u_upper, t.system.m, t.t_final, t.parameterization.t_final),
            task,
            (b.u_lower.at[0].set(-bound), b.u_upper.at[0].set(bound), m, period, period),
        )
        return -lc.solve(t, p0, tol=1e-10).cost

    b0, m0, t0 = jnp.asarray(0.1), jnp.asarray(float(task.system.m)), jnp.asarray(float(task.t_final))
    # the same optimum, to the barrier's gap between tol 1e-8 and 1e-10 (2e-7)
    assert abs(float(distance(b0, m0, t0)) + float(sol.cost)) < 1e-6
    # a tol below what float64 resolves here (the KKT error stops near 1e-11): reported as stalled
    # at an optimal point, not as a line search that found nothing (which suggested infeasibility)
    tight = lc.solve(task, sol, tol=1e-14)
    assert not bool(tight.converged) and tight.result == lc.SOLVER_RESULTS.stalled
    assert float(tight.kkt_error) < 1e-8 and abs(float(tight.cost - sol.cost)) < 1e-6
    grad = jax.grad(distance, argnums=(0, 1, 2))(b0, m0, t0)
    forward = jax.jacfwd(distance, argnums=(0, 1, 2))(b0, m0, t0)
    np.testing.assert_allclose(np.asarray(forward), np.asarray(grad), rtol=1e-9)
    for i, (x, eps) in enumerate(((b0, 1e-5), (m0, 1e-4), (t0, 1e-4))):
        args = [b0, m0, t0]
        args[i] = x + eps
        up = float(distance(*args))
        args[i] = x - eps
        down = float(distance(*args))
        np.testing.assert_allclose(float(grad[i]), (up - down) / (2 * eps), rtol=1e-5)


def test_a_singular_steering_bound_and_a_failed_period_are_named():
    """A snakeboard steering bound reaching |phi| = pi/2 is refused (the solver's iterates reached
    the singularity and it failed with a message about the Hessian); a start whose period fails
    (here at cos(phi) = 0) makes monodromy and replay_gait raise naming the rollout's result, not
    return NaNs or LAPACK's error on them."""
    for make in (lc.drive_gait, lc.turn_gait, lc.reach):
        with pytest.raises(ValueError, match="'max_steer'.*pi/2"):
            make(max_steer=2.0)
    with pytest.raises(ValueError, match="'max_steer'"):
        lc.drive_gait(max_steer=(-1.0, 1.6))
    task = lc.drive_gait(n_steps=10)
    p = task.init()
    singular = lc.GaitParams(p.controls, jnp.asarray(p.state).at[0].set(0.5 * np.pi))  # phi at pi/2
    for analysis in (lc.monodromy, lambda t, q: lc.replay_gait(t, q, cycles=1)):
        with pytest.raises(ValueError, match="singular configuration"):
            analysis(task, singular)
    with pytest.raises(ValueError, match="'M'"):
        lc.floquet(np.full((2, 2), np.nan))


def test_gait_bad_inputs_are_clear():
    sb = lj.Snakeboard()
    kw = dict(objective=(lc.Displacement(),), constraints=(lc.InitialRest((0, 2)),), cyclic=("psi",))
    with pytest.raises(ValueError, match="'period'"):
        lc.make_gait(sb, period=0.0, n_steps=10, **kw)
    with pytest.raises(ValueError, match="'n_steps'"):
        lc.make_gait(sb, period=1.0, n_steps=1, **kw)
    with pytest.raises(ValueError, match="NetDisplacement"):
        lc.NetDisplacement(dx=[0.1, 0.2])
    with pytest.raises(ValueError, match="lower"):
        lc.Bounds.of(sb, q={"phi": (1.0, -1.0)})
    with pytest.raises(ValueError, match="periodic"):
        lc.replay_gait(lc.parallel_park(n_steps=10), None)
    with pytest.raises(ValueError, match="'cycles'"):
        lc.replay_gait(lc.drive_gait(n_steps=10), None, cycles=0)
    with pytest.raises(TypeError, match="make_gait: 'system'"):
        lc.make_gait(None, period=1.0, n_steps=10, objective=(lc.Displacement(),))
    with pytest.raises(ValueError, match="floquet: 'M' must be a square"):
        lc.floquet(np.eye(3)[:2])
    # one name is a name (it was split into its letters)
    assert lc.make_gait(sb, period=1.0, n_steps=10, **(kw | dict(cyclic="psi"))).periodic.cyclic == ("psi",)
    with pytest.raises(TypeError, match="make_gait: 'cyclic'"):
        lc.make_gait(sb, period=1.0, n_steps=10, **(kw | dict(cyclic=(1,))))
    with pytest.raises(TypeError, match="lc.Periodic: 'cyclic'"):
        lc.Periodic(cyclic=(1,))


def test_a_coordinate_the_equations_depend_on_is_not_cyclic():
    """``cyclic`` names coordinates that no equation depends on. The snakeboard's steering angle
    declared cyclic was accepted: the solve reported success for a "gait" whose phi went 0 -> 1
    per cycle, which replay_gait compared without phi and which met cos(phi) = 0 in its second
    cycle. A built-in model declares its cyclic coordinates; an ``lj.System`` is tested on its
    equations (the racer's hinge angle is refused, a rotor that nothing depends on accepted)."""
    sb = lj.Snakeboard()
    kw = dict(period=np.pi, n_steps=10, objective=(lc.Displacement(),))
    with pytest.raises(ValueError, match=r"\['phi'\] are not cyclic: Snakeboard"):
        lc.make_gait(sb, cyclic=("psi", "phi"), **kw)
    with pytest.raises(ValueError, match=r"\['phi'\] are not cyclic: System"):
        lc.make_gait(lj.roller_racer(drag=0.3), cyclic=("phi",), **kw)

    def lagrangian(r, u, xi):  # a knife-edge sleigh carrying a rotor of angle r
        return 0.5 * (xi[1] ** 2 + (xi[2] + 0.3 * xi[0]) ** 2 + 0.2 * xi[0] ** 2 + 0.05 * (xi[0] + u[0]) ** 2)

    rotor = lj.System(
        1,
        lagrangian,
        lambda r: jnp.zeros((3, 1)),
        lambda r: jnp.eye(3, 2),
        lambda r: jnp.array([[0.0, 0.0, 1.0, 0.0]]),
        shape_names=("rotor",),
    )
    assert lc.make_gait(rotor, cyclic=("rotor",), **kw).periodic.cyclic == ("rotor",)


def test_a_warm_start_from_a_solution_stays_at_its_optimum():
    """A custom gait (the snakeboard's most displacement along the diagonal, RDP order 2) re-solved
    from its own Solution: the states were pushed 1e-2 off their active bounds, far from the
    optimum for the warm start's barrier of 1e-6, and the re-solve spent its 1000 iterations at a
    KKT error of 2.8e-8 (every sensitivity NaN). Pushed by 1e-9, it converges in a few iterations
    to the same optimum (the objective is flat there: within 1e-6 of it relative)."""
    sb, r2 = lj.Snakeboard(), np.sqrt(0.5)
    task = lc.make_gait(
        sb,
        period=2.0,
        n_steps=60,
        objective=(lc.Displacement((r2, r2)),),
        constraints=(lc.InitialRest((0, 2)),),
        cyclic=("psi",),
        bounds=lc.Bounds.of(sb, q={"phi": 0.8}, u={"f_psi": 0.08, "f_phi": (-0.05, 0.15)}),
        integrator=lj.RDP(order=2),
    )
    sol = lc.solve(task)
    assert bool(sol.converged), lc.SOLVER_RESULTS[sol.result]
    warm = lc.solve(task, sol)
    assert bool(warm.converged) and int(warm.iterations) < 40, (
        lc.SOLVER_RESULTS[warm.result],
        warm.iterations,
    )
    assert abs(float(warm.cost) - float(sol.cost)) < 1e-6 * abs(float(sol.cost)), (warm.cost, sol.cost)


def test_gait_analysis_and_tracker_check_their_inputs(drive):
    """The cycle map, the monodromy and the tracker name what is wrong with their inputs: a ``z``
    of another shape (eagerly and under ``jit``; it was padded or truncated), a start whose period
    fails (the snakeboard's singularity: NaN with no reason before), NaN parameters, parameters
    of a fixed-start task, weights that are not positive and finite and a fractional number of
    sweeps (NaN gains or a silent zero feedback before); a tracker built from a solution that
    did not converge warns (its start is not a periodic orbit)."""
    task, sol = drive
    z0 = np.asarray(lc.monodromy(task, sol)[0])
    for z in (z0[:3], np.append(z0, 0.0)):
        with pytest.raises(ValueError, match="'z' must have shape \\(4,\\)"):
            lc.cycle_map(task, sol.params, z)
    with pytest.raises(ValueError, match="'z' must have shape"):
        jax.jit(lambda z: lc.cycle_map(task, sol.params, z))(jnp.zeros(5))
    with pytest.raises(ValueError, match="rollout from 'z' failed: singular"):
        lc.cycle_map(task, sol.params, np.array([np.pi / 2, 0.0, 0.0, 0.0]))
    nan_start = lc.GaitParams(sol.params.controls, sol.params.state.at[0].set(jnp.nan))
    with pytest.raises(ValueError, match="'params' must be finite"):
        lc.monodromy(task, nan_start)
    with pytest.raises(TypeError, match="'params' of a periodic task must be lc.GaitParams"):
        lc.replay_gait(task, sol.params.controls)
    for kw, match in (
        (dict(r_weight=float("nan")), "'r_weight'"),
        (dict(q_weight=-1.0), "'q_weight'"),
        (dict(q_weight=0.0), "'q_weight'"),
        (dict(sweeps=2.5), "'sweeps'"),
    ):
        with pytest.raises((TypeError, ValueError), match=match):
            lc.gait_tracker(task, sol, **kw)
    unconverged = lc.solve(task, max_iterations=2)
    assert not bool(unconverged.converged)
    with pytest.warns(UserWarning, match="did not converge"):
        lc.gait_tracker(task, unconverged)


def test_tracker_holds_the_drive_gait_under_model_error(drive):
    """10 cycles of the drive gait on a snakeboard 5 % heavier than the model, from a perturbed
    start (phi + 0.02 rad, rotor rate + 0.05 rad/s): open loop the displacement per cycle is more
    than 5 % off the nominal; with lc.gait_tracker (torques saturated at their bounds) every
    cycle stays within 5 %. The runs are reference-grade: RDP order 6 at h = T/400, which matches
    lj.reference (that takes no feedback policy) to 1e-8 m on the nominal open-loop run."""
    task, sol = drive
    tracker = lc.gait_tracker(task, sol)
    q0, qdot0 = task.initial_state(sol.params)
    cycles, per = 10, 400
    T = float(task.t_final)
    heavy = eqx.tree_at(lambda s: s.m, task.system, task.system.m * 1.05)

    @jax.jit
    def perturbed(q0, qdot0, params):  # one program, not one per operation
        q0p = q0.at[4].add(0.02)
        v = task.system.velocities_from_qdot(q0, qdot0) + jnp.array([0.05, 0.0, 0.0])
        return q0p, task.system.qdot_from_velocities(q0p, v, task.controls(params)(0.0))

    q0p, qdot0p = perturbed(q0, qdot0, sol.params)

    @eqx.filter_jit
    def run(system, controls, q, qdot):
        traj = lj.simulate(
            system, q, qdot, controls, t_final=cycles * T, n_steps=cycles * per, integrator=lj.RDP(order=6)
        )
        return traj.q[::per], traj.result

    @jax.jit
    def per_cycle(g):
        return jax.vmap(lambda a, b: lj.lie.compose(lj.lie.inverse(a), b))(g[:-1, :3], g[1:, :3])

    open_loop = task.controls(sol.params).over(cycles)
    nodes, result = run(task.system, open_loop, q0, qdot0)
    ref = lj.reference(task.system, q0, qdot0, open_loop, np.arange(cycles + 1) * T)
    assert result == lj.RESULTS.successful
    np.testing.assert_allclose(np.asarray(nodes), np.asarray(ref.q), atol=1e-8)
    nominal = -float(sol.cost)
    drift = {}
    for name, controls in (("open", open_loop), ("tracked", tracker)):
        nodes, result = run(heavy, controls, q0p, qdot0p)
        assert result == lj.RESULTS.successful
        drift[name] = np.max(np.abs(np.asarray(per_cycle(nodes))[:, 0] - nominal)) / nominal
    assert drift["tracked"] < 0.05 < drift["open"], drift


def test_tracker_leaves_a_run_on_the_gait_on_it(drive):
    """Started exactly on the optimised cycle with the exact model, the tracked run stays on the
    cycle as the open-loop run does: after each of 3 cycles its reduced state is within 1e-9 of
    the start on the task's own grid and integrator, and within 1e-6 at h / 8 with RDP order 8
    (the policy is sampled between the cycle's nodes there). The feedback once compared the state
    of a step's start with the reference at later times of the step, and the reference between
    the nodes was interpolated linearly: the tracked runs settled 4e-2 and 2e-3 off the cycle."""
    task, sol = drive
    tracker = lc.gait_tracker(task, sol)
    q0, qdot0 = task.initial_state(sol.params)
    T, n, cycles = float(task.t_final), task.n_steps, 3

    def reduced(q, qdot):
        return np.concatenate(
            [np.asarray(q)[list(tracker.keep)], np.asarray(task.system.velocities_from_qdot(q, qdot))]
        )

    z0 = reduced(q0, qdot0)
    for integrator, per_step, tol in ((task.integrator, 1, 1e-9), (lj.RDP(order=8), 8, 1e-6)):
        steps = n * per_step
        traj = lj.simulate(
            task.system, q0, qdot0, tracker, t_final=cycles * T, n_steps=cycles * steps, integrator=integrator
        )
        assert traj.result == lj.RESULTS.successful
        off = [
            np.max(np.abs(reduced(traj.q[c * steps], traj.qdot[c * steps]) - z0))
            for c in range(1, cycles + 1)
        ]
        assert max(off) < tol, (integrator, off)


def test_infeasible_prescribed_displacement_is_reported(drive):
    """A net rotation of 20 rad per cycle, far beyond what the torque bounds allow in one period
    (the drive gait's own constraint with another target: the same compiled program): not
    converged, with a result that names the cause, never a silent NaN passed off as an answer."""
    task, sol = drive
    (i,) = [k for k, c in enumerate(task.constraints) if isinstance(c, lc.NetDisplacement)]
    far = eqx.tree_at(lambda t: t.constraints[i].target, task, jnp.array([20.0]))
    bad = lc.solve(far, sol.params, max_iterations=300)
    assert not bool(bad.converged)
    assert bad.result in (
        lc.SOLVER_RESULTS.infeasible,
        lc.SOLVER_RESULTS.line_search_failed,
        lc.SOLVER_RESULTS.max_iterations,
    ), lc.SOLVER_RESULTS[bad.result]
    assert float(bad.max_violation) > 1e-3
    assert np.isfinite(float(bad.max_violation))


def _racer_momentum_equation():
    """The roller racer's momentum ``p(phi, phidot, s)`` and its rate ``pdot(phi, phidot, s, f)``
    along the continuous reduced equations (hinge torque ``f``), vectorised; and the coefficients
    ``a(phi)``, ``beta(phi)`` of ``pdot = a phidot p + beta phidot^2`` read off them."""
    racer = lj.roller_racer()

    def p(phi, phidot, s):
        q = jnp.stack([0.0, 0.0, 0.0, phi])
        return racer.momentum(q, racer.qdot_from_velocities(q, jnp.stack([phidot, s]), jnp.zeros(1)))[0]

    def pdot(phi, phidot, s, f):
        q = jnp.stack([0.0, 0.0, 0.0, phi])
        acc = racer.velocity_dynamics(q, jnp.stack([phidot, s]), jnp.stack([f]), jnp.zeros(1))
        return jax.jvp(p, (phi, phidot, s), (phidot, acc[0], acc[1]))[1]

    def coefficients(phi):
        # a: the slope in p at unit hinge rate; beta: the rest at unit hinge rate
        a = (pdot(phi, 1.0, 1.0, 0.0) - pdot(phi, 1.0, 0.0, 0.0)) / (p(phi, 1.0, 1.0) - p(phi, 1.0, 0.0))
        return a, pdot(phi, 1.0, 0.0, 0.0) - a * p(phi, 1.0, 0.0)

    return racer, jax.jit(jax.vmap(p)), jax.jit(jax.vmap(pdot)), jax.jit(jax.vmap(coefficients))


def test_the_roller_racer_has_no_gait_its_momentum_grows_every_cycle():
    """Why ``lj.roller_racer()`` has no gait: its momentum equation is
    ``pdot = a(phi) phidot p + beta(phi) phidot^2`` with ``beta > 0`` and no hinge torque in it, so
    ``Phi(phi) p`` with ``Phi = exp(-int_0^phi a)`` grows by ``int beta Phi phidot^2 dt > 0`` over
    any cycle in which the hinge moves: no periodic motion but coasting. Checked on the continuous
    equations at random states (the torque's absence, the form, ``beta > 0`` on [-pi, pi]) and on
    the model (RDP order 4): over one period of random periodic torques, ``Phi p`` at the nodes
    never decreases (to 1e-9) and its gain matches the quadrature of ``beta Phi phidot^2``."""
    racer, P, Pd, coefficients = _racer_momentum_equation()
    rng = np.random.default_rng(3)
    phi, phidot = rng.uniform(-np.pi, np.pi, 64), rng.uniform(-3, 3, 64)
    s, f = rng.uniform(-2, 2, 64), rng.uniform(-5, 5, 64)
    np.testing.assert_allclose(Pd(phi, phidot, s, f), Pd(phi, phidot, s, 0 * f), rtol=1e-12, atol=1e-12)

    # the model: one period of random periodic hinge torques from a moving start
    T, n = 4.0, 400
    coef, k = rng.normal(size=(2, 3)), np.arange(1, 4)

    def torque(t, q, qdot):
        w = 2 * jnp.pi * k * t / T
        return jnp.stack([jnp.sum(coef[0] * jnp.sin(w) + coef[1] * jnp.cos(w))])

    q0 = np.array([0.0, 0.0, 0.0, 0.3])
    qdot0 = np.asarray(eqx.filter_jit(racer.qdot_from_velocities)(q0, jnp.array([0.8, -0.4]), jnp.zeros(1)))
    traj = lj.simulate(
        racer, q0, qdot0, lj.Policy(torque, 1), t_final=T, n_steps=n, integrator=lj.RDP(order=4)
    )
    assert traj.result == lj.RESULTS.successful
    q, qdot = np.asarray(traj.q), np.asarray(traj.qdot)
    v = np.asarray(jax.jit(lambda a, b: jax.vmap(racer.velocities_from_qdot)(a, b))(q, qdot))
    phis, rates = q[:, 3], v[:, 0]
    x, w = np.polynomial.legendre.leggauss(20)  # Phi(phi) = exp(-int_0^phi a), per node

    # the coefficients at every angle this test reads, in one call (one compiled program): the
    # random states, a grid on [-pi, pi], the quadrature points and the nodes
    parts = (phi, np.linspace(-np.pi, np.pi, 721), (0.5 * phis[:, None] * (x[None, :] + 1)).ravel(), phis)
    a_all, beta_all = (
        np.split(np.asarray(c), np.cumsum([p.size for p in parts])[:-1])
        for c in coefficients(np.concatenate(parts))
    )
    momenta = np.asarray(
        P(np.concatenate([phi, phis]), np.concatenate([phidot, rates]), np.concatenate([s, v[:, 1]]))
    )
    rebuilt = a_all[0] * phidot * momenta[:64] + beta_all[0] * phidot**2
    np.testing.assert_allclose(Pd(phi, phidot, s, 0 * f), rebuilt, rtol=1e-10, atol=1e-12)
    assert float(np.min(beta_all[1])) > 0.005

    Phi = np.exp(-0.5 * phis * (a_all[2].reshape(-1, x.size) @ w))
    weighted = Phi * momenta[64:]
    assert np.all(np.diff(weighted) > -1e-9), np.diff(weighted).min()
    beta_phi = beta_all[3] * Phi * rates**2
    gain = float(np.sum(0.5 * (beta_phi[1:] + beta_phi[:-1])) * T / n)
    assert gain > 0.01
    np.testing.assert_allclose(weighted[-1] - weighted[0], gain, rtol=1e-4)
