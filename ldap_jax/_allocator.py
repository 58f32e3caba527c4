"""The process's memory allocator: keeping what a compiled program frees for its next call.

XLA's CPU backend allocates a program's temporaries afresh at every call, as one block, and frees
it when the call returns. glibc's ``malloc`` serves a block above its mmap threshold (at most
32 MiB) with a new ``mmap`` and gives it back to the system on ``free``, so every call touches
its temporaries' pages for the first time again: a minor page fault per 4 KiB page, paid in
system time. A gradient through a rollout stores its residuals for the backward pass in such a
block (about 64 MB for a batch of 1000 snakeboard runs of 1000 order-2 steps): about 16e3 faults
per call, 15-20% of the gradient's time on a 2-core machine (``scripts/bench.py --only
default_call``). The forward rollout keeps no such block.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import platform

__all__ = ["keep_freed_memory"]

# glibc's mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_M_ARENA_MAX = -8
#: with :func:`keep_freed_memory`: blocks up to 1 GiB come from the heap, which is not trimmed
#: until 2 GiB lie free at its top (mallopt takes a C int), and threads that have no arena yet
#: share the main one (another arena's heaps hold at most 64 MiB: a larger block is mapped anew
#: whatever the threshold)
_KEEP = {_M_MMAP_THRESHOLD: 1 << 30, _M_TRIM_THRESHOLD: (1 << 31) - 1, _M_ARENA_MAX: 1}
#: ``keep_freed_memory(False)``: glibc's thresholds once its dynamic rule has reached its ceiling
#: (mmap above 32 MiB, trim above twice that), as in a process that has freed a large block
_RELEASE = {_M_MMAP_THRESHOLD: 32 << 20, _M_TRIM_THRESHOLD: 64 << 20}


def _libc():
    """glibc, or ``None`` (another C library or operating system: nothing to set)."""
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:  # pragma: no cover - glibc without a loadable libc.so
        return None
    return libc if hasattr(libc, "mallopt") and hasattr(libc, "malloc_trim") else None


def keep_freed_memory(keep: bool = True) -> bool:
    """Tell the process's allocator (glibc's ``malloc``) to keep the memory a compiled program
    frees, so that its next call reuses the same pages instead of mapping and touching new ones.

    Worth it when one compiled program with large temporaries is called many times from Python,
    e.g. a jitted gradient through a batched rollout in an optimisation loop: a gradient keeps its
    forward pass's residuals (about 8 arrays of ``(n_steps, batch)`` floats for the snakeboard's
    order-2 step), which XLA allocates anew at each call. Measured for a batch of 1000 snakeboard
    runs of 1000 steps, on 2 cores: about 16e3 page faults per gradient call and 15-20% of its time
    without; none with. A forward rollout gains little (it keeps no residuals). What it saves
    depends on how XLA allocates a program's temporaries: measured with XLA's default code
    generation (a plain ``jax.jit``).

    Call it first, before anything runs (as :func:`use_cpu_cores`): the threads that JAX starts
    then share glibc's main arena, and blocks of any size up to 1 GiB are kept. Called later,
    a thread that already has an arena of its own keeps it, and that arena's blocks above 64 MiB
    (its heaps' limit) are still mapped anew at every call: the setting then helps programs whose
    temporaries stay below that.

    The cost: the process holds on to the most memory it has used at once (its peak) instead of
    returning freed blocks to the system. It is a setting of the whole process (every library's
    allocations), applied at once and until changed; ``keep_freed_memory(False)`` returns to
    releasing blocks above 32 MiB (glibc's own ceiling) and trims the heap now (the threads keep
    sharing one arena). The same, for a whole run, from the environment:
    ``MALLOC_ARENA_MAX=1 MALLOC_MMAP_THRESHOLD_=1073741824 MALLOC_TRIM_THRESHOLD_=2147483647``.

    Args:
        keep: keep freed memory (default ``True``), or release it again (``False``).

    Returns:
        Whether the setting was applied: ``True`` on Linux with glibc, ``False`` elsewhere (other
        allocators are left as they are).

    Example:
        >>> import ldap_jax as lj
        >>> lj.keep_freed_memory()  # doctest: +SKIP
        True
    """
    if not isinstance(keep, bool):
        raise TypeError(f"'keep' must be True or False, got {keep!r}")
    libc = _libc()
    if libc is None:
        return False
    for param, value in (_KEEP if keep else _RELEASE).items():  # each 1 on success
        if not libc.mallopt(param, value):  # pragma: no cover - glibc refused the value
            return False
    if not keep:
        libc.malloc_trim(0)
    return True
