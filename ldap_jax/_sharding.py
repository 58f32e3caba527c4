"""A batch split over devices: :func:`shard_vmap`, the one-axis mesh it uses by default, and
:func:`global_batch`, a batch whose processes each build only their own rows.

``jax.vmap`` runs a batch as one program on one device; on a CPU that is one core, whatever the
machine has. :func:`shard_vmap` is ``jax.vmap`` with the batch split over the devices of a mesh
by ``jax.shard_map``, so that each device runs the vmapped function on its own members, with its
own loops: a ``while_loop`` under ``vmap`` runs until the slowest member in the batch is done,
and here until the slowest member on each device is. On a CPU, make one device per core before
JAX starts: :func:`use_cpu_cores`.

When JAX runs as several processes (``jax.distributed.initialize``, e.g. through
:mod:`ldap_jax.launch`), ``jax.devices()`` lists the devices of every process and the same
functions split a batch over all of them: each process runs the members its own devices hold,
and the results are global arrays (each process holds its devices' rows). Arguments are then
global arrays, best built by :func:`global_batch` so that no process makes the whole batch, or
host arrays with the same value in every process.
"""

from __future__ import annotations

import functools
import os
import re
from collections.abc import Callable, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from ._compilation_cache import jit

__all__ = ["device_mesh", "global_batch", "shard_vmap", "use_cpu_cores"]

_AXIS = "batch"
_COUNT_FLAG = "--xla_force_host_platform_device_count"


def use_cpu_cores(n: int | None = None) -> int:
    """Ask XLA for ``n`` host (CPU) devices, one per core (default: ``os.cpu_count()``), so that
    :func:`shard_vmap` and the study split a batch over the cores; it appends
    ``--xla_force_host_platform_device_count=n`` to ``XLA_FLAGS``.

    XLA reads the flag when JAX's backend starts (the first computation, or ``jax.devices()``):
    call this after importing the library and before anything runs. A count already in
    ``XLA_FLAGS`` is kept; once the backend has started nothing changes.

    Returns:
        The number of host devices JAX has, or will have when it starts.

    Raises:
        ValueError: ``n`` is not a positive integer.

    Example:
        >>> import ldap_jax as lj
        >>> lj.use_cpu_cores()  # e.g. 2 on a 2-core machine
    """
    if n is None:
        n = os.cpu_count() or 1
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"'n' must be a positive integer, got {n!r}")
    if _backend_started():
        return len(jax.devices("cpu"))  # host devices, also where an accelerator is the default
    flags = os.environ.get("XLA_FLAGS", "")
    given = re.search(rf"{_COUNT_FLAG}=(\d+)", flags)
    if given:
        return int(given.group(1))
    os.environ["XLA_FLAGS"] = f"{flags} {_COUNT_FLAG}={int(n)}".strip()
    return int(n)


def _backend_started() -> bool:
    try:
        from jax._src import xla_bridge

        return bool(xla_bridge.backends_are_initialized())
    except (ImportError, AttributeError):  # pragma: no cover - another JAX: assume it has
        return True


def device_mesh(devices: Sequence[jax.Device] | None = None) -> Mesh:
    """A one-axis mesh ``("batch",)`` over ``devices`` (default: all of ``jax.devices()``, i.e.
    every GPU of the node, or of every host after ``jax.distributed.initialize()``)."""
    if devices is not None:
        if isinstance(devices, (str, bytes, jax.Device)):
            raise TypeError(
                f"'devices' must be a sequence of jax devices (e.g. jax.devices()), got {devices!r}"
            )
        devices = list(devices)
        if not devices or not all(isinstance(d, jax.Device) for d in devices):
            raise ValueError(f"'devices' must be a non-empty sequence of jax devices, got {devices!r}")
        if len(set(devices)) != len(devices):
            raise ValueError(f"'devices' must be distinct, got {devices!r}")
    devices = jax.devices() if devices is None else devices
    return Mesh(np.asarray(devices), (_AXIS,))


