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
import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, PRNGKeyArray

from .._compilation_cache import compiled_unless_staged, compiler_options
from .._reference import reference
from .._rollout import check_checkpoint
from .._simulate import Trajectory, simulate
from .._validation import check_array, check_positive_int, check_scalar, is_concrete, known_initial_violation
from ..integrators import RDP, AbstractIntegrator
from ..systems import AbstractSystem, Car, Snakeboard
from ._costs import (
    AbstractTerm,
    BoundPenalty,
    Effort,
    Forward,
    Node,
    TerminalPose,
    TerminalRest,
    evaluate_terms,
    pose_error,
)
from ._parameterizations import AbstractParameterization, SampledControls, SinusoidGait

__all__ = [
    "Task",
    "Penalty",
    "parallel_park",
    "u_turn",
    "forward_gait",
    "reach",
    "TASKS",
    "replay",
    "gradient_memory",
]

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
            self.q_lower,
            self.q_upper,
            self.c_lower,
            self.c_upper,
            self.parameterization.scale,
            self.penalty.bounds,
        )
        return terms

    def objective_terms(self) -> dict[str, AbstractTerm]:
        names = [type(t).__name__.lower() for t in self.objective]
        return {
            n if names.count(n) == 1 else f"{n}{i}": t for i, (n, t) in enumerate(zip(names, self.objective))
        }

    @compiled_unless_staged
    def terms(self, traj: Trajectory, params) -> dict[str, Array]:
        """Every term on a trajectory (objective terms scaled by ``objective_weight``)."""
        ctl = self.controls(params)
        c = jax.vmap(ctl)(traj.t)
        obs = Node(traj.q, traj.qdot)
        out = {
            k: self.objective_weight * v
            for k, v in evaluate_terms(self.objective_terms(), self.system, obs, c, self.h, self.q0).items()
        }
        out.update(evaluate_terms(self.constraint_terms(), self.system, obs, c, self.h, self.q0))
        return out

    @compiled_unless_staged
    def loss(self, params) -> tuple[Array, dict]:
        """The penalty form ``(J, terms)``: the weighted objective plus the constraint penalties.

        Called on values (or under a top-level ``jax.grad``) it runs as one compiled program,
        compiled once for all later values; inside your ``jax.jit`` it is traced inline."""
        terms = self.terms(self.rollout(params), params)
        return sum(terms.values()), terms

    def value(self, params) -> Array:
        """The scalar penalty-form loss."""
        return self.loss(params)[0]

    def init(self, key: PRNGKeyArray | None = None, *, amplitude: float | None = None):
        """An initial guess (deterministic for ``key=None``, random otherwise; vmap over keys)."""
        return _initial_guess(self, key, self.init_amplitude if amplitude is None else amplitude)

    def with_options(self, *, integrator=None, checkpoint=None, n_steps=None, goal=None, system=None) -> Task:
        """A copy with another integrator, checkpoint policy, number of steps, goal or system."""
        task = self
        if integrator is not None:
            if not isinstance(integrator, AbstractIntegrator):
                raise TypeError(
                    f"'integrator' must be an ldap_jax integrator (e.g. lj.RDP()), got {type(integrator)}"
                )
            task = eqx.tree_at(lambda t: t.integrator, task, integrator)
        if system is not None:
            if not isinstance(system, type(self.system)):
                raise TypeError(
                    f"'system' must be a {type(self.system).__name__} like the task's, got {type(system)}"
                )
            task = eqx.tree_at(lambda t: t.system, task, system)
        if goal is not None:
            goal = check_array("goal", goal, (3,), "(a pose x, y, theta)").astype(float)
            task = eqx.tree_at(lambda t: t.goal, task, goal, is_leaf=lambda x: x is None)
        if checkpoint is not None:
            task = dataclasses.replace(task, checkpoint=check_checkpoint(checkpoint))
        if n_steps is not None:
            task = dataclasses.replace(task, n_steps=check_positive_int("n_steps", n_steps))
            if isinstance(task.parameterization, SampledControls):
                task = dataclasses.replace(
                    task, parameterization=dataclasses.replace(task.parameterization, n_steps=int(n_steps))
                )
        return task


