"""RDP of order 4, 6 and 8: the folded momentum state, exact symmetry, composition orders, per-substep
structure, node velocities from the momenta, gradients and bad settings."""

import importlib.util
import os

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import (
    discrete_momenta,
    fitted_order,
    index,
    maneuvers,
    reference_batch,
    simulate_ns,
    systems,
)

import ldap_jax as lj
from ldap_jax import lie
from ldap_jax.integrators import SCHEMES

SYSTEMS = systems()


def _reduced_momenta(system, q, pu, mu):
    """What later steps read of a carried pair: ``pu - A(r)^T mu`` and ``e(r)^T mu``."""
    r = q[3:]
    return jnp.concatenate([pu - system.connection(r).T @ mu, system.symmetry_basis(r).T @ mu])


# --------------------------------------------------------------------- the paper's scheme, unfolded
def _paper_rollout(system, q0, qdot0, ctl, h, n):
    """The paper's RDP (alpha = 1/2, exp, dtau^-1 = I - ad/2) with the previous step's force kept
    apart, ``F_k = a f_{k-1+a} + (1-a) f_{k+a}`` multiplied by the current ``h``: written here from
    (21), (23) with a Newton solve, independently of the library's step."""
    a = 0.5
    r0, rdot0 = q0[3:], qdot0[3:]
    xi0 = lj.systems.body_velocity(q0, qdot0)
    pu0, mu0 = jax.grad(system.reduced_lagrangian, argnums=(1, 2))(r0, rdot0, xi0)
    dyn = np.asarray(system.dynamic_index)
    nd = dyn.size

    def step(state, k):
        q, pu, mu, f_prev = state
        r = q[3:]
        c0, c1 = ctl(k * h), ctl((k + 1) * h)
        f0, uk0 = system.inputs(c0)
        f1, uk1 = system.inputs(c1)
        f_a = (1 - a) * f0 + a * f1
        force = a * f_prev + (1 - a) * f_a
        u_kin = 0.5 * (uk0 + uk1)

        def unpack(z):
            u = u_kin.at[dyn].set(z[:nd])
            r_a = r + a * h * u
            return u, system.symmetry_basis(r_a) @ z[nd:] - system.connection(r_a) @ u

        def residual(z):
            u, xi = unpack(z)
            dl_du, dl_dxi = jax.grad(system.reduced_lagrangian, argnums=(1, 2))(r + a * h * u, u, xi)
            jump = lie.dtau_inv(h * xi, "exp", 1).T @ dl_dxi - mu
            hor = dl_du - pu - system.connection(r).T @ jump - h * force
            return jnp.concatenate([hor[dyn], system.symmetry_basis(r).T @ jump])

        z = jnp.zeros(nd + system.symmetry_basis(r).shape[1])
        for _ in range(8):
            z = z - jnp.linalg.solve(jax.jacfwd(residual)(z), residual(z))
        u, xi = unpack(z)
        dl_du, dl_dxi = jax.grad(system.reduced_lagrangian, argnums=(1, 2))(r + a * h * u, u, xi)
        q_next = jnp.concatenate([lie.compose(q[:3], lie.exp(h * xi)), r + h * u])
        mu_next = lie.dtau_inv(-h * xi, "exp", 1).T @ dl_dxi
        # what the next step reads of the momenta: pu + h a f_{k+a} (its force term) with mu
        seen = _reduced_momenta(system, q_next, dl_du + h * a * f_a, mu_next)
        return (q_next, dl_du, mu_next, f_a), (q_next, seen)

    state0 = (q0, pu0, mu0, jnp.zeros_like(pu0))
    _, (q, p) = jax.lax.scan(step, state0, jnp.arange(n, dtype=q0.dtype))
    return q, p


