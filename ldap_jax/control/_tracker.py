"""Feedback that holds a gait: a periodic time-varying LQR on the cycle.

A gait's Floquet multipliers sit at 1 (:mod:`._gait_analysis`): executed open loop under any model
error, it drifts, and its displacement per cycle with it. :func:`gait_tracker` linearises the
task's discrete dynamics along the optimised cycle, in the gait's reduced state
``z = (r, v)`` (non-cyclic shape, minimal velocities; the group and the cyclic coordinates do not
enter the dynamics), with a control correction ``du`` held over each step::

    dz_{k+1} = A_k dz_k + B_k du_k,

and solves the periodic discrete Riccati equation by sweeping the backward recursion
``P_k = Q + A_k^T P_{k+1} (A_k - B_k K_k)``, ``K_k = (R + B_k^T P_{k+1} B_k)^-1 B_k^T P_{k+1} A_k``
over several periods until ``P_0`` repeats. The policy is
``u(t) = clip(u_ff(t) + K_k (z_ref(t_s) - z), u_lower, u_upper)`` with ``z`` the state taken at
``t_s`` (the start of the simulation step that contains ``t``), ``k`` the cycle's step containing
``t_s mod T`` and ``z_ref`` the cycle's reduced state between the nodes (the cubic Hermite
interpolant of the node states and their rates from the continuous equations).
"""

from __future__ import annotations

import inspect

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._compilation_cache import jit
from .._discrete import discretize
from .._policy import AbstractPolicy
from .._validation import check_positive_int, is_concrete
from . import _export
from ._gait_analysis import _configuration, _keep, gait_params, reduced_state
from ._task import Task

__all__ = ["GaitTracker", "gait_tracker"]


class GaitTracker(AbstractPolicy):
    """The periodic LQR policy of :func:`gait_tracker` (an ``lj`` policy: pass it as the controls
    of :func:`ldap_jax.simulate`).

    Attributes:
        feedforward: the gait's periodic controls.
        z_ref: the cycle's reduced state at the nodes, (N + 1, n_z).
        gains: the feedback gains of the steps, (N, n_channels, n_z).
        period: T (s). u_lower, u_upper: the saturation (the task's control bounds).
        keep: indices in ``q`` of the non-cyclic shape coordinates.
        z_rate: the time derivative of the cycle's reduced state at the start and at the end of
            each step, (N, 2, n_z), from the continuous equations with the step's controls (the
            reference between the nodes is their cubic Hermite interpolant); ``None``: linear
            interpolation.
    """

    feedforward: AbstractPolicy | object
    z_ref: Float[Array, "K nz"]
    gains: Float[Array, "N m nz"]
    period: Array
    u_lower: Array
    u_upper: Array
    system: object
    keep: tuple[int, ...] = eqx.field(static=True)
    z_rate: Float[Array, "N 2 nz"] | None = None

    @property
    def n_channels(self) -> int:
        return self.gains.shape[1]

    def __call__(self, t, q, qdot):
        return self.sampled(t, t, q, qdot)

    def sampled(self, t, t_state, q, qdot):
        """``clip(u_ff(t) + K_k (z_ref(t_state) - z), u_lower, u_upper)``, ``k`` the cycle's step
        that contains ``t_state mod T``: the state is compared with the cycle where it was taken
        (compared at ``t``, a run exactly on the cycle got a feedback of ``K_k (z_ref(t) -
        z_ref(t_state))`` inside every step and settled away from the cycle)."""
        n = self.gains.shape[0]
        s = t_state - self.period * jnp.floor(t_state / self.period)
        x = s / self.period * n
        k = jnp.clip(jnp.floor(x).astype(jnp.int32), 0, n - 1)
        w = x - k.astype(x.dtype)
        if self.z_rate is None:
            z_ref = (1 - w) * self.z_ref[k] + w * self.z_ref[k + 1]
        else:
            # cubic Hermite on the step: the cycle is smooth inside a step and kinked at its nodes
            # (the controls' slope changes there). Linear interpolation's error, read as a state
            # error, pushed a run on the cycle sampled between its nodes 7e-4 off it (drive gait,
            # h / 8); an interpolant through the neighbouring nodes, across the kinks, 5e-4
            h = self.period / n
            z_ref = (
                (2 * w**3 - 3 * w**2 + 1) * self.z_ref[k]
                + (w**3 - 2 * w**2 + w) * h * self.z_rate[k, 0]
                + (3 * w**2 - 2 * w**3) * self.z_ref[k + 1]
                + (w**3 - w**2) * h * self.z_rate[k, 1]
            )
        v = self.system.velocities_from_qdot(q, qdot)
        z = jnp.concatenate([q[jnp.asarray(self.keep, int)], v])
        u = self.feedforward(t) + self.gains[k] @ (z_ref - z)
        return jnp.clip(u, self.u_lower, self.u_upper)


