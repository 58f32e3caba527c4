"""Integrators: each a pure ``init`` / ``step`` / ``observe`` over a system description."""

from ._base import AbstractAlphaIntegrator as AbstractAlphaIntegrator
from ._base import AbstractIntegrator as AbstractIntegrator
from ._base import StepInfo as StepInfo
from ._composition import SCHEMES as SCHEMES
from ._dla import DLA as DLA
from ._dla import DLAState as DLAState
from ._gni import GNI as GNI
from ._gni import GNIState as GNIState
from ._rdp import RDP as RDP
from ._rdp import RDPState as RDPState
from ._runge_kutta import RK2 as RK2
from ._runge_kutta import RK4 as RK4
from ._runge_kutta import AbstractRungeKutta as AbstractRungeKutta
from ._runge_kutta import ButcherTableau as ButcherTableau
