"""The system description shared by every integrator (see ``docs/mathematics.md``, section 1).

A system lives on ``Q = M x SE(2)`` with coordinates ``q = (x, y, theta, r_1, ..., r_n)``
(positions in metres, angles in radians). It is described once, in two views that must agree:

* the *reduced view* read by RDP: reduced Lagrangian ``l(r, u, xi)``, nonholonomic connection
  ``A(r)`` (3 x n), constrained-symmetry basis ``e(r)`` (3 x c), and shape forces;
* the *full view* read by RK, DLA, GNI, the diffrax reference and the checks: the Lagrangian
  ``L(q, qdot) = l(r, rdot, g^-1 gdot)`` and the constraint one-forms ``omega(q) qdot = 0``,
  derived from the constraints in the body frame ``C(r) [xi; rdot] = 0`` (they do not depend on
  the pose: the constraints are SE(2)-invariant).

Shape coordinates are either force-driven or *kinematic*: the velocity of a kinematic shape
coordinate is prescribed by a control channel (the car's steering rate ``sigma_dot = u_sigma``).
Lie-algebra vectors are ``xi = (omega, v_x, v_y)`` (body angular rate, body-frame velocity).
"""

from __future__ import annotations

import abc
import dataclasses
from typing import Any, ClassVar, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from .._compilation_cache import as_dtype, asarray, compiled_unless_staged
from .._linalg import solve
from .._numerics import safe_vnorm

__all__ = ["AbstractSystem", "Observation", "body_velocity", "spatial_velocity", "physical_parameter"]


def physical_parameter(x: Any) -> Array:
    """Converter for physical parameters: a floating array (the default float dtype for ints).

    Raises:
        TypeError: for anything that is not a real number or an array of real numbers (e.g. a
            string, ``None``, a complex number); the message names the parameter.
    """
    from .._fields import converter_field

    value = x

    def bad(what: str) -> TypeError:
        cls, name = converter_field()
        where = f"{cls}: " if cls else ""
        which = f"physical parameter '{name}'" if name else "a physical parameter"
        return TypeError(f"{where}{which} must be {what}, got {value!r}")

    if isinstance(x, (str, bytes)) or x is None or (isinstance(x, np.ndarray) and x.dtype.kind in "USO"):
        raise bad("a real number or an array of real numbers")
    try:
        x = asarray(x)  # a host value without an eager JAX operation
    except (TypeError, ValueError) as err:
        raise bad("a real number or an array of real numbers") from err
    if not (jnp.issubdtype(x.dtype, jnp.floating) or jnp.issubdtype(x.dtype, jnp.integer)):
        raise bad(f"real (dtype {x.dtype})")
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = as_dtype(x, jnp.result_type(float))
    return x


def concrete(x) -> bool:
    """True when ``x`` holds a value now (not a tracer of ``jit``, ``vmap`` or ``grad``)."""
    return not isinstance(x, jax.core.Tracer)


def _number(x) -> str:
    """A parameter's value for an error message: ``0.1``, ``[0.02, -1]`` (the value under an eager
    ``jax.grad``, whose tracer holds one; ``traced`` when there is none)."""
    if isinstance(x, jax.core.Tracer):
        with jax.ensure_compile_time_eval():
            x = jax.lax.stop_gradient(x)
        if isinstance(x, jax.core.Tracer):
            return "(traced)"
    return np.array2string(np.asarray(x), separator=", ", formatter={"float_kind": lambda v: f"{v:.6g}"})


def positive_checks(obj, *names: str) -> tuple[tuple[str, Array | np.ndarray | np.bool_], ...]:
    """``(message, condition)`` pairs: each named parameter positive and finite (the condition a
    NumPy boolean for a known value: no eager JAX operation, each a compilation in a new
    process; a traced one for a tracer)."""

    def ok(x):
        if concrete(x):
            x = np.asarray(x)
            return np.isfinite(x) & (x > 0)
        return jnp.isfinite(x) & (x > 0)

    return tuple(
        (f"parameter {name!r} must be positive and finite", ok(getattr(obj, name))) for name in names
    )


def random_draws(key: Array, n: int, dtype) -> tuple[Array, Any, Any]:
    """``n`` keys split from ``key`` and the two draws the maneuver samplers use:
    ``uniform(k, shape, lo, hi)`` and ``sign(k, shape)`` (+-1 with equal odds), in ``dtype``."""

    def uniform(k, shape, lo, hi):
        return jax.random.uniform(k, shape, dtype, lo, hi)

    def sign(k, shape):
        return jnp.where(jax.random.bernoulli(k, 0.5, shape), 1.0, -1.0).astype(dtype)

    return jax.random.split(key, n), uniform, sign


