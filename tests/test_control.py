"""Discrete optimal control: the discrete-time dynamics, feedback policies, the interior-point
solver (convergence, hard constraints, replay accuracy, sensitivities, vmap), the optax loop on
the penalty form, and the cost terms."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from helpers import compiled_programs, eager_operations

import ldap_jax as lj
from ldap_jax import control as lc

# ----------------------------------------------------------------------- discrete-time dynamics
DISCRETE_CASES = [
    ("car", lambda: lj.RDP()),
    ("snakeboard", lambda: lj.RDP(order=6)),
    ("snakeboard", lambda: lj.RDP(solver="newton")),
    ("car", lambda: lj.RK4()),
]


@pytest.mark.parametrize("name,make", DISCRETE_CASES, ids=["car-rdp", "sb-rdp6", "sb-newton", "car-rk4"])
def test_discrete_dynamics_reproduce_simulate_and_differentiate(name, make):
    """x_{k+1} = f(x_k, u_k, u_{k+1}) rolled out equals simulate with the same node controls
    (lj.Sampled) to round-off, and df/dx, df/du match central differences."""
    system = {"car": lj.Car(), "snakeboard": lj.Snakeboard()}[name]
    integrator = make()
    n, t_final = 30, 3.0
    us = 0.1 * jax.random.normal(jax.random.PRNGKey(1), (n + 1, 2))
    q0 = jnp.array([0.1, -0.2, 0.3, 0.0, 0.2])
    v0 = jnp.array([2.0]) if name == "car" else jnp.array([0.5, 0.1, 0.3])
    qdot0 = system.qdot_from_velocities(q0, v0, us[0])
    traj = lj.simulate(
        system, q0, qdot0, lj.Sampled(us, t_final), t_final=t_final, n_steps=n, integrator=integrator
    )
    dyn = lj.discretize(system, integrator, h=t_final / n)
    # compiled, not op by op
    xs = eqx.filter_jit(dyn.rollout)(eqx.filter_jit(dyn.init)(q0, qdot0, us[0]), us)
    nodes = eqx.filter_jit(lambda d, x, u: jax.vmap(d.node)(x, u))(dyn, xs, us)
    np.testing.assert_allclose(nodes[0], traj.q, atol=1e-12)
    np.testing.assert_allclose(nodes[1], traj.qdot, atol=1e-12)
    # host copies: the differences below are NumPy arithmetic (op by op, JAX compiles each)
    x, u0, u1 = np.asarray(xs)[5], np.asarray(us)[5], np.asarray(us)[6]
    jx, ju = jax.jit(lambda a, b, c: jax.jacfwd(dyn.step, argnums=(0, 2))(a, b, c))(x, u0, u1)
    jx, ju = np.asarray(jx), np.asarray(ju)
    step = jax.jit(lambda a, b, c: dyn.step(a, b, c))  # one program for the differences (eagerly: op by op)
    eps = 1e-6
    for i in range(x.size):
        e = np.zeros_like(x)
        e[i] = eps
        fd = (np.asarray(step(x + e, u0, u1)) - np.asarray(step(x - e, u0, u1))) / (2 * eps)
        np.testing.assert_allclose(jx[:, i], fd, rtol=1e-6, atol=1e-8)
    for i in range(u1.size):
        e = np.zeros_like(u1)
        e[i] = eps
        fd = (np.asarray(step(x, u0, u1 + e)) - np.asarray(step(x, u0, u1 - e))) / (2 * eps)
        np.testing.assert_allclose(ju[:, i], fd, rtol=1e-6, atol=1e-8)


def test_discrete_dynamics_called_eagerly_compile_once_and_inline_under_jit():
    """Called on values, init/step/observe/node each run as one compiled program (not one per
    operation), and new values (controls, k) compile nothing more; under jax.grad on values the
    step is one program too; inside a jit the step is traced inline: the caller's jaxpr is the
    one the undecorated step gives, with no added call boundary."""
    car = lj.Car()
    dyn = lj.discretize(car, lj.RDP(order=4), h=0.07)
    u0, u1 = np.array([0.05, 0.2]), np.array([0.05, 0.3])
    q0 = np.array([0.1, -0.2, 0.3, 0.0, 0.2])
    qdot0 = car.qdot_from_velocities(q0, np.array([1.0]), u0)
    lj.compiler_options()  # the library's once-per-process check of XLA's options, done
    with compiled_programs() as first:
        x0 = dyn.init(q0, qdot0, u0)
        x1 = dyn.step(x0, u0, u1)
        obs = dyn.observe(x1, u1)
        node = dyn.node(x1, u1)
        g = jax.grad(lambda x: jnp.sum(dyn.step(x, u0, u1)))(x0)
    # one program per method, two for the gradient of the step (linearised, transposed), two
    # for this test's own sum under grad, which runs op by op, and init's check of qdot0 on the
    # constraints (simulate's program); op by op the methods compiled 90
    assert len(first) <= 9, first
    with compiled_programs() as again:
        x2 = dyn.step(x1, u1, u1 + 0.1, 1)
        dyn.step(x2, u1 + 0.1, u0, k=2)
        dyn.observe(x2, u0)
        jax.grad(lambda x: jnp.sum(dyn.step(x, u1, u0)))(x1)
    assert again == []
    # the same values as the whole computation compiled by the caller
    ref = jax.jit(
        lambda a, b, c, d: (
            (x := dyn.init(a, b, c)),
            (y := dyn.step(x, c, d)),
            dyn.observe(y, d).q,
            dyn.node(y, d)[1],
            jax.grad(lambda z: jnp.sum(dyn.step(z, c, d)))(x),
        )
    )(q0, qdot0, u0, u1)
    for a, b in zip((x0, x1, obs.q, node[1], g), ref):
        np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-15)
    # under the caller's jit: inline
    inline = jax.make_jaxpr(lambda x: dyn.step(x, u0, u1))(x0)
    undecorated = jax.make_jaxpr(lambda x: type(dyn).step.__wrapped__(dyn, x, u0, u1))(x0)
    assert [e.primitive.name for e in inline.jaxpr.eqns] == [e.primitive.name for e in undecorated.jaxpr.eqns]


def test_policy_with_zero_feedback_equals_open_loop():
    """A linear feedback policy with zero gain reproduces its feedforward applied open-loop; with a
    gain it changes the run and still works under vmap; a plain function f(t, q, qdot) is a policy."""
    car = lj.Car()
    q0, qdot0, ctl = car.sample_maneuver(jax.random.PRNGKey(2))
    kw = dict(t_final=4.0, n_steps=80)
    open_loop = lj.simulate(car, q0, qdot0, ctl, **kw)
    zero = lj.LinearPolicy(ctl, jnp.zeros((2, 10)))
    closed = lj.simulate(car, q0, qdot0, zero, **kw)
    np.testing.assert_allclose(closed.q, open_loop.q, atol=1e-13)
    np.testing.assert_allclose(closed.qdot, open_loop.qdot, atol=1e-13)
    gain = np.zeros((2, 10))
    gain[0, 5] = -0.05  # damp the wheel rate around zero
    damped = lj.simulate(car, q0, qdot0, lj.LinearPolicy(ctl, jnp.asarray(gain, gain.dtype)), **kw)
    assert float(np.max(np.abs(np.asarray(damped.q) - np.asarray(open_loop.q)))) > 1e-3

    def law(t, q, qd):
        return ctl(t)

    by_policy = lj.simulate(car, q0, qdot0, lj.Policy(law, 2), **kw)
    np.testing.assert_allclose(by_policy.q, open_loop.q, atol=1e-13)
    # a plain function is the same feedback law (lj.Policy(law, n_controls)): the same program
    np.testing.assert_array_equal(lj.simulate(car, q0, qdot0, law, **kw).q, by_policy.q)


def test_linear_policy_about_its_own_run_reproduces_it():
    """A LinearPolicy whose reference is the open-loop run itself (its nodes) gets no feedback on
    that run, for a composed step that samples the policy inside the step (RDP order 4): the run
    equals the open loop to 1e-11 with a gain of order 1 on every state. The feedback compares
    the state of the step's start with the reference there; compared at the later sample times
    of the step, it had pushed the run 1e-3 off its reference."""
    car = lj.Car()
    q0, qdot0, ctl = car.sample_maneuver(jax.random.PRNGKey(2))
    kw = dict(t_final=4.0, n_steps=80, integrator=lj.RDP(order=4))
    open_loop = lj.simulate(car, q0, qdot0, ctl, **kw)
    reference = jnp.concatenate([open_loop.q, open_loop.qdot], axis=1)
    gain = 0.5 * jnp.ones((2, 10))
    policy = lj.LinearPolicy(ctl, gain, reference, open_loop.t)
    closed = lj.simulate(car, q0, qdot0, policy, **kw)
    np.testing.assert_allclose(closed.q, open_loop.q, atol=1e-11)
    np.testing.assert_allclose(closed.qdot, open_loop.qdot, atol=1e-11)


# ------------------------------------------------------------------------------------- the solver
@pytest.fixture(scope="module")
def car_solutions():
    """parallel_park and u_turn with RDP(order=4) on the same grid (N = 120: one compilation)."""
    out = {}
    for name, make in (("parallel_park", lc.parallel_park), ("u_turn", lc.u_turn)):
        task = make(n_steps=120)  # the default model: lj.RDP(order=4)
        assert task.integrator == lj.RDP(order=4)
        out[name] = (task, lc.solve(task))
    return out


@pytest.mark.parametrize("name", ["parallel_park", "u_turn"])
def test_solve_meets_the_constraints_on_the_reference(name, car_solutions):
    """From the default guess: converged, the model's constraints met to 1e-8, and on the
    high-accuracy reference the goal reached to 1e-6 m and 1e-6 rad, at rest to 1e-6, with the
    bounds held at the nodes to 1e-8; the solution's model-error estimate agrees with the replay."""
    task, sol = car_solutions[name]
    assert bool(sol.converged), lc.SOLVER_RESULTS[sol.result]
    assert float(sol.max_violation) < 1e-8
    rp = lc.replay(task, sol.params)
    assert rp["reference_result"] == lj.RESULTS.successful
    assert rp["final_position_error"] < 1e-6 and rp["final_heading_error"] < 1e-6, rp
    assert rp["final_speed_ref"] < 1e-6
    assert rp["max_bound_violation"] < 1e-8
    # between the nodes a state on a bound leaves it by O(h^2): seen there, not at the nodes
    assert 1e-7 < rp["max_bound_violation_between"] < 1e-3, rp["max_bound_violation_between"]
    # the solve's own estimate of the model's error (h against h/2) is (1 - 2^-4) times the model's
    # error measured on the reference, for an order-4 method in its asymptotic range
    measured = np.array([rp["model_position_error"], rp["model_heading_error"]])
    np.testing.assert_allclose(np.asarray(sol.model_error), (15 / 16) * measured, rtol=0.05)
    if name == "u_turn":  # a bound is active at the optimum (the lane |y| <= 1/2 or |sigma| <= 1)
        q_ref = np.asarray(rp["q_ref"])
        assert max(np.max(np.abs(q_ref[:, 1])) / 0.5, np.max(np.abs(q_ref[:, 4])) / 1.0) > 0.999