@pytest.mark.parametrize("name", list(SYSTEMS))
def test_folded_state_equals_paper_scheme_at_constant_step(name):
    """Folding the force into the carried momentum changes nothing at a constant step: the
    trajectories and the carried momenta (through what later steps read) agree to 1e-12 over
    1000 steps, for the closed-form kernel and the general Newton step."""
    system = SYSTEMS[name]
    q0, qdot0, ctl = index(maneuvers(system, 1, seed=11), 0)
    n, t_final = 1000, 10.0
    h = t_final / n
    q_ref, p_ref = (np.asarray(x) for x in jax.jit(lambda: _paper_rollout(system, q0, qdot0, ctl, h, n))())
    for integrator in (lj.RDP(), lj.RDP(solver="newton")):

        def ours(integrator=integrator):
            state = integrator.init(system, h, q0, qdot0, None)
            nodes = jnp.asarray(integrator.control_nodes)

            def step(state, k):
                state, _ = integrator.step(system, h, state, jax.vmap(ctl)(k * h + h * nodes))
                q, pu, mu = integrator.momenta(system, state)
                return state, (q, _reduced_momenta(system, q, pu, mu))

            return jax.lax.scan(step, state, jnp.arange(n, dtype=q0.dtype))[1]

        q, p = (np.asarray(x) for x in jax.jit(ours)())
        assert float(np.max(np.abs(q - q_ref))) < 1e-12 * (1 + float(np.max(np.abs(q_ref))))
        assert float(np.max(np.abs(p - p_ref))) < 1e-12 * (1 + float(np.max(np.abs(p_ref))))


@eqx.filter_jit
def _there_and_back(system, integrator, q0, qdot0, c, h):
    """A step with ``h`` then one with ``-h`` (controls ``c`` read backwards): the carried
    momenta (as later steps read them) before, after one step and after both. One program per
    system and integrator: ``h`` and the controls are traced."""
    state0 = integrator.init(system, h, q0, qdot0, c)
    state1, _ = integrator.step(system, h, state0, c)
    state2, _ = integrator.step(system, -h, state1, c[::-1])
    seen = []
    for state in (state0, state1, state2):
        q, pu, mu = integrator.momenta(system, state)
        seen.append((q, _reduced_momenta(system, q, pu, mu)))
    return seen


@pytest.mark.parametrize("name", list(SYSTEMS))
@pytest.mark.parametrize("forced", [True, False])
def test_step_then_negative_step_returns_to_start(name, forced):
    """RDP at alpha = 1/2 is symmetric: a step with h, then one with -h (controls read at its own
    two ends), returns to the start to 1e-13 (configuration and carried momenta), forced or not,
    for both retractions and both the kernel and the Newton step."""
    system = SYSTEMS[name]
    q0, qdot0, ctl = index(maneuvers(system, 1, seed=12), 0)
    if not forced:
        ctl = lj.Sinusoids(jnp.zeros_like(ctl.amplitude), ctl.frequency, ctl.phase)
    t = 0.7
    for integrator in (lj.RDP(), lj.RDP(retraction="cayley"), lj.RDP(solver="newton")):
        for h in (0.05, 0.3):
            c = np.stack([np.asarray(ctl(t)), np.asarray(ctl(t + h))])
            seen = _there_and_back(system, integrator, q0, qdot0, c, jnp.asarray(h))
            (qa, ra), (q1, _), (qb, rb) = jax.tree_util.tree_map(np.asarray, seen)  # host copies
            assert float(np.max(np.abs(q1 - qa))) > 1e-3  # it did move
            assert float(np.max(np.abs(qb - qa))) < 1e-13
            assert float(np.max(np.abs(rb - ra))) < 1e-13 * (1 + float(np.max(np.abs(ra))))


def _terminal_errors(system, integrator, batch, t_final, ns):
    """Largest terminal position error over the batch at each step count of ``ns`` (ratios powers
    of two): one compiled program for all of them (helpers.simulate_ns)."""
    ref = np.asarray(reference_batch(system, batch, jnp.array([t_final])).q)[:, -1]
    runs = simulate_ns(system, integrator, batch, t_final, ns, diagnostics=False)
    errs = []
    for n in ns:
        assert not bool(np.any(runs[n].failed))
        errs.append(float(np.max(np.linalg.norm(runs[n].q[:, n, :3] - ref[:, :3], axis=-1))))
    return errs


ORDER_CASES = [
    (name, order, retraction)
    for name in SYSTEMS
    for order, retraction in ((4, "exp"), (4, "cayley"), (6, "exp"), (6, "cayley"))
]


