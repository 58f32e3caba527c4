"""The one rollout loop: any integrator on any system, every save policy, one failure rule.

:func:`rollout` drives ``integrator.step`` with ``lax.scan`` and reports nodes through
``integrator.observe``. :func:`ldap_jax.simulate`, the Monte Carlo study and the discrete-time
dynamics of the control module all run it; the closed-form car and snakeboard kernels plug in
through the integrator (their state is the kernel's), not through a loop of their own.

Per step ``k`` (node ``k`` to node ``k + 1``): read the controls at the integrator's fractions of
the step (or ask the feedback policy, with the state of node ``k``; an integrator that reads them
at the step's two ends only takes node ``k``'s from the carry and evaluates node ``k + 1``'s, when
the controls offer :meth:`~ldap_jax.AbstractControls.node_sampler`), step, observe node ``k + 1``
(configuration, velocity from the carried momenta, diagnostics), accumulate the work, apply the
failure rule (:func:`ldap_jax._results.first_failure`: the first failure wins, every later
node is NaN; the state is frozen where it must be, :func:`_advance`) and, with diagnostics on, the
divergence test on the energy balance.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from . import _tracing
from ._numerics import SAVED, materialise_result, saved
from ._results import RESULTS, first_failure
from .integrators import AbstractIntegrator
from .systems import AbstractSystem, Observation
from .systems._base import body_velocity

__all__ = ["rollout", "RolloutOutput", "check_checkpoint", "check_save", "SavePlan"]


# ----------------------------------------------------------------------------- options
def check_checkpoint(checkpoint: Any) -> bool | str | int:
    """Validate the ``checkpoint`` option of :func:`ldap_jax.simulate`."""
    if checkpoint in (False, None):
        return False
    if checkpoint is True or checkpoint == "step":
        return "step"
    if checkpoint == "sqrt":
        return "sqrt"
    if isinstance(checkpoint, (int, np.integer)) and not isinstance(checkpoint, bool) and checkpoint >= 1:
        return int(checkpoint)
    raise ValueError(
        f"'checkpoint' must be False, True/'step', 'sqrt' or a positive chunk length, got {checkpoint!r}"
    )


class SavePlan(NamedTuple):
    """Which nodes a rollout returns: every ``stride``-th node (``stride`` divides ``n_steps``),
    then, if ``indices`` is not None, only the nodes with those numbers (multiples of ``stride``)."""

    stride: int
    indices: tuple[int, ...] | None


def check_save(save: Any, n_steps: int) -> SavePlan:
    """Validate ``save`` (``"all"``, ``"final"``, a stride ``k`` or a sequence of node indices)."""
    if isinstance(save, str):
        if save == "all":
            return SavePlan(1, None)
        if save == "final":
            return SavePlan(n_steps, (n_steps,))
        raise ValueError(f"'save' must be 'all', 'final', a positive stride or node indices, got {save!r}")
    if isinstance(save, (int, np.integer)) and not isinstance(save, bool):
        if save < 1 or n_steps % save:
            raise ValueError(f"'save': a stride must be a positive divisor of n_steps={n_steps}, got {save}")
        return SavePlan(int(save), None)
    if isinstance(save, jax.core.Tracer):
        raise ValueError(
            "'save': node indices must be known when simulate is traced (a NumPy array, a list or a "
            "concrete JAX array; they fix the output's shape), got a traced array"
        )
    if isinstance(save, (Sequence, np.ndarray, jax.Array)) and not isinstance(save, (str, bytes)):
        items = list(save) if isinstance(save, Sequence) else [np.asarray(save)]
        if any(isinstance(i, (bool, np.bool_)) or np.asarray(i).dtype == np.bool_ for i in items):
            raise ValueError(f"'save': node indices must be integers (not a boolean mask), got {save!r}")
        try:
            values = np.asarray(save, dtype=float).ravel()
        except (TypeError, ValueError) as err:
            raise ValueError(f"'save': node indices must be integers, got {save!r}") from err
        if not np.all(np.isfinite(values)) or np.any(values != np.round(values)):
            raise ValueError(f"'save': node indices must be integers, got {save!r}")
        idx = [int(i) for i in values]
        if not idx or any(i < 0 or i > n_steps for i in idx) or any(b <= a for a, b in zip(idx, idx[1:])):
            raise ValueError(
                "'save': node indices must be strictly increasing integers in "
                f"[0, n_steps={n_steps}], got {save!r}"
            )
        return SavePlan(1, tuple(idx))
    raise ValueError(f"'save' must be 'all', 'final', a positive stride or node indices, got {save!r}")


# ----------------------------------------------------------------------------- the loop
class RolloutOutput(NamedTuple):
    """What :func:`rollout` returns; leading axis = saved nodes (M)."""

    t: Array
    obs: Observation  # fields (M, ...); energy etc. computed whether or not they are returned
    work: Array  # (M,)
    step_residual: Array  # (M,) largest relative step residual since the previous saved node
    converged: Array  # (M,) every implicit solve since the previous saved node converged
    iterations: Array  # (M,) Newton iterations since the previous saved node
    result: RESULTS
    failure_index: Array


class _Carry(NamedTuple):
    state: Any
    obs: Observation
    work: Array
    abs_work: Array
    impulse: Array  # (4, n_shape): the forces' impulse since t0, its lowest and highest values, f_k
    residual: Array
    converged: Array
    iterations: Array
    result: RESULTS
    failure_index: Array
    c_node: tuple[Array, ...] | None  # the controls at the node (the next step's start), when carried
    # with friction and the divergence test: the friction's work since t0 and its power at the node
    friction_work: Array | None = None
    friction_power: Array | None = None


def _friction_power(system: AbstractSystem, obs: Observation) -> Array:
    """The power of a system's friction forces at a node: ``<f_r, u> + <F, xi>`` (W, <= 0)."""
    u = obs.qdot[3:]
    xi = body_velocity(obs.q, obs.qdot)
    f_r, force = system.dissipative_forces(obs.q[3:], u, xi)
    return jnp.dot(f_r, u) + jnp.dot(force, xi)