def test_tasks_that_differ_only_outside_the_solver_share_its_program(car_solutions):
    """A task's name, penalty weights, memory policy and guess settings are static but unread by
    the solver: changing them traces no new interior-point program and gives the same solution
    (the fixture's parallel_park and u_turn share one program this way)."""
    task, sol = car_solutions["parallel_park"]
    other = dataclasses.replace(
        task,
        name="renamed",
        objective_weight=jnp.asarray(1.0),
        guess=lc.Guess(amplitude=0.05),
        checkpoint=True,
    )
    lc.solve(task, task.init())  # traced by the fixture, unless conftest emptied JAX's caches since
    with compiled_programs("trace") as names:
        again = lc.solve(other, task.init())
    assert "_run" not in names, names
    np.testing.assert_array_equal(again.params, sol.params)
    assert int(again.iterations) == int(sol.iterations)


def test_failed_line_search_far_from_feasibility_restarts_and_converges(car_solutions):
    """A U-turn goal (one of 16 random goals around the task's) on which the iterate jams against
    the lane bound and the line search fails far from feasibility (the release before the restart
    stopped there, violation 0.49): the restart pushes the point inside the bounds, resets the
    multipliers, and the solve converges to a solution that holds on the reference."""
    task, _ = car_solutions["u_turn"]
    task = task.with_options(goal=jnp.array([-0.1202, 0.2345, 2.8586]))
    sol = lc.solve(task)
    assert int(sol.resets) >= 1
    assert bool(sol.converged), lc.SOLVER_RESULTS[sol.result]
    assert float(sol.max_violation) < 1e-8
    rp = lc.replay(task, sol.params)
    assert rp["final_position_error"] < 1e-6 and rp["final_heading_error"] < 1e-6, rp
    assert rp["max_bound_violation"] < 1e-8


def test_solve_from_rest_restarts_with_perturbed_controls_and_converges(car_solutions):
    """From zero controls (the car at rest throughout) the linearised car has no authority over
    its lateral position and heading: the first Newton step is zero and its line search fails. The
    first restart (the same point pushed inside the bounds) fails the same way; the second perturbs
    the controls within their bounds, and both car tasks converge to solutions that hold on the
    reference (the previous release stopped on both after five restarts)."""
    for name in ("parallel_park", "u_turn"):
        task, _ = car_solutions[name]
        sol = lc.solve(task, jnp.zeros((task.n_steps + 1, 2)))
        assert int(sol.resets) >= 2, name
        assert bool(sol.converged), (name, lc.SOLVER_RESULTS[sol.result])
        assert float(sol.max_violation) < 1e-8
        rp = lc.replay(task, sol.params)
        assert rp["final_position_error"] < 1e-6 and rp["final_heading_error"] < 1e-6, (name, rp)
        assert rp["final_speed_ref"] < 1e-6 and rp["max_bound_violation"] < 1e-8, (name, rp)


