"""The reduced d'Alembert-Pontryagin (RDP) integrator (paper Sec. 4.2, eqs. (17)-(25)), and its
symmetric compositions of order 4, 6 and 8."""

from __future__ import annotations

from typing import Any, Literal, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._newton import newton
from .._numerics import materialise_result, safe_vnorm
from .._results import RESULTS
from ..lie import compose, dtau_inv, retract
from ..systems import AbstractClosedFormSystem, AbstractSystem, Observation
from ..systems._base import body_velocity, spatial_velocity
from ._base import AbstractAlphaIntegrator, StepInfo, classify, concrete_float, finite
from ._composition import DEFAULT_SCHEMES, SCHEMES, scheme_nodes

__all__ = ["RDP", "RDPState"]


class RDPState(NamedTuple):
    """State of the general RDP step at node ``k`` (the closed-form kernels keep their own).

    Attributes:
        q: configuration ``q_k = (x, y, theta, r)``.
        pu: incoming shape momentum ``d_u l_{k-1} + h alpha (d_r l_{k-1} + f_{k-1+alpha})`` (n,):
            the previous step's force is folded in, so a step needs nothing of the previous step
            size (variable and negative steps are exact; the scheme is symmetric at alpha = 1/2).
        mu: incoming group momentum ``(dtau^-1_{-h xi_{k-1}})^* d_xi l_{k-1}`` (3,).
        u: previous shape velocity ``u_{k-1}`` (n,), the Newton warm start.
        w: previous locked-velocity coordinates ``Omega_{k-1}`` in the basis ``e(r)`` (c,), the
            Newton warm start.

    Only ``pu - A(r_k)^T mu`` and ``e(r_k)^T mu`` enter the next step (and the node velocity):
    two states that agree in those are the same state.
    """

    q: Array
    pu: Array
    mu: Array
    u: Array
    w: Array


def _locked_coords(e: Array, v: Array) -> Array:
    """Coordinates of ``v`` in the columns of ``e`` (least squares; empty when c = 0)."""
    from .._linalg import solve

    if e.shape[1] == 0:
        return jnp.zeros((0,), v.dtype)
    return solve(e.T @ e, e.T @ v)


