"""The snakeboard (paper Sec. 5.2, corrected; ``docs/mathematics.md`` section 6)."""

from __future__ import annotations

from typing import ClassVar, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._numerics import materialise, plain_active, safe_norm, saved, sincos
from ..lie._scalar import (
    Pose,
    body_to_qdot,
    dtau1_transpose,
    pose_from_xy_theta,
    pose_retract,
)
from ..lie._se2 import exp_parts, exp_series_derivative, small_angle
from ._base import concrete, physical_parameter, positive_checks, random_draws
from ._closed_form import AbstractClosedFormSystem

__all__ = ["Snakeboard", "SnakeboardKernelState"]


class SnakeboardKernelState(NamedTuple):
    """The snakeboard's RDP kernel state: pose, shape with the steering angle's cosine and sine,
    and the incoming momenta ``pu = (p_psi, p_phi)``, ``mu = (mu_1, mu_2, mu_3)``."""

    pose: Pose
    psi: Array
    phi: Array
    cos_phi: Array
    sin_phi: Array
    pu: tuple[Array, Array]
    mu: tuple[Array, Array, Array]


def _below(I, m, l):  # noqa: E741
    """``I < m l^2``: in NumPy for known values (no eager program), traced otherwise."""
    if all(concrete(x) for x in (I, m, l)):
        return np.asarray(I) < np.asarray(m) * np.asarray(l) ** 2
    return I < m * l**2