def _where(mask, a, b):
    return jax.tree_util.tree_map(lambda x, y: jnp.where(mask, x, y), a, b)


def _stop_if(failed, tree):
    """``tree`` with its gradient cut where ``failed`` (a select: a NaN cotangent made inside a
    discarded step cannot leak through it, as it would through a multiplication by zero)."""
    return jax.tree_util.tree_map(
        lambda x: jnp.where(failed, jax.lax.stop_gradient(x), x) if eqx_inexact(x) else x, tree
    )


def _solves_equations(integrator: AbstractIntegrator, system: AbstractSystem) -> bool:
    """True when a step of ``integrator`` on ``system`` iterates (Newton's method): the general
    RDP step, DLA, or any integrator that declares itself ``implicit``."""
    from .integrators import RDP

    if isinstance(integrator, RDP):
        return not integrator.uses_kernel(system)
    return bool(integrator.implicit)


@jax.custom_jvp
def _advance(keep, new, old):
    """The next carried state of an explicit step: ``new`` as it is, whether the step failed or
    not. A failed state runs on, its later nodes NaN at the output, and no copy of the last good
    state is kept: keeping one cost a copy of the state and a select per field at every step
    (RDP2 1.16x, RDP6 1.2x the time of a run without).

    Differentiated (either mode) it is ``new`` where ``keep`` and ``old`` elsewhere: the state is
    frozen at its last good value, as an implicit step's always is, so that the discarded steps
    after a failure run on finite values, and their zero cotangents times their partials stay
    zero for every input the batch shares (a model's parameters, the step size), as
    :func:`failure_mask` promises."""
    return new


@_advance.defjvp
def _advance_jvp(primals, tangents):
    keep, new, old = primals
    _, d_new, d_old = tangents

    def pick(a, b):
        if jax.dtypes.result_type(a) == jax.dtypes.float0:
            return a
        return jnp.where(keep, a, b)

    return _where(keep, new, old), jax.tree_util.tree_map(pick, d_new, d_old)


def _run_on(keep, new, old):
    """The next carried state: ``new``, also after a failure (:func:`_advance` without its
    derivative rule)."""
    return new


