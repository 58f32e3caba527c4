"""Rollouts: :func:`simulate` runs any integrator on any system with one ``lax.scan``."""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ._compilation_cache import as_dtype, jit, note_program, program_key
from ._controls import AbstractControls, Constant
from ._policy import AbstractPolicy, LinearPolicy, Policy
from ._results import RESULTS
from ._rollout import check_checkpoint, check_save, rollout
from ._typing import ArrayLike
from ._validation import (
    ArrayOrSequence,
    cast_floats,
    check_array,
    check_positive_int,
    check_positive_number,
    check_scalar,
    input_result,
    raise_if_concrete,
)
from .integrators import RDP, AbstractIntegrator
from .systems import AbstractSystem

__all__ = ["simulate", "Trajectory"]


class Trajectory(eqx.Module):
    """A discrete trajectory and its diagnostics, at the saved nodes (``M`` of them: ``N + 1``
    for ``save="all"``). Shapes for a single trajectory; a vmapped call adds leading batch axes.

    Attributes:
        t: node times ``t_k`` (s), (M,).
        q: configurations ``q_k = (x, y, theta, r1, ...)`` (m, rad), (M, d). NaN after a failure.
        qdot: velocities at the nodes (m/s, rad/s), (M, d), on the constraints; for RDP read from
            the carried momenta (the inverse of the reduced Legendre transform), not differenced.
            NaN after a failure.
        energy: ``E(q_k, qdot_k)`` (J), (M,); ``None`` with ``diagnostics=False``.
        work: control work ``int_{t0}^{t_k} <f, rdot> dt`` (J, trapezoidal on every node), (M,);
            ``None`` with ``diagnostics=False``.
        momentum: nonholonomic momentum ``mu_b = <dl/dxi, e_b(r)>`` at the nodes, (M, c); ``None``
            with ``diagnostics=False``.
        constraint_residual: ``|omega(q_k) qdot_k|``, (M,); ``None`` with ``diagnostics=False``.
        step_residual: largest residual of the steps since the previous saved node, relative to
            the scale of their momenta (RDP: the horizontal (23) and discrete momentum (21)
            equations; 0 for the explicit RK), (M,); ``None`` with ``diagnostics=False``. NaN
            after a failure.
        converged: every implicit solve since the previous saved node converged, (M,).
        result: a :class:`~ldap_jax.RESULTS` item (``RESULTS[traj.result]`` is the message).
        failure_index: index of the first failed step (``n_steps`` when none failed; 0 for
            invalid inputs found on traced values).
    """

    t: Float[Array, " M"]
    q: Float[Array, "M d"]
    qdot: Float[Array, "M d"]
    energy: Float[Array, " M"] | None
    work: Float[Array, " M"] | None
    momentum: Float[Array, "M c"] | None
    constraint_residual: Float[Array, " M"] | None
    step_residual: Float[Array, " M"] | None
    converged: Bool[Array, " M"]
    result: RESULTS
    failure_index: Int[Array, ""]

    @property
    def failed(self) -> Bool[Array, "*batch"]:
        """True where the integration failed (see :attr:`result`)."""
        return self.result != RESULTS.successful

    def filled(self, value: float = 0.0) -> Trajectory:
        """This trajectory with a failed run's floating arrays (every node, every diagnostic)
        replaced by ``value``: the double ``where`` that drops failed members from a batched loss
        with exact, finite gradients for the others (``result`` and ``failure_index`` are kept).
        Works on a single trajectory and on a batch (``failed`` of shape ``(B,)``)."""
        failed = self.failed

        def fill(x):
            if not (eqx.is_array(x) and jnp.issubdtype(x.dtype, jnp.inexact)):
                return x
            mask = failed.reshape(failed.shape + (1,) * (x.ndim - failed.ndim))
            return jnp.where(mask, jnp.asarray(value, x.dtype), x)

        fields = ("q", "qdot", "energy", "work", "momentum", "constraint_residual", "step_residual")
        return eqx.tree_at(
            lambda tr: [getattr(tr, f) for f in fields if getattr(tr, f) is not None],
            self,
            [fill(getattr(self, f)) for f in fields if getattr(self, f) is not None],
        )

    @property
    def energy_balance(self) -> Float[Array, "*batch M"]:
        """``E_k - E_0 - W_k``: zero for the exact flow (work-energy balance)."""
        if self.energy is None or self.work is None:
            raise ValueError("energy_balance needs the diagnostics (simulate(..., diagnostics=True))")
        return self.energy - self.energy[..., :1] - self.work