def global_batch(make: Callable[[np.ndarray], Any], n: int, *, mesh: Mesh | None = None) -> Any:
    """A batch of ``n`` members as global arrays split over the devices of ``mesh`` along their
    leading axis (``NamedSharding(mesh, P("batch"))``), of which each process builds only the rows
    of its own devices: in a run of several processes, no process holds the whole batch.

    The batch is padded to a multiple of the number of devices with copies of its last member
    (as :func:`shard_vmap` pads); ``make`` is called once per device of this process with the
    global indices of that device's rows, so a batch made from a seed and member indices is the
    same whatever the number of processes, and ``shard_vmap`` takes it without padding again.

    Args:
        make: ``make(indices) -> pytree``: the members ``indices`` (a NumPy ``int64`` array of
            global indices in ``[0, n)``), every leaf an array with leading size
            ``len(indices)``; the same tree structure, trailing shapes and dtypes for every call.
        n: the number of members.
        mesh: a mesh with one axis (default: :func:`device_mesh`, the devices of all processes).

    Returns:
        ``make``'s pytree of global arrays, leading size ``n`` rounded up to a multiple of the
        number of devices; rows ``n`` and beyond repeat member ``n - 1``.

    Raises:
        ValueError: ``n`` is not a positive integer, ``mesh`` has more than one axis, or
            ``make`` returns leaves of another leading size.

    Example:
        >>> keys = lambda idx: jax.random.split(jax.random.PRNGKey(0), 1000)[idx]
        >>> batch = lj.global_batch(lambda idx: jax.vmap(car.sample_maneuver)(keys(idx)), 1000)
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"'n' must be a positive integer, got {n!r}")
    mesh = device_mesh() if mesh is None else mesh
    if len(mesh.axis_names) != 1:
        raise ValueError(f"'mesh' must have one axis, got {mesh.axis_names}")
    size = mesh.devices.size
    n_padded = -(-int(n) // size) * size
    sharding = NamedSharding(mesh, PartitionSpec(mesh.axis_names[0]))
    # the rows of each of this process's devices (a device may appear once in a mesh)
    rows = sharding.addressable_devices_indices_map((n_padded,))
    if not rows:
        raise ValueError(f"'mesh' holds no device of this process (process {jax.process_index()})")
    shards = {}
    for device, index in rows.items():
        indices = np.minimum(np.arange(n_padded)[index[0]], n - 1)
        part = make(indices)
        for leaf in jax.tree_util.tree_leaves(part):
            if np.shape(leaf)[:1] != (len(indices),):
                raise ValueError(
                    f"'make' must return leaves with leading size len(indices) = {len(indices)}, "
                    f"got shape {np.shape(leaf)}"
                )
        shards[device] = jax.device_put(part, device)
    parts = list(shards.values())
    treedef = jax.tree_util.tree_structure(parts[0])
    leaves = [jax.tree_util.tree_leaves(p) for p in parts]

    def assemble(i: int) -> jax.Array:
        first = leaves[0][i]
        shape = (n_padded, *first.shape[1:])
        return jax.make_array_from_single_device_arrays(shape, sharding, [ls[i] for ls in leaves])

    return jax.tree_util.tree_unflatten(treedef, [assemble(i) for i in range(len(leaves[0]))])


def shard_vmap(
    fn: Callable, *, in_axes: int | None | Sequence[int | None] = 0, mesh: Mesh | None = None
) -> Callable:
    """``jax.vmap(fn, in_axes)`` as one compiled program whose batch is split over the devices of
    ``mesh`` (default: :func:`device_mesh`, all devices).

    The batch is padded to a multiple of the number of devices (with copies of its last member,
    dropped from the result), split evenly (``jax.shard_map``), and each device runs
    ``jax.vmap(fn)`` on its part: its loops run until its own members are done, not the whole
    batch's. The result equals ``jax.vmap(fn, in_axes)(*args)``, up to the round-off of another
    compiled program. The program compiles with :func:`ldap_jax.compiler_options`, and once per
    argument structure and shapes (keep the returned function, as with ``jax.jit``; a batch the
    devices do not divide compiles a second, small one that drops the padding). It is
    differentiable in both modes: the gradient with respect to an argument given once
    (``in_axes=None``) is summed over the devices.

    In a run of several processes, the result of a batch whose size the devices divide stays split
    over them (each process holds its devices' rows; ``multihost_utils.process_allgather`` gathers
    them); for any other size, the padding is dropped by a second program, which gathers the whole
    result to every process. A batch made by :func:`global_batch` is padded already and stays
    split. Under the caller's own ``jax.jit`` that drop is part of the one program: a member
    that raises there (``simulate(..., throw=True)``) leaves the other devices waiting in it, and
    XLA ends the process after 40 s; read the result codes instead (``throw=False``, the default).

    Measured on 2 CPU cores (two host devices), 16 ``lc.solve`` calls on perturbed
    ``parallel_park`` goals: 0.27-0.36 s against 0.44-0.63 s for ``jax.vmap``; 64: 1.17-1.33 s
    against 1.89-2.22 s.

    Args:
        fn: the function of one member; its outputs are arrays (or pytrees of arrays and static
            values, such as a :class:`~ldap_jax.control.Solution`).
        in_axes: ``0`` (every positional argument is batched along its leading axis), ``None``
            (none is), or one of ``0``/``None`` per positional argument (``None``: the same for
            every member, e.g. a task or a model).
        mesh: a mesh with one axis named ``"batch"`` (:func:`device_mesh`; default: all devices).

    Returns:
        A function of the same positional arguments, returning ``fn``'s outputs with a leading
        batch axis.

    Raises:
        ValueError: (when called) no argument is batched, batched leaves that are not arrays or
            disagree on the batch size, an empty batch, a bad ``in_axes``, a mesh with more than
            one axis.

    Example:
        >>> solve_all = lj.shard_vmap(lambda g: lc.solve(task.with_options(goal=g)).params)
        >>> params = solve_all(goals)  # goals (B, 3)
    """
    if mesh is not None and not isinstance(mesh, Mesh):
        raise TypeError(f"'mesh' must be a jax.sharding.Mesh (lj.device_mesh(devices)), got {type(mesh)}")
    if mesh is not None and tuple(mesh.axis_names) != (_AXIS,):
        raise ValueError(f"'mesh' must have one axis named {_AXIS!r} (lj.device_mesh), got {mesh.axis_names}")

    @functools.wraps(fn)
    def batched(*args):
        axes = _in_axes(in_axes, len(args))
        n = _batch_size(args, axes)
        m = device_mesh() if mesh is None else mesh
        out, static = _program(fn, m, axes, n, args)
        leaves = jax.tree_util.tree_leaves(out)
        if leaves and leaves[0].shape[0] != n:
            # the padding dropped by a program of its own: in the sharded program, a slice to a size
            # the devices do not divide is a collective, which a device whose members raised (e.g.
            # simulate(throw=True)) never joins: XLA would abort the process after 40 s
            out = _take(out, n)
        return eqx.combine(out, static)

    return batched


def _in_axes(in_axes, n_args: int) -> tuple[int | None, ...]:
    axes = tuple(in_axes) if isinstance(in_axes, (tuple, list)) else (in_axes,) * n_args
    if len(axes) != n_args or any(a not in (0, None) or isinstance(a, bool) for a in axes):
        raise ValueError(
            f"'in_axes' must be 0, None, or one of 0/None per positional argument ({n_args}), got {in_axes!r}"
        )
    if 0 not in axes:
        raise ValueError("shard_vmap needs at least one batched argument (an in_axes of 0)")
    return axes


def _batch_size(args: tuple, axes: tuple) -> int:
    sizes = set()
    for i, (arg, axis) in enumerate(zip(args, axes)):
        if axis is None:
            continue
        for leaf in jax.tree_util.tree_leaves(arg):
            if not eqx.is_array_like(leaf) or np.ndim(leaf) == 0:
                raise ValueError(
                    f"argument {i} is batched (in_axes 0): every leaf must be an array with a leading "
                    f"batch axis, got {type(leaf).__name__} of shape {np.shape(leaf)}"
                )
            sizes.add(np.shape(leaf)[0])
    if len(sizes) != 1:
        raise ValueError(f"the batched arguments disagree on the batch size: {sorted(sizes)}")
    n = sizes.pop()
    if n == 0:
        raise ValueError("an empty batch")
    return n


@jit
def _program(fn: Callable, mesh: Mesh, axes: tuple, n: int, args: tuple):
    size = mesh.devices.size
    pad = (-n) % size

    def padded(x):
        return jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)]) if pad else x

    args = tuple(jax.tree_util.tree_map(padded, a) if ax == 0 else a for a, ax in zip(args, axes))
    dynamic, static = eqx.partition(args, eqx.is_array)
    spec = PartitionSpec(_AXIS)
    specs = tuple(
        jax.tree_util.tree_map(lambda _, ax=ax: spec if ax == 0 else PartitionSpec(), d)
        for d, ax in zip(dynamic, axes)
    )
    static_out: list[Any] = []

    def local(dyn):
        out = jax.vmap(fn, in_axes=axes)(*eqx.combine(dyn, static))
        out_dynamic, out_static = eqx.partition(out, eqx.is_array)
        static_out.append(out_static)
        return out_dynamic

    out = _shard_map(local, mesh, (specs,), spec)(dynamic)
    return out, static_out[0]


@jit
def _take(out, n: int):
    return jax.tree_util.tree_map(lambda x: x[:n], out)


def _shard_map(f: Callable, mesh: Mesh, in_specs, out_specs) -> Callable:
    """``jax.shard_map`` without its check of which values vary over the devices (loops whose
    carries start the same on every device vary after one trip); ``jax.experimental``'s before
    JAX 0.6."""
    if hasattr(jax, "shard_map"):
        return jax.shard_map(f, mesh=mesh, in_specs=in_specs, out_specs=out_specs, check_vma=False)
    from jax.experimental.shard_map import shard_map  # pragma: no cover - JAX < 0.6

    return shard_map(
        f, mesh=mesh, in_specs=in_specs, out_specs=out_specs, check_rep=False
    )  # pragma: no cover
