"""SE(2): group axioms, agreement with independent implementations, NaN-free gradients."""

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest
import scipy.linalg

from ldap_jax import lie
from ldap_jax.lie import SE2

rng = np.random.default_rng(0)
VS = [jnp.asarray(rng.normal(size=3)) for _ in range(5)] + [
    jnp.array([0.0, 0.3, -0.2]),
    jnp.array([1e-9, 1.0, 2.0]),
]


def _mat(g):  # pose (x, y, theta) -> 3x3
    g = np.asarray(g)
    c, s = np.cos(g[2]), np.sin(g[2])
    return np.array([[c, -s, g[0]], [s, c, g[1]], [0, 0, 1]])


def _pose(m):  # 3x3 -> pose (x, y, theta)
    return np.array([m[0, 2], m[1, 2], np.arctan2(m[1, 0], m[0, 0])])


def _inv(g):
    return lie.inverse(g)


@pytest.mark.parametrize("v", VS)
def test_exp_matches_matrix_exponential(v):
    np.testing.assert_allclose(_mat(lie.exp(v)), scipy.linalg.expm(np.asarray(lie.hat(v))), atol=1e-12)


@pytest.mark.parametrize("v", VS)
def test_cay_matches_matrix_formula(v):
    x = np.asarray(lie.hat(v))
    expected = np.linalg.solve(np.eye(3) - x / 2, np.eye(3) + x / 2)
    np.testing.assert_allclose(_mat(lie.cay(v)), expected, atol=1e-12)
    np.testing.assert_allclose(SE2.cay(v).as_matrix(), expected, atol=1e-12)


@pytest.mark.parametrize("v", VS)
def test_log_and_cay_inv_invert(v):
    v = np.array(v)  # a host copy
    v[0] = np.clip(v[0], -3.0, 3.0)
    v = jnp.asarray(v, v.dtype)
    np.testing.assert_allclose(lie.log(lie.exp(v)), v, atol=1e-12)
    np.testing.assert_allclose(lie.cay_inv(lie.cay(v)), v, atol=1e-12)
    np.testing.assert_allclose(lie.vee(lie.hat(v)), v, atol=0)


@pytest.mark.parametrize("v", VS)
def test_agrees_with_jaxlie(v):
    # jaxlie's tangent order is (vx, vy, omega); ours is (omega, vx, vy).
    with jax.numpy_dtype_promotion("standard"):  # jaxlie mixes weak types internally
        _check_against_jaxlie(v)


