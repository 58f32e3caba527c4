"""Constraints of an optimal control task, as composable terms, and the bounds at the nodes.

Each constraint is a small module with one ``residual`` method. :func:`~ldap_jax.control.solve`
holds them exactly (equalities and inequalities of its interior-point method);
:func:`~ldap_jax.control.optimize` minimises their quadratic penalties instead, weighted by
``weight`` (ignored by ``solve``). Four kinds, by where they apply:

* **terminal** equalities ``r(node_N, q_0) = 0`` (:class:`TerminalPose`, :class:`TerminalRest`,
  :class:`NetDisplacement`, :class:`TerminalConstraint`);
* **path** inequalities ``g(t_k, q_k, qdot_k, c_k) <= 0`` at every node (:class:`PathConstraint`);
* **initial** equalities ``r(node_0, c_0) = 0`` on a free start (:class:`InitialRest`,
  :class:`InitialConstraint`): the anchor of a periodic task;
* the **boundary** condition :class:`Periodic`, which makes the start a decision variable and
  asks the reduced state and the controls to return after one period.

A constraint of your own subclasses :class:`AbstractTerminalConstraint`,
:class:`AbstractPathConstraint` or :class:`AbstractInitialConstraint` and overrides ``residual``.
"""

from __future__ import annotations

import abc
import inspect
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._compilation_cache import asarray
from .._typing import ArrayLike
from .._validation import is_concrete
from ._terms import bound_penalty, check_known, displacement, pose_error

__all__ = [
    "AbstractConstraint",
    "AbstractTerminalConstraint",
    "AbstractPathConstraint",
    "AbstractInitialConstraint",
    "TerminalPose",
    "TerminalRest",
    "NetDisplacement",
    "TerminalConstraint",
    "PathConstraint",
    "InitialRest",
    "InitialConstraint",
    "Periodic",
    "Bounds",
]


def _indices(x: Any) -> tuple[int, ...]:
    """A tuple of Python ints (the velocity indices of a rest condition), or a ``TypeError``."""
    items = (x,) if isinstance(x, (int, np.integer)) else x
    try:
        items = tuple(items)
    except TypeError:
        items = None
    if not items or any(isinstance(i, bool) or not isinstance(i, (int, np.integer)) for i in items):
        raise TypeError(f"'indices' must be a non-empty tuple of integers (velocity indices), got {x!r}")
    return tuple(int(i) for i in items)


def check_rest_indices(con: Any, system: Any) -> None:
    """A rest condition's indices must name minimal velocities of ``system``."""
    n = system.n_velocities
    bad = [i for i in con.indices if not -n <= i < n]
    if bad:
        raise ValueError(
            f"{type(con).__name__}: 'indices' {bad} out of range: {type(system).__name__} has {n} "
            "minimal velocities (system.velocities_from_qdot)"
        )


def _rest_residual(con: Any, system: Any, obs: Any) -> Array:
    check_rest_indices(con, system)
    v = system.velocities_from_qdot(obs.q, obs.qdot)
    return v[jnp.asarray(con.indices, int)]


def _user_residual(con: Any, r: Any) -> Array:
    r = jnp.atleast_1d(r)
    if r.ndim != 1:
        raise ValueError(f"{type(con).__name__}: 'fn' must return a scalar or a vector, got shape {r.shape}")
    return r


def _check_fn(con: Any, n_args: int, signature: str) -> None:
    """``con.fn`` callable with ``n_args`` positional arguments (where Python can tell)."""
    if not callable(con.fn):
        raise TypeError(f"{type(con).__name__}: 'fn' must be a function {signature}, got {con.fn!r}")
    try:
        sig = inspect.signature(con.fn)
    except (TypeError, ValueError):  # a builtin without a signature: not checked
        return
    try:
        sig.bind(*range(n_args))
    except TypeError as err:
        raise TypeError(
            f"{type(con).__name__}: 'fn' must take {n_args} arguments {signature}; {con.fn!r} {err}"
        ) from None


def _pose_goal(x: Any) -> Array:
    """A goal pose as a float array (integers converted), or a ``TypeError`` naming ``goal``."""
    if isinstance(x, (jax.Array, jax.core.Tracer)):
        return x if jnp.issubdtype(x.dtype, jnp.floating) else x.astype(jnp.result_type(float))
    try:
        return asarray(np.asarray(x, float))
    except (TypeError, ValueError):
        raise TypeError(f"TerminalPose: 'goal' must be a pose (x, y, theta) of numbers, got {x!r}") from None


