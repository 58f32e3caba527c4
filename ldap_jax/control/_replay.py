"""Replays of optimised controls on the high-accuracy reference (:func:`ldap_jax.reference`)."""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import numpy as np

from .._compilation_cache import compiler_options
from .._reference import reference
from .._simulate import Trajectory
from ._solve import checked_params
from ._task import Task
from ._terms import pose_error

__all__ = ["replay", "gradient_memory"]


def replay(task: Task, params, *, rtol: float | None = None, atol: float | None = None) -> dict:
    """Replay the optimized controls on the high-accuracy reference (:func:`ldap_jax.reference`,
    at tolerances ``rtol`` and ``atol``, default ``None``: the reference's, 1e-11 each in float64).

    Returns a dict with the reference configurations ``q_ref`` at the step times, the model's
    ``q_model``, the terminal errors against the goal when the task has one (else the model error
    at ``t_N``: ``final_position_error`` [m], ``final_heading_error`` [rad]), the model errors,
    the terminal speed of the reference (``final_speed_ref``, the norm of ``(xdot, ydot,
    thetadot)``), the largest bound violation at the nodes on the reference (``max_bound_violation``)
    and between them (``max_bound_violation_between``: the configuration bounds at three points
    inside every step; the optimiser holds the bounds at the nodes only, and a coordinate on a
    bound at a node leaves it by ``O(h^2)`` in between when force-driven, the drive gait's steering
    angle 2.6e-4 rad at N = 100, and by ``O(h)`` when its rate is a control, as the car's
    ``sigma``), every term (``terms_reference``), the ``forward_displacement`` of the reference
    and its result (``reference_result``, an :data:`ldap_jax.RESULTS` item).

    ``params`` are one solution's (``lc.solve(task).params``; the
    :class:`~ldap_jax.control.Solution` itself counts as its ``params``, with a warning when it
    did not converge); other values are a ``TypeError`` or ``ValueError`` naming them.
    """
    params = checked_params(task, params, "replay")
    traj = task.rollout(params)
    q0, qdot0 = task.initial_state(params)
    # the nodes and _BETWEEN points inside every step, from one reference solve
    t = np.asarray(traj.t)
    inside = t[:-1, None] + np.diff(t)[:, None] * np.arange(_BETWEEN + 1)[None, :] / (_BETWEEN + 1)
    ts = np.append(inside.ravel(), t[-1]).astype(t.dtype)
    dense = reference(task.system, q0, qdot0, task.controls(params), ts, rtol=rtol, atol=atol)
    ref = dataclasses.replace(dense, q=dense.q[:: _BETWEEN + 1], qdot=dense.qdot[:: _BETWEEN + 1])
    c, e, terms_ref = _replayed(task, params, traj, ref.q, ref.qdot)
    q_ref, q_mod, c = np.asarray(ref.q), np.asarray(traj.q), np.asarray(c)
    model_pos = float(np.linalg.norm(q_ref[-1, :2] - q_mod[-1, :2]))
    # host arithmetic in NumPy and math: each eager JAX operation compiled a program of its own
    model_head = abs(math.remainder(float(q_ref[-1, 2] - q_mod[-1, 2]), 2 * math.pi))
    if task.goal is not None:
        goal = np.asarray(task.goal)
        pos = float(np.linalg.norm(q_ref[-1, :2] - goal[:2]))
        head = abs(math.remainder(float(q_ref[-1, 2] - goal[2]), 2 * math.pi))
        e = np.asarray(e)
    else:
        pos, head = model_pos, model_head
    b = task.bounds
    lo, hi = np.asarray(b.q_lower), np.asarray(b.q_upper)
    viol_q = np.max(np.maximum(q_ref - hi, 0.0) + np.maximum(lo - q_ref, 0.0))
    viol_c = np.max(np.maximum(c - np.asarray(b.u_upper), 0.0) + np.maximum(np.asarray(b.u_lower) - c, 0.0))
    q_dense = np.asarray(dense.q)
    viol_between = np.max(np.maximum(q_dense - hi, 0.0) + np.maximum(lo - q_dense, 0.0))
    x0, y0, th0 = np.asarray(q0)[:3]
    forward = float((q_ref[-1, 0] - x0) * np.cos(th0) + (q_ref[-1, 1] - y0) * np.sin(th0))
    return {
        "q_ref": q_ref,
        "q_model": q_mod,
        "t": np.asarray(traj.t),
        "final_position_error": pos,
        "final_heading_error": head,
        "model_position_error": model_pos,
        "model_heading_error": model_head,
        "pose_error_log": None if e is None else e.tolist(),
        "final_speed_ref": float(np.linalg.norm(np.asarray(ref.qdot)[-1, :3])),
        "max_bound_violation": float(max(viol_q, viol_c)),
        "max_bound_violation_between": float(viol_between),
        "terms_reference": {k: float(v) for k, v in terms_ref.items()},
        "forward_displacement": forward,
        "reference_result": ref.result,
    }


#: Points inside every step at which :func:`replay` checks the configuration bounds.
_BETWEEN = 3


def gradient_memory(task: Task, params) -> dict:
    """Memory of the compiled gradient of ``task.value`` (XLA's ``memory_analysis``), in bytes.

    ``temp`` is the scratch space (the residuals reverse mode stores: this is what
    ``checkpoint`` shrinks), ``peak`` = arguments + outputs + temporaries.
    """
    compiled = (
        jax.jit(lambda p: jax.grad(task.value)(p), compiler_options=compiler_options())
        .lower(params)
        .compile()
    )
    ma = compiled.memory_analysis()
    temp = int(ma.temp_size_in_bytes)
    args = int(ma.argument_size_in_bytes)
    out = int(ma.output_size_in_bytes)
    return {"temp_bytes": temp, "argument_bytes": args, "output_bytes": out, "peak_bytes": temp + args + out}


@eqx.filter_jit
def _replayed(task: Task, params, traj: Trajectory, q_ref, qdot_ref):
    """What :func:`replay` reads off the reference, as one compiled program (op by op it compiled
    a hundred small ones): the control values at the step times, the goal's pose error (``None``
    without a goal) and every term of the task on the reference trajectory."""
    c = jax.vmap(task.controls(params))(traj.t)
    e = None if task.goal is None else pose_error(q_ref[-1], task.goal)
    # the reference's nodes in the model's trajectory, without the model's diagnostics
    diagnostics = dict.fromkeys(("energy", "work", "momentum", "constraint_residual", "step_residual"))
    on_ref = dataclasses.replace(traj, q=q_ref, qdot=qdot_ref, **diagnostics)
    return c, e, task.terms(on_ref, params)
