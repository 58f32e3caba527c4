""":func:`make_task`: a :class:`~ldap_jax.control.Task` from its pieces, every piece checked."""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._compilation_cache import asarray
from .._rollout import check_checkpoint
from .._validation import check_array, check_positive_int, check_scalar, is_concrete, known_initial_violation
from ..integrators import RDP, AbstractIntegrator
from ..systems import AbstractSystem
from ._constraints import (
    AbstractConstraint,
    AbstractInitialConstraint,
    Bounds,
    InitialRest,
    Periodic,
    TerminalPose,
    TerminalRest,
    check_rest_indices,
)
from ._parameterizations import AbstractParameterization, SampledControls
from ._task import Guess, Task
from ._terms import AbstractTerm, Effort

__all__ = ["make_task"]


def make_task(
    system: AbstractSystem,
    *,
    t_final: float,
    n_steps: int,
    q0: Any = None,
    qdot0: Any = None,
    objective: tuple[AbstractTerm, ...] = (),
    constraints: tuple[AbstractConstraint, ...] = (),
    bounds: Bounds | None = None,
    controls: AbstractParameterization | None = None,
    integrator: AbstractIntegrator | None = None,
    guess: Guess | None = None,
    objective_weight: float = 1.0,
    name: str = "task",
    checkpoint: bool | str | int = False,
) -> Task:
    """An optimal control task, from public pieces: what a built-in task is made of.

    Minimise the sum of the ``objective`` terms over the node controls (and, for a periodic task,
    the start), subject to the discrete dynamics of ``integrator``, the ``constraints`` and the
    ``bounds`` at the nodes; :func:`~ldap_jax.control.solve` holds every constraint exactly.

    Args:
        system: the model, e.g. ``lj.Car()``.
        t_final: horizon (s, > 0); for a periodic task, the period.
        n_steps: number of steps N (an integer >= 1; >= 2 for a periodic task).
        q0, qdot0: the fixed initial state (d,), ``qdot0`` on the constraints; omit both for a
            periodic task (the start is then a decision variable).
        objective: objective terms, summed (e.g. ``(lc.Effort(scale),)``, ``(lc.Displacement(),)``).
        constraints: constraint terms: terminal equalities (``lc.TerminalPose(goal)``,
            ``lc.TerminalRest(indices)``, ``lc.NetDisplacement(dx=...)``, ``lc.TerminalConstraint(fn)``),
            path inequalities ``lc.PathConstraint(fn)`` (``fn(t, q, qdot, c) <= 0`` at the nodes),
            and for a gait ``lc.Periodic(cyclic=...)`` with conditions on the start
            (``lc.InitialRest(indices)``, ``lc.InitialConstraint(fn)``).
        bounds: bounds at the nodes (``lc.Bounds.of(system, q=..., u=...)``; default none).
        controls: the control parameterization (default per-step ``lc.SampledControls`` with
            unit scale; ``solve`` needs per-step controls).
        integrator: the dynamics model (default ``lj.RDP(order=4)``: fourth order, the model whose
            error stays below ``solve``'s tolerance on the built-in tasks; a periodic task needs
            an RDP integrator, whose flat state is invariant under the symmetry).
        guess: how ``task.init()`` guesses (default ``lc.Guess()``).
        objective_weight: the objective's weight in the penalty form only (:meth:`Task.loss`).
        name: the task's name.
        checkpoint: the penalty form's rollout memory policy (as for ``lj.simulate``).

    Returns:
        :class:`Task`.

    Raises:
        TypeError: a piece of the wrong type; the message names it.
        ValueError: a bad shape or value (non-finite or out-of-bounds ``q0``, ``qdot0`` off the
            constraints, ``t_final <= 0``, empty bounds, a goal outside them, a periodic task with
            a fixed start or fewer than 2 steps, controls with the wrong number of channels); the
            message names the argument.

    Example:
        A car parks around an obstacle, with least effort::

            car = lj.Car()
            task = lc.make_task(
                car, t_final=10.0, n_steps=100, q0=jnp.zeros(5), qdot0=jnp.zeros(5),
                objective=(lc.Effort(jnp.array([0.11, 0.5])),),
                constraints=(lc.TerminalPose(jnp.array([1.0, 0.25, 0.0])), lc.TerminalRest((0,)),
                             lc.PathConstraint(lambda t, q, qd, c: 0.1**2 - (q[0] - 0.5)**2 - q[1]**2)),
                bounds=lc.Bounds.of(car, q={"sigma": 1.0}),
                controls=lc.SampledControls(10.0, 100, jnp.array([0.11, 0.5])),
            )
            sol = lc.solve(task)
    """
    _check_types(system, objective, constraints, bounds, controls, integrator, guess, name)
    objective, constraints = tuple(objective), tuple(constraints)
    periodic = [c for c in constraints if isinstance(c, Periodic)]
    n_steps = check_positive_int("n_steps", n_steps)
    t_final = asarray(check_scalar("t_final", t_final), float)
    _check_concrete_positive("t_final", t_final)
    d, m = system.n_config, system.n_controls
    context = f"for {type(system).__name__}"
    if periodic:
        q0, qdot0 = _check_periodic(system, periodic, constraints, q0, qdot0, n_steps, integrator)
    else:
        if q0 is None or qdot0 is None:
            raise ValueError(
                "'q0' and 'qdot0' are required (a fixed start), or add lc.Periodic() to 'constraints'"
            )
        if any(isinstance(c, AbstractInitialConstraint) for c in constraints):
            raise ValueError(
                "'constraints': initial conditions (lc.InitialRest, ...) need a free start (lc.Periodic)"
            )
        q0 = check_array("q0", q0, (d,), context).astype(float)
        qdot0 = check_array("qdot0", qdot0, (d,), context).astype(float)
    if bounds is None:
        bounds = Bounds(
            jnp.full(d, -jnp.inf), jnp.full(d, jnp.inf), jnp.full(m, -jnp.inf), jnp.full(m, jnp.inf)
        )
    bounds = _check_bounds(bounds, d, m, context)
    controls = SampledControls(t_final, n_steps, np.ones(m)) if controls is None else controls
    _check_controls(controls, system, n_steps, t_final)
    objective_weight = asarray(check_scalar("objective_weight", objective_weight), float)
    if is_concrete(objective_weight) and not (
        np.isfinite(float(objective_weight)) and float(objective_weight) >= 0
    ):
        raise ValueError(f"'objective_weight' must be non-negative and finite, got {float(objective_weight)}")
    task = Task(
        name=name,
        system=system,
        integrator=RDP(order=4) if integrator is None else integrator,
        t_final=t_final,
        n_steps=n_steps,
        q0=q0,
        qdot0=qdot0,
        parameterization=controls,
        objective=objective,
        constraints=constraints,
        bounds=bounds,
        guess=Guess() if guess is None else guess,
        objective_weight=objective_weight,
        checkpoint=check_checkpoint(checkpoint),
    )
    _check_values(task)
    _check_pieces(task)
    return task