def test_solve_cost_is_the_effort_and_far_below_the_guess(car_solutions):
    """The reported cost is the task's effort term (without its penalty-form weight): the exact
    integral of the squared scaled controls, piecewise linear between the nodes,
    ``sum_k h/3 (U_k^2 + U_k U_{k+1} + U_{k+1}^2)``, which a fine trapezoid sum of the interpolated
    controls reproduces to 1e-6; the rectangle sum over-counts it. The solution's penalty-form
    loss is far below the default guess's."""
    task, sol = car_solutions["parallel_park"]
    assert float(task.value(sol.params)) < 1e-3 * float(task.value(task.init()))
    assert float(sol.cost) == pytest.approx(
        float(task.terms(task.rollout(sol.params), sol.params)["effort"]) / 1e-5, rel=1e-9
    )
    U = np.asarray(sol.params)  # scaled node controls
    t = np.linspace(0.0, 1.0, 200 * task.n_steps + 1)
    fine = np.stack(
        [np.interp(t, np.linspace(0, 1, task.n_steps + 1), U[:, i]) for i in range(U.shape[1])], 1
    )
    trapezoid = float(task.t_final) * np.sum(0.5 * (fine[1:] ** 2 + fine[:-1] ** 2)) / (t.size - 1)
    assert float(sol.cost) == pytest.approx(trapezoid, rel=1e-6)
    rectangles = float(task.h) * np.sum(U**2)
    assert rectangles > float(sol.cost) * (1 + 1e-3)


def test_passive_entries_skip_their_derivatives_without_changing_them():
    """A gait's stage form carries a constant copy of its start (passive entries: identity
    dynamics, read only by the return conditions). The solver skips their Jacobians and Hessians;
    the derivatives it assembles equal those of the same functions with nothing declared passive."""
    from ldap_jax.control import _kkt, _solve
    from ldap_jax.control._stage_form import to_variables

    # the order-2 step: the passive entries are the same; its second derivatives compile in 2/3
    # of the order-4 composition's time
    task = lc.drive_gait(n_steps=8, integrator=lj.RDP())
    _, fns, _, _, lay = _solve.setup(task, "exact")
    assert fns.n_passive > 0
    p, v = to_variables(lay, task.init())

    @jax.jit  # the point: one program (op by op, each operation compiled alone)
    def point(p, v):
        chi = _kkt.rollout(fns, p, v)
        chi = chi + 1e-3 * jax.random.normal(jax.random.PRNGKey(3), chi.shape)
        y = jax.random.normal(jax.random.PRNGKey(4), chi.shape)
        nu = jax.random.normal(jax.random.PRNGKey(5), (jax.eval_shape(fns.terminal, chi[-1]).shape[0],))
        return chi, y, nu

    chi, y, nu = point(p, v)
    full = fns._replace(n_passive=0)
    a = jax.jit(lambda: _kkt.derivatives(fns, p, chi, v, y, nu, jnp.inf))()
    b = jax.jit(lambda: _kkt.derivatives(full, p, chi, v, y, nu, jnp.inf))()
    for name, x, z in zip(a._fields, a, b):
        np.testing.assert_allclose(np.asarray(x), np.asarray(z), rtol=1e-12, atol=1e-12, err_msg=name)


def test_base_curvature_reaches_the_exact_hessian_solution(car_solutions):
    """hessian="base" (the default: the order-2 step's second derivatives in the Hessian of an
    order-4 composition) and hessian="exact" reach the same optimum of the composition's problem:
    the Jacobians and constraints are exact in both, only the Newton matrix differs. Iterated to
    tol=1e-11, below the default, both converge (the solves' iterative refinement: without it the
    line search failed at KKT errors of 5e-10 to 2e-8, depending on the code generation) and end at
    the same point to 1e-10 (at the default tol they agree to a few 1e-6, as the solutions of a KKT
    error of 1e-9 may)."""
    task, default = car_solutions["parallel_park"]
    assert bool(default.converged)
    base = lc.solve(task, tol=1e-11)
    exact = lc.solve(task, tol=1e-11, hessian="exact")
    for sol in (base, exact):
        assert bool(sol.converged), lc.SOLVER_RESULTS[sol.result]
        assert float(sol.kkt_error) < 1e-11 and float(sol.max_violation) < 1e-11
    np.testing.assert_allclose(base.params, exact.params, rtol=0, atol=1e-10)
    np.testing.assert_allclose(base.cost, exact.cost, rtol=1e-12)
    np.testing.assert_allclose(default.params, exact.params, rtol=0, atol=1e-5)
    assert lc.curvature_integrator(task.integrator) == lj.RDP()
    assert lc.curvature_integrator(lj.RK4()) == lj.RK4()


def _random_qp(seed, K=12, n=4, m=2, p=2, s=3, stiff=0.0, near_identity=False):
    """A random stage-form QP (see ldap_jax.control._riccati): free initial parameters (s),
    stages j = 1 .. K-1 with positive definite Hessians; ``stiff`` is added to about a third of
    their diagonal entries (the barrier terms of active bounds); ``near_identity``: state
    Jacobians ``I + O(0.1)``, as for a short step. Returns ``(QPMatrices, QPVector)``."""
    from ldap_jax.control._riccati import QPMatrices, QPVector

    rng = np.random.default_rng(seed)
    W = rng.normal(size=(K - 1, n + m, n + m))
    W = np.einsum("jab,jcb->jac", W, W) + np.eye(n + m)
    W += np.einsum("ja,ab->jab", np.where(rng.random((K - 1, n + m)) < 0.3, stiff, 0.0), np.eye(n + m))
    QK = rng.normal(size=(n, n))
    Wp = rng.normal(size=(s, s))
    Z = rng.normal(size=(K - 1, n, n + m))
    G = rng.normal(size=(n, s))
    if near_identity:  # the linearised flow of a short step (the start: as a step's controls)
        Z = np.concatenate([np.eye(n) + 0.1 * Z[:, :, :n], 0.3 * Z[:, :, n:]], axis=2)
        G = 0.3 * G
    mat = QPMatrices(
        Wp=Wp @ Wp.T + np.eye(s), G=G, W=W, Z=Z, QK=QK @ QK.T + np.eye(n), C=rng.normal(size=(p, n))
    )
    rhs = QPVector(
        wp=rng.normal(size=s),
        e0=rng.normal(size=n),
        w=rng.normal(size=(K - 1, n + m)),
        e=rng.normal(size=(K - 1, n)),
        qK=rng.normal(size=n),
        c=rng.normal(size=p),
    )
    return mat, rhs


