"""Exported solver programs: a new process solves a problem structure it has solved before without
tracing the solver again.

A first ``lc.solve`` in a new process spends most of its time outside the solve itself: tracing
the interior-point program in Python (2.4-3.7 s for ``parallel_park``), lowering it (0.6-0.9 s)
and compiling it with XLA (tens of seconds; JAX's persistent compilation cache turns that into a
read of about 1 s). :mod:`jax.export` keeps the traced and lowered program (StableHLO) as bytes,
so a later process deserialises it and goes straight to XLA, which the persistent cache serves.

The program is exported as a function of the task's *arrays* (goal, bounds, model parameters,
horizon, the guess and the solver's tolerances): a task that differs only in those values uses
the same export. Everything else is part of the key, and a program is only served for the exact
key it was exported for:

* the tree structure of the (task, guess, options) with every node's type (module and name) and
  static data, and every static leaf (e.g. ``n_steps``, the integrator's order, ``hessian``);
* the shape and dtype of every array;
* the library's source (a hash of every ``.py`` file of the package), JAX's, jaxlib's and
  equinox's versions, ``jax_enable_x64``, the backend and the library's XLA options.

A structure whose description holds an object identity (a ``<function ... at 0x...>``: a
user-written term or system method captured as static data) or a type from outside the library,
JAX, equinox and NumPy (a class of your own: its code is not in the key) is never exported.

``lc.solve`` exports two programs: the interior-point run (for a batch of guesses, the run of
every start) and the finish (the optimum with its IFT derivative rule, the model-error
estimate). Under a user's ``jit`` or ``vmap`` both are traced as always. Under ``grad``/``jvp``
the run's inputs are cut from differentiation, so the run is the exported program. The finish
under a top-level ``grad``/``jvp`` (one differentiation directly over the evaluation, as
``jax.grad(f)(x)`` called outside any other transformation) runs as two exported programs
(:func:`differentiated`): the finish on the primal values and its Jacobian with respect to the
task's arrays; otherwise (``jacfwd``, ``hessian``, under ``vmap``) its
derivative is traced.

The exports live in the persistent compilation cache's directory (``jax_compilation_cache_dir``,
set by :func:`ldap_jax.enable_compilation_cache`), under ``ldap_jax_exports/``. Without a cache
directory the solver's programs are exported in memory only (:data:`IN_MEMORY`): the process's
first solve still gets the quick first compilation (:func:`prepare`), and nothing is written;
the optimised compilation that follows it starts with the program's second call (a script that
solves once exits after its answer).
``LDAP_JAX_EXPORT=0`` turns exports off.

The process that compiles an exported program also stores its executable there (keyed by the
export's key and the machine's backend, see :func:`_executable`): a later process loads it
directly, without lowering the exported module to look it up in JAX's cache. Each program's
compilation (or the load of its executable) runs in a thread of its own from the moment its export
is ready: ``lc.solve`` exports its finish while XLA compiles its run (:func:`prepare`), and the
files are written meanwhile or after the program is handed over.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import pathlib
import re
import tempfile
import threading
import types
import warnings
import zlib
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import numpy as np

__all__ = ["enabled", "export_dir", "call", "prepare", "differentiated"]

SUBDIR = "ldap_jax_exports"
_ADDRESS = re.compile(r" at 0x[0-9a-fA-F]+")
_lock = threading.Lock()
_lock_lapack = threading.Lock()
_source: str | None = None
_loaded: dict[Any, Callable | None] = {}  # in-process: key -> compiled callable (None: do not export)
_keys: dict[Any, str | bool] = {}  # in-process: a call's structures -> its key (False: none)


def enabled() -> bool:
    """Whether exports are on (``LDAP_JAX_EXPORT`` is not ``0``): stored in the persistent
    compilation cache's directory when one is set (:func:`export_dir`), in memory otherwise
    (the solver's programs only, :data:`IN_MEMORY`)."""
    return os.environ.get("LDAP_JAX_EXPORT", "1").strip() not in ("0", "false", "False")


#: the programs exported without a cache directory (kept in memory): ``lc.solve``'s, whose first
#: solve in a process compiles its run quickly and the finish meanwhile (:func:`prepare`); the
#: others' exports pay for themselves across processes only
IN_MEMORY = ("run", "run_batch", "finish")


def _serves(name: str) -> bool:
    """Whether program ``name`` goes through an export here (see :func:`enabled`)."""
    return enabled() and (export_dir() is not None or name in IN_MEMORY)


def export_dir() -> pathlib.Path | None:
    """The directory of the exported programs, or ``None`` without a compilation cache."""
    root = jax.config.jax_compilation_cache_dir
    return None if not root else pathlib.Path(root) / SUBDIR


def _source_hash() -> str:
    """A hash of the library's source, JAX's versions and the settings a program depends on."""
    global _source
    if _source is None:
        import jaxlib

        from .._compilation_cache import compiler_options

        h = hashlib.sha256()
        package = pathlib.Path(__file__).resolve().parents[1]
        for path in sorted(package.rglob("*.py")):
            h.update(str(path.relative_to(package)).encode())
            h.update(path.read_bytes())
        h.update(f"jax {jax.__version__} jaxlib {jaxlib.__version__} equinox {eqx.__version__}".encode())
        h.update(repr(sorted((compiler_options() or {}).items())).encode())
        _source = h.hexdigest()
    return _source + f" x64={bool(jax.config.jax_enable_x64)} backend={jax.default_backend()}"


#: modules whose types may appear in a key: their code is in the key (the library's source, the
#: versions of JAX, jaxlib and equinox) or fixed (Python's built-ins, NumPy's scalar types)
_KNOWN_MODULES = ("ldap_jax", "builtins", "equinox", "jax", "jaxlib", "numpy")


def _known(kind: type) -> bool:
    module = getattr(kind, "__module__", None) or ""
    return module.split(".")[0] in _KNOWN_MODULES


def _describe(treedef, strict: bool = True) -> str | None:
    """The tree structure with every node's type by module and name and its static data, or
    ``None`` (``strict``) if a node's type comes from code outside the key (e.g. a class of your
    own: its methods may change between processes while its name stays)."""
    data = treedef.node_data()
    if data is None:  # a leaf
        return "*"
    kind, aux = data
    if strict and not _known(kind):
        return None
    children = [_describe(c, strict) for c in treedef.children()]
    if None in children:
        return None
    return f"{kind.__module__}.{kind.__qualname__}[{aux!r}]({','.join(children)})"


def _is_shape(x: Any) -> bool:
    return eqx.is_array(x) or isinstance(x, jax.ShapeDtypeStruct)


def _signature(name: str, args: tuple, shapes: bool = False) -> tuple[str, list, Any, Any] | None:
    """``(key, array leaves, static part, array treedef)`` of a call of program ``name`` on
    ``args``, or ``None`` if the structure cannot be keyed across processes. With ``shapes``,
    ``jax.ShapeDtypeStruct`` leaves stand for arrays of their shape and dtype."""
    arrays, static = eqx.partition(args, _is_shape if shapes else eqx.is_array)
    leaves, treedef = jax.tree_util.tree_flatten(arrays)
    static_leaves, static_def = jax.tree_util.tree_flatten(static)
    # a repeat call: the key by the tree structures' own equality (3 ms -> well under 1 ms a call)
    try:
        fast = (
            name,
            treedef,
            static_def,
            tuple((type(x), x) for x in static_leaves),
            tuple((x.shape, x.dtype) for x in leaves),
            bool(jax.config.jax_enable_x64),
        )
        key = _keys.get(fast)
    except TypeError:  # unhashable static data
        fast = key = None
    if key is None:
        key = _key(name, leaves, treedef, static_leaves, static_def)
        if fast is not None:
            if len(_keys) > 10_000:  # pragma: no cover - bound the bookkeeping
                _keys.clear()
            _keys[fast] = key
    return None if key is False else (key, leaves, static, treedef)


#: plain values a library function's closure may hold and still be keyed by its text
_PLAIN = (bool, int, float, complex, str, bytes, type(None))


def _static_text(x: Any, seen: frozenset = frozenset()) -> str | None:
    """The text of a static leaf in a key, or ``None`` if it cannot be keyed across processes.

    A function defined in the library (e.g. the Lagrangian of ``lj.roller_racer()``, a nested
    function whose parameters are arguments) is its module and qualified name, with the values
    its closure holds: its code is in the key through the library's source hash. Its closure may
    hold other such functions and plain Python values; anything else (an array, a user's
    function or object) makes the leaf unkeyable. Other leaves are their ``repr``
    (an object identity in it, ``at 0x...``, makes the whole key unusable)."""
    if isinstance(x, types.FunctionType) and (x.__module__ or "").split(".")[0] == "ldap_jax":
        if id(x) in seen:  # a closure that refers back to itself
            return f"<{x.__qualname__}>"
        cells = [c.cell_contents for c in x.__closure__ or ()]
        held = (*cells, *(x.__defaults__ or ()), *(x.__kwdefaults__ or {}).values())
        parts = [_static_text(v, seen | {id(x)}) for v in held]
        if None in parts:
            return None
        return f"<function {x.__module__}.{x.__qualname__}({','.join(parts)})>"
    if isinstance(x, types.FunctionType):
        return None
    if seen and not (
        isinstance(x, _PLAIN) or (isinstance(x, tuple) and all(isinstance(v, _PLAIN) for v in x))
    ):
        return None  # inside a closure: only plain values are keyed by their text
    return repr(x)


def _key(name, leaves, treedef, static_leaves, static_def) -> str | bool:
    """The key of a program (see the module's docstring), or ``False`` for none."""
    described = _describe(treedef), _describe(static_def)
    if None in described or not all(_known(type(x)) for x in static_leaves):
        return False
    static_text = [_static_text(x) for x in static_leaves]
    if None in static_text:
        return False
    text = "\n".join(
        [
            name,
            *described,
            repr(static_text),
            repr([(tuple(x.shape), str(x.dtype)) for x in leaves]),
            _source_hash(),
        ]
    )
    if _ADDRESS.search(text):
        return False
    return hashlib.sha256(text.encode()).hexdigest()[:32]


def _paths(key: str) -> tuple[pathlib.Path, pathlib.Path] | None:
    """The files of the export ``key``, or ``None`` without a cache directory (kept in memory)."""
    folder = export_dir()
    if folder is None:
        return None
    return folder / f"{key}.jaxexport", folder / f"{key}.json"


def _write(path: pathlib.Path, data: bytes) -> None:
    """Write atomically (a concurrent reader sees the old file or the whole new one)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name + ".")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.chmod(tmp, 0o644)  # as the cache's own files (mkstemp makes them private)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _compiled(exported, name: str) -> Callable:
    from .._compilation_cache import compiler_options

    def call(*xs):
        return exported.call(*xs)

    call.__name__ = call.__qualname__ = f"exported_{name}"
    options = compiler_options()
    kwargs = {} if options is None else {"compiler_options": options}
    return jax.jit(call, **kwargs)


def call(
    name: str, fun: Callable, args: tuple, out_template: Callable[[], Any], *, top_level: bool = False
) -> Any:
    """``fun(*args)`` through an exported program, or ``NotImplemented`` if this call cannot use
    one (exports off, a traced argument, a call under a trace that stages code out, a structure
    without a key, an export that fails).

    Args:
        name: the program's name (part of the key).
        fun: the function to run; traced only when no export exists for the key yet.
        args: its arguments (a tuple of pytrees); array leaves become the program's arguments,
            the rest is static (baked into the program and part of the key).
        out_template: builds a pytree with the structure of ``fun``'s output (any leaves): the
            output is rebuilt in it, after a check that it matches the structure recorded at
            export.
        top_level: only outside every JAX trace. Otherwise also on concrete arguments under
            ``grad``/``jvp`` or a ``vmap`` they are not batched over (the program then runs on
            them as it is, outside those traces, like the library's :func:`~ldap_jax.jit`).
    """
    if not _serves(name):
        return NotImplemented
    from .._compilation_cache import _runs_at_top_level, _traced, in_trace

    inside = in_trace()
    if inside and (top_level or _traced(args) or not _runs_at_top_level(args, False)):
        return NotImplemented
    if inside and not _can_leave_traces():  # pragma: no cover - a future JAX
        return NotImplemented
    signature = _signature(name, args)
    if signature is None:
        return NotImplemented
    leaves = signature[1]
    runner = _runner_for(name, fun, signature, out_template, inside=inside)
    if runner is None:
        return NotImplemented
    with _outside_traces(inside):
        return runner(leaves)


def prepare(
    name: str, fun: Callable, args: tuple, out_template: Callable[[], Any], *, quick: bool = False
) -> Any:
    """Start what a later :func:`call` of program ``name`` on arguments like ``args`` needs (the
    export, or its load, and the compilation, which runs in a thread of its own) and return the
    program's output as ``jax.ShapeDtypeStruct`` leaves in ``out_template``'s structure, or
    ``None`` where :func:`call` would not use an export.

    ``args``' array leaves may be ``jax.ShapeDtypeStruct``s (an output of another program that
    has not run yet): ``lc.solve`` prepares its finish while XLA compiles its run, so a first
    solve takes the longer of the two rather than their sum. Only outside every JAX trace.

    With ``quick``, the first process to export the program compiles it twice if it is the
    process's first such program: first with :data:`QUICK_OPTIONS` (about half XLA's time; the
    program runs about 3x slower), which the first calls use, then, in the same thread, with the
    library's options, which later calls use once it is ready and whose executable is the one
    stored for later processes. Without a cache directory (nothing stored) that second
    compilation starts at the program's second call instead, in a thread of its own.
    ``LDAP_JAX_QUICK_FIRST=0`` turns this off."""
    if not _serves(name):
        return None
    from .._compilation_cache import in_trace

    if in_trace():
        return None
    signature = _signature(name, args, shapes=True)
    if signature is None:
        return None
    runner = _runner_for(name, fun, signature, out_template, quick=quick)
    return None if runner is None else runner.out_shapes


def _runner_for(name, fun, signature, out_template, *, quick=False, inside=False) -> Callable | None:
    """The process's runner of program ``name`` for ``signature`` (:func:`_signature`): the one
    already loaded, else loaded or exported now (``None``: not exported)."""
    key, leaves, static, treedef = signature
    with _lock:
        runner = _loaded.get(key, NotImplemented)
        if runner is NotImplemented:
            with _outside_traces(inside):
                runner = _load_or_export(name, key, fun, leaves, static, treedef, out_template, quick)
            _loaded[key] = runner
    return runner


#: the most Jacobian columns (scalars of the arrays it is taken with respect to) an exported
#: derivative computes; above, the derivative is traced as written
MAX_COLUMNS = 1000


def differentiated(
    name: str, fun: Callable, args: tuple, out_template: Callable[[], Any], n_wrt: int = 1
) -> Any:
    """``fun(*args)`` under a top-level ``jax.grad``/``jax.jvp`` through two exported programs, or
    ``NotImplemented`` where it cannot (see below).

    Where one differentiation trace lies directly over the evaluation (``jax.grad(f)(x)`` or
    ``jax.jvp`` outside any other transformation) and every traced leaf of ``args`` is an
    inexact array of that trace with a concrete primal value, among the leaves of the first
    ``n_wrt`` arguments (for ``lc.solve``'s finish: the task), ``fun`` runs on the primal values
    (the program :func:`call` serves as ``name``) and its Jacobian ``J_ij = d out_i / d theta_j``
    with respect to every inexact leaf ``theta_j`` of those arguments (forward mode, one column
    per scalar, at most :data:`MAX_COLUMNS`) is a second exported program, ``name +
    "_jacobian"``: one program whichever of them a derivative traces (the mass, the goal, both).
    The outputs' tangents are ``sum_j J_ij . t_j`` over the traced leaves, a contraction linear
    in the tangents that JAX transposes for reverse mode, so a new process neither traces nor
    differentiates ``fun``.

    The derivative is first order: the Jacobian is a constant of the contraction. Under a second
    differentiation (``jax.hessian``), ``jacfwd`` (``vmap`` of ``jvp``), a ``vmap`` or a staging
    trace, with a traced leaf that is not such an array, or above :data:`MAX_COLUMNS`, it
    declines and ``fun``'s derivative is traced as written. It declines too without a cache
    directory: the Jacobian program pays for itself across processes, not within one.
    """
    if not _serves(name + "_jacobian"):  # not in memory: exported with a cache directory only
        return NotImplemented
    try:
        from jax._src import core
        from jax._src.interpreters import ad

        trace = core.trace_ctx.trace
        if not isinstance(trace, (ad.JVPTrace, ad.LinearizeTrace)) or not isinstance(
            trace.parent_trace, core.EvalTrace
        ):
            return NotImplemented
        if core.trace_ctx.axis_env is not core.top_axis_env:  # pragma: no cover - a named axis
            return NotImplemented
    except (ImportError, AttributeError):  # pragma: no cover - a future JAX
        return NotImplemented
    leaves, treedef = jax.tree_util.tree_flatten(args)
    n_first = len(jax.tree_util.tree_leaves(args[:n_wrt]))  # their leaves come first
    primals, traced = [], []
    for i, x in enumerate(leaves):
        if isinstance(x, core.Tracer):
            primal = getattr(x, "primal", None)
            if (
                i >= n_first
                or x._trace is not trace
                or isinstance(primal, core.Tracer)
                or not eqx.is_inexact_array(primal)
            ):
                return NotImplemented
            traced.append(i)
            x = primal
        primals.append(x)
    positions = [i for i in range(n_first) if eqx.is_inexact_array(primals[i])]
    if sum(int(np.size(primals[i])) for i in positions) > MAX_COLUMNS:
        return NotImplemented
    primal_args = jax.tree_util.tree_unflatten(treedef, primals)
    with _outside_traces(True):
        out = call(name, fun, primal_args, out_template, top_level=True)
        if out is NotImplemented or not traced:
            return out
        flat, out_def = jax.tree_util.tree_flatten(out)
        inexact = [k for k, o in enumerate(flat) if eqx.is_inexact_array(o)]
        jac = call(
            name + "_jacobian",
            _jacobian_of(fun),
            (primal_args, tuple(positions)),
            lambda: [[0] * len(positions) for _ in inexact],
        )
    if jac is NotImplemented:
        return NotImplemented
    columns = [positions.index(i) for i in traced]
    jac = [[row[c] for c in columns] for row in jac]
    tangents = _with_tangents([flat[k] for k in inexact], jac, [leaves[i] for i in traced])
    for k, value in zip(inexact, tangents):
        flat[k] = value
    return jax.tree_util.tree_unflatten(out_def, flat)


def _jacobian_of(fun: Callable) -> Callable:
    """``(args, positions) -> J``: the Jacobian (forward mode) of ``fun(*args)``'s inexact output
    leaves with respect to ``args``' leaves at ``positions``, ``J[i][j]`` of shape
    ``out_i.shape + leaf_j.shape``."""

    def jacobian(args, positions):
        leaves, treedef = jax.tree_util.tree_flatten(args)

        def outputs(chosen):
            new = list(leaves)
            for i, x in zip(positions, chosen):
                new[i] = x
            out = fun(*jax.tree_util.tree_unflatten(treedef, new))
            return [o for o in jax.tree_util.tree_leaves(out) if eqx.is_inexact_array(o)]

        return jax.jacfwd(outputs)([leaves[i] for i in positions])

    return jacobian


@jax.custom_jvp
def _with_tangents(values, jac, thetas):
    """``values``, whose tangents are the Jacobian ``jac``'s contraction with those of ``thetas``."""
    return values


@_with_tangents.defjvp
def _with_tangents_jvp(primals, tangents):
    import jax.numpy as jnp

    values, jac, thetas = primals
    t_thetas = tangents[2]
    out = []
    for value, row in zip(values, jac):
        t = sum(jnp.tensordot(j, dt, axes=jnp.ndim(dt)) for j, dt in zip(row, t_thetas))
        out.append(jnp.asarray(t, value.dtype))
    return values, out


def _can_leave_traces() -> bool:
    try:
        from jax._src import core

        return hasattr(core, "set_current_trace") and hasattr(core, "eval_trace")
    except ImportError:  # pragma: no cover
        return False


def _outside_traces(inside: bool):
    """A context that runs under JAX's evaluation trace (values in, values out)."""
    if not inside:
        return contextlib.nullcontext()
    from jax._src import core

    return core.set_current_trace(core.eval_trace)


def _out_structure(out_template: Callable[[], Any]):
    return jax.tree_util.tree_structure(out_template())


def _load_or_export(name, key, fun, leaves, static, treedef, out_template, quick=False) -> Callable | None:
    from jax import export as jex

    paths = _paths(key)
    out_def = _out_structure(out_template)
    exported, lapack, custom = None, True, True
    if paths is not None and paths[0].exists() and paths[1].exists():
        program_path, meta_path = paths
        try:
            meta = json.loads(meta_path.read_text())
            candidate = jex.deserialize(bytearray(program_path.read_bytes()))
            if (
                meta.get("out") == _describe(out_def, strict=False)
                and candidate.out_tree.num_leaves == out_def.num_leaves
            ):
                exported, lapack = candidate, meta.get("lapack", True) is not False
                custom = meta.get("custom_calls", True) is not False
        except Exception:  # a damaged or foreign file: export again
            exported = None
    if exported is None:
        traced_out = []

        def flat(*xs):
            arrays = jax.tree_util.tree_unflatten(treedef, xs)
            out = fun(*eqx.combine(arrays, static))
            traced_out.append(jax.tree_util.tree_structure(out))
            return tuple(jax.tree_util.tree_leaves(out))

        flat.__name__ = flat.__qualname__ = f"export_{name}"

        try:
            avals = [jax.ShapeDtypeStruct(x.shape, x.dtype) for x in leaves]
            exported, lowered = _export_lowered(jax.jit(flat), avals)
            if traced_out[-1] != out_def:  # the template does not describe the output
                return None
            # the module's bytecode holds its operations' and custom calls' names as strings
            module = bytes(exported.mlir_module_serialized)
            lapack = b"lapack" in module  # a LAPACK call (none in the solver's)
            custom = b"custom_call" in module  # any call of a kernel registered at run time
        except Exception as err:  # e.g. a host callback: not exportable, trace as usual
            _warn_not_exported(err)
            return None
        runner = _runner(name, key, exported, leaves, out_def, lapack, custom, lowered, quick)
        if paths is None:  # no cache directory: the export is this process's only
            return runner
        program_path, meta_path = paths
        try:  # written while XLA compiles the program (another thread)
            _write(program_path, bytes(exported.serialize()))
            meta = {"out": _describe(out_def, strict=False), "lapack": lapack, "custom_calls": custom}
            _write(meta_path, json.dumps(meta).encode())
        except Exception as err:  # pragma: no cover - e.g. a full disk: traced again next time
            _warn_not_exported(err)
        return runner
    return _runner(name, key, exported, leaves, out_def, lapack, custom)


def _warn_not_exported(err: Exception) -> None:
    warnings.warn(
        f"lc.solve could not export its program ({type(err).__name__}: {err}); it is traced "
        "in every new process (LDAP_JAX_EXPORT=0 turns exports off)",
        stacklevel=5,
    )


class _Background:
    """``fun()`` in a thread of its own (XLA's compilation releases the GIL, so the caller traces
    and lowers other programs meanwhile); :meth:`result` waits for its value or raises its error.
    ``fun`` returns ``(value, then)``: ``then`` (or ``None``) runs in that thread after the value
    is handed over (storing the executable). The thread is not a daemon: a process waits for it
    before it exits."""

    def __init__(self, fun: Callable, name: str):
        self._done = threading.Event()
        self._value: Any = None
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, args=(fun,), name=f"ldap_jax-{name}", daemon=False)
        self._thread.start()

    def _run(self, fun: Callable) -> None:
        then = None
        try:
            self._value, then = fun()
        except BaseException as err:  # handed to the caller of result()
            self._error = err
        finally:
            self._done.set()
        if then is not None:
            then()

    def result(self) -> Any:
        self._done.wait()
        if self._error is not None:
            raise self._error
        return self._value

    def forget(self) -> None:
        """Drop the value (its caller holds it)."""
        self._value = None


