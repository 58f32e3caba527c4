"""simulate: batching, compilation, gradients, dtypes, save options, errors, failure reporting.

(That the closed-form kernels equal the general Newton step is tests/test_closed_form.py.)
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import code, index, maneuvers, simulate_batch, systems

import ldap_jax as lj

SYSTEMS = systems()


@eqx.filter_jit
def _run(system, q0, qdot0, ctl):
    return lj.simulate(system, q0, qdot0, ctl, t_final=3.0, n_steps=60)


@pytest.mark.parametrize("name", list(SYSTEMS))
def test_vmap_equals_loop(name):
    system = SYSTEMS[name]
    man = maneuvers(system, 16, seed=2)
    batched = simulate_batch(system, lj.RDP(), man, 3.0, 60)
    q, qdot, energy = (np.asarray(x) for x in (batched.q, batched.qdot, batched.energy))  # host copies
    for i in range(16):
        single = _run(system, *index(man, i))
        np.testing.assert_allclose(q[i], single.q, rtol=1e-13, atol=1e-13)
        np.testing.assert_allclose(qdot[i], single.qdot, rtol=1e-13, atol=1e-13)
        np.testing.assert_allclose(energy[i], single.energy, rtol=1e-13, atol=1e-13)


def test_vmap_over_model_parameters():
    ms = jnp.array([0.8, 1.0, 1.3])
    q0, qdot0, ctl = index(maneuvers(SYSTEMS["snakeboard"], 1, seed=4), 0)

    def run(m):
        return lj.simulate(lj.Snakeboard(m=m), q0, qdot0, ctl, t_final=2.0, n_steps=50).q[-1]

    batched = np.asarray(jax.vmap(run)(ms))
    for i, m in enumerate(ms):
        np.testing.assert_allclose(batched[i], run(m), rtol=1e-13, atol=1e-14)


class _CountingRK4(lj.RK4):
    def init(self, system, h, q0, qdot0, c0):
        _CountingRK4.traces += 1
        return super().init(system, h, q0, qdot0, c0)


def test_no_recompilation_with_new_values():
    _CountingRK4.traces = 0
    integrator = _CountingRK4()
    for seed, m, t_final in ((0, 1.0, 2.0), (1, 1.3, 3.5)):
        sb = lj.Snakeboard(m=m)
        q0, qdot0, ctl = index(maneuvers(sb, 1, seed=seed), 0)
        lj.simulate(sb, q0, qdot0, ctl, t_final=t_final, n_steps=40, integrator=integrator)
    assert _CountingRK4.traces == 1


class _StepCountingRK4(lj.RK4):
    def step(self, system, h, state, c):
        _StepCountingRK4.traces += 1
        return super().step(system, h, state, c)


def test_step_is_traced_once_across_programs():
    """Programs that differ in their step count, save policy, batching or differentiation trace the
    integrator's step once (:func:`ldap_jax._tracing.traced_once`), and each gives its own answer."""
    _StepCountingRK4.traces = 0
    sb = SYSTEMS["snakeboard"]
    integrator = _StepCountingRK4()
    q0, qdot0, ctl = index(maneuvers(sb, 2, seed=3), 0)

    def final(n, **kw):
        q = lj.simulate(sb, q0, qdot0, ctl, t_final=2.0, n_steps=n, integrator=integrator, **kw).q
        return np.asarray(q)[-1]

    q20, q40, q40_final = final(20), final(40), final(40, save="final")
    assert _StepCountingRK4.traces == 1
    np.testing.assert_allclose(q40, q40_final, rtol=1e-13, atol=1e-13)
    batch = maneuvers(sb, 2, seed=3)
    q20s = jax.vmap(
        lambda a, b, c: lj.simulate(sb, a, b, c, t_final=2.0, n_steps=20, integrator=integrator).q[-1]
    )(*batch)
    np.testing.assert_allclose(np.asarray(q20s)[0], q20, rtol=1e-13, atol=1e-13)
    ref = final(320)
    err20, err40 = (float(np.linalg.norm(q - ref)) for q in (q20, q40))
    assert 0 < 8 * err40 < err20, (err20, err40)  # each program integrates with its own step (RK4)
    jax.grad(
        lambda a: lj.simulate(
            sb,
            q0,
            qdot0,
            eqx.tree_at(lambda c: c.amplitude, ctl, a),
            t_final=2.0,
            n_steps=30,
            integrator=integrator,
        ).q[-1, 0]
    )(ctl.amplitude)
    assert _StepCountingRK4.traces == 1


