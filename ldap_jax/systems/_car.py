"""The steered car with simple dynamics (paper Sec. 5.1; ``docs/mathematics.md`` section 5)."""

from __future__ import annotations

from typing import ClassVar, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array

from .._numerics import safe_norm
from ..lie._scalar import Pose, body_to_qdot, dtau1_transpose, pose_from_xy_theta, pose_retract
from ._base import physical_parameter, positive_checks, random_draws
from ._closed_form import AbstractClosedFormSystem

__all__ = ["Car", "CarKernelState"]


class CarKernelState(NamedTuple):
    """The car's RDP kernel state: pose, shape, and the incoming momenta ``pu = (p_psi, 0)``,
    ``mu = (mu_1, mu_2, mu_3)``."""

    pose: Pose
    psi: Array
    sigma: Array
    pu: tuple[Array, Array]
    mu: tuple[Array, Array, Array]


class Car(AbstractClosedFormSystem):
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
        m: mass (kg, default 1). I: rear-wheel inertia (kg m^2, default 0.1). K: yaw inertia
            (kg m^2, default 0.2). rho: wheel radius (m, default 0.1).
        l: distance between the axles (m, default 0.5). All positive.
    """

    m: Array = eqx.field(converter=physical_parameter, default=1.0)
    I: Array = eqx.field(converter=physical_parameter, default=0.1)  # noqa: E741
    K: Array = eqx.field(converter=physical_parameter, default=0.2)
    rho: Array = eqx.field(converter=physical_parameter, default=0.1)
    l: Array = eqx.field(converter=physical_parameter, default=0.5)  # noqa: E741

    shape_names: ClassVar[tuple[str, ...]] = ("psi", "sigma")
    cyclic_names: ClassVar[tuple[str, ...] | None] = ("psi",)  # the wheel angle
    control_names: ClassVar[tuple[str, ...]] = ("f_psi", "u_sigma")
    kinematic: ClassVar[tuple[bool, ...]] = (False, True)
    n_velocities: ClassVar[int] = 1

    def parameter_checks(self):
        return positive_checks(self, "m", "I", "K", "rho", "l")

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
    def body_constraints(self, r):
        """``C(sigma) [xi; rdot] = 0``.

        That is ``v_x = rho psidot``, ``v_y = 0``, ``omega = (rho / l) sigma psidot``.
        """
        z = jnp.zeros_like(r[1])
        o = jnp.ones_like(z)
        return jnp.array(
            [[z, o, z, -self.rho + z, z], [z, z, o, z, z], [o, z, z, -self.rho * r[1] / self.l, z]]
        )

    # minimal continuous form, v = (psidot,)
    def qdot_from_velocities(self, q, v, u_kin):
        rv = self.rho * v[0]
        return jnp.stack([rv * jnp.cos(q[2]), rv * jnp.sin(q[2]), rv * q[4] / self.l, v[0], u_kin[1]])

    def velocities_from_qdot(self, q, qdot):
        return qdot[3:4]

    def effective_inertia(self, sigma):
        """``I + m rho^2 + K rho^2 sigma^2 / l^2`` (:meth:`_wheel_inertia` at ``sigma_a = sigma_k``)."""
        return self._wheel_inertia(sigma, sigma)

    def velocity_dynamics(self, q, v, f, u_kin, u_kin_dot=None):
        # the steering's acceleration does not enter the wheel's equation (sigma has no inertia)
        sigma = q[4]
        gyro = self.K * self.rho**2 * sigma * u_kin[1] * v[0] / self.l**2
        return ((f[0] - gyro) / self.effective_inertia(sigma))[None]

    # one compiled program per signature (op by op, a first draw compiled some 50 small ones)
    @eqx.filter_jit
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

        dtype = self.m.dtype
        ks, u, sign = random_draws(key, 10, dtype)
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

    # ------------------------------------------------------ closed-form RDP (paper Sec. 5.1)
    def _solve(self, b_psi, mu, sigma_k, sigma_a):
        """The horizontal equation (23) for the wheel's rate (the car has no momentum equation)::

            (I + rho^2 m + K rho^2 sigma_k sigma_a / l^2) u^psi = b_psi - (A(r_k)^T mu_in)_psi,

        ``b_psi = p_psi + h (1 - alpha) f^psi_{k+alpha}``, ``-(A(r_k)^T mu)_psi = (rho sigma_k / l) mu_1
        + rho mu_2``. At ``sigma_a = sigma_k`` and ``h = 0`` it inverts the reduced Legendre transform."""
        rho, l = self.rho, self.l
        rhs = b_psi + (rho * sigma_k / l) * mu[0] + rho * mu[1]
        return rhs / self._wheel_inertia(sigma_k, sigma_a)

    def _wheel_inertia(self, sigma_k, sigma_a):
        """``I + rho^2 m + K rho^2 sigma_k sigma_a / l^2``: the coefficient of ``u^psi`` in (23) (the
        denominator of :meth:`_solve`, the slope of the residual in ``u^psi``)."""
        return self.I + self.m * self.rho**2 + self.K * self.rho**2 * sigma_k * sigma_a / self.l**2

    def kernel_init(self, q, pu, mu):
        return CarKernelState(
            pose_from_xy_theta(q[0], q[1], q[2]),
            q[3],
            q[4],
            (pu[0], jnp.zeros_like(pu[0])),
            (mu[0], mu[1], mu[2]),
        )

    def kernel_momenta(self, state):
        g = state.pose
        q = jnp.stack([g.x, g.y, g.theta, state.psi, state.sigma])
        return q, jnp.stack(state.pu), jnp.stack(state.mu)

    def kernel_step(self, alpha, h, retraction, state, c0, c1):
        """One RDP step (paper Sec. 5.1): ``u^sigma`` is the trapezoidal average of the prescribed
        steering rate, ``u^psi`` from :meth:`_solve` at ``sigma_a = sigma_k + alpha h u^sigma``,
        ``xi = -A(r_{k+alpha}) u``; the next incoming momenta are ``pu = I u^psi + h alpha f^psi`` and
        ``mu = (I + ad_{h xi} / 2)^T d_xi l``."""
        a = alpha
        m, inertia, kk, rho, l = self.m, self.I, self.K, self.rho, self.l
        zero = jnp.zeros_like(state.psi)
        fa = (1 - a) * c0[0] + a * c1[0]
        b = state.pu[0] + h * (1 - a) * fa
        u_sig = 0.5 * (c0[1] + c1[1])
        sigma_a = state.sigma + a * h * u_sig

        def horizontal(u_psi):
            """Outgoing ``h xi``, momentum, and the residual of (23) in difference form."""
            xi = (rho * sigma_a / l * u_psi, rho * u_psi, zero)
            mu_new = (kk * xi[0], m * xi[1], m * xi[2])
            hxi = tuple(h * x for x in xi)
            jump = tuple(x - y for x, y in zip(dtau1_transpose(hxi, mu_new, 1.0), state.mu))
            return hxi, mu_new, inertia * u_psi + (rho * state.sigma / l) * jump[0] + rho * jump[1] - b

        # The ratio-form solve rounds numerator and denominator differently: a relative bias ~eps
        # per step that the momentum recursion accumulates (visible in float32). One Newton
        # correction on the difference-form residual (linear in u^psi, slope = the denominator)
        # removes it.
        u_psi = self._solve(b, state.mu, state.sigma, sigma_a)
        u_psi = u_psi - horizontal(u_psi)[2] / self._wheel_inertia(state.sigma, sigma_a)
        hxi, mu_new, r = horizontal(u_psi)
        scale = 1.0 + jnp.abs(b) + safe_norm(*state.mu)
        residual = jnp.abs(r) / scale
        new = CarKernelState(
            pose_retract(state.pose, hxi, retraction),
            state.psi + h * u_psi,
            state.sigma + h * u_sig,
            (inertia * u_psi + h * a * fa, zero),
            dtau1_transpose(hxi, mu_new, -1.0),
        )
        return new, residual, jnp.zeros(jnp.shape(residual), bool)

    def _kernel_velocity(self, state, c):
        """Configuration and velocities ``(u, xi)`` from the carried momenta (:meth:`_solve` at ``h = 0``)."""
        u_psi = self._solve(state.pu[0], state.mu, state.sigma, state.sigma)
        u = jnp.stack([u_psi, c[1]])
        rho = self.rho
        xi = jnp.stack([rho * state.sigma / self.l * u_psi, rho * u_psi, jnp.zeros_like(u_psi)])
        g = state.pose
        return jnp.stack([g.x, g.y, g.theta, state.psi, state.sigma]), u, xi

    def kernel_observe(self, state, c):
        q, u, xi = self._kernel_velocity(state, c)
        rotation = (state.pose.cos, state.pose.sin)
        return self.observation(q, u, xi, c, rotation=rotation, momentum=jnp.zeros((0,), u.dtype))

    def kernel_node(self, state, c):
        q, u, xi = self._kernel_velocity(state, c)
        return q, body_to_qdot(state.pose, u, xi)