def body_velocity(q: Float[Array, " d"], qdot: Float[Array, " d"]) -> Float[Array, " 3"]:
    """``xi = g^-1 gdot = (thetadot, c xdot + s ydot, -s xdot + c ydot)`` for ``q = (x, y, theta, r)``."""
    c, s = jnp.cos(q[2]), jnp.sin(q[2])
    return jnp.stack([qdot[2], c * qdot[0] + s * qdot[1], -s * qdot[0] + c * qdot[1]])


def spatial_velocity(q: Float[Array, " d"], xi: Float[Array, " 3"]) -> Float[Array, " 3"]:
    """``(xdot, ydot, thetadot)`` from the body velocity ``xi = (omega, v_x, v_y)``."""
    c, s = jnp.cos(q[2]), jnp.sin(q[2])
    return jnp.stack([c * xi[1] - s * xi[2], s * xi[1] + c * xi[2], xi[0]])


class Observation(NamedTuple):
    """What a rollout reports at a node ``t_k``.

    Attributes:
        q: configuration ``(x, y, theta, r)`` (m, rad).
        qdot: velocity (m/s, rad/s), on the constraints.
        energy: ``E(q, qdot)`` (J).
        momentum: nonholonomic momentum ``<d_xi l, e_b(r)>`` (c,).
        constraint_residual: ``|omega(q) qdot|``.
        power: power of the shape forces at ``t_k``, ``<f(t_k), rdot>`` (W).
    """

    q: Array
    qdot: Array
    energy: Array
    momentum: Array
    constraint_residual: Array
    power: Array