def eqx_inexact(x) -> bool:
    return hasattr(x, "dtype") and jnp.issubdtype(x.dtype, jnp.inexact)


def failure_mask(values, ok, sink):
    """``values`` where ``ok`` (a per-node mask on each leaf's leading axis), NaN elsewhere: the
    nodes after a failure.

    Its derivative says what the NaN means. A cotangent at a failed node that is zero (the loss
    masked the failed run out with a double ``where``) passes as an exact zero, so it cannot
    poison a batch; a nonzero one (the loss reads the failed run, NaN included) makes the
    gradient with respect to every input of the run (``sink``: the system, controls, initial
    state, times and integrator) NaN, whether the run failed at its first step or later (a
    multiplication by a NaN mask only reached the inputs that the frozen state depended on: a
    failure at step 0 gave an exact 0 gradient for the controls). One call per leaf, so that a
    leaf the loss does not use keeps a symbolic zero cotangent and no derivative is formed for
    it (a dense zero times the infinite derivative of ``|v|`` at ``v = 0`` was NaN).
    """
    return jax.tree_util.tree_map(lambda x: _mask_leaf(x, ok, sink) if eqx_inexact(x) else x, values)


def failure_mask_linear(values, ok, sink):
    """:func:`failure_mask` for forward mode (``jax.jvp``, ``jax.jacfwd``, ``jax.hessian``), which
    a custom VJP does not support: the failed nodes are ``NaN + 0 * sum(sink)``. Its derivative is
    linear, so it cannot tell a masked node from a read one by the cotangent: a loss whose
    derivative at the NaN nodes is NaN (a square, a norm, a product) gets NaN for every input; a
    zero cotangent (a double ``where``) gives exact zeros; a loss linear in a failed node gets 0
    from it (its value is NaN)."""
    total = sum(jnp.sum(y) for y in sink) if sink else 0.0

    def one(x):
        if not eqx_inexact(x):
            return x
        fill = jnp.asarray(jnp.nan, x.dtype) + jnp.asarray(0.0, x.dtype) * total.astype(x.dtype)
        return jnp.where(_node_mask(ok, x), x, fill)

    return jax.tree_util.tree_map(one, values)


def _node_mask(ok, x):
    return ok.reshape(ok.shape + (1,) * (x.ndim - ok.ndim))


@jax.custom_vjp
def _mask_leaf(x, ok, sink):
    return jnp.where(_node_mask(ok, x), x, jnp.asarray(jnp.nan, x.dtype))


def _mask_leaf_fwd(x, ok, sink):
    return _mask_leaf(x, ok, sink), (ok, sink)


def _mask_leaf_bwd(res, ct):
    ok, sink = res
    m = _node_mask(ok, ct)
    # behind a barrier: a cotangent XLA knows to be zero (the nodes before the last, when a loss
    # reads only ``q[-1]``) made the reduction a constant that XLA folded at compile time, element
    # by element (2.5-4 s for B = N = 1000)
    read = jnp.any(jax.lax.optimization_barrier(~m & (ct != 0)))
    ct_sink = jax.tree_util.tree_map(
        lambda y: jnp.where(read, jnp.asarray(jnp.nan, y.dtype), jnp.zeros_like(y)), sink
    )
    return jnp.where(m, ct, jnp.zeros_like(ct)), None, ct_sink


_mask_leaf.defvjp(_mask_leaf_fwd, _mask_leaf_bwd)


