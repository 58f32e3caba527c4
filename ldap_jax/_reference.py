"""High-accuracy reference solutions with diffrax (ground truth for tests and sweeps)."""

from __future__ import annotations

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from ._controls import AbstractControls
from .systems import AbstractSystem

__all__ = ["reference", "Solution"]


class Solution(eqx.Module):
    """A reference solution sampled at ``ts``.

    Attributes:
        t: sample times (T,). q: configurations (T, d). qdot: velocities (T, d).
        result: 0 when diffrax succeeded (``diffrax.RESULTS``), else the failure code.
        num_steps: accepted + rejected steps taken by the adaptive solver.
    """

    t: Float[Array, " T"]
    q: Float[Array, "T d"]
    qdot: Float[Array, "T d"]
    result: Int[Array, ""]
    num_steps: Int[Array, ""]

    @property
    def failed(self):
        return self.result != 0


def reference(
    system: AbstractSystem,
    q0: ArrayLike,
    qdot0: ArrayLike,
    controls: AbstractControls,
    ts: ArrayLike,
    *,
    t0: ArrayLike = 0.0,
    rtol: float = 1e-11,
    atol: float = 1e-11,
    solver: diffrax.AbstractSolver | None = None,
    max_steps: int = 2**22,
) -> Solution:
    """Solve the continuous Lagrange-d'Alembert equations with diffrax at tight tolerances.

    Integrates the minimal form ``(q, v)`` of the equations of motion (the system's
    ``velocity_dynamics``, checked against the full KKT form ``M qddot = F + omega^T lambda``
    in the tests) with Dopri8 and a PID step-size controller.

    Args:
        system, q0, qdot0, controls: as for :func:`ldap_jax.simulate`.
        ts: non-decreasing sample times (T,), all ``>= t0``; e.g. ``traj.t`` of a
            :func:`~ldap_jax.simulate` run, or just ``[t_final]``.
        t0: the time at which ``(q0, qdot0)`` is given (default 0, as for :func:`~ldap_jax.simulate`).
        rtol, atol: tolerances (float64 recommended: enable ``jax_enable_x64``).
        solver: a diffrax solver (default ``diffrax.Dopri8()``).
        max_steps: cap on solver steps.

    Returns:
        :class:`Solution` with ``q`` and ``qdot`` at ``ts``.
    """
    ts = jnp.asarray(ts)
    if ts.ndim != 1 or ts.shape[0] < 1:
        raise ValueError(f"'ts' must be a non-empty 1-d array of times, got shape {ts.shape}")
    for name, x in (("q0", q0), ("qdot0", qdot0)):
        if jnp.shape(x) != (system.n_config,):
            raise ValueError(f"'{name}' must have shape ({system.n_config},), got {jnp.shape(x)}")
    if controls.n_channels != system.n_controls:
        raise ValueError(
            f"'controls' has {controls.n_channels} channels, the system takes {system.n_controls}"
        )
    if jnp.ndim(t0) != 0:
        raise ValueError(f"'t0' must be a scalar, got shape {jnp.shape(t0)}")
    if not isinstance(ts, jax.core.Tracer) and not isinstance(t0, jax.core.Tracer):
        ts_np = np.asarray(ts)
        if np.any(np.diff(ts_np) < 0) or ts_np[0] < float(t0):
            raise ValueError(f"'ts' must be non-decreasing and start at or after t0={float(t0)}, got {ts_np}")
    return _reference(system, q0, qdot0, controls, ts, t0, rtol, atol, solver or diffrax.Dopri8(), max_steps)


@eqx.filter_jit
def _reference(system, q0, qdot0, controls, ts, t0, rtol, atol, solver, max_steps):
    dtype = jnp.result_type(q0, qdot0, ts)
    from ._simulate import _cast

    system, controls = _cast(system, dtype), _cast(controls, dtype)
    q0, qdot0, ts = jnp.asarray(q0, dtype), jnp.asarray(qdot0, dtype), jnp.asarray(ts, dtype)
    t0 = jnp.asarray(t0, dtype)
    qdot0 = system.consistent_qdot(q0, qdot0, controls(t0))
    v0 = system.velocities_from_qdot(q0, qdot0)

    def vector_field(t, y, args):
        return system.ode(y, controls(t))

    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(vector_field),
        solver,
        t0=t0,
        t1=ts[-1],
        dt0=None,
        y0=(q0, v0),
        saveat=diffrax.SaveAt(ts=ts),
        stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol),
        max_steps=max_steps,
        throw=False,
    )
    q, v = sol.ys
    u_kin = jax.vmap(lambda t: system.inputs(controls(t))[1])(ts)
    qdot = jax.vmap(system.qdot_from_velocities)(q, v, u_kin)
    result = jnp.where(sol.result == diffrax.RESULTS.successful, 0, 1).astype(jnp.int32)
    return Solution(t=ts, q=q, qdot=qdot, result=result, num_steps=sol.stats["num_steps"])