def _runner(
    name, key, exported, leaves, out_def, lapack: bool, custom: bool, lowered=None, quick: bool = False
) -> Callable:
    """The call of an exported program on its array leaves. Its compilation (or the load of its
    stored executable) starts at once in a thread of its own; the first call waits for it.
    ``lowered``: the module the export was made from, compiled as it is (see :func:`_executable`);
    ``quick``: compiled first with :data:`QUICK_OPTIONS` (see :func:`prepare`)."""
    from .._compilation_cache import compiler_options

    compiled = _compiled(exported, name)
    executable: list = [None]  # the compiled program, once the first call has it
    optimised: list = [None]  # with quick: the program with the library's options, once ready
    deferred: list = [None]  # with quick and no cache directory: its compilation, not yet started
    deferred_lock = threading.Lock()
    stored = export_dir() is not None  # decided here, not in the compiling thread
    avals = [jax.ShapeDtypeStruct(x.shape, x.dtype) for x in leaves]

    # the quick program only for the first program of a process that asks for one: later in a
    # process the second compilation competes with the process's own work (other programs'
    # compilations) for the cores, and costs more than it saves
    quick = quick and lowered is not None and not custom and not _quick_spent[0] and _quick_allowed()
    if quick:
        _quick_spent[0] = True

    def build():
        if not quick:
            return _executable(key, compiled, exported, avals, lapack, custom, lowered)
        first = _quick_program(lowered, compiler_options() or {})
        if first is None:  # an XLA that knows none of the quick options: compiled once
            return _executable(key, compiled, exported, avals, lapack, custom, lowered)

        def then():
            program, store = _executable(key, compiled, exported, avals, lapack, custom, lowered)
            optimised[0] = program
            if store is not None:
                store()

        if not stored:
            # nothing to store: the optimised program would serve only later calls in this
            # process, so a second call starts it (a one-shot script exits after its answer
            # instead of waiting for a compilation that no call uses)
            deferred[0] = then
            return first, None
        return first, then

    pending = _Background(build, name)

    def start_deferred():
        with deferred_lock:
            then, deferred[0] = deferred[0], None
        if then is not None:
            _Background(lambda: (None, then), f"{name}-optimised")

    def runner(xs):
        # NumPy arrays: never weakly typed, so a value made under grad (a Python number that
        # became a weak-typed array) meets the same compiled program, not a copy compiled again
        xs = [np.asarray(x) for x in xs]
        if optimised[0] is not None:
            executable[0] = None  # the quick program: no longer held (nor its memory mappings)
            return jax.tree_util.tree_unflatten(out_def, optimised[0](*xs))
        if executable[0] is None:
            with _lock:  # the first call (the one that waits for the program) in one thread
                if executable[0] is None:
                    program = pending.result()
                    outs = program(*xs)
                    executable[0] = program
                    pending.forget()
                    return jax.tree_util.tree_unflatten(out_def, outs)
        if deferred[0] is not None:
            start_deferred()
        return jax.tree_util.tree_unflatten(out_def, executable[0](*xs))

    runner.out_shapes = jax.tree_util.tree_unflatten(
        out_def, [jax.ShapeDtypeStruct(a.shape, a.dtype) for a in exported.out_avals]
    )
    return runner


