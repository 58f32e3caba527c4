"""Bring your own system: the general RDP step and the derived continuous equations."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import (
    RACER,
    SLEIGH,
    STEERED_SLEIGH_LENGTH,
    fitted_order,
    index,
    maneuvers,
    reference_batch,
    simulate_ns,
    simulate_over_alphas,
    sleigh_batch,
    sleigh_newton_run,
    steered_sleigh,
    systems,
)

import ldap_jax as lj
from ldap_jax.integrators import RDP

SYSTEMS = systems()


def user_car(car):
    """The car written only through the public description (no closed form)."""
    p = dict(m=car.m, I=car.I, K=car.K, rho=car.rho, l=car.l)
    return lj.System(
        2,
        lambda p, r, u, xi: (
            0.5 * (p["I"] * u[0] ** 2 + p["K"] * xi[0] ** 2 + p["m"] * (xi[1] ** 2 + xi[2] ** 2))
        ),
        lambda p, r: jnp.array([[-p["rho"] * r[1] / p["l"], 0.0], [-p["rho"], 0.0], [0.0, 0.0]]),
        params=p,
        kinematic=(False, True),
    )


def user_snakeboard(sb):
    p = dict(m=sb.m, l=sb.l, I=sb.I, J=sb.J)

    def lagrangian(p, r, u, xi):
        return 0.5 * (
            p["I"] * u[0] ** 2
            + 2 * p["I"] * u[0] * xi[0]
            + 2 * p["J"] * u[1] ** 2
            + p["m"] * p["l"] ** 2 * xi[0] ** 2
            + p["m"] * (xi[1] ** 2 + xi[2] ** 2)
        )

    def connection(p, r):
        s = jnp.sin(r[1])
        return jnp.array(
            [
                [p["I"] * s**2 / (p["m"] * p["l"] ** 2), 0.0],
                [-p["I"] * jnp.sin(2 * r[1]) / (2 * p["m"] * p["l"]), 0.0],
                [0.0, 0.0],
            ]
        )

    def basis(p, r):
        return jnp.stack([jnp.sin(2 * r[1]), -2 * p["l"] * jnp.cos(r[1]) ** 2, 0.0])[:, None]

    return lj.System(2, lagrangian, connection, basis, params=p, singularity=lambda p, r: jnp.cos(r[1]))


USER = {"car": user_car(SYSTEMS["car"]), "snakeboard": user_snakeboard(SYSTEMS["snakeboard"])}


@pytest.mark.parametrize("name", list(SYSTEMS))
def test_derived_continuous_equations_equal_hand_written(name):
    model, user = SYSTEMS[name], USER[name]
    rng = np.random.default_rng(0)

    @eqx.filter_jit  # one program, not op by op
    def both(model, user, q, c, v_model):
        f, u_kin = model.inputs(c)
        qdot = model.qdot_from_velocities(q, v_model, u_kin)
        v = user.velocities_from_qdot(q, qdot)
        qd_user = jax.jvp(
            user.qdot_from_velocities,
            (q, v, u_kin),
            (qdot, user.velocity_dynamics(q, v, f, u_kin), jnp.zeros(2)),
        )[1]
        vm = model.velocities_from_qdot(q, qdot)
        qd_model = jax.jvp(
            model.qdot_from_velocities,
            (q, vm, u_kin),
            (qdot, model.velocity_dynamics(q, vm, f, u_kin), jnp.zeros(2)),
        )[1]
        return qdot, user.qdot_from_velocities(q, v, u_kin), qd_user, qd_model

    for _ in range(10):
        q = jnp.asarray(rng.normal(size=5))
        c = jnp.asarray(rng.normal(size=2))
        v_model = jnp.asarray(rng.normal(size=model.n_velocities))
        qdot, qdot_user, qd_user, qd_model = both(model, user, q, c, v_model)
        np.testing.assert_allclose(qdot_user, qdot, atol=1e-14)
        np.testing.assert_allclose(qd_user, qd_model, atol=1e-12)


@pytest.mark.parametrize("retraction", ["exp", "cayley"])
@pytest.mark.parametrize("name", list(SYSTEMS))
def test_general_step_on_user_description_equals_closed_form(name, retraction):
    """1000-step trajectories of the user-described car and snakeboard through the general
    Newton step match the hand-derived closed forms to 1e-10, for alpha in {0, 1/2, 1}."""
    model = SYSTEMS[name]
    batch = maneuvers(model, 1, seed=31)
    alphas = (0.0, 0.5, 1.0)
    # without the diagnostics the comparison does not read: a smaller program
    quiet = {"diagnostics": False}
    closed = simulate_over_alphas(model, batch, alphas, 20.0, 1000, quiet, retraction=retraction)
    general = simulate_over_alphas(USER[name], batch, alphas, 20.0, 1000, quiet, retraction=retraction)
    assert RDP().uses_kernel(model) and not RDP().uses_kernel(USER[name])
    for alpha, c, g in zip(alphas, closed, general):
        assert not bool(np.any(np.asarray(c.failed))) and not bool(np.any(np.asarray(g.failed))), alpha
        assert bool(np.all(np.asarray(g.converged)))
        np.testing.assert_allclose(g.q, c.q, rtol=0, atol=1e-10, err_msg=str(alpha))
        np.testing.assert_allclose(g.qdot, c.qdot, rtol=0, atol=1e-10, err_msg=str(alpha))


class PrintedSign(RDP):
    """RDP with the connection term of (23) as (25) prints it (+A instead of -A)."""

    def _residual(self, system, h, r, u, xi, pu_force, mu_in):
        hor, vert = super()._residual(system, h, r, u, xi, pu_force, mu_in)
        a = self._alpha(r.dtype)
        mu = jax.grad(system.reduced_lagrangian, argnums=2)(r + a * h * u, u, xi)
        jump = self._dtau(h * xi).T @ mu - mu_in
        return hor + 2 * system.connection(r).T @ jump, vert


def test_sign_of_the_connection_term():
    """(23)'s sign converges to the continuous solution; (25) as printed (+A) does not."""
    car = USER["car"]
    batch = maneuvers(SYSTEMS["car"], 1, seed=3)
    ref = lj.reference(car, *index(batch, 0), jnp.array([0.0, 4.0]))
    ref_q = np.asarray(ref.q)
    errs = {}
    for label, integ in (("(23)", RDP()), ("(25) printed", PrintedSign(solver="newton"))):
        runs = simulate_ns(car, integ, batch, 4.0, (100, 200), diagnostics=False)  # q alone is read
        errs[label] = [float(np.linalg.norm(runs[n].q[0, -1, :3] - ref_q[-1, :3])) for n in (100, 200)]
    print(errs)
    assert fitted_order([1, 0.5], errs["(23)"]) > 1.9
    assert min(errs["(25) printed"]) > 100 * errs["(23)"][-1]
    assert errs["(25) printed"][-1] > 0.5 * errs["(25) printed"][0]  # no convergence