class AbstractConstraint(eqx.Module):
    """A constraint; its ``weight`` (a field of every concrete constraint) is its weight in the
    penalty form (:meth:`Task.loss`)."""

    def __check_init__(self):
        weight = getattr(self, "weight", None)  # a constraint of a user's may have none
        if weight is not None:
            check_known(type(self).__name__, "weight", weight, positive=False)

    def penalty(self, r: Array) -> Array:
        """The penalty of the residual ``r`` (equalities: ``weight |r|^2``)."""
        return self.weight * jnp.sum(r**2)


class AbstractTerminalConstraint(AbstractConstraint):
    """An equality ``residual(system, node_N, q0) = 0`` at the last node."""

    @abc.abstractmethod
    def residual(self, system: Any, obs: Any, q0: Array) -> Float[Array, " k"]: ...


class AbstractPathConstraint(AbstractConstraint):
    """An inequality ``residual(system, t_k, node_k, c_k) <= 0`` at every node ``k = 0 .. N``."""

    @abc.abstractmethod
    def residual(self, system: Any, t: Array, obs: Any, c: Array) -> Float[Array, " k"]: ...

    def penalty(self, r: Array) -> Array:
        return self.weight * jnp.sum(jnp.maximum(r, 0.0) ** 2)


class AbstractInitialConstraint(AbstractConstraint):
    """An equality ``residual(system, node_0, c_0) = 0`` on a free (periodic) start."""

    @abc.abstractmethod
    def residual(self, system: Any, obs: Any, c: Array) -> Float[Array, " k"]: ...


class TerminalPose(AbstractTerminalConstraint):
    """The pose at ``t_N`` equals ``goal = (x, y, theta)``: ``log(g_goal^-1 g_N) = 0``
    (:func:`pose_error`). Penalty: ``w_heading e_1^2 + w_position (e_2^2 + e_3^2)``."""

    goal: Float[Array, " 3"] = eqx.field(converter=_pose_goal)
    w_heading: Array = eqx.field(default=1.0, converter=asarray)
    w_position: Array = eqx.field(default=1.0, converter=asarray)

    def __check_init__(self):
        for name in ("w_heading", "w_position"):
            check_known("TerminalPose", name, getattr(self, name), positive=False)
        if self.goal.shape != (3,):
            raise ValueError(
                f"TerminalPose: 'goal' must be a pose (x, y, theta), got shape {self.goal.shape}"
            )

    @property
    def weight(self) -> Array:  # type: ignore[override]
        return self.w_position

    def residual(self, system, obs, q0):
        return pose_error(obs.q, self.goal)

    def penalty(self, r):
        return self.w_heading * r[0] ** 2 + self.w_position * (r[1] ** 2 + r[2] ** 2)

    def terminal(self, system, obs, q0):
        """The penalty at the node (the form :class:`AbstractTerm` uses)."""
        return self.penalty(self.residual(system, obs, q0))


class TerminalRest(AbstractTerminalConstraint):
    """The minimal velocities ``v = system.velocities_from_qdot(q, qdot)`` with indices
    ``indices`` vanish at ``t_N`` (the car's wheel rate ``(0,)``; the snakeboard's board speed
    ``s``, ``(2,)``). An index outside the system's minimal velocities is an error.
    ``weight``: its penalty weight in ``optimize`` (default 1; ``solve`` holds it exactly)."""

    indices: tuple[int, ...] = eqx.field(static=True, converter=_indices)
    weight: Array = eqx.field(default=1.0, converter=asarray)

    def residual(self, system, obs, q0=None):
        return _rest_residual(self, system, obs)

    def terminal(self, system, obs, q0):
        return self.penalty(self.residual(system, obs, q0))