def check_problem(
    system: Any, controls: Any, q0: Any, qdot0: Any, *, policies: bool, caller: str
) -> tuple[Any, Array, Array]:
    """Validate what :func:`simulate` and :func:`ldap_jax.reference` share: the system, the
    controls (``None``: zero inputs; a policy only when ``policies``) and their channel count, the
    initial configuration and velocity; warns (naming ``caller``) when float32 is forced because
    float64 is off. Returns ``(controls, q0, qdot0)``."""
    if not isinstance(system, AbstractSystem):
        raise TypeError(
            f"'system' must be an ldap_jax system (e.g. lj.Car, lj.Snakeboard), got {type(system)}"
        )
    if controls is None:
        controls = Constant(jnp.zeros(system.n_controls, jnp.result_type(float)))
    kinds = (AbstractControls, AbstractPolicy) if policies else (AbstractControls,)
    if policies and callable(controls) and not isinstance(controls, kinds):
        controls = Policy(controls, system.n_controls)  # a function (or callable module): a feedback law
    if not isinstance(controls, kinds):
        raise TypeError(
            "'controls' must be ldap_jax controls (e.g. lj.Sinusoids)"
            + (", a policy (lj.Policy, or a function u = f(t, q, qdot))" if policies else " (open loop)")
            + f" or None, got {type(controls)}"
        )
    if controls.n_channels != system.n_controls:
        raise ValueError(
            f"'controls' has {controls.n_channels} channels but {type(system).__name__} takes "
            f"{system.n_controls} {system.control_names}"
        )
    if isinstance(controls, AbstractControls):  # a batch of controls must come through jax.vmap
        shape = tuple(jax.eval_shape(controls, jax.ShapeDtypeStruct((), jnp.result_type(float))).shape)
        if shape != (system.n_controls,):
            raise ValueError(
                f"'controls' gives values of shape {shape} at a time, expected ({system.n_controls},) "
                f"for {type(system).__name__}; controls with a batch axis go through jax.vmap"
            )
    d = system.n_config
    q0 = check_array("q0", q0, (d,), f"for {type(system).__name__}")
    qdot0 = check_array("qdot0", qdot0, (d,), f"for {type(system).__name__}")
    if q0.dtype != qdot0.dtype:  # the run's common dtype, in which the checks must also be made
        dtype = jnp.result_type(q0, qdot0)
        q0, qdot0 = as_dtype(q0, dtype), as_dtype(qdot0, dtype)
    if jnp.result_type(q0, qdot0) == jnp.float32 and not jax.config.jax_enable_x64:
        warnings.warn(
            f"ldap_jax.{caller} runs in float32 because jax_enable_x64 is off; enable float64 "
            '(jax.config.update("jax_enable_x64", True)) for its accuracy',
            stacklevel=3,
        )
    return controls, q0, qdot0


