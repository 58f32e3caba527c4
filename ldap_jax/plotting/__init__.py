"""Matplotlib figures and GIF animations of ldap_jax trajectories.

Imported only where used (``import ldap_jax.plotting``), so the core imports without matplotlib.
Every figure function returns the :class:`matplotlib.figure.Figure` (or draws into given axes);
every axis is labelled with units (SI: m, rad, s, J).

* Paths: :func:`plot_paths` (vehicles drawn small and sparse, start and end marked),
  :func:`plot_position_error` (error against a reference over time), :func:`draw_vehicle`.
* Diagnostics: :func:`plot_diagnostics` (energy and work, the energy balance, the momentum, one
  row per system), :func:`plot_energy_error` (long-run ``|E - E0 - W|``).
* Accuracy: :func:`plot_convergence` (error against step, reference slopes),
  :func:`plot_work_precision` (error against runtime; takes a study's rows as they are).
* Gaits: :func:`plot_shape_loop` (shape-space loop, momentum, path), :func:`plot_gait_family`
  (a family's trade-off curve and efficiency).
* Animation: :func:`animate` (a GIF; in a notebook ``IPython.display.Image(filename=path)``).
"""

from ._animate import animate as animate
from ._animate import frame_indices as frame_indices
from ._common import style_for as style_for
from ._convergence import fitted_order as fitted_order
from ._convergence import plot_convergence as plot_convergence
from ._convergence import plot_work_precision as plot_work_precision
from ._convergence import study_curves as study_curves
from ._diagnostics import plot_diagnostics as plot_diagnostics
from ._diagnostics import plot_energy_error as plot_energy_error
from ._family import plot_gait_family as plot_gait_family
from ._paths import plot_paths as plot_paths
from ._paths import plot_position_error as plot_position_error
from ._shape import plot_shape_loop as plot_shape_loop
from ._vehicles import Part as Part
from ._vehicles import draw_vehicle as draw_vehicle
from ._vehicles import rectangle as rectangle
from ._vehicles import vehicle_parts as vehicle_parts

__all__ = [
    "animate",
    "draw_vehicle",
    "fitted_order",
    "frame_indices",
    "Part",
    "plot_convergence",
    "plot_diagnostics",
    "plot_gait_family",
    "plot_energy_error",
    "plot_paths",
    "plot_position_error",
    "plot_shape_loop",
    "plot_work_precision",
    "rectangle",
    "study_curves",
    "style_for",
    "vehicle_parts",
]
