"""Periodic gaits as hard-constrained limit cycles: the builder and the built-in gaits.

A gait is a periodic motion of the reduced state (everything invariant under SE(2): the shape,
the shape velocities, the body velocities or momenta; for RDP the momenta the next step reads),
driven by periodic controls, that moves the group by the same net displacement
``dg = g(0)^-1 g(T)`` every cycle. Its start is a decision variable on the constraint manifold,
with the group at the identity and the cyclic shape coordinates (a rotor or wheel angle) at 0.

A cycle needs an *anchor*. For the snakeboard, periodicity alone leaves the problem unbounded:
the board speed ``s`` obeys ``s' = a(t) s + b(t)`` with ``a = -1/2 d/dt ln(m l^2 - I sin^2 phi)``
(from the momentum equation), so ``int_0^T a dt = 0`` for every periodic ``phi``: the homogeneous
solution is periodic, and adding any multiple of it keeps every return condition while the board
coasts (a solver maximising distance runs off to thousands of metres). The snakeboard gaits
therefore start each cycle with the board at rest (``s = 0``; the rotor and the wheels may turn):
any periodic ``s`` with a zero can be shifted in time to satisfy it. For the car the family of
time-shifted cycles is nearly flat, and a phase condition fixes it: the rear wheel is at rest at
the cycle's start.
"""

from __future__ import annotations

import math
from typing import Any

import jax
import numpy as np

from .._validation import check_positive_int
from ..integrators import AbstractIntegrator
from ..systems import AbstractSystem, Car, Snakeboard, System, roller_racer
from ._build import make_task
from ._constraints import (
    AbstractConstraint,
    Bounds,
    InitialRest,
    NetDisplacement,
    Periodic,
    cyclic_names,
    per_channel,
)
from ._parameterizations import SampledControls
from ._task import Guess, Task
from ._tasks import car_effort_scale, model_of, snakeboard_steer
from ._terms import AbstractTerm, Displacement, Effort, Rotation

__all__ = ["make_gait", "drive_gait", "turn_gait", "sideways_gait", "racer_gait"]


def _period(period: Any) -> float:
    # a Python or NumPy number, or a concrete 0-d array (e.g. another task's ``t_final``)
    arr = None if isinstance(period, (bool, str, bytes, jax.core.Tracer)) else np.asarray(period)
    if arr is None or arr.ndim != 0 or arr.dtype.kind not in "iuf":
        raise TypeError(f"'period' must be a positive number (s), got {period!r}")
    if not (math.isfinite(float(period)) and float(period) > 0):
        raise ValueError(f"'period' must be positive and finite (s), got {period!r}")
    return float(period)


def _steps(n_steps: Any) -> int:
    n = check_positive_int("n_steps", n_steps)
    if n < 2:
        raise ValueError(f"'n_steps' of a gait must be at least 2 (nodes per period), got {n}")
    return n


def make_gait(
    system: AbstractSystem,
    *,
    period: float,
    n_steps: int,
    objective: tuple[AbstractTerm, ...],
    constraints: tuple[AbstractConstraint, ...] = (),
    cyclic: tuple[str, ...] = (),
    bounds: Bounds | None = None,
    scale: Any = None,
    integrator: AbstractIntegrator | None = None,
    guess: Guess | None = None,
    name: str = "gait",
) -> Task:
    """A periodic gait task of any system: :func:`make_task` with :class:`Periodic` and per-step
    controls over one period.

    Args:
        system: the model (``lj.Snakeboard()``, ``lj.Car()``, ``lj.roller_racer(drag=0.3)``, any
            ``lj.System``).
        period: the period T (s, > 0).
        n_steps: nodes per period N (>= 2).
        objective: objective terms (e.g. ``(lc.Displacement(),)``: the displacement per cycle).
        constraints: further constraints: a prescribed displacement per cycle
            (``lc.NetDisplacement(dx=..., dy=..., dtheta=...)``), the anchor on the start
            (``lc.InitialRest(indices)``), path constraints.
        cyclic: names of the cyclic shape coordinates (start at 0, drift freely; default none):
            coordinates that no equation depends on, such as a rotor or wheel angle (a name the
            equations depend on is refused).
        bounds: bounds at the nodes (``lc.Bounds.of(system, q=..., u=...)``).
        scale: per-channel control scale (default: the control bounds' half-widths where finite,
            else 1).
        integrator: an RDP integrator (default ``lj.RDP(order=4)``).
        guess: how the default guess is made (default: one smooth periodic guess).
        name: the task's name.

    Returns:
        A periodic :class:`Task`; ``lc.solve(task)`` returns :class:`GaitParams` parameters.

    Not every system has a gait. The roller racer's momentum obeys
    ``p' = a(phi) phidot p + beta(phi) phidot^2`` with ``beta > 0`` and no torque in it, so
    ``exp(-int_0^phi a) p`` grows over any cycle in which the hinge moves: it has no periodic
    motion but coasting, and ``lc.solve`` does not converge on its gait task (locally infeasible
    constraints, or an iteration budget spent while the objective runs away). With
    friction (``lj.roller_racer(drag=0.3)``) it has limit cycles: :func:`racer_gait`.

    Raises:
        TypeError, ValueError: ``period <= 0``, ``n_steps < 2``, and as :func:`make_task`.
    """
    if not isinstance(system, AbstractSystem):
        raise TypeError(
            f"make_gait: 'system' must be an ldap_jax system (lj.Snakeboard(), lj.Car(), an "
            f"lj.System), got {type(system).__name__}"
        )
    cyclic = cyclic_names(cyclic, "make_gait")  # one name, or several
    period, n_steps = _period(period), _steps(n_steps)
    m = system.n_controls
    if bounds is not None and not isinstance(bounds, Bounds):
        raise TypeError(
            f"'bounds' must be lc.Bounds (e.g. lc.Bounds.of(system, q=..., u=...)), got {bounds!r}"
        )
    if scale is None:
        scale = np.ones(m)
        if bounds is not None:
            width = 0.5 * (np.asarray(bounds.u_upper) - np.asarray(bounds.u_lower))
            scale = np.where(np.isfinite(width), width, 1.0)
    return make_task(
        system,
        t_final=period,
        n_steps=n_steps,
        objective=(objective,) if isinstance(objective, AbstractTerm) else tuple(objective),
        constraints=(
            Periodic(cyclic),
            *((constraints,) if isinstance(constraints, AbstractConstraint) else constraints),
        ),
        bounds=bounds,
        controls=SampledControls(period, n_steps, np.asarray(scale, float)),
        integrator=integrator,
        guess=guess,
        name=name,
    )


