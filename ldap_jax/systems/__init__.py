"""System descriptions: the reduced and full views of a nonholonomic system on M x SE(2)."""

from ._base import AbstractSystem as AbstractSystem
from ._base import Observation as Observation
from ._base import body_velocity as body_velocity
from ._base import spatial_velocity as spatial_velocity
from ._car import Car as Car
from ._closed_form import AbstractClosedFormSystem as AbstractClosedFormSystem
from ._description import System as System
from ._examples import chaplygin_sleigh as chaplygin_sleigh
from ._examples import roller_racer as roller_racer
from ._snakeboard import Snakeboard as Snakeboard