def _check_pieces(task: Task) -> None:
    """Shapes the pieces must agree on: the effort's scale and the explicit guess against the
    channels and nodes, the rest conditions' indices against the minimal velocities."""
    m = task.system.n_controls
    for term in task.objective:
        if isinstance(term, Effort) and jnp.shape(term.scale) not in ((m,), (1,)):
            raise ValueError(
                f"'objective': lc.Effort's scale has shape {jnp.shape(term.scale)}, "
                f"{type(task.system).__name__} has {m} control channels {task.system.control_names}"
            )
    for con in task.constraints:
        if isinstance(con, (TerminalRest, InitialRest)):
            check_rest_indices(con, task.system)
    guess = task.guess.controls
    if guess is not None and jnp.shape(guess) != (task.n_steps + 1, m):
        raise ValueError(
            f"'guess': Guess.controls must have shape {(task.n_steps + 1, m)} (N + 1 nodes, channels), "
            f"got {jnp.shape(guess)}"
        )


def _check_types(system, objective, constraints, bounds, controls, integrator, guess, name) -> None:
    if not isinstance(name, str):
        raise TypeError(f"'name' must be a string, got {name!r}")
    if not isinstance(system, AbstractSystem):
        raise TypeError(f"'system' must be an ldap_jax system (e.g. lj.Car()), got {type(system)}")
    for arg, kind, what in (
        ("objective", AbstractTerm, "objective terms (e.g. (lc.Effort(scale),))"),
        ("constraints", AbstractConstraint, "constraint terms (e.g. (lc.TerminalPose(goal),))"),
    ):
        value = {"objective": objective, "constraints": constraints}[arg]
        if not isinstance(value, (tuple, list)) or not all(isinstance(t, kind) for t in value):
            raise TypeError(f"'{arg}' must be a tuple of {what}, got {value!r}")
    checks = (
        ("bounds", bounds, Bounds, "an lc.Bounds"),
        ("controls", controls, AbstractParameterization, "an lc parameterization (lc.SampledControls)"),
        ("integrator", integrator, AbstractIntegrator, "an ldap_jax integrator (e.g. lj.RDP(order=4))"),
        ("guess", guess, Guess, "an lc.Guess"),
    )
    for arg, value, kind, what in checks:
        if value is not None and not isinstance(value, kind):
            raise TypeError(f"'{arg}' must be {what} or None, got {type(value)}")