def _executable(
    key: str, compiled, exported, xs: list, lapack: bool, custom: bool, lowered=None
) -> tuple[Callable, Any]:
    """The compiled program of an export for arguments of the shapes of ``xs``, and a function that
    stores its executable (or ``None``): ``(program, store)``.

    Through ``jax.jit`` a process lowers the exported module (0.2-0.4 s of a warm first solve) to
    look the program up in JAX's persistent cache. Instead, the process that compiles the program
    stores its executable next to the export (``<key>.<machine>.executable``, keyed by the
    backend's platform, its version, the devices and ``XLA_FLAGS``), and later processes load it
    without lowering. An executable that XLA read back from JAX's own cache serialises without
    its kernels, so only one compiled in this process is stored; one that does not load is
    compiled through ``jax.jit`` as before. A program with a custom call (a LAPACK kernel) is
    never stored: JAX registers those kernels while lowering, and an executable loaded without
    that crashed the process at its first call (the gait tracker's)."""
    if custom:
        if lapack:
            return compiled, None
        return _lowered_without_lapack_setup(compiled), None
    path = _executable_path(key)
    in_tree = jax.tree_util.tree_structure((tuple(xs), {}))
    if path is not None and path.exists():
        try:
            from jax.experimental.serialize_executable import deserialize_and_load

            loaded = deserialize_and_load(zlib.decompress(path.read_bytes()), in_tree, exported.out_tree)
            return _checked_first_call(loaded, compiled, path, lapack), None
        except Exception:  # a damaged or foreign file: lower and compile as usual
            pass
    events = []

    def listener(event, **kwargs):
        if event.startswith("/jax/compilation_cache/") and threading.get_ident() == thread:
            events.append(event)

    thread = threading.get_ident()
    jax.monitoring.register_event_listener(listener)
    try:
        if lowered is not None:  # the export's own lowering: neither deserialised nor lowered again
            from .._compilation_cache import compiler_options

            executable = _compile_lowered(lowered, compiler_options())
        else:
            with contextlib.nullcontext() if lapack else _without_lapack_setup():
                lowered = compiled.lower(*xs)
            executable = lowered.compile()
    finally:
        jax.monitoring.unregister_event_listener(listener)
    # stored only when XLA compiled it here: JAX's cache was asked and had no copy (an
    # executable JAX already held in this process may have come from its cache)
    asked = "/jax/compilation_cache/compile_requests_use_cache" in events
    compiled_here = asked and "/jax/compilation_cache/cache_hits" not in events
    if path is None or not compiled_here:
        return executable, None

    def store():  # after the program is handed over: off the first call's path
        try:
            from jax.experimental.serialize_executable import serialize

            _write(path, zlib.compress(serialize(executable)[0], 1))
        except Exception:  # pragma: no cover - a backend that cannot serialise: not stored
            pass

    return executable, store