def _dense_qp_solution(mat, rhs):
    """The QP's KKT system assembled densely: unknowns (dp, dx_1..dx_K, dv_1..dv_{K-1})."""
    K1, n, nm = mat.Z.shape
    m, s, p = nm - n, mat.G.shape[1], mat.C.shape[0]
    nx, nv = (K1 + 1) * n, K1 * m
    N = s + nx + nv
    H, g = np.zeros((N, N)), np.zeros(N)
    A, b = np.zeros((nx + p, N)), np.zeros(nx + p)
    X = lambda j: list(range(s + (j - 1) * n, s + j * n))  # noqa: E731  (dx_j, j = 1..K)
    V = lambda j: list(range(s + nx + (j - 1) * m, s + nx + j * m))  # noqa: E731  (dv_j)
    H[:s, :s], g[:s] = mat.Wp, rhs.wp
    A[0:n, X(1)] = np.eye(n)  # dx_1 - G dp = e_0
    A[0:n, :s] = -mat.G
    b[0:n] = rhs.e0
    for j in range(1, K1 + 1):
        idx = X(j) + V(j)
        H[np.ix_(idx, idx)] += mat.W[j - 1]
        g[idx] += rhs.w[j - 1]
        rows = list(range(j * n, (j + 1) * n))  # dx_{j+1} - Z_j z_j = e_j
        A[np.ix_(rows, X(j + 1))] = np.eye(n)
        A[np.ix_(rows, idx)] -= mat.Z[j - 1]
        b[rows] = rhs.e[j - 1]
    H[np.ix_(X(K1 + 1), X(K1 + 1))] += mat.QK
    g[X(K1 + 1)] += rhs.qK
    A[nx:, X(K1 + 1)] = mat.C
    b[nx:] = -rhs.c
    kkt = np.block([[H, A.T], [A, np.zeros((nx + p, nx + p))]])
    z = np.linalg.solve(kkt, np.concatenate([-g, b]))
    return z[:s], z[s : s + nx].reshape(K1 + 1, n), z[s + nx : N].reshape(K1, m)


def test_riccati_solves_the_qp_and_refinement_reduces_the_residual():
    """The Riccati recursion's step (free initial parameters included) equals a dense solve of the
    QP's full KKT system; on a system with 1e10 barrier terms, each step of iterative refinement
    reduces the stationarity residual at least tenfold, and refinement stops once the residual is
    below atol."""
    from ldap_jax.control import _riccati

    # compiled (one program per shape and refinement count), not op by op
    riccati_factor = jax.jit(_riccati.riccati_factor)
    riccati_apply = jax.jit(_riccati.riccati_apply, static_argnums=2)
    kkt_residual = jax.jit(_riccati.kkt_residual)
    _apply = jax.jit(_riccati._apply)
    size = lambda r: max(float(np.max(np.abs(np.asarray(x)), initial=0.0)) for x in r)  # noqa: E731

    mat, rhs = _random_qp(0)
    f = riccati_factor(mat, np.zeros(()))
    assert bool(f.positive)
    sol = riccati_apply(f, rhs)
    dp, dx, dv = _dense_qp_solution(mat, rhs)
    np.testing.assert_allclose(np.asarray(sol.dp), dp, rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.asarray(sol.dx), dx, rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.asarray(sol.dv), dv, rtol=0, atol=1e-9)
    assert size(kkt_residual(f, rhs, sol)) < 1e-10

    # ill-conditioned (1e10 barrier terms): refinement
    def residual(f, rhs, k, atol=0.0):
        return size(kkt_residual(f, rhs, riccati_apply(f, rhs, k, atol)))

    tenfold = 0
    for seed in range(8):
        mat, rhs = _random_qp(seed, K=30, stiff=1e10, near_identity=True)
        f = riccati_factor(mat, np.zeros(()))
        res = [residual(f, rhs, k) for k in range(3)]
        assert res[0] > 1e-3 and res[1] < res[0] / 2 and res[2] <= res[1], (seed, res)
        tenfold += res[1] < res[0] / 10
        assert residual(f, rhs, 2, atol=res[1] * 1.01) == res[1]  # stops below atol
    # the worst-conditioned draw (seed 1) gains 3x per step; the others at least tenfold
    assert tenfold >= 6, tenfold
    # factors of another matrix (the residual's stage Hessians 10x those factored), on which
    # unguarded refinement diverges: a correction that increases the residual is not taken
    mat, rhs = _random_qp(0)
    f = riccati_factor(mat, np.zeros(()))
    f = f._replace(mat=mat._replace(W=10 * mat.W, QK=10 * mat.QK))
    s = _apply(f, rhs)
    for _ in range(2):  # unguarded
        s = jax.tree_util.tree_map(np.add, s, _apply(f, kkt_residual(f, rhs, s)))
    unguarded = size(kkt_residual(f, rhs, s))
    res = [residual(f, rhs, k) for k in range(3)]
    assert res[2] <= res[1] <= res[0] < unguarded, (res, unguarded)


def test_bound_push_moves_points_inside_one_and_two_sided_bounds():
    """The push that places the initial guess (and a restarted iterate) strictly inside the bounds:
    one-sided bounds (lower only, upper only) are honoured as well as two-sided ones, a point well
    inside is left alone, and unbounded entries are untouched."""
    from ldap_jax.control._ipm import pushed as _pushed

    inf = np.inf
    lo = jnp.array([0.0, -inf, -1.0, -1.0, -inf, 100.0])
    hi = jnp.array([inf, 2.0, 1.0, 1.0, inf, inf])
    x = jnp.array([-3.0, 5.0, 1.0, 0.2, 7.0, 100.0])
    out = np.asarray(_pushed(x, lo, hi, 1e-2))
    np.testing.assert_allclose(out, [1e-2, 2.0 - 2e-2, 1.0 - 1e-2, 0.2, 7.0, 101.0], rtol=0, atol=1e-15)


def test_ipm_solves_a_stage_form_without_a_perturbation():
    """``OCPFunctions.perturbation=None`` (restarts never perturb) is a valid stage form: a double
    integrator steered to a goal with least effort, under a bound on the speed that the
    least-effort motion would cross, converges with the dynamics, the goal and the bound met.
    The first control is the free initial parameter ``p``: ``chi_1 = F_0(p)``."""
    from ldap_jax.control._ipm import SOLVER_RESULTS, IPMOptions, ipm_solve
    from ldap_jax.control._kkt import OCPFunctions, constraints

    h, K = 0.1, 20
    A = jnp.array([[1.0, h, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]])  # chi = (position, speed, u)
    B = jnp.array([0.5 * h**2, h, 1.0])

    fns = OCPFunctions(
        first=lambda p: B * p[0],
        dynamics=lambda chi, v, k: A @ chi + B * v[0],
        stage_cost=lambda chi, v: h * chi[2] ** 2,
        terminal_cost=lambda chi: h * chi[2] ** 2,
        terminal=lambda chi: chi[:2] - jnp.array([1.0, 0.0]),
    )
    assert fns.perturbation is None
    lo = jnp.array([-jnp.inf, -0.6, -jnp.inf])
    hi = jnp.array([jnp.inf, 0.6, jnp.inf])
    p0, v0, chi0 = np.zeros(1), np.zeros((K - 1, 1)), np.zeros((K, 3))
    st = jax.jit(lambda p, c, v: ipm_solve(fns, p, c, v, lo, hi, IPMOptions(tol=1e-9)))(p0, chi0, v0)
    assert st.result == SOLVER_RESULTS.successful, int(st.iteration)
    defects, cK = (np.asarray(x) for x in constraints(fns, st.p, st.chi, st.v))
    assert float(np.max(np.abs(defects))) < 1e-10 and float(np.max(np.abs(cK))) < 1e-10
    # the least-effort profile would peak at 0.75 m/s: the bound is active and held
    assert 0.6 - 1e-6 < float(np.max(np.abs(np.asarray(st.chi)[:, 1]))) < 0.6