def _check_against_jaxlie(v):
    tj = lie.tangent_to_jaxlie(v)
    gj = jaxlie.SE2.exp(tj)
    g = SE2.exp(v)
    np.testing.assert_allclose(g.as_matrix(), gj.as_matrix(), atol=1e-12)
    h = SE2.exp(jnp.asarray(rng.normal(size=3)))
    hj = jaxlie.SE2.from_matrix(h.as_matrix())
    np.testing.assert_allclose((g @ h).as_matrix(), (gj @ hj).as_matrix(), atol=1e-12)
    lj_log = gj.log()
    np.testing.assert_allclose(g.log(), np.asarray(lj_log)[[2, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(np.asarray(g.adjoint())[1:, 1:], np.asarray(gj.adjoint())[:2, :2], atol=1e-12)


@pytest.mark.parametrize("v", VS)
def test_poses_compose_invert_and_retract_as_matrices(v):
    """compose, inverse and retract on poses (x, y, theta) are the matrix product, inverse and
    g tau(v)."""
    g, h = jnp.asarray(rng.normal(size=3)), jnp.asarray(rng.normal(size=3))
    np.testing.assert_allclose(_mat(lie.compose(g, h)), _mat(g) @ _mat(h), atol=1e-12)
    np.testing.assert_allclose(_mat(lie.inverse(g)), np.linalg.inv(_mat(g)), atol=1e-12)
    np.testing.assert_allclose(_mat(lie.compose(g, lie.inverse(g))), np.eye(3), atol=1e-12)
    for retraction, tau in (("exp", lie.exp), ("cayley", lie.cay)):
        np.testing.assert_allclose(lie.retract(v, retraction), tau(v), atol=0)
    # SE2 reads and writes the same poses
    np.testing.assert_allclose(SE2.from_xy_theta(*g).as_matrix(), _mat(g), atol=1e-12)
    back = np.asarray(SE2.from_xy_theta(*g).as_xy_theta())
    np.testing.assert_allclose(back[:2], np.asarray(g)[:2], atol=1e-15)
    np.testing.assert_allclose(np.exp(1j * float(back[2])), np.exp(1j * float(g[2])), atol=1e-14)
    assert -np.pi < float(back[2]) <= np.pi
    ge = np.asarray(SE2.exp(v).as_xy_theta())
    np.testing.assert_allclose(ge, _pose(_mat(lie.exp(v))), atol=1e-12)
    np.testing.assert_allclose(ge[:2], np.asarray(lie.exp(v))[:2], atol=1e-12)


@pytest.mark.parametrize("v", VS)
def test_jaxlie_conversions(v):
    with jax.numpy_dtype_promotion("standard"):  # jaxlie mixes weak types internally
        t = lie.tangent_to_jaxlie(v)
        np.testing.assert_allclose(t, [v[1], v[2], v[0]], atol=0)
        np.testing.assert_allclose(lie.tangent_from_jaxlie(t), v, atol=0)
        gj = jaxlie.SE2.exp(t)
        g = SE2.from_jaxlie(gj)
        np.testing.assert_allclose(g.as_matrix(), gj.as_matrix(), atol=1e-12)
        np.testing.assert_allclose(g.as_matrix(), SE2.exp(v).as_matrix(), atol=1e-12)
        np.testing.assert_allclose(g.to_jaxlie().as_matrix(), gj.as_matrix(), atol=0)
        np.testing.assert_allclose(lie.tangent_from_jaxlie(gj.log()), g.log(), atol=1e-12)


def test_group_axioms():
    a, b, c = (SE2.exp(jnp.asarray(rng.normal(size=3))) for _ in range(3))
    e = SE2.identity(jnp.float64)
    np.testing.assert_allclose(((a @ b) @ c).as_matrix(), (a @ (b @ c)).as_matrix(), atol=1e-12)
    np.testing.assert_allclose((a @ e).as_matrix(), a.as_matrix(), atol=1e-15)
    np.testing.assert_allclose((a @ a.inverse()).as_matrix(), np.eye(3), atol=1e-12)
    # Ad_g v = vee(g hat(v) g^-1)
    v = jnp.asarray(rng.normal(size=3))
    am = np.asarray(a.as_matrix())
    np.testing.assert_allclose(
        np.asarray(a.adjoint()) @ np.asarray(v),
        lie.vee(am @ np.asarray(lie.hat(v)) @ np.linalg.inv(am)),
        atol=1e-12,
    )
    # ad_v w = vee([v^, w^])
    w = jnp.asarray(rng.normal(size=3))
    hv, hw = np.asarray(lie.hat(v)), np.asarray(lie.hat(w))
    np.testing.assert_allclose(np.asarray(lie.ad(v)) @ np.asarray(w), lie.vee(hv @ hw - hw @ hv), atol=1e-12)


@pytest.mark.parametrize("retraction", ["exp", "cayley"])
@pytest.mark.parametrize("v", VS)
def test_dtau_inv_against_finite_difference(retraction, v):
    """dtau_v d = d/de log(tau(v + e d) tau(v)^-1) at e = 0; dtau^-1 inverts it."""
    tau = lie.exp if retraction == "exp" else lie.cay
    tau_inv = lie.log if retraction == "exp" else lie.cay_inv
    d = jnp.asarray(rng.normal(size=3))
    eps = 1e-6

    def right_diff(s):
        return tau_inv(lie.compose(tau(v + s * d), _inv(tau(v))))

    dtau_d = (np.asarray(right_diff(eps)) - np.asarray(right_diff(-eps))) / (2 * eps)
    dtau_inv = np.asarray(lie.dtau_inv(v, retraction))
    np.testing.assert_allclose(dtau_inv @ dtau_d, d, atol=1e-8)
    # and the forward-mode derivative agrees to round-off
    jvp = jax.jvp(right_diff, (0.0,), (1.0,))[1]
    np.testing.assert_allclose(dtau_inv @ np.asarray(jvp), d, atol=1e-12)


@pytest.mark.parametrize("v", VS)
def test_dcay_inv_matches_matrix_form(v):
    """(29): dcay^-1_x y = (I - x/2) y (I + x/2)."""
    y = jnp.asarray(rng.normal(size=3))
    x = np.asarray(lie.hat(v))
    expected = lie.vee((np.eye(3) - x / 2) @ np.asarray(lie.hat(y)) @ (np.eye(3) + x / 2))
    np.testing.assert_allclose(np.asarray(lie.dcay_inv(v)) @ np.asarray(y), expected, atol=1e-12)


@pytest.mark.parametrize("v", VS)
def test_dexp_inv_series_converges_to_exact(v):
    v = 0.2 * v
    exact = np.asarray(lie.dexp_inv(v))
    errs = [float(np.max(np.abs(np.asarray(lie.dtau_inv(v, "exp", p)) - exact))) for p in (1, 2, 4, 8)]
    assert errs[-1] < 1e-9
    assert errs[0] >= errs[1] >= errs[2] >= errs[3] or max(errs) < 1e-12


def test_finite_gradients_at_zero_rotation():
    v0 = jnp.array([0.0, 0.7, -0.4])
    fns = {
        "exp": lambda v: jnp.sum(lie.exp(v) ** 2),
        "log": lambda v: jnp.sum(lie.log(v) ** 2),
        "dexp_inv": lambda v: jnp.sum(lie.dexp_inv(v) ** 2),
        "cay": lambda v: jnp.sum(lie.cay(v) ** 2),
        "SE2.exp": lambda v: jnp.sum(SE2.exp(v).unit_complex_xy ** 2),
    }
    v0_near = np.array(v0)  # a host copy
    v0_near[0] = 1e-3
    for name, fn in fns.items():
        grad = jax.jit(jax.grad(fn))  # compiled, not op by op
        g = grad(v0)
        hess = jax.jit(jax.hessian(fn))(v0)
        assert np.all(np.isfinite(g)) and np.all(np.isfinite(hess)), name
        # the Taylor branch is continuous with the closed form
        g_near = grad(v0_near)
        np.testing.assert_allclose(g, g_near, atol=1e-2, err_msg=name)
    # exp near 0 agrees with the exact value from both sides of the branch switch
    for w in (1e-5, 2e-4, 1e-3):
        v = jnp.array([w, 0.3, 0.2])
        np.testing.assert_allclose(_mat(lie.exp(v)), scipy.linalg.expm(np.asarray(lie.hat(v))), atol=1e-14)
        np.testing.assert_allclose(lie.dexp_inv(v), lie.dtau_inv(v, "exp", 8), atol=1e-14)


def _series(coef, w, n_terms=12):
    """``sum_k coef(k) w^k`` over the first terms with a nonzero coefficient (float64; exact to
    round-off for |w| <= 0.5 with these coefficients)."""
    return sum(coef(k) * w**k for k in range(2 * n_terms + 2) if coef(k) != 0.0)


def test_second_derivatives_across_the_small_angle_threshold():
    """``lie.exp``'s ``(1 - cos w) / w`` and ``lie.dexp_inv``'s ``beta = (1 - (w/2) cot(w/2)) / w``
    lose ``eps / w^(k+2)`` of their k-th derivatives to cancellation above the Taylor threshold:
    their second derivatives against the series differentiated term by term (Bernoulli numbers from
    SciPy), below, at and above the threshold (0.105 in float64) and at the old one (1.2e-4, where
    the second derivative had no correct digit), to 1e-8 relative."""
    from math import factorial

    from scipy.special import bernoulli

    bern = bernoulli(40)
    # b(w) = (1 - cos w)/w = sum_n (-1)^n w^(2n+1) / (2n+2)!; b'' term by term
    b2 = lambda k: 0.0 if k % 2 == 0 else (-1) ** ((k + 1) // 2) * (k + 2) * (k + 1) / factorial(k + 3)  # noqa: E731
    # beta(w) = -sum_{n>=1} (-1)^n B_2n w^(2n-1) / (2n)!; beta'' term by term
    beta2 = (  # noqa: E731
        lambda k: (
            0.0
            if k % 2 == 0
            else -((-1) ** ((k + 3) // 2)) * bern[k + 3] * (k + 2) * (k + 1) / factorial(k + 3)
        )
    )
    h_exp = jax.jit(jax.hessian(lambda v: lie.exp(v)[1]))  # = b(w) at v = (w, 1, 0)
    h_beta = jax.jit(jax.hessian(lambda v: lie.dexp_inv(v)[1, 0]))  # = beta(w) there
    for w in (1e-6, 1.2e-4, 1.23e-4, 1.5e-4, 1e-3, 1e-2, 0.1, 0.1052, 0.11, 0.2, 0.4):
        v = jnp.array([w, 1.0, 0.0])
        for name, fn, coef in (("exp", h_exp, b2), ("dexp_inv", h_beta, beta2)):
            exact = _series(coef, w)
            got = float(fn(v)[0, 0])
            assert abs(got - exact) <= 1e-8 * abs(exact), (name, w, got, exact)


def test_integer_tangents_are_converted():
    """Integer tangents give the float results of the same values (``exp`` and ``dexp_inv`` read
    their dtype's epsilon)."""
    v = np.array([1, 2, -1])
    for fn in (lie.exp, lie.dexp_inv, lie.log, lie.cay):
        np.testing.assert_allclose(fn(v), fn(v.astype(float)), rtol=1e-15, atol=1e-15)
    got, want = SE2.exp(v).unit_complex_xy, SE2.exp(v.astype(float)).unit_complex_xy
    np.testing.assert_allclose(got, want, atol=1e-15)
