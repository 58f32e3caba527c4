"""The reference solver against an independent integration of the full Lagrange-d'Alembert DAE."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import STEERED_SLEIGH_LENGTH, compiled_programs, index, maneuvers, steered_sleigh, systems

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
    assert float(np.max(np.abs(np.asarray(a.q) - np.asarray(b.q)))) < 1e-9


def test_reference_shares_one_program_across_sample_counts_and_tolerances():
    """11, 13 and 2 samples (all padded to 32) and another tolerance run the program compiled for
    the first request; the samples the requests share agree to round-off (the solver's steps do
    not depend on where it samples), and the padding never shows in the result."""
    sb = SYSTEMS["snakeboard"]
    q0, qdot0, ctl = index(maneuvers(sb, 1, seed=22), 0)
    ts = jnp.linspace(0.0, 10.0, 11)
    # the sample times on the host (op by op, JAX compiles each operation)
    more = jnp.asarray(np.sort(np.concatenate([np.asarray(ts), [2.5, 7.5]])), ts.dtype)
    a = lj.reference(sb, q0, qdot0, ctl, ts)
    with compiled_programs() as names:
        b = lj.reference(sb, q0, qdot0, ctl, more)
        lj.reference(sb, q0, qdot0, ctl, ts, rtol=1e-12, atol=1e-12)
        ends = lj.reference(sb, q0, qdot0, ctl, jnp.asarray(np.asarray(ts)[[0, -1]], ts.dtype))
    assert "jit(_reference)" not in names, names
    assert a.q.shape == (11, 5) and b.q.shape == (13, 5) and b.t.shape == (13,) and ends.q.shape == (2, 5)
    np.testing.assert_allclose(ends.q, np.asarray(a.q)[[0, -1]], rtol=0, atol=1e-13)
    np.testing.assert_array_equal(b.t, more)
    shared = np.isin(np.asarray(more), np.asarray(ts))
    np.testing.assert_allclose(np.asarray(b.q)[shared], a.q, rtol=0, atol=1e-13)
    np.testing.assert_allclose(np.asarray(b.qdot)[shared], a.qdot, rtol=0, atol=1e-13)


def test_reference_program_has_no_host_callback():
    """The reference's program holds no host callback (diffrax's run-time checks of the save
    times are off while it is traced: the times are validated before), so JAX's persistent
    compilation cache keeps it and a new process does not compile it again; equinox's error mode
    is restored after tracing."""
    import equinox._errors as errors

    from ldap_jax import _reference

    sb = SYSTEMS["snakeboard"]
    q0, qdot0, ctl = index(maneuvers(sb, 1, seed=22), 0)
    ts = _reference._padded(jnp.linspace(0.0, 10.0, 11))
    mode = errors.EQX_ON_ERROR
    args = (sb, q0, qdot0, ctl, ts, jnp.asarray(0.0), jnp.asarray(1e-11), jnp.asarray(1e-11))
    text = _reference._reference.lower(*args, diffrax.Dopri8(), 4096, False).as_text()
    assert "callback" not in text
    assert errors.EQX_ON_ERROR == mode


def test_reference_is_converged_on_sampled_controls():
    """The same on piecewise-linear (sampled) controls, whose slope jumps at every sample: the
    reference steps onto the samples (``Sampled.breakpoints``). Stepping across them, Dopri8 at
    1e-11 was 1e-9 to 1.2e-7 away in the steering angle on an optimised snakeboard reach. Here
    (160 kinks, random torques, the steering one small enough to stay clear of cos(phi) = 0) the
    two tolerances agree to 1e-10 (measured 6e-14; 6.7e-9 without the breakpoints)."""
    sb = SYSTEMS["snakeboard"]
    scale = jnp.array([[0.1, 0.005]])
    values = scale * jax.random.uniform(jax.random.PRNGKey(3), (161, 2), minval=-1.0, maxval=1.0)
    ctl = lj.Sampled(values, 16.0)
    np.testing.assert_allclose(
        np.asarray(ctl.breakpoints())[[0, 1, -1]], [0.0, 0.1, 16.0], rtol=0, atol=1e-14
    )
    ts = jnp.linspace(0.0, 16.0, 17)
    z = jnp.zeros(5)
    a = lj.reference(sb, z, z, ctl, ts)
    b = lj.reference(sb, z, z, ctl, ts, rtol=1e-13, atol=1e-13)
    assert int(a.result._value) == 0 and int(b.result._value) == 0
    assert float(np.max(np.abs(np.asarray(a.q) - np.asarray(b.q)))) < 1e-10


def test_reference_vmaps():
    car = SYSTEMS["car"]
    man = maneuvers(car, 3, seed=23)
    ts = jnp.linspace(0.0, 1.0, 5)
    batched = jax.vmap(lambda a, b, c: lj.reference(car, a, b, c, ts))(*man)
    single = lj.reference(car, *index(man, 2), ts)
    np.testing.assert_allclose(np.asarray(batched.q)[2], single.q, atol=1e-12)


def test_initial_state_is_at_t0_whatever_ts_holds():
    """The initial state is given at ``t0`` (default 0, as for ``simulate``), not at ``ts[0]``:
    asking for the final time alone gives the same answer as a full grid; ``t0`` shifts it."""
    sb = SYSTEMS["snakeboard"]
    q0, qdot0, ctl = index(maneuvers(sb, 1, seed=24), 0)
    full = lj.reference(sb, q0, qdot0, ctl, jnp.linspace(0.0, 4.0, 9))
    last = lj.reference(sb, q0, qdot0, ctl, jnp.array([4.0]))
    np.testing.assert_allclose(np.asarray(last.q)[0], np.asarray(full.q)[-1], atol=1e-10)
    car = SYSTEMS["car"]  # (the snakeboard maneuvers are phase-matched to start at t = 0)
    q0, qdot0, ctl = index(maneuvers(car, 1, seed=24), 0)
    qdot0 = car.consistent_qdot(q0, qdot0, ctl(1.0))
    shifted = lj.reference(car, q0, qdot0, ctl, jnp.array([1.0, 5.0]), t0=1.0)
    traj = lj.simulate(car, q0, qdot0, ctl, t0=1.0, t_final=5.0, n_steps=400)
    unshifted = lj.reference(car, q0, qdot0, ctl, jnp.array([4.0]))
    shifted_q, traj_q, unshifted_q = (np.asarray(x.q) for x in (shifted, traj, unshifted))
    np.testing.assert_allclose(shifted_q[0], q0, atol=1e-14)
    assert float(np.linalg.norm(shifted_q[-1, :2] - traj_q[-1, :2])) < 1e-3
    assert float(np.linalg.norm(shifted_q[-1, :2] - unshifted_q[-1, :2])) > 1e-2
    with pytest.raises(ValueError, match="'ts'"):
        lj.reference(sb, q0, qdot0, ctl, jnp.array([2.0, 1.0]))
    with pytest.raises(ValueError, match="'ts'"):
        lj.reference(sb, q0, qdot0, ctl, jnp.array([0.5, 1.0]), t0=1.0)


def test_reference_reports_failures_and_bad_inputs():
    """The solve stops at the singularity (RESULTS.singular, NaN at the samples it did not reach),
    reports an exhausted step budget, and checks its inputs like simulate."""
    sb = SYSTEMS["snakeboard"]
    singular = lj.Sinusoids(
        amplitude=jnp.array([[0.05], [0.02]]),
        frequency=jnp.array([[1.0], [0.0]]),
        phase=jnp.array([[0.0], [np.pi / 2]]),
    )
    ts = jnp.linspace(0.0, 10.0, 11)
    sol = lj.reference(sb, jnp.zeros(5), jnp.zeros(5), singular, ts)
    assert sol.result == lj.RESULTS.singular and bool(sol.failed)
    reached = np.all(np.isfinite(np.asarray(sol.q)), axis=1)
    assert reached[0] and not reached[-1]
    k = int(np.argmin(reached))  # the first sample after the singularity; none reached later
    assert not np.any(reached[k:]) and np.all(np.isnan(np.asarray(sol.qdot)[k:]))
    assert abs(float(np.asarray(sol.q)[k - 1, 4])) < np.pi / 2
    short = lj.reference(sb, jnp.zeros(5), jnp.zeros(5), singular, ts, max_steps=10)
    assert short.result == lj.RESULTS.max_steps_reached
    assert np.isnan(np.asarray(short.q)[-1]).all()
    with pytest.raises(ValueError, match="'qdot0' violates"):
        lj.reference(sb, jnp.zeros(5), jnp.array([0.0, 1.0, 0.0, 0.0, 0.0]), singular, ts)
    with pytest.raises(ValueError, match="'rtol'"):
        lj.reference(sb, jnp.zeros(5), jnp.zeros(5), singular, ts, rtol=0.0)
    with pytest.raises(ValueError, match="'max_steps'"):
        lj.reference(sb, jnp.zeros(5), jnp.zeros(5), singular, ts, max_steps=0)
    with pytest.raises(ValueError, match="'ts'"):
        lj.reference(sb, jnp.zeros(5), jnp.zeros(5), singular, jnp.array([0.0, jnp.nan]))
    # traced inputs: the bad member is reported, not raised
    bad = jax.vmap(lambda qd: lj.reference(sb, jnp.zeros(5), qd, None, ts).result._value)(
        jnp.stack([jnp.zeros(5), jnp.array([0.0, 1.0, 0.0, 0.0, 0.0])])
    )
    np.testing.assert_array_equal(bad, [0, lj.RESULTS.invalid_input._value])


def test_reference_reports_a_declared_singularity_it_approaches():
    """A sleigh written with a symmetry basis that is unbounded at ``cos(phi) = 0`` (all of the
    motion in ``v_x``, ``e = (tan(phi) / L, 1, 0)``), its ``singularity=`` declared: its steering
    swings through pi/2. The adaptive steps shrank towards it without a sign change until
    ``max_steps_reached`` ("loosen the tolerances"); the magnitude test simulate's steps use
    (below ``eps^(1/4)``) reports ``singular``, as simulate does."""
    declared, length = steered_sleigh("tan", singularity=lambda r: jnp.cos(r[0])), STEERED_SLEIGH_LENGTH
    q0 = jnp.array([0.0, 0.0, 0.0, 1.2])
    qdot0 = jnp.array([0.5, 0.0, float(np.tan(1.2)) * 0.5 / length, 8.0])
    ref = lj.reference(declared, q0, qdot0, None, jnp.linspace(0.0, 1.0, 11))
    assert ref.result == lj.RESULTS.singular, lj.RESULTS[ref.result]
    run = lj.simulate(declared, q0, qdot0, None, t_final=1.0, n_steps=100)
    assert run.result == lj.RESULTS.singular
