"""Built-in point-to-point tasks for the car and the snakeboard, written with the public pieces
(:func:`make_task`, the terms and constraints) a user would write them with.

Each task's dynamics model defaults to ``lj.RDP(order=4)``: with it, the optimised controls
replayed on the high-accuracy reference meet the goal to about 1e-7 m, the solver's own accuracy
(``lj.RDP()``, order 2, misses by millimetres at the same step).
"""

from __future__ import annotations

import numbers

import numpy as np

from ..integrators import AbstractIntegrator
from ..systems import Car, Snakeboard
from ._build import make_task
from ._constraints import Bounds, TerminalPose, TerminalRest, per_channel
from ._parameterizations import SampledControls, SinusoidGait
from ._task import Guess, Task
from ._terms import Effort, Forward


def model_of(system, cls: type, task: str):
    """A shipped task's model: ``cls()`` for ``None``, ``system`` when it is a ``cls``, else a
    ``TypeError`` naming ``system``."""
    if system is None:
        return cls()
    if not isinstance(system, cls):
        raise TypeError(f"{task}: 'system' must be an lj.{cls.__name__}, got {type(system).__name__}")
    return system


__all__ = ["parallel_park", "u_turn", "forward_gait", "reach", "car_effort_scale"]


def car_effort_scale(car: Car) -> np.ndarray:
    """The car tasks' control scales: the wheel torque by the wheel's inertia ``I + m rho^2``
    (N m), the steering rate by 0.5 (1/s)."""
    # on the host (NumPy): each eager JAX operation costs a compilation in a new process
    I, m, rho = (float(np.asarray(x)) for x in (car.I, car.m, car.rho))  # noqa: E741
    return np.asarray([I + m * rho**2, 0.5])


def _positive(where: str, name: str, x):
    """``x`` unchanged, or a ``ValueError`` naming ``name`` when it is a number that is not > 0
    (other values are left to :meth:`Bounds.of`, which names the bound)."""
    number = isinstance(x, numbers.Real) and not isinstance(x, bool)
    if number and not (float(x) > 0 and np.isfinite(float(x))):
        raise ValueError(f"{where}: '{name}' must be a positive finite number, got {x!r}")
    return x