def simulate(
    system: AbstractSystem,
    q0: ArrayOrSequence,
    qdot0: ArrayOrSequence,
    controls: AbstractControls | AbstractPolicy | Callable | None = None,
    *,
    t_final: ArrayLike,
    n_steps: int,
    integrator: AbstractIntegrator | None = None,
    t0: ArrayLike = 0.0,
    save: str | int | Any = "all",
    diagnostics: bool = True,
    checkpoint: bool | str | int = False,
    divergence: float | None = 100.0,
    throw: bool = False,
    check_constraints: bool = True,
) -> Trajectory:
    """Integrate ``system`` from ``(q0, qdot0)`` over ``[t0, t_final]`` in ``n_steps`` steps.

    One ``lax.scan`` over the integrator's pure ``step``, jit-compiled; vmap over ``q0``,
    ``qdot0``, ``controls`` (and the system's parameters) at the call site; differentiable in
    every floating input. The dtype follows ``q0``/``qdot0``; the system and controls are cast
    to it. Works the same eagerly, under ``jax.jit`` and under ``jax.vmap``: inputs whose
    values are known are checked at once (``ValueError`` naming the argument); inputs whose
    values are traced are checked in the run, and a bad one fails that trajectory alone with
    ``RESULTS.invalid_input`` (every node NaN).

    Args:
        system: e.g. :class:`~ldap_jax.Car` or :class:`~ldap_jax.Snakeboard`.
        q0: initial configuration ``(x, y, theta, r1, ...)`` (m, rad), shape (d,).
        qdot0: initial velocity (m/s, rad/s), shape (d,); must satisfy the constraints
            ``omega(q0) qdot0 = 0``. Entries of kinematic shape coordinates (the car's
            ``sigma_dot``) are taken from the controls at ``t0``.
        controls: open-loop controls with ``system.n_controls`` channels (e.g.
            :class:`~ldap_jax.Sinusoids`), a feedback policy (:class:`~ldap_jax.Policy`,
            ``u = pi(t, q, qdot)``; a plain function ``pi(t, q, qdot)`` is taken as
            ``lj.Policy(pi, system.n_controls)``), or ``None`` for none (zero forces and
            steering rates).
        t_final: end time (s), ``> t0``.
        n_steps: number of steps N (static: each new N compiles once). For compositions
            (``RDP(order=4 | 6 | 8)``) the number of composed steps.
        integrator: default ``RDP(alpha=0.5, retraction="exp")`` (order 2).
        t0: start time (s, default 0).
        save: which nodes to return: ``"all"`` (default; N + 1 nodes), ``"final"`` (the last node
            only), a stride ``k`` dividing N (nodes 0, k, 2k, ..., N), or a sequence of node
            indices. Memory during the run is O(saved nodes) for the first three. The saved nodes
            are always an axis of their own (M), so ``"final"`` gives M = 1: ``traj.q[-1]`` is the
            node (``traj.q[..., -1, :]`` under ``vmap``), the same for every ``save``.
        diagnostics: (default ``True``) compute energy, work, momentum and constraint residual
            (observing every node, needed for the work integral and the divergence test). ``False``
            observes the saved nodes only: the fastest positions-only run.
        checkpoint: memory policy for reverse mode: ``False`` (default, the fastest: the closed-form
            kernels store only each step's sin/cos values and failure masks and recompute the rest),
            ``True``/``"step"`` (``jax.checkpoint`` on the step: O(N) states), ``"sqrt"`` (nested,
            ~sqrt(N) checkpointed chunks: O(sqrt N) states for about one extra forward pass), or an
            integer chunk length.
        divergence: (default 100) fail with ``RESULTS.diverged`` once ``|E_k - E_0 - W_k|`` exceeds
            ``divergence * (|E_0| + min(int |<f, rdot>| dt, E_f))`` (the energy balance broken by
            orders of magnitude: a numerically unstable run); ``None`` (or ``inf``) disables it.
            ``E_f = 1/2 P^T M^-1 P`` is the energy that the forces' impulse (its range ``P`` over
            the run, from the controls' ``impulse_spread``; accumulated along the nodes for a
            policy) gives the system at rest at ``q0``: a scale set by the inputs, which a
            diverging run cannot inflate as it inflates its own absolute work. Checked at
            every node when ``diagnostics`` is on (with ``diagnostics=False`` only non-finite
            states are caught). Independently, a non-finite energy, work, momentum or
            constraint residual at any node fails the run with ``RESULTS.nonfinite``.
        throw: (default ``False``) raise (inside jit, via ``eqx.error_if``) if the integration
            failed, with the failure's message. Under ``jax.vmap`` it raises when any member failed
            and does not say which one (the check runs inside the batched program): run without
            ``throw`` and read ``jnp.nonzero(traj.failed)`` to find the members.
        check_constraints: check that ``qdot0`` satisfies the constraints (default ``True``:
            a ``ValueError`` eagerly, ``invalid_input`` on traced values). With ``False`` a
            ``qdot0`` off the constraints is the caller's responsibility: node 0 reports it as
            given, and each integrator reads only what its scheme takes from it (the momenta
            of its components, or their projection), so the runs differ from one another.

    Returns:
        :class:`Trajectory`.

    Failed runs and gradients: a loss that reads a failed run (its NaN nodes) gets NaN gradients
    with respect to every input of that run, whether it failed at its first step or later. To
    leave failed members out of a batched loss, mask their *outputs* with a double ``where``,
    ``q = jnp.where(traj.failed, 0.0, traj.q)`` (or :meth:`Trajectory.filled`), before the loss
    reads them: the failed members then contribute exact zeros, and the healthy members'
    gradients are those of the batch without them. One exception in reverse mode: a member
    whose failing step has non-finite partial derivatives itself (an overflow, ``nonfinite``,
    e.g. a control amplitude of 1e160) makes the gradient of a parameter the batch shares (the
    model's, a common gain) NaN even when masked, since JAX sums the members' contributions
    before any mask could act on them; its own inputs' gradients are NaN too. A ``singular``
    failure (finite partials) is masked exactly; ``jax.jacfwd`` is exact in both cases. Masking
    only the loss (``jnp.where(traj.failed, 0.0, loss(traj.q))``) is not enough: the loss's own
    derivative at the NaN nodes is NaN (``0 * NaN``), in any JAX program. In forward mode (``jax.jacfwd``,
    ``jax.hessian``, applied to a function that calls ``simulate`` directly or under ``jax.jit``
    inside them) the mask is linear: a loss linear in a failed node gets 0 from it (its value is
    NaN). A forward-mode transformation of an already jitted function that calls ``simulate``
    (``jax.jacfwd(jax.jit(f))``) is not supported: apply ``jax.jit`` outside it.
    ``jax.linearize`` is not supported either (it traces as ``jax.grad`` does, and the rollout's
    reverse-mode derivatives cannot be pushed forward): use ``jax.jvp`` or ``jax.jacfwd``. A
    gradient of a gradient (reverse over reverse) works for the closed-form steps and RK; through
    Newton's method (DLA, ``RDP(solver="newton")`` or ``dtau_order=None``, an ``lj.System``'s
    RDP) JAX cannot reverse its ``while_loop`` twice: use ``jax.hessian`` (forward over reverse).

    Raises:
        TypeError: a system, controls or integrator of the wrong type.
        ValueError: bad shapes or dtypes, ``n_steps < 1``, ``t_final <= t0``, non-finite initial
            state, a bad ``save``/``checkpoint``, or ``qdot0`` violating the constraints (checked
            now when the values are known; see above otherwise).

    Example:
        >>> sb = lj.Snakeboard(m=1.0, l=0.5, I=0.05, J=0.02)
        >>> ctl = lj.Sinusoids(amplitude=[[0.1], [0.02]], frequency=[[2.0], [2.0]], phase=[[0.0], [0.0]])
        >>> traj = lj.simulate(sb, jnp.zeros(5), jnp.zeros(5), ctl, t_final=5.0, n_steps=500)
        >>> traj.q.shape, bool(traj.failed)
        ((501, 5), False)
    """
    integrator = RDP() if integrator is None else integrator
    if not isinstance(integrator, AbstractIntegrator):
        raise TypeError(
            f"'integrator' must be an ldap_jax integrator (e.g. lj.RDP()), got {type(integrator)}"
        )
    controls, q0, qdot0 = check_problem(system, controls, q0, qdot0, policies=True, caller="simulate")
    if isinstance(controls, AbstractPolicy):
        _check_policy(controls, q0, qdot0)
        controls = _lift_closure(controls, q0, qdot0)
    n_steps = check_positive_int("n_steps", n_steps)
    t_final, t0 = check_scalar("t_final", t_final), check_scalar("t0", t0)
    plan = check_save(save, n_steps)
    checkpoint = check_checkpoint(checkpoint)
    if divergence is not None:
        divergence = check_positive_number("divergence", divergence, allow_inf=True)
    raise_if_concrete(system, integrator, q0, qdot0, controls, t0, t_final, check_constraints, n_steps)
    settings = dict(
        forward_mode=_forward_mode((system, integrator, q0, qdot0, controls, t0, t_final)),
        traced_parameters=_traced((system, integrator, t0, t_final)),
        n_steps=n_steps,
        plan=plan,
        diagnostics=bool(diagnostics),
        checkpoint=checkpoint,
        divergence=divergence,
        throw=bool(throw),
        check_constraints=bool(check_constraints),
    )
    # a long session that keeps asking for new programs (a new n_steps compiles anew) trims JAX's
    # caches before it exhausts the process's memory mappings (see lj.trim_compilation_cache)
    note_program(("simulate", program_key(system, q0, qdot0, controls, integrator), tuple(settings.items())))
    return _simulate(
        system,
        q0,
        qdot0,
        controls,
        jnp.asarray(t0),  # arrays, not Python floats: a new value must not recompile
        jnp.asarray(t_final),
        integrator,
        **settings,
    )


