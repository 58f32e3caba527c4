"""Discrete-time dynamics: any system and integrator as ``x_{k+1} = f(x_k, u_k, u_{k+1}, k)``.

The step of an integrator, with the controls of a step given by their values at the step's two
ends and interpolated linearly in between (exactly what :class:`~ldap_jax.Sampled` controls on
the same grid give to :func:`~ldap_jax.simulate`), is a discrete-time dynamical system. This
module exposes it, on a flat state vector, for optimizers that want ``f`` and its Jacobians
(iLQR, DDP, SQP, MPC, tracking), the way trajax's ``dynamics(x, u, t)`` is used.

The flat state of RDP is minimal: ``x = (q, P, nu)`` with ``P = pu - A(r)^T mu`` (n) and
``nu = e(r)^T mu`` (c), the only parts of the carried momenta that a step reads (two carried pairs
with the same ``(P, nu)`` are the same state), so ``df/dx`` has no redundant directions. Other
integrators use their state flattened.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Float

from . import _tracing
from ._compilation_cache import as_dtype, compiled_unless_staged
from ._controls import Constant
from ._linalg import solve
from ._results import RESULTS
from ._typing import ArrayLike
from ._validation import cast_floats, check_array, is_concrete, known_initial_violation
from .integrators import RDP, AbstractIntegrator
from .systems import AbstractSystem, Observation

__all__ = ["DiscreteDynamics", "discretize"]


class DiscreteDynamics(eqx.Module):
    """``x_{k+1} = f(x_k, u_k, u_{k+1}, k)`` for a system, an integrator and a step ``h``.

    ``u_k`` are control channel values at ``t_k = t0 + k h`` (shape ``(n_controls,)``); inside a
    step the integrator reads them interpolated linearly. All methods are pure, jit-able,
    vmap-able and differentiable; the state is a flat vector of length :attr:`n_state`. Called on
    values (in a notebook, or under a top-level ``jax.grad``/``jax.jacfwd``) each method runs as
    one compiled program, compiled once for all later values; inside your ``jax.jit`` it is traced
    inline into your program. To compile a method on its own, use ``eqx.filter_jit(dyn.step)``
    or ``jax.jit(lambda x, u0, u1: dyn.step(x, u0, u1))``: ``jax.jit(dyn.step)`` fails, as for any
    equinox module holding arrays (a bound method must be hashable for ``jax.jit``).

    Arguments are checked when a method is traced: a state, configuration or control of the wrong
    shape raises a ``ValueError`` naming it and the expected length. The dynamics compute in the
    dtype of ``h`` (a Python float: the default float, float64 with ``jax_enable_x64``); states,
    configurations and controls of another float dtype are converted to it (for float32 dynamics
    pass ``h=jnp.float32(...)``).

    Attributes:
        system, integrator: the model and the scheme.
        h: step (s). t0: time of node 0 (s).

    Example:
        >>> dyn = lj.discretize(lj.Car(), lj.RDP(order=6), h=0.1)
        >>> x = dyn.init(q0, qdot0, u0)
        >>> x1 = dyn.step(x, u0, u1, 0)
        >>> A = jax.jacfwd(dyn.step)(x, u0, u1, 0)   # df/dx
    """

    system: AbstractSystem
    integrator: AbstractIntegrator
    h: Array
    t0: Array
    template: Any = eqx.field(static=True)

    @property
    def n_state(self) -> int:
        """Length of the flat state."""
        return self.template[0]

    @property
    def n_controls(self) -> int:
        return self.system.n_controls

    def _checked(self, name: str, x: ArrayLike, kind: str) -> Array:
        """``x`` as a float vector of the length of its ``kind`` (``"x"`` a state, ``"q"`` a
        configuration, ``"u"`` controls), or an error naming ``name`` (shapes are static, so
        this runs once, when the method is traced)."""
        n = {"x": self.n_state, "q": self.system.n_config, "u": self.n_controls}[kind]
        what = {"x": "n_state", "q": "n_config", "u": "n_controls"}[kind]
        x = check_array(name, x, (n,), f"({what} of this {type(self.system).__name__} discretization)")
        dtype = self.h.dtype  # the dynamics' dtype (h's): inputs of another are converted to it
        if x.dtype != dtype:
            x = as_dtype(x, dtype)
        return x

    def _minimal(self) -> bool:
        return isinstance(self.integrator, RDP)

    # ------------------------------------------------------------------ state <-> flat
    def pack(self, state: Any) -> Float[Array, " n"]:
        """The flat vector of an integrator state."""
        if self._minimal():
            q, pu, mu = self.integrator.momenta(self.system, state)
            r = q[3:]
            p = pu - self.system.connection(r).T @ mu
            nu = self.system.symmetry_basis(r).T @ mu
            return jnp.concatenate([q, p, nu])
        return ravel_pytree(state)[0]

    def unpack(self, x: Float[Array, " n"], u: Array | None = None) -> Any:
        """The integrator state of a flat vector (``u``: the controls at its node, used by
        integrators that carry a warm start)."""
        system = self.system
        if self._minimal():
            d, n = system.n_config, system.n_shape
            q, p, nu = x[:d], x[d : d + n], x[d + n :]
            r = q[3:]
            e = system.symmetry_basis(r)
            mu = e @ solve(e.T @ e, nu) if e.shape[1] else jnp.zeros(3, x.dtype)
            pu = p + system.connection(r).T @ mu
            if self.integrator.uses_kernel(system):
                return system.kernel_init(q, pu, mu)
            from .integrators._rdp import RDPState

            u_prev = jnp.zeros(n, x.dtype) if u is None else system.inputs(u)[1]
            return RDPState(q=q, pu=pu, mu=mu, u=u_prev, w=jnp.zeros(e.shape[1], x.dtype))
        _, unravel = ravel_pytree(self._example_state(x.dtype))
        return unravel(x)

    def _example_state(self, dtype):
        d = self.system.n_config
        z = jnp.zeros(d, dtype)
        c = jnp.zeros((len(self.integrator.control_nodes), self.system.n_controls), dtype)
        return self.integrator.init(self.system, jnp.ones((), dtype), z, z, c)

    # ------------------------------------------------------------------ dynamics
    def stage_controls(self, u0: Array, u1: Array) -> Float[Array, "S n_controls"]:
        """The values the integrator reads on a step: linear interpolation at its fractions."""
        f = jnp.asarray(self.integrator.control_nodes, u0.dtype)[:, None]
        return (1 - f) * u0[None] + f * u1[None]

    def init(self, q0: ArrayLike, qdot0: ArrayLike, u0: ArrayLike) -> Float[Array, " n"]:
        """The flat state at node 0 from a configuration and a velocity on the constraints
        (kinematic entries of ``qdot0`` are taken from ``u0``).

        Raises:
            ValueError: a shape that does not fit the system; on known values, a non-finite
                entry or a ``qdot0`` off the constraints (as :func:`ldap_jax.simulate`).
        """
        if is_concrete((q0, qdot0, u0)):
            # inputs rounded to a coarser dtype than the dynamics' are off the constraints by that
            # rounding: the tolerance is the coarser dtype's
            eps = [np.finfo(np.asarray(v).dtype).eps for v in (q0, qdot0) if np.asarray(v).dtype.kind == "f"]
            q0, qdot0, u0 = (
                self._checked("q0", q0, "q"),
                self._checked("qdot0", qdot0, "q"),
                self._checked("u0", u0, "u"),
            )
            for name, v in (("q0", q0), ("qdot0", qdot0), ("u0", u0)):
                if not np.all(np.isfinite(np.asarray(v))):
                    raise ValueError(f"'{name}' must be finite, got {np.asarray(v)}")
            viol, tol = known_initial_violation(self.system, q0, qdot0, Constant(u0), 0.0)[1:]
            tol *= max(1.0, max(eps, default=0.0) / float(np.finfo(q0.dtype).eps)) ** 0.75
            if not viol <= tol:
                raise ValueError(
                    f"'qdot0' violates the constraints of {type(self.system).__name__} "
                    f"({viol:.2e} > {tol:.2e})"
                )
        return self._init(q0, qdot0, u0)

    @compiled_unless_staged
    def _init(self, q0, qdot0, u0):
        system = self.system
        q0, qdot0, u0 = (
            self._checked("q0", q0, "q"),
            self._checked("qdot0", qdot0, "q"),
            self._checked("u0", u0, "u"),
        )
        qdot0 = system.consistent_qdot(q0, qdot0, u0)
        c = self.stage_controls(u0, u0)
        return self.pack(self.integrator.init(system, self.h, q0, qdot0, c))

    @compiled_unless_staged
    def step(
        self, x: Float[Array, " n"], u0: ArrayLike, u1: ArrayLike, k: ArrayLike = 0
    ) -> Float[Array, " n"]:
        """``x_{k+1}`` from ``x_k`` and the control values at both ends of the step (``k`` is
        accepted for time-varying use; the dynamics are autonomous in ``k`` for open-loop
        controls, which enter only through ``u``).

        The step's value whatever its result: a step that did not converge or crossed the
        system's singularity returns its last iterate (an optimizer's trial point may). Use
        :meth:`step_with_info` for the result code, or :meth:`rollout`, which marks a failed
        step's state and every later one NaN."""
        return self.step_with_info(x, u0, u1, k)[0]

    @compiled_unless_staged
    def step_with_info(self, x, u0, u1, k=0):
        """``(x_{k+1}, StepInfo)``: the step's result code and residual."""
        x = self._checked("x", x, "x")
        u0, u1 = (self._checked(name, u, "u").astype(x.dtype) for name, u in (("u0", u0), ("u1", u1)))
        state = self.unpack(x, u0)
        state, info = _tracing.step(self.integrator, self.system, self.h, state, self.stage_controls(u0, u1))
        x1 = self.pack(state)
        # a step traced in discretize (under the user's jit) is checked here: NaN and invalid_input
        ok = jnp.isfinite(self.h) & (self.h > 0)
        info = info._replace(result=RESULTS.where(ok, info.result, RESULTS.invalid_input))
        x1 = jnp.where(ok, x1, jnp.nan)
        return x1, info

    @compiled_unless_staged
    def observe(self, x: Float[Array, " n"], u: ArrayLike) -> Observation:
        """The node held by ``x``: configuration, velocity (from the momenta for RDP) and the
        diagnostics, with ``u`` the controls at the node."""
        x = self._checked("x", x, "x")
        u = self._checked("u", u, "u").astype(x.dtype)
        return self.integrator.observe(self.system, self.unpack(x, u), u)

    @compiled_unless_staged
    def node(self, x: Float[Array, " n"], u: ArrayLike) -> tuple[Array, Array]:
        """``(q, qdot)`` held by ``x`` (no diagnostics: the light path for costs and constraints)."""
        x = self._checked("x", x, "x")
        u = self._checked("u", u, "u").astype(x.dtype)
        return self.integrator.node(self.system, self.unpack(x, u), u)

    @compiled_unless_staged
    def rollout(self, x0: Float[Array, " n"], us: Float[Array, "K n_controls"]) -> Float[Array, "K n"]:
        """States at nodes ``0 .. K-1`` from ``x0`` and the control values ``us`` (K >= 1) at the
        nodes (one ``lax.scan``). From a step that fails (Newton not converged, the system's
        singularity, a non-finite state) on, the states are NaN."""
        m = self.system.n_controls
        if jnp.ndim(us) != 2 or jnp.shape(us)[0] < 1 or jnp.shape(us)[1] != m:
            raise ValueError(f"'us' must be (K, {m}) with K >= 1 nodes, got shape {jnp.shape(us)}")

        def body(x, uu):
            x1, info = self.step_with_info(x, uu[0], uu[1])
            x1 = jnp.where(info.result == RESULTS.successful, x1, jnp.nan)
            return x1, x1

        _, xs = jax.lax.scan(body, x0, (us[:-1], us[1:]))
        return jnp.concatenate([x0[None], xs])