def test_traced_once_keeps_constants_concrete():
    """What is concrete at the call stays concrete inside (code may branch on it) and is part of the
    key; traced values are the inner program's arguments; an eager call runs as it is."""
    from ldap_jax._numerics import plain
    from ldap_jax._tracing import traced_once

    seen = []

    @traced_once
    def scale(p, x):
        seen.append(isinstance(p["a"], jax.core.Tracer))
        return x * p["a"] + p["b"]

    two, three = {"a": jnp.asarray(2.0), "b": 1.0}, {"a": jnp.asarray(3.0), "b": 1.0}
    out = jax.jit(lambda x: (scale(two, x), scale(two, 2 * x), scale(three, x)))(jnp.asarray(1.0))
    assert [float(v) for v in out] == [3.0, 5.0, 4.0]
    assert seen == [False, False]  # one trace per constant: 2.0 (twice), 3.0
    with plain():  # the kernels trace differently inside plain(): a new key
        jax.jit(lambda x: scale(two, x))(jnp.asarray(1.0))
    assert seen == [False, False, False]
    assert float(jax.grad(lambda x: scale({"a": x, "b": 0.0}, x))(jnp.asarray(3.0))) == 6.0
    assert seen[-1] is True  # a traced parameter is an argument of the inner program
    assert float(scale(two, 4.0)) == 9.0 and seen[-1] is False  # eager: no inner program


def _fd_check(loss, x, eps=1e-6, rtol=1e-5):
    """``jax.grad(loss)(x)`` against central differences (one compiled value-and-gradient)."""
    value_and_grad = jax.jit(jax.value_and_grad(loss))
    grad = np.asarray(value_and_grad(x)[1])
    flat = np.asarray(x).ravel()
    fd = np.zeros_like(flat)
    for i in range(flat.size):
        e = np.zeros_like(flat)
        e[i] = eps
        fd[i] = (
            float(value_and_grad(jnp.asarray((flat + e).reshape(x.shape), flat.dtype))[0])
            - float(value_and_grad(jnp.asarray((flat - e).reshape(x.shape), flat.dtype))[0])
        ) / (2 * eps)
    np.testing.assert_allclose(grad.ravel(), fd, rtol=rtol, atol=rtol * np.abs(fd).max())
    return grad


@pytest.mark.parametrize("name", list(SYSTEMS))
@pytest.mark.parametrize(
    "integrator", [lj.RDP(), lj.RDP(alpha=0.0, retraction="cayley"), lj.RK4()], ids=["rdp", "rdp0cay", "rk4"]
)
def test_gradient_wrt_control_amplitudes_matches_finite_differences(name, integrator):
    system = SYSTEMS[name]
    q0, qdot0, ctl = index(maneuvers(system, 1, seed=6), 0)
    target = jnp.array([0.5, -0.3, 1.0])

    def loss(amplitude):
        c = lj.Sinusoids(amplitude=amplitude, frequency=ctl.frequency, phase=ctl.phase)
        traj = lj.simulate(
            system, q0, qdot0, c, t_final=4.0, n_steps=200, integrator=integrator, check_constraints=False
        )
        return jnp.sum((traj.q[-1, :3] - target) ** 2)

    grad = _fd_check(loss, ctl.amplitude)
    assert np.abs(grad).max() > 1e-6


@pytest.mark.parametrize("name", list(SYSTEMS))
def test_gradient_wrt_initial_state_and_parameters(name):
    """d/dx0 (a pure translation of the start) and d/dm (the mass, through the whole rollout) of
    |q_N|^2, in one loss of (x0, m)."""
    system = SYSTEMS[name]
    q0, qdot0, ctl = index(maneuvers(system, 1, seed=8), 0)

    def loss(p):
        sys_ = eqx.tree_at(lambda s: s.m, system, p[1])
        q = lj.simulate(
            sys_, q0.at[0].set(p[0]), qdot0, ctl, t_final=3.0, n_steps=150, check_constraints=False
        ).q
        return jnp.sum(q[-1] ** 2)

    grad = _fd_check(loss, np.array([np.asarray(q0)[0], np.asarray(system.m)]))
    assert abs(grad[1]) > 1e-8


@pytest.mark.parametrize("name", list(SYSTEMS))
def test_saved_diagnostics_keep_their_derivatives_under_a_stride(name):
    """The nodes inside a stride (or before save="final") are observed for the diagnostics' tests
    without a derivative, and the saved node again from its state with one: the gradient of each
    saved field (configuration, velocity, energy, work, momentum, constraint residual) with
    respect to the controls and the initial state equals the one read from save="all" at the same
    node."""
    system = SYSTEMS[name]
    q0, qdot0, ctl = index(maneuvers(system, 1, seed=17), 0)
    full = lj.simulate(system, q0, qdot0, ctl, t_final=2.0, n_steps=24, check_constraints=False)
    names = ("q", "qdot", "energy", "work", "momentum", "constraint_residual")
    fields = [f for f in names if getattr(full, f).size]
    assert len(fields) >= 5  # the car has no momentum

    def read(save, node, args):
        amplitude, x0 = args
        c = lj.Sinusoids(amplitude=amplitude, frequency=ctl.frequency, phase=ctl.phase)
        traj = lj.simulate(
            system, q0.at[0].set(x0), qdot0, c, t_final=2.0, n_steps=24, save=save, check_constraints=False
        )
        return jnp.concatenate([jnp.ravel(getattr(traj, f)[node]) for f in fields])

    def jac(save, node):  # one row per output, columns: the amplitudes, then x0
        j = jax.jit(jax.jacrev(lambda a: read(save, node, a)))((ctl.amplitude, q0[0]))
        return np.concatenate([np.asarray(j[0]).reshape(len(j[1]), -1), np.asarray(j[1])[:, None]], axis=1)

    rows = np.repeat(fields, [np.size(getattr(full, f)[0]) for f in fields])
    for got, want in ((jac("final", -1), jac("all", 24)), (jac(8, 2), jac("all", 16))):
        for row, g, w in zip(rows, got, want):
            scale = np.abs(w).max()
            assert scale > 0 or row == "constraint_residual", row  # ~1e-16: safe_norm's derivative 0
            np.testing.assert_allclose(g, w, rtol=0, atol=1e-12 * max(scale, 1.0), err_msg=row)