def _car_to_rest(
    name, car, *, q0, goal, y_bound, weights, t_final, n_steps, integrator, max_steer, checkpoint, amplitude
):
    """The car tasks: from rest at ``q0`` to rest at the pose ``goal``, least effort,
    ``|y| <= y_bound`` and ``|sigma| <= max_steer`` at the nodes."""
    max_steer = _positive(name, "max_steer", max_steer)
    scale = car_effort_scale(car)
    heading, position, rest, bounds = weights
    q = {"sigma": max_steer} | ({} if y_bound is None else {"y": y_bound})
    return make_task(
        car,
        t_final=t_final,
        n_steps=n_steps,
        q0=np.asarray(q0, float),
        qdot0=np.zeros(5),
        objective=(Effort(scale),),
        constraints=(TerminalPose(np.asarray(goal, float), heading, position), TerminalRest((0,), rest)),
        bounds=Bounds.of(car, q=q, weight=bounds),
        controls=SampledControls(t_final, n_steps, scale),
        integrator=integrator,
        guess=Guess(amplitude=amplitude),
        objective_weight=1e-5,
        name=name,
        checkpoint=checkpoint,
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
    distance sideways) in ``t_final`` (s, default 10) with ``n_steps`` steps (default 100),
    minimising the effort (wheel torque scaled by the wheel's inertia, steering rate by 0.5 1/s);
    per-step controls; ``|sigma| <= max_steer`` (default 1; ``sigma = tan`` of the steering angle).
    Model: ``integrator`` (default ``lj.RDP(order=4)``); ``system`` default ``lj.Car()``;
    ``checkpoint`` as for :func:`~ldap_jax.simulate` (default ``False``)."""
    car = model_of(system, Car, "parallel_park")
    l = float(car.l)
    return _car_to_rest(
        "parallel_park",
        car,
        q0=np.zeros(5),
        goal=[0.0, 0.5 * l, 0.0],
        y_bound=None,
        weights=(100.0, 100.0 / l**2, 10.0, 100.0),
        t_final=t_final,
        n_steps=n_steps,
        integrator=integrator,
        max_steer=max_steer,
        checkpoint=checkpoint,
        amplitude=0.3,
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
    """Car U-turn in a lane of ``width`` (m, default 1): from rest at ``(0, -width/4, 0)`` to rest
    at ``(0, width/4, pi)`` in ``t_final`` (default 12 s, ``n_steps`` default 120) with the rear
    axle inside ``|y| <= width/2`` and ``|sigma| <= max_steer`` (default 1; minimum turning radius
    ``l / max_steer``: with the defaults a plain U-turn needs 1 m, so the car must back up),
    minimising the effort. Model: ``integrator`` (default ``lj.RDP(order=4)``) on ``system``
    (default ``lj.Car()``); ``checkpoint`` as for :func:`~ldap_jax.simulate` (default ``False``)."""
    car = model_of(system, Car, "u_turn")
    width = _positive("u_turn", "width", width)
    return _car_to_rest(
        "u_turn",
        car,
        q0=[0.0, -width / 4, 0.0, 0.0, 0.0],
        goal=[0.0, width / 4, np.pi],
        y_bound=width / 2,
        weights=(100.0, 100.0, 10.0, 1000.0),
        t_final=t_final,
        n_steps=n_steps,
        integrator=integrator,
        max_steer=max_steer,
        checkpoint=checkpoint,
        amplitude=0.1,
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
    """Snakeboard sinusoid gait from rest, for :func:`~ldap_jax.control.optimize`: the rotor and
    steering torques (N m) are sums of ``n_terms`` sinusoids (free amplitudes, shared frequencies
    and phases) that maximise the displacement along the initial heading in ``t_final`` (s,
    default 10), with ``|f| <= max_torque`` and ``|phi| <= max_steer`` as soft (penalty) bounds.

    This is an open-loop start from rest, not a periodic gait: the motion it finds is not a limit
    cycle and its bounds are penalties. For a periodic gait with hard constraints use
    :func:`~ldap_jax.control.drive_gait` and :func:`~ldap_jax.control.solve`.

    Defaults: ``system`` ``lj.Snakeboard()``, ``n_steps`` 100, ``max_torque`` 0.1 N m per channel,
    ``max_steer`` 1 rad, ``n_terms`` 1, ``frequency`` 2 rad/s (the initial guess's),
    ``integrator`` ``lj.RDP(order=4)``, ``checkpoint`` ``False`` (the rollout's memory policy in
    reverse mode, as for :func:`~ldap_jax.simulate`)."""
    sb = model_of(system, Snakeboard, "forward_gait")
    torques = per_channel("max_torque", sb.control_names, max_torque)
    return make_task(
        sb,
        t_final=t_final,
        n_steps=n_steps,
        q0=np.zeros(5),
        qdot0=np.zeros(5),
        objective=(Forward(),),
        bounds=Bounds.of(sb, q={"phi": snakeboard_steer(max_steer, "forward_gait")}, u=torques, weight=1e4),
        controls=SinusoidGait(
            np.asarray(list(torques.values()), float), n_terms=n_terms, frequency=frequency
        ),
        integrator=integrator,
        guess=Guess(amplitude=0.1),
        name="forward_gait",
        checkpoint=checkpoint,
    )


def snakeboard_steer(max_steer, where: str):
    """``max_steer`` checked for a snakeboard task: its bound ``|phi| <= max_steer`` (or the
    interval ``(lo, hi)``) must lie inside ``(-pi/2, pi/2)``, where ``cos(phi) != 0``; at
    ``phi = +-pi/2`` the snakeboard's equations are singular, and a solve whose iterates reach it
    fails with a message about the Hessian."""
    try:
        value = np.asarray(max_steer, float)
    except (TypeError, ValueError):
        return max_steer  # not numeric (or traced): Bounds.of names it
    lo, hi = (-value, value) if value.ndim == 0 else (value if value.shape == (2,) else (None, None))
    if lo is not None and not (-0.5 * np.pi < lo and hi < 0.5 * np.pi):
        raise ValueError(
            f"{where}: 'max_steer' must keep the steering angle inside (-pi/2, pi/2), where "
            f"cos(phi) != 0 (the snakeboard's equations are singular at |phi| = pi/2), got {max_steer!r}"
        )
    return max_steer


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
    """Snakeboard reach: from rest at the origin to ``goal = (x, y, theta)`` (m, m, rad; default
    ``(2, 1, pi/2)``) with the board at rest (speed ``s = 0``) in ``t_final`` (default 16 s,
    ``n_steps`` default 160), minimising the effort; per-step torques (N m) initialised from a gait,
    ``|f| <= max_torque``, ``|phi| <= max_steer`` (defaults 0.1 N m and 1 rad). Model: ``integrator``
    (default ``lj.RDP(order=4)``) on ``system`` (default ``lj.Snakeboard()``); ``frequency`` of the
    initial gait guess (default 2 rad/s); ``checkpoint`` as for :func:`~ldap_jax.simulate`
    (default ``False``)."""
    sb = model_of(system, Snakeboard, "reach")
    torques = per_channel("max_torque", sb.control_names, max_torque)
    scale = np.asarray(list(torques.values()), float)
    return make_task(
        sb,
        t_final=t_final,
        n_steps=n_steps,
        q0=np.zeros(5),
        qdot0=np.zeros(5),
        objective=(Effort(scale),),
        constraints=(TerminalPose(np.asarray(goal, float), 10.0, 10.0), TerminalRest((2,), 10.0)),
        bounds=Bounds.of(sb, q={"phi": snakeboard_steer(max_steer, "reach")}, u=torques),
        controls=SampledControls(t_final, n_steps, scale),
        integrator=integrator,
        guess=Guess(amplitude=0.9, gait=SinusoidGait(scale, n_terms=1, frequency=frequency)),
        objective_weight=1e-5,
        name="reach",
        checkpoint=checkpoint,
    )
