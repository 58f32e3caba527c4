"""Optimal control tasks for the car and the snakeboard, and their replay on the reference.

A :class:`Task` bundles a system, an initial state, a horizon, a control parameterization, an
integrator (the optimizer's dynamics model; RDP by default) and the weights of the loss

    J = w_heading e_1^2 + w_position (e_2^2 + e_3^2)             e = log(g_goal^-1 g_N)
        + w_stop |(xdot, ydot, thetadot)_N|^2                      come to rest
        + w_effort sum_k h |c_k / scale|^2                         control effort
        + w_bound (sum_k h (pen(q_k) + pen(c_k)))                  state and control bounds
        - w_forward <(x_N, y_N) - (x_0, y_0), (cos theta_0, sin theta_0)>   forward displacement

with ``pen`` the quadratic exterior penalty of :func:`bound_penalty`.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, PRNGKeyArray

from .._reference import reference
from .._scan import check_checkpoint
from .._simulate import Trajectory, simulate
from ..integrators import RDP, AbstractIntegrator
from ..systems import AbstractSystem, Car, Snakeboard
from ._costs import bound_penalty, effort_cost, pose_error, wrap_angle
from ._parameterizations import AbstractParameterization, SampledControls, SinusoidGait

__all__ = ["Task", "parallel_park", "u_turn", "forward_gait", "reach", "TASKS", "replay", "gradient_memory"]

_INF = float("inf")


class Task(eqx.Module):
    """An optimal control problem: ``loss(params)`` through a differentiable rollout.

    Attributes:
        name: task name. system: the model. q0, qdot0: initial state (on the constraints).
        t_final: horizon (s). n_steps: steps of the rollout (static).
        parameterization: params -> controls. integrator: the dynamics model (default RDP).
        goal: goal pose ``(x, y, theta)`` or None. weights: see the module docstring.
        q_lower, q_upper: bounds on ``q`` (5,), infinite entries are off.
        c_max: bound on ``|c|`` per channel (n_channels,), infinite entries are off.
        guess: optional gait whose samples initialise sampled controls.
        checkpoint: the rollout's memory policy in reverse mode, as for
            :func:`~ldap_jax.simulate` (``False``, ``True``/``"step"``, ``"sqrt"`` or a chunk length).
    """

    name: str = eqx.field(static=True)
    system: AbstractSystem
    q0: Array
    qdot0: Array
    t_final: Array
    n_steps: int = eqx.field(static=True)
    parameterization: AbstractParameterization
    integrator: AbstractIntegrator
    goal: Array | None
    w_heading: Array
    w_position: Array
    w_stop: Array
    w_effort: Array
    w_bound: Array
    w_forward: Array
    q_lower: Array
    q_upper: Array
    c_max: Array
    guess: SinusoidGait | None = None
    checkpoint: bool | str | int = eqx.field(static=True, default=False)
    init_amplitude: float = eqx.field(static=True, default=0.3)

    @property
    def h(self) -> Array:
        return self.t_final / self.n_steps

    def controls(self, params):
        return self.parameterization.controls(params)

    def rollout(self, params) -> Trajectory:
        """The optimizer's trajectory (``self.integrator``, ``n_steps`` steps)."""
        return simulate(
            self.system,
            self.q0,
            self.qdot0,
            self.controls(params),
            t_final=self.t_final,
            n_steps=self.n_steps,
            integrator=self.integrator,
            checkpoint=self.checkpoint,
            check_constraints=False,
        )

    def loss(self, params) -> tuple[Array, dict]:
        """``(J, terms)``: the scalar loss and its terms (see the module docstring)."""
        traj = self.rollout(params)
        ctl = self.controls(params)
        c = jax.vmap(ctl)(traj.t)  # control values at the nodes
        h = self.h
        q_n = traj.q[-1]
        scale = self.parameterization.scale
        terms = {}
        if self.goal is not None:
            e = pose_error(q_n, self.goal)
            terms["pose"] = self.w_heading * e[0] ** 2 + self.w_position * (e[1] ** 2 + e[2] ** 2)
        terms["stop"] = self.w_stop * jnp.sum(traj.qdot[-1, :3] ** 2)
        terms["effort"] = self.w_effort * effort_cost(c, h, scale)
        pen_q = jax.vmap(lambda q: bound_penalty(q, self.q_lower, self.q_upper))(traj.q)
        cmax = self.c_max / scale
        pen_c = jax.vmap(lambda v: bound_penalty(v / scale, -cmax, cmax))(c)
        terms["bounds"] = self.w_bound * h * (jnp.sum(pen_q) + jnp.sum(pen_c))
        th0 = self.q0[2]
        forward = (q_n[0] - self.q0[0]) * jnp.cos(th0) + (q_n[1] - self.q0[1]) * jnp.sin(th0)
        terms["forward"] = -self.w_forward * forward
        total = sum(terms.values())
        return total, terms

    def value(self, params) -> Array:
        """The scalar loss."""
        return self.loss(params)[0]

    def init(self, key: PRNGKeyArray | None = None, *, amplitude: float | None = None):
        """An initial guess (deterministic for ``key=None``, random otherwise; vmap over keys)."""
        p = self.parameterization
        amplitude = self.init_amplitude if amplitude is None else amplitude
        if self.guess is not None and isinstance(p, SampledControls):
            gp = self.guess.init(key, amplitude=amplitude)
            ts = p.t0 + (p.t_final - p.t0) * jnp.linspace(0.0, 1.0, p.n_steps + 1)
            return jax.vmap(self.guess.controls(gp))(ts) / p.scale[None, :]
        return p.init(key, amplitude=amplitude)

    def with_options(self, *, integrator=None, checkpoint=None, n_steps=None) -> Task:
        """A copy with another integrator, checkpoint policy (as for ``simulate``) or number of steps."""
        task = self
        if integrator is not None:
            task = eqx.tree_at(lambda t: t.integrator, task, integrator)
        if checkpoint is not None:
            task = dataclasses.replace(task, checkpoint=check_checkpoint(checkpoint))
        if n_steps is not None:
            task = dataclasses.replace(task, n_steps=int(n_steps))
            if isinstance(task.parameterization, SampledControls):
                task = dataclasses.replace(
                    task, parameterization=dataclasses.replace(task.parameterization, n_steps=int(n_steps))
                )
        return task