def discretize(
    system: AbstractSystem, integrator: AbstractIntegrator | None = None, *, h: ArrayLike, t0: ArrayLike = 0.0
) -> DiscreteDynamics:
    """The discrete-time dynamics ``x_{k+1} = f(x_k, u_k, u_{k+1}, k)`` of ``integrator`` (default
    ``lj.RDP()``) on ``system`` with step ``h`` (s), node ``k`` at ``t_k = t0 + k h`` (``t0``
    default 0).

    Raises:
        TypeError, ValueError: a bad system, integrator, step or start time.
    """
    integrator = RDP() if integrator is None else integrator
    if not isinstance(system, AbstractSystem):
        raise TypeError(f"'system' must be an ldap_jax system, got {type(system)}")
    if not isinstance(integrator, AbstractIntegrator):
        raise TypeError(f"'integrator' must be an ldap_jax integrator, got {type(integrator)}")
    h_arr = check_array("h", h, ())
    if not isinstance(h_arr, jax.core.Tracer) and not bool(jnp.isfinite(h_arr) & (h_arr > 0)):
        raise ValueError(f"'h' must be a positive finite step, got {h}")
    t0_arr = check_array("t0", t0, ())
    if not isinstance(t0_arr, jax.core.Tracer) and not bool(jnp.isfinite(t0_arr)):
        raise ValueError(f"'t0' must be finite, got {t0}")
    dtype = h_arr.dtype
    system, integrator = cast_floats((system, integrator), dtype)
    probe = DiscreteDynamics(system, integrator, h_arr, jnp.asarray(t0, dtype), (0,))
    d = system.n_config
    z = jnp.zeros(d, dtype)
    n = jax.eval_shape(lambda: probe.init(z, z, jnp.zeros(system.n_controls, dtype))).shape[0]
    return DiscreteDynamics(system, integrator, h_arr, jnp.asarray(t0, dtype), (int(n),))
