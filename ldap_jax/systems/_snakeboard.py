"""The snakeboard (paper Sec. 5.2, corrected; DESIGN.md section 6)."""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from ._base import AbstractSystem, _concrete, check_positive, positive_parameter

__all__ = ["Snakeboard"]


class Snakeboard(AbstractSystem):
    r"""The snakeboard: a board with a momentum rotor and two coupled steered wheel sets.

    Coordinates ``q = (x, y, theta, psi, phi)``: rotor angle ``psi`` and wheel steering angle
    ``phi``. Controls ``(f_psi, f_phi)``: torques on the rotor and on the steering.

    Lagrangian (paper's M in the order (psi, phi, theta, x, y), with the 1/2 the paper drops)::

        L = (I psidot^2 + 2 I psidot thetadot + 2 J phidot^2 + m l^2 thetadot^2
             + m (xdot^2 + ydot^2)) / 2,

    constraints ``-l cos(phi) thetadot - sin(theta + phi) xdot + cos(theta + phi) ydot = 0`` and
    ``l cos(phi) thetadot - sin(theta - phi) xdot + cos(theta - phi) ydot = 0``, i.e. in the body
    frame ``v_y = 0`` and ``l thetadot = -tan(phi) v_x``. Reduced view (27):
    ``e_1(r) = (sin 2phi, -2 l cos^2 phi, 0)``,
    ``[A(r)] = [[I sin^2(phi) / (m l^2), 0], [-I sin(2 phi) / (2 m l), 0], [0, 0]]``.

    Continuous equations with the speed ``s`` (``xdot = -l cos(phi) cos(theta) s``,
    ``ydot = -l cos(phi) sin(theta) s``, ``thetadot = sin(phi) s``), corrected from Sec. 5.2::

        [[I, I sin phi], [I sin phi, m l^2]] (psi_ddot, s_dot) = (f_psi - I cos(phi) phidot s, 0),
        2 J phi_ddot = f_phi                    (the paper prints 2 I: a typo).

    The momentum ``mu_1 = 2 m l^2 cos(phi) s + I sin(2 phi) psidot`` obeys
    ``mu_1_dot = 2 I cos^2(phi) psidot phidot - mu_1 tan(phi) phidot``. At ``cos(phi) = 0`` the
    two constraints become dependent and the reduced description breaks down
    (:meth:`singular`).

    Args:
        m: mass. l: half wheelbase. I: rotor inertia. J: inertia of one wheel set about its
            steering axis. All positive, and ``I < m l^2`` (the board's yaw inertia is
            normalised so that ``J_board + I + 2 J = m l^2``).
    """

    m: Array = eqx.field(converter=positive_parameter)
    l: Array = eqx.field(converter=positive_parameter)  # noqa: E741
    I: Array = eqx.field(converter=positive_parameter)  # noqa: E741
    J: Array = eqx.field(converter=positive_parameter)

    shape_names: ClassVar[tuple[str, ...]] = ("psi", "phi")
    control_names: ClassVar[tuple[str, ...]] = ("f_psi", "f_phi")
    kinematic: ClassVar[tuple[bool, ...]] = (False, False)
    n_velocities: ClassVar[int] = 3

    def __check_init__(self):
        check_positive(self, "m", "l", "I", "J")
        if _concrete(self.I) and _concrete(self.m) and _concrete(self.l):
            inertia, m, l = (np.asarray(x) for x in (self.I, self.m, self.l))
            if not bool(np.all(inertia < m * l**2)):
                raise ValueError(
                    f"Snakeboard: parameter 'I' must satisfy I < m l^2 (rotor inertia below the "
                    f"board's), got I={inertia}, m l^2={m * l**2}"
                )

    # reduced view
    def reduced_lagrangian(self, r, u, xi):
        return 0.5 * (
            self.I * u[0] ** 2
            + 2.0 * self.I * u[0] * xi[0]
            + 2.0 * self.J * u[1] ** 2
            + self.m * self.l**2 * xi[0] ** 2
            + self.m * (xi[1] ** 2 + xi[2] ** 2)
        )

    def connection(self, r):
        phi = r[1]
        z = jnp.zeros_like(phi)
        ml2 = self.m * self.l**2
        return jnp.array(
            [
                [self.I * jnp.sin(phi) ** 2 / ml2, z],
                [-self.I * jnp.sin(2 * phi) / (2 * self.m * self.l), z],
                [z, z],
            ]
        )

    def symmetry_basis(self, r):
        return self.e1(r[1])[:, None]

    def e1(self, phi):
        """``e_1(phi) = (sin 2phi, -2 l cos^2 phi, 0)`` (27)."""
        return jnp.stack([jnp.sin(2 * phi), -2 * self.l * jnp.cos(phi) ** 2, jnp.zeros_like(phi)])

    def inputs(self, controls):
        return controls, jnp.zeros_like(controls)

    # full view
    def constraint_forms(self, q):
        th, phi = q[2], q[4]
        z = jnp.zeros_like(th)
        lc = self.l * jnp.cos(phi)
        return jnp.array(
            [
                [-jnp.sin(th + phi), jnp.cos(th + phi), -lc, z, z],
                [-jnp.sin(th - phi), jnp.cos(th - phi), lc, z, z],
            ]
        )

    # minimal continuous form, v = (psidot, phidot, s)
    def qdot_from_velocities(self, q, v, u_kin):
        th, phi = q[2], q[4]
        s = v[2]
        lcs = self.l * jnp.cos(phi) * s
        return jnp.stack([-lcs * jnp.cos(th), -lcs * jnp.sin(th), jnp.sin(phi) * s, v[0], v[1]])

    def velocities_from_qdot(self, q, qdot):
        th, phi = q[2], q[4]
        vx = jnp.cos(th) * qdot[0] + jnp.sin(th) * qdot[1]
        s = jnp.sin(phi) * qdot[2] - jnp.cos(phi) * vx / self.l
        return jnp.stack([qdot[3], qdot[4], s])

    def velocity_dynamics(self, q, v, f, u_kin):
        phi = q[4]
        psidot, phidot, s = v
        sp = jnp.sin(phi)
        rhs = f[0] - self.I * jnp.cos(phi) * phidot * s
        det = self.I * (self.m * self.l**2 - self.I * sp**2)
        psi_dd = self.m * self.l**2 * rhs / det
        s_d = -self.I * sp * rhs / det
        return jnp.stack([psi_dd, f[1] / (2 * self.J), s_d])

    def singularity(self, q):
        """``cos(phi)``: the reduced description breaks down where it vanishes."""
        return jnp.cos(q[4])

    def sample_maneuver(self, key, *, n_terms: int = 2, max_steer: float = 1.0):
        """A random maneuver that stays away from the singularity ``cos(phi) = 0``.

        Rotor torque: ``n_terms`` sinusoids with amplitudes ``I U(0.5, 3)``, frequencies
        ``U(0.5, 3)`` rad/s. Steering: ``phi(t) = phi_c + b sin(w t + p)`` produced by the torque
        ``f_phi = -2 J b w^2 sin(w t + p)`` with ``phi(0), phidot(0)`` matched to it (DESIGN.md
        section 6: an unmatched phase drives phi into the singularity), ``|phi_c| + b <= max_steer``.
        Deterministic in ``key``; vmap over keys for a batch.

        Returns:
            ``(q0, qdot0, controls)`` with ``qdot0`` on the constraints.
        """
        from .._controls import Sinusoids

        ks = jax.random.split(key, 12)
        dtype = self.m.dtype
        u = lambda k, shape, lo, hi: jax.random.uniform(k, shape, dtype, lo, hi)  # noqa: E731
        sign = lambda k, shape: jnp.where(jax.random.bernoulli(k, 0.5, shape), 1.0, -1.0).astype(dtype)  # noqa: E731
        a_f = self.I * u(ks[0], (n_terms,), 0.5, 3.0) * sign(ks[1], (n_terms,))
        w_f = u(ks[2], (n_terms,), 0.5, 3.0)
        p_f = u(ks[3], (n_terms,), 0.0, 2 * jnp.pi)
        b = u(ks[4], (), 0.2, 0.7) * max_steer
        phi_c = u(ks[5], (), -1.0, 1.0) * (max_steer - b)
        w = u(ks[6], (), 0.5, 2.5)
        p = u(ks[7], (), 0.0, 2 * jnp.pi)
        a_s = jnp.zeros(n_terms, dtype).at[0].set(-2 * self.J * b * w**2)
        w_s = jnp.ones(n_terms, dtype).at[0].set(w)
        p_s = jnp.zeros(n_terms, dtype).at[0].set(p)
        ctl = Sinusoids(
            amplitude=jnp.stack([a_f, a_s]), frequency=jnp.stack([w_f, w_s]), phase=jnp.stack([p_f, p_s])
        )
        zero = jnp.zeros((), dtype)
        q0 = jnp.stack([zero, zero, u(ks[8], (), -jnp.pi, jnp.pi), zero, phi_c + b * jnp.sin(p)])
        v0 = jnp.stack([u(ks[9], (), -1.0, 1.0), b * w * jnp.cos(p), u(ks[10], (), -0.6, 0.6)])
        qdot0 = self.qdot_from_velocities(q0, v0, jnp.zeros(2, dtype))
        return q0, qdot0, ctl

    # closed-form RDP step (paper Sec. 5.2 corrected), dtau^-1 truncated to I - ad/2
    def rdp_closed_form(self, alpha, h, r, u_kin, b, m_in):
        """Solve the snakeboard's RDP step: explicit phi row, then a 2 x 2 linear solve.

        ``u^phi_k = b_phi / (2 J)``, ``phi_a = phi_k + alpha h u^phi_k``, ``xi_k = c_k e_1(phi_a)``, and::

            [[1, sin 2phi_a], [I sin 2phi_k, m l^2 kappa]] (u^psi_k, c_k)
                = (b_psi / I, <mu_in, e_1(phi_k)>),
            kappa = 4 cos(phi_a) cos(phi_k) cos(phi_a - phi_k),

        with ``b = d_u l_{k-1} + h F_k`` (row 1 is the rotor's horizontal equation, row 2 the
        discrete momentum equation (21)).
        """
        phi_k = r[1]
        u_phi = b[1] / (2 * self.J)
        phi_a = phi_k + alpha * h * u_phi
        s2a, s2k = jnp.sin(2 * phi_a), jnp.sin(2 * phi_k)
        ca, ck = jnp.cos(phi_a), jnp.cos(phi_k)
        ml2 = self.m * self.l**2
        kappa = 4 * ca * ck * jnp.cos(phi_a - phi_k)
        b1 = b[0] / self.I
        b2 = m_in @ self.e1(phi_k)
        det = ml2 * kappa - self.I * s2k * s2a
        u_psi = (ml2 * kappa * b1 - s2a * b2) / det
        c = (b2 - self.I * s2k * b1) / det
        xi = c * self.e1(phi_a)
        return jnp.stack([u_psi, u_phi]), xi
