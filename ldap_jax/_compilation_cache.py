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
The library also calls it by itself where user code compiles repeatedly: :func:`ldap_jax.simulate`
and :func:`ldap_jax.reference` count the distinct programs they are asked for (a new ``n_steps``,
save plan, integrator, dtype, ...) and, every :data:`CHECK_EVERY` new ones, trim
(:func:`note_program`; only when called outside any JAX trace).

The library's own compiled entry points (``simulate``, ``reference``, the control solvers, the
study's batches) are built with :func:`jit`, which compiles with :func:`compiler_options`: on a
CPU, XLA's loop emitters. Our programs are long chains of scalar arithmetic inside loops; with
these emitters XLA compiles them in 0.5-0.6x the time, and they run 1.0-1.16x as long
(``scripts/bench.py`` measures both).
"""

from __future__ import annotations

import functools
import gc
import inspect
import math
import os
import sys
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import numpy as np

__all__ = [
    "memory_mappings",
    "trim_compilation_cache",
    "enable_compilation_cache",
    "note_program",
    "program_key",
    "CHECK_EVERY",
    "FAST_COMPILE_OPTIONS",
    "compiler_options",
    "jit",
    "asarray",
]

#: XLA compile options for the library's programs (:func:`jit`), each measured on 2 CPU cores:
#:
#: * ``xla_cpu_use_fusion_emitters=False``: XLA's loop emitters instead of its newer fusion
#:   emitters. ``scripts/bench.py --only compile`` (batched snakeboard rollouts, 16 x 1000 steps):
#:   compilation 0.5-0.6x (RDP2 2.80 -> 1.44 s, RDP6 2.29 -> 1.42 s, RK4 1.95 -> 0.96 s), run time
#:   1.0-1.16x. A batch of 16 interior-point solves (``jax.vmap(lc.solve)``): first call 14.7 ->
#:   7.7 s.
#: * ``xla_cpu_experimental_ynn_fusion_type=""``: no YNNPACK fusions. XLA hands the small batched
#:   matrix products of a vmapped Riccati recursion to YNNPACK, whose per-call cost grows faster
#:   than the batch: the factorisation of 64 problems (101 stages, 7 x 7 blocks) 24 -> 4.6 ms, a
#:   batch of 16 solves 0.76 -> 0.52 s; rollouts unchanged (``bench.py --only throughput``, two
#:   alternating runs each, every integrator within 5%).
#:
#: An option this XLA does not know is left out (each is checked once). Set the environment
#: variable ``LDAP_JAX_FAST_COMPILE=0`` to compile with XLA's defaults instead.
FAST_COMPILE_OPTIONS: dict[str, Any] = {
    "xla_cpu_use_fusion_emitters": False,
    "xla_cpu_experimental_ynn_fusion_type": "",
}
_UNSET = object()
_options: Any = _UNSET

#: :func:`note_program` checks the memory mappings every this many new programs: a compiled
#: rollout holds 300 to 600 mappings, so 8 programs stay far below the half of
#: ``vm.max_map_count`` (65530 by default) that :func:`trim_compilation_cache` leaves as margin.
CHECK_EVERY = 8
_seen: set = set()
_new_programs = 0


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
    if isinstance(threshold, bool) or not isinstance(threshold, (int, float, np.floating, np.integer)):
        raise TypeError(f"'threshold' must be a number in (0, 1], got {threshold!r}")
    if not 0.0 < threshold <= 1.0:
        raise ValueError(f"'threshold' must be in (0, 1], got {threshold}")
    usage = memory_mappings()
    if usage is None or usage[0] <= threshold * usage[1]:
        return False
    jax.clear_caches()
    gc.collect()
    return True


def in_trace() -> bool:
    """True inside a JAX trace (``jit``, ``vmap``, ``grad``...): clearing caches is unsafe there,
    and a check on known values must run at trace time (``jax.ensure_compile_time_eval``)."""
    try:
        from jax._src import core

        return not core.trace_state_clean()
    except (ImportError, AttributeError):  # pragma: no cover - a future JAX: never trim
        return True


def note_program(key: Any) -> bool:
    """Record that the library is about to run the program identified by ``key`` (hashable: the
    static settings, tree structures, shapes and dtypes that select a compilation). Every
    :data:`CHECK_EVERY` distinct new keys, call :func:`trim_compilation_cache` (which clears
    JAX's caches only above half of the mapping budget). A no-op inside a JAX trace or for an
    unhashable key.

    Returns:
        True if the caches were cleared.
    """
    global _new_programs
    try:
        if key in _seen:
            return False
    except TypeError:  # unhashable static data: do not track
        return False
    if in_trace():
        return False
    if len(_seen) > 100_000:  # pragma: no cover - bound the bookkeeping
        _seen.clear()
    _seen.add(key)
    _new_programs += 1
    if _new_programs < CHECK_EVERY:
        return False
    _new_programs = 0
    if trim_compilation_cache():
        _seen.clear()  # every program compiles anew
        return True
    return False


def program_key(*parts: Any) -> Any:
    """A hashable key for :func:`note_program`: the tree structure of ``parts`` and the shape and
    dtype of every array leaf (the identity of other leaves, e.g. functions)."""
    leaves, treedef = jax.tree_util.tree_flatten(parts)

    def signature(x):
        if hasattr(x, "shape") and hasattr(x, "dtype"):
            return tuple(x.shape), str(x.dtype)
        if isinstance(x, (bool, int, float, complex, str, type(None))):
            return x  # static under eqx.filter_jit: a new value compiles anew
        return type(x), id(x)

    return treedef, tuple(signature(x) for x in leaves)


def enable_compilation_cache(
    path: str | os.PathLike | None = None, *, min_compile_seconds: float = 0.05
) -> str:
    """Opt in to JAX's persistent compilation cache: compiled programs are written to ``path`` and
    a later process (a script run again, a restarted notebook) loads them instead of compiling.

    Compiling the larger programs (an interior-point solve, a gradient through a long rollout)
    takes tens of seconds on a CPU; with the cache a new process pays that once per program and
    machine. The cache is keyed by the program, the JAX version and the device, so stale entries
    are never used. Call it once, before the first compilation. With the cache on,
    :func:`ldap_jax.control.solve` also stores its traced programs (``jax.export``) in the folder
    ``ldap_jax_exports`` inside it, so a new process solving a problem of the same structure does
    not trace them again (``LDAP_JAX_EXPORT=0``: not).

    Args:
        path: cache directory (default ``$LDAP_JAX_CACHE`` or ``~/.cache/ldap_jax/xla``; a relative
            path is taken from the working folder now, and the absolute path returned); created
            if missing.
        min_compile_seconds: only programs that took at least this long to compile are stored
            (default 0.05 s: a task's checks and default guess are such programs; stored, a warm
            first ``lc.solve`` of ``parallel_park`` compiled 0.2 s instead of 1.4-2.3 s of them on
            a loaded 2-core machine; single operations, which compile faster than they are read,
            stay out).

    Returns:
        The cache directory.

    Example:
        >>> import ldap_jax as lj
        >>> lj.enable_compilation_cache()   # doctest: +SKIP
    """
    if path is None:
        path = os.environ.get("LDAP_JAX_CACHE") or os.path.join(
            os.path.expanduser("~"), ".cache", "ldap_jax", "xla"
        )
    path = os.fspath(path)
    if not path.strip():
        raise ValueError("'path' must name a folder, got an empty path")
    seconds = float(min_compile_seconds)
    if not (seconds >= 0 and math.isfinite(seconds)):
        raise ValueError(
            f"'min_compile_seconds' must be non-negative and finite, got {min_compile_seconds!r}"
        )
    path = os.path.abspath(path)  # JAX reads a relative path against the working folder of each write
    os.makedirs(path, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", seconds)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path


def asarray(x: Any, dtype: Any = None) -> jax.Array:
    """``jnp.asarray(x, dtype)`` (the same dtype, weak type and errors) without an eager JAX
    operation for a value on the host (a Python number, a list, a NumPy array): that is copied to
    the device (``jax.device_put``), where ``jnp.asarray`` (JAX 0.10) runs a one-operation program
    that each new process compiles (``stage``, ``convert_element_type``: 5-60 ms each, the first
    0.15 s). JAX arrays and tracers go to ``jnp.asarray``."""
    import jax.numpy as jnp

    if x is None or isinstance(x, (jax.Array, jax.core.Tracer, np.ma.MaskedArray)):
        return jnp.asarray(x, dtype)
    try:
        a = np.asarray(x, dtype)
    except (TypeError, ValueError, OverflowError):
        return jnp.asarray(x, dtype)  # its own error
    if a.dtype.kind not in "buifc" or (a.dtype.kind in "ui" and not jax.config.jax_enable_x64):
        return jnp.asarray(x, dtype)  # its own error (or its overflow check into 32 bits)
    if dtype is None and isinstance(x, (int, float, complex)) and not isinstance(x, bool):
        return jax.device_put(x)  # a weakly typed scalar, as jnp.asarray makes it
    return jax.device_put(a)


def as_dtype(x: Any, dtype: Any) -> jax.Array:
    """``x`` (an array or a tracer) converted to ``dtype``: a known value through the host
    (:func:`asarray`, no eager conversion program), a traced one by ``astype``."""
    if isinstance(x, jax.core.Tracer):
        return x.astype(dtype)
    return asarray(np.asarray(x), dtype)


def compiler_options() -> dict[str, Any] | None:
    """The XLA compile options of the library's programs: those of :data:`FAST_COMPILE_OPTIONS`
    that this XLA knows (each checked once, by compiling a one-operation program; with the
    persistent cache on, once per cache directory and JAX version: :data:`PROBE_FILE`), or ``None``
    (XLA's defaults) if ``LDAP_JAX_FAST_COMPILE=0`` or it knows none of them.

    Pass them to your own ``jax.jit`` to compile a rollout as fast as the library does:

    Example:
        >>> import jax, ldap_jax as lj
        >>> f = jax.jit(lambda x: 2 * x, compiler_options=lj.compiler_options())
    """
    global _options
    if _options is _UNSET:
        known = {}
        if os.environ.get("LDAP_JAX_FAST_COMPILE", "1").strip() not in ("0", "false", "False"):
            names = _probed_options()
            known = {key: FAST_COMPILE_OPTIONS[key] for key in names}
        _options = known or None
    return None if _options is None else dict(_options)


#: the file in the persistent compilation cache's directory that keeps :func:`compiler_options`'
#: probe results, per JAX version, backend and option set
PROBE_FILE = "ldap_jax_compiler_options.json"


def _probed_options() -> list[str]:
    """The names of :data:`FAST_COMPILE_OPTIONS` this XLA accepts, each found by compiling a
    one-operation program with it; with the persistent compilation cache on, the answer is kept in
    :data:`PROBE_FILE` next to the cache (keyed by the versions of JAX and jaxlib, the backend and
    the options), so a new process does not compile the probes again (two compilations, 50-60 ms)."""
    import json

    import jaxlib

    key = (
        f"jax {jax.__version__} jaxlib {jaxlib.__version__} backend {jax.default_backend()} "
        f"options {sorted(FAST_COMPILE_OPTIONS.items())!r}"
    )
    root = jax.config.jax_compilation_cache_dir
    path = os.path.join(root, PROBE_FILE) if root else None
    stored: dict = {}
    if path is not None:
        try:
            with open(path) as f:
                stored = json.load(f)
            names = stored[key]
            if isinstance(names, list) and all(name in FAST_COMPILE_OPTIONS for name in names):
                return names
        except (OSError, ValueError, KeyError, TypeError):
            stored = stored if isinstance(stored, dict) else {}
    names = []
    for name, value in FAST_COMPILE_OPTIONS.items():
        try:
            probe = jax.jit(lambda x: x + 1, compiler_options={name: value})
            probe.lower(np.float32(0)).compile()
            names.append(name)
        except Exception:  # pragma: no cover - an XLA without this option
            pass
    if path is not None:
        try:  # written whole, then renamed: a reader never sees half a file
            os.makedirs(root, exist_ok=True)
            tmp = f"{path}.{os.getpid()}.tmp"
            with open(tmp, "w") as f:
                json.dump({**stored, key: names}, f)
            os.replace(tmp, path)
        except OSError:  # pragma: no cover - a read-only cache: probe again next time
            pass
    return names


def _traced(args: Any) -> bool:
    """True if a leaf of ``args`` is a JAX tracer (also if JAX's core cannot be read: a future JAX)."""
    try:
        from jax._src import core
    except ImportError:  # pragma: no cover
        return True
    return any(isinstance(x, core.Tracer) for x in jax.tree_util.tree_leaves(args))


def _runs_at_top_level(args: Any, traced: bool | None = None) -> bool:
    """True if a program called with ``args`` here runs as a top-level one (and may carry compile
    options): inside ``jax.vmap`` (possibly nested) with no ``jit`` or other staging trace around
    it, whose batched program runs at the top; or inside differentiation (``jax.grad``,
    ``jax.jvp``, again with nothing staging around it) when no argument is traced, so that JAX
    calls the program on its values as it is (the same program as outside, compiled once).
    ``traced``: :func:`_traced` of ``args`` if the caller has it."""
    try:
        from jax._src import core
        from jax._src.interpreters import ad, batching

        concrete = not (_traced(args) if traced is None else traced)
        trace = core.trace_ctx.trace
        while isinstance(trace, batching.BatchTrace) or (
            concrete and isinstance(trace, (ad.JVPTrace, ad.LinearizeTrace))
        ):
            trace = trace.parent_trace
        return isinstance(trace, core.EvalTrace)
    except (ImportError, AttributeError):  # pragma: no cover - a future JAX: no options
        return False


def _staging() -> bool:
    """True under a trace that stages code out (``jax.jit``, a ``lax.scan`` body,
    ``jax.eval_shape``...), possibly below ``vmap``/``grad``; False with only ``vmap`` and
    differentiation traces (or none) around, where a ``jit`` call is a top-level program. Also
    True if JAX's core cannot be read (a future JAX: then nothing is wrapped)."""
    try:
        from jax._src import core
        from jax._src.interpreters import partial_eval as pe

        trace = core.trace_ctx.trace
        while not isinstance(trace, core.EvalTrace):
            if isinstance(trace, pe.DynamicJaxprTrace) or not hasattr(trace, "parent_trace"):
                return True
            trace = trace.parent_trace
        return False
    except (ImportError, AttributeError):  # pragma: no cover
        return True


def compiled_unless_staged(method: Callable) -> Callable:
    """A method that, called on values or under a top-level ``vmap``/``grad``/``jacfwd``, runs as
    one compiled program (:func:`jit`; numbers and lists become NumPy arrays first, so new values
    never recompile), and under a trace that stages code out (the caller's ``jax.jit``, a scan
    body) is traced inline as written, so the caller's program is the one it would have been
    (a nested ``jit`` boundary measured 1.3-1.6x slower in the control solver's program). Eager
    calls would otherwise compile every operation as its own program (a first ``init`` of the
    discrete dynamics: 65 programs, 1.3 s)."""
    jitted = jit(method)
    signature = inspect.signature(method)

    def as_array(x: Any) -> Any:
        return x if isinstance(x, (jax.Array, np.ndarray, np.generic)) else np.asarray(x)

    @functools.wraps(method)
    def wrapper(self, *args, **kwargs):
        if _staging():
            return method(self, *args, **kwargs)
        # every argument positional, defaults filled in: one program whichever way it is called
        bound = signature.bind(self, *args, **kwargs)
        bound.apply_defaults()
        return jitted(self, *jax.tree_util.tree_map(as_array, bound.args[1:]))

    return wrapper


class _Jit:
    """``equinox.filter_jit(fun)``; called outside any JAX trace, under a top-level ``jax.vmap``
    (whose batched program runs as a top-level one) or on plain values under a top-level
    ``jax.grad``/``jax.vmap`` (then run outside those traces: the same program as a call outside
    them, compiled once), compiled with :func:`compiler_options`. JAX accepts compile options only
    on a top-level program: inside a user's ``jit``, or on arguments a ``grad`` traces, the
    program is the user's and compiles with its options. Attributes (``lower``, equinox's
    ``_cached``) are the top-level wrapper's."""

    def __init__(self, fun: Callable):
        self._fun = fun
        self._top = None
        self._nested = None
        functools.update_wrapper(self, fun)

    def _build(self):
        if self._top is None:
            options = compiler_options()
            kwargs = {} if options is None else {"compiler_options": options}
            self._top = eqx.filter_jit(self._fun, **kwargs)
        return self._top

    def __call__(self, *args, **kwargs):
        if in_trace():
            traced = _traced((args, kwargs))
            if not _runs_at_top_level((args, kwargs), traced):
                if self._nested is None:
                    self._nested = eqx.filter_jit(self._fun)
                return self._nested(*args, **kwargs)
            if not traced:
                # plain values under a grad or vmap: the program runs on them as it is, so run it
                # outside those traces (their rules would re-trace it as a new program)
                from jax._src import core

                outside = getattr(core, "set_current_trace", None)
                if outside is not None and hasattr(core, "eval_trace"):  # else: a future JAX
                    with outside(core.eval_trace):
                        return self._build()(*args, **kwargs)
        return self._build()(*args, **kwargs)

    def __getattr__(self, name):
        if name.startswith("__"):
            raise AttributeError(name)
        return getattr(self._build(), name)


def jit(fun: Callable) -> Callable:
    """``equinox.filter_jit(fun)`` compiled with :func:`compiler_options` when its program runs at
    the top level (see :class:`_Jit`; the options are decided at the first call, so importing the
    library does not start JAX's backend). Arrays are traced, everything else is static, exactly
    as with ``filter_jit``."""
    return _Jit(fun)