def _task(name, system, q0, qdot0, t_final, n_steps, parameterization, integrator, **kw) -> Task:
    d, n = system.n_config, system.n_controls
    q0, qdot0 = jnp.asarray(q0, float), jnp.asarray(qdot0, float)
    viol = float(system.constraint_residual(q0, system.consistent_qdot(q0, qdot0, jnp.zeros(n))))
    if not viol < 1e-10:
        raise ValueError(f"'qdot0' violates the constraints of {type(system).__name__} ({viol:.2e})")
    if isinstance(n_steps, bool) or not isinstance(n_steps, int) or n_steps < 1:
        raise ValueError(f"'n_steps' must be a positive integer, got {n_steps!r}")
    if not float(t_final) > 0:
        raise ValueError(f"'t_final' must be positive, got {t_final}")
    f = lambda x: jnp.asarray(x, float)  # noqa: E731
    return Task(
        name=name,
        system=system,
        q0=q0,
        qdot0=qdot0,
        t_final=f(t_final),
        n_steps=n_steps,
        parameterization=parameterization,
        integrator=integrator if integrator is not None else RDP(),
        goal=None if kw.get("goal") is None else f(kw["goal"]),
        w_heading=f(kw.get("w_heading", 0.0)),
        w_position=f(kw.get("w_position", 0.0)),
        w_stop=f(kw.get("w_stop", 0.0)),
        w_effort=f(kw.get("w_effort", 0.0)),
        w_bound=f(kw.get("w_bound", 0.0)),
        w_forward=f(kw.get("w_forward", 0.0)),
        q_lower=f(kw.get("q_lower", np.full(d, -_INF))),
        q_upper=f(kw.get("q_upper", np.full(d, _INF))),
        c_max=f(kw.get("c_max", np.full(n, _INF))),
        guess=kw.get("guess"),
        checkpoint=kw.get("checkpoint", False),
        init_amplitude=kw.get("init_amplitude", 0.3),
    )


def default_car() -> Car:
    return Car(m=1.0, I=0.1, K=0.2, rho=0.1, l=0.5)