def _lowered_without_lapack_setup(compiled) -> Callable:
    """``compiled`` (``jax.jit``), its first call (which lowers it) without JAX's LAPACK set-up."""
    state = [False]

    def call(*xs):
        if state[0]:
            return compiled(*xs)
        with _without_lapack_setup():
            out = compiled(*xs)
        state[0] = True
        return out

    return call


def _checked_first_call(loaded, compiled, path: pathlib.Path, lapack: bool) -> Callable:
    """``loaded``, whose first call falls back to ``compiled`` (``jax.jit``) if it fails (an
    executable without its kernels fails when run): the file is then removed."""
    state = [False]

    def call(*xs):
        if state[0]:
            return loaded(*xs)
        try:
            out = jax.block_until_ready(loaded(*xs))
        except Exception:
            with contextlib.suppress(OSError):
                path.unlink()
            with contextlib.nullcontext() if lapack else _without_lapack_setup():
                return compiled(*xs)
        state[0] = True
        return out

    return call


def _executable_path(key: str) -> pathlib.Path | None:
    """Where the executable of the export ``key`` for this machine's backend is kept (``None``:
    nowhere, without a cache directory)."""
    if export_dir() is None:
        return None
    try:
        devices = jax.devices()
        backend = devices[0].client
        text = [backend.platform, backend.platform_version, os.environ.get("XLA_FLAGS", "")]
        text += [d.device_kind for d in devices]
        try:
            from jax._src.lib import xla_client

            text.append(str(xla_client.get_topology_for_devices(devices).fingerprint()))
        except Exception:  # no topology for this backend: its devices' kinds
            pass
    except Exception:  # pragma: no cover
        return None
    text.append(_host_cpu())
    machine = hashlib.sha256("\n".join(text).encode()).hexdigest()[:16]
    return export_dir() / f"{key}.{machine}.executable"