def _linearised_steps(task: Task, params):
    """``(z_nodes, A, B)``: the cycle's reduced states and the Jacobians of each step's map."""
    dyn = discretize(task.system, task.integrator, h=task.h)
    controls = task.parameterization.values(params.controls)  # (N + 1, m) physical controls
    system = task.system

    def start(z, c):
        q, v = _configuration(task, z)
        return q, system.qdot_from_velocities(q, v, c)

    def step(z, du, k):
        c0, c1 = controls[k] + du, controls[k + 1] + du
        q, qdot = start(z, c0)
        x1 = dyn.step(dyn.init(q, qdot, c0), c0, c1, k)
        q1, qdot1 = dyn.node(x1, c1)
        return reduced_state(task, q1, qdot1)

    traj = task.rollout(params)
    z_nodes = jax.vmap(lambda q, qd: reduced_state(task, q, qd))(traj.q, traj.qdot)
    ks = jnp.arange(task.n_steps)
    m = controls.shape[1]
    A = jax.vmap(lambda z, k: jax.jacfwd(step, argnums=0)(z, jnp.zeros((m,), z.dtype), k))(z_nodes[:-1], ks)
    B = jax.vmap(lambda z, k: jax.jacfwd(step, argnums=1)(z, jnp.zeros((m,), z.dtype), k))(z_nodes[:-1], ks)
    return z_nodes, A, B


def periodic_lqr(A: Array, B: Array, Q: Array, R: Array, sweeps: int = 20) -> tuple[Array, Array]:
    """Gains ``K_k`` (N, m, n) and ``P_0`` of the periodic discrete Riccati equation, by ``sweeps``
    periods of the backward recursion from ``P_N = Q``."""

    def backward(P, AB):
        Ak, Bk = AB
        S = R + Bk.T @ P @ Bk
        K = jnp.linalg.solve(S, Bk.T @ P @ Ak)
        P_new = Q + Ak.T @ P @ (Ak - Bk @ K)
        return 0.5 * (P_new + P_new.T), K

    def sweep(P, _):
        P0, K = jax.lax.scan(backward, P, (A, B), reverse=True)
        return P0, K

    P0, Ks = jax.lax.scan(sweep, Q, None, length=sweeps)
    return Ks[-1], P0


def _tracker_of(task: Task, params, q_weight, r_weight, sweeps: int):
    z_nodes, A, B = _linearised_steps(task, params)
    nz = A.shape[1]
    scale = task.parameterization.scale
    Q = q_weight * jnp.eye(nz, dtype=A.dtype)
    R = r_weight * jnp.diag(1.0 / scale**2)
    K, _ = periodic_lqr(A, B, Q, R, sweeps)
    return z_nodes, K, _cycle_rates(task, params, z_nodes)