def test_solve_reach_snakeboard():
    """From the default guess and from rest (zero torques: the linearised snakeboard has no
    authority over its position, so this needs the perturbed restart), converged to solutions that
    reach the goal at rest on the reference, with the torque and steering bounds held."""
    task = lc.reach(integrator=lj.RDP(order=4))
    for guess in (None, jnp.zeros((task.n_steps + 1, 2))):
        sol = lc.solve(task, guess)
        assert bool(sol.converged), lc.SOLVER_RESULTS[sol.result]
        assert guess is None or int(sol.resets) >= 2
        rp = lc.replay(task, sol.params)
        assert rp["final_position_error"] < 1e-6 and rp["final_heading_error"] < 1e-6, rp
        assert rp["final_speed_ref"] < 1e-6 and rp["max_bound_violation"] < 1e-8
        c = np.asarray(jax.vmap(task.controls(sol.params))(rp["t"]))
        assert np.max(np.abs(c)) <= 0.1 + 1e-12


#: The tests of the small parallel_park (N = 40, RDP order 2) share its compiled programs with
#: each other and with tests/test_export.py (the same task): one worker runs them all.
PARK40_GROUP = pytest.mark.xdist_group("parallel_park_40")


@pytest.fixture(scope="module")
def small_park():
    task = lc.parallel_park(integrator=lj.RDP(), n_steps=40)
    return task, task.init()


@PARK40_GROUP
def test_sensitivities_match_finite_differences_of_resolves(small_park):
    """d(optimal effort)/d(goal, mass) and d(optimal controls)/d(goal) by the implicit function
    theorem, in forward and reverse mode, against central differences of re-solves (rtol 1e-4),
    without compiling the interior-point run again."""
    task, p0 = small_park

    def optimum(goal, m):
        sol = lc.solve(task.with_options(goal=goal, system=lj.Car(m=m)), p0, tol=1e-11)
        return sol.cost, sol.params[10]

    g0, m0 = task.goal, jnp.asarray(1.0)
    optimum(g0, m0)
    with compiled_programs() as names:
        dcost = jax.grad(lambda g, m: optimum(g, m)[0], argnums=(0, 1))(g0, m0)
        dparams = jax.jacfwd(lambda g: optimum(g, m0)[1])(g0)
    # the interior-point run is the program the solve above compiled: derivatives compile only
    # the implicit-function-theorem step (the traced finish under jacfwd; under grad, with the
    # persistent cache on, its exported Jacobian), unless a test of this worker compiled it first
    assert not {"jit(_run)", "jit(_solve)", "jit(exported_run)"} & set(names), names
    eps = 1e-4
    dcost_goal, dparams = np.asarray(dcost[0]), np.asarray(dparams)
    for i in range(3):
        e = np.zeros(3)
        e[i] = eps
        (cp, pp), (cm, pm) = optimum(g0 + e, m0), optimum(g0 - e, m0)
        np.testing.assert_allclose(dcost_goal[i], (float(cp) - float(cm)) / (2 * eps), rtol=1e-4)
        fd = (np.asarray(pp) - np.asarray(pm)) / (2 * eps)
        np.testing.assert_allclose(dparams[:, i], fd, rtol=1e-4, atol=1e-6)
    cp, cm = optimum(g0, m0 + eps)[0], optimum(g0, m0 - eps)[0]
    np.testing.assert_allclose(dcost[1], (float(cp) - float(cm)) / (2 * eps), rtol=1e-4)


@PARK40_GROUP
def test_sensitivity_to_an_active_bound_at_tight_tolerances(small_park):
    """d(optimal effort)/d(steering bound) with the bound |sigma| <= 0.3 active, against central
    differences of re-solves, at tolerances 1e-8 and 1e-12 (rtol 1e-7). The bound multipliers'
    complementarity at the returned point, not the barrier parameter, weights the right-hand side:
    with the barrier parameter the derivative drifted as the tolerance tightened (1e-8 at
    tol=1e-8, 2.7e-6 at 1e-10, 3e-4 at 1e-12)."""
    task, p0 = small_park
    b = task.bounds

    def solve(s, tol, start=p0):
        bounds = lc.Bounds(b.q_lower.at[4].set(-s), b.q_upper.at[4].set(s), b.u_lower, b.u_upper)
        return lc.solve(task.with_options(bounds=bounds), start, tol=tol)

    s0, eps = 0.3, 1e-5
    sol = solve(s0, 1e-12)
    assert bool(sol.converged)
    # a previous Solution as the guess counts as its params: the same optimum at once
    again = solve(s0, 1e-12, start=sol)
    assert bool(again.converged) and int(again.iterations) < int(sol.iterations)
    np.testing.assert_allclose(np.asarray(again.params), np.asarray(sol.params), atol=1e-9)
    q0, qdot0 = task.initial_state(sol.params)
    traj = lj.simulate(
        task.system,
        q0,
        qdot0,
        task.controls(sol.params),
        t_final=task.t_final,
        n_steps=task.n_steps,
        integrator=task.integrator,
        diagnostics=False,
    )
    assert np.max(np.abs(np.asarray(traj.q)[:, 4])) > s0 - 1e-6  # the bound is active
    fd = (float(solve(s0 + eps, 1e-12).cost) - float(solve(s0 - eps, 1e-12).cost)) / (2 * eps)
    for tol in (1e-8, 1e-12):
        g = float(jax.grad(lambda s, tol=tol: solve(s, tol).cost)(jnp.asarray(s0)))
        assert abs(g - fd) <= 1e-7 * abs(fd), (tol, g, fd)


#: the car's masses of the members of :func:`vmapped_park` (members 3 and 4 invalid)
PARK_MASSES = np.array([1.0, 1.0, 1.0, -1.0, 0.0, 1.0])


@pytest.fixture(scope="module")
def vmapped_park(small_park):
    """One vmapped solve of the small parallel_park over goals and the car's mass (traced: no
    construction-time check), read by two tests (one compiled program instead of a vmap over the
    goals and another over the masses): members 0-2 are three goals at the default mass, members
    3 and 4 the first goal at the invalid masses -1 and 0, member 5 a goal with a NaN ``x``."""
    task, p0 = small_park
    offsets = np.array(
        [[0.0, 0.0, 0.0], [0.05, 0.01, 0.0], [-0.05, 0.0, 0.02], [0.0] * 3, [0.0] * 3, [np.nan, 0, 0]]
    )
    goals = task.goal[None] + jax.device_put(offsets)
    masses = jax.device_put(PARK_MASSES)
    batch = jax.vmap(lambda g, m: lc.solve(task.with_options(goal=g, system=lj.Car(m=m)), p0))(goals, masses)
    return goals, batch