def _check_concrete_positive(name: str, x) -> None:
    with jax.ensure_compile_time_eval():
        if is_concrete(x) and not (np.isfinite(float(x)) and float(x) > 0):
            raise ValueError(f"'{name}' must be positive and finite, got {float(x)}")


def _check_periodic(system, periodic, constraints, q0, qdot0, n_steps, integrator):
    if len(periodic) > 1:
        raise ValueError("'constraints' may hold one lc.Periodic boundary condition, got several")
    if q0 is not None or qdot0 is not None:
        raise ValueError("a periodic task's start is a decision variable: give neither 'q0' nor 'qdot0'")
    if n_steps < 2:
        raise ValueError(f"'n_steps' of a periodic task must be at least 2, got {n_steps}")
    if integrator is not None and not isinstance(integrator, RDP):
        raise ValueError(
            "a periodic task needs an RDP integrator (lj.RDP(order=2 | 4 | 6 | 8)), whose flat state "
            f"(q, P, nu) is invariant under the symmetry; got {type(integrator).__name__}"
        )
    unknown = [n for n in periodic[0].cyclic if n not in system.shape_names]
    if unknown:
        raise ValueError(
            f"lc.Periodic: unknown cyclic coordinates {unknown}; {type(system).__name__}'s shape "
            f"coordinates are {system.shape_names}"
        )
    dependent = _not_cyclic(system, periodic[0].cyclic)
    if dependent:
        raise ValueError(
            f"lc.Periodic: {dependent} are not cyclic: {type(system).__name__}'s equations depend on "
            "them, so a gait must bring them back after each period (a cyclic coordinate, such as a "
            "rotor or wheel angle, appears in none of the equations); leave them out of 'cyclic'"
        )
    return None, None


def _not_cyclic(system: AbstractSystem, names: tuple[str, ...]) -> list[str]:
    """The ``names`` whose shift changes the system's equations. A system that declares its
    cyclic coordinates (``cyclic_names``) is taken at its word; otherwise the continuous
    equations ``(qdot, vdot) = ode((q, v), c)`` are evaluated at three random states and
    controls, and again with each coordinate shifted by 0.37: a cyclic one changes nothing
    (to 1e-9 relative; a point where the equations are not finite is skipped)."""
    if not names:
        return []
    if system.cyclic_names is not None:
        return [n for n in names if n not in system.cyclic_names]
    if not is_concrete(system):  # a model of traced parameters (a sensitivity): checked when built
        return []
    # once per system's functions and names (a loop of ``with_options`` would compile it each time)
    key = (type(system), names, *(x for x in jax.tree_util.tree_leaves(system) if callable(x)))
    if key not in _CYCLIC_CHECKED:
        _CYCLIC_CHECKED[key] = _shifted_equations_differ(system, names)
    return _CYCLIC_CHECKED[key]


_CYCLIC_CHECKED: dict = {}