def _sleigh_case():
    q0, qdot0, ctl = index(sleigh_batch(), 0)
    return SLEIGH, q0, qdot0, ctl


def _racer_case(seed=0):
    rng = np.random.default_rng(seed)
    ctl = lj.Sinusoids(
        amplitude=[[rng.uniform(0.2, 0.5), rng.uniform(0.0, 0.2)]],
        frequency=[[rng.uniform(1.5, 3.0), rng.uniform(0.5, 1.5)]],
        phase=[[rng.uniform(0, 6), 0.0]],
    )
    q0 = jnp.array([0.0, 0.0, rng.uniform(-3, 3), rng.uniform(-0.3, 0.3)])
    v0 = jnp.asarray(rng.uniform(-0.3, 0.3, size=2))
    qdot0 = eqx.filter_jit(RACER.qdot_from_velocities)(q0, v0, jnp.zeros(1))  # one program, not op by op
    return RACER, q0, qdot0, ctl


@pytest.mark.parametrize("case", ["sleigh", "racer"])
def test_new_systems_reduced_equals_full_lagrange_dalembert(case):
    system = (_sleigh_case if case == "sleigh" else _racer_case)()[0]
    rng = np.random.default_rng(2)

    @eqx.filter_jit  # one program, not op by op
    def reduced_and_full(system, q, v, f):
        zero = jnp.zeros(system.n_shape)
        qdot = system.qdot_from_velocities(q, v, zero)
        qddot = jax.jvp(
            system.qdot_from_velocities, (q, v, zero), (qdot, system.velocity_dynamics(q, v, f, zero), zero)
        )[1]
        return system.constraint_residual(q, qdot), qddot, system.full_acceleration(q, qdot, f, zero)[0]

    for _ in range(10):
        q = jnp.asarray(rng.normal(size=system.n_config))
        v = jnp.asarray(rng.normal(size=system.n_velocities))
        f = jnp.asarray(rng.normal(size=system.n_shape))
        residual, qddot, qddot_full = reduced_and_full(system, q, v, f)
        assert float(residual) < 1e-14
        np.testing.assert_allclose(qddot, qddot_full, atol=1e-12)


