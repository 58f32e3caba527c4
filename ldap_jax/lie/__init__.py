"""Lie groups: SE(2) with the retractions and inverse differentials of the paper (App. A, B)."""

from ._se2 import SE2 as SE2
from ._se2 import ad as ad
from ._se2 import cay as cay
from ._se2 import cay_inv as cay_inv
from ._se2 import compose as compose
from ._se2 import dcay_inv as dcay_inv
from ._se2 import dexp_inv as dexp_inv
from ._se2 import dtau_inv as dtau_inv
from ._se2 import exp as exp
from ._se2 import hat as hat
from ._se2 import log as log
from ._se2 import retract as retract
from ._se2 import vee as vee