def test_bad_checkpoint_policy_is_named():
    # (that every policy gives the same gradient, on the kernel and the Newton step, is
    # tests/test_closed_form.py::test_gradients_match)
    sb = SYSTEMS["snakeboard"]
    q0, qdot0, ctl = index(maneuvers(sb, 1, seed=9), 0)
    for bad in ("binomial", -3, 2.5):
        with pytest.raises(ValueError, match="'checkpoint'"):
            lj.simulate(sb, q0, qdot0, ctl, t_final=5.0, n_steps=300, checkpoint=bad)


@pytest.mark.parametrize("name", list(SYSTEMS))
def test_float32_stays_float32(name):
    """float32 in, float32 out (RK4 here; the RDP kernels and Newton step in float32 are
    tests/test_closed_form.py::test_kernel_equals_newton_float32, RDP(order=6) tests/test_order.py)."""
    integrator = lj.RK4()
    system = SYSTEMS[name]
    q0, qdot0, ctl = index(maneuvers(system, 1, seed=1), 0)
    ctl32 = jax.tree_util.tree_map(lambda x: x.astype(jnp.float32), ctl)
    traj = lj.simulate(
        system,
        q0.astype(jnp.float32),
        qdot0.astype(jnp.float32),
        ctl32,
        t_final=2.0,
        n_steps=100,
        integrator=integrator,
    )
    for leaf in (
        traj.t,
        traj.q,
        traj.qdot,
        traj.energy,
        traj.work,
        traj.momentum,
        traj.constraint_residual,
        traj.step_residual,
    ):
        assert leaf.dtype == jnp.float32
    ref = lj.simulate(system, q0, qdot0, ctl, t_final=2.0, n_steps=100, integrator=integrator)
    np.testing.assert_allclose(traj.q, ref.q, rtol=1e-4, atol=1e-4)
    assert not bool(traj.failed)


def test_sampled_controls_reproduce_rdp_on_the_nodes():
    """RDP reads controls only at the nodes: Sampled(values at t_k) gives the same trajectory."""
    # the controls' values in one compiled program per controls' structure (op by op, each
    # operation compiled alone); the times on the host
    values = jax.jit(lambda c, t: jax.vmap(c)(t))
    for system in SYSTEMS.values():
        q0, qdot0, ctl = index(maneuvers(system, 1, seed=12), 0)
        n, t_final = 200, 4.0
        ts = np.linspace(0.0, t_final, n + 1)
        sampled = lj.Sampled(values=values(ctl, ts), t_final=t_final)
        a = lj.simulate(system, q0, qdot0, ctl, t_final=t_final, n_steps=n)
        b = lj.simulate(system, q0, qdot0, sampled, t_final=t_final, n_steps=n)
        np.testing.assert_allclose(a.q, b.q, rtol=1e-13, atol=1e-13)
        t7, t8 = ts[7], ts[8]
        at_nodes = np.asarray(values(ctl, np.array([t7, t8])))
        np.testing.assert_allclose(
            values(sampled, np.array([t7 + 0.3 * (t8 - t7)]))[0],
            0.7 * at_nodes[0] + 0.3 * at_nodes[1],
            rtol=1e-12,
        )


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_sinusoid_sampler_equals_the_controls_at_the_fractions(dtype):
    """The rollouts' sampler (angle addition, one sincos of the step's angles) equals the controls
    evaluated at ``t + f h``, to a few ulps of the amplitudes' sum, for 3 channels x 4 terms, one
    term, and no channels; so does the node sampler (one sine per term, the order-2 rollouts'),
    at ``t``."""
    rng = np.random.default_rng(5)
    eps = float(jnp.finfo(dtype).eps)
    fractions = jnp.asarray([0.0, 0.5, 0.2113, 1.0], dtype)

    @jax.jit  # one program per shape (op by op, each operation would compile alone)
    def both(ctl, t, h):
        return ctl.sampler(h, fractions)(t), jax.vmap(ctl)(t + h * fractions), ctl.node_sampler()(t), ctl(t)

    for n_ch, n_terms in ((3, 4), (2, 1), (0, 2)):
        a, w, p = (rng.uniform(-2, 2, (n_ch, n_terms)).astype(dtype) for _ in range(3))
        a, w3, p = (jnp.asarray(x, dtype) for x in (a, 3 * w, p))  # 3 * w on the host, in dtype
        ctl = lj.Sinusoids(amplitude=a, frequency=w3, phase=p)
        for t, h in ((0.0, 0.1), (7.3, 0.013), (95.0, 0.5)):
            got, want, node, at_t = both(ctl, jnp.asarray(t, dtype), jnp.asarray(h, dtype))
            assert got.shape == want.shape == (4, n_ch) and got.dtype == dtype
            # the angles w (t + f h) differ by rounding from w t + w f h: |w| (|t| + h) eps each
            amplitudes = float(jnp.sum(jnp.abs(a), initial=0.0))
            tol = 8 * eps * (1 + 6 * (float(t) + float(h))) * amplitudes
            np.testing.assert_allclose(got, want, rtol=0, atol=tol)
            # the same angles w t + p: the sines' rounding and the sum's order only
            assert node.shape == at_t.shape == (n_ch,) and node.dtype == dtype
            np.testing.assert_allclose(node, at_t, rtol=0, atol=4 * eps * amplitudes)


