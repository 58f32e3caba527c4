"""Optimal control tasks for the car and the snakeboard, and their replay on the reference.

A :class:`Task` is a system, an initial state, a horizon and a control parameterization, with

* an *objective*: a tuple of cost terms (:mod:`._costs`, e.g. the control effort), and
* *constraints*: a terminal pose (``goal``), the system at rest at ``t_N`` (``rest``) and bounds
  on the configuration and the controls at the nodes.

:func:`~ldap_jax.control.solve` treats the constraints as hard (equalities and inequalities of
an interior-point method); :func:`~ldap_jax.control.optimize` minimises the penalty form
:meth:`Task.loss`, the objective plus quadratic penalties of the constraints weighted by
:class:`Penalty`. The dynamics model is the task's integrator (``lj.RDP()`` by default).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, PRNGKeyArray

from .._reference import reference
from .._rollout import check_checkpoint
from .._simulate import Trajectory, simulate
from .._validation import check_positive_int
from ..integrators import RDP, AbstractIntegrator
from ..systems import AbstractSystem, Car, Snakeboard
from ._costs import AbstractTerm, BoundPenalty, Effort, Forward, Node, TerminalPose, TerminalRest, evaluate_terms
from ._costs import pose_error, wrap_angle
from ._parameterizations import AbstractParameterization, SampledControls, SinusoidGait

__all__ = ["Task", "Penalty", "parallel_park", "u_turn", "forward_gait", "reach", "TASKS", "replay", "gradient_memory"]

_INF = float("inf")


class Penalty(NamedTuple):
    """Weights of the penalty form (:meth:`Task.loss`): heading and position error at the goal,
    the rest condition, and the bounds."""

    heading: float = 100.0
    position: float = 100.0
    rest: float = 10.0
    bounds: float = 100.0


class Task(eqx.Module):
    """An optimal control problem through a differentiable rollout.

    Attributes:
        name: task name. system: the model. q0, qdot0: initial state (on the constraints).
        t_final: horizon (s). n_steps: steps of the rollout (static).
        parameterization: params -> controls. integrator: the dynamics model.
        objective: cost terms, summed (e.g. ``(Effort(scale),)``).
        goal: terminal pose ``(x, y, theta)`` or None. rest: indices of the minimal velocities
            held at zero at ``t_N`` (``TerminalRest``), or ``()``.
        q_lower, q_upper: bounds on ``q`` at the nodes (d,), infinite entries are off.
        c_lower, c_upper: bounds on the controls at the nodes (n_channels,), physical units.
        penalty: weights of the penalty form. objective_weight: the objective's weight there.
        guess: optional gait whose samples initialise sampled controls.
        checkpoint: the rollout's memory policy in reverse mode (as for :func:`~ldap_jax.simulate`).
    """

    name: str = eqx.field(static=True)
    system: AbstractSystem
    q0: Array
    qdot0: Array
    t_final: Array
    n_steps: int = eqx.field(static=True)
    parameterization: AbstractParameterization
    integrator: AbstractIntegrator
    objective: tuple[AbstractTerm, ...]
    goal: Array | None
    rest: tuple[int, ...] = eqx.field(static=True)
    q_lower: Array
    q_upper: Array
    c_lower: Array
    c_upper: Array
    penalty: Penalty
    objective_weight: Array
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
            divergence=None,
        )

    def constraint_terms(self) -> dict[str, AbstractTerm]:
        """The constraints as penalty terms (weights of :attr:`penalty`)."""
        terms = {}
        if self.goal is not None:
            terms["pose"] = TerminalPose(self.goal, self.penalty.heading, self.penalty.position)
        if self.rest:
            terms["rest"] = TerminalRest(self.rest, self.penalty.rest)
        terms["bounds"] = BoundPenalty(
            self.q_lower, self.q_upper, self.c_lower, self.c_upper, self.parameterization.scale, self.penalty.bounds
        )
        return terms

    def objective_terms(self) -> dict[str, AbstractTerm]:
        names = [type(t).__name__.lower() for t in self.objective]
        return {n if names.count(n) == 1 else f"{n}{i}": t for i, (n, t) in enumerate(zip(names, self.objective))}

    def terms(self, traj: Trajectory, params) -> dict[str, Array]:
        """Every term on a trajectory (objective terms scaled by ``objective_weight``)."""
        ctl = self.controls(params)
        c = jax.vmap(ctl)(traj.t)
        obs = Node(traj.q, traj.qdot)
        out = {k: self.objective_weight * v for k, v in evaluate_terms(self.objective_terms(), self.system, obs, c, self.h, self.q0).items()}
        out.update(evaluate_terms(self.constraint_terms(), self.system, obs, c, self.h, self.q0))
        return out

    def loss(self, params) -> tuple[Array, dict]:
        """The penalty form ``(J, terms)``: the weighted objective plus the constraint penalties."""
        terms = self.terms(self.rollout(params), params)
        return sum(terms.values()), terms

    def value(self, params) -> Array:
        """The scalar penalty-form loss."""
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

    def with_options(self, *, integrator=None, checkpoint=None, n_steps=None, goal=None, system=None) -> Task:
        """A copy with another integrator, checkpoint policy, number of steps, goal or system."""
        task = self
        if integrator is not None:
            task = eqx.tree_at(lambda t: t.integrator, task, integrator)
        if system is not None:
            task = eqx.tree_at(lambda t: t.system, task, system)
        if goal is not None:
            task = eqx.tree_at(lambda t: t.goal, task, jnp.asarray(goal, float), is_leaf=lambda x: x is None)
        if checkpoint is not None:
            task = dataclasses.replace(task, checkpoint=check_checkpoint(checkpoint))
        if n_steps is not None:
            task = dataclasses.replace(task, n_steps=check_positive_int("n_steps", n_steps))
            if isinstance(task.parameterization, SampledControls):
                task = dataclasses.replace(
                    task, parameterization=dataclasses.replace(task.parameterization, n_steps=int(n_steps))
                )
        return task


def make_task(
    name: str,
    system: AbstractSystem,
    q0,
    qdot0,
    t_final: float,
    n_steps: int,
    parameterization: AbstractParameterization,
    integrator: AbstractIntegrator | None,
    *,
    objective: tuple[AbstractTerm, ...],
    goal=None,
    rest: tuple[int, ...] = (),
    q_lower=None,
    q_upper=None,
    c_max=None,
    penalty: Penalty = Penalty(),
    objective_weight: float = 1.0,
    guess: SinusoidGait | None = None,
    checkpoint=False,
    init_amplitude: float = 0.3,
) -> Task:
    """Build a :class:`Task`, checking its pieces (the message names the argument)."""
    d, n = system.n_config, system.n_controls
    f = lambda x: jnp.asarray(x, float)  # noqa: E731
    q0, qdot0 = f(q0), f(qdot0)
    if q0.shape != (d,) or qdot0.shape != (d,):
        raise ValueError(f"'q0' and 'qdot0' must have shape ({d},), got {q0.shape}, {qdot0.shape}")
    viol = float(system.constraint_residual(q0, system.consistent_qdot(q0, qdot0, jnp.zeros(n))))
    if not viol < 1e-10:
        raise ValueError(f"'qdot0' violates the constraints of {type(system).__name__} ({viol:.2e})")
    n_steps = check_positive_int("n_steps", n_steps)
    if not float(t_final) > 0:
        raise ValueError(f"'t_final' must be positive, got {t_final}")
    q_lower = f(np.full(d, -_INF) if q_lower is None else q_lower)
    q_upper = f(np.full(d, _INF) if q_upper is None else q_upper)
    c_max = f(np.full(n, _INF) if c_max is None else c_max)
    if np.any(np.asarray(q_lower) >= np.asarray(q_upper)) or np.any(np.asarray(c_max) <= 0):
        raise ValueError(f"the bounds are empty: q_lower={q_lower}, q_upper={q_upper}, c_max={c_max}")
    if np.any(np.asarray(q0) < np.asarray(q_lower)) or np.any(np.asarray(q0) > np.asarray(q_upper)):
        raise ValueError(f"'q0' {q0} lies outside the bounds [{q_lower}, {q_upper}]")
    if goal is not None:
        goal = f(goal)
        if goal.shape != (3,):
            raise ValueError(f"'goal' must be a pose (x, y, theta), got shape {goal.shape}")
        g_q = np.concatenate([np.asarray(goal), np.full(d - 3, np.nan)])
        lo, hi = np.asarray(q_lower), np.asarray(q_upper)
        outside = (g_q < lo) | (g_q > hi)
        if np.any(outside[:3]):
            raise ValueError(f"'goal' {np.asarray(goal)} lies outside the bounds of (x, y, theta): [{lo[:3]}, {hi[:3]}]")
    return Task(
        name=name,
        system=system,
        q0=q0,
        qdot0=qdot0,
        t_final=f(t_final),
        n_steps=n_steps,
        parameterization=parameterization,
        integrator=integrator if integrator is not None else RDP(),
        objective=tuple(objective),
        goal=goal,
        rest=tuple(int(i) for i in rest),
        q_lower=q_lower,
        q_upper=q_upper,
        c_lower=-c_max,
        c_upper=c_max,
        penalty=penalty,
        objective_weight=f(objective_weight),
        guess=guess,
        checkpoint=check_checkpoint(checkpoint),
        init_amplitude=init_amplitude,
    )


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
    distance sideways) in ``t_final`` (s), minimising the effort; per-step controls (wheel torque
    in N m, steering rate in 1/s); ``|sigma| <= max_steer`` (``sigma = tan`` of the steering angle)."""
    car = system if system is not None else Car()
    l = float(car.l)
    scale = [float(car.I + car.m * car.rho**2), 0.5]
    return make_task(
        "parallel_park",
        car,
        np.zeros(5),
        np.zeros(5),
        t_final,
        n_steps,
        SampledControls(t_final, n_steps, scale),
        integrator,
        objective=(Effort(jnp.asarray(scale)),),
        objective_weight=1e-5,
        goal=[0.0, 0.5 * l, 0.0],
        rest=(0,),
        penalty=Penalty(heading=100.0, position=100.0 / l**2, rest=10.0, bounds=100.0),
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
    """Car U-turn in a lane of ``width`` (m): from rest at ``(0, -width/4, 0)`` to rest at
    ``(0, width/4, pi)`` with the rear axle inside ``|y| <= width/2`` and ``|sigma| <= max_steer``
    (minimum turning radius ``l / max_steer``: with the defaults a plain U-turn needs 1 m, so the
    car must back up), minimising the effort."""
    car = system if system is not None else Car()
    scale = [float(car.I + car.m * car.rho**2), 0.5]
    return make_task(
        "u_turn",
        car,
        [0.0, -width / 4, 0.0, 0.0, 0.0],
        np.zeros(5),
        t_final,
        n_steps,
        SampledControls(t_final, n_steps, scale),
        integrator,
        objective=(Effort(jnp.asarray(scale)),),
        objective_weight=1e-5,
        goal=[0.0, width / 4, np.pi],
        rest=(0,),
        penalty=Penalty(heading=100.0, position=100.0, rest=10.0, bounds=1000.0),
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
    """Snakeboard forward gait: from rest, the periodic gait (rotor and steering torques in N m,
    sums of ``n_terms`` sinusoids with free amplitudes, shared frequencies and phases) that
    maximises the displacement along the initial heading in ``t_final`` (s), with
    ``|f| <= max_torque`` and ``|phi| <= max_steer`` (rad; well away from ``cos(phi) = 0``)."""
    sb = system if system is not None else Snakeboard()
    return make_task(
        "forward_gait",
        sb,
        np.zeros(5),
        np.zeros(5),
        t_final,
        n_steps,
        SinusoidGait(list(max_torque), n_terms=n_terms, frequency=frequency),
        integrator,
        objective=(Forward(),),
        penalty=Penalty(bounds=1e4),
        init_amplitude=0.1,
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
    """Snakeboard reach: from rest at the origin to ``goal = (x, y, theta)`` (m, m, rad) with the
    board at rest (speed ``s = 0``), minimising the effort; per-step torques (N m) initialised from
    a gait, ``|f| <= max_torque``, ``|phi| <= max_steer``."""
    sb = system if system is not None else Snakeboard()
    return make_task(
        "reach",
        sb,
        np.zeros(5),
        np.zeros(5),
        t_final,
        n_steps,
        SampledControls(t_final, n_steps, list(max_torque)),
        integrator,
        objective=(Effort(jnp.asarray(max_torque, float)),),
        objective_weight=1e-5,
        goal=list(goal),
        rest=(2,),
        penalty=Penalty(heading=10.0, position=10.0, rest=10.0, bounds=100.0),
        q_lower=[-_INF, -_INF, -_INF, -_INF, -max_steer],
        q_upper=[_INF, _INF, _INF, _INF, max_steer],
        c_max=list(max_torque),
        guess=SinusoidGait(list(max_torque), n_terms=1, frequency=frequency),
        init_amplitude=0.9,
        checkpoint=checkpoint,
    )


TASKS = {
    ("car", "parallel_park"): parallel_park,
    ("car", "u_turn"): u_turn,
    ("snakeboard", "forward_gait"): forward_gait,
    ("snakeboard", "reach"): reach,
}


def replay(task: Task, params, *, rtol: float = 1e-11, atol: float = 1e-11) -> dict:
    """Replay the optimized controls on the high-accuracy reference (:func:`ldap_jax.reference`).

    Returns a dict with the reference configurations ``q_ref`` at the step times, the model's
    ``q_model``, the terminal errors against the goal when the task has one (else the model error
    at ``t_N``: ``final_position_error`` [m], ``final_heading_error`` [rad]), the model errors,
    the terminal speed of the reference (``final_speed_ref``, the norm of ``(xdot, ydot,
    thetadot)``), the largest bound violation at the nodes on the reference (``max_bound_violation``),
    every term (``terms_reference``) and the ``forward_displacement`` of the reference.
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
    c = np.asarray(jax.vmap(task.controls(params))(traj.t))
    lo, hi = np.asarray(task.q_lower), np.asarray(task.q_upper)
    viol_q = np.max(np.maximum(q_ref - hi, 0.0) + np.maximum(lo - q_ref, 0.0))
    viol_c = np.max(np.maximum(c - np.asarray(task.c_upper), 0.0) + np.maximum(np.asarray(task.c_lower) - c, 0.0))
    th0 = float(task.q0[2])
    forward = float((q_ref[-1, 0] - task.q0[0]) * np.cos(th0) + (q_ref[-1, 1] - task.q0[1]) * np.sin(th0))
    terms_ref = task.terms(Trajectory(
        t=traj.t, q=ref.q, qdot=ref.qdot, energy=None, work=None, momentum=None, constraint_residual=None,
        step_residual=None, converged=traj.converged, result=traj.result, failure_index=traj.failure_index,
    ), params)
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
        "terms_reference": {k: float(v) for k, v in terms_ref.items()},
        "forward_displacement": forward,
        "reference_result": int(ref.result._value),
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
