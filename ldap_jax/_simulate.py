"""Rollouts: :func:`simulate` runs any integrator on any system with one ``lax.scan``."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from ._controls import AbstractControls
from ._scan import check_checkpoint, checkpointed_scan
from .integrators import RDP, AbstractIntegrator, _fast
from .systems import AbstractSystem

__all__ = ["simulate", "Trajectory", "RESULTS"]

#: Result codes of a trajectory (``Trajectory.result``).
RESULTS = {0: "successful", 1: "non-finite values", 2: "singular configuration", 3: "solver did not converge"}


class Trajectory(eqx.Module):
    """A discrete trajectory and its diagnostics. Shapes for a single trajectory; a vmapped
    call adds leading batch axes.

    Attributes:
        t: node times ``t_k``, (N+1,).
        q: configurations ``q_k = (x, y, theta, r1, r2)``, (N+1, d). NaN after a failure.
        qdot: velocity estimates at the nodes, (N+1, d). NaN after a failure.
        energy: ``E(q_k, qdot_k)``, (N+1,).
        work: control work ``int_0^{t_k} <f, rdot> dt`` (trapezoidal on the nodes), (N+1,).
        momentum: nonholonomic momentum ``mu_b = <dl/dxi, e_b(r)>`` at the nodes, (N+1, c).
        constraint_residual: ``|omega(q_k) qdot_k|``, (N+1,).
        step_residual: residual of the step's equations after the solve (for RDP: the
            horizontal (23) and discrete momentum (21) equations), (N+1,).
        converged: per-step convergence of implicit solves, (N+1,).
        result: 0 on success, else a code of :data:`RESULTS` (the first failure).
        failure_index: index of the first failed step (N+1 when none failed).
    """

    t: Float[Array, " N1"]
    q: Float[Array, "N1 d"]
    qdot: Float[Array, "N1 d"]
    energy: Float[Array, " N1"]
    work: Float[Array, " N1"]
    momentum: Float[Array, "N1 c"]
    constraint_residual: Float[Array, " N1"]
    step_residual: Float[Array, " N1"]
    converged: Bool[Array, " N1"]
    result: Int[Array, ""]
    failure_index: Int[Array, ""]

    @property
    def failed(self) -> Bool[Array, ""]:
        """True where the integration failed (see :attr:`result`)."""
        return self.result != 0

    @property
    def energy_balance(self) -> Float[Array, " N1"]:
        """``E_k - E_0 - W_k``: zero for the exact flow (work-energy balance)."""
        return self.energy - self.energy[..., :1] - self.work


def _check_inputs(system, q0, qdot0, controls, n_steps, integrator):
    if not isinstance(system, AbstractSystem):
        raise TypeError(
            f"'system' must be an ldap_jax system (e.g. lj.Car, lj.Snakeboard), got {type(system)}"
        )
    if not isinstance(controls, AbstractControls):
        raise TypeError(f"'controls' must be an ldap_jax control (e.g. lj.Sinusoids), got {type(controls)}")
    if not isinstance(integrator, AbstractIntegrator):
        raise TypeError(
            f"'integrator' must be an ldap_jax integrator (e.g. lj.RDP()), got {type(integrator)}"
        )
    d = system.n_config
    for name, x in (("q0", q0), ("qdot0", qdot0)):
        if jnp.shape(x) != (d,):
            raise ValueError(
                f"'{name}' must have shape ({d},) for {type(system).__name__}, got {jnp.shape(x)}"
            )
        dtype = jnp.result_type(x)
        if not jnp.issubdtype(dtype, jnp.floating):
            raise ValueError(f"'{name}' must be a floating-point array, got dtype {dtype}")
    if controls.n_channels != system.n_controls:
        raise ValueError(
            f"'controls' has {controls.n_channels} channels but {type(system).__name__} takes "
            f"{system.n_controls} {system.control_names}"
        )
    if isinstance(n_steps, bool) or not isinstance(n_steps, (int, np.integer)) or n_steps < 1:
        raise ValueError(f"'n_steps' must be a positive integer, got {n_steps!r}")


def _has_tracer(tree) -> bool:
    return any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(tree))


def _check_constraints_now(system, q0, qdot0, controls, t0):
    """Eager check of ``omega(q0) qdot0 = 0`` for concrete inputs (a clear ``ValueError``)."""
    q0, qdot0 = jnp.asarray(q0), jnp.asarray(qdot0)
    qdot0 = system.consistent_qdot(q0, qdot0, controls(jnp.asarray(t0, q0.dtype)))
    viol = float(system.constraint_residual(q0, qdot0))
    tol = 1e4 * float(jnp.finfo(qdot0.dtype).eps) * (1.0 + float(jnp.max(jnp.abs(qdot0))))
    if not viol <= tol:
        raise ValueError(
            f"'qdot0' violates the constraints: |omega(q0) qdot0| = {viol:.3e} > {tol:.1e}. "
            f"Build it on the constraint distribution, e.g. system.qdot_from_velocities(q0, v0, u_kin)."
        )


def _common_dtype(q0, qdot0):
    dtype = jnp.result_type(q0, qdot0)
    return dtype


def _cast(tree, dtype):
    return jax.tree_util.tree_map(
        lambda x: x.astype(dtype) if eqx.is_array(x) and jnp.issubdtype(x.dtype, jnp.floating) else x, tree
    )


def simulate(
    system: AbstractSystem,
    q0: ArrayLike,
    qdot0: ArrayLike,
    controls: AbstractControls,
    *,
    t_final: ArrayLike,
    n_steps: int,
    integrator: AbstractIntegrator | None = None,
    t0: ArrayLike = 0.0,
    checkpoint: bool = False,
    throw: bool = False,
    check_constraints: bool = True,
    fast_path: bool = True,
) -> Trajectory:
    """Integrate ``system`` from ``(q0, qdot0)`` over ``[t0, t_final]`` in ``n_steps`` steps.

    One ``lax.scan`` over the integrator's pure ``step``, jit-compiled; vmap over ``q0``,
    ``qdot0``, ``controls`` (and the system's parameters) at the call site; differentiable in
    every floating input. The dtype follows ``q0``/``qdot0``; the system and controls are cast to it.

    Args:
        system: e.g. :class:`~ldap_jax.Car` or :class:`~ldap_jax.Snakeboard`.
        q0: initial configuration ``(x, y, theta, r1, r2)``.
        qdot0: initial velocity; must satisfy the constraints ``omega(q0) qdot0 = 0``.
            Entries of kinematic shape coordinates (the car's ``sigma_dot``) are taken from the
            controls at ``t0``.
        controls: control signal with ``system.n_controls`` channels.
        t_final: end time (> t0).
        n_steps: number of steps N (static: each new N compiles once).
        integrator: default ``RDP(alpha=0.5, retraction="exp")``.
        t0: start time.
        checkpoint: memory policy for reverse mode: ``False`` (the fastest: store every step's
            internals; the car/snakeboard RDP kernel stores only each step's sin/cos values and
            failure masks and recomputes its arithmetic),
            ``True``/``"step"`` (``jax.checkpoint`` on the scan body: O(N) states), ``"sqrt"``
            (nested: ~sqrt(N) checkpointed chunks of ~sqrt(N) steps, O(sqrt N) states for about one
            extra forward pass), or an integer chunk length.
        throw: raise (inside jit, via ``eqx.error_if``) if the integration failed.
        check_constraints: raise when ``qdot0`` violates the constraints.
        fast_path: use the specialised kernel where one exists (``RDP`` with the closed form on
            ``Car`` and ``Snakeboard``: structure-of-arrays state, trigonometric values computed
            once and reused, diagnostics inside the scan). It computes the same trajectory as
            the general path to round-off; ``False`` forces the general path.

    Returns:
        :class:`Trajectory` with ``t`` (N+1,), ``q`` and ``qdot`` (N+1, d), diagnostics and a
        result code.

    Raises:
        ValueError: bad shapes or dtypes, ``n_steps < 1``, ``t_final <= t0``, or ``qdot0``
            violating the constraints.

    Example:
        >>> sb = lj.Snakeboard(m=1.0, l=0.5, I=0.05, J=0.02)
        >>> ctl = lj.Sinusoids(amplitude=[[0.1], [0.02]], frequency=[[2.0], [2.0]], phase=[[0.0], [0.0]])
        >>> traj = lj.simulate(sb, jnp.zeros(5), jnp.zeros(5), ctl, t_final=5.0, n_steps=500)
    """
    if integrator is None:
        integrator = RDP()
    _check_inputs(system, q0, qdot0, controls, n_steps, integrator)
    for name, val in (("t_final", t_final), ("t0", t0)):
        if jnp.ndim(val) != 0:
            raise ValueError(f"'{name}' must be a scalar, got shape {jnp.shape(val)}")
    if not isinstance(t_final, jax.core.Tracer) and not isinstance(t0, jax.core.Tracer):
        if not float(t_final) > float(t0):
            raise ValueError(f"'t_final' must exceed t0 (a positive step), got t_final={t_final}, t0={t0}")
    if check_constraints and not _has_tracer((q0, qdot0, controls, system, t0)):
        _check_constraints_now(system, q0, qdot0, controls, t0)
    # arrays, not Python floats: a new value must not trigger a new compilation
    t0, t_final = jnp.asarray(t0), jnp.asarray(t_final)
    return _simulate(
        system,
        q0,
        qdot0,
        controls,
        t0,
        t_final,
        integrator,
        n_steps=int(n_steps),
        checkpoint=check_checkpoint(checkpoint),
        throw=throw,
        check_constraints=check_constraints,
        fast_path=bool(fast_path),
    )


@eqx.filter_jit
def _simulate(
    system,
    q0,
    qdot0,
    controls,
    t0,
    t_final,
    integrator,
    *,
    n_steps,
    checkpoint,
    throw,
    check_constraints,
    fast_path=True,
):
    dtype = _common_dtype(q0, qdot0)
    q0 = jnp.asarray(q0, dtype)
    qdot0 = jnp.asarray(qdot0, dtype)
    system = _cast(system, dtype)
    controls = _cast(controls, dtype)
    t0 = jnp.asarray(t0, dtype)
    t_final = jnp.asarray(t_final, dtype)
    h = (t_final - t0) / n_steps
    eps = jnp.finfo(dtype).eps

    c_first = controls(t0)
    qdot0 = system.consistent_qdot(q0, qdot0, c_first)
    if check_constraints:
        viol = system.constraint_residual(q0, qdot0)
        tol = 1e4 * eps * (1.0 + jnp.max(jnp.abs(qdot0)))
        qdot0 = eqx.error_if(
            qdot0,
            viol > tol,
            "'qdot0' violates the constraints omega(q0) qdot0 = 0 (project it onto the constraints)",
        )

    t_nodes = t0 + h * jnp.arange(n_steps + 1, dtype=dtype)
    if fast_path and _fast.supports(system, integrator):
        out = _fast.rdp_rollout(system, integrator, q0, qdot0, controls, t0, h, n_steps, checkpoint)
        work = jnp.concatenate(
            [jnp.zeros((1,), dtype), jnp.cumsum(0.5 * h * (out.power[1:] + out.power[:-1]))]
        )
        traj = Trajectory(
            t=t_nodes,
            q=out.q,
            qdot=out.qdot,
            energy=out.energy,
            work=work,
            momentum=out.momentum,
            constraint_residual=out.constraint_residual,
            step_residual=out.step_residual,
            converged=out.converged,
            result=out.result,
            failure_index=out.failure_index,
        )
        if throw:
            traj = eqx.error_if(
                traj, out.result != 0, "simulate: the integration failed (see Trajectory.result)"
            )
        return traj

    fractions = jnp.asarray(integrator.control_nodes, dtype)
    stage_t = t_nodes[:, None] + h * fractions[None, :]
    cvals = jax.vmap(jax.vmap(controls))(stage_t)  # (N+1, S, n_channels)

    state0 = integrator.init(system, h, q0, qdot0, cvals[0])
    nan = jnp.asarray(jnp.nan, dtype)

    def body(carry, c_k):
        state, code, index, k = carry
        new_state, (q_k, qdot_k), info = integrator.step(system, h, state, c_k)
        q_next = integrator.configuration(new_state)
        leaves = jax.tree_util.tree_leaves(new_state)
        finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in leaves]))
        step_code = jnp.where(
            ~finite,
            1,
            jnp.where(
                system.singular(q_next, integrator.configuration(state)), 2, jnp.where(info.converged, 0, 3)
            ),
        )
        ok_before = code == 0
        new_code = jnp.where(ok_before, step_code, code)
        new_index = jnp.where(ok_before & (step_code != 0), k, index)
        keep = new_code == 0
        state_out = jax.tree_util.tree_map(lambda a, b: jnp.where(keep, a, b), new_state, state)
        q_out = jnp.where(ok_before, q_k, nan)
        qdot_out = jnp.where(keep, qdot_k, nan)
        out = (q_out, qdot_out, info.residual, info.converged)
        return (state_out, new_code, new_index, k + 1), out

    init = (state0, jnp.zeros((), jnp.int32), jnp.asarray(n_steps + 1, jnp.int32), jnp.zeros((), jnp.int32))
    (_, code, index, _), (q, qdot, residual, converged) = checkpointed_scan(
        body, init, cvals, length=n_steps + 1, checkpoint=checkpoint
    )
    # node 0 reports the given initial velocity. The last scan step only produced the velocity
    # estimate at t_N; a failure there leaves q_N valid but is still reported in `result`.
    qdot = qdot.at[0].set(qdot0)

    c_nodes = cvals[:, 0] if float(integrator.control_nodes[0]) == 0.0 else jax.vmap(controls)(t_nodes)
    energy = jax.vmap(system.energy)(q, qdot)
    f_nodes = jax.vmap(lambda c: system.inputs(c)[0])(c_nodes)
    power = jax.vmap(system.power)(f_nodes, qdot)
    work = jnp.concatenate([jnp.zeros((1,), dtype), jnp.cumsum(0.5 * h * (power[1:] + power[:-1]))])
    momentum = jax.vmap(system.momentum)(q, qdot)
    cres = jax.vmap(system.constraint_residual)(q, qdot)
    traj = Trajectory(
        t=t_nodes,
        q=q,
        qdot=qdot,
        energy=energy,
        work=work,
        momentum=momentum,
        constraint_residual=cres,
        step_residual=residual,
        converged=converged,
        result=code,
        failure_index=index,
    )
    if throw:
        traj = eqx.error_if(traj, code != 0, "simulate: the integration failed (see Trajectory.result)")
    return traj
