"""The system description shared by every integrator (DESIGN.md section 1).

A system lives on ``Q = M x SE(2)`` with coordinates ``q = (x, y, theta, r_1, ..., r_n)``.
It is described once, in two views that must agree:

* the *reduced view* read by RDP: reduced Lagrangian ``l(r, u, xi)``, nonholonomic connection
  ``A(r)`` (3 x n), constrained-symmetry basis ``e(r)`` (3 x c), and shape forces;
* the *full view* read by RK, the diffrax reference and the checks: the Lagrangian
  ``L(q, qdot) = l(r, rdot, g^-1 gdot)`` and the constraint one-forms ``omega(q) qdot = 0``.

Shape coordinates are either force-driven or *kinematic*: the velocity of a kinematic shape
coordinate is prescribed by a control channel (the car's steering rate ``sigma_dot = u_sigma``).
"""

from __future__ import annotations

import abc
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from .._linalg import solve

__all__ = ["AbstractSystem", "body_velocity", "positive_parameter"]


def positive_parameter(x: ArrayLike) -> Array:
    """Converter for physical parameters: a floating array (default float dtype for ints)."""
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    return x


def _concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def check_positive(obj, *names: str) -> None:
    """Raise ``ValueError`` naming the parameter when a concrete parameter is not positive."""
    for name in names:
        value = getattr(obj, name)
        if _concrete(value) and not bool(np.all(np.asarray(value) > 0)):
            raise ValueError(f"{type(obj).__name__}: parameter {name!r} must be positive, got {value}")


def body_velocity(q: Float[Array, " d"], qdot: Float[Array, " d"]) -> Float[Array, 3]:
    """``xi = g^-1 gdot = (thetadot, c xdot + s ydot, -s xdot + c ydot)`` for ``q = (x, y, theta, r)``."""
    c, s = jnp.cos(q[2]), jnp.sin(q[2])
    return jnp.stack([qdot[2], c * qdot[0] + s * qdot[1], -s * qdot[0] + c * qdot[1]])


def spatial_velocity(q: Float[Array, " d"], xi: Float[Array, 3]) -> Float[Array, 3]:
    """``(xdot, ydot, thetadot)`` from the body velocity ``xi = (omega, v_x, v_y)``."""
    c, s = jnp.cos(q[2]), jnp.sin(q[2])
    return jnp.stack([c * xi[1] - s * xi[2], s * xi[1] + c * xi[2], xi[0]])


