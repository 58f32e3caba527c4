"""The specialised RDP rollout (``ldap_jax.integrators._fast``) equals the general path.

The fast path reorganises the computation (scalar state, composed rotations, trigonometric
values reused, polynomial sin/cos, diagnostics inside the scan) but must produce the same
trajectory, diagnostics, failure reports and gradients as ``RDP.step`` in the general scan,
to round-off. In float64 "round-off" is a small multiple of eps per step; in float32 the fast
path may differ from the general one by no more than the general path's own float32 round-off
(its distance to the float64 run) allows.
"""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import maneuvers, systems

import ldap_jax as lj
from ldap_jax.integrators._fast import sincos, supports

SYSTEMS = systems()
N_STEPS, T_FINAL, BATCH = 200, 4.0, 3
CASES = list(itertools.product(["car", "snakeboard"], [0.0, 0.5, 1.0], ["exp", "cayley"]))
FIELDS = ("q", "qdot", "energy", "work", "momentum")


def _run(system, integrator, batch, fast, dtype=jnp.float64, n_steps=N_STEPS):
    q0, qdot0, ctl = batch
    cast = lambda x: x.astype(dtype)  # noqa: E731
    system = jax.tree_util.tree_map(cast, system)
    ctl = jax.tree_util.tree_map(cast, ctl)

    def one(q, qd, c):
        return lj.simulate(
            system, q, qd, c, t_final=T_FINAL, n_steps=n_steps, integrator=integrator, fast_path=fast
        )

    return jax.jit(jax.vmap(one))(cast(q0), cast(qdot0), ctl)


def _maxdiff(a, b):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.max(np.abs(a - b))) if a.size else 0.0


def _scale(a):
    a = np.asarray(a, np.float64)
    return 1.0 + (float(np.max(np.abs(a))) if a.size else 0.0)


@pytest.mark.parametrize("name,alpha,retraction", CASES)
def test_fast_equals_general_float64(name, alpha, retraction):
    system = SYSTEMS[name]
    integrator = lj.RDP(alpha=alpha, retraction=retraction)
    assert supports(system, integrator)
    batch = maneuvers(system, BATCH, seed=3)
    fast, gen = _run(system, integrator, batch, True), _run(system, integrator, batch, False)
    eps = float(jnp.finfo(jnp.float64).eps)
    # round-off accumulates at most linearly in the number of steps; observed ~1e-15 relative
    tol = 10 * eps * N_STEPS
    for field in FIELDS:
        a, b = getattr(fast, field), getattr(gen, field)
        assert a.shape == b.shape and a.dtype == b.dtype, field
        assert _maxdiff(a, b) <= tol * _scale(b), (field, _maxdiff(a, b))
    # residual-type outputs are round-off themselves: both tiny relative to the velocities
    vel = _scale(gen.qdot)
    for field in ("constraint_residual", "step_residual"):
        assert float(jnp.max(getattr(fast, field))) <= 100 * eps * vel, field
        assert float(jnp.max(getattr(gen, field))) <= 100 * eps * vel, field
    np.testing.assert_array_equal(fast.converged, gen.converged)
    np.testing.assert_array_equal(fast.result, gen.result)
    np.testing.assert_array_equal(fast.failure_index, gen.failure_index)
    np.testing.assert_array_equal(fast.t, gen.t)


# every alpha and both retractions appear for each model (kept small: each case compiles 3 rollouts)
F32_CASES = [
    ("car", 0.0, "cayley"),
    ("car", 0.5, "exp"),
    ("car", 1.0, "exp"),
    ("snakeboard", 0.0, "exp"),
    ("snakeboard", 0.5, "cayley"),
    ("snakeboard", 1.0, "cayley"),
]


@pytest.mark.parametrize("name,alpha,retraction", F32_CASES)
def test_fast_equals_general_float32(name, alpha, retraction):
    system = SYSTEMS[name]
    integrator = lj.RDP(alpha=alpha, retraction=retraction)
    batch = maneuvers(system, BATCH, seed=4)
    fast = _run(system, integrator, batch, True, jnp.float32)
    gen = _run(system, integrator, batch, False, jnp.float32)
    ref = _run(system, integrator, batch, False, jnp.float64)
    assert fast.q.dtype == jnp.float32 and fast.energy.dtype == jnp.float32
    eps32 = float(jnp.finfo(jnp.float32).eps)
    for field in FIELDS:
        a, b, c = getattr(fast, field), getattr(gen, field), getattr(ref, field)
        own_roundoff = _maxdiff(b, c)  # the general path's float32 error
        assert _maxdiff(a, b) <= 4 * own_roundoff + 10 * eps32 * _scale(c), (field, _maxdiff(a, b))
    np.testing.assert_array_equal(fast.result, gen.result)