def _traced(tree: Any) -> bool:
    """True when a leaf of ``tree`` is traced (a value of the caller's ``jit``, ``grad`` or
    ``vmap``): only then can a derivative with respect to it be asked for."""
    return any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(tree))


def _forward_mode(tree: Any) -> bool:
    """True when an input is being differentiated in forward mode (``jax.jvp``, ``jax.jacfwd``,
    ``jax.hessian``: a JVP tracer somewhere in a leaf's stack of tracers). The failed nodes are then
    masked without the custom VJP, which has no forward mode. (A forward-mode transformation
    outside a ``jax.jit`` that holds the call is not seen, and fails with JAX's message.)"""
    for x in jax.tree_util.tree_leaves(tree):
        for _ in range(64):
            if not isinstance(x, jax.core.Tracer):
                break
            if type(x).__name__ == "JVPTracer":
                return True
            x = getattr(x, "primal", getattr(x, "val", None))
    return False


def _lift_closure(policy: AbstractPolicy, q0: Array, qdot0: Array) -> AbstractPolicy:
    """A :class:`Policy` of a plain function that closes over traced values (a gain captured under
    the caller's ``jit`` or ``grad``), with those values made leaves of the policy
    (``eqx.filter_closure_convert``): hidden in the closure, the entry points took the policy for
    a constant and checked or compiled it as one (``TracerBoolConversionError`` under ``jit``, a
    leaked tracer under ``grad``). Other policies are returned as they are (a converted policy
    is a new object at every call, so it would compile anew every call)."""
    if not isinstance(policy, Policy) or isinstance(policy.fn, eqx.Module):
        return policy
    t = jnp.zeros((), q0.dtype)
    converted = eqx.filter_closure_convert(policy.fn, t, q0, qdot0)
    if not any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(converted)):
        return policy
    return Policy(converted, policy.n_channels)