class NetDisplacement(AbstractTerminalConstraint):
    """A prescribed net displacement from ``q_0`` to ``q_N``: any subset of ``dx``, ``dy`` (m, in
    the body frame of ``q_0``) and ``dtheta`` (rad, not wrapped) given (:func:`displacement`); for
    a gait, the displacement per cycle.

    Args:
        dx, dy, dtheta: the targets; ``None`` leaves a component free.
        weight: penalty weight in ``optimize`` (default 1; ``solve`` holds the constraint exactly).
    """

    target: Float[Array, " k"]
    components: tuple[int, ...] = eqx.field(static=True)
    weight: Array = eqx.field(default=1.0, converter=asarray)

    def __init__(self, dx=None, dy=None, dtheta=None, *, weight: ArrayLike = 1.0):
        given = [(i, x) for i, x in enumerate((dx, dy, dtheta)) if x is not None]
        if not given:
            raise ValueError("NetDisplacement: give at least one of 'dx', 'dy', 'dtheta'")
        self.components = tuple(i for i, _ in given)
        real = jnp.result_type(float)
        if any(isinstance(x, jax.core.Tracer) for _, x in given):
            self.target = jnp.stack([jnp.asarray(x, real) for _, x in given])
        else:  # known values on the host (an eager stack is a compilation in a new process)
            self.target = asarray(np.stack([np.asarray(x, real) for _, x in given]))
        if self.target.ndim != 1:
            raise ValueError(f"NetDisplacement: each target must be a scalar, got shape {self.target.shape}")
        if is_concrete(self.target) and not np.all(np.isfinite(np.asarray(self.target))):
            raise ValueError(f"NetDisplacement: the targets must be finite, got {np.asarray(self.target)}")
        self.weight = asarray(weight)

    def residual(self, system, obs, q0):
        return displacement(obs.q, q0)[jnp.asarray(self.components)] - self.target


class TerminalConstraint(AbstractTerminalConstraint):
    """A user equality ``fn(q_N, qdot_N) = 0`` at the last node (``fn`` returns a vector).
    ``weight``: its penalty weight in ``optimize`` (default 1; ``solve`` holds it exactly)."""

    fn: Callable
    weight: Array = eqx.field(default=1.0, converter=asarray)

    def __check_init__(self):
        _check_fn(self, 2, "fn(q, qdot)")

    def residual(self, system, obs, q0):
        return _user_residual(self, self.fn(obs.q, obs.qdot))


class PathConstraint(AbstractPathConstraint):
    """A user inequality ``fn(t, q, qdot, c) <= 0`` at every node (``fn`` returns a scalar or a
    vector): an obstacle (``r^2 - |p - p_obs|^2 <= 0``), a speed limit, a state-dependent
    control bound. Held at the nodes; between them the motion is not checked.
    ``weight``: its penalty weight in ``optimize`` (default 1; ``solve`` holds it exactly)."""

    fn: Callable
    weight: Array = eqx.field(default=1.0, converter=asarray)

    def __check_init__(self):
        _check_fn(self, 4, "fn(t, q, qdot, c)")

    def residual(self, system, t, obs, c):
        return _user_residual(self, self.fn(t, obs.q, obs.qdot, c))


class InitialRest(AbstractInitialConstraint):
    """The minimal velocities with indices ``indices`` vanish at the (free) start: the anchor of
    a periodic gait (the snakeboard's board speed ``s``: ``(2,)``; the car's wheel rate: ``(0,)``).
    ``weight``: its penalty weight in ``optimize`` (default 1; ``solve`` holds it exactly)."""

    indices: tuple[int, ...] = eqx.field(static=True, converter=_indices)
    weight: Array = eqx.field(default=1.0, converter=asarray)

    def residual(self, system, obs, c):
        return _rest_residual(self, system, obs)


class InitialConstraint(AbstractInitialConstraint):
    """A user equality ``fn(q_0, qdot_0, c_0) = 0`` on the (free) start.
    ``weight``: its penalty weight in ``optimize`` (default 1; ``solve`` holds it exactly)."""

    fn: Callable
    weight: Array = eqx.field(default=1.0, converter=asarray)

    def __check_init__(self):
        _check_fn(self, 3, "fn(q, qdot, c)")

    def residual(self, system, obs, c):
        return _user_residual(self, self.fn(obs.q, obs.qdot, c))


def cyclic_names(cyclic, where: str = "lc.Periodic") -> tuple[str, ...]:
    """``cyclic`` as a tuple of coordinate names: one name, or several; a ``TypeError`` naming
    ``where`` for anything else."""
    names = (cyclic,) if isinstance(cyclic, str) else tuple(cyclic)
    if not all(isinstance(n, str) for n in names):
        raise TypeError(f"{where}: 'cyclic' must be a tuple of shape coordinate names, got {cyclic!r}")
    return names


class Periodic(AbstractConstraint):
    """The boundary condition of a gait: one period ``[0, T]``, with the start free.

    The start's group element is the identity (the symmetry) and the ``cyclic`` shape
    coordinates (by name; e.g. a rotor or wheel angle, which nothing depends on) start at 0;
    the rest of the start's reduced state is a decision variable. At ``t_N = T`` the reduced
    state (the non-cyclic shape, and the momenta that the next step reads) and the controls
    equal those at ``t_0``; the group moves by the net displacement per cycle, and the cyclic
    coordinates drift freely.

    Args:
        cyclic: names of the cyclic shape coordinates (default: none).
        weight: penalty weight of the return conditions in ``optimize`` (default 1).
    """

    cyclic: tuple[str, ...] = eqx.field(static=True, default=(), converter=cyclic_names)
    weight: Array = eqx.field(default=1.0, converter=asarray)