@eqx.filter_jit
def _initial_guess(task: Task, key: PRNGKeyArray | None, amplitude: float) -> Array:
    # one compiled program (op by op, a guess compiled some 15 small programs on a first call)
    p = task.parameterization
    if task.guess is not None and isinstance(p, SampledControls):
        gp = task.guess.init(key, amplitude=amplitude)
        ts = p.t0 + (p.t_final - p.t0) * jnp.linspace(0.0, 1.0, p.n_steps + 1)
        return jax.vmap(task.guess.controls(gp))(ts) / p.scale[None, :]
    return p.init(key, amplitude=amplitude)


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
    """Build a :class:`Task`, checking its pieces.

    Raises:
        TypeError: a piece of the wrong type (``system``, ``parameterization``, ``integrator``,
            ``objective``, ``penalty``, ``guess``, a non-numeric array); the message names it.
        ValueError: a bad shape or value (non-finite or out-of-bounds ``q0``, ``qdot0`` off the
            constraints, ``t_final <= 0``, empty bounds, a ``goal`` outside them, ``rest``
            indices out of range, negative weights, controls with the wrong number of
            channels); the message names the argument.
    """
    if not isinstance(name, str):
        raise TypeError(f"'name' must be a string, got {name!r}")
    if not isinstance(system, AbstractSystem):
        raise TypeError(f"'system' must be an ldap_jax system (e.g. lj.Car()), got {type(system)}")
    if not isinstance(parameterization, AbstractParameterization):
        raise TypeError(
            f"'parameterization' must be an lc parameterization (lc.SampledControls, lc.SinusoidGait), "
            f"got {type(parameterization)}"
        )
    if integrator is not None and not isinstance(integrator, AbstractIntegrator):
        raise TypeError(
            f"'integrator' must be an ldap_jax integrator (e.g. lj.RDP()) or None, got {type(integrator)}"
        )
    objective = tuple(objective) if isinstance(objective, (tuple, list)) else objective
    if not isinstance(objective, tuple) or not all(isinstance(t, AbstractTerm) for t in objective):
        raise TypeError(
            f"'objective' must be a tuple of cost terms (e.g. (lc.Effort(scale),)), got {objective!r}"
        )
    if not isinstance(penalty, Penalty):
        raise TypeError(f"'penalty' must be an lc.Penalty, got {type(penalty)}")
    if guess is not None and not isinstance(guess, SinusoidGait):
        raise TypeError(f"'guess' must be an lc.SinusoidGait or None, got {type(guess)}")
    d, n = system.n_config, system.n_controls
    f = lambda x: jnp.asarray(x, float)  # noqa: E731
    context = f"for {type(system).__name__}"
    q0 = check_array("q0", q0, (d,), context).astype(float)
    qdot0 = check_array("qdot0", qdot0, (d,), context).astype(float)
    n_steps = check_positive_int("n_steps", n_steps)
    t_final = f(check_scalar("t_final", t_final))
    scale = getattr(parameterization, "scale", None)
    if scale is not None and jnp.shape(scale)[-1:] != (n,):
        raise ValueError(
            f"'parameterization' has {jnp.shape(scale)[-1] if jnp.ndim(scale) else 0} channels (its scale), "
            f"{type(system).__name__} takes {n} {system.control_names}"
        )
    q_lower = check_array("q_lower", np.full(d, -_INF) if q_lower is None else q_lower, (d,), context).astype(
        float
    )
    q_upper = check_array("q_upper", np.full(d, _INF) if q_upper is None else q_upper, (d,), context).astype(
        float
    )
    c_max = check_array("c_max", np.full(n, _INF) if c_max is None else c_max, (n,), context).astype(float)
    if goal is not None:
        goal = check_array("goal", goal, (3,), "(a pose x, y, theta)").astype(float)
    if isinstance(rest, (int, np.integer)) or not all(
        isinstance(i, (int, np.integer)) and not isinstance(i, bool) for i in tuple(rest)
    ):
        raise TypeError(f"'rest' must be a tuple of integer indices of the minimal velocities, got {rest!r}")
    rest = tuple(int(i) for i in rest)
    if any(not 0 <= i < system.n_velocities for i in rest):
        raise ValueError(
            f"'rest' indices must lie in [0, {system.n_velocities}) (the minimal velocities of "
            f"{type(system).__name__}), got {rest}"
        )
    objective_weight = f(check_scalar("objective_weight", objective_weight))
    checkpoint = check_checkpoint(checkpoint)
    if isinstance(init_amplitude, bool) or not isinstance(init_amplitude, (int, float)):
        raise TypeError(f"'init_amplitude' must be a number, got {init_amplitude!r}")
    if not (np.isfinite(init_amplitude) and init_amplitude > 0):
        raise ValueError(f"'init_amplitude' must be positive and finite, got {init_amplitude!r}")
    # value checks, where the values are known (a task built inside jit skips them)
    with jax.ensure_compile_time_eval():
        if is_concrete((q0, qdot0)):
            for name_, x in (("q0", q0), ("qdot0", qdot0)):
                if not np.all(np.isfinite(np.asarray(x))):
                    raise ValueError(f"'{name_}' must be finite, got {np.asarray(x)}")
        if is_concrete(t_final) and not (np.isfinite(float(t_final)) and float(t_final) > 0):
            raise ValueError(f"'t_final' must be positive and finite, got {float(t_final)}")
        if isinstance(parameterization, SampledControls) and is_concrete(parameterization.t_final):
            if parameterization.n_steps != n_steps:
                raise ValueError(
                    f"'parameterization' samples {parameterization.n_steps} steps but 'n_steps' is {n_steps}"
                )
            if is_concrete(t_final) and not np.isclose(float(parameterization.t_final), float(t_final)):
                raise ValueError(
                    f"'parameterization' spans t_final={float(parameterization.t_final)} but 't_final' is "
                    f"{float(t_final)}"
                )
    if is_concrete((system, q0, qdot0)):
        viol = known_initial_violation(system, q0, qdot0, None, 0.0)[1]
        if not viol < 1e-10:
            raise ValueError(f"'qdot0' violates the constraints of {type(system).__name__} ({viol:.2e})")
    lo, hi, cm = np.asarray(q_lower), np.asarray(q_upper), np.asarray(c_max)
    if np.any(np.isnan(lo)) or np.any(np.isnan(hi)) or np.any(lo >= hi):
        raise ValueError(f"'q_lower' must lie below 'q_upper' (no NaN), got q_lower={lo}, q_upper={hi}")
    if np.any(~(cm > 0)):
        raise ValueError(f"'c_max' must be positive (inf: no bound), got {cm}")
    if is_concrete(q0) and (np.any(np.asarray(q0) < lo) or np.any(np.asarray(q0) > hi)):
        raise ValueError(f"'q0' {np.asarray(q0)} lies outside the bounds [{lo}, {hi}]")
    if goal is not None and is_concrete(goal):
        g = np.asarray(goal)
        if not np.all(np.isfinite(g)):
            raise ValueError(f"'goal' must be finite, got {g}")
        if np.any((g < lo[:3]) | (g > hi[:3])):
            raise ValueError(f"'goal' {g} lies outside the bounds of (x, y, theta): [{lo[:3]}, {hi[:3]}]")
    weights = np.asarray(tuple(penalty), float)
    if not np.all(np.isfinite(weights) & (weights >= 0)):
        raise ValueError(f"'penalty' weights must be non-negative and finite, got {penalty}")
    if is_concrete(objective_weight) and not (
        np.isfinite(float(objective_weight)) and float(objective_weight) >= 0
    ):
        raise ValueError(f"'objective_weight' must be non-negative and finite, got {float(objective_weight)}")
    return Task(
        name=name,
        system=system,
        q0=q0,
        qdot0=qdot0,
        t_final=t_final,
        n_steps=n_steps,
        parameterization=parameterization,
        integrator=integrator if integrator is not None else RDP(),
        objective=objective,
        goal=goal,
        rest=rest,
        q_lower=q_lower,
        q_upper=q_upper,
        c_lower=-c_max,
        c_upper=c_max,
        penalty=penalty,
        objective_weight=objective_weight,
        guess=guess,
        checkpoint=checkpoint,
        init_amplitude=init_amplitude,
    )


