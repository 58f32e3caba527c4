"""Lie groups: SE(2) with the retractions and inverse differentials of the paper (App. A, B).

Conventions (see :mod:`ldap_jax.lie._se2`): poses ``(x, y, theta)``, Lie-algebra vectors
``(omega, v_x, v_y)``, :class:`SE2` stored as jaxlie's ``(cos, sin, x, y)``.
"""

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
from ._se2 import inverse as inverse
from ._se2 import log as log
from ._se2 import retract as retract
from ._se2 import tangent_from_jaxlie as tangent_from_jaxlie
from ._se2 import tangent_to_jaxlie as tangent_to_jaxlie
from ._se2 import vee as vee
