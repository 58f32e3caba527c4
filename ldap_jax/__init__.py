"""ldap_jax: geometric integrators for nonholonomic systems with symmetries, in JAX.

The RDP (reduced d'Alembert-Pontryagin) integrator of Kobilarov, Marsden and Sukhatme,
"Geometric discretization of nonholonomic systems with symmetries" (DCDS-S, 2010), with the
steered car and the snakeboard, RK baselines, a diffrax reference, and end-to-end
differentiable rollouts.

The core imports JAX and equinox only: ``ldap_jax.control`` (optax), ``ldap_jax.study`` and
``ldap_jax.plotting`` (matplotlib) are imported when first used (``lj.control``, ``import
ldap_jax.plotting``), and diffrax when :func:`reference` is first called.
"""

import importlib as _importlib
from typing import Any as _Any

from . import integrators as integrators
from . import lie as lie
from . import systems as systems
from ._allocator import keep_freed_memory as keep_freed_memory
from ._compilation_cache import compiler_options as compiler_options
from ._compilation_cache import enable_compilation_cache as enable_compilation_cache
from ._compilation_cache import memory_mappings as memory_mappings
from ._compilation_cache import trim_compilation_cache as trim_compilation_cache
from ._controls import AbstractControls as AbstractControls
from ._controls import Constant as Constant
from ._controls import Sampled as Sampled
from ._controls import Sinusoids as Sinusoids
from ._discrete import DiscreteDynamics as DiscreteDynamics
from ._discrete import discretize as discretize
from ._policy import AbstractPolicy as AbstractPolicy
from ._policy import LinearPolicy as LinearPolicy
from ._policy import Policy as Policy
from ._reference import Solution as Solution
from ._reference import reference as reference
from ._results import RESULTS as RESULTS
from ._sharding import device_mesh as device_mesh
from ._sharding import global_batch as global_batch
from ._sharding import shard_vmap as shard_vmap
from ._sharding import use_cpu_cores as use_cpu_cores
from ._simulate import Trajectory as Trajectory
from ._simulate import simulate as simulate
from .integrators import DLA as DLA
from .integrators import GNI as GNI
from .integrators import RDP as RDP
from .integrators import RK2 as RK2
from .integrators import RK4 as RK4
from .lie import SE2 as SE2
from .systems import AbstractSystem as AbstractSystem
from .systems import Car as Car
from .systems import Snakeboard as Snakeboard
from .systems import System as System
from .systems import chaplygin_sleigh as chaplygin_sleigh
from .systems import roller_racer as roller_racer

#: subpackages imported on first attribute access (``lj.control``), not with the core
_LAZY_SUBPACKAGES = ("control", "plotting", "study")


def __getattr__(name: str) -> _Any:
    """Import a subpackage of :data:`_LAZY_SUBPACKAGES` when it is first accessed, and read
    ``__version__`` from the package metadata when first asked for (``importlib.metadata`` takes
    about 0.08 s to import) (PEP 562)."""
    if name in _LAZY_SUBPACKAGES:
        module = _importlib.import_module(f".{name}", __name__)
        globals()[name] = module
        return module
    if name == "__version__":
        import importlib.metadata

        try:
            version = importlib.metadata.version("ldap_jax")
        except importlib.metadata.PackageNotFoundError:  # pragma: no cover
            version = "0.0.0"
        globals()[name] = version
        return version
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY_SUBPACKAGES) | {"__version__"})
