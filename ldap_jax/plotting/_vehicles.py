"""Vehicle outlines: the car, the snakeboard and a generic pose marker, as polygons and lines in
the plane, for static figures and animations alike."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Literal, NamedTuple

import numpy as np
from matplotlib.artist import Artist
from matplotlib.axes import Axes
from matplotlib.lines import Line2D
from matplotlib.patches import Polygon

from ..systems import AbstractSystem, Car, Snakeboard

__all__ = ["Part", "rectangle", "vehicle_parts", "vehicle_size", "draw_vehicle", "VehicleArtists"]


class Part(NamedTuple):
    """One piece of a vehicle drawing.

    Attributes:
        xy: vertices in the plane (k, 2) (m): a closed polygon for ``"outline"``/``"solid"``,
            an open polyline for ``"line"``.
        kind: ``"outline"`` (edge only), ``"solid"`` (filled) or ``"line"``.
    """

    xy: np.ndarray
    kind: Literal["outline", "solid", "line"] = "outline"


#: A custom drawing: configuration ``q`` (d,) -> parts. The number and kinds of the parts must
#: not depend on ``q`` (animations update them in place).
Drawer = Callable[[np.ndarray], Sequence[Part]]


def rectangle(cx: float, cy: float, heading: float, length: float, width: float) -> np.ndarray:
    """Corners (4, 2) of a rectangle centred at ``(cx, cy)`` (m), its length along ``heading``
    (rad), for :class:`Part`."""
    c, s = np.cos(heading), np.sin(heading)
    pts = 0.5 * np.array([[length, width], [-length, width], [-length, -width], [length, -width]])
    return pts @ np.array([[c, s], [-s, c]]) + np.array([cx, cy])


def _segment(x0: float, y0: float, x1: float, y1: float) -> np.ndarray:
    return np.array([[x0, y0], [x1, y1]])


def vehicle_size(system: AbstractSystem) -> float:
    """The vehicle's drawn length (m): the car's body, the snakeboard's board; 0.3 m otherwise."""
    if isinstance(system, Car):
        return 1.3 * float(system.l)
    if isinstance(system, Snakeboard):
        return 2.3 * float(system.l)
    return 0.3


def _car(system: Car, q: np.ndarray, scale: float) -> list[Part]:
    x, y, th, sigma = float(q[0]), float(q[1]), float(q[2]), float(q[4])
    c, s = np.cos(th), np.sin(th)
    ell = float(system.l) * scale
    width, wheel = 0.5 * ell, 0.3 * ell
    steer = np.arctan(sigma)
    parts = [Part(rectangle(x + c * ell / 2, y + s * ell / 2, th, 1.3 * ell, width), "outline")]
    # axles, then the rear wheels (along the body) and the front wheels (steered by atan(sigma))
    for ax_pos in (0.0, ell):
        cx, cy = x + c * ax_pos, y + s * ax_pos
        parts.append(
            Part(
                _segment(cx + s * width / 2, cy - c * width / 2, cx - s * width / 2, cy + c * width / 2),
                "line",
            )
        )
    for ax_pos, heading in ((0.0, th), (ell, th + steer)):
        for side in (-1.0, 1.0):
            wx = x + c * ax_pos - s * side * width / 2
            wy = y + s * ax_pos + c * side * width / 2
            parts.append(Part(rectangle(wx, wy, heading, wheel, wheel / 3), "solid"))
    return parts


def _snakeboard(system: Snakeboard, q: np.ndarray, scale: float) -> list[Part]:
    x, y, th, psi, phi = (float(v) for v in q[:5])
    c, s = np.cos(th), np.sin(th)
    ell = float(system.l) * scale
    parts = [Part(rectangle(x, y, th, 2.3 * ell, 0.22 * ell), "outline")]
    # wheel sets: at -l steered by +phi, at +l steered by -phi (the constraints' geometry)
    track, wheel = 0.5 * ell, 0.22 * ell
    for pos, steer in ((-ell, phi), (ell, -phi)):
        cx, cy = x + c * pos, y + s * pos
        hd = th + steer
        ch, sh = np.cos(hd), np.sin(hd)
        parts.append(
            Part(
                _segment(cx + sh * track / 2, cy - ch * track / 2, cx - sh * track / 2, cy + ch * track / 2),
                "line",
            )
        )
        for side in (-1.0, 1.0):
            parts.append(
                Part(
                    rectangle(cx - sh * side * track / 2, cy + ch * side * track / 2, hd, wheel, wheel / 2.5),
                    "solid",
                )
            )
    # the rotor: a disc with a spoke at angle theta + psi (its spin is visible)
    ang = np.linspace(0.0, 2 * np.pi, 25)
    r = 0.3 * ell
    parts.append(Part(np.stack([x + r * np.cos(ang), y + r * np.sin(ang)], axis=1), "outline"))
    parts.append(Part(_segment(x, y, x + r * np.cos(th + psi), y + r * np.sin(th + psi)), "line"))
    return parts