class Snakeboard(AbstractClosedFormSystem):
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
        m: mass (kg, default 1). l: half wheelbase (m, default 0.5). I: rotor inertia (kg m^2,
            default 0.05). J: inertia of one wheel set about its steering axis (kg m^2, default
            0.02). All positive, and ``I < m l^2`` (the board's yaw inertia is
            normalised so that ``J_board + I + 2 J = m l^2``).
    """

    m: Array = eqx.field(converter=physical_parameter, default=1.0)
    l: Array = eqx.field(converter=physical_parameter, default=0.5)  # noqa: E741
    I: Array = eqx.field(converter=physical_parameter, default=0.05)  # noqa: E741
    J: Array = eqx.field(converter=physical_parameter, default=0.02)

    shape_names: ClassVar[tuple[str, ...]] = ("psi", "phi")
    cyclic_names: ClassVar[tuple[str, ...] | None] = ("psi",)  # the rotor angle (not phi, the steering)
    control_names: ClassVar[tuple[str, ...]] = ("f_psi", "f_phi")
    kinematic: ClassVar[tuple[bool, ...]] = (False, False)
    n_velocities: ClassVar[int] = 3

    def parameter_checks(self):
        return positive_checks(self, "m", "l", "I", "J") + (
            (
                "parameter 'I' must satisfy I < m l^2 (the rotor's inertia below the board's)",
                _below(self.I, self.m, self.l),
            ),
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

    def reduced_energy(self, r, u, xi):
        """``E = l`` (the reduced Lagrangian is the kinetic energy), written out: the general
        ``<d_u l, u> + <d_xi l, xi> - l`` by autodiff left a dot product of its own in every
        node's observation."""
        return self.reduced_lagrangian(r, u, xi)

    def power(self, f, rdot):
        """``<f, rdot> = f_psi psidot + f_phi phidot``, written out (a dot product was a kernel
        of its own in every node's observation)."""
        return f[0] * rdot[0] + f[1] * rdot[1]

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
    def body_constraints(self, r):
        """``C(phi) [xi; rdot] = 0``: rows ``(-l cos phi, -sin phi, cos phi, 0, 0)`` and
        ``(l cos phi, sin phi, cos phi, 0, 0)`` (the two wheel sets roll without slipping)."""
        sp, cp = jnp.sin(r[1]), jnp.cos(r[1])
        z, lc = jnp.zeros_like(cp), self.l * cp
        return jnp.array([[-lc, -sp, cp, z, z], [lc, sp, cp, z, z]])

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

    def velocity_dynamics(self, q, v, f, u_kin, u_kin_dot=None):
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

    # one compiled program per signature (op by op, a first draw compiled some 50 small ones)
    @eqx.filter_jit
    def sample_maneuver(self, key, *, n_terms: int = 2, max_steer: float = 1.0):
        """A random maneuver that stays away from the singularity ``cos(phi) = 0``.

        Rotor torque: ``n_terms`` sinusoids with amplitudes ``I U(0.5, 3)``, frequencies
        ``U(0.5, 3)`` rad/s. Steering: ``phi(t) = phi_c + b sin(w t + p)`` produced by the torque
        ``f_phi = -2 J b w^2 sin(w t + p)`` with ``phi(0), phidot(0)`` matched to it (``docs/mathematics.md``
        section 6: an unmatched phase drives phi into the singularity), ``|phi_c| + b <= max_steer``.
        Deterministic in ``key``; vmap over keys for a batch.

        Returns:
            ``(q0, qdot0, controls)`` with ``qdot0`` on the constraints.
        """
        from .._controls import Sinusoids

        dtype = self.m.dtype
        ks, u, sign = random_draws(key, 12, dtype)
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

    # --------------------------------------------- closed-form RDP (paper Sec. 5.2, corrected)
    def _solve(self, b_psi, nu, s_k, c_k, s_a, c_a):
        """The rotor's horizontal row and the momentum equation (21), solved for ``(u^psi, c)``
        with ``xi = c e_1(phi_a)``::

            [[1, sin 2phi_a], [I sin 2phi_k, m l^2 kappa]] (u^psi, c) = (b_psi / I, nu),
            kappa = 4 cos(phi_a) cos(phi_k) cos(phi_a - phi_k),

        ``b_psi = p_psi + h (1 - alpha) f^psi_{k+alpha}``, ``nu = <mu_in, e_1(phi_k)>``; the
        determinant ``4 cos phi_a cos phi_k (m l^2 cos(phi_a - phi_k) - I sin phi_a sin phi_k)``
        vanishes only at ``cos phi = 0``. At ``phi_a = phi_k`` and ``h = 0`` this is the
        reduced Legendre transform's inverse (the node velocity)."""
        ml2 = self.m * self.l**2
        s2a, s2k = 2 * s_a * c_a, 2 * s_k * c_k
        kappa = 4 * c_a * c_k * (c_a * c_k + s_a * s_k)
        b1 = b_psi / self.I
        det = ml2 * kappa - self.I * s2k * s2a
        u_psi = (ml2 * kappa * b1 - s2a * nu) / det
        c = (nu - self.I * s2k * b1) / det
        return u_psi, c

    def kernel_init(self, q, pu, mu):
        s, c = sincos(q[4])
        return SnakeboardKernelState(
            pose_from_xy_theta(q[0], q[1], q[2]), q[3], q[4], c, s, (pu[0], pu[1]), (mu[0], mu[1], mu[2])
        )

    def kernel_momenta(self, state):
        g = state.pose
        q = jnp.stack([g.x, g.y, g.theta, state.psi, state.phi])
        return q, jnp.stack(state.pu), jnp.stack(state.mu)

    def kernel_step(self, alpha, h, retraction, state, c0, c1):
        """One RDP step (paper Sec. 5.2, corrected): the steering row is explicit,
        ``u^phi = b_phi / (2 J)``, then the 2 x 2 solve of :meth:`_solve` at ``phi_a``; the incoming
        momenta of the next node are ``pu = d_u l + h alpha f_{k+alpha}`` (``d_r l = 0``) and
        ``mu = (I + ad_{h xi} / 2)^T d_xi l``."""
        return self._step_parts(alpha, h, retraction, state, c0, c1)[:3]

    def kernel_step_reverse(self, alpha, h, retraction, state, c0, c1):
        """:meth:`kernel_step` with a hand-written VJP (:func:`_symmetric_step`) for the
        symmetric step (``alpha = 1/2``, a Python float) with the exponential map."""
        if isinstance(alpha, float) and alpha == 0.5 and retraction == "exp" and not plain_active():
            return _symmetric_step(self, h, state, c0, c1)
        return self.kernel_step(alpha, h, retraction, state, c0, c1)

    def _step_parts(self, alpha, h, retraction, state, c0, c1):
        """:meth:`kernel_step` and its right-hand side ``b = pu + h (1 - alpha) f_{k+alpha}``
        (the one intermediate value its VJP reads)."""
        a = alpha
        m, l, inertia, jj = self.m, self.l, self.I, self.J
        ml2 = m * l**2
        ck, sk = state.cos_phi, state.sin_phi
        fa = ((1 - a) * c0[0] + a * c1[0], (1 - a) * c0[1] + a * c1[1])
        b = (state.pu[0] + h * (1 - a) * fa[0], state.pu[1] + h * (1 - a) * fa[1])
        u_phi = b[1] / (2 * jj)
        phi_next = state.phi + h * u_phi
        if isinstance(a, float) and a == 0.0:  # phi_a = phi_k: reuse the carried values
            sa, ca = sk, ck
            sn, cn = sincos(phi_next)
        elif isinstance(a, float) and a == 1.0:  # phi_a = phi_{k+1}
            sn, cn = sincos(phi_next)
            sa, ca = sn, cn
        elif isinstance(a, float) and a == 0.5:
            # phi_a and phi_{k+1} are phi_k turned by d and 2 d, d = h u^phi / 2: one sincos, two
            # rotations of the carried (cos, sin), renormalised to first order at every step
            sd, cd = sincos(0.5 * h * u_phi)
            sa, ca = _turned(sk, ck, sd, cd)
            sn, cn = _turned(sa, ca, sd, cd)
            unit = 1.5 - 0.5 * (sn * sn + cn * cn)  # one Newton step back to the unit circle
            sn, cn = sn * unit, cn * unit
        else:
            sa, ca = sincos(state.phi + a * h * u_phi)
            sn, cn = sincos(phi_next)
        sa, ca, sn, cn = saved(*materialise(sa, ca, sn, cn))
        e1k = (2 * sk * ck, -2 * l * ck**2)
        nu = state.mu[0] * e1k[0] + state.mu[1] * e1k[1]  # <mu_in, e_1(phi_k)> (mu_3 pairs with 0)
        u_psi, c = self._solve(b[0], nu, sk, ck, sa, ca)
        xi = (c * 2 * sa * ca, -2 * l * ca**2 * c, jnp.zeros_like(c))
        dl_du = (inertia * (u_psi + xi[0]), 2 * jj * u_phi)
        mu_new = (ml2 * xi[0] + inertia * u_psi, m * xi[1], m * xi[2])
        hxi = tuple(h * x for x in xi)
        # residual of (23) (psi, phi rows) and (21), rebuilt from the solution
        jump = tuple(x - y for x, y in zip(dtau1_transpose(hxi, mu_new, 1.0), state.mu))
        a_k = (inertia * sk**2 / ml2, -inertia * sk * ck / (m * l))  # first column of A(phi_k)
        hor0 = dl_du[0] - (a_k[0] * jump[0] + a_k[1] * jump[1]) - b[0]
        vert = e1k[0] * jump[0] + e1k[1] * jump[1]
        scale = 1.0 + safe_norm(b[0], b[1]) + safe_norm(*state.mu)
        residual = safe_norm(hor0, dl_du[1] - b[1], vert) / scale
        singular = (jnp.abs(cn) < jnp.finfo(cn.dtype).eps ** 0.25) | (cn * ck < 0)
        new = SnakeboardKernelState(
            pose_retract(state.pose, hxi, retraction),
            state.psi + h * u_psi,
            phi_next,
            cn,
            sn,
            (dl_du[0] + h * a * fa[0], dl_du[1] + h * a * fa[1]),
            dtau1_transpose(hxi, mu_new, -1.0),
        )
        return new, residual, singular, b

    def _kernel_velocity(self, state):
        """Configuration, velocities ``(u, xi)`` from the carried momenta (:meth:`_solve` at
        ``h = 0``) and the node's momentum ``nu = <mu_in, e_1(phi_k)>``."""
        ck, sk = state.cos_phi, state.sin_phi
        l = self.l
        nu = state.mu[0] * 2 * sk * ck - state.mu[1] * 2 * l * ck**2
        u_psi, cc = self._solve(state.pu[0], nu, sk, ck, sk, ck)
        u = jnp.stack([u_psi, state.pu[1] / (2 * self.J)])
        xi = jnp.stack([cc * 2 * sk * ck, -2 * l * ck**2 * cc, jnp.zeros_like(cc)])
        g = state.pose
        return jnp.stack([g.x, g.y, g.theta, state.psi, state.phi]), u, xi, nu

    def kernel_observe(self, state, c):
        q, u, xi, nu = self._kernel_velocity(state)
        # |C(phi) [xi; u]| (body_constraints) with the carried cos and sin of phi
        ck, sk = state.cos_phi, state.sin_phi
        lc = self.l * ck * xi[0]
        rest = sk * xi[1]
        rows = (-lc - rest + ck * xi[2], lc + rest + ck * xi[2])
        return self.observation(
            q,
            u,
            xi,
            c,
            rotation=(state.pose.cos, state.pose.sin),
            momentum=nu[None],
            constraint_residual=safe_norm(rows[0], rows[1]),
        )

    def kernel_node(self, state, c):
        q, u, xi, _ = self._kernel_velocity(state)
        return q, body_to_qdot(state.pose, u, xi)