class RDP(AbstractAlphaIntegrator):
    r"""Reduced d'Alembert-Pontryagin integrator of Kobilarov, Marsden and Sukhatme.

    On a step ``[t_k, t_k + h]`` with ``r_{k+a} = r_k + a h u_k`` and
    ``xi_k = Omega_k - A(r_{k+a}) u_k``, ``Omega_k in span e(r_{k+a})``, the unknowns
    ``(u_k, Omega_k)`` solve the horizontal (23) and vertical (21) equations, written with the
    incoming momenta ``(pu_k, mu_k)`` of the state::

        d_u l_k - h (1-a) (d_r l_k + f_{k+a}) - A(r_k)^T (dtau^-1_{h xi_k}^* d_xi l_k - mu_k) = pu_k,
        < dtau^-1_{h xi_k}^* d_xi l_k - mu_k, e_b(r_k) > = 0,

    with ``l_k = l(r_{k+a}, u_k, xi_k)``, ``f_{k+a} = (1-a) f(t_k) + a f(t_k + h)``; then
    ``g_{k+1} = g_k tau(h xi_k)``, ``r_{k+1} = r_k + h u_k``, and the next node's incoming momenta
    ``pu_{k+1} = d_u l_k + h a (d_r l_k + f_{k+a})``, ``mu_{k+1} = dtau^-1_{-h xi_k}^* d_xi l_k``.
    At a constant step this is the paper's scheme (its force ``a f_{k-1+a} + (1-a) f_{k+a}``);
    folding the previous step's share of the force into ``pu`` makes it exact for variable steps
    and, at ``a = 1/2``, exactly symmetric: a step with ``h`` then one with ``-h`` returns to
    the start. Kinematic shape coordinates take ``u_k`` = the trapezoidal average of the
    prescribed velocity over the step. (The paper's matrix form (25) needs ``-A``, ``d_r l`` and
    the weighted force; see ``docs/corrections.md``.)

    Initialisation (discrete Legendre transform): ``pu_0 = d_u l``, ``mu_0 = d_xi l`` at the initial
    velocity. Node velocities are read from the carried momenta by inverting the reduced Legendre
    transform (:meth:`~ldap_jax.systems.AbstractSystem.velocity_from_momenta`), for every order.

    **Order.** ``order=2`` (the default at ``alpha = 1/2``) is the paper's method; ``alpha != 1/2``
    gives order 1. ``order=4``, ``6`` and ``8`` compose the symmetric ``alpha = 1/2`` step
    (``scheme``: default ``"suzuki5"``, 5 substeps, ``"least_error11"``, 11 substeps, and
    ``"kahan_li17"``, 17 substeps; also ``"mclachlan5"``, ``"triple_jump"``, ``"kahan_li9"``,
    ``"yoshida7"``, ``"mclachlan15"``), each substep an RDP step with its own
    (possibly negative) size reading the controls at its own two ends: the constraints, (21) and
    (23) hold at every substep. ``n_steps`` of :func:`~ldap_jax.simulate` counts the composed steps.
    Schemes whose substeps leave the step (triple jump, Yoshida's, McLachlan's 15) drop to order 2 on
    piecewise-linear sampled controls; the defaults stay inside.

    **Solvers.** Systems with a closed form (:class:`~ldap_jax.systems.AbstractClosedFormSystem`:
    the car and the snakeboard, paper Sec. 5.1, 5.2) run their explicit kernel when
    ``dtau_order == 1`` (``dtau^-1 ~ I - ad/2``, which is what those closed forms are). Otherwise
    the equations are solved by Newton's method (Jacobians by ``jax.jacfwd``, warm-started from
    the previous step, at most ``newton_iterations``), differentiated by the implicit function
    theorem; non-convergence is reported per step.

    Properties: explicit for the car and the snakeboard, implicit in general; exact discrete
    momentum equation (Prop. 1); the constraints hold exactly at every (sub)step; energy error
    bounded over long runs (no drift).

    Args:
        alpha: quadrature point in [0, 1] (default 1/2).
        retraction: ``"exp"`` (default) or ``"cayley"``.
        order: 2, 4, 6 or 8 (default 2 at ``alpha = 1/2``, 1 otherwise). Orders above 2 need
            ``alpha = 1/2``. Order 8 reaches tight tolerances (1e-6 m and below over 10 s)
            for the least work.
        scheme: composition scheme for ``order > 2`` (a key of
            ``ldap_jax.integrators.SCHEMES`` of that order; default ``"suzuki5"``,
            ``"least_error11"``, ``"kahan_li17"`` for orders 4, 6, 8). ``"least_error11"``
            reaches a given error with about 0.75x the substeps of Kahan and Li's 9-stage
            ``"kahan_li9"``.
        dtau_order: ``1`` (default) truncates ``dtau^-1`` to ``I - ad/2`` (the paper's explicit
            car/snakeboard schemes); ``None`` uses the exact ``dexp^-1`` (28) or ``dcay^-1`` (32);
            ``p >= 2`` truncates the series after ``ad^p``.
        solver: ``"auto"`` (default: closed form where the system has one, else Newton) or ``"newton"``.
        newton_iterations: Newton budget per step (default 20).
        reverse_only: not a setting (default ``False``): set by the rollout of a program that
            is not differentiated in forward mode, to run the closed-form kernels' hand-written
            VJP; the values are the same.

    Raises:
        ValueError: a bad setting (the message names it).

    Example:
        >>> traj = lj.simulate(sb, q0, qdot0, ctl, t_final=10.0, n_steps=100, integrator=lj.RDP(order=6))
    """

    alpha: Any = 0.5
    retraction: Literal["exp", "cayley"] = eqx.field(default="exp", static=True)
    order: int = eqx.field(default=None, static=True)  # type: ignore[assignment]
    scheme: str | None = eqx.field(default=None, static=True)
    dtau_order: int | None = eqx.field(default=1, static=True)
    solver: Literal["auto", "newton"] = eqx.field(default="auto", static=True)
    newton_iterations: int = eqx.field(default=20, static=True)
    #: Set by the rollout of a program not differentiated in forward mode: the closed-form kernels
    #: then run :meth:`~ldap_jax.systems.AbstractClosedFormSystem.kernel_step_reverse` (a
    #: hand-written VJP, no forward mode). Not a setting: the values are the same.
    reverse_only: bool = eqx.field(default=False, static=True, repr=False)

    def __post_init__(self):
        a = concrete_float(self.alpha)
        if self.order is None:
            self.order = 1 if (a is not None and a != 0.5) else 2
        if self.scheme is None and self.order in DEFAULT_SCHEMES:
            self.scheme = DEFAULT_SCHEMES[self.order]

    def __check_init__(self):
        if self.retraction not in ("exp", "cayley"):
            raise ValueError(f"RDP: 'retraction' must be 'exp' or 'cayley', got {self.retraction!r}")
        if isinstance(self.order, bool) or self.order not in (1, 2, 4, 6, 8):
            raise ValueError(f"RDP: 'order' must be 2, 4, 6 or 8, got {self.order!r}")
        a = concrete_float(self.alpha)
        if self.order == 1 and (a is None or a == 0.5):
            raise ValueError(
                f"RDP: 'order' must be 2, 4, 6 or 8, got 1 (order 1 is what alpha != 1/2 gives, "
                f"set from alpha; alpha={self.alpha!r} here)"
            )
        if self.order >= 2 and a is not None and a != 0.5:
            raise ValueError(
                f"RDP: 'order' {self.order} needs the symmetric base step alpha = 1/2, got alpha={a} "
                f"(alpha != 1/2 gives order 1)"
            )
        if self.order > 2:
            if self.scheme not in SCHEMES:
                raise ValueError(f"RDP: 'scheme' must be one of {sorted(SCHEMES)}, got {self.scheme!r}")
            if SCHEMES[self.scheme][0] != self.order:
                raise ValueError(
                    f"RDP: 'scheme' {self.scheme!r} has order {SCHEMES[self.scheme][0]}, not {self.order}"
                )
        elif self.scheme is not None:
            raise ValueError(
                f"RDP: 'scheme' applies to order 4, 6 or 8, got scheme={self.scheme!r} at order 2"
            )
        if self.dtau_order is not None and (
            isinstance(self.dtau_order, bool) or not isinstance(self.dtau_order, int) or self.dtau_order < 1
        ):
            raise ValueError(f"RDP: 'dtau_order' must be None or an integer >= 1, got {self.dtau_order!r}")
        if self.solver not in ("auto", "newton"):
            raise ValueError(f"RDP: 'solver' must be 'auto' or 'newton', got {self.solver!r}")
        if (
            isinstance(self.newton_iterations, bool)
            or not isinstance(self.newton_iterations, int)
            or self.newton_iterations < 1
        ):
            raise ValueError(
                f"RDP: 'newton_iterations' must be a positive integer, got {self.newton_iterations!r}"
            )
        super().__check_init__()

    # ------------------------------------------------------------------ settings
    @property
    def weights(self) -> tuple[float, ...]:
        """Substep sizes as fractions of the step (``(1.0,)`` at order 1 and 2)."""
        return SCHEMES[self.scheme][1] if self.order > 2 else (1.0,)

    @property
    def control_nodes(self) -> tuple[float, ...]:
        return scheme_nodes(self.weights)

    @property
    def implicit(self) -> bool:  # type: ignore[override]
        return self.solver == "newton" or self.dtau_order != 1

    def uses_kernel(self, system: AbstractSystem) -> bool:
        """True when ``system`` runs its closed-form kernel under this integrator."""
        return isinstance(system, AbstractClosedFormSystem) and self.solver == "auto" and self.dtau_order == 1

    def _alpha(self, dtype) -> Any:
        a = concrete_float(self.alpha)
        return a if a is not None else jnp.asarray(self.alpha, dtype)  # a Python float enables a in {0, 1}

    # ------------------------------------------------------------------ init / observe
    def init(self, system, h, q0, qdot0, c):
        r0, rdot0 = q0[3:], qdot0[3:]
        xi0 = body_velocity(q0, qdot0)
        pu, mu = jax.grad(system.reduced_lagrangian, argnums=(1, 2))(r0, rdot0, xi0)
        if self.uses_kernel(system):
            return system.kernel_init(q0, pu, mu)
        w0 = _locked_coords(system.symmetry_basis(r0), xi0 + system.connection(r0) @ rdot0)
        return RDPState(q=q0, pu=pu, mu=mu, u=rdot0, w=w0)

    def momenta(self, system: AbstractSystem, state: Any) -> tuple[Array, Array, Array]:
        """``(q, pu, mu)`` held by a state (general or kernel)."""
        if self.uses_kernel(system):
            return system.kernel_momenta(state)
        return state.q, state.pu, state.mu

    def observe(self, system, state, c) -> Observation:
        if self.uses_kernel(system):
            return system.kernel_observe(state, c)
        q = state.q
        u, xi = system.velocity_from_momenta(q[3:], state.pu, state.mu, system.inputs(c)[1])
        return system.observation(q, u, xi, c)

    def node(self, system, state, c):
        if self.uses_kernel(system):
            return system.kernel_node(state, c)
        q = state.q
        u, xi = system.velocity_from_momenta(q[3:], state.pu, state.mu, system.inputs(c)[1])
        return q, jnp.concatenate([spatial_velocity(q, xi), u])

    # ------------------------------------------------------------------ steps
    def step(self, system, h, state, c):
        weights = self.weights
        if len(weights) == 1:
            new, info = self._substep(system, h, state, c[0], c[1])
            # the step's code computed once: the whole step would otherwise be fused into every
            # consumer of the failure mask (each field of the next state: 15 copies of the step)
            return new, info._replace(result=materialise_result(info.result))
        # the composition: a scan over the substeps (a short loop, so the step compiles once)
        dtype = jnp.result_type(h)
        gam = jnp.asarray(weights, dtype)
        if self.uses_kernel(system):
            # an explicit substep cannot fail to converge: its singularity flags are ORed and the
            # state tested for finiteness once per composed step (not at every substep: 1.5-4%
            # faster); a step that met the singularity reports it, finite or not
            kernel_step = self._kernel(system)
            alpha = self._alpha(dtype)

            def kbody(carry, xs):
                st, singular, residual = carry
                g, c0, c1 = xs
                st, res, sing = kernel_step(alpha, g * h, self.retraction, st, c0, c1)
                return (st, singular | sing, jnp.maximum(residual, res)), None

            init = (state, jnp.zeros((), bool), jnp.zeros((), dtype))
            (state, singular, residual), _ = jax.lax.scan(kbody, init, (gam, c[:-1], c[1:]))
            result = RESULTS.where(
                singular,
                RESULTS.singular,
                RESULTS.where(finite(state), RESULTS.successful, RESULTS.nonfinite),
            )
            info = StepInfo(
                result=materialise_result(result), residual=residual, iterations=jnp.zeros((), jnp.int32)
            )
            return state, info

        def body(carry, xs):
            st, result, residual, iterations = carry
            g, c0, c1 = xs
            st, info = self._substep(system, g * h, st, c0, c1)
            result = RESULTS.where(result == RESULTS.successful, info.result, result)
            return (st, result, jnp.maximum(residual, info.residual), iterations + info.iterations), None

        zero = jnp.zeros((), dtype)
        init = (state, RESULTS.successful, zero, jnp.zeros((), jnp.int32))
        (state, result, residual, iterations), _ = jax.lax.scan(body, init, (gam, c[:-1], c[1:]))
        return state, StepInfo(result=result, residual=residual, iterations=iterations)

    def _substep(self, system, h, state, c0, c1) -> tuple[Any, StepInfo]:
        """One RDP step of size ``h`` with control values ``c0`` at its start, ``c1`` at its end."""
        if self.uses_kernel(system):
            dtype = jnp.result_type(h)
            new, residual, singular = self._kernel(system)(
                self._alpha(dtype), h, self.retraction, state, c0, c1
            )
            # an explicit step has nothing to converge; its residual is a diagnostic only
            result = classify(finite(new), singular, jnp.ones((), bool))
            return new, StepInfo(result=result, residual=residual, iterations=jnp.zeros((), jnp.int32))
        return self._newton_step(system, h, state, c0, c1)

    def _kernel(self, system):
        """The closed-form step of ``system`` (with its hand-written VJP outside forward mode)."""
        return system.kernel_step_reverse if self.reverse_only else system.kernel_step

    def _residual(self, system, h, r, u, xi, pu_force, mu_in):
        """Horizontal (23) and vertical (21) residuals at ``(u, xi)``; ``pu_force`` is
        ``pu_k + h (1-a) f_{k+a}``. Friction (a dissipation function ``R``) evaluated at the
        step's ``(r_{k+a}, u, xi)``, split like the shape forces: ``h (1-a) f_r`` joins ``pu_force``
        and ``h (1-a) F`` is taken off the group momentum before its transport, as if it acted on
        the step's momentum ``d_xi l``."""
        a = self._alpha(r.dtype)
        r_a = r + a * h * u
        dl_dr, dl_du, dl_dxi = jax.grad(system.reduced_lagrangian, argnums=(0, 1, 2))(r_a, u, xi)
        friction = system.dissipative_forces(r_a, u, xi)
        if friction is not None:
            f_r, F = friction
            pu_force = pu_force + h * (1 - a) * f_r
            dl_dxi = dl_dxi - h * (1 - a) * F
        jump = self._dtau(h * xi).T @ dl_dxi - mu_in
        hor = dl_du - h * (1 - a) * dl_dr - system.connection(r).T @ jump - pu_force
        return hor, system.symmetry_basis(r).T @ jump

    def _dtau(self, v):
        return dtau_inv(v, self.retraction, self.dtau_order)

    def _newton_step(self, system, h, state: RDPState, c0, c1) -> tuple[RDPState, StepInfo]:
        q = state.q
        r = q[3:]
        dtype = q.dtype
        a = self._alpha(dtype)
        f0, uk0 = system.inputs(c0)
        f1, uk1 = system.inputs(c1)
        f_a = (1 - a) * f0 + a * f1
        u_kin = 0.5 * (uk0 + uk1)
        pu_force = state.pu + h * (1 - a) * f_a
        dyn = np.asarray(system.dynamic_index, dtype=int)
        kin = np.asarray(system.kinematic_index, dtype=int)
        nd = dyn.size

        def unpack(z):
            u = u_kin.at[dyn].set(z[:nd]) if nd else u_kin
            r_a = r + a * h * u
            return u, system.symmetry_basis(r_a) @ z[nd:] - system.connection(r_a) @ u

        def residual(z):
            hor, vert = self._residual(system, h, r, *unpack(z), pu_force, state.mu)
            return jnp.concatenate([hor[dyn], vert])

        scale = 1.0 + safe_vnorm(pu_force) + safe_vnorm(state.mu)
        u_guess = state.u.at[kin].set(u_kin[kin]) if kin.size else state.u
        z, info = newton(
            residual,
            jnp.concatenate([u_guess[dyn], state.w]),
            tol=10 * jnp.finfo(dtype).eps ** 0.75 * scale,
            max_iterations=self.newton_iterations,
        )
        u, xi = unpack(z)
        r_a = r + a * h * u
        dl_dr, dl_du, dl_dxi = jax.grad(system.reduced_lagrangian, argnums=(0, 1, 2))(r_a, u, xi)
        friction = system.dissipative_forces(r_a, u, xi)
        if friction is not None:  # the step's end takes the share alpha
            f_r, F = friction
            f_a = f_a + f_r
            dl_dxi = dl_dxi + h * a * F
        g_next = compose(q[:3], retract(h * xi, self.retraction))
        new = RDPState(
            q=jnp.concatenate([g_next, r + h * u]),
            pu=dl_du + h * a * (dl_dr + f_a),
            mu=self._dtau(-h * xi).T @ dl_dxi,
            u=u,
            w=z[nd:],
        )
        result = classify(finite(new), system.singular(new.q, q), info.converged)
        return new, StepInfo(result=result, residual=info.residual / scale, iterations=info.iterations)