class AbstractSystem(eqx.Module):
    """A nonholonomic mechanical system with SE(2) symmetry.

    Subclasses give the reduced view (:meth:`reduced_lagrangian`, :meth:`connection`,
    :meth:`symmetry_basis`), the constraints in the body frame (:meth:`body_constraints`), how
    control channels enter (:meth:`inputs`), and the continuous equations of motion in a minimal
    set of velocities ``v`` (:meth:`qdot_from_velocities`, :meth:`velocities_from_qdot`,
    :meth:`velocity_dynamics`). Everything else (full Lagrangian, constraint one-forms, energy,
    momentum, the reduced Legendre transform and its inverse, the Lagrange-d'Alembert
    accelerations used to check the equations) is derived here.
    """

    shape_names: ClassVar[tuple[str, ...]]
    control_names: ClassVar[tuple[str, ...]]
    kinematic: ClassVar[tuple[bool, ...]]
    n_velocities: ClassVar[int]
    #: The shape coordinates that nothing depends on (a rotor or wheel angle: the equations are
    #: invariant under shifting them), by name; ``None`` (default): not declared, a gait's
    #: ``cyclic`` coordinates are then tested on the equations themselves.
    cyclic_names: ClassVar[tuple[str, ...] | None] = None

    def parameter_checks(self) -> tuple[tuple[str, Array | np.ndarray | np.bool_], ...]:
        """``(message, condition)`` pairs the physical parameters must satisfy (default: none); a
        condition on known values may be a NumPy boolean (no eager JAX operation).

        Checked at construction when the parameters are concrete (a ``ValueError`` with the
        message), and in every run when they are traced (e.g. a model built inside ``vmap``),
        where a violation fails that trajectory with ``RESULTS.invalid_input``.
        """
        return ()

    def __check_init__(self):
        with jax.ensure_compile_time_eval():
            checks = self.parameter_checks()
        for message, ok in checks:
            if concrete(ok) and not bool(np.all(np.asarray(ok))):
                values = ", ".join(
                    f"{f.name}={_number(getattr(self, f.name))}"
                    for f in dataclasses.fields(self)
                    if eqx.is_array(getattr(self, f.name))
                )
                raise ValueError(f"{type(self).__name__}: {message}, got {values}")

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
        """``l(r, u, xi) = L(r, u, e, xi)`` (J)."""

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

    @abc.abstractmethod
    def body_constraints(self, r: Array) -> Float[Array, "m d"]:
        """The constraints in the body frame: ``C(r) [xi; rdot] = 0`` with ``xi = (omega, v_x, v_y)``
        (prescribed shape velocities excluded)."""

    # ------------------------------------------------------------------- full view
    def lagrangian(self, q: Array, qdot: Array) -> Array:
        """``L(q, qdot) = l(r, rdot, g^-1 gdot)`` (the symmetry reduces L to l)."""
        return self.reduced_lagrangian(q[3:], qdot[3:], body_velocity(q, qdot))

    def constraint_forms(self, q: Array) -> Float[Array, "m d"]:
        """Constraint one-forms ``omega(q) = C(r) diag(B(theta), I)``.

        Here ``xi = B(theta)(xdot, ydot, thetadot)``.
        """
        c, s = jnp.cos(q[2]), jnp.sin(q[2])
        z, o = jnp.zeros_like(c), jnp.ones_like(c)
        b = jnp.array([[z, z, o], [c, s, z], [-s, c, z]])
        cmat = self.body_constraints(q[3:])
        return jnp.concatenate([cmat[:, :3] @ b, cmat[:, 3:]], axis=1)

    # ----------------------------------------------- continuous equations, minimal form
    @abc.abstractmethod
    def qdot_from_velocities(self, q: Array, v: Array, u_kin: Array) -> Array:
        """``qdot`` on the constraint distribution from independent velocities ``v``."""

    @abc.abstractmethod
    def velocities_from_qdot(self, q: Array, qdot: Array) -> Array:
        """Inverse of :meth:`qdot_from_velocities` on the constraint distribution."""

    @abc.abstractmethod
    def velocity_dynamics(
        self, q: Array, v: Array, f: Array, u_kin: Array, u_kin_dot: Array | None = None
    ) -> Array:
        """``vdot`` from the Lagrange-d'Alembert equations; ``u_kin_dot``: the prescribed
        accelerations of the kinematic coordinates (default ``None``: zero), where they enter."""

    @property
    def has_friction(self) -> bool:
        """Whether :meth:`dissipative_forces` gives forces (default False)."""
        return False

    def dissipative_forces(self, r: Array, u: Array, xi: Array) -> tuple[Array, Array] | None:
        """Friction forces ``(f_r, F) = -(d_u R, d_xi R)`` of a Rayleigh dissipation function
        ``R(r, u, xi)``: on the shape (n,) and on the group (a body-frame covector, paired with
        ``xi``), or ``None`` (the default) for a system without friction."""
        return None

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

    # ------------------------------------------------------- reduced Legendre transform
    def reduced_energy(self, r: Array, u: Array, xi: Array) -> Array:
        """Energy ``E = <d_u l, u> + <d_xi l, xi> - l`` (J) at shape ``r`` and velocities ``(u, xi)``."""
        lag, (du, dxi) = jax.value_and_grad(self.reduced_lagrangian, argnums=(1, 2))(r, u, xi)
        return jnp.dot(du, u) + jnp.dot(dxi, xi) - lag

    def reduced_momentum(self, r: Array, u: Array, xi: Array) -> Float[Array, " c"]:
        """Nonholonomic momentum ``mu_b = <d_xi l, e_b(r)>`` (paper (7))."""
        return self.symmetry_basis(r).T @ jax.grad(self.reduced_lagrangian, argnums=2)(r, u, xi)

    def velocity_from_momenta(
        self, r: Array, pu: Array, mu: Array, u_kin: Array
    ) -> tuple[Float[Array, " n"], Float[Array, " 3"]]:
        """Invert the reduced Legendre transform on the constraint distribution.

        Finds ``(u, xi)``, ``xi = e(r) w - A(r) u`` and ``u`` equal to ``u_kin`` in its kinematic
        entries, such that (the RDP equations (21), (23) at ``h = 0``)::

            d_u l - A(r)^T d_xi l = pu - A(r)^T mu      (force-driven rows),
            e(r)^T d_xi l         = e(r)^T mu,

        i.e. the velocity whose momenta are ``(pu, mu)`` modulo what the constraints absorb. This
        is how every RDP order reports node velocities: from its carried momenta, not by
        differencing positions. One Newton step from rest: exact for ``l`` quadratic in the
        velocities (every mechanical system, with or without a potential).

        Returns:
            ``(u (n,), xi (3,))``.
        """
        residual, unpack, z0 = self._legendre_residual(r, pu, mu, u_kin)
        z = z0 - solve(jax.jacfwd(residual)(z0), residual(z0))
        return unpack(z)

    def shape_mobility(self, r: Array) -> Float[Array, "n n"]:
        """``A = d u / d pu`` of :meth:`velocity_from_momenta` at rest (``mu = 0``, no prescribed
        velocity): the shape velocity an impulse ``P`` of the shape forces gives the system at
        rest at shape ``r`` is ``A P``, with kinetic energy ``1/2 P^T A P`` (the constrained
        inverse mass matrix on the shape coordinates; zero rows and columns for kinematic ones).

        ``velocity_from_momenta`` is affine in ``pu``: its residual ``R(z) - S^T pu`` has the
        Jacobian ``J`` of the Newton step, and ``dz / d pu = J^-1 [S; 0]`` (``S`` selecting the
        force-driven entries), so ``A`` is the leading block of ``J^-1`` scattered onto them.
        """
        n = self.n_shape
        dyn = np.asarray(self.dynamic_index, dtype=int)
        zero = jnp.zeros(n, r.dtype)
        residual, _, z0 = self._legendre_residual(r, zero, jnp.zeros(3, r.dtype), zero)
        nd = dyn.size
        if nd == 0:
            return jnp.zeros((n, n), r.dtype)
        rhs = jnp.eye(z0.size, nd, dtype=r.dtype)
        block = solve(jax.jacfwd(residual)(z0), rhs)[:nd]
        return jnp.zeros((n, n), r.dtype).at[np.ix_(dyn, dyn)].set(block)

    def _legendre_residual(self, r: Array, pu: Array, mu: Array, u_kin: Array):
        """The residual of :meth:`velocity_from_momenta` in the unknowns ``z = (u[dyn], w)``, the
        map ``z -> (u, xi)`` and the starting point ``z = 0``."""
        dyn = np.asarray(self.dynamic_index, dtype=int)
        nd = dyn.size
        a_r, e_r = self.connection(r), self.symmetry_basis(r)

        def unpack(z):
            u = u_kin.at[dyn].set(z[:nd]) if nd else u_kin
            return u, e_r @ z[nd:] - a_r @ u

        def residual(z):
            u, xi = unpack(z)
            du, dxi = jax.grad(self.reduced_lagrangian, argnums=(1, 2))(r, u, xi)
            jump = dxi - mu
            hor = du - a_r.T @ jump - pu
            return jnp.concatenate([hor[dyn], e_r.T @ jump])

        return residual, unpack, jnp.zeros(nd + e_r.shape[1], r.dtype)

    def observation(
        self,
        q: Array,
        u: Array,
        xi: Array,
        controls: Array,
        *,
        rotation: tuple[Array, Array] | None = None,
        momentum: Array | None = None,
        constraint_residual: Array | None = None,
    ) -> Observation:
        """The :class:`Observation` at a node with configuration ``q``, shape velocity ``u`` and
        body velocity ``xi``; ``controls`` are the channel values at the node's time.

        ``rotation`` (``(cos theta, sin theta)``), ``momentum`` and ``constraint_residual`` may be
        passed when the caller already holds them or has a cheaper way (the closed-form kernels
        do: they carry the cosines and sines of their angles); they are computed otherwise.
        """
        r = q[3:]
        c, s = rotation if rotation is not None else (jnp.cos(q[2]), jnp.sin(q[2]))
        xyt = jnp.stack([c * xi[1] - s * xi[2], s * xi[1] + c * xi[2], xi[0]])
        f, _ = self.inputs(controls)
        return Observation(
            q=q,
            qdot=jnp.concatenate([xyt, u]),
            energy=self.reduced_energy(r, u, xi),
            momentum=self.reduced_momentum(r, u, xi) if momentum is None else momentum,
            constraint_residual=self.body_constraint_residual(r, u, xi)
            if constraint_residual is None
            else constraint_residual,
            power=self.power(f, u),
        )

    # ----------------------------------------------------------------- derived
    @compiled_unless_staged
    def energy(self, q: Array, qdot: Array) -> Array:
        """Energy ``E = <dL/dqdot, qdot> - L`` (J)."""
        return self.reduced_energy(q[3:], qdot[3:], body_velocity(q, qdot))

    @compiled_unless_staged
    def momentum(self, q: Array, qdot: Array) -> Float[Array, " c"]:
        """Nonholonomic momentum ``mu_b = <dl/dxi, e_b(r)>`` (paper (7))."""
        return self.reduced_momentum(q[3:], qdot[3:], body_velocity(q, qdot))

    def body_constraint_residual(self, r: Array, u: Array, xi: Array) -> Array:
        """``|C(r) [xi; u]|``: the constraint violation of the velocity ``(u, xi)``."""
        return safe_vnorm(self.body_constraints(r) @ jnp.concatenate([xi, u]))

    @compiled_unless_staged
    def constraint_residual(self, q: Array, qdot: Array) -> Array:
        """``|omega(q) qdot|`` (Euclidean norm; m/s and rad/s mixed as the constraints are written)."""
        return self.body_constraint_residual(q[3:], qdot[3:], body_velocity(q, qdot))

    def power(self, f: Array, rdot: Array) -> Array:
        """Power of the shape forces ``<f, rdot>`` (W; kinematic coordinates carry no force)."""
        idx = np.asarray(self.dynamic_index, dtype=int)
        return jnp.dot(f[idx], rdot[idx])

    def full_acceleration(self, q: Array, qdot: Array, f: Array, u_kin_dot: Array) -> tuple[Array, Array]:
        """Accelerations from the full Lagrange-d'Alembert equations, by autodiff.

        Solves the KKT system
        ``M(q) qddot = dL/dq - (d/dq dL/dqdot) qdot + F + omega^T lambda``,
        ``omega(q) qddot + (d/dq (omega(q) qdot)) qdot = 0`` and, for kinematic shape
        coordinates, ``rddot_i = d u_kin_i / dt``. ``F = (0, 0, 0, f)``, plus the friction of a
        dissipation function (:meth:`dissipative_forces`) where the system has one.

        Returns:
            ``(qddot, lambda)``.
        """
        d = self.n_config
        dl_dqdot = jax.grad(self.lagrangian, argnums=1)
        mass = jax.jacfwd(dl_dqdot, argnums=1)(q, qdot)
        mixed = jax.jacfwd(dl_dqdot, argnums=0)(q, qdot)
        dl_dq = jax.grad(self.lagrangian, argnums=0)(q, qdot)
        force = jnp.zeros(d, q.dtype).at[3:].set(f)
        friction = self.dissipative_forces(q[3:], qdot[3:], body_velocity(q, qdot))
        if friction is not None:
            # the body-frame covector F on (x, y, theta): <F, eta> with eta = (dtheta, R^T (dx, dy)),
            # so (R (F_x, F_y), F_theta): the rotation of a body velocity (R orthogonal)
            f_r, F = friction
            force = force + jnp.concatenate([spatial_velocity(q, F), f_r])
        omega = self.constraint_forms(q)
        kin = np.asarray(self.kinematic_index, dtype=int)
        e_kin = jnp.eye(d, dtype=q.dtype)[3 + kin] if kin.size else jnp.zeros((0, d), q.dtype)
        rows = jnp.concatenate([omega, e_kin], axis=0)
        domega_qdot = jax.jacfwd(lambda qq: self.constraint_forms(qq) @ qdot)(q) @ qdot
        rhs_c = jnp.concatenate([-domega_qdot, u_kin_dot[kin] if kin.size else jnp.zeros(0, q.dtype)])
        m = rows.shape[0]
        kkt = jnp.block([[mass, -rows.T], [rows, jnp.zeros((m, m), q.dtype)]])
        rhs = jnp.concatenate([dl_dq - mixed @ qdot + force, rhs_c])
        sol = solve(kkt, rhs)
        return sol[:d], sol[d:]

    def ode(
        self, y: tuple[Array, Array], controls: Array, controls_dot: Array | None = None
    ) -> tuple[Array, Array]:
        """Right-hand side of the minimal continuous equations, ``y = (q, v)``, with the
        controls' values and (default ``None``: taken as zero) their time derivative, whose
        kinematic channels are the prescribed coordinates' accelerations."""
        q, v = y
        f, u_kin = self.inputs(controls)
        if controls_dot is None or not len(self.kinematic_index):
            vdot = self.velocity_dynamics(q, v, f, u_kin)
        else:
            vdot = self.velocity_dynamics(q, v, f, u_kin, self.inputs(controls_dot)[1])
        return self.qdot_from_velocities(q, v, u_kin), vdot

    def consistent_qdot(self, q: Array, qdot: Array, controls: Array) -> Array:
        """``qdot`` with its kinematic shape entries replaced by the prescribed velocities."""
        _, u_kin = self.inputs(controls)
        kin = np.asarray(self.kinematic_index, dtype=int)
        if kin.size == 0:
            return qdot
        return qdot.at[3 + kin].set(u_kin[kin])