def _car_to_rest(
    name, car, *, q0, goal, y_bound, penalty, t_final, n_steps, integrator, max_steer, checkpoint, **kw
):
    """The car tasks: from rest at ``q0`` to rest at the pose ``goal``, least effort (wheel torque
    scaled by the wheel's inertia, steering rate by 0.5 1/s), ``|y| <= y_bound`` and
    ``|sigma| <= max_steer`` at the nodes."""
    scale = [float(car.I + car.m * car.rho**2), 0.5]
    return make_task(
        name,
        car,
        q0,
        np.zeros(5),
        t_final,
        n_steps,
        SampledControls(t_final, n_steps, np.asarray(scale, float)),
        integrator,
        objective=(Effort(jnp.asarray(scale)),),
        objective_weight=1e-5,
        goal=goal,
        rest=(0,),
        penalty=penalty,
        q_lower=[-_INF, -y_bound, -_INF, -_INF, -max_steer],
        q_upper=[_INF, y_bound, _INF, _INF, max_steer],
        checkpoint=checkpoint,
        **kw,
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
    return _car_to_rest(
        "parallel_park",
        car,
        q0=np.zeros(5),
        goal=[0.0, 0.5 * l, 0.0],
        y_bound=_INF,
        penalty=Penalty(heading=100.0, position=100.0 / l**2, rest=10.0, bounds=100.0),
        t_final=t_final,
        n_steps=n_steps,
        integrator=integrator,
        max_steer=max_steer,
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
    return _car_to_rest(
        "u_turn",
        car,
        q0=[0.0, -width / 4, 0.0, 0.0, 0.0],
        goal=[0.0, width / 4, np.pi],
        y_bound=width / 2,
        penalty=Penalty(heading=100.0, position=100.0, rest=10.0, bounds=1000.0),
        t_final=t_final,
        n_steps=n_steps,
        integrator=integrator,
        max_steer=max_steer,
        checkpoint=checkpoint,
        init_amplitude=0.1,
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
        SinusoidGait(np.asarray(max_torque, float), n_terms=n_terms, frequency=frequency),
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
        SampledControls(t_final, n_steps, np.asarray(max_torque, float)),
        integrator,
        objective=(Effort(jnp.asarray(max_torque, float)),),
        objective_weight=1e-5,
        goal=list(goal),
        rest=(2,),
        penalty=Penalty(heading=10.0, position=10.0, rest=10.0, bounds=100.0),
        q_lower=[-_INF, -_INF, -_INF, -_INF, -max_steer],
        q_upper=[_INF, _INF, _INF, _INF, max_steer],
        c_max=list(max_torque),
        guess=SinusoidGait(np.asarray(max_torque, float), n_terms=1, frequency=frequency),
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
    lo, hi = np.asarray(task.q_lower), np.asarray(task.q_upper)
    viol_q = np.max(np.maximum(q_ref - hi, 0.0) + np.maximum(lo - q_ref, 0.0))
    viol_c = np.max(
        np.maximum(c - np.asarray(task.c_upper), 0.0) + np.maximum(np.asarray(task.c_lower) - c, 0.0)
    )
    x0, y0, th0 = np.asarray(task.q0)[:3]
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
        "terms_reference": {k: float(v) for k, v in terms_ref.items()},
        "forward_displacement": forward,
        "reference_result": int(ref.result._value),
    }


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