@pytest.mark.parametrize("case", ["sleigh", "racer"])
def test_new_systems_converge_with_order_two(case):
    system, q0, qdot0, ctl = (_sleigh_case if case == "sleigh" else _racer_case)()
    batch = jax.tree_util.tree_map(lambda x: x[None], (q0, qdot0, ctl))
    t_final = 6.0
    ref = reference_batch(system, batch, jnp.linspace(0.0, t_final, 41))
    variants = [(RDP(), 2), (lj.RK4(), 4)]
    if (
        case == "sleigh"
    ):  # the exact dcay^-1 through the Newton step (covered for the racer by the gradient test)
        variants.insert(1, (RDP(retraction="cayley", dtau_order=None), 2))
    ns = (40, 80, 160)
    for integrator, order in variants:
        runs = simulate_ns(system, integrator, batch, t_final, ns, diagnostics=False)  # q alone is read
        errs = []
        for n in ns:
            assert not bool(np.any(runs[n].failed))
            q = runs[n].q[:, :: n // 40]
            errs.append(float(np.max(np.linalg.norm(q[..., :3] - np.asarray(ref.q)[..., :3], axis=-1))))
        p = fitted_order([t_final / n for n in ns], errs)
        print(case, integrator, errs, p)
        assert p > order - 0.15


def test_sleigh_energy_and_momentum_equation():
    """The unforced sleigh conserves energy; RDP keeps it over 10^4 steps and satisfies its
    discrete momentum equations (21) to round-off."""
    traj = sleigh_newton_run("exp")
    assert not bool(np.any(np.asarray(traj.failed)))
    e = np.asarray(traj.energy)
    assert np.abs(e - e[:, :1]).max() < 1e-6 * e[:, 0].min()
    assert float(np.max(np.asarray(traj.step_residual))) < 1e-12
    # the continuous momentum is not conserved: the sleigh's momentum changes
    assert float(np.min(np.ptp(np.asarray(traj.momentum)[..., 0], axis=1))) > 1e-2


def test_roller_racer_momentum_and_energy():
    racer, q0, qdot0, ctl = _racer_case(1)
    traj = lj.simulate(racer, q0, qdot0, ctl, t_final=20.0, n_steps=2000)
    assert not bool(traj.failed)
    balance, work, q = (np.asarray(x) for x in (traj.energy_balance, traj.work, traj.q))  # host copies
    assert float(np.max(np.asarray(traj.step_residual))) < 1e-11
    assert float(np.max(np.abs(balance))) < 1e-2 * float(np.max(np.abs(work)) + 1e-3)
    assert abs(float(q[-1, 0] - q[0, 0])) + abs(float(q[-1, 1] - q[0, 1])) > 0.1  # it moves


def test_gradient_through_general_implicit_step():
    racer, q0, qdot0, ctl = _racer_case(2)

    def loss(amp):
        c = lj.Sinusoids(amplitude=amp, frequency=ctl.frequency, phase=ctl.phase)
        traj = lj.simulate(
            racer, q0, qdot0, c, t_final=3.0, n_steps=150, integrator=RDP(dtau_order=None), diagnostics=False
        )
        return jnp.sum(traj.q[-1, :3] ** 2)

    value_and_grad = jax.jit(jax.value_and_grad(loss))
    amp = ctl.amplitude
    grad = np.asarray(value_and_grad(amp)[1]).ravel()
    eps = 1e-6
    fd = []
    amp = np.asarray(amp)  # the differences' points on the host (op by op, JAX compiles each operation)
    for i in range(amp.size):
        e = np.zeros(amp.size)
        e[i] = eps
        e = e.reshape(amp.shape)
        fd.append((float(value_and_grad(amp + e)[0]) - float(value_and_grad(amp - e)[0])) / (2 * eps))
    np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-5 * np.abs(fd).max())


