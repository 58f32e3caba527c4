"""Bring your own system: a nonholonomic system on ``M x SE(2)`` from a few functions.

The user writes the reduced view of the paper (Sec. 3): the reduced Lagrangian ``l(r, u, xi)``,
the local form ``A(r)`` of a connection whose horizontal lifts ``(dr, -A(r) dr)`` satisfy the
constraints, and a body basis ``e(r)`` of the constrained symmetries; optionally the constraints
themselves in the body frame, ``C(r) [xi; rdot] = 0`` (the full view, for DLA/GNI and the
Lagrange-d'Alembert checks). Everything else is derived by autodiff:

* RDP runs the general implicit step (21), (23) (Newton, implicit-function-theorem gradients);
* the continuous equations used by RK and the diffrax reference are the reduced equations (4)-(8),
  written with the full momentum ``mu = dl/dxi``:

      vertical (7):    <mu_dot, e_b(r)> = <mu, ad_xi e_b(r)>,
      horizontal (8):  d/dt dl/du - dl/dr = A(r)^T (mu_dot - ad_xi^* mu) + f,
      reconstruction (4), (5): g^-1 gdot = xi = E(r) w - A(r) rdot,  rdot = u,

  solved for the accelerations ``(rddot, wdot)`` (the system is affine in them).

Any complement of the symmetries in the constraint distribution gives the same equations: ``A``
need not be the paper's nonholonomic connection, only a valid horizontal lift.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import PyTree

from .._linalg import solve
from .._numerics import safe_vnorm
from ..lie import ad
from ._base import AbstractSystem, body_velocity, spatial_velocity

__all__ = ["System"]


def _shape_of(fn_name: str, fn: Callable, *args):
    """``jax.eval_shape(fn, *args)``; an error inside the user's function is re-raised with the
    same type, naming the function (e.g. a wrong number of arguments, a shape mismatch)."""
    try:
        return jax.eval_shape(fn, *args)
    except Exception as err:  # the user's code: any error, re-raised naming the function
        kind = next((k for k in (TypeError, IndexError) if isinstance(err, k)), ValueError)
        raise kind(f"System: calling {fn_name} (with the shapes of its arguments) failed: {err}") from err


def _check_shape(name: str, fn_name: str, shape_struct, expected: tuple) -> None:
    if not hasattr(shape_struct, "shape"):
        raise ValueError(
            f"System: {fn_name} must return an array of shape {expected} ({name}), got {shape_struct!r}"
        )
    got = tuple(shape_struct.shape)
    if got != expected:
        raise ValueError(f"System: {fn_name} must return an array of shape {expected} ({name}), got {got}")


class System(AbstractSystem):
    r"""A nonholonomic system with SE(2) symmetry, described by its reduced view.

    Args:
        n_shape: dimension ``n`` of the shape space ``M = R^n`` (0 for none).
        lagrangian: ``l(r, u, xi) -> scalar`` (``r``, ``u`` of shape (n,), ``xi = (omega, v_x, v_y)``).
            A potential is welcome: ``l = T - V(r)``.
        connection: ``A(r) -> (3, n)``, with ``xi = Omega - A(r) rdot``.
        symmetry_basis: ``e(r) -> (3, c)``, body basis of the constrained symmetries; ``None`` for
            ``c = 0`` (the principal kinematic case, like the car).
        constraints: optional ``C(r) -> (m, 3 + n)`` with ``C(r) [xi; rdot] = 0`` on the constraint
            distribution (the full view; needed by DLA and GNI). ``m = 3 - c`` for a consistent
            description.
        params: optional pytree of parameters; when given, every function is called with it
            first (``l(params, r, u, xi)``, ...), so the parameters are differentiable and
            vmappable.
        kinematic: per shape coordinate, True where its velocity is prescribed by a control
            (like the car's steering) instead of driven by a force. Default: all force-driven.
        shape_names: names of the shape coordinates (default ``r1, r2, ...``).
        singularity: optional ``s(r) -> scalar`` vanishing where the description breaks down
            (NaN counts as a singularity).
        dissipation: optional Rayleigh dissipation function ``R(r, u, xi) -> scalar`` (``>= 0``,
            e.g. ``c v_x^2 / 2`` for a viscous rolling resistance): friction forces
            ``f_r = -d_u R`` on the shape and ``F = -d_xi R`` on the group (a body-frame covector)
            enter the Lagrange-d'Alembert principle as ``int <f_r, delta r> + <F, eta> dt``. The
            RDP steps evaluate them at each step's velocities and split them as the shape forces
            (``1 - alpha`` to the step's start, ``alpha`` to its end); RK and ``lj.reference``
            take them in the continuous equations; DLA and GNI do not take them (a
            ``ValueError``). The diagnostics' work ``W`` is that of the controls only, so that
            ``E_0 + W - E`` is the energy dissipated. Default: none (energy conserved).

    Controls: one channel per shape coordinate, in order: a generalized force ``f_i`` on a
    force-driven coordinate, the prescribed velocity ``u_i`` of a kinematic one. (The continuous
    equations of a kinematic coordinate whose prescribed acceleration enters the dynamics use the
    control's time derivative, which :func:`ldap_jax.reference` provides; the RK baselines
    estimate it from their stage values, RK4 to ``O(h^2)``, RK2 to ``O(h)``, which makes RK2 of
    order 1 there.)

    Raises:
        ValueError: at construction, when a function returns an array of the wrong shape (the
            message names the function).

    Example (the Chaplygin sleigh, a knife edge at distance ``a`` behind the centre of mass)::

        sleigh = lj.System(
            n_shape=0,
            lagrangian=lambda r, u, xi: 0.5 * (m * xi[1] ** 2 + m * (xi[2] + a * xi[0]) ** 2
                                               + I * xi[0] ** 2),
            connection=lambda r: jnp.zeros((3, 0)),
            symmetry_basis=lambda r: jnp.array([[1.0, 0.0], [0.0, 1.0], [0.0, 0.0]]),
            constraints=lambda r: jnp.array([[0.0, 0.0, 1.0]]),
        )
    """

    n: int = eqx.field(static=True)
    # ordinary fields: a callable that is an eqx.Module holding arrays (a network, a fitted model)
    # exposes them to jax.grad and jax.vmap like any parameter
    lagrangian_fn: Callable
    connection_fn: Callable
    symmetry_basis_fn: Callable | None
    constraints_fn: Callable | None
    singularity_fn: Callable | None
    dissipation_fn: Callable | None
    kinematic_mask: tuple[bool, ...] = eqx.field(static=True)
    names: tuple[str, ...] = eqx.field(static=True)
    n_symmetries: int = eqx.field(static=True)
    params: PyTree[Any]

    def __init__(
        self,
        n_shape: int,
        lagrangian: Callable,
        connection: Callable,
        symmetry_basis: Callable | None = None,
        constraints: Callable | None = None,
        *,
        params: PyTree[Any] = None,
        kinematic: tuple[bool, ...] | None = None,
        shape_names: tuple[str, ...] | None = None,
        singularity: Callable | None = None,
        dissipation: Callable | None = None,
    ):
        if isinstance(n_shape, bool) or not isinstance(n_shape, (int, np.integer)):
            raise TypeError(f"System: 'n_shape' must be a non-negative integer, got {n_shape!r}")
        if n_shape < 0:
            raise ValueError(f"System: 'n_shape' must be a non-negative integer, got {n_shape!r}")
        self.n = int(n_shape)
        for name, fn, required in (
            ("lagrangian", lagrangian, True),
            ("connection", connection, True),
            ("symmetry_basis", symmetry_basis, False),
            ("constraints", constraints, False),
            ("singularity", singularity, False),
            ("dissipation", dissipation, False),
        ):
            if not callable(fn) and (required or fn is not None):
                raise TypeError(
                    f"System: '{name}' must be a function{'' if required else ' or None'}, got {type(fn)}"
                )
        self.lagrangian_fn = lagrangian
        self.connection_fn = connection
        self.symmetry_basis_fn = symmetry_basis
        self.constraints_fn = constraints
        self.singularity_fn = singularity
        self.dissipation_fn = dissipation
        self.params = jax.tree_util.tree_map(jnp.asarray, params)
        if kinematic is not None and (
            isinstance(kinematic, (str, bytes)) or not hasattr(kinematic, "__len__")
        ):
            raise TypeError(f"System: 'kinematic' must be a tuple of booleans, got {kinematic!r}")
        if shape_names is not None and (
            isinstance(shape_names, (str, bytes)) or not hasattr(shape_names, "__len__")
        ):
            raise TypeError(f"System: 'shape_names' must be a tuple of strings, got {shape_names!r}")
        kinematic = tuple(bool(k) for k in (kinematic or (False,) * self.n))
        if len(kinematic) != self.n:
            raise ValueError(
                f"System: 'kinematic' must have one entry per shape coordinate ({self.n}), got {kinematic}"
            )
        self.kinematic_mask = kinematic
        names = tuple(shape_names or (f"r{i + 1}" for i in range(self.n)))
        if len(names) != self.n:
            raise ValueError(f"System: 'shape_names' must have {self.n} entries, got {names}")
        self.names = names
        # shapes, checked at trace time (no FLOPs)
        params_ = self.params

        def call(fn):
            return lambda *args: fn(*args) if params_ is None else fn(params_, *args)

        dtype = jnp.result_type(float)
        r = jax.ShapeDtypeStruct((self.n,), dtype)
        xi = jax.ShapeDtypeStruct((3,), dtype)
        lag = _shape_of("lagrangian(r, u, xi)", call(lagrangian), r, r, xi)
        _check_shape("a scalar", "lagrangian(r, u, xi)", lag, ())
        if not jnp.issubdtype(lag.dtype, jnp.floating):  # it is differentiated
            raise TypeError(f"System: lagrangian(r, u, xi) must return a floating scalar, got {lag.dtype}")
        _check_shape("3 x n", "connection(r)", _shape_of("connection(r)", call(connection), r), (3, self.n))
        if symmetry_basis is None:
            self.n_symmetries = 0
        else:
            e = _shape_of("symmetry_basis(r)", call(symmetry_basis), r)
            if len(e.shape) != 2 or e.shape[0] != 3 or e.shape[1] > 3:
                raise ValueError(
                    f"System: symmetry_basis(r) must return an array of shape (3, c), got {tuple(e.shape)}"
                )
            self.n_symmetries = int(e.shape[1])
        if constraints is not None:
            c = _shape_of("constraints(r)", call(constraints), r)
            _check_shape("(3 - c) x (3 + n)", "constraints(r)", c, (3 - self.n_symmetries, 3 + self.n))
        if singularity is not None:
            _check_shape("a scalar", "singularity(r)", _shape_of("singularity(r)", call(singularity), r), ())
        if dissipation is not None:
            _check_shape(
                "a scalar",
                "dissipation(r, u, xi)",
                _shape_of("dissipation(r, u, xi)", call(dissipation), r, r, xi),
                (),
            )

    def _call(self, fn, *args):
        return fn(*args) if self.params is None else fn(self.params, *args)

    # ------------------------------------------------------------ description
    @property
    def shape_names(self) -> tuple[str, ...]:  # type: ignore[override]
        return self.names

    @property
    def kinematic(self) -> tuple[bool, ...]:  # type: ignore[override]
        return self.kinematic_mask

    @property
    def control_names(self) -> tuple[str, ...]:  # type: ignore[override]
        return tuple(("u_" if k else "f_") + n for n, k in zip(self.names, self.kinematic_mask))

    @property
    def n_velocities(self) -> int:  # type: ignore[override]
        return len(self.dynamic_index) + self.n_symmetries

    def reduced_lagrangian(self, r, u, xi):
        return self._call(self.lagrangian_fn, r, u, xi)

    def connection(self, r):
        return self._call(self.connection_fn, r)

    def symmetry_basis(self, r):
        if self.symmetry_basis_fn is None:
            return jnp.zeros((3, 0), r.dtype)
        return self._call(self.symmetry_basis_fn, r)

    def inputs(self, controls):
        kin = jnp.asarray(self.kinematic_mask, bool)
        zero = jnp.zeros_like(controls)
        return jnp.where(kin, zero, controls), jnp.where(kin, controls, zero)

    @property
    def has_friction(self) -> bool:  # type: ignore[override]
        return self.dissipation_fn is not None

    def dissipative_forces(self, r, u, xi):
        if self.dissipation_fn is None:
            return None
        f_r, F = jax.grad(lambda u_, xi_: self._call(self.dissipation_fn, r, u_, xi_), argnums=(0, 1))(u, xi)
        kin = jnp.asarray(self.kinematic_mask, bool)  # a kinematic coordinate takes no force
        return jnp.where(kin, 0.0, -f_r), -F

    def singularity(self, q):
        """The user's ``singularity(r)``, with NaN taken as 0: a singularity (at a NaN state the
        step reports the non-finite state first)."""
        if self.singularity_fn is None:
            return jnp.ones((), q.dtype)
        s = self._call(self.singularity_fn, q[3:])
        return jnp.where(jnp.isnan(s), jnp.zeros_like(s), s)

    # ------------------------------------------------------------ full view
    def body_constraints(self, r):
        """``C(r)`` with ``C(r) [xi; rdot] = 0``."""
        if self.constraints_fn is None:
            raise ValueError(
                "System: this description has no full view; pass constraints=C(r) "
                "(the constraints in the body frame) to use it"
            )
        return self._call(self.constraints_fn, r)

    def body_constraint_residual(self, r, u, xi):
        """``|C(r) [xi; u]|`` from the full view, or, without one, the distance of
        ``xi + A(r) u`` from ``span e(r)``."""
        if self.constraints_fn is not None:
            return super().body_constraint_residual(r, u, xi)
        v = xi + self.connection(r) @ u
        e = self.symmetry_basis(r)
        if e.shape[1]:
            v = v - e @ solve(e.T @ e, e.T @ v)
        return safe_vnorm(v)

    # ------------------------------------------- continuous equations (derived)
    def _split(self, v, u_kin):
        dyn = jnp.asarray(self.dynamic_index, dtype=int)
        nd = len(self.dynamic_index)
        rdot = u_kin.at[dyn].set(v[:nd]) if nd else u_kin
        return rdot, v[nd:]

    def qdot_from_velocities(self, q, v, u_kin):
        r = q[3:]
        rdot, w = self._split(v, u_kin)
        xi = self.symmetry_basis(r) @ w - self.connection(r) @ rdot
        return jnp.concatenate([spatial_velocity(q, xi), rdot])

    def velocities_from_qdot(self, q, qdot):
        r, rdot = q[3:], qdot[3:]
        dyn = jnp.asarray(self.dynamic_index, dtype=int)
        e = self.symmetry_basis(r)
        omega = body_velocity(q, qdot) + self.connection(r) @ rdot
        w = solve(e.T @ e, e.T @ omega) if e.shape[1] else jnp.zeros((0,), q.dtype)
        return jnp.concatenate([rdot[dyn], w])

    def velocity_dynamics(self, q, v, f, u_kin, u_kin_dot=None):
        """Accelerations ``(rddot_dyn, wdot)`` from the reduced equations (4)-(8)."""
        r = q[3:]
        rdot, w = self._split(v, u_kin)
        u_kin_dot = jnp.zeros_like(u_kin) if u_kin_dot is None else u_kin_dot
        dyn = jnp.asarray(self.dynamic_index, dtype=int)
        nd = len(self.dynamic_index)

        def parts(r_, rdot_, w_):
            xi = self.symmetry_basis(r_) @ w_ - self.connection(r_) @ rdot_
            dl_dr, dl_du, mu = jax.grad(self.reduced_lagrangian, argnums=(0, 1, 2))(r_, rdot_, xi)
            return dl_du, mu, xi, dl_dr

        def residual(acc):
            rddot = u_kin_dot.at[dyn].set(acc[:nd]) if nd else u_kin_dot
            (dl_du, mu, xi, dl_dr), (dl_du_dot, mu_dot, _, _) = jax.jvp(
                parts, (r, rdot, w), (rdot, rddot, acc[nd:])
            )
            e = self.symmetry_basis(r)
            vert = e.T @ mu_dot - (ad(xi) @ e).T @ mu
            hor = dl_du_dot - dl_dr - self.connection(r).T @ (mu_dot - ad(xi).T @ mu) - f
            friction = self.dissipative_forces(r, rdot, xi)
            if friction is not None:  # the virtual displacement eta = e dw - A dr
                f_r, F = friction
                hor = hor - f_r + self.connection(r).T @ F
                vert = vert - e.T @ F
            return jnp.concatenate([hor[dyn], vert])

        acc0 = jnp.zeros(self.n_velocities, q.dtype)
        res0 = residual(acc0)
        jac = jax.jacfwd(residual)(acc0)
        return -solve(jac, res0)