def _torque_bounds(sb: Snakeboard, max_torque, max_steer, where: str) -> Bounds:
    phi = snakeboard_steer(max_steer, where)
    return Bounds.of(sb, q={"phi": phi}, u=per_channel("max_torque", sb.control_names, max_torque))


def _drive_guess(n_steps: int) -> np.ndarray:
    """The drive gait's default guess (scaled controls): the rotor torque at twice the steering
    frequency, ``0.9 sin(4 pi t / T)``, and the steering torque ``-0.9 cos(2 pi t / T)``. Smaller
    amplitudes and random periodic guesses (8 of 8 tried) converge to a nearby local optimum
    (0.2620069 m per cycle, against 0.2620924 from this one: IPOPT's best of 5 on the same problem)."""
    s = np.linspace(0.0, 1.0, n_steps + 1)
    return np.stack([0.9 * np.sin(4 * np.pi * s), -0.9 * np.cos(2 * np.pi * s)], axis=1)


def drive_gait(
    system: Snakeboard | None = None,
    *,
    period: float = math.pi,
    n_steps: int = 100,
    max_torque: Any = (0.1, 0.1),
    max_steer: Any = 1.0,
    integrator: AbstractIntegrator | None = None,
) -> Task:
    """The snakeboard's drive gait: maximise the forward displacement per cycle (along the start's
    heading) with zero net rotation, the board at rest at the cycle's start.

    Args:
        system: default ``lj.Snakeboard()``.
        period: T (s, default pi). n_steps: nodes per period (default 100).
        max_torque: bounds of the rotor and steering torques (N m, default 0.1 each): one
            number ``b`` for both (``[-b, b]``), or one entry per channel, ``(rotor, steering)``,
            each a number or a pair ``(lo, hi)``; so ``(0.05, 0.2)`` means ``|f_psi| <= 0.05``
            and ``|f_phi| <= 0.2``, and an asymmetric rotor bound is ``((-0.05, 0.1), 0.1)``.
        max_steer: bound of the steering angle ``phi`` (rad, default 1; or ``(lo, hi)``).
        integrator: default ``lj.RDP(order=4)``.
    """
    sb = model_of(system, Snakeboard, "drive_gait")
    return make_gait(
        sb,
        period=period,
        n_steps=n_steps,
        objective=(Displacement((1.0, 0.0)),),
        constraints=(InitialRest((0, 2)), NetDisplacement(dtheta=0.0)),
        cyclic=("psi",),
        bounds=_torque_bounds(sb, max_torque, max_steer, "drive_gait"),
        integrator=integrator,
        guess=Guess(controls=_drive_guess(_steps(n_steps))),
        name="drive_gait",
    )