@PARK40_GROUP
def test_solve_vmaps_over_goals(small_park, vmapped_park):
    task, p0 = small_park
    goals, batch = vmapped_park
    params, converged, iterations = (np.asarray(x) for x in (batch.params, batch.converged, batch.iterations))
    for i in range(3):
        one = lc.solve(task.with_options(goal=goals[i]), p0)
        np.testing.assert_allclose(params[i], one.params, rtol=1e-7, atol=1e-9)
        assert bool(converged[i]) and int(iterations[i]) == int(one.iterations)


def _loops(jaxpr, inside=()):
    """``(primitive, enclosing primitives)`` of every loop in a jaxpr, nested ones included."""
    out = []
    for eqn in jaxpr.eqns:
        name = eqn.primitive.name
        if name in ("while", "scan"):
            out.append((name, inside))
        for v in eqn.params.values():
            for sub in v if isinstance(v, (tuple, list)) else (v,):
                inner = getattr(sub, "jaxpr", sub)
                if hasattr(inner, "eqns"):
                    out += _loops(inner, (*inside, name))
    return out


@PARK40_GROUP
def test_vmapped_solve_runs_its_members_one_after_another(small_park):
    """Under ``jax.vmap`` the interior-point loop of each member runs inside a ``lax.map`` (a scan
    over the members), not as one batched while loop that runs every member for the slowest one's
    iterations (traced only)."""
    task, p0 = small_park
    goals = task.goal[None] + jnp.array([[0.0, 0.0, 0.0], [0.05, 0.01, 0.0]])
    jaxpr = jax.make_jaxpr(jax.vmap(lambda g: lc.solve(task.with_options(goal=g), p0).iterations))(goals)
    whiles = [inside for name, inside in _loops(jaxpr.jaxpr) if name == "while"]
    assert whiles and all("scan" in inside for inside in whiles), whiles


@PARK40_GROUP
def test_curvature_tol_is_traced_and_reaches_the_same_optimum(small_park):
    """The dynamics' curvature from the first iteration (curvature_tol=inf) instead of below a
    violation of 0.1: the same optimum of parallel_park, and no new interior-point program."""
    task, p0 = small_park
    default = lc.solve(task, p0, tol=1e-10)
    with compiled_programs() as names:
        early = lc.solve(task, p0, tol=1e-10, curvature_tol=jnp.inf)
    assert not {"jit(_run)", "jit(_solve)"} & set(names), names
    assert bool(default.converged) and bool(early.converged)
    assert int(early.iterations) != int(default.iterations)  # the switch did act (19 and 65)
    # two points within a KKT error of 1e-10 of the optimum: their costs agree to that order
    np.testing.assert_allclose(early.cost, default.cost, rtol=1e-11)
    np.testing.assert_allclose(early.params, default.params, rtol=0, atol=1e-8)


def test_solve_bad_inputs_are_clear():
    task = lc.parallel_park(n_steps=40)
    with pytest.raises(ValueError, match="'tol'"):
        lc.solve(task, tol=0.0)
    with pytest.raises(ValueError, match="'curvature_tol'"):
        lc.solve(task, curvature_tol=0.0)
    with pytest.raises(TypeError, match="'curvature_tol'"):
        lc.solve(task, curvature_tol="inf")
    with pytest.raises(ValueError, match="'max_iterations'"):
        lc.solve(task, max_iterations=0)
    with pytest.raises(ValueError, match="'hessian'"):
        lc.solve(task, hessian="newton")
    with pytest.raises(ValueError, match="'params0'"):
        lc.solve(task, jnp.zeros((40, 2)))
    with pytest.raises(ValueError, match="sampled controls"):
        lc.solve(lc.forward_gait())
    with pytest.raises(ValueError, match="'goal'"):  # a goal outside the lane
        lc.make_task(
            lj.Car(),
            t_final=10.0,
            n_steps=20,
            q0=np.zeros(5),
            qdot0=np.zeros(5),
            objective=(lc.Effort(jnp.ones(2)),),
            constraints=(lc.TerminalPose([0.0, 2.0, 0.0]),),
            bounds=lc.Bounds.of(lj.Car(), q={"y": 0.5, "sigma": 1.0}),
        )
    with pytest.raises(ValueError, match="'goal'"):  # the same check on a copy
        task.with_options(goal=[0.0, np.nan, 0.0])
    with pytest.raises(ValueError, match="'barrier'"):
        lc.solve(task, barrier=-1.0)
    with pytest.raises(TypeError, match="'task'"):
        lc.solve("parallel_park")


@PARK40_GROUP  # the small parallel_park with other bounds and goal: its programs
def test_unreachable_goal_is_reported_not_converged():
    """A goal the torque bound cannot reach in time: no silent answer, converged=False with a reason."""
    task = lc.parallel_park(integrator=lj.RDP(), n_steps=40).with_options(goal=[30.0, 0.25, 0.0])
    task = task.with_options(
        bounds=lc.Bounds.of(task.system, q={"sigma": 1.0}, u={"f_psi": 0.01, "u_sigma": 0.5})
    )
    sol = lc.solve(task, max_iterations=60)
    assert not bool(sol.converged)
    assert sol.result != lc.SOLVER_RESULTS.successful
    assert lc.SOLVER_RESULTS[sol.result] != ""
    assert float(sol.max_violation) > 1e-3


# --------------------------------------------------------------------------- the penalty form
SMALL = {
    "parallel_park": lambda **kw: lc.parallel_park(t_final=10.0, n_steps=40, **kw),
    "forward_gait": lambda **kw: lc.forward_gait(t_final=6.0, n_steps=40, **kw),
}


@pytest.mark.parametrize("name", sorted(SMALL))
def test_penalty_gradient_matches_finite_differences(name):
    """Directional derivative of the penalty-form loss (reverse mode through the rollout) vs
    central differences (step 1e-5: truncation and round-off far below the 1e-6 tolerance)."""
    task = SMALL[name]()
    p = task.init()
    leaves, treedef = jax.tree_util.tree_flatten(p)
    # the point, the direction and the differences on the host (op by op, JAX compiles each)
    keys = np.asarray(jax.random.split(jax.random.PRNGKey(1), len(leaves)))
    p = jax.tree_util.tree_unflatten(
        treedef,
        [np.asarray(x) + 0.05 * np.asarray(jax.random.normal(k, x.shape)) for x, k in zip(leaves, keys)],
    )
    v = jax.tree_util.tree_unflatten(
        treedef, [np.asarray(jax.random.normal(k, x.shape)) for x, k in zip(leaves, keys[::-1])]
    )
    value = eqx.filter_jit(task.value)
    grad = eqx.filter_jit(lambda x: jax.grad(task.value)(x))(p)
    eps = 1e-5
    shift = lambda s: jax.tree_util.tree_map(lambda x, d: x + s * d, p, v)  # noqa: E731
    fd = (float(value(shift(eps))) - float(value(shift(-eps)))) / (2 * eps)
    ad = sum(
        np.vdot(np.asarray(a), b)
        for a, b in zip(jax.tree_util.tree_leaves(grad), jax.tree_util.tree_leaves(v))
    )
    assert abs(float(ad - fd)) <= 1e-6 * (abs(float(fd)) + 1e-3 * float(value(p))), (float(ad), float(fd))