def test_save_options_select_the_same_nodes():
    """save="final", a stride and node indices return exactly those nodes of save="all";
    diagnostics=False keeps the positions and drops the diagnostics."""
    car = SYSTEMS["car"]
    q0, qdot0, ctl = index(maneuvers(car, 1, seed=14), 0)
    kw = dict(t_final=3.0, n_steps=60)
    full = lj.simulate(car, q0, qdot0, ctl, **kw)
    assert full.q.shape == (61, 5) and full.t.shape == (61,)
    final = lj.simulate(car, q0, qdot0, ctl, save="final", **kw)
    full_t, full_q, full_energy = np.asarray(full.t), np.asarray(full.q), np.asarray(full.energy)
    np.testing.assert_array_equal(final.q, full_q[-1:])
    np.testing.assert_array_equal(final.work, np.asarray(full.work)[-1:])
    strided = lj.simulate(car, q0, qdot0, ctl, save=20, **kw)
    np.testing.assert_array_equal(strided.t, full_t[::20])
    np.testing.assert_array_equal(strided.q, full_q[::20])
    np.testing.assert_array_equal(strided.energy, full_energy[::20])
    picked = lj.simulate(car, q0, qdot0, ctl, save=[0, 7, 60], **kw)
    np.testing.assert_array_equal(picked.q, full_q[np.array([0, 7, 60])])
    lean = lj.simulate(car, q0, qdot0, ctl, save=20, diagnostics=False, **kw)
    np.testing.assert_array_equal(lean.q, strided.q)
    assert lean.energy is None and lean.work is None and lean.step_residual is None
    with pytest.raises(ValueError, match="energy_balance"):
        lean.energy_balance  # noqa: B018
    for bad in (7, 0, "some", [3, 2], [61]):
        with pytest.raises(ValueError, match="'save'"):
            lj.simulate(car, q0, qdot0, ctl, save=bad, **kw)