def _host_cpu() -> str:
    """The host's processor and the instruction-set extensions it offers (Linux: ``/proc/cpuinfo``'s
    first ``flags`` line; elsewhere what :mod:`platform` says): XLA compiles for the host's CPU,
    and a cache folder shared by machines with different CPUs (a cluster's file system) must not
    hand one of them machine code it cannot run."""
    import platform

    text = f"{platform.machine()} {platform.processor()}"
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith(("flags", "Features")):
                    return f"{text} {line.split(':', 1)[-1].strip()}"
    except OSError:
        pass
    return text


_quick_spent = [False]  # a quick program was compiled in this process


def _quick_allowed() -> bool:
    return os.environ.get("LDAP_JAX_QUICK_FIRST", "1").strip() not in ("0", "false", "False")


#: XLA options of a first, quick compilation (:func:`prepare`'s ``quick``): LLVM without its
#: optimisation passes (``parallel_park``'s run program: XLA's compilation 3.9 against 7.7 s of
#: CPU, the run 136-144 ms against 46-49 ms, the solution the same to 8e-14, 21 iterations), nor
#: its expensive ones, XLA's fast-compile preset of HLO passes and one LLVM module instead of
#: several compiled on threads (the optimised program compiles on the other core meanwhile): on
#: top of the first, XLA's compilation of that program 0.8x again
QUICK_OPTIONS: dict[str, Any] = {
    "xla_backend_optimization_level": 0,
    "xla_llvm_disable_expensive_passes": True,
    "xla_cpu_opt_preset": "CPU_OPT_PRESET_FAST_COMPILE",
    "xla_cpu_parallel_codegen_split_count": 1,
}
#: the quick options an older XLA may not know (it rejects the compilation): then tried without them
QUICK_NEWER = ("xla_cpu_opt_preset", "xla_cpu_parallel_codegen_split_count")