def test_failure_reporting_matches():
    """Singularity (code 2) at the same step, NaN after it, finite before; `throw` raises."""
    sb = SYSTEMS["snakeboard"]
    amp = jnp.array([[[0.05], [0.0]], [[0.05], [0.02]]])  # second: constant torque -> singular
    freq = jnp.array([[[1.0], [0.0]], [[1.0], [0.0]]])
    phase = jnp.array([[[0.0], [0.0]], [[0.0], [np.pi / 2]]])
    q0, qdot0 = jnp.zeros((2, 5)), jnp.zeros((2, 5))
    for alpha in (0.0, 1.0):
        runs = []
        for fast in (True, False):

            def one(q, qd, a, f, p, fast=fast, alpha=alpha):
                ctl = lj.Sinusoids(a, f, p)
                return lj.simulate(
                    sb, q, qd, ctl, t_final=10.0, n_steps=1000, integrator=lj.RDP(alpha=alpha), fast_path=fast
                )

            runs.append(jax.vmap(one)(q0, qdot0, amp, freq, phase))
        fast, gen = runs
        np.testing.assert_array_equal(fast.result, [0, 2])
        np.testing.assert_array_equal(fast.result, gen.result)
        np.testing.assert_array_equal(fast.failure_index, gen.failure_index)
        for field in ("q", "qdot", "energy", "work", "momentum", "constraint_residual"):
            a, b = np.asarray(getattr(fast, field)), np.asarray(getattr(gen, field))
            np.testing.assert_array_equal(np.isnan(a), np.isnan(b), err_msg=field)
        k = int(fast.failure_index[1])
        assert 0 < k < 1000 and np.all(np.isfinite(np.asarray(fast.q[1, : k + 1])))
        np.testing.assert_allclose(fast.q[1, : k + 1], gen.q[1, : k + 1], rtol=0, atol=1e-10)
    with pytest.raises(Exception, match="integration failed"):
        lj.simulate(
            sb,
            q0[1],
            qdot0[1],
            lj.Sinusoids(amp[1], freq[1], phase[1]),
            t_final=10.0,
            n_steps=1000,
            throw=True,
        )


@pytest.mark.parametrize("name,checkpoint", [("car", False), ("snakeboard", False), ("snakeboard", True)])
def test_gradients_match(name, checkpoint):
    """Reverse-mode gradients of a terminal cost in controls, initial state and parameters."""
    system = SYSTEMS[name]
    q0, qdot0, ctl = maneuvers(system, 2, seed=5)

    def loss(system, q0, ctl, fast):
        def one(q, qd, c):
            traj = lj.simulate(
                system, q, qd, c, t_final=T_FINAL, n_steps=N_STEPS, fast_path=fast, checkpoint=checkpoint
            )
            return jnp.sum(traj.q[-1, :3] ** 2) + traj.energy[-1]

        return jnp.sum(jax.vmap(one)(q0, qdot0, ctl))

    g_fast = jax.grad(loss, argnums=(0, 1, 2))(system, q0, ctl, True)
    g_gen = jax.grad(loss, argnums=(0, 1, 2))(system, q0, ctl, False)
    for a, b in zip(jax.tree_util.tree_leaves(g_fast), jax.tree_util.tree_leaves(g_gen)):
        assert np.all(np.isfinite(np.asarray(a)))
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-9 * _scale(b))


def test_sincos_accuracy_and_derivative():
    rng = np.random.default_rng(0)
    for dtype, lim, ulps in ((np.float64, 1e4, 2.0), (np.float32, 1e3, 2.0)):
        x = np.concatenate([rng.uniform(-4, 4, 20000), rng.uniform(-lim, lim, 20000)]).astype(dtype)
        s, c = jax.jit(sincos)(jnp.asarray(x))
        assert s.dtype == dtype
        x64 = x.astype(np.float64)
        # absolute error in units of eps: the reduction's error is absolute, ~ |n| eps_pio2
        err_s = np.abs(np.asarray(s, np.float64) - np.sin(x64)) / np.finfo(dtype).eps
        err_c = np.abs(np.asarray(c, np.float64) - np.cos(x64)) / np.finfo(dtype).eps
        assert err_s.max() <= ulps and err_c.max() <= ulps, (dtype, err_s.max(), err_c.max())
    ds, dc = (
        jax.vmap(jax.grad(lambda t: sincos(t)[0]))(jnp.linspace(-3, 3, 7)),
        jax.vmap(jax.grad(lambda t: sincos(t)[1]))(jnp.linspace(-3, 3, 7)),
    )
    np.testing.assert_allclose(ds, np.cos(np.linspace(-3, 3, 7)), rtol=1e-15, atol=1e-15)
    np.testing.assert_allclose(dc, -np.sin(np.linspace(-3, 3, 7)), rtol=1e-15, atol=1e-15)


def test_dispatch():
    """Only RDP with the closed form on the exact Car/Snakeboard classes takes the fast path."""
    sb = SYSTEMS["snakeboard"]

    class MySnakeboard(lj.Snakeboard):
        pass

    assert supports(sb, lj.RDP())
    assert supports(SYSTEMS["car"], lj.RDP(alpha=1.0, retraction="cayley"))
    assert not supports(sb, lj.RDP(dtau_order=None))
    assert not supports(sb, lj.RDP(solver="newton"))
    assert not supports(sb, lj.RK4())
    assert not supports(MySnakeboard(m=1.0, l=0.5, I=0.05, J=0.02), lj.RDP())
