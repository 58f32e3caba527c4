"""Discrete optimal control through the library's integrators.

Problems are written from public pieces: objective terms (:class:`Effort`, :class:`Displacement`,
:class:`Rotation`, ...), constraint terms (:class:`TerminalPose`, :class:`NetDisplacement`,
:class:`PathConstraint`, the gait boundary condition :class:`Periodic`, ...), :class:`Bounds` and
:func:`make_task` (or :func:`make_gait`). :func:`solve` holds every constraint exactly (a jitted
primal-dual interior-point method with Riccati steps; sensitivities by the implicit function
theorem); :func:`optimize` minimises the penalty form with optax. Built-in tasks: the car's
:func:`parallel_park`, :func:`u_turn` and :func:`sideways_gait`, the snakeboard's :func:`reach`,
:func:`drive_gait` and :func:`turn_gait`, the roller racer's :func:`racer_gait`.
"""

from ._build import make_task as make_task
from ._constraints import AbstractConstraint as AbstractConstraint
from ._constraints import AbstractInitialConstraint as AbstractInitialConstraint
from ._constraints import AbstractPathConstraint as AbstractPathConstraint
from ._constraints import AbstractTerminalConstraint as AbstractTerminalConstraint
from ._constraints import Bounds as Bounds
from ._constraints import InitialConstraint as InitialConstraint
from ._constraints import InitialRest as InitialRest
from ._constraints import NetDisplacement as NetDisplacement
from ._constraints import PathConstraint as PathConstraint
from ._constraints import Periodic as Periodic
from ._constraints import TerminalConstraint as TerminalConstraint
from ._constraints import TerminalPose as TerminalPose
from ._constraints import TerminalRest as TerminalRest
from ._gait_analysis import cycle_map as cycle_map
from ._gait_analysis import floquet as floquet
from ._gait_analysis import monodromy as monodromy
from ._gait_analysis import replay_gait as replay_gait
from ._gaits import drive_gait as drive_gait
from ._gaits import make_gait as make_gait
from ._gaits import racer_gait as racer_gait
from ._gaits import sideways_gait as sideways_gait
from ._gaits import turn_gait as turn_gait
from ._ipm import SOLVER_RESULTS as SOLVER_RESULTS
from ._optimize import OptimizeResult as OptimizeResult
from ._optimize import best_of as best_of
from ._optimize import default_optimizer as default_optimizer
from ._optimize import multistart as multistart
from ._optimize import optimize as optimize
from ._parameterizations import AbstractParameterization as AbstractParameterization
from ._parameterizations import PeriodicControls as PeriodicControls
from ._parameterizations import SampledControls as SampledControls
from ._parameterizations import SinusoidGait as SinusoidGait
from ._replay import gradient_memory as gradient_memory
from ._replay import replay as replay
from ._solve import Solution as Solution
from ._solve import curvature_integrator as curvature_integrator
from ._solve import solve as solve
from ._task import GaitParams as GaitParams
from ._task import Guess as Guess
from ._task import Task as Task
from ._tasks import forward_gait as forward_gait
from ._tasks import parallel_park as parallel_park
from ._tasks import reach as reach
from ._tasks import u_turn as u_turn
from ._terms import AbstractTerm as AbstractTerm
from ._terms import Displacement as Displacement
from ._terms import Effort as Effort
from ._terms import Forward as Forward
from ._terms import Node as Node
from ._terms import Rotation as Rotation
from ._terms import bound_penalty as bound_penalty
from ._terms import displacement as displacement
from ._terms import effort_cost as effort_cost
from ._terms import pose_error as pose_error
from ._terms import wrap_angle as wrap_angle
from ._tracker import GaitTracker as GaitTracker
from ._tracker import gait_tracker as gait_tracker

TASKS = {
    ("car", "parallel_park"): parallel_park,
    ("car", "u_turn"): u_turn,
    ("car", "sideways_gait"): sideways_gait,
    ("snakeboard", "forward_gait"): forward_gait,
    ("snakeboard", "reach"): reach,
    ("snakeboard", "drive_gait"): drive_gait,
    ("snakeboard", "turn_gait"): turn_gait,
    ("roller_racer", "racer_gait"): racer_gait,
}