def rollout(
    system: AbstractSystem,
    integrator: AbstractIntegrator,
    q0: Array,
    qdot0: Array,
    controls: Any,
    t0: Array,
    h: Array,
    n_steps: int,
    *,
    plan: SavePlan = SavePlan(1, None),
    diagnostics: bool = True,
    checkpoint: bool | str | int = False,
    divergence: float | None = 100.0,
    initial_result: RESULTS = RESULTS.successful,
    forward_mode: bool = False,
    traced_parameters: bool = True,
) -> RolloutOutput:
    """Integrate from ``(q0, qdot0)`` at ``t0`` with ``n_steps`` steps of size ``h``.

    Inputs are already validated and cast to one dtype (:func:`ldap_jax.simulate` does that);
    ``qdot0`` is consistent with the controls (kinematic entries). ``controls`` is an
    :class:`~ldap_jax.AbstractControls` (open loop) or an :class:`~ldap_jax.AbstractPolicy`
    (``u = pi(t, q_k, qdot_k)`` at the step's control times, with the state of the step's start).

    Args:
        plan: which nodes to return (:func:`check_save`).
        diagnostics: observe every node (energy, momentum, constraint residual, power, the
            work integral and the divergence test); with False only the saved nodes are observed.
        checkpoint: reverse-mode memory policy (:func:`check_checkpoint`).
        divergence: the run fails with ``RESULTS.diverged`` when the energy balance
            ``|E_k - E_0 - W_k|`` exceeds ``divergence * (|E_0| + int |P| dt)`` at an observed node
            (``None``: never). Needs ``diagnostics``.
        initial_result: a failure found in the inputs on traced values (the run then reports it
            with every node NaN).
        forward_mode: the caller differentiates in forward mode: the failed nodes are masked by
            :func:`failure_mask_linear` (a custom VJP has no forward mode).
        traced_parameters: the model's or the integrator's parameters or the times may be
            differentiated (a leaf is traced at the caller): a differentiated run then keeps a
            failed state frozen (:func:`_advance`). With all of them constant, only the state and
            the controls carry derivatives, and their cut at every step after a failure is a
            select, which no partial of the failed state can pass.
    """
    from ._controls import Sinusoids
    from ._policy import AbstractPolicy
    from .integrators import RDP

    if isinstance(integrator, RDP) and not forward_mode and integrator.uses_kernel(system):
        # reverse mode only: the closed-form step's hand-written VJP (the same values)
        integrator = dataclasses.replace(integrator, reverse_only=True)
    dtype = q0.dtype
    fractions = jnp.asarray(integrator.control_nodes, dtype)
    node_is_last = float(integrator.control_nodes[-1]) == 1.0
    policy = isinstance(controls, AbstractPolicy)
    sample_node = None
    if policy:
        sample_open = None
    else:
        # outside forward mode, the sinusoids' hand-written VJP (the same values)
        reverse_only = {"reverse_only": True} if isinstance(controls, Sinusoids) and not forward_mode else {}
        sample_open = controls.sampler(h, fractions, **reverse_only)
        if tuple(float(f) for f in integrator.control_nodes) == (0.0, 1.0) and integrator.order == 2:
            # the controls at the step's end carried into the next step (evaluated once per node).
            # The symmetric steps only: at alpha != 1/2 (order 1) the round-off of the carried
            # values took a float32 comparison of the car's kernel with its Newton step just past
            # its bound (tests/test_closed_form.py), and order 1 is not a step one runs for speed
            sample_node = controls.node_sampler()

    def node_time(k):
        return t0 + h * k.astype(dtype)

    def sample(k, obs):
        t = node_time(k)
        if policy:
            return jax.vmap(lambda tt: controls.sampled(tt, t, obs.q, obs.qdot))(t + h * fractions)
        return sample_open(t)

    def node_controls(k, c_stage):
        return c_stage[-1] if node_is_last else controls(node_time(k))

    def vector(columns):  # the carried controls (one scalar per channel, see step) as a vector
        return jnp.stack(columns) if columns else jnp.zeros((0,), dtype)

    c_first = controls(t0, q0, qdot0) if policy else controls(t0)
    k0 = jnp.zeros((), jnp.int32)
    if sample_node is None:
        c_node0 = None
        c_stage0 = sample(k0, Observation(q0, qdot0, *([None] * 4)))
    else:
        c_node0 = tuple(sample_node(node_time(k0)))
        c_stage0 = jnp.stack([vector(c_node0), sample_node(node_time(k0 + 1))])
    state0 = _tracing.init(integrator, system, h, q0, qdot0, c_stage0)
    obs0 = _tracing.observe(integrator, system, state0, c_first)
    obs0 = obs0._replace(qdot=qdot0)  # node 0 reports the given velocity
    energy_scale0 = jnp.abs(obs0.energy)
    zero = jnp.zeros((), dtype)
    check_divergence = diagnostics and divergence is not None
    # friction's work enters the energy balance of the divergence test (E - E0 = W + W_friction):
    # left out, the energy it dissipates grew past the test's bound in long healthy runs
    friction = check_divergence and system.has_friction
    n_s = system.n_shape
    impulse0 = jnp.zeros((4, n_s), dtype)
    static_forcing = None  # the forcing scale, when the controls know their impulse
    mobility = _mobility(system, q0) if check_divergence else None
    mobility = None if mobility is None else jnp.abs(jax.lax.stop_gradient(mobility))
    if mobility is not None:
        spread = None if policy else controls.impulse_spread(t0, t0 + h * n_steps)
        if spread is not None:
            spread = jnp.abs(system.inputs(jax.lax.stop_gradient(spread).astype(dtype))[0])
            static_forcing = 0.5 * spread @ mobility @ spread
        else:
            f0 = system.inputs(c_first)[0].astype(dtype)
            impulse0 = impulse0.at[3].set(f0)

    # after a failure the state is kept at its last good value where a later step cannot run on a
    # failed one: a policy (user code, evaluated on the state) and a step that iterates (Newton's
    # method on a NaN state would spend its whole budget, for every member of a batch); an
    # explicit step on open-loop controls keeps it only when differentiated with respect to a
    # parameter that its steps read directly (:func:`_advance`), else it runs on
    if policy or _solves_equations(integrator, system):
        advance = _where
    elif traced_parameters:
        advance = _advance
    else:
        advance = _run_on

    def step(carry: _Carry, k, observe: bool, emitted: bool = True):
        """Step k: node k -> node k + 1 (observed when ``observe``; ``emitted``: the observation
        is the node's output, else it serves the diagnostics' tests alone)."""
        # after a failure the steps run on the failed state (on the frozen one, see advance), and
        # their results are discarded: cut their gradient with a select, so that a non-finite
        # partial inside them (times the zero cotangent a discarded value gets) cannot reach the
        # inputs as a NaN
        failed_before = carry.result != RESULTS.successful
        if checkpoint is False:
            # kept as a mask for reverse mode (one byte per step and member, not the int32 code)
            (failed_before,) = saved(failed_before)
        state_in, obs_in = _stop_if(failed_before, (carry.state, carry.obs))
        if sample_node is None:
            c_stage = _stop_if(failed_before, sample(k, obs_in))
            c_next = None
        else:
            c_end = sample_node(node_time(k + 1))
            # carried channel by channel (carried as one vector, XLA stored it twice, in two
            # layouts: 3 kernels per step more)
            c_next = tuple(c_end)
            # the gradient cut on each scalar before they are stacked (a select on the stacked
            # (2, channels) array left its cotangent in a (B, 2, 2) layout that every sampler
            # term's backward kernel transposed again)
            c_stage = jnp.stack([vector(x) for x in _stop_if(failed_before, (carry.c_node, c_next))])
        new_state, info = _tracing.step(integrator, system, h, state_in, c_stage)
        step_result = info.result
        obs, work, abs_work, impulse = carry.obs, carry.work, carry.abs_work, carry.impulse
        friction_work, p_f = carry.friction_work, carry.friction_power
        if observe:
            if policy:
                obs_new = _tracing.observe(integrator, system, new_state, c_stage[-1])
                c_node = controls(t0 + h * (k + 1).astype(dtype), obs_new.q, obs_new.qdot)
                obs_new = obs_new._replace(power=system.power(system.inputs(c_node)[0], obs_new.qdot[3:]))
            else:
                c_node = node_controls(k + 1, c_stage)
                obs_new = _tracing.observe(integrator, system, new_state, c_node)
                if not emitted:
                    # a node inside a segment, observed for the tests alone: its derivative cut
                    # (the segment's last node is observed again from its state, with one).
                    # Carried with their derivatives, the node's velocity, energy and momentum
                    # were transposed at every step of a reverse pass, their cotangents zero
                    # unless the loss read the saved node's diagnostics (a terminal cost's gradient
                    # took 1.35-1.4x as long). The power keeps its derivative: the work integral,
                    # an output, sums it (unread, JAX drops it)
                    cut = jax.tree_util.tree_map(jax.lax.stop_gradient, obs_new._replace(power=None))
                    obs_new = cut._replace(power=obs_new.power)
            if diagnostics:
                work = carry.work + 0.5 * h * (carry.obs.power + obs_new.power)
                abs_work = carry.abs_work + 0.5 * jnp.abs(h) * (
                    jnp.abs(carry.obs.power) + jnp.abs(obs_new.power)
                )
                ok_diag = jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in obs_new]))
                step_result = RESULTS.where(
                    (step_result == RESULTS.successful) & ~ok_diag, RESULTS.nonfinite, step_result
                )
                if check_divergence:
                    lost = 0.0
                    if friction:
                        p_f = _friction_power(system, obs_new)
                        friction_work = carry.friction_work + 0.5 * h * (carry.friction_power + p_f)
                        lost = friction_work
                    balance = jnp.abs(obs_new.energy - obs0.energy - work - lost)
                    # the scale of the work: the absolute work so far, but no more than the
                    # energy the forces' impulse can give the system at rest at q0 (the absolute
                    # work of a diverging run grows with its divergence: the test never fired)
                    if mobility is None:  # a description without a full view: the absolute work
                        work_scale = abs_work
                    else:
                        if static_forcing is None:
                            impulse = _impulse(carry.impulse, system.inputs(c_node)[0].astype(dtype), h)
                            spread = impulse[2] - impulse[1]
                            forcing = 0.5 * spread @ mobility @ spread
                        else:
                            forcing = static_forcing
                        work_scale = jnp.fmin(abs_work, forcing)
                    bound = divergence * (energy_scale0 + work_scale) + jnp.finfo(dtype).tiny
                    step_result = RESULTS.where(
                        (step_result == RESULTS.successful) & (balance > bound), RESULTS.diverged, step_result
                    )
            obs = obs_new
        if observe and diagnostics:
            # computed once: XLA would otherwise fuse the node's diagnostics into every consumer
            # of the failure mask (the integrator's step gives its own code computed once)
            step_result = materialise_result(step_result)
        result, index, keep = first_failure(carry.result, carry.failure_index, step_result, k)
        if checkpoint is False:
            (keep,) = saved(keep)
        if light and observe:
            # node k + 1 is emitted as it is (NaN after a failure, as every later node); the
            # carry keeps its power alone, for the work's trapezoid (not 14 values per step)
            obs_carry = carry.obs._replace(power=jnp.where(keep, obs.power, carry.obs.power))
            emitted = obs
        else:
            obs_carry = emitted = _where(keep, obs, carry.obs)
        if friction:
            fric = dict(
                friction_work=jnp.where(keep, friction_work, carry.friction_work),
                friction_power=jnp.where(keep, p_f, carry.friction_power),
            )
        else:
            fric = {}
        new = _Carry(
            **fric,
            state=advance(keep, new_state, carry.state),
            obs=obs_carry,
            work=jnp.where(keep, work, carry.work),
            abs_work=jnp.where(keep, abs_work, carry.abs_work),
            impulse=jnp.where(keep, impulse, carry.impulse),
            # the failed step's residual is the last one counted (a failed state runs on)
            residual=jnp.where(failed_before, carry.residual, jnp.maximum(carry.residual, info.residual)),
            converged=carry.converged & (info.result != RESULTS.not_converged),
            iterations=carry.iterations + info.iterations,
            result=result,
            failure_index=index,
            c_node=c_next,
        )
        return new, emitted

    def emit(carry: _Carry, obs: Observation):
        # the nodes after a failure hold the frozen state (or the discarded one) here; _assemble
        # makes them NaN
        out = (obs, carry.work, carry.residual, carry.converged, carry.iterations)
        return carry._replace(
            residual=zero, converged=jnp.ones((), bool), iterations=jnp.zeros((), jnp.int32)
        ), out

    stride = plan.stride
    n_seg = n_steps // stride
    observe_inner = diagnostics or policy
    # every node emitted as it is observed, and the carry holds no observation but the power (a
    # policy reads the node's state at the next step, and a segment emits its carried last node)
    light = stride == 1 and not policy

    def inner_body(carry, k):
        return step(carry, k, observe_inner, emitted=policy)[0], None

    def segment(carry, j):
        if stride == 1:
            return emit(*step(carry, j, True))
        # every step of the segment in one scan body: the step is in the program once, as with
        # save="all" (a last step outside the scan was a second copy that XLA compiled again:
        # final-node and strided programs compiled 1.2-1.7x as long, their gradients too)
        last = j * stride + stride - 1
        ks = j * stride + jnp.arange(stride, dtype=jnp.int32)
        carry, _ = jax.lax.scan(_policy_body(inner_body, checkpoint), carry, ks)
        if not policy:  # the inner steps observed nothing, or for the tests alone: observe the last node
            if sample_node is None:
                c_last = node_controls(last + 1, sample(last, carry.obs))
            else:
                c_last = vector(carry.c_node)
            carry = carry._replace(obs=_tracing.observe(integrator, system, carry.state, c_last))
        return emit(carry, carry.obs)

    carry0 = _Carry(
        friction_work=zero if friction else None,
        friction_power=_friction_power(system, obs0) if friction else None,
        state=state0,
        obs=obs0,
        work=zero,
        abs_work=zero,
        impulse=impulse0,
        residual=zero,
        converged=jnp.ones((), bool),
        iterations=jnp.zeros((), jnp.int32),
        result=initial_result,
        failure_index=jnp.where(initial_result == RESULTS.successful, n_steps, 0).astype(jnp.int32),
        c_node=c_node0,
    )
    # every floating input of the run: a loss reading a failed node gets NaN gradients for all
    sink = jax.tree_util.tree_leaves((system, integrator, q0, qdot0, controls, t0, h))
    sink = ([x for x in sink if eqx_inexact(x)], forward_mode)
    seg_body = segment
    if checkpoint == "sqrt" or (isinstance(checkpoint, int) and not isinstance(checkpoint, bool)):
        if stride == 1:  # nested: chunks of ~sqrt(N) (or the given length) steps, each checkpointed
            last_q = functools.partial(_last_q, integrator, system, c=c_first)
            return _chunked(step, emit, carry0, n_steps, checkpoint, plan, t0, h, obs0, sink, last_q)
        seg_body = jax.checkpoint(segment)
    elif stride == 1:
        seg_body = _policy_body(segment, checkpoint)
    carry, outs = jax.lax.scan(seg_body, carry0, jnp.arange(n_seg, dtype=jnp.int32))
    return _assemble(
        carry, outs, obs0, plan, t0, h, n_steps, sink, _last_q(integrator, system, carry, c_first)
    )


