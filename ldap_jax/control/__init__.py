"""Discrete optimal control through the library's integrators: costs on SE(2) as composable terms,
control parameterizations, tasks with hard constraints, a jitted interior-point solver
(:func:`solve`), optax loops on the penalty form (:func:`optimize`), and the car/snakeboard tasks
(parallel parking, U-turn, gaits, reach)."""

from ._costs import AbstractTerm as AbstractTerm
from ._costs import BoundPenalty as BoundPenalty
from ._costs import Effort as Effort
from ._costs import Forward as Forward
from ._costs import Node as Node
from ._costs import TerminalPose as TerminalPose
from ._costs import TerminalRest as TerminalRest
from ._costs import bound_penalty as bound_penalty
from ._costs import effort_cost as effort_cost
from ._costs import pose_error as pose_error
from ._costs import wrap_angle as wrap_angle
from ._ipm import SOLVER_RESULTS as SOLVER_RESULTS
from ._optimize import OptimizeResult as OptimizeResult
from ._optimize import best_of as best_of
from ._optimize import default_optimizer as default_optimizer
from ._optimize import multistart as multistart
from ._optimize import optimize as optimize
from ._parameterizations import AbstractParameterization as AbstractParameterization
from ._parameterizations import SampledControls as SampledControls
from ._parameterizations import SinusoidGait as SinusoidGait
from ._solve import Solution as Solution
from ._solve import curvature_integrator as curvature_integrator
from ._solve import solve as solve
from ._tasks import TASKS as TASKS
from ._tasks import Penalty as Penalty
from ._tasks import Task as Task
from ._tasks import forward_gait as forward_gait
from ._tasks import gradient_memory as gradient_memory
from ._tasks import make_task as make_task
from ._tasks import parallel_park as parallel_park
from ._tasks import reach as reach
from ._tasks import replay as replay
from ._tasks import u_turn as u_turn