def _quick_program(lowered, options: dict):
    """``lowered`` compiled with ``options`` and :data:`QUICK_OPTIONS` on top; without the options
    of :data:`QUICK_NEWER` if XLA rejects them, or ``None`` if it rejects the rest too."""
    quick = {**options, **QUICK_OPTIONS}
    older = {k: v for k, v in quick.items() if k not in QUICK_NEWER}
    # the older set only where it differs from both (else it is the quick or the optimised program)
    for candidate in (quick, older) if older not in (quick, options) else (quick,):
        try:
            return _compile_lowered(lowered, candidate)
        except Exception:  # an XLA without (some of) these options: fewer, or none
            continue
    return None


def _compile_lowered(lowered, options: dict | None):
    """``lowered.compile(options)`` without writing JAX's persistent cache: the executable of an
    export's own lowering is stored next to the export (:func:`_executable`), and JAX's key for
    that module is never looked up again (a later process lowers the export, another module).
    The write (serialising and compressing a few MB) would delay the program's first call."""
    import math

    from jax._src import config

    with config.persistent_cache_min_compile_time_secs(math.inf):
        return lowered.compile(options)


def _export_lowered(fun_jit, avals: list) -> tuple[Any, Any]:
    """``(exported, lowered)``: ``jax.export`` of ``fun_jit`` at ``avals`` without source locations
    (:func:`_without_locations`), and the lowered module it was made from (``None`` where this
    JAX's export cannot be taken apart: then as ``jax.export`` does, and stripped afterwards).

    The module is stripped where it was lowered, before it is serialised, and XLA compiles that
    module as it is: a first solve neither deserialises the module to strip it nor lowers the
    export again to compile it (with MLIR's set-up, 0.3-0.5 s of the cold first solve). The
    lowering leaves Python's tracebacks out of the locations (``parallel_park``'s run: 0.59
    against 0.71 s, five alternating pairs under load)."""
    try:
        from jax._src import config
        from jax._src.export import _export as internal
        from jax._src.interpreters import mlir
        from jax._src.lib.mlir import passmanager

        traced = fun_jit.trace(*avals)
        # no Python tracebacks in the locations (they are stripped): a sixth shorter lowering
        with config.traceback_in_locations_limit(0):
            lowered = traced.lower(
                lowering_platforms=(internal.default_export_platform(),),
                _private_parameters=mlir.LoweringParameters(
                    for_export=True,
                    hoist_constants_as_args=False,
                    export_ignore_forward_compatibility=config.export_ignore_forward_compatibility.value,
                ),
            )
        module = lowered._lowering.stablehlo()
        with module.context:
            passmanager.PassManager.parse("builtin.module(strip-debuginfo)").run(module.operation)
        return internal._export_lowered(lowered, traced.jaxpr, traced.fun_name), lowered
    except (ImportError, AttributeError, TypeError):  # pragma: no cover - a future JAX
        from jax import export as jex

        return _without_locations(jex.export(fun_jit)(*avals)), None