@pytest.mark.parametrize("name,order,retraction", ORDER_CASES)
def test_composition_orders(name, order, retraction):
    """Observed orders 4.0 +- 0.3 and 6.0 +- 0.5 against lj.reference on random maneuvers."""
    system = SYSTEMS[name]
    batch = maneuvers(system, 3, seed=13)
    integrator = lj.RDP(order=order, retraction=retraction)
    ns = (16, 32, 64) if order == 4 else (8, 16, 32)
    errs = _terminal_errors(system, integrator, batch, 2.0, ns)
    p = fitted_order([2.0 / n for n in ns], errs)
    print(name, order, retraction, errs, p)
    assert abs(p - order) < (0.3 if order == 4 else 0.5), (errs, p)
    assert errs[-1] > 1e-13  # above round-off, so the slope is the scheme's


def _composition_weights_script():
    """scripts/composition_weights.py, which derived the ``least_error11`` weights."""
    path = os.path.join(os.path.dirname(__file__), "..", "scripts", "composition_weights.py")
    spec = importlib.util.spec_from_file_location("composition_weights", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_least_error11_has_order_6_and_a_smaller_leading_error():
    """The weights of ``least_error11`` satisfy the order-6 conditions of a palindromic composition
    of a symmetric step (the ``h^3`` and ``h^5`` terms of ``log`` of the composed flows
    ``exp(g h X1 + (g h)^3 X3 + ...)`` vanish, random ``X``) and its ``h^7`` term is smaller than
    Kahan and Li's 9-stage one by more than ``(11 / 9)^6 / 0.8^6``: fewer substeps at equal error."""
    script = _composition_weights_script()
    new, old = SCHEMES["least_error11"][1], SCHEMES["kahan_li9"][1]
    assert len(new) == 11 and np.all(np.diff(lj.RDP(order=6).control_nodes) != 0.0)
    assert np.max(np.abs(script.order_6_conditions(new))) < 1e-15
    terms, terms_old = script.error_terms(new, seeds=(4, 5)), script.error_terms(old, seeds=(4, 5))
    assert terms[3] < 1e-14 and terms[5] < 1e-14 and terms_old[5] < 1e-14
    effective = 11 * terms[7] ** (1 / 6) / (9 * terms_old[7] ** (1 / 6))
    assert effective < 0.8, effective


@pytest.mark.parametrize("name", list(SYSTEMS))
def test_least_error11_beats_kahan_li9_at_equal_substeps(name):
    """On the models, 18 steps of 11 substeps land closer to lj.reference than 22 steps of 9 (the
    same 198 substeps): the mean pose error (x, y, theta) over 16 random maneuvers is less than
    half (measured 0.2-0.35x; single maneuvers can be worse, about one in five)."""
    system = SYSTEMS[name]
    batch = maneuvers(system, 16, seed=7)
    ref = np.asarray(reference_batch(system, batch, jnp.array([2.0])).q)[:, -1, :3]
    errors = []
    for integrator, n in ((lj.RDP(order=6), 18), (lj.RDP(order=6, scheme="kahan_li9"), 22)):
        run = simulate_ns(system, integrator, batch, 2.0, (n,), diagnostics=False)[n]
        assert not bool(np.any(run.failed))
        errors.append(float(np.mean(np.linalg.norm(run.q[:, n, :3] - ref, axis=-1))))
    new, old = errors
    assert new < 0.5 * old, (new, old)
    assert new > 1e-12  # above the reference's accuracy


ORDER_8_CASES = [
    (name, retraction, scheme)
    for name in SYSTEMS
    for retraction, scheme in (("exp", "kahan_li17"), ("cayley", "kahan_li17"), ("exp", "mclachlan15"))
]


@pytest.mark.parametrize("name,retraction,scheme", ORDER_8_CASES)
def test_order_8_by_self_convergence(name, retraction, scheme):
    """Order 8 measured from the method's own successive differences ``|q_N - q_2N|`` at
    N = 16, 32, 64 over 4 s (errors from 1e-8 to 1e-12 m, where a comparison with the reference
    would meet its own tolerance): 8.0 +- 0.3. The limit is lj.reference's solution: each
    maneuver's N = 16 error against it equals its difference to N = 32 to 5% (plus 1e-11 m, the
    reference's own accuracy)."""
    system = SYSTEMS[name]
    batch = maneuvers(system, 3, seed=13)
    ns = (16, 32, 64)
    integrator = lj.RDP(order=8, retraction=retraction, scheme=scheme)
    runs = simulate_ns(system, integrator, batch, 4.0, ns, diagnostics=False)
    q = {}
    for n in ns:
        assert not bool(np.any(runs[n].failed))
        q[n] = runs[n].q[:, n, :3]
    diffs = [float(np.max(np.linalg.norm(q[a] - q[b], axis=-1))) for a, b in ((16, 32), (32, 64))]
    p = float(np.log2(diffs[0] / diffs[1]))
    assert abs(p - 8) < 0.3, (diffs, p)
    assert diffs[1] > 1e-13  # above round-off
    ref = np.asarray(reference_batch(system, batch, jnp.array([4.0])).q)[:, -1]
    error = np.linalg.norm(q[16] - ref[:, :3], axis=-1)
    estimate = np.linalg.norm(q[16] - q[32], axis=-1)
    assert np.all(np.abs(error - estimate) <= 0.05 * estimate + 1e-11), (error, estimate)


def test_order_8_on_sampled_controls_keeps_its_order_inside_the_step():
    """On piecewise-linear controls (lj.Sampled, a kink on a step boundary every 0.25 s) Kahan and
    Li's 17 stages, whose substeps stay inside the step, keep order 8 (> 7.5 from successive
    differences); McLachlan's 15, whose substeps reach 5% beyond it and cross the kinks, fall to
    order 2 (1.8-2.2)."""
    sb = SYSTEMS["snakeboard"]
    q0, qdot0, ctl = index(maneuvers(sb, 1, seed=3), 0)
    t_final = 2.0
    samples = lj.Sampled(
        np.stack([np.asarray(ctl(t)) for t in np.linspace(0.0, t_final, 9)]), t_final=t_final
    )
    for scheme, (low, high) in (("kahan_li17", (7.5, 9.0)), ("mclachlan15", (1.8, 2.2))):
        integrator = lj.RDP(order=8, scheme=scheme)
        q = [
            np.asarray(
                lj.simulate(
                    sb,
                    q0,
                    qdot0,
                    samples,
                    t_final=t_final,
                    n_steps=n,
                    integrator=integrator,
                    diagnostics=False,
                ).q[-1, :2]
            )
            for n in (8, 16, 32)
        ]
        p = float(np.log2(np.linalg.norm(q[0] - q[1]) / np.linalg.norm(q[1] - q[2])))
        assert low < p < high, (scheme, p)


def test_triple_jump_and_mclachlan_reach_order_4_on_smooth_controls():
    system = SYSTEMS["snakeboard"]
    # three maneuvers, as test_composition_orders: its program of the reference solutions is reused
    batch = maneuvers(system, 3, seed=14)
    for scheme in ("triple_jump", "mclachlan5"):
        errs = _terminal_errors(system, lj.RDP(order=4, scheme=scheme), batch, 2.0, (16, 32, 64))
        assert abs(fitted_order([1 / 8, 1 / 16, 1 / 32], errs) - 4) < 0.3, (scheme, errs)


@eqx.filter_jit  # one program, not op by op
def _substep_residuals(sb, ctl, q, hs_, ts):
    """(21) and (23) rebuilt from the substep configurations ``q`` (steps ``hs_`` at times ``ts``):
    the vertical and horizontal residuals, and the momenta ``mu``."""
    dl_du, mu, jump = discrete_momenta(sb, q, hs_, 0.5)
    e = jax.vmap(sb.e1)(q[1:-1, 4])
    vertical = jnp.sum(jump * e, axis=1)
    f = jax.vmap(ctl)(jnp.asarray(ts))
    f_a = 0.5 * (f[:-1] + f[1:])
    # horizontal (23) for the rotor, d_r l = 0: I (u + xi1) jumps by h_{k-1}/2 f_{k-1+a} + h_k/2 f_{k+a}
    a_k = jax.vmap(sb.connection)(q[1:-1, 3:])
    horizontal = (
        dl_du[1:, 0]
        - dl_du[:-1, 0]
        - 0.5 * (hs_[:-1] * f_a[:-1, 0] + hs_[1:] * f_a[1:, 0])
        - jnp.einsum("ki,ki->k", a_k[:, :, 0], jump)
    )
    return vertical, horizontal, mu


def test_substeps_satisfy_the_discrete_equations():
    """Every substep of a composition is an RDP step: (21) and (23), rebuilt from the substep
    configurations with each substep's own (possibly negative) h, hold to round-off, and the
    constraints hold at every node."""
    sb = SYSTEMS["snakeboard"]
    q0, qdot0, ctl = index(maneuvers(sb, 1, seed=15), 0)
    weights = lj.RDP(order=6).weights
    h, n_macro = 0.2, 20
    base = lj.RDP()
    hs = np.tile(np.asarray(weights) * h, n_macro)
    ts = np.concatenate([[0.0], np.cumsum(hs)])

    def run():
        state = base.init(sb, h, q0, qdot0, None)

        def step(state, x):
            hi, ti = x
            state, info = base.step(sb, hi, state, jnp.stack([ctl(ti), ctl(ti + hi)]))
            return state, base.momenta(sb, state)[0]

        return jax.lax.scan(step, state, (jnp.asarray(hs), jnp.asarray(ts[:-1])))[1]

    q = np.concatenate([np.asarray(q0)[None], np.asarray(jax.jit(run)())])  # on the host
    residuals = _substep_residuals(sb, ctl, q, jnp.asarray(hs, hs.dtype), jnp.asarray(ts, ts.dtype))
    vertical, horizontal, mu = (np.asarray(x) for x in residuals)
    scale = float(np.max(np.abs(mu)))
    assert np.any(hs < 0)
    assert float(np.max(np.abs(vertical))) < 1e-13 * scale / h
    assert float(np.max(np.abs(horizontal))) < 1e-13 * scale / h
    traj = lj.simulate(sb, q0, qdot0, ctl, t_final=h * n_macro, n_steps=n_macro, integrator=lj.RDP(order=6))
    np.testing.assert_allclose(traj.q, q[:: len(weights)], atol=1e-13)
    residual, qdot, step_residual = (
        np.asarray(x) for x in (traj.constraint_residual, traj.qdot, traj.step_residual)
    )
    assert float(np.max(residual)) < 1e-14 * float(np.max(np.abs(qdot)))
    assert float(np.max(step_residual)) < 1e-14


@pytest.mark.parametrize("name", list(SYSTEMS))
def test_node_velocities_from_momenta(name):
    """Trajectory.qdot is read from the carried momenta: at order 2 it is second-order accurate
    against the reference velocity, and the energy balance E - E0 - W converges at order 2."""
    system = SYSTEMS[name]
    batch = maneuvers(system, 1, seed=16)
    q0, qdot0, ctl = index(batch, 0)
    ns = (100, 200, 400)
    runs = simulate_ns(system, lj.RDP(), batch, 4.0, ns)  # one program for the three step counts
    # the samples t = 0, 1, ..., 4 s are nodes of every run: one reference for the three
    ref = np.asarray(lj.reference(system, q0, qdot0, ctl, runs[ns[0]].t[0, :: ns[0] // 4]).qdot)
    errs, balance = [], []
    for n in ns:
        assert not bool(np.any(runs[n].failed))
        errs.append(float(np.max(np.abs(runs[n].qdot[0, :: n // 4] - ref))))
        balance.append(float(np.max(np.abs(runs[n].energy_balance))))
    assert abs(fitted_order([1, 0.5, 0.25], errs) - 2) < 0.15, errs
    assert abs(fitted_order([1, 0.5, 0.25], balance) - 2) < 0.15, balance


@pytest.mark.parametrize("name", list(SYSTEMS))
def test_energy_bounded_for_every_order(name):
    """10^5 unforced steps (free rolling, no steering: the energy is conserved exactly): the
    energy error with velocities from the momenta stays bounded (no linear drift) at every
    order, and far below what differenced velocities gave."""
    system = SYSTEMS[name]
    if name == "car":
        q0 = jnp.array([0.0, 0.0, 0.1, 0.0, 0.4])
        qdot0 = system.qdot_from_velocities(q0, jnp.array([3.0]), jnp.zeros(2))
    else:
        q0 = jnp.array([0.0, 0.0, 0.3, 0.0, 0.5])
        qdot0 = system.qdot_from_velocities(q0, jnp.array([1.0, 0.0, 0.4]), jnp.zeros(2))
    for order in (2, 4, 6):
        traj = lj.simulate(
            system, q0, qdot0, None, t_final=5000.0, n_steps=100_000, integrator=lj.RDP(order=order), save=100
        )
        energy = np.asarray(traj.energy)
        err = np.abs(energy - energy[0])
        first, second = err[: err.size // 2].max(), err[err.size // 2 :].max()
        print(name, order, first, second)
        assert not bool(traj.failed)
        assert second < 1.5 * first + 1e-13, (first, second)
        assert err.max() < 1e-6 * float(energy[0])


def test_gradient_through_order_6_matches_central_differences():
    sb = SYSTEMS["snakeboard"]
    q0, qdot0, ctl = index(maneuvers(sb, 1, seed=17), 0)

    @jax.jit
    def loss(amplitude):
        c = lj.Sinusoids(amplitude, ctl.frequency, ctl.phase)
        q = lj.simulate(
            sb,
            q0,
            qdot0,
            c,
            t_final=3.0,
            n_steps=30,
            integrator=lj.RDP(order=6),
            save="final",
            diagnostics=False,
        ).q
        return jnp.sum((q[-1, :3] - jnp.array([0.5, -0.3, 1.0])) ** 2)

    x = ctl.amplitude
    grad = np.asarray(jax.grad(loss)(x)).ravel()
    eps = 1e-6
    fd = []
    x = np.asarray(x)  # the differences' points on the host (op by op, JAX compiles each operation)
    for i in range(x.size):
        e = np.zeros(x.size)
        e[i] = eps
        e = e.reshape(x.shape)
        fd.append((float(loss(x + e)) - float(loss(x - e))) / (2 * eps))
    np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-5 * np.abs(fd).max())


def test_vmap_equals_loop_and_float32_keeps_float32():
    sb = SYSTEMS["snakeboard"]
    batch = maneuvers(sb, 4, seed=18)
    run = jax.jit(  # q alone is read: no diagnostics
        lambda a, b, c: (
            lj.simulate(sb, a, b, c, t_final=2.0, n_steps=20, integrator=lj.RDP(order=6), diagnostics=False).q
        )
    )
    batched = np.asarray(jax.vmap(run)(*batch))
    for i in range(4):
        np.testing.assert_allclose(batched[i], run(*index(batch, i)), rtol=1e-13, atol=1e-13)
    q0, qdot0, ctl = jax.tree_util.tree_map(lambda x: x.astype(jnp.float32), index(batch, 0))
    traj = lj.simulate(sb, q0, qdot0, ctl, t_final=2.0, n_steps=20, integrator=lj.RDP(order=6))
    assert traj.q.dtype == jnp.float32 and traj.qdot.dtype == jnp.float32 and traj.energy.dtype == jnp.float32
    np.testing.assert_allclose(traj.q, batched[0], atol=1e-4)


def test_bad_order_settings_name_the_argument():
    with pytest.raises(ValueError, match="'order'"):
        lj.RDP(order=3)
    with pytest.raises(ValueError, match="'order'"):
        lj.RDP(order=4, alpha=0.0)
    with pytest.raises(ValueError, match="'scheme'"):
        lj.RDP(order=4, scheme="nonexistent")
    with pytest.raises(ValueError, match="'scheme'"):
        lj.RDP(order=4, scheme="kahan_li9")
    with pytest.raises(ValueError, match="'scheme'"):
        lj.RDP(scheme="suzuki5")
    assert lj.RDP().order == 2 and lj.RDP(alpha=0.0).order == 1
    assert lj.RDP(order=4).order == 4 and lj.RDP(order=6).scheme == "least_error11"
    assert lj.RDP(order=8).scheme == "kahan_li17" and len(lj.RDP(order=8).weights) == 17
    assert lj.RDP(order=6).control_nodes[0] == 0.0 and lj.RDP(order=6).control_nodes[-1] == 1.0