@pytest.fixture(scope="module")
def park40():
    """The optimize tests' task: they share one compiled L-BFGS chunk (one xdist group)."""
    return SMALL["parallel_park"]()


def test_optimize_compiles_once_keeps_terms_and_stops(park40):
    """L-BFGS on the penalty form: one compilation for all chunks, the loss falls 100x, the cost
    terms are kept per iteration, and a stopping tolerance ends the run early."""
    from ldap_jax.control import _optimize

    task = park40
    p0 = task.init()
    # other optimize runs on this worker (other losses or optimizers) may have compiled programs of
    # their own; this one is the first of its xdist group to compile its chunk: exactly one new
    before = _optimize._run_chunk._cached._cache_size()
    res = lc.optimize(task.loss, p0, n_iterations=40, chunk=10)
    assert _optimize._run_chunk._cached._cache_size() - before == 1
    assert float(res.loss) <= float(res.losses[0]) / 100
    assert set(res.aux) == {"effort", "terminalpose", "terminalrest", "bounds"}
    assert res.aux["terminalpose"].shape == (40,)
    np.testing.assert_allclose(
        sum(np.asarray(v)[3] for v in res.aux.values()), np.asarray(res.losses)[3], rtol=1e-12
    )
    stopped = lc.optimize(task.loss, p0, n_iterations=400, chunk=10, tol=1e-3)
    assert bool(stopped.converged) and stopped.iterations < 400
    # the tolerance is traced: another tol ran the same compiled chunk
    assert _optimize._run_chunk._cached._cache_size() - before == 1


def test_optimize_takes_any_optax_transformation():
    task = SMALL["parallel_park"]()
    p0 = task.init()
    for opt in (optax.sgd(1e-4), optax.adam(1e-2)):
        res = lc.optimize(task.value, p0, n_iterations=10, optimizer=opt)
        assert float(res.loss) < float(res.losses[0])


def test_optimize_warns_when_the_loss_is_never_finite():
    with pytest.warns(UserWarning, match="never finite"):
        lc.optimize(lambda p: jnp.sum(p) * jnp.nan, jnp.ones(3), n_iterations=2, optimizer=optax.sgd(0.1))


def test_optimize_warns_when_the_loss_never_falls_below_the_guess(park40):
    """From zero controls the parallel parking car cannot move at first order: the penalty's
    gradient is exactly zero, L-BFGS stays at the guess and its stopping test holds. The run says
    so instead of passing the guess off as an optimum; multistart counts the starts concerned, and a
    start that makes progress raises nothing (the suite turns warnings into errors)."""
    task = park40
    p0 = jnp.zeros((task.n_steps + 1, 2))
    grad0 = np.asarray(jax.jit(jax.grad(task.value))(p0))  # compiled, not op by op
    assert float(np.max(np.abs(grad0))) == 0.0
    with pytest.warns(UserWarning, match="never fell below its value at the initial guess"):
        res = lc.optimize(task.loss, p0, n_iterations=10, chunk=10)
    np.testing.assert_array_equal(res.params, p0)
    saddle = lambda p: p[0] ** 2 - p[1] ** 2 + p[2] ** 2  # noqa: E731
    starts = jnp.array([[0.0, 0.0, 0.0], [1.0, 0.5, 1.0]])
    with pytest.warns(UserWarning, match="1 of 2 starts: the loss never fell"):
        lc.multistart(saddle, starts, n_iterations=3, optimizer=optax.sgd(0.1))


def test_multistart_vmap_equals_loop(park40):
    """A vmapped multistart is the loop of single runs (the single runs are the program the other
    optimize tests compile: same task, loss and chunk)."""
    task = park40
    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    p0 = jax.vmap(task.init)(keys)
    n = 10
    batch = lc.multistart(task.loss, p0, n_iterations=n)
    for i in range(3):
        one = lc.optimize(task.loss, p0[i], n_iterations=n, chunk=10)
        np.testing.assert_allclose(np.asarray(batch.losses)[i], one.losses, rtol=1e-9)
        np.testing.assert_allclose(np.asarray(batch.params)[i], one.params, rtol=1e-8, atol=1e-10)
        for name in one.aux:
            np.testing.assert_allclose(np.asarray(batch.aux[name])[i], one.aux[name], rtol=1e-9, atol=1e-12)
    assert float(lc.best_of(batch).loss) == float(np.min(np.asarray(batch.loss)))


def test_checkpoint_same_gradient_less_memory():
    task = lc.forward_gait(t_final=10.0, n_steps=2000)
    p = task.init()
    ck = task.with_options(checkpoint="sqrt")
    # the programs lc.gradient_memory compiles (the same function and options): it reads them
    # from the persistent cache instead of compiling them again
    options = lj.compiler_options()
    g0 = jax.jit(lambda p: jax.grad(task.value)(p), compiler_options=options)(p)
    g1 = jax.jit(lambda p: jax.grad(ck.value)(p), compiler_options=options)(p)
    for a, b in zip(jax.tree_util.tree_leaves(g0), jax.tree_util.tree_leaves(g1)):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-12)
    assert lc.gradient_memory(ck, p)["temp_bytes"] < lc.gradient_memory(task, p)["temp_bytes"]


# ------------------------------------------------------------------------------------ terms
def test_pose_error_on_se2():
    # compiled (one program each), not op by op; the points on the host
    pose_error = jax.jit(lc.pose_error)
    goal = np.array([0.3, -0.2, 0.7])
    q = np.array([0.3, -0.2, 0.7, 1.0, 2.0])
    np.testing.assert_allclose(pose_error(q, goal), 0.0, atol=1e-15)
    q = np.array([1.0, 0.5, -2.5, 0.0, 0.0])
    expected = jax.jit(lambda g, x: lj.lie.log(lj.lie.compose(lj.lie.inverse(g), x[:3])))(goal, q)
    np.testing.assert_allclose(pose_error(q, goal), expected, atol=1e-13)
    turned = np.array(q)  # a host copy
    turned[2] += 2 * np.pi
    np.testing.assert_allclose(pose_error(turned, goal), pose_error(q, goal), atol=1e-12)
    term = lc.TerminalPose(goal, 1.0, 1.0)
    node = lc.Node(np.array([0.3, -0.2, 0.7, 0.0, 0.0]), np.zeros(5))
    grad = jax.jit(jax.grad(lambda x: term.terminal(lj.Car(), node._replace(q=x), np.zeros(5))))(node.q)
    assert np.all(np.isfinite(np.asarray(grad)))
    np.testing.assert_allclose(grad, 0.0, atol=1e-14)