@pytest.mark.parametrize("name", list(SYSTEMS))
@pytest.mark.parametrize("make", [lj.RDP, lambda: lj.RDP(order=4), lj.RK4], ids=["RDP2", "RDP4", "RK4"])
def test_node_diagnostics_equal_the_formulas(name, make):
    """The default call emits each node's diagnostics as it observes them and carries only the
    node's power (for the work's trapezoid). They equal, to 1e-12 at every saved node: the
    formulas on the saved ``(q, qdot)`` (energy, momentum, constraint residual, and the work as
    the trapezoidal sum of ``<f(t_k), rdot_k>``), and the observations that a feedback run of the
    same controls carries from step to step (the loop that keeps the whole observation)."""
    system = SYSTEMS[name]
    q0, qdot0, ctl = index(maneuvers(system, 1, seed=21), 0)
    kw = dict(t_final=4.0, n_steps=80, integrator=make())
    traj = lj.simulate(system, q0, qdot0, ctl, **kw)
    assert not bool(traj.failed)
    q, qdot = traj.q, traj.qdot
    energy = jax.vmap(system.energy)(q, qdot)
    scale = 1.0 + float(jnp.max(jnp.abs(energy)))
    np.testing.assert_allclose(traj.energy, energy, rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(traj.momentum, jax.vmap(system.momentum)(q, qdot), rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(
        traj.constraint_residual, jax.vmap(system.constraint_residual)(q, qdot), atol=1e-12
    )
    power = jax.vmap(lambda t, v: system.power(system.inputs(ctl(t))[0], v[3:]))(traj.t, qdot)
    h = traj.t[1] - traj.t[0]
    work = np.concatenate([[0.0], np.cumsum(0.5 * h * (power[1:] + power[:-1]))])
    np.testing.assert_allclose(traj.work, work, rtol=0, atol=1e-12 * scale)
    carried = lj.simulate(system, q0, qdot0, lj.Policy(lambda t, q, qd: ctl(t), system.n_controls), **kw)
    for field in ("q", "qdot", "energy", "work", "momentum", "constraint_residual"):
        np.testing.assert_allclose(getattr(traj, field), getattr(carried, field), rtol=0, atol=1e-12 * scale)


def _inner_call_sites(jaxpr, found=None) -> dict:
    """How many call sites each traced-once integrator function (``ldap_jax._tracing``) has in a
    program, keyed by the function's (cached, shared) jaxpr."""
    found = {} if found is None else found
    for eqn in jaxpr.eqns:
        if eqn.params.get("name") == "inner" and "jaxpr" in eqn.params:
            key = id(eqn.params["jaxpr"].jaxpr)
            found[key] = found.get(key, 0) + 1
        for value in eqn.params.values():
            for v in value if isinstance(value, (tuple, list)) else (value,):
                if hasattr(v, "jaxpr") and hasattr(v.jaxpr, "eqns"):
                    _inner_call_sites(v.jaxpr, found)
                elif hasattr(v, "eqns"):
                    _inner_call_sites(v, found)
    return found


def test_every_save_option_has_the_step_once():
    """A stride or save="final" puts the step into the program as often as save="all" does (once):
    the last step of a segment is not a second copy of the step (XLA compiled it twice; final-node
    programs and their gradients then compiled 1.2-1.7x as long). The observation is there twice
    (node 0, the loop), and with diagnostics and a stride a third time: the segment's last node is
    observed again from its state, with its derivative (the loop's observation serves the tests
    alone, its derivative cut)."""
    sb = SYSTEMS["snakeboard"]
    q0, qdot0, ctl = index(maneuvers(sb, 1, seed=14), 0)
    kw = dict(t_final=1.0, n_steps=12)
    for integrator in (lj.RDP(), lj.RK4()):
        counts = {}
        for save in ("all", "final", 4):
            for diagnostics in (True, False):
                opts = dict(integrator=integrator, save=save, diagnostics=diagnostics, **kw)
                jaxpr = jax.make_jaxpr(lambda q0: lj.simulate(sb, q0, qdot0, ctl, **opts).q)(q0)
                counts[save, diagnostics] = sorted(_inner_call_sites(jaxpr.jaxpr).values())
        # the initial state, the divergence test's mobility (with diagnostics) and the step once
        # each; the observation twice (node 0, the loop)
        assert counts["all", True] == [1, 1, 1, 2], counts
        assert counts["all", False] == [1, 1, 2], counts
        for save in ("final", 4):
            assert counts[save, False] == counts["all", False], counts
            assert counts[save, True] == [1, 1, 1, 3], counts


SINGULAR = lj.Sinusoids(
    amplitude=jnp.array([[0.05], [0.02]]),
    frequency=jnp.array([[1.0], [0.0]]),
    phase=jnp.array([[0.0], [np.pi / 2]]),
)


def test_snakeboard_singularity_is_reported():
    """A constant steering torque drives phi through pi/2: the failure is flagged, not NaN-silent."""
    sb = SYSTEMS["snakeboard"]
    q0 = jnp.zeros(5)
    for integrator in (lj.RDP(), lj.RK4()):
        traj = lj.simulate(sb, q0, jnp.zeros(5), SINGULAR, t_final=10.0, n_steps=1000, integrator=integrator)
        assert traj.result == lj.RESULTS.singular and bool(traj.failed)
        assert int(traj.result._value) == 2
        k = int(traj.failure_index)
        assert 0 < k < 1000
        # nodes up to the failed step's start are finite, every later node is NaN
        q, energy = np.asarray(traj.q), np.asarray(traj.energy)
        assert np.all(np.isfinite(q[: k + 1])) and np.all(np.isnan(q[k + 1 :]))
        assert np.all(np.isnan(energy[k + 1 :]))
        assert abs(float(q[k, 4])) > 1.4
        with pytest.raises(Exception, match="singular configuration"):
            lj.simulate(
                sb, q0, jnp.zeros(5), SINGULAR, t_final=10.0, n_steps=1000, integrator=integrator, throw=True
            )


def test_failure_does_not_poison_gradients_of_other_batch_members():
    sb = SYSTEMS["snakeboard"]
    q0 = jnp.zeros(5)
    amp = jnp.array([[[0.05], [0.0]], [[0.05], [0.02]]])  # second: constant torque -> singular
    freq = jnp.array([[[1.0], [0.0]], [[1.0], [0.0]]])
    phase = jnp.array([[[0.0], [0.0]], [[0.0], [np.pi / 2]]])

    def final_x(a, f, p):
        traj = lj.simulate(sb, q0, jnp.zeros(5), lj.Sinusoids(a, f, p), t_final=10.0, n_steps=500)
        return traj.q[-1, 0], traj.failed

    x, failed = (np.asarray(y) for y in jax.jit(jax.vmap(final_x))(amp, freq, phase))
    assert not bool(failed[0]) and bool(failed[1]) and np.isfinite(float(x[0])) and np.isnan(float(x[1]))
    g = jax.jit(jax.grad(lambda a: jax.vmap(final_x)(a, freq, phase)[0][0]))(amp)
    # the good member's gradient is finite (here exactly 0: without steering the board cannot move,
    # whatever the rotor does); a loss that ignores the failed member gives its parameters an exact
    # zero (nothing of it is read), and one that reads it gives them NaN (never a silent zero)
    g = np.asarray(g)
    assert np.all(np.isfinite(g[0]))
    assert np.all(g[1] == 0)
    g = np.asarray(jax.jit(jax.grad(lambda a: jnp.sum(jax.vmap(final_x)(a, freq, phase)[0])))(amp))
    assert np.all(np.isfinite(g[0])) and np.all(np.isnan(g[1]))


def test_documented_sequence_inputs():
    """Where the library documents Python sequences and numbers, they work like arrays: q0/qdot0
    as lists ("lists and integer arrays are converted"), reference times as a list ("or just
    [t_final]"), parameters as Python numbers; a string is refused by name."""
    car = SYSTEMS["car"]
    q0 = jnp.array([0.0, 0.0, 0.3, 0.0, 0.1])
    qdot0 = car.qdot_from_velocities(q0, jnp.array([2.0]), jnp.zeros(2))
    a = lj.simulate(
        car,
        [float(x) for x in np.asarray(q0)],
        [float(x) for x in np.asarray(qdot0)],
        None,
        t_final=1.0,
        n_steps=10,
    )
    b = lj.simulate(car, q0, qdot0, None, t_final=1.0, n_steps=10)
    np.testing.assert_array_equal(a.q, b.q)
    np.testing.assert_array_equal(
        lj.reference(car, q0, qdot0, None, [1.0]).q, lj.reference(car, q0, qdot0, None, jnp.array([1.0])).q
    )
    assert lj.Car(m=2).m.dtype == jnp.float64 and float(lj.Snakeboard(l=1).l) == 1.0
    with pytest.raises(TypeError, match="physical parameter"):
        lj.Car(m="heavy")
    with pytest.raises(TypeError, match="'q0'"):
        lj.simulate(car, "zeros", qdot0, None, t_final=1.0, n_steps=10)


class TestBadInput:
    sb = SYSTEMS["snakeboard"]
    ctl = lj.Sinusoids(
        amplitude=jnp.array([[0.1], [0.0]]),
        frequency=jnp.array([[1.0], [1.0]]),
        phase=jnp.array([[0.0], [0.0]]),
    )

    def run(self, q0=None, qdot0=None, ctl=None, **kw):
        args = dict(t_final=1.0, n_steps=10)
        args.update(kw)
        return lj.simulate(
            self.sb,
            jnp.zeros(5) if q0 is None else q0,
            jnp.zeros(5) if qdot0 is None else qdot0,
            self.ctl if ctl is None else ctl,
            **args,
        )

    def test_shapes(self):
        with pytest.raises(ValueError, match="'q0'.*shape"):
            self.run(q0=jnp.zeros(4))
        with pytest.raises(ValueError, match="'qdot0'.*shape"):
            self.run(qdot0=jnp.zeros((2, 5)))
        with pytest.raises(ValueError, match="'controls'.*channels"):
            self.run(
                ctl=lj.Sinusoids(
                    amplitude=jnp.array([[0.1]]), frequency=jnp.array([[1.0]]), phase=jnp.array([[0.0]])
                )
            )
        with pytest.raises(ValueError, match="'amplitude'.*shape"):
            lj.Sinusoids(
                amplitude=jnp.array([0.1, 0.2]), frequency=jnp.array([1.0, 1.0]), phase=jnp.array([0.0, 0.0])
            )
        with pytest.raises(ValueError, match="shapes differ"):
            lj.Sinusoids(
                amplitude=jnp.array([[0.1, 0.2]]), frequency=jnp.array([[1.0]]), phase=jnp.array([[0.0]])
            )
        with pytest.raises(TypeError, match="'controls'"):
            self.run(ctl=lambda t: jnp.zeros(2))
        with pytest.raises(TypeError, match="'integrator'"):
            self.run(integrator="rdp")

    def test_dtype(self):
        # integers are converted to the default float; other dtypes are refused by name
        np.testing.assert_array_equal(self.run(q0=jnp.zeros(5, dtype=jnp.int32)).q, self.run().q)
        with pytest.raises(ValueError, match="'q0'.*float32 or float64"):
            self.run(q0=jnp.zeros(5, dtype=jnp.float16))
        with pytest.raises(ValueError, match="'qdot0'.*float32 or float64"):
            self.run(qdot0=jnp.zeros(5, dtype=jnp.complex64))
        with pytest.raises(TypeError, match="'q0'"):
            self.run(q0="zeros")

    def test_settings(self):
        with pytest.raises(ValueError, match="'alpha'"):
            lj.RDP(alpha=1.5)
        with pytest.raises(ValueError, match="'alpha'"):
            lj.RDP(alpha=-0.1)
        with pytest.raises(ValueError, match="'retraction'"):
            lj.RDP(retraction="euler")
        with pytest.raises(ValueError, match="'solver'"):
            lj.RDP(solver="broyden")
        with pytest.raises(ValueError, match="'n_steps'"):
            self.run(n_steps=0)
        with pytest.raises(TypeError, match="'n_steps'"):
            self.run(n_steps=2.5)
        with pytest.raises(ValueError, match="'t_final'"):
            self.run(t_final=0.0)
        with pytest.raises(ValueError, match="'t_final'"):
            self.run(t_final=-1.0)
        with pytest.raises(ValueError, match="'q0' must be finite"):
            self.run(q0=jnp.full(5, jnp.nan))
        with pytest.raises(ValueError, match="'divergence'"):
            self.run(divergence=-1.0)

    def test_constraint_violating_qdot0(self):
        bad = jnp.array([0.0, 1.0, 0.0, 0.0, 0.0])  # sideways sliding
        with pytest.raises(ValueError, match="'qdot0' violates the constraints"):
            self.run(qdot0=bad)
        car = SYSTEMS["car"]
        with pytest.raises(ValueError, match="'qdot0' violates"):
            lj.simulate(
                car, jnp.zeros(5), jnp.array([1.0, 0.0, 0.0, 0.0, 0.0]), self.ctl, t_final=1.0, n_steps=5
            )
        # inside jit the values are traced: the run reports invalid_input (every node NaN), whose
        # message names qdot0, and throw=True raises it
        traj = jax.jit(lambda qd: self.run(qdot0=qd))(bad)
        assert traj.result == lj.RESULTS.invalid_input and int(traj.failure_index) == 0
        assert "qdot0" in lj.RESULTS[traj.result]
        assert bool(np.all(np.isnan(np.asarray(traj.q))))
        with pytest.raises(Exception, match="qdot0"):
            jax.jit(lambda qd: self.run(qdot0=qd, throw=True).q)(bad)
        # a vmapped batch fails only its bad member
        ok = jax.vmap(lambda qd: self.run(qdot0=qd))(np.stack([np.zeros(5), np.asarray(bad)]))
        np.testing.assert_array_equal(code(ok.result), [0, lj.RESULTS.invalid_input._value])
        assert bool(np.all(np.isfinite(np.asarray(ok.q)[0])))


def test_float32_without_x64_is_warned_by_name():
    """With float64 off, simulate and reference say they run in float32 (checked before any
    other input: the runs below stop at a bad setting, nothing compiles)."""
    car = lj.Car()
    z = jnp.zeros(5, jnp.float32)
    with jax.enable_x64(False):
        with pytest.warns(UserWarning, match="ldap_jax.simulate runs in float32"):
            with pytest.raises(ValueError, match="'n_steps'"):
                lj.simulate(car, z, z, None, t_final=1.0, n_steps=0)
        with pytest.warns(UserWarning, match="ldap_jax.reference runs in float32"):
            with pytest.raises(ValueError, match="'rtol'"):
                lj.reference(car, z, z, None, jnp.array([0.0, 1.0], jnp.float32), rtol=-1.0)


def test_mixed_dtypes_are_checked_in_the_runs_dtype():
    """``q0`` in float32 with ``qdot0`` in float64 runs in float64 (JAX's promotion), so the
    up-front constraint check is made there: ``qdot0`` built on the float64 pose violates the
    constraints at the float32-rounded one by 1e-8, a ``ValueError`` naming it (as for the other
    order), not a run of NaN nodes reported as ``invalid_input`` on traced values. (JAX's standard
    promotion, a user's default; the suite's strict promotion refuses mixed dtypes outright.)"""
    with jax.numpy_dtype_promotion("standard"):
        _mixed_dtypes()


def _mixed_dtypes():
    car = lj.Car()
    q0 = np.array([0.1, -0.2, 0.3, 0.0, 0.2])
    v0 = jax.device_put(np.array([5.0]))
    qdot0 = np.asarray(car.qdot_from_velocities(jax.device_put(q0), v0, np.zeros(2)))
    for a, b in ((q0.astype(np.float32), qdot0), (q0, qdot0.astype(np.float32))):
        with pytest.raises(ValueError, match="'qdot0' violates the constraints"):
            lj.simulate(car, a, b, t_final=1.0, n_steps=8, diagnostics=False)
    # on the constraints at the float32 pose, the run is float64 and succeeds
    q32 = q0.astype(np.float32)
    qdot0 = car.qdot_from_velocities(jax.device_put(q32.astype(np.float64)), jnp.array([5.0]), jnp.zeros(2))
    traj = lj.simulate(car, q32, qdot0, t_final=1.0, n_steps=8, diagnostics=False)
    assert traj.q.dtype == jnp.float64 and not bool(traj.failed)


def test_a_step_that_underflows_to_zero_is_refused():
    """``t_final - t0 > 0`` whose step ``(t_final - t0) / n_steps`` is 0 in the run's dtype: a
    ``ValueError`` naming ``t_final`` eagerly, ``invalid_input`` under ``jit``."""
    sb = SYSTEMS["snakeboard"]
    z = np.zeros(5)
    with pytest.raises(ValueError, match="'t_final' - 't0' .* gives a step of 0 in float64"):
        lj.simulate(sb, z, z, t_final=5e-324, n_steps=4, diagnostics=False)
    run = jax.jit(lambda tf: lj.simulate(sb, z, z, t_final=tf, n_steps=4, diagnostics=False).result)
    assert code(run(5e-324)) == code(lj.RESULTS.invalid_input)
    assert code(run(1e-300)) == code(lj.RESULTS.successful)


def test_residual_diagnostics_have_finite_derivatives_at_rest():
    """The step and constraint residuals are norms of quantities that vanish on a run at rest;
    their derivatives there are 0 in both modes (``sqrt``'s slope at 0 made them NaN)."""
    sb = SYSTEMS["snakeboard"]

    def loss(p):
        q0 = jnp.zeros(5).at[0].set(p[0])
        traj = lj.simulate(sb, q0, jnp.zeros(5), lj.Constant(jnp.stack([p[1], 0.0])), t_final=1.0, n_steps=4)
        return jnp.stack([jnp.sum(traj.constraint_residual), jnp.sum(traj.step_residual)])

    p = jnp.zeros(2)
    for jac in (jax.jacrev, jax.jacfwd):
        np.testing.assert_array_equal(np.asarray(jax.jit(jac(loss))(p)), np.zeros((2, 2)))


def test_float32_defaults_and_checks():
    """In float32 (float32 inputs, float64 on): ``lj.reference``'s default tolerances are 1e-6, not
    float64's 1e-11 (which spent ``max_steps`` and failed), and its solution is within float32's
    reach of the float64 one; the constraint check on ``qdot0`` rejects a car velocity 0.1% off its
    rolling constraint (its tolerance was 1e4 eps = 6.4e-3 there); ``lj.discretize`` with a
    float32 step takes float64 states and controls into its float32 dynamics; ``lc.solve``'s
    default tolerance on a float32 task is 1e-5 and a tighter one warns."""
    import warnings

    from ldap_jax import control as lc
    from ldap_jax._validation import cast_floats
    from ldap_jax.control._solve import _checked

    car = SYSTEMS["car"]
    q0 = np.array([0.1, -0.2, 0.3, 0.0, 0.2])
    qdot0 = np.asarray(
        car.qdot_from_velocities(jax.device_put(q0), jax.device_put(np.array([5.0])), np.zeros(2))
    )
    ctl = lj.Sinusoids(jnp.array([[0.3], [0.5]]), jnp.array([[3.0], [2.0]]), jnp.array([[0.0], [0.0]]))
    ts = np.array([0.0, 0.5, 1.0])
    exact = lj.reference(car, q0, qdot0, ctl, ts)
    # a float32 run: qdot0 built on the float32 pose (in float64 arithmetic, then rounded)
    q32 = q0.astype(np.float32)
    qd32 = np.asarray(
        car.qdot_from_velocities(jax.device_put(q32.astype(np.float64)), jnp.array([5.0]), jnp.zeros(2))
    ).astype(np.float32)
    ctl32 = cast_floats(ctl, jnp.float32)
    sol = lj.reference(car, q32, qd32, ctl32, ts.astype(np.float32))
    assert code(sol.result) == code(lj.RESULTS.successful) and sol.q.dtype == jnp.float32
    assert np.max(np.abs(np.asarray(sol.q, float) - np.asarray(exact.q))) < 1e-4
    bad = qd32.copy()
    bad[0] *= 1.001  # the rolling constraint broken by 0.1%
    with pytest.raises(ValueError, match="'qdot0' violates the constraints"):
        lj.simulate(car, q32, bad, ctl32, t_final=1.0, n_steps=4, diagnostics=False)
    dyn = lj.discretize(car, h=jnp.float32(0.1))
    assert dyn.init(q0, qdot0, np.zeros(2)).dtype == jnp.float32  # float64 inputs, float32 dynamics
    task = cast_floats(lc.parallel_park(n_steps=20), jnp.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert float(_checked(task, None, None, 1000, "base", 0.1, None)[0].tol) == pytest.approx(1e-5)
    with pytest.warns(UserWarning, match=r"KKT tolerance \(1e-08\) is below float32 round-off"):
        _checked(task, None, 1e-8, 1000, "base", 0.1, None)