def test_vmap_over_64_maneuvers_equals_loop_for_user_system():
    keys = jax.random.split(jax.random.PRNGKey(0), 64)
    amps = jax.vmap(lambda k: jax.random.uniform(k, (1, 1), minval=0.1, maxval=0.5))(keys)
    ctl = lj.Sinusoids(amplitude=amps, frequency=jnp.full((64, 1, 1), 2.0), phase=jnp.zeros((64, 1, 1)))
    q0 = jnp.zeros(4)
    qdot0 = jnp.zeros(4)
    run = jax.jit(lambda c: lj.simulate(RACER, q0, qdot0, c, t_final=2.0, n_steps=50, diagnostics=False).q)
    batched = np.asarray(jax.vmap(run)(ctl))
    for i in range(0, 64, 7):
        np.testing.assert_allclose(batched[i], run(index(ctl, i)), rtol=1e-12, atol=1e-13)


def test_inconsistent_shapes_name_the_function():
    def lag(r, u, xi):
        return 0.5 * jnp.sum(xi**2) + 0.5 * jnp.sum(u**2)

    with pytest.raises(ValueError, match="connection"):
        lj.System(2, lag, lambda r: jnp.zeros((3, 3)))
    with pytest.raises(ValueError, match="symmetry_basis"):
        lj.System(2, lag, lambda r: jnp.zeros((3, 2)), lambda r: jnp.zeros((2, 1)))
    with pytest.raises(ValueError, match="lagrangian"):
        lj.System(2, lambda r, u, xi: xi, lambda r: jnp.zeros((3, 2)))
    with pytest.raises(ValueError, match="constraints"):
        lj.System(
            2, lag, lambda r: jnp.zeros((3, 2)), lambda r: jnp.zeros((3, 1)), lambda r: jnp.zeros((2, 4))
        )
    with pytest.raises(ValueError, match="'kinematic'"):
        lj.System(2, lag, lambda r: jnp.zeros((3, 2)), kinematic=(True,))
    with pytest.raises(ValueError, match="'d1' and 'd2'"):
        lj.roller_racer(d1=0.4, d2=0.4)
    with pytest.raises(ValueError, match="'a'"):
        lj.chaplygin_sleigh(a=-1.0)


def test_a_kinematic_coordinates_acceleration_enters_the_reference_and_rk4():
    """A sleigh whose front wheel (with inertia) is steered at a prescribed rate: the steering's
    acceleration enters the other equations. lj.reference took it as zero and ended 0.4 m off
    (reporting success), RK4 converged to that (order 0). Now the reference agrees with
    RDP(order=6), which needs no acceleration (a different, discrete route), and RK4 converges
    to it at order 4."""
    sleigh, length = steered_sleigh(kinematic=(True,)), STEERED_SLEIGH_LENGTH
    ctl = lj.Sinusoids(amplitude=[[0.6]], frequency=[[1.5]], phase=[[0.3]])
    q0 = jnp.array([0.0, 0.0, 0.1, 0.2])
    qdot0 = jnp.array([np.cos(0.1), np.sin(0.1), np.tan(0.2) / length, 0.6 * np.sin(0.3)])
    ref = lj.reference(sleigh, q0, qdot0, ctl, jnp.array([0.0, 10.0])).q[-1]
    rdp6 = lj.simulate(
        sleigh, q0, qdot0, ctl, t_final=10.0, n_steps=160, integrator=lj.RDP(order=6), save="final"
    )
    np.testing.assert_allclose(np.asarray(rdp6.q[-1]), np.asarray(ref), atol=1e-8)
    errors = [
        float(
            jnp.max(
                jnp.abs(
                    lj.simulate(
                        sleigh, q0, qdot0, ctl, t_final=10.0, n_steps=n, integrator=lj.RK4(), save="final"
                    ).q[-1]
                    - ref
                )
            )
        )
        for n in (200, 400)
    ]
    assert 3.5 < np.log2(errors[0] / errors[1]) < 4.5, errors