def _shifted_equations_differ(system: AbstractSystem, names: tuple[str, ...]) -> list[str]:
    rng = np.random.default_rng(0)
    d, dtype = system.n_config, jnp.result_type(float)
    q = rng.uniform(-0.5, 0.5, (3, d))
    v = rng.normal(0.0, 0.5, (3, system.n_velocities))
    c = rng.normal(0.0, 0.3, (3, system.n_controls))
    index = [3 + system.shape_names.index(n) for n in names]
    shifted = np.stack([q + 0.37 * np.eye(d)[i] for i in index])  # (names, 3, d)

    def rhs(q, v, c):
        return jnp.concatenate(system.ode((q, v), c))

    batched = jax.jit(jax.vmap(jax.vmap(rhs), (0, None, None)))
    out = np.asarray(batched(np.stack([q, *shifted]).astype(dtype), v.astype(dtype), c.astype(dtype)))
    base, moved = out[0], out[1:]
    ok = np.isfinite(base).all(axis=-1) & np.isfinite(moved).all(axis=-1)  # (names, 3)
    change = np.abs(moved - base[None]).max(axis=-1) / (1.0 + np.abs(base).max(axis=-1))[None]
    return [n for n, bad in zip(names, np.any(ok & (change > 1e-9), axis=-1)) if bad]


def _check_bounds(bounds: Bounds, d: int, m: int, context: str) -> Bounds:
    q_lo = check_array("bounds.q_lower", bounds.q_lower, (d,), context).astype(float)
    q_hi = check_array("bounds.q_upper", bounds.q_upper, (d,), context).astype(float)
    u_lo = check_array("bounds.u_lower", bounds.u_lower, (m,), context).astype(float)
    u_hi = check_array("bounds.u_upper", bounds.u_upper, (m,), context).astype(float)
    if is_concrete((q_lo, q_hi, u_lo, u_hi)):
        for name, lo, hi in (("q", q_lo, q_hi), ("u", u_lo, u_hi)):
            lo, hi = np.asarray(lo), np.asarray(hi)
            if np.any(np.isnan(lo)) or np.any(np.isnan(hi)) or np.any(lo >= hi):
                raise ValueError(
                    f"'bounds': {name}_lower must lie below {name}_upper (no NaN), got {name}_lower={lo}, "
                    f"{name}_upper={hi}"
                )
    return dataclasses.replace(bounds, q_lower=q_lo, q_upper=q_hi, u_lower=u_lo, u_upper=u_hi)


def _check_controls(controls, system, n_steps, t_final) -> None:
    m = system.n_controls
    scale = getattr(controls, "scale", None)
    if scale is not None and jnp.shape(scale)[-1:] != (m,):
        raise ValueError(
            f"'controls' has {jnp.shape(scale)[-1] if jnp.ndim(scale) else 0} channels (its scale), "
            f"{type(system).__name__} takes {m} {system.control_names}"
        )
    if isinstance(controls, SampledControls):
        if controls.n_steps != n_steps:
            raise ValueError(f"'controls' samples {controls.n_steps} steps but 'n_steps' is {n_steps}")
        with jax.ensure_compile_time_eval():
            if is_concrete(controls.t0) and float(controls.t0) != 0.0:
                raise ValueError(
                    f"'controls' start at t0={float(controls.t0)}, but a task runs from t = 0 (node k at "
                    "k h): make the SampledControls with t0=0"
                )
        with jax.ensure_compile_time_eval():
            if is_concrete((controls.t_final, t_final)) and not np.isclose(
                float(controls.t_final), float(t_final)
            ):
                raise ValueError(
                    f"'controls' spans t_final={float(controls.t_final)} but 't_final' is {float(t_final)}"
                )


