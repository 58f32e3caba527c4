"""Two systems the paper does not treat, written only through the public :class:`System`."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .._compilation_cache import asarray
from ._description import System

__all__ = ["chaplygin_sleigh", "roller_racer"]


def _positive(**kwargs) -> dict:
    """The parameters as float arrays, each a real, positive and finite number (the message names
    a bad one: ``TypeError`` for a non-number, ``ValueError`` for a value out of range)."""
    out = {}
    for name, value in kwargs.items():
        if isinstance(value, (bool, str, bytes)) or value is None:
            raise TypeError(f"parameter {name!r} must be a positive number, got {value!r}")
        if isinstance(value, jax.core.Tracer):  # a traced parameter (vmap, grad): not checked here
            out[name] = jnp.asarray(value, dtype=jnp.result_type(float))
            continue
        try:
            arr = np.asarray(value)
        except (TypeError, ValueError) as err:  # pragma: no cover - ragged input
            raise TypeError(f"parameter {name!r} must be a positive number, got {value!r}") from err
        if arr.dtype.kind not in "iuf":
            raise TypeError(f"parameter {name!r} must be a positive number, got {value!r}")
        if not np.all(np.isfinite(arr) & (arr > 0)):
            raise ValueError(f"parameter {name!r} must be positive and finite, got {value}")
        out[name] = asarray(value, dtype=jnp.result_type(float))  # no eager program
    return out


def chaplygin_sleigh(m: float = 1.0, I: float = 0.2, a: float = 0.3) -> System:  # noqa: E741
    r"""The Chaplygin sleigh: a rigid body on a knife edge, ``Q = SE(2)``, no shape.

    ``g = (x, y, theta)`` is the pose of the knife edge's contact point ``P``; the centre of mass
    sits at distance ``a`` ahead of ``P`` on the body axis. With ``xi = (omega, v_x, v_y)`` at ``P``::

        l(xi) = (m v_x^2 + m (v_y + a omega)^2 + I omega^2) / 2,     constraint  v_y = 0,

    so both remaining symmetry directions are constrained symmetries,
    ``e(r) = [(1, 0, 0), (0, 1, 0)]`` (``c = 2``), and the dynamics is the momentum equation (7)
    alone: ``v_x_dot = a omega^2``, ``(I + m a^2) omega_dot = -m a v_x omega``. Energy is conserved.

    Args:
        m: mass (kg, default 1). I: yaw inertia about the centre of mass (kg m^2, default 0.2).
            a: distance from the contact point to the centre of mass (m, default 0.3). All positive.
    """
    p = _positive(m=m, I=I, a=a)

    def lagrangian(p, r, u, xi):
        return 0.5 * (p["m"] * xi[1] ** 2 + p["m"] * (xi[2] + p["a"] * xi[0]) ** 2 + p["I"] * xi[0] ** 2)

    def connection(p, r):
        return jnp.zeros((3, 0), r.dtype)

    def symmetry_basis(p, r):
        return jnp.eye(3, 2, dtype=r.dtype)

    def constraints(p, r):
        return jnp.array([[0.0, 0.0, 1.0]], dtype=r.dtype)

    return System(0, lagrangian, connection, symmetry_basis, constraints, params=p)


def roller_racer(
    m1: float = 1.0,
    I1: float = 0.1,  # noqa: E741
    m2: float = 0.5,
    I2: float = 0.05,  # noqa: E741
    d1: float = 0.5,
    d2: float = 0.3,
    k: float = 1.0,
    drag: float | None = None,
) -> System:
    r"""The roller racer: two wheeled bodies joined by a torque-driven, spring-loaded hinge.

    ``g = (x, y, theta)`` is the pose of the front body at its wheel axle (its centre of mass).
    The hinge sits ``d1`` ahead of it; the rear body, at relative angle ``phi`` (the shape), has
    its wheel axle (and centre of mass) ``d2`` behind the hinge. Neither axle slips sideways.
    In the front body's frame, with ``xi = (omega, v_x, v_y)``, the rear axle moves with
    ``v_2 = (v_x + d2 (omega + phidot) sin phi, v_y + d1 omega - d2 (omega + phidot) cos phi)``, and::

        l = (m1 (v_x^2 + v_y^2) + I1 omega^2 + m2 |v_2|^2 + I2 (omega + phidot)^2 - k phi^2) / 2,
        constraints:  v_y = 0,   (d1 cos phi - d2) omega - sin(phi) v_x + cos(phi) v_y - d2 phidot = 0.

    Constrained symmetry ``e_1(phi) = (sin phi, d1 cos phi - d2, 0)`` (``c = 1``); horizontal lift
    ``A(phi) = -d2 (d1 cos phi - d2, -sin phi, 0) / ((d1 cos phi - d2)^2 + sin^2 phi)`` (regular for
    ``d1 != d2``). The control is the hinge torque ``f_phi``; oscillating it propels the racer (a
    snakeboard-like gait with a different connection, and a potential ``k phi^2 / 2`` so that
    ``d_r l != 0``).

    Without friction the racer has no periodic motion but coasting: its momentum obeys
    ``p' = a(phi) phidot p + beta(phi) phidot^2`` with ``beta > 0`` (no torque in it), so
    ``exp(-int_0^phi a) p`` grows over every cycle in which the hinge moves. With ``drag``, a
    viscous rolling resistance of both axles along their bodies,
    ``R = drag (v_x^2 + (v_2 . (cos phi, sin phi))^2) / 2``, pumping and drag balance on limit
    cycles: the racer has gaits (``lc.make_gait``).

    Args:
        m1, I1: mass and yaw inertia of the front body (kg, kg m^2; defaults 1 and 0.1).
        m2, I2: of the rear body (defaults 0.5 and 0.05).
        d1, d2: front axle to hinge, hinge to rear axle (m, ``d1 != d2``; defaults 0.5 and 0.3).
        k: hinge stiffness (N m/rad, default 1).
        drag: rolling-resistance coefficient (N s/m, positive), or ``None`` (default): no friction.
    """
    p = _positive(m1=m1, I1=I1, m2=m2, I2=I2, d1=d1, d2=d2, k=k)
    if drag is not None:
        p |= _positive(drag=drag)
    if all(not isinstance(x, jax.core.Tracer) for x in (d1, d2)) and np.any(
        np.isclose(np.asarray(d1), np.asarray(d2))
    ):
        raise ValueError(
            f"parameters 'd1' and 'd2' must differ (the lift is singular at phi = 0), got {d1}, {d2}"
        )

    def rear_axle(p, r, u, xi):
        """The rear axle's velocity in the front body's frame."""
        phi, phidot = r[0], u[0]
        om, vx, vy = xi
        w2 = om + phidot
        return vx + p["d2"] * w2 * jnp.sin(phi), vy + p["d1"] * om - p["d2"] * w2 * jnp.cos(phi)

    def lagrangian(p, r, u, xi):
        phi, phidot = r[0], u[0]
        om, vx, vy = xi
        w2 = om + phidot
        v2x, v2y = rear_axle(p, r, u, xi)
        kinetic = p["m1"] * (vx**2 + vy**2) + p["I1"] * om**2 + p["m2"] * (v2x**2 + v2y**2) + p["I2"] * w2**2
        return 0.5 * (kinetic - p["k"] * phi**2)

    def connection(p, r):
        phi = r[0]
        c = p["d1"] * jnp.cos(phi) - p["d2"]
        den = c**2 + jnp.sin(phi) ** 2
        return (-p["d2"] / den * jnp.stack([c, -jnp.sin(phi), jnp.zeros_like(phi)]))[:, None]

    def symmetry_basis(p, r):
        phi = r[0]
        return jnp.stack([jnp.sin(phi), p["d1"] * jnp.cos(phi) - p["d2"], jnp.zeros_like(phi)])[:, None]

    def constraints(p, r):
        phi = r[0]
        z, o = jnp.zeros_like(phi), jnp.ones_like(phi)
        return jnp.array(
            [[z, z, o, z], [p["d1"] * jnp.cos(phi) - p["d2"], -jnp.sin(phi), jnp.cos(phi), -p["d2"] * o]]
        )

    def dissipation(p, r, u, xi):
        v2x, v2y = rear_axle(p, r, u, xi)
        along = v2x * jnp.cos(r[0]) + v2y * jnp.sin(r[0])
        return 0.5 * p["drag"] * (xi[1] ** 2 + along**2)

    return System(
        1,
        lagrangian,
        connection,
        symmetry_basis,
        constraints,
        params=p,
        shape_names=("phi",),
        dissipation=None if drag is None else dissipation,
    )
