"""Keep long sessions (test suites, sweeps, notebooks) below the OS limit on memory mappings.

XLA's CPU backend (jaxlib 0.10) loads every compiled kernel into memory mappings of its own: one
``lj.simulate`` with ``lj.DLA()`` on the snakeboard holds about 600 mappings for as long as JAX's
caches keep the executable alive. Linux caps a process at ``vm.max_map_count`` mappings
(65530 by default); a process that compiles a few hundred programs crosses it, the next
compilation fails inside XLA (``INTERNAL: Failed to materialize symbols``) and the process dies
with a segmentation fault while that error propagates. Nothing is leaked: dropping JAX's caches
(``jax.clear_caches()``) unmaps everything, at the price of recompiling what is used again.

:func:`trim_compilation_cache` does that only when the mapping count is high, so it is cheap to
call between units of work (the study calls it between points, the test suite between tests).
"""

from __future__ import annotations

import gc
import sys

import jax

__all__ = ["memory_mappings", "trim_compilation_cache"]


def memory_mappings() -> tuple[int, int] | None:
    """``(mappings in use, vm.max_map_count)`` for this process, or ``None`` off Linux."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        with open("/proc/self/maps", "rb") as f:
            used = sum(1 for _ in f)
        with open("/proc/sys/vm/max_map_count") as f:
            limit = int(f.read().strip())
    except (OSError, ValueError):
        return None
    return used, limit


def trim_compilation_cache(threshold: float = 0.5) -> bool:
    """Clear JAX's compilation caches if this process uses more than ``threshold`` of its
    memory-mapping budget (``vm.max_map_count``).

    Args:
        threshold: fraction of ``vm.max_map_count`` in ``(0, 1]`` above which to clear.

    Returns:
        True if the caches were cleared.

    Raises:
        ValueError: if ``threshold`` is not in ``(0, 1]``.

    Example:
        >>> import ldap_jax as lj
        >>> for n_steps in (100, 200, 400):  # every new n_steps compiles a new program
        ...     ...  # lj.simulate(..., n_steps=n_steps)
        ...     _ = lj.trim_compilation_cache()
    """
    if not 0.0 < threshold <= 1.0:
        raise ValueError(f"'threshold' must be in (0, 1], got {threshold}")
    usage = memory_mappings()
    if usage is None or usage[0] <= threshold * usage[1]:
        return False
    jax.clear_caches()
    gc.collect()
    return True