def _check_policy(policy: AbstractPolicy, q0: Array, qdot0: Array) -> None:
    """A feedback policy must map ``(t, q, qdot)`` to ``(n_channels,)`` (checked on shapes only)."""
    d = q0.shape[0]
    if isinstance(policy, LinearPolicy) and jnp.shape(policy.gain)[-1] != 2 * d:
        raise ValueError(
            f"'controls': the LinearPolicy gain must have 2 d = {2 * d} columns (x = (q, qdot)), "
            f"got shape {tuple(jnp.shape(policy.gain))}"
        )
    try:
        out = eqx.filter_eval_shape(
            lambda p, t, q, qd: p(t, q, qd), policy, jnp.zeros((), q0.dtype), q0, qdot0
        )
    except TypeError as err:  # e.g. a function of t alone
        raise TypeError(
            f"'controls': calling the policy as f(t, q, qdot) failed ({err}); for controls that "
            "depend on time alone use lj.Sampled, lj.Sinusoids or lj.Policy(lambda t, q, qdot: f(t), n)"
        ) from err
    if not hasattr(out, "shape") or tuple(out.shape) != (policy.n_channels,):
        raise ValueError(
            f"'controls': the policy must return an array of shape ({policy.n_channels},) (its n_channels), "
            f"got {getattr(out, 'shape', out)}"
        )


@jit
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
    plan,
    diagnostics,
    checkpoint,
    divergence,
    throw,
    check_constraints,
    forward_mode,
    traced_parameters,
):
    dtype = jnp.result_type(q0, qdot0)
    q0, qdot0 = jnp.asarray(q0, dtype), jnp.asarray(qdot0, dtype)
    system, controls, integrator = cast_floats((system, controls, integrator), dtype)
    t0, t_final = jnp.asarray(t0, dtype), jnp.asarray(t_final, dtype)
    h = (t_final - t0) / n_steps
    c0 = controls(t0, q0, qdot0) if isinstance(controls, AbstractPolicy) else controls(t0)
    qdot0 = system.consistent_qdot(q0, qdot0, c0)
    initial = input_result(system, integrator, q0, qdot0, t0, t_final, check_constraints, controls, n_steps)
    out = rollout(
        system,
        integrator,
        q0,
        qdot0,
        controls,
        t0,
        h,
        n_steps,
        plan=plan,
        diagnostics=diagnostics,
        checkpoint=checkpoint,
        divergence=divergence,
        initial_result=initial,
        forward_mode=forward_mode,
        traced_parameters=traced_parameters,
    )
    obs = out.obs
    traj = Trajectory(
        t=out.t,
        q=obs.q,
        qdot=obs.qdot,
        energy=obs.energy if diagnostics else None,
        work=out.work if diagnostics else None,
        momentum=obs.momentum if diagnostics else None,
        constraint_residual=obs.constraint_residual if diagnostics else None,
        step_residual=out.step_residual if diagnostics else None,
        converged=out.converged,
        result=out.result,
        failure_index=out.failure_index,
    )
    if throw:
        traj = out.result.error_if(traj, out.result != RESULTS.successful)
    return traj