def _last_q(integrator, system, carry, c):
    """The last node's configuration, read from the final carry's state (the same values as the
    last emitted node's: the configuration is a field or a stack of fields of the state; the
    controls ``c`` only shape the velocity, which is not read)."""
    return integrator.node(system, carry.state, c)[0]


def _mobility(system: AbstractSystem, q0: Array) -> Array | None:
    """``A`` with ``1/2 P^T A P`` the kinetic energy an impulse ``P`` of the shape forces gives the
    system at rest at ``q0`` (:meth:`~ldap_jax.systems.AbstractSystem.shape_mobility`: the
    constrained inverse mass matrix on the shape coordinates), or ``None`` for a description
    without a full view (the test then scales by the absolute work). The probe for the full view
    is the shape of ``C(r)`` alone (tracing the full equations' accelerations to find out took
    half of a simulate's tracing)."""
    try:  # a System description without a full view (no constraints given) has no such scale
        jax.eval_shape(system.body_constraints, q0[3:])
    except ValueError:
        return None
    return _tracing.shape_mobility(system, q0[3:])


def _impulse(prev: Array, f: Array, h: Array) -> Array:
    """The impulse record ``(P, min P, max P, f)`` after one more step (trapezoidal)."""
    p = prev[0] + 0.5 * h * (prev[3] + f)
    return jnp.stack([p, jnp.minimum(prev[1], p), jnp.maximum(prev[2], p), f])