def default_snakeboard() -> Snakeboard:
    return Snakeboard(m=1.0, l=0.5, I=0.05, J=0.02)


def parallel_park(
    system: Car | None = None,
    *,
    t_final: float = 10.0,
    n_steps: int = 100,
    integrator: AbstractIntegrator | None = None,
    checkpoint: bool | str | int = False,
    max_steer: float = 1.0,
) -> Task:
    """Car parallel parking: from rest at ``(0, 0, 0)`` to rest at ``(0, l/2, 0)`` (half the axle
    distance sideways) in ``t_final``; per-step controls; ``|sigma| <= max_steer``."""
    car = system if system is not None else default_car()
    l = float(car.l)
    z = np.zeros(5)
    inertia = float(car.I + car.m * car.rho**2)
    return _task(
        "parallel_park",
        car,
        z,
        z,
        t_final,
        n_steps,
        SampledControls(t_final, n_steps, [inertia, 0.5]),
        integrator,
        goal=[0.0, 0.5 * l, 0.0],
        w_heading=100.0,
        w_position=100.0 / l**2,
        w_stop=10.0,
        w_effort=1e-5,
        w_bound=100.0,
        q_lower=[-_INF, -_INF, -_INF, -_INF, -max_steer],
        q_upper=[_INF, _INF, _INF, _INF, max_steer],
        checkpoint=checkpoint,
    )


def u_turn(
    system: Car | None = None,
    *,
    t_final: float = 12.0,
    n_steps: int = 120,
    width: float = 1.0,
    integrator: AbstractIntegrator | None = None,
    checkpoint: bool | str | int = False,
    max_steer: float = 1.0,
) -> Task:
    """Car U-turn in a lane of ``width``: from rest at ``(0, -width/4, 0)`` to rest at
    ``(0, width/4, pi)`` with the rear axle inside ``|y| <= width/2`` and ``|sigma| <= max_steer``
    (minimum turning radius ``l / max_steer``: with the defaults a plain U-turn needs 1 m, so the
    car must back up)."""
    car = system if system is not None else default_car()
    inertia = float(car.I + car.m * car.rho**2)
    q0 = np.array([0.0, -width / 4, 0.0, 0.0, 0.0])
    return _task(
        "u_turn",
        car,
        q0,
        np.zeros(5),
        t_final,
        n_steps,
        SampledControls(t_final, n_steps, [inertia, 0.5]),
        integrator,
        goal=[0.0, width / 4, np.pi],
        w_heading=100.0,
        w_position=100.0,
        w_stop=10.0,
        w_effort=1e-5,
        w_bound=1000.0,
        init_amplitude=0.1,
        q_lower=[-_INF, -width / 2, -_INF, -_INF, -max_steer],
        q_upper=[_INF, width / 2, _INF, _INF, max_steer],
        checkpoint=checkpoint,
    )


def forward_gait(
    system: Snakeboard | None = None,
    *,
    t_final: float = 10.0,
    n_steps: int = 100,
    max_torque: tuple[float, float] = (0.1, 0.1),
    max_steer: float = 1.0,
    n_terms: int = 1,
    frequency: float = 2.0,
    integrator: AbstractIntegrator | None = None,
    checkpoint: bool | str | int = False,
) -> Task:
    """Snakeboard forward gait: from rest, the periodic gait (rotor and steering torques, sums of
    ``n_terms`` sinusoids with free amplitudes, shared frequencies and phases) that maximises the
    displacement along the initial heading in ``t_final``, with ``|f| <= max_torque`` and
    ``|phi| <= max_steer`` (well away from the singularity ``cos(phi) = 0``) as penalties."""
    sb = system if system is not None else default_snakeboard()
    z = np.zeros(5)
    return _task(
        "forward_gait",
        sb,
        z,
        z,
        t_final,
        n_steps,
        SinusoidGait(list(max_torque), n_terms=n_terms, frequency=frequency),
        integrator,
        w_forward=1.0,
        w_bound=1e4,
        init_amplitude=0.1,
        w_effort=0.0,
        q_lower=[-_INF, -_INF, -_INF, -_INF, -max_steer],
        q_upper=[_INF, _INF, _INF, _INF, max_steer],
        c_max=list(max_torque),
        checkpoint=checkpoint,
    )