def _pose_marker(q: np.ndarray, scale: float) -> list[Part]:
    x, y, th = float(q[0]), float(q[1]), float(q[2])
    size = 0.3 * scale
    c, s = np.cos(th), np.sin(th)
    tri = np.array([[size / 2, 0.0], [-size / 2, size / 3], [-size / 2, -size / 3]])
    return [Part(tri @ np.array([[c, s], [-s, c]]) + np.array([x, y]), "outline")]


def vehicle_parts(
    system: AbstractSystem, q: np.ndarray, *, scale: float = 1.0, vehicle: Drawer | None = None
) -> list[Part]:
    """The vehicle at configuration ``q = (x, y, theta, r...)`` as :class:`Part` s.

    Car: body from the rear axle ``(x, y)`` forward, rear wheels along the body, front wheels
    (at ``l``) steered by ``atan(sigma)``. Snakeboard: the board (length ``2 l`` between the
    wheel sets), the wheel set at ``-l`` steered by ``+phi`` and the one at ``+l`` by ``-phi``,
    the rotor as a disc with a spoke at ``theta + psi``. Other systems: a triangle (0.3 m x
    ``scale``) pointing along ``theta``.

    Args:
        system: the system (its type and lengths set the drawing).
        q: configuration (d,) (m, rad).
        scale: drawing scale (1: true size).
        vehicle: a custom drawing ``q -> parts`` (it then ignores ``scale``).

    Returns:
        The parts, in a fixed order and number for a given system.
    """
    q = np.asarray(q, dtype=float)
    if vehicle is not None:
        return [p if isinstance(p, Part) else Part(np.asarray(p[0], float), p[1]) for p in vehicle(q)]
    if isinstance(system, Car):
        return _car(system, q, scale)
    if isinstance(system, Snakeboard):
        return _snakeboard(system, q, scale)
    return _pose_marker(q, scale)


class VehicleArtists:
    """The artists of one vehicle drawing, updatable in place (for animations).

    Args:
        ax: axes to draw into.
        parts: the initial parts (:func:`vehicle_parts`).
        color: colour of every part.
        alpha: opacity.
        lw: line width of outlines and lines (points).
        zorder: drawing order.
        label: legend label (given to the first part).
    """

    def __init__(
        self,
        ax: Axes,
        parts: Sequence[Part],
        *,
        color: str = "k",
        alpha: float = 1.0,
        lw: float = 1.2,
        zorder: float = 4,
        label: str | None = None,
    ):
        self.artists: list[Artist] = []
        for i, part in enumerate(parts):
            lab = label if i == 0 else None
            if part.kind == "line":
                (art,) = ax.plot(
                    part.xy[:, 0], part.xy[:, 1], color=color, alpha=alpha, lw=lw, zorder=zorder, label=lab
                )
            else:
                solid = part.kind == "solid"
                art = Polygon(
                    part.xy,
                    closed=True,
                    fill=solid,
                    facecolor=color if solid else "none",
                    edgecolor=color,
                    alpha=alpha,
                    lw=0.5 if solid else lw,
                    zorder=zorder,
                    label=lab,
                )
                ax.add_patch(art)
            self.artists.append(art)

    def update(self, parts: Sequence[Part] | None) -> None:
        """Move the drawing to ``parts``; ``None`` hides it (e.g. after a failure)."""
        for art, part in zip(self.artists, parts or [None] * len(self.artists)):
            if part is None:
                art.set_visible(False)
                continue
            art.set_visible(True)
            if isinstance(art, Line2D):
                art.set_data(part.xy[:, 0], part.xy[:, 1])
            else:
                art.set_xy(part.xy)


def draw_vehicle(
    ax: Axes,
    system: AbstractSystem,
    q: np.ndarray,
    *,
    color: str = "k",
    alpha: float = 1.0,
    scale: float = 1.0,
    lw: float = 1.2,
    vehicle: Drawer | None = None,
    label: str | None = None,
) -> list[Artist]:
    """Draw the vehicle at configuration ``q = (x, y, theta, r1, r2, ...)`` (m, rad).

    See :func:`vehicle_parts` for the drawings (car with steered front wheels; snakeboard with
    both wheel sets and the rotor; a pose triangle for other systems).

    Args:
        ax: matplotlib axes (equal aspect recommended).
        system: the system.
        q: configuration (d,).
        color: colour.
        alpha: opacity in [0, 1].
        scale: drawing scale (1: true size).
        lw: outline width (points).
        vehicle: custom drawing ``q -> parts`` (:class:`Part`).
        label: legend label.

    Returns:
        The matplotlib artists drawn.
    """
    parts = vehicle_parts(system, q, scale=scale, vehicle=vehicle)
    return VehicleArtists(ax, parts, color=color, alpha=alpha, lw=lw, label=label).artists