def _turned(s: Array, c: Array, sd: Array, cd: Array) -> tuple[Array, Array]:
    """``(sin, cos)(x + d)`` from ``(sin, cos) x`` and ``(sin, cos) d``: a rotation by ``d``."""
    return s * cd + c * sd, c * cd - s * sd


@jax.custom_vjp
def _symmetric_step(system: Snakeboard, h: Array, state: SnakeboardKernelState, c0: Array, c1: Array):
    """``system.kernel_step(0.5, h, "exp", state, c0, c1)`` with a hand-written VJP.

    The VJP is the transpose of the step's derivative written out (the solve of
    :meth:`Snakeboard._solve` by its adjoint, the rotations of the steering angle's cosine and sine,
    the exponential map with its Taylor branch): no cotangent sums over broadcast shapes. It reads
    from the forward pass only the step's right-hand side ``b = pu + h f / 2`` (it depends on the
    controls, whose sines it would otherwise recompute) and rebuilds the rest from ``b`` and the
    carried state with the step's own expressions: the half turn's ``(sin, cos)(h u^phi / 2)``,
    ``(sin, cos) phi_a`` (the carried ``(sin, cos) phi_k`` turned by it), ``(u^psi, c)`` (the
    2 x 2 solve) and the rotation's ``(sin, cos) w``. Under the rollout's reverse mode every saved
    value is an ``(N, B)`` array that the forward loop writes and the backward reads, its memory
    mapped afresh (first-touch page faults) at every call: 2 here, against 8 with the sines and
    cosines, ``u^psi`` and ``c`` saved (``docs/development.md`` has the measurements). The
    derivatives with respect to the model's parameters and the step size come from JAX's own VJP
    of :meth:`Snakeboard.kernel_step` (computed only when a loss asks for them). The residual, a
    diagnostic, has no derivative.
    """
    return system.kernel_step(0.5, h, "exp", state, c0, c1)