def reach(
    system: Snakeboard | None = None,
    *,
    goal: tuple[float, float, float] = (2.0, 1.0, 0.5 * np.pi),
    t_final: float = 16.0,
    n_steps: int = 160,
    max_torque: tuple[float, float] = (0.1, 0.1),
    max_steer: float = 1.0,
    frequency: float = 2.0,
    integrator: AbstractIntegrator | None = None,
    checkpoint: bool | str | int = False,
) -> Task:
    """Snakeboard reach: from rest at the origin to ``goal = (x, y, theta)`` with the board at
    rest; per-step torques initialised from a gait, ``|f| <= max_torque``, ``|phi| <= max_steer``."""
    sb = system if system is not None else default_snakeboard()
    z = np.zeros(5)
    return _task(
        "reach",
        sb,
        z,
        z,
        t_final,
        n_steps,
        SampledControls(t_final, n_steps, list(max_torque)),
        integrator,
        goal=list(goal),
        w_heading=10.0,
        w_position=10.0,
        w_stop=10.0,
        w_effort=1e-5,
        w_bound=100.0,
        q_lower=[-_INF, -_INF, -_INF, -_INF, -max_steer],
        q_upper=[_INF, _INF, _INF, _INF, max_steer],
        c_max=list(max_torque),
        guess=SinusoidGait(list(max_torque), n_terms=1, frequency=frequency),
        checkpoint=checkpoint,
    )


TASKS = {
    ("car", "parallel_park"): parallel_park,
    ("car", "u_turn"): u_turn,
    ("snakeboard", "forward_gait"): forward_gait,
    ("snakeboard", "reach"): reach,
}


def replay(task: Task, params, *, rtol: float = 1e-10, atol: float = 1e-10) -> dict:
    """Replay the optimized controls on the high-accuracy reference (:func:`ldap_jax.reference`).

    Returns a dict with the reference configurations ``q_ref`` at the step times, the model's
    ``q_model``, and the terminal errors: against the goal (``final_position_error`` [m],
    ``final_heading_error`` [rad]) when the task has one, else the model error at ``t_N``
    (reference vs the optimizer's own rollout); ``model_position_error`` always; and
    ``forward_displacement`` of the reference.
    """
    traj = task.rollout(params)
    ref = reference(task.system, task.q0, task.qdot0, task.controls(params), traj.t, rtol=rtol, atol=atol)
    q_ref, q_mod = np.asarray(ref.q), np.asarray(traj.q)
    model_pos = float(np.linalg.norm(q_ref[-1, :2] - q_mod[-1, :2]))
    model_head = float(abs(wrap_angle(q_ref[-1, 2] - q_mod[-1, 2])))
    if task.goal is not None:
        goal = np.asarray(task.goal)
        pos = float(np.linalg.norm(q_ref[-1, :2] - goal[:2]))
        head = float(abs(wrap_angle(q_ref[-1, 2] - goal[2])))
        e = np.asarray(pose_error(q_ref[-1], goal))
    else:
        pos, head, e = model_pos, model_head, None
    th0 = float(task.q0[2])
    forward = float((q_ref[-1, 0] - task.q0[0]) * np.cos(th0) + (q_ref[-1, 1] - task.q0[1]) * np.sin(th0))
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
        "forward_displacement": forward,
        "reference_result": int(ref.result),
    }


def gradient_memory(task: Task, params) -> dict:
    """Memory of the compiled gradient of ``task.value`` (XLA's ``memory_analysis``), in bytes.

    ``temp`` is the scratch space (the residuals reverse mode stores: this is what
    ``checkpoint`` shrinks), ``peak`` = arguments + outputs + temporaries.
    """
    compiled = jax.jit(lambda p: jax.grad(task.value)(p)).lower(params).compile()
    ma = compiled.memory_analysis()
    temp = int(ma.temp_size_in_bytes)
    args = int(ma.argument_size_in_bytes)
    out = int(ma.output_size_in_bytes)
    return {"temp_bytes": temp, "argument_bytes": args, "output_bytes": out, "peak_bytes": temp + args + out}