def _without_locations(exported):
    """``exported`` with its module's source locations removed (MLIR's ``strip-debuginfo``).

    Every operation of a traced module carries its Python traceback and name stack, which XLA
    keeps as metadata on each instruction of the compiled program and of its serialized
    executable: stripped, the solver's run executable is a quarter smaller (4.3 -> 3.1 MB on
    ``parallel_park``) and XLA deserialises it in 0.41 s of CPU instead of 0.46 s (best of six,
    alternating in one process); its compilation takes as long. An export that cannot be
    stripped (a future JAX) is kept as it is."""
    try:
        import dataclasses

        from jax._src.export import _export as internal
        from jax._src.interpreters import mlir
        from jax._src.lib import _jax
        from jax._src.lib.mlir import passmanager

        with mlir.make_ir_context():
            module = _jax.mlir.deserialize_portable_artifact(exported.mlir_module_serialized)
            passmanager.PassManager.parse("builtin.module(strip-debuginfo)").run(module.operation)
            stripped = internal._module_to_bytecode(module)
        return dataclasses.replace(exported, mlir_module_serialized=stripped)
    except Exception:  # pragma: no cover - a future JAX: keep the locations
        return exported


_skip_lapack_threads: dict[int, int] = {}  # the threads lowering without JAX's LAPACK set-up
_skip_lapack_original: list = []  # JAX's own set-up while ours stands in for it