def turn_gait(
    system: Snakeboard | None = None,
    *,
    period: float = math.pi,
    n_steps: int = 100,
    max_torque: Any = (0.1, 0.1),
    max_steer: Any = 1.0,
    starts: int = 16,
    integrator: AbstractIntegrator | None = None,
) -> Task:
    """The snakeboard's turn gait: maximise the rotation per cycle (counter-clockwise) with zero net
    translation, the board at rest at the cycle's start; bounds as :func:`drive_gait`.

    The problem has many local optima (random starts end anywhere between 0.01 and 0.1 rad per
    cycle, or at the trivial cycle), so the default guess is a batch of ``starts`` random periodic
    guesses at the torque bounds' full amplitude (default 16; all 16 converged, 2 to 0.10082 rad
    per cycle, IPOPT's best of 25 on the same formulation being 0.1008173; at 0.7 of the bounds
    the best was 0.0805),
    which ``lc.solve`` runs in one program, returning the best converged one.

    Args:
        system: default ``lj.Snakeboard()``.
        period: T (s, default pi). n_steps: nodes per period (default 100).
        max_torque, max_steer: as :func:`drive_gait` (defaults 0.1 N m and 1 rad).
        starts: the number of random periodic guesses (default 16).
        integrator: default ``lj.RDP(order=4)``.
    """
    sb = model_of(system, Snakeboard, "turn_gait")
    return make_gait(
        sb,
        period=period,
        n_steps=n_steps,
        objective=(Rotation(),),
        constraints=(InitialRest((0, 2)), NetDisplacement(dx=0.0, dy=0.0)),
        cyclic=("psi",),
        bounds=_torque_bounds(sb, max_torque, max_steer, "turn_gait"),
        integrator=integrator,
        guess=Guess(amplitude=1.0, starts=check_positive_int("starts", starts)),
        name="turn_gait",
    )


def sideways_gait(
    system: Car | None = None,
    *,
    shift: float = 0.05,
    period: float = 4.0,
    n_steps: int = 100,
    max_torque: Any = 0.4,
    max_steer: Any = 1.0,
    starts: int = 4,
    integrator: AbstractIntegrator | None = None,
) -> Task:
    """The car's sideways gait: a net shift of ``shift`` (m, default 0.05) to the left per cycle
    with the heading unchanged, minimum effort (the :func:`parallel_park` scales), the rear wheel
    at rest at the cycle's start (the phase condition).

    Args:
        system: default ``lj.Car()``.
        shift: sideways displacement per cycle (m). period: T (s, default 4). n_steps: nodes
            per period (default 100).
        max_torque: bound of the wheel torque (N m, default 0.4; or ``(lo, hi)``).
        max_steer: bound of ``sigma`` (default 1; or ``(lo, hi)``).
        starts: random periodic guesses run as a batch (default 4). The problem has at least two
            local optima: one smooth guess converged to an effort of 160.2256, 15 of 16 random
            ones to 62.4809 (IPOPT's best of 5 on the same formulation: 62.4809).
        integrator: default ``lj.RDP(order=4)``.
    """
    car = model_of(system, Car, "sideways_gait")
    scale = car_effort_scale(car)
    return make_gait(
        car,
        period=period,
        n_steps=n_steps,
        objective=(Effort(scale),),
        constraints=(InitialRest((0,)), NetDisplacement(dx=0.0, dy=shift, dtheta=0.0)),
        cyclic=("psi",),
        bounds=Bounds.of(car, q={"sigma": max_steer}, u={"f_psi": max_torque}),
        scale=scale,
        integrator=integrator,
        guess=Guess(amplitude=0.3, starts=check_positive_int("starts", starts)),
        name="sideways_gait",
    )


def racer_gait(
    system: System | None = None,
    *,
    period: float = 4.6,
    n_steps: int = 100,
    max_torque: Any = 0.3,
    max_steer: Any = 1.0,
    integrator: AbstractIntegrator | None = None,
) -> Task:
    """The roller racer's gait: maximise the forward displacement per cycle (along the start's
    heading) with zero net rotation, by the hinge torque alone, through :func:`make_gait`.

    The racer needs friction to have a gait at all (without it, every wiggle of the hinge adds
    momentum and its reduced state never returns; see :func:`ldap_jax.roller_racer`). With a
    rolling resistance, pumping and drag balance on a limit cycle, which needs no anchor: there is
    no coasting family to rule out. At the defaults the cycle is asymptotically stable (Floquet
    multipliers of modulus about 0.1): an error dies out within a few cycles.

    Args:
        system: default ``lj.roller_racer(drag=0.3)`` (a racer with ``drag``).
        period: T (s, default 4.6, about the hinge's natural period). n_steps: nodes per period
            (default 100).
        max_torque: bound of the hinge torque (N m, default 0.3; or ``(lo, hi)``).
        max_steer: bound of the hinge angle ``phi`` (rad, default 1; or ``(lo, hi)``).
        integrator: default ``lj.RDP(order=4)``.

    Raises:
        ValueError: a racer without friction.
    """
    racer = system if system is not None else roller_racer(drag=0.3)
    if not racer.has_friction:
        raise ValueError(
            "racer_gait: 'system' needs friction (e.g. lj.roller_racer(drag=0.3)): without it the "
            "racer has no periodic motion but coasting"
        )
    s = np.linspace(0.0, 1.0, _steps(n_steps) + 1)
    return make_gait(
        racer,
        period=period,
        n_steps=n_steps,
        objective=(Displacement((1.0, 0.0)),),
        constraints=(NetDisplacement(dtheta=0.0),),
        bounds=Bounds.of(racer, q={"phi": max_steer}, u={"f_phi": max_torque}),
        integrator=integrator,
        guess=Guess(controls=0.9 * np.sin(2 * np.pi * s)[:, None]),
        name="racer_gait",
    )