def _check_values(task: Task) -> None:
    """Value checks where the values are known (a task built inside jit skips them)."""
    b = task.bounds
    lo, hi = (np.asarray(b.q_lower), np.asarray(b.q_upper)) if is_concrete(b) else (None, None)
    if task.q0 is not None and is_concrete((task.system, task.q0, task.qdot0)):
        for name, x in (("q0", task.q0), ("qdot0", task.qdot0)):
            if not np.all(np.isfinite(np.asarray(x))):
                raise ValueError(f"'{name}' must be finite, got {np.asarray(x)}")
        viol = known_initial_violation(task.system, task.q0, task.qdot0, None, 0.0)[1]
        if not viol < 1e-10:
            raise ValueError(f"'qdot0' violates the constraints of {type(task.system).__name__} ({viol:.2e})")
        if lo is not None and (np.any(np.asarray(task.q0) <= lo) or np.any(np.asarray(task.q0) >= hi)):
            raise ValueError(
                f"'q0' {np.asarray(task.q0)} lies on or outside the bounds [{lo}, {hi}] (the "
                "interior-point solver holds every bound strictly: the start must lie inside them)"
            )
    fixed = task.fixed_start
    if fixed is not None and lo is not None:
        idx, val = fixed
        if np.any(val <= lo[idx]) or np.any(val >= hi[idx]):
            coords = ("x", "y", "theta", *task.system.shape_names)
            names = [coords[i] for i in idx]
            raise ValueError(
                f"'bounds' must contain a gait's fixed start strictly: {names} start at 0, but their "
                f"bounds are [{lo[idx]}, {hi[idx]}]"
            )
    goal = task.goal
    if goal is not None and is_concrete(goal) and lo is not None:
        g = np.asarray(goal)
        if g.shape != (3,):
            raise ValueError(f"'goal' (lc.TerminalPose) must be a pose (x, y, theta), got shape {g.shape}")
        if not np.all(np.isfinite(g)):
            raise ValueError(f"'goal' must be finite, got {g}")
        if np.any((g < lo[:3]) | (g > hi[:3])):
            raise ValueError(f"'goal' {g} lies outside the bounds of (x, y, theta): [{lo[:3]}, {hi[:3]}]")


def rebuild(task: Task, **changes) -> Task:
    """``task`` with some pieces changed, checked as :func:`make_task` checks them."""
    allowed = {
        "integrator",
        "system",
        "n_steps",
        "t_final",
        "checkpoint",
        "goal",
        "bounds",
        "objective",
        "constraints",
        "guess",
        "controls",
        "name",
    }
    unknown = set(changes) - allowed
    if unknown:
        raise TypeError(f"with_options: unknown options {sorted(unknown)}; allowed: {sorted(allowed)}")
    changes = {k: v for k, v in changes.items() if v is not None}
    if "system" in changes and not isinstance(changes["system"], type(task.system)):
        raise TypeError(
            f"'system' must be a {type(task.system).__name__} like the task's, got {type(changes['system'])}"
        )
    constraints = changes.pop("constraints", task.constraints)
    if "goal" in changes:
        goal = check_array("goal", changes.pop("goal"), (3,), "(a pose x, y, theta)").astype(float)
        if task.goal is None:
            raise ValueError("'goal': this task has no terminal pose (lc.TerminalPose) to move")
        constraints = tuple(
            dataclasses.replace(c, goal=goal) if isinstance(c, TerminalPose) else c for c in constraints
        )
    n_steps = check_positive_int("n_steps", changes.pop("n_steps", task.n_steps))
    t_final = changes.pop("t_final", task.t_final)
    controls = changes.pop("controls", task.parameterization)
    if isinstance(controls, SampledControls) and (n_steps != controls.n_steps or t_final is not task.t_final):
        controls = SampledControls(t_final, n_steps, controls.scale, t0=controls.t0)
    guess = changes.pop("guess", task.guess)
    if (
        guess is task.guess
        and guess.controls is not None
        and is_concrete(guess.controls)
        and n_steps != task.n_steps
    ):
        # the task's own explicit guess, resampled (linearly, over the normalised time) to the new nodes
        old = np.asarray(guess.controls)
        s_new = np.linspace(0, 1, n_steps + 1)
        s_old = np.linspace(0, 1, old.shape[0])
        resampled = np.stack([np.interp(s_new, s_old, col) for col in old.T], axis=1)
        guess = dataclasses.replace(guess, controls=resampled)
    return make_task(
        changes.pop("system", task.system),
        t_final=t_final,
        n_steps=n_steps,
        q0=task.q0,
        qdot0=task.qdot0,
        objective=changes.pop("objective", task.objective),
        constraints=constraints,
        bounds=changes.pop("bounds", task.bounds),
        controls=controls,
        integrator=changes.pop("integrator", task.integrator),
        guess=guess,
        objective_weight=task.objective_weight,
        name=changes.pop("name", task.name),
        checkpoint=changes.pop("checkpoint", task.checkpoint),
    )