def test_penalty_form_on_values_is_one_program():
    """``task.loss`` and ``task.terms`` called on values (a notebook's first ``task.value(p)``)
    run as one compiled program each, not operation by operation (measured before: 123 programs
    and 3.6 s; a first ``jax.grad(task.value)`` 189 programs and 7.5 s), and give the value traced
    inline into a caller's ``jit``."""
    task = lc.parallel_park(n_steps=12)
    p = task.init()
    with compiled_programs() as names:
        value = task.value(p)
    assert "jit(loss)" in names and len(names) <= 3, names
    np.testing.assert_allclose(value, jax.jit(lambda x: task.value(x))(p), rtol=1e-13)
    traj = task.rollout(p)
    with compiled_programs() as names:
        terms = task.terms(traj, p)
    assert names == ["jit(terms)"], names
    assert sum(float(v) for v in terms.values()) == pytest.approx(float(value), rel=1e-13)


@PARK40_GROUP
def test_terms_compose_and_replay_reuses_them(small_park):
    """The penalty form is the sum of its terms; the replay scores the reference with the same terms."""
    task, p0 = small_park
    total, terms = task.loss(p0)
    assert float(total) == pytest.approx(sum(float(v) for v in terms.values()), rel=1e-13)
    effort = eqx.filter_jit(  # one program, not op by op
        lambda task, p, t: lc.effort_cost(jax.vmap(task.controls(p))(t), task.h, task.parameterization.scale)
    )(task, p0, task.rollout(p0).t)
    assert float(terms["effort"]) == pytest.approx(1e-5 * float(effort), rel=1e-12)
    rp = lc.replay(task, p0)
    assert set(rp["terms_reference"]) == set(terms)
    assert float(rp["terms_reference"]["effort"]) == pytest.approx(float(terms["effort"]), rel=1e-12)


def test_bound_penalty():
    lo, hi = jnp.array([-1.0, -jnp.inf]), jnp.array([1.0, jnp.inf])
    assert float(lc.bound_penalty(jnp.array([0.5, 100.0]), lo, hi)) == 0.0
    assert float(lc.bound_penalty(jnp.array([1.5, 0.0]), lo, hi)) == pytest.approx(0.25)
    g = jax.grad(lc.bound_penalty)(jnp.array([0.5, 1e300]), lo, hi)
    assert np.all(np.isfinite(np.asarray(g)))


def test_bad_arguments():
    task = SMALL["parallel_park"]()
    with pytest.raises(ValueError, match="n_iterations"):
        lc.optimize(task.value, task.init(), n_iterations=0)
    with pytest.raises(ValueError, match="chunk"):
        lc.optimize(task.value, task.init(), n_iterations=3, chunk=0)
    with pytest.raises(ValueError, match="n_steps"):
        lc.SampledControls(1.0, 0, [1.0, 1.0])
    with pytest.raises(ValueError, match="n_terms"):
        lc.SinusoidGait([1.0, 1.0], n_terms=0)
    with pytest.raises(ValueError, match="n_steps"):
        lc.parallel_park(n_steps=0)
    with pytest.raises(TypeError, match="optimizer"):
        lc.optimize(task.value, task.init(), n_iterations=3, optimizer="adam")


@PARK40_GROUP
def test_solve_flags_invalid_traced_parameters_and_nan_gradients_of_failures(small_park, vmapped_park):
    """Under vmap over the car's mass [1, -1, 0] (traced: no construction-time check; members 0, 3
    and 4 of the shared vmapped solve), and over a goal with a NaN (member 5), the solve of each
    invalid member ends with invalid_input and converged=False, the valid one converges; and the
    derivative of a solve that did not converge (max_iterations=1) is NaN, not a finite number that
    looks like a sensitivity (the derivatives in goal and mass of the sensitivities test: its
    compiled programs, other values)."""
    task, p0 = small_park
    _, batch = vmapped_park
    assert np.asarray(batch.converged)[[0, 3, 4, 5]].tolist() == [True, False, False, False]
    results = np.asarray(batch.result._value)
    assert results[3] == results[4] == results[5] == lc.SOLVER_RESULTS.invalid_input._value

    def effort(goal, m, iterations):
        return lc.solve(task.with_options(goal=goal, system=lj.Car(m=m)), p0, max_iterations=iterations).cost

    grad = jax.grad(effort, argnums=(0, 1))
    m0 = jnp.asarray(1.0)
    assert np.isnan(float(grad(task.goal, m0, 1)[1]))
    assert np.isfinite(float(grad(task.goal, m0, 1000)[1]))


@PARK40_GROUP
def test_eager_vmapped_solve_traces_the_solver_once(small_park, vmapped_park):
    """An eager ``jax.vmap`` of ``lc.solve`` (no ``jit`` around it) called again with other values
    traces none of the solver's programs: the map over its members is one compiled program per
    problem structure (it was traced again on every call: 4 parking solves took 7.2 s per call
    instead of 0.4 s)."""
    task, p0 = small_park
    goals, first = vmapped_park
    masses = jax.device_put(PARK_MASSES)
    moved = jax.device_put(np.asarray(goals) + np.array([[0.01, 0.0, 0.0]]))

    def solve(g, m):
        return lc.solve(task.with_options(goal=g, system=lj.Car(m=m)), p0)

    # the fixture's call again (it traced the solver, unless the worker emptied JAX's caches since:
    # tests/conftest.py trims them between tests when the memory mappings grow)
    jax.vmap(solve)(goals, masses)
    with compiled_programs("trace") as names:
        again = jax.vmap(solve)(moved, masses)
    assert not names, names
    assert np.all(np.asarray(again.converged)[:3])
    assert np.max(np.abs(np.asarray(again.params)[0] - np.asarray(first.params)[0])) > 1e-4  # a new goal


# ----------------------------------------------------------------------- a new process's first solve
def test_task_construction_and_solve_setup_run_no_eager_operation():
    """``lc.parallel_park()`` (its car's parameter checks, its value checks) and ``lc.solve``'s
    set-up (the default guess, the options, the solver's view) run no eager JAX operation on its
    known values: in a new process each would compile a program of its own. The guess made on
    the host equals the compiled one."""
    from ldap_jax.control._solve import _checked, _solver_view
    from ldap_jax.control._task import _initial_guess

    with eager_operations() as ops:
        task = lc.parallel_park()
        _, params0, _ = _checked(task, None, 1e-8, 1000, "base", 0.1, None)
        _solver_view(task)
    assert ops == []
    np.testing.assert_allclose(params0, _initial_guess(task, None, task.guess.amplitude), rtol=0, atol=1e-15)
    assert params0.dtype == jnp.float64 and params0.shape == (101, 2)
    # the checks still stop bad values
    with pytest.raises(ValueError, match="'m'"):
        lc.parallel_park(lj.Car(m=-1.0))
    with pytest.raises(ValueError, match="'qdot0' violates the constraints"):
        lc.make_task(
            lj.Car(),
            t_final=1.0,
            n_steps=10,
            q0=np.zeros(5),
            qdot0=np.array([0.0, 1.0, 0, 0, 0]),
            objective=(lc.Effort(np.ones(2)),),
            constraints=(),
        )