@contextlib.contextmanager
def _without_lapack_setup():
    """Lower an exported program without JAX's set-up of LAPACK on the CPU, in this thread.

    Lowering any exported program for the CPU first sets up jaxlib's LAPACK kernels, which imports
    SciPy's LAPACK (``scipy.linalg``): 0.4-1.4 s of a warm first solve of 1-3 s, measured. The
    solver's programs hold no LAPACK call (checked at export: ``"lapack"`` in the module), so
    theirs is skipped; a program with one is lowered as JAX does. Other threads are unaffected
    (programs are lowered in several threads at once: see :class:`_Background`).
    """
    try:
        from jax._src.export import _export as internal

        internal._ensure_backends_initialized  # noqa: B018 - present in this JAX
    except (ImportError, AttributeError):  # pragma: no cover - a future JAX: as JAX does
        yield
        return
    thread = threading.get_ident()
    with _lock_lapack:
        if not _skip_lapack_threads:
            original = internal._ensure_backends_initialized
            _skip_lapack_original.append(original)

            def ensure(platforms):
                if threading.get_ident() in _skip_lapack_threads:
                    return None
                return original(platforms)

            internal._ensure_backends_initialized = ensure
        _skip_lapack_threads[thread] = _skip_lapack_threads.get(thread, 0) + 1
    try:
        yield
    finally:
        with _lock_lapack:
            _skip_lapack_threads[thread] -= 1
            if not _skip_lapack_threads[thread]:
                del _skip_lapack_threads[thread]
            if not _skip_lapack_threads:
                internal._ensure_backends_initialized = _skip_lapack_original.pop()