def _symmetric_fwd(system, h, state, c0, c1):
    new, residual, singular, b = system._step_parts(0.5, h, "exp", state, c0, c1)
    # the step's right-hand side b = pu + h f / 2 (it reads the controls): the backward rebuilds
    # the rest from it and the carried state with the step's own expressions
    b_psi, b_phi = saved(*b)
    return (new, residual, singular), (system, h, state, c0, c1, b_psi, b_phi)


def _symmetric_bwd(res, ct):
    system, h, state, c0, c1, b_psi, b_phi = res
    nb = ct[0]
    m, l, inertia, jj = system.m, system.l, system.I, system.J
    ml2 = m * l**2
    sd, cd = sincos(0.5 * h * (b_phi / (2 * jj)))  # the half turn h u^phi / 2, u^phi = b_phi / 2J
    ck, sk = state.cos_phi, state.sin_phi
    mu0, mu1 = state.mu[0], state.mu[1]
    g = state.pose
    # forward values rebuilt from the saved ones (the same expressions as the step's)
    nu = mu0 * (2 * sk * ck) + mu1 * (-2 * l * ck**2)
    sa, ca = _turned(sk, ck, sd, cd)
    u_psi, cc = system._solve(b_psi, nu, sk, ck, sa, ca)
    xi0 = cc * 2 * sa * ca
    xi1 = -2 * l * ca**2 * cc
    w, v2 = h * xi0, h * xi1
    n2 = m * xi1
    small, ws = small_angle(w)
    sw0, cw0 = sincos(ws)  # the exponential map's rotation (its safe stand-in, as the step's)
    ta, tb, cr, sr = exp_parts(w, sw0, cw0)
    dx, dy = ta * v2, tb * v2
    # the next state's incoming momenta mu = (n1, n2, -w n2 / 2) and pu
    pb0, pb1 = nb.pu
    mb0, mb1, mb2 = nb.mu
    n1b = mb0
    n2b = mb1 - 0.5 * w * mb2
    wb = -0.5 * n2 * mb2 + nb.pose.theta
    u_psib = inertia * pb0 + h * nb.psi + inertia * n1b
    xi0b = inertia * pb0 + ml2 * n1b
    u_phib = 2 * jj * pb1 + h * nb.phi
    xi1b = m * n2b
    # the exponential map: g' = g exp(w, v2, 0)
    pxb, pyb, pcb, psb = nb.pose.x, nb.pose.y, nb.pose.cos, nb.pose.sin
    c, s = g.cos, g.sin
    g_cb = pxb * dx + pyb * dy + pcb * cr + psb * sr
    g_sb = -pxb * dy + pyb * dx - pcb * sr + psb * cr
    dxb = pxb * c + pyb * s
    dyb = -pxb * s + pyb * c
    crb = pcb * c + psb * s
    srb = -pcb * s + psb * c
    v2b = dxb * ta + dyb * tb
    tab, tbb = dxb * v2, dyb * v2
    # below the threshold (d/dw of the series: cos' = -sin = -w sinc, sin' = cos = 1 - w cosc)
    dsinc, dcosc = exp_series_derivative(w)
    w_small = tab * dsinc + tbb * dcosc - crb * (w * ta) + srb * cr
    sw0b = tab / ws + srb
    cw0b = -tbb / ws + crb
    w_big = -tab * ta / ws - tbb * tb / ws + cw0 * sw0b - sw0 * cw0b
    wb = wb + jnp.where(small, w_small, w_big)
    # a division by a runtime 1 marks a value "expensive" for XLA's fusion pass, which then computes
    # it once instead of fusing the chain that makes it into every consumer
    one = jax.lax.stop_gradient(w) * 0 + 1
    wb, v2b = wb / one, v2b / one
    xi0b = xi0b + h * wb
    xi1b = xi1b + h * v2b
    # xi = (c sin 2phi_a, -2 l cos^2 phi_a c, 0)
    ccb = 2 * sa * ca * xi0b - 2 * l * ca**2 * xi1b
    sab = 2 * cc * ca * xi0b
    cab = 2 * cc * sa * xi0b - 4 * l * ca * cc * xi1b
    # the solve: det (u^psi, c) = (ml2 kappa b0 / I - s2a nu, nu - s2k b0)
    s2a, s2k = 2 * sa * ca, 2 * sk * ck
    gk = ca * ck + sa * sk
    kappa = 4 * ca * ck * gk
    b1_ = b_psi / inertia
    det = ml2 * kappa - inertia * s2k * s2a
    ub, cb = u_psib / det, ccb / det
    detb = -(ub * u_psi + cb * cc)
    kappab = ml2 * (b1_ * ub + detb)
    b0b = (ml2 * kappa * ub - inertia * s2k * cb) / inertia
    s2ab = -nu * ub - inertia * s2k * detb
    nub = cb - s2a * ub
    s2kb = -inertia * (b1_ * cb + s2a * detb)
    k4 = 4 * kappab
    cab = cab + k4 * ck * (gk + ca * ck) + 2 * sa * s2ab
    sab = sab + k4 * ca * ck * sk + 2 * ca * s2ab
    ckb = k4 * ca * (gk + ca * ck) + 2 * sk * s2kb + nub * (2 * sk * mu0 - 4 * l * ck * mu1)
    skb = k4 * ca * ck * sa + 2 * ck * s2kb + nub * 2 * ck * mu0
    sab, cab, skb, ckb = sab / one, cab / one, skb / one, ckb / one
    # phi_a and phi_{k+1}: (sa, ca) = (sk, ck) turned by d, (sn, cn) = (sa, ca) turned by d, renormalised
    sn_, cn_ = sa * cd + ca * sd, ca * cd - sa * sd
    unit = 1.5 - 0.5 * (sn_ * sn_ + cn_ * cn_)
    unitb = nb.sin_phi * sn_ + nb.cos_phi * cn_
    snb = nb.sin_phi * unit - unitb * sn_
    cnb = nb.cos_phi * unit - unitb * cn_
    sab = sab + snb * cd - cnb * sd
    cab = cab + snb * sd + cnb * cd
    cdb = snb * sa + cnb * ca + sab * sk + cab * ck
    sdb = snb * ca - cnb * sa + sab * ck - cab * sk
    skb = skb + sab * cd - cab * sd
    ckb = ckb + sab * sd + cab * cd
    u_phib = u_phib + 0.5 * h * (sdb * cd - cdb * sd)
    b1b = u_phib / (2 * jj)
    fa0b, fa1b = 0.5 * h * (pb0 + b0b), 0.5 * h * (pb1 + b1b)
    zero = jnp.zeros_like(mb2)
    state_b = SnakeboardKernelState(
        Pose(pxb, pyb, nb.pose.theta, g_cb, g_sb),
        nb.psi,
        nb.phi,
        ckb,
        skb,
        (b0b, b1b),
        (nub * 2 * sk * ck, nub * (-2 * l * ck**2), zero),
    )
    c_b = jnp.stack([0.5 * fa0b, 0.5 * fa1b])
    # the model's parameters and the step size: JAX's own VJP (dropped by XLA when not asked for)
    _, pull = jax.vjp(lambda sys, hh: sys.kernel_step(0.5, hh, "exp", state, c0, c1)[0], system, h)
    system_b, h_b = pull(nb)
    return system_b, h_b, state_b, c_b, c_b


_symmetric_step.defvjp(_symmetric_fwd, _symmetric_bwd)