def _cycle_rates(task: Task, params, z_nodes: Array) -> Array:
    """``dz/dt`` of the cycle at the start and at the end of each step, (N, 2, n_z), from the
    continuous equations with the step's linearly interpolated controls (their slope is the
    step's: the prescribed shape velocities' derivative, where a system reads it)."""
    system = task.system
    keep = _keep(task)
    c = task.parameterization.values(params.controls)  # (N + 1, m)
    slope = (c[1:] - c[:-1]) / task.h
    takes_rate = "u_kin_dot" in inspect.signature(system.velocity_dynamics).parameters

    def rate(z, ck, dck):
        q, v = _configuration(task, z)
        f, u_kin = system.inputs(ck)
        qdot = system.qdot_from_velocities(q, v, u_kin)
        extra = (system.inputs(dck)[1],) if takes_rate else ()
        return jnp.concatenate([qdot[keep], system.velocity_dynamics(q, v, f, u_kin, *extra)])

    start = jax.vmap(rate)(z_nodes[:-1], c[:-1], slope)
    end = jax.vmap(rate)(z_nodes[1:], c[1:], slope)
    return jnp.stack([start, end], axis=1)


_tracker_traced = jit(_tracker_of)  # the library's compile options, as the exported program's


def _tracker(task: Task, params, q_weight, r_weight, sweeps: int):
    """``(reference reduced states, gains, the states' rates)``, through the program an earlier
    process exported when it can (as ``lc.solve``'s: no tracing in a new process)."""
    args = (task, params, q_weight, r_weight, sweeps)
    out = _export.call("gait_tracker", _tracker_of, args, lambda: (0, 0, 0))
    return _tracker_traced(*args) if out is NotImplemented else out


def gait_tracker(
    task: Task, solution, *, q_weight: float = 1.0, r_weight: float = 1e-3, sweeps: int = 20
) -> GaitTracker:
    """A periodic time-varying LQR that holds ``task``'s optimised gait against model error.

    Args:
        task: a periodic task (``lc.drive_gait()``, ...).
        solution: its :class:`~ldap_jax.control.Solution` (or the :class:`GaitParams` themselves).
        q_weight: weight of the reduced-state error (``Q = q_weight I``, natural units; default 1).
        r_weight: weight of the control correction (``R = r_weight diag(1 / scale^2)``: a
            correction of the controls' scale costs ``r_weight``; default 1e-3: with the drive gait
            under a 5 % mass error, 1e-2 kept the displacement per cycle within 4.5 % of nominal,
            1e-3 within 3.7 % (1.2 % in the tenth), the open loop 6.7 % off).
        sweeps: periods of the backward Riccati recursion (default 20).

    Returns:
        :class:`GaitTracker`, an ``lj`` policy over any number of cycles:
        ``lj.simulate(system, q0, qdot0, tracker, t_final=cycles * T, ...)``.

    Raises:
        TypeError, ValueError: a task that is not periodic, a ``solution`` that is not its
            :class:`~ldap_jax.control.Solution` or :class:`GaitParams`, weights that are not
            positive and finite, ``sweeps`` not a positive integer. A solution that did not
            converge gives a warning (its start is not a periodic orbit).
    """
    params = gait_params(task, solution, "gait_tracker")
    for name, w in (("q_weight", q_weight), ("r_weight", r_weight)):
        if isinstance(w, (str, bytes, bool)) or np.ndim(w) != 0:
            raise TypeError(f"'{name}' must be a positive number, got {w!r}")
        if is_concrete(w) and not (np.isfinite(float(w)) and float(w) > 0):
            raise ValueError(f"'{name}' must be positive and finite, got {float(w)}")
    sweeps = check_positive_int("sweeps", sweeps)
    # host values stay NumPy (an eager jnp.asarray is a program of its own in a new process)
    real = jnp.result_type(float)
    weights = [w if isinstance(w, jax.Array) else np.asarray(w, real) for w in (q_weight, r_weight)]
    z_nodes, K, rates = _tracker(task, params, *weights, sweeps)
    b = task.bounds
    return GaitTracker(
        feedforward=task.controls(params),
        z_ref=z_nodes,
        gains=K,
        period=jnp.asarray(task.t_final),
        u_lower=jnp.asarray(b.u_lower),
        u_upper=jnp.asarray(b.u_upper),
        system=task.system,
        keep=tuple(int(i) for i in np.asarray(_keep(task))),
        z_rate=rates,
    )
