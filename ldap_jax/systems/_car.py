"""The steered car with simple dynamics (paper Sec. 5.1; DESIGN.md section 5)."""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array

from ._base import AbstractSystem, check_positive, positive_parameter

__all__ = ["Car"]


class Car(AbstractSystem):
    r"""Car with rear-wheel drive and kinematic steering on ``Q = R x R x SE(2)``.

    Coordinates ``q = (x, y, theta, psi, sigma)``: rear-wheel rolling angle ``psi`` and
    ``sigma = tan(steering angle)``. Controls ``(f_psi, u_sigma)``: rear-wheel torque and the
    prescribed steering rate ``sigma_dot = u_sigma``.

    Lagrangian ``L = (I psidot^2 + K thetadot^2 + m (xdot^2 + ydot^2)) / 2``; constraints
    ``xdot = rho cos(theta) psidot``, ``ydot = rho sin(theta) psidot``,
    ``thetadot = (rho / l) sigma psidot`` (the paper's "rho/I" is a typo for rho/l).
    Reduced: ``[A(r)] = [[-rho sigma / l, 0], [-rho, 0], [0, 0]]`` (26), no constrained symmetry.
    Continuous equation (Sec. 5.1)::

        (I + m rho^2 + K rho^2 sigma^2 / l^2) psi_ddot = f_psi - K rho^2 sigma u_sigma psidot / l^2.

    Args:
        m: mass. I: rear-wheel inertia. K: yaw inertia. rho: wheel radius.
        l: distance between the axles. All positive.
    """

    m: Array = eqx.field(converter=positive_parameter)
    I: Array = eqx.field(converter=positive_parameter)  # noqa: E741
    K: Array = eqx.field(converter=positive_parameter)
    rho: Array = eqx.field(converter=positive_parameter)
    l: Array = eqx.field(converter=positive_parameter)  # noqa: E741

    shape_names: ClassVar[tuple[str, ...]] = ("psi", "sigma")
    control_names: ClassVar[tuple[str, ...]] = ("f_psi", "u_sigma")
    kinematic: ClassVar[tuple[bool, ...]] = (False, True)
    n_velocities: ClassVar[int] = 1

    def __check_init__(self):
        check_positive(self, "m", "I", "K", "rho", "l")

    # reduced view
    def reduced_lagrangian(self, r, u, xi):
        return 0.5 * (self.I * u[0] ** 2 + self.K * xi[0] ** 2 + self.m * (xi[1] ** 2 + xi[2] ** 2))

    def connection(self, r):
        z = jnp.zeros_like(r[1])
        return jnp.array([[-self.rho * r[1] / self.l, z], [-self.rho + z, z], [z, z]])

    def symmetry_basis(self, r):
        return jnp.zeros((3, 0), r.dtype)

    def inputs(self, controls):
        z = jnp.zeros_like(controls[0])
        return jnp.stack([controls[0], z]), jnp.stack([z, controls[1]])

    # full view
    def constraint_forms(self, q):
        c, s = jnp.cos(q[2]), jnp.sin(q[2])
        z, o = jnp.zeros_like(c), jnp.ones_like(c)
        return jnp.array(
            [
                [c, s, z, -self.rho + z, z],
                [-s, c, z, z, z],
                [z, z, o, -self.rho * q[4] / self.l, z],
            ]
        )

    # minimal continuous form, v = (psidot,)
    def qdot_from_velocities(self, q, v, u_kin):
        rv = self.rho * v[0]
        return jnp.stack([rv * jnp.cos(q[2]), rv * jnp.sin(q[2]), rv * q[4] / self.l, v[0], u_kin[1]])

    def velocities_from_qdot(self, q, qdot):
        return qdot[3:4]

    def effective_inertia(self, sigma):
        """``I + m rho^2 + K rho^2 sigma^2 / l^2``."""
        return self.I + self.m * self.rho**2 + self.K * (self.rho * sigma / self.l) ** 2

    def velocity_dynamics(self, q, v, f, u_kin):
        sigma = q[4]
        gyro = self.K * self.rho**2 * sigma * u_kin[1] * v[0] / self.l**2
        return ((f[0] - gyro) / self.effective_inertia(sigma))[None]

    def sample_maneuver(self, key, *, n_terms: int = 2):
        """A random maneuver with non-trivial paths (reversals, sharp turns, winding).

        Rear-wheel torque: ``n_terms`` sinusoids with amplitudes ``(I + m rho^2) U(0.5, 3)``,
        frequencies ``U(0.3, 2)`` rad/s; steering rate ``u_sigma = B sin(w t + p)`` with
        ``B ~ U(0.2, 1)``; initial ``|sigma| < 0.5`` and rolling rate ``+-U(2, 8)`` rad/s.
        Deterministic in ``key``; vmap over keys for a batch.

        Returns:
            ``(q0, qdot0, controls)`` with ``qdot0`` on the constraints.
        """
        from .._controls import Sinusoids

        ks = jax.random.split(key, 10)
        dtype = self.m.dtype
        u = lambda k, shape, lo, hi: jax.random.uniform(k, shape, dtype, lo, hi)  # noqa: E731
        sign = lambda k, shape: jnp.where(jax.random.bernoulli(k, 0.5, shape), 1.0, -1.0).astype(dtype)  # noqa: E731
        a_f = (self.I + self.m * self.rho**2) * u(ks[0], (n_terms,), 0.5, 3.0) * sign(ks[1], (n_terms,))
        w_f = u(ks[2], (n_terms,), 0.3, 2.0)
        p_f = u(ks[3], (n_terms,), 0.0, 2 * jnp.pi)
        a_s = jnp.zeros(n_terms, dtype).at[0].set(u(ks[4], (), 0.2, 1.0) * sign(ks[5], ()))
        w_s = jnp.ones(n_terms, dtype).at[0].set(u(ks[6], (), 0.5, 2.0))
        p_s = jnp.zeros(n_terms, dtype).at[0].set(u(ks[7], (), 0.0, 2 * jnp.pi))
        ctl = Sinusoids(
            amplitude=jnp.stack([a_f, a_s]), frequency=jnp.stack([w_f, w_s]), phase=jnp.stack([p_f, p_s])
        )
        theta0 = u(ks[8], (), -jnp.pi, jnp.pi)
        sigma0 = u(ks[9], (), -0.5, 0.5)
        psidot0 = u(jax.random.fold_in(key, 1), (), 2.0, 8.0) * sign(jax.random.fold_in(key, 2), ())
        zero = jnp.zeros((), dtype)
        q0 = jnp.stack([zero, zero, theta0, zero, sigma0])
        qdot0 = self.qdot_from_velocities(q0, psidot0[None], ctl(zero) * jnp.array([0.0, 1.0], dtype))
        return q0, qdot0, ctl

    # closed-form RDP step (paper Sec. 5.1), dtau^-1 truncated to I - ad/2
    def rdp_closed_form(self, alpha, h, r, u_kin, b, m_in):
        """Solve the car's RDP step explicitly (paper Sec. 5.1).

        ``(I + rho^2 m + K rho^2 sigma_k sigma_{k+a} / l^2) u^psi_k = b_psi - (A(r_k)^T mu_in)_psi``
        with ``b = d_u l_{k-1} + h F_k`` and ``mu_in`` the incoming momentum; then
        ``xi_k = -A(r_{k+a}) u_k``.
        """
        sigma_k = r[1]
        sigma_a = r[1] + alpha * h * u_kin[1]
        a_k = self.connection(r)
        rhs = b[0] - a_k[:, 0] @ m_in
        inertia = self.I + self.m * self.rho**2 + self.K * self.rho**2 * sigma_k * sigma_a / self.l**2
        u_psi = rhs / inertia
        u = jnp.stack([u_psi, u_kin[1]])
        xi = -self.connection(jnp.stack([r[0], sigma_a])) @ u
        return u, xi