class AbstractSystem(eqx.Module):
    """A nonholonomic mechanical system with SE(2) symmetry.

    Subclasses give the reduced view (:meth:`reduced_lagrangian`, :meth:`connection`,
    :meth:`symmetry_basis`), the constraint one-forms (:meth:`constraint_forms`), how control
    channels enter (:meth:`inputs`), and the continuous equations of motion in a minimal set of
    velocities ``v`` (:meth:`qdot_from_velocities`, :meth:`velocities_from_qdot`,
    :meth:`velocity_dynamics`). Everything else (full Lagrangian, energy, momentum, the
    Lagrange-d'Alembert accelerations used to check the equations) is derived here.
    """

    shape_names: ClassVar[tuple[str, ...]]
    control_names: ClassVar[tuple[str, ...]]
    kinematic: ClassVar[tuple[bool, ...]]
    n_velocities: ClassVar[int]

    @property
    def n_shape(self) -> int:
        return len(self.shape_names)

    @property
    def n_config(self) -> int:
        return 3 + self.n_shape

    @property
    def n_controls(self) -> int:
        return len(self.control_names)

    @property
    def dynamic_index(self) -> tuple[int, ...]:
        """Indices of force-driven shape coordinates."""
        return tuple(i for i, k in enumerate(self.kinematic) if not k)

    @property
    def kinematic_index(self) -> tuple[int, ...]:
        """Indices of shape coordinates whose velocity is prescribed."""
        return tuple(i for i, k in enumerate(self.kinematic) if k)

    # ----------------------------------------------------------------- reduced view
    @abc.abstractmethod
    def reduced_lagrangian(self, r: Array, u: Array, xi: Array) -> Array:
        """``l(r, u, xi) = L(r, u, e, xi)``."""

    @abc.abstractmethod
    def connection(self, r: Array) -> Float[Array, "3 n"]:
        """Local form ``[A(r)]`` of the nonholonomic connection: ``xi = Omega - A(r) rdot``."""

    @abc.abstractmethod
    def symmetry_basis(self, r: Array) -> Float[Array, "3 c"]:
        """Body-fixed basis ``[e_1(r), ..., e_c(r)]`` of the constrained symmetries ``s_r``."""

    @abc.abstractmethod
    def inputs(self, controls: Array) -> tuple[Array, Array]:
        """Split control channel values into shape forces ``f`` (n,) and prescribed shape
        velocities ``u_kin`` (n,; only the kinematic entries are read)."""

    # ------------------------------------------------------------------- full view
    def lagrangian(self, q: Array, qdot: Array) -> Array:
        """``L(q, qdot) = l(r, rdot, g^-1 gdot)`` (the symmetry reduces L to l)."""
        return self.reduced_lagrangian(q[3:], qdot[3:], body_velocity(q, qdot))

    @abc.abstractmethod
    def constraint_forms(self, q: Array) -> Float[Array, "m d"]:
        """Constraint one-forms ``omega(q)`` with ``omega(q) qdot = 0`` (prescribed shape
        velocities excluded)."""

    # ----------------------------------------------- continuous equations, minimal form
    @abc.abstractmethod
    def qdot_from_velocities(self, q: Array, v: Array, u_kin: Array) -> Array:
        """``qdot`` on the constraint distribution from independent velocities ``v``."""

    @abc.abstractmethod
    def velocities_from_qdot(self, q: Array, qdot: Array) -> Array:
        """Inverse of :meth:`qdot_from_velocities` on the constraint distribution."""

    @abc.abstractmethod
    def velocity_dynamics(self, q: Array, v: Array, f: Array, u_kin: Array) -> Array:
        """``vdot`` from the Lagrange-d'Alembert equations."""

    def singularity(self, q: Array) -> Array:
        """A scalar that vanishes where the reduced description breaks down (default 1: never).

        Rollouts report a failure when it falls below ``eps**0.25`` in magnitude or changes sign
        within a step."""
        return jnp.ones((), q.dtype)

    def singular(self, q: Array, q_prev: Array | None = None) -> Bool[Array, ""]:
        """True at (or, given ``q_prev``, across) a singularity of the reduced description."""
        s = self.singularity(q)
        out = jnp.abs(s) < jnp.finfo(q.dtype).eps ** 0.25
        if q_prev is not None:
            out = out | (s * self.singularity(q_prev) < 0)
        return out

    # ----------------------------------------------------------------- derived
    def energy(self, q: Array, qdot: Array) -> Array:
        """Energy ``E = <dL/dqdot, qdot> - L``."""
        lag, p = jax.value_and_grad(self.lagrangian, argnums=1)(q, qdot)
        return jnp.dot(p, qdot) - lag

    def momentum(self, q: Array, qdot: Array) -> Float[Array, " c"]:
        """Nonholonomic momentum ``mu_b = <dl/dxi, e_b(r)>`` (paper (7))."""
        r, rdot, xi = q[3:], qdot[3:], body_velocity(q, qdot)
        mu = jax.grad(self.reduced_lagrangian, argnums=2)(r, rdot, xi)
        return self.symmetry_basis(r).T @ mu

    def constraint_residual(self, q: Array, qdot: Array) -> Array:
        """``|omega(q) qdot|`` (Euclidean norm)."""
        return jnp.linalg.norm(self.constraint_forms(q) @ qdot)

    def power(self, f: Array, qdot: Array) -> Array:
        """Power of the shape forces ``<f, rdot>`` (kinematic coordinates carry no force)."""
        idx = jnp.asarray(self.dynamic_index, dtype=int)
        return jnp.dot(f[idx], qdot[3:][idx])

    def full_acceleration(self, q: Array, qdot: Array, f: Array, u_kin_dot: Array) -> tuple[Array, Array]:
        """Accelerations from the full Lagrange-d'Alembert equations, by autodiff.

        Solves the KKT system
        ``M(q) qddot = dL/dq - (d/dq dL/dqdot) qdot + F + omega^T lambda``,
        ``omega(q) qddot + (d/dq (omega(q) qdot)) qdot = 0`` and, for kinematic shape
        coordinates, ``rddot_i = d u_kin_i / dt``. ``F = (0, 0, 0, f)``.

        Returns:
            ``(qddot, lambda)``.
        """
        d = self.n_config
        dl_dqdot = jax.grad(self.lagrangian, argnums=1)
        mass = jax.jacfwd(dl_dqdot, argnums=1)(q, qdot)
        mixed = jax.jacfwd(dl_dqdot, argnums=0)(q, qdot)
        dl_dq = jax.grad(self.lagrangian, argnums=0)(q, qdot)
        force = jnp.zeros(d, q.dtype).at[3:].set(f)
        omega = self.constraint_forms(q)
        kin = jnp.asarray(self.kinematic_index, dtype=int)
        e_kin = jnp.eye(d, dtype=q.dtype)[3 + kin] if kin.size else jnp.zeros((0, d), q.dtype)
        rows = jnp.concatenate([omega, e_kin], axis=0)
        domega_qdot = jax.jacfwd(lambda qq: self.constraint_forms(qq) @ qdot)(q) @ qdot
        rhs_c = jnp.concatenate([-domega_qdot, u_kin_dot[kin] if kin.size else jnp.zeros(0, q.dtype)])
        m = rows.shape[0]
        kkt = jnp.block([[mass, -rows.T], [rows, jnp.zeros((m, m), q.dtype)]])
        rhs = jnp.concatenate([dl_dq - mixed @ qdot + force, rhs_c])
        sol = solve(kkt, rhs)
        return sol[:d], sol[d:]

    def ode(self, y: tuple[Array, Array], controls: Array) -> tuple[Array, Array]:
        """Right-hand side of the minimal continuous equations, ``y = (q, v)``."""
        q, v = y
        f, u_kin = self.inputs(controls)
        return self.qdot_from_velocities(q, v, u_kin), self.velocity_dynamics(q, v, f, u_kin)

    def consistent_qdot(self, q: Array, qdot: Array, controls: Array) -> Array:
        """``qdot`` with its kinematic shape entries replaced by the prescribed velocities."""
        _, u_kin = self.inputs(controls)
        kin = jnp.asarray(self.kinematic_index, dtype=int)
        if kin.size == 0:
            return qdot
        return qdot.at[3 + kin].set(u_kin[kin])

    def locked_velocity(self, r: Array, rdot: Array, momentum: Array) -> Float[Array, 3]:
        """Body velocity ``xi = E(r) w - A(r) rdot`` whose nonholonomic momentum
        ``E(r)^T dl/dxi`` equals ``momentum`` (c,). Exact for ``l`` quadratic in ``xi``."""
        e = self.symmetry_basis(r)
        a_rdot = self.connection(r) @ rdot
        if e.shape[1] == 0:
            return -a_rdot

        def proj(w):
            return e.T @ jax.grad(self.reduced_lagrangian, argnums=2)(r, rdot, e @ w - a_rdot)

        w0 = jnp.zeros(e.shape[1], r.dtype)
        res0 = proj(w0) - momentum
        jac = jax.jacfwd(proj)(w0)
        w = -solve(jac, res0)
        return e @ w - a_rdot
