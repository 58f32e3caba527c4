"""The small dense solve (ldap_jax._linalg.solve) against LAPACK, and that no compiled rollout,
gradient or reference calls a LAPACK kernel (jaxlib's batched LU deadlocks when a batch is
sharded over several XLA host devices)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import maneuvers, systems

import ldap_jax as lj
from ldap_jax import study
from ldap_jax._linalg import solve as _solve

SYSTEMS = systems()
solve = jax.jit(_solve)  # compiled, not op by op (each check compiles one program, not dozens)


@pytest.mark.parametrize("n", [1, 2, 3, 5, 8, 12])
def test_solve_equals_lapack(n):
    rng = np.random.default_rng(n)
    a = rng.normal(size=(20, n, n))
    b = rng.normal(size=(20, n))
    x = solve(a, b)
    x_ref = np.linalg.solve(a, b[..., None])[..., 0]
    np.testing.assert_allclose(x, x_ref, rtol=1e-11, atol=1e-12)
    bm = rng.normal(size=(n, 3))
    np.testing.assert_allclose(solve(a[0], bm), np.linalg.solve(a[0], bm), rtol=1e-11, atol=1e-12)
    # one right-hand side broadcast against a batch of matrices, as jnp.linalg.solve
    np.testing.assert_allclose(solve(a, b[0]), np.linalg.solve(a, b[0]), rtol=1e-11, atol=1e-12)


def test_solve_needs_pivoting_on_kkt_systems():
    """A KKT matrix with a singular mass block and a zero constraint block (the car's sigma
    direction): the zero diagonal entries need the row exchanges."""
    mass = np.diag([1.0, 2.0, 0.0])
    c = np.array([[0.0, 1.0, 1.0], [1.0, 0.0, 0.5]])
    kkt = np.block([[mass, c.T], [c, np.zeros((2, 2))]])
    rhs = np.arange(1.0, 6.0)
    np.testing.assert_allclose(solve(kkt, rhs), np.linalg.solve(kkt, rhs), rtol=1e-13)


def test_solve_errors_and_singular():
    with pytest.raises(ValueError, match="'a'"):
        _solve(jnp.ones((2, 3)), jnp.ones(2))
    with pytest.raises(ValueError, match="'b'"):
        _solve(jnp.eye(2), jnp.ones(3))
    assert not bool(np.all(np.isfinite(np.asarray(solve(np.zeros((2, 2)), np.ones(2))))))


def test_solve_gradients_equal_lapack():
    rng = np.random.default_rng(3)
    a = rng.normal(size=(4, 4)) + 3 * np.eye(4)  # on the host (op by op, JAX compiles each operation)
    a = jnp.asarray(a, a.dtype)
    b = jnp.asarray(rng.normal(size=4))
    for argnum in (0, 1):
        g = jax.jit(jax.grad(lambda a, b: jnp.sum(jnp.sin(solve(a, b))), argnum))(a, b)
        g_ref = jax.jit(jax.grad(lambda a, b: jnp.sum(jnp.sin(jnp.linalg.solve(a, b))), argnum))(a, b)
        np.testing.assert_allclose(g, g_ref, rtol=1e-11, atol=1e-13)


def _lowered_text(system, integrator, grad=False):
    man = maneuvers(system, 4, seed=0)

    def rollout(q0, qdot0, ctl):
        traj = lj.simulate(system, q0, qdot0, ctl, t_final=1.0, n_steps=8, integrator=integrator)
        return jnp.sum(traj.q[-1, :2])

    f = jax.vmap(rollout)
    if grad:
        f = jax.vmap(jax.grad(rollout, argnums=2))
    return jax.jit(f).lower(*man).as_text()


@pytest.mark.parametrize("model", ["car", "snakeboard"])
@pytest.mark.parametrize("method", ["rdp", "gni", "gni_folded", "dla", "rk4"])
def test_no_lapack_in_compiled_rollouts(model, method):
    system = SYSTEMS[model]
    integrator = study.make_integrator(method)
    text = _lowered_text(system, integrator)
    assert "lapack" not in text.lower()
    if method in ("rdp", "dla"):
        assert "lapack" not in _lowered_text(system, integrator, grad=True).lower()


def test_no_lapack_in_general_step_and_reference():
    system = SYSTEMS["snakeboard"]
    text = _lowered_text(system, lj.RDP(dtau_order=None, solver="newton"))
    assert "lapack" not in text.lower()
    q0, qdot0, ctl = maneuvers(system, 1, seed=0)
    ts = jnp.linspace(0.0, 1.0, 3)
    ref = jax.jit(lambda q0, qdot0, ctl: lj.reference(system, q0, qdot0, ctl, ts=ts).q)
    first = jax.tree_util.tree_map(lambda x: np.asarray(x)[0], (q0, qdot0, ctl))  # host copies
    text = ref.lower(*first).as_text()
    assert "lapack" not in text.lower()