def _policy_body(body, checkpoint):
    """The scan body under the memory policy (the segmented and chunked cases are handled apart)."""
    if checkpoint is False:
        return jax.checkpoint(body, policy=jax.checkpoint_policies.save_only_these_names(SAVED))
    if checkpoint == "step":
        return jax.checkpoint(body)
    return body


def _chunked(step, emit, carry0, n_steps, checkpoint, plan, t0, h, obs0, sink, last_q):
    """Save every node, ~sqrt(N) checkpointed chunks of ~sqrt(N) steps (or chunks of the given
    length): O(sqrt N) stored carries for about one extra forward pass."""
    k = max(1, math.isqrt(n_steps - 1) + 1) if checkpoint == "sqrt" else min(int(checkpoint), n_steps)
    n_chunks = -(-n_steps // k)
    valid_steps = np.arange(n_chunks * k) < n_steps

    def masked(carry, inp):
        kk, ok = inp
        new, out = emit(*step(carry, kk, True))
        return _where(ok, new, carry), out

    @jax.checkpoint
    def chunk(carry, inp):
        return jax.lax.scan(masked, carry, inp)

    ks = jnp.arange(n_chunks * k, dtype=jnp.int32).reshape(n_chunks, k)
    carry, outs = jax.lax.scan(chunk, carry0, (ks, jnp.asarray(valid_steps).reshape(n_chunks, k)))
    last_q = last_q(carry=carry)
    outs = jax.tree_util.tree_map(lambda o: o.reshape((n_chunks * k,) + o.shape[2:])[:n_steps], outs)
    return _assemble(carry, outs, obs0, plan, t0, h, n_steps, sink, last_q)


def _assemble(carry, outs, obs0, plan, t0, h, n_steps, sink, last_q) -> RolloutOutput:
    """Prepend node 0 to the scanned outputs and select the saved nodes.

    The last node's configuration is ``last_q``, read from the final carry (the same values as the
    last emitted node's), masked apart from the other nodes' and joined to them: a program that
    reads the last node alone (``traj.q[-1]``) then reads the carry, XLA drops the scan's stacked
    configurations, and the loop writes no ``(N + 1, d)`` buffer (about 1e4 first-touch page
    faults per call at B = N = 1000)."""
    dtype = obs0.q.dtype
    first = (obs0, jnp.zeros((), dtype), jnp.zeros((), dtype), jnp.ones((), bool), jnp.zeros((), jnp.int32))
    outs = jax.tree_util.tree_map(lambda x0, xs: jnp.concatenate([jnp.asarray(x0)[None], xs]), first, outs)
    nodes = np.arange(0, n_steps + 1, plan.stride)
    sink, forward_mode = sink
    mask = failure_mask_linear if forward_mode else failure_mask

    def ok_at(at):  # a node after the failing step (every node, for invalid inputs) is NaN
        ok = (carry.result == RESULTS.successful) | (jnp.asarray(at, jnp.int32) <= carry.failure_index)
        return ok & (carry.result != RESULTS.invalid_input)

    if plan.indices is None:
        q_all = outs[0].q
        obs, work = mask((outs[0]._replace(q=None), outs[1]), ok_at(nodes), sink)
        # the configurations but the last, masked, then the last (node 0 stays with the scanned
        # nodes: masked apart, its observation fused differently and changed by round-off)
        q = jnp.concatenate(
            [mask(q_all[:-1], ok_at(nodes[:-1]), sink), mask(last_q[None], ok_at(nodes[-1:]), sink)]
        )
        obs = obs._replace(q=q)
    else:
        sel = np.searchsorted(nodes, np.asarray(plan.indices))
        nodes = nodes[sel]
        outs = jax.tree_util.tree_map(lambda x: x[sel], outs)
        obs, work = mask((outs[0], outs[1]), ok_at(nodes), sink)
    _, _, residual, converged, iterations = outs
    # a node reports the steps since the previous saved one: NaN when they all came after the
    # failed step (they ran on a failed state, or a frozen one)
    residual = jnp.where(ok_at(nodes - plan.stride), residual, jnp.asarray(jnp.nan, residual.dtype))
    return RolloutOutput(
        t=t0 + h * jnp.asarray(nodes, dtype),
        obs=obs,
        work=work,
        step_residual=residual,
        converged=converged,
        iterations=iterations,
        result=carry.result,
        failure_index=carry.failure_index,
    )