class Bounds(eqx.Module):
    """Box bounds at the nodes: ``q_lower <= q_k <= q_upper`` and ``u_lower <= c_k <= u_upper``
    (physical units; infinite entries are off; lower and upper may differ in magnitude).

    Build by name with :meth:`of`, e.g. ``lc.Bounds.of(lj.Snakeboard(), q={"phi": 1.0},
    u={"f_psi": 0.1, "f_phi": (-0.05, 0.1)})`` (a number ``b`` means ``[-b, b]``).

    Attributes:
        q_lower, q_upper: (d,). u_lower, u_upper: (n_controls,). weight: penalty weight (the
            penalty form: ``weight * h * (excess^2)`` summed over the nodes, controls scaled).
    """

    q_lower: Float[Array, " d"] = eqx.field(converter=asarray)
    q_upper: Float[Array, " d"] = eqx.field(converter=asarray)
    u_lower: Float[Array, " n"] = eqx.field(converter=asarray)
    u_upper: Float[Array, " n"] = eqx.field(converter=asarray)
    weight: Array = eqx.field(default=100.0, converter=asarray)

    def __check_init__(self):
        check_known("Bounds", "weight", self.weight, positive=False)

    @classmethod
    def of(cls, system, *, q: dict | None = None, u: dict | None = None, weight: float = 100.0) -> Bounds:
        """Bounds named by coordinate (``x``, ``y``, ``theta`` and ``system.shape_names``) and
        control channel (``system.control_names``); each value ``b`` (``[-b, b]``) or ``(lo, hi)``.

        Raises:
            ValueError: an unknown name, or ``lo >= hi``.
        """
        coords = ("x", "y", "theta", *system.shape_names)
        for what, spec in (("q", q), ("u", u)):
            if spec is not None and not isinstance(spec, dict):
                raise TypeError(f"Bounds.of: '{what}' must be a dict of bounds by name, got {spec!r}")
        q_lo, q_hi = _by_name("q", q or {}, coords)
        u_lo, u_hi = _by_name("u", u or {}, tuple(system.control_names))
        return cls(asarray(q_lo), asarray(q_hi), asarray(u_lo), asarray(u_hi), weight)

    def penalty(self, q: Array, c: Array, scale: Array, h: Array) -> Array:
        """``weight * h * (bound_penalty(q) + bound_penalty(c / scale))`` at one node."""
        pen = bound_penalty(q, self.q_lower, self.q_upper)
        pen = pen + bound_penalty(c / scale, self.u_lower / scale, self.u_upper / scale)
        return self.weight * h * pen


def per_channel(arg: str, names: tuple[str, ...], value: Any) -> dict:
    """``{name: bound}`` for each of ``names`` from ``value``: one bound for every channel (a
    number ``b`` or a pair ``(lo, hi)`` when there is one channel) or a sequence of one bound per
    channel; anything else is a ``ValueError`` naming ``arg``."""
    try:
        items = list(value)
    except TypeError:  # a number (or a 0-d array): every channel
        return dict.fromkeys(names, value)
    if len(names) == 1 and len(items) == 2 and all(np.ndim(x) == 0 for x in items):
        return dict.fromkeys(names, value)
    if len(items) != len(names):
        raise ValueError(
            f"'{arg}' must be one bound for every channel or one per channel {names}, got {value!r}"
        )
    return dict(zip(names, items))


def _by_name(what: str, spec: dict, names: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = np.full(len(names), -np.inf), np.full(len(names), np.inf)
    for key, value in spec.items():
        if key not in names:
            raise ValueError(f"Bounds: unknown {what} name {key!r}; the names are {names}")
        try:
            if np.ndim(value) == 0:
                a, b = -float(value), float(value)
            elif np.shape(value) == (2,):
                a, b = float(value[0]), float(value[1])
            else:
                raise ValueError
        except (TypeError, ValueError):
            raise ValueError(
                f"Bounds: the {what} bound of {key!r} must be a number b ([-b, b]) or a pair "
                f"(lo, hi), got {value!r}"
            ) from None
        if not a < b:
            raise ValueError(f"Bounds: the {what} bound of {key!r} must have lower < upper, got ({a}, {b})")
        i = names.index(key)
        lo[i], hi[i] = a, b
    return lo, hi
