"""A :class:`Task` in the stage form of :mod:`._kkt`, on the discrete dynamics of its integrator.

The stage state ``chi_j = (x_{j-1}, u_{j-1}, s_{j-1}, z, u_0)`` (``j = 1 .. K``, ``K = N + 1``)
holds node ``j - 1``: the integrator's flat state ``x`` (:func:`ldap_jax.discretize`; for RDP
``(q, P, nu)``, the configuration and the momenta the next step reads), the scaled node controls
``u``, and one entry ``s`` per path constraint, the constraint's value at the node: the dynamics
compute it from the next node, so ``s_j <= 0`` is a simple bound and a guess that violates the
constraint is a multiple-shooting defect, not a barrier failure. The control of stage ``j`` is
the next node's scaled controls ``v_j = u_j``.

* A task with a fixed start has the initial parameters ``p = u_0`` and
  ``chi_1 = (x_0(q_0, qdot_0, u_0), u_0, s_0)``.
* A periodic task (:class:`~ldap_jax.control.Periodic`) has ``p = (z, u_0)``: ``z`` is the start's
  reduced state in the flat coordinates (the non-cyclic shape and the momenta ``P`` of the
  force-driven shape coordinates and ``nu``), the group at the identity and the cyclic shape
  coordinates at 0. ``chi`` carries constant copies of ``z`` and ``u_0`` (passive entries), so that
  the return conditions ``reduced(x_N) = z``, ``u_N = u_0`` and the start's anchor conditions are
  terminal equalities, and the Riccati recursion keeps its stage-wise structure.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._discrete import DiscreteDynamics
from ._constraints import AbstractInitialConstraint, AbstractTerminalConstraint
from ._ipm import pushed
from ._kkt import OCPFunctions
from ._terms import Node

__all__ = ["Layout", "layout", "problem_functions", "to_variables", "from_variables"]


class Layout(NamedTuple):
    """The static sizes of a task's stage form and where its parts sit."""

    nx: int  # flat state
    m: int  # controls
    n_path: int  # path-constraint entries
    reduced: tuple[int, ...]  # indices of the reduced state in x (periodic tasks; else ())
    periodic: bool

    @property
    def nz(self) -> int:
        return len(self.reduced)

    @property
    def n_passive(self) -> int:
        return self.nz + self.m if self.periodic else 0

    @property
    def n(self) -> int:
        return self.nx + self.m + self.n_path + self.n_passive

    def split(self, chi: Array):
        """``(x, u, s, z, u0)`` of a stage state (``z``, ``u0``: copies, empty unless periodic)."""
        a = self.nx
        b = a + self.m
        c = b + self.n_path
        d = c + (self.nz if self.periodic else 0)
        return chi[:a], chi[a:b], chi[b:c], chi[c:d], chi[d:]


def _reduced_indices(task, dyn: DiscreteDynamics) -> tuple[int, ...]:
    """Indices in the flat RDP state ``(q, P, nu)`` of the reduced state: the non-cyclic shape
    coordinates, ``P`` of the force-driven shape coordinates, and ``nu``."""
    system = task.system
    d, n = system.n_config, system.n_shape
    cyclic = set(task.periodic.cyclic)
    shape = [3 + i for i, name in enumerate(system.shape_names) if name not in cyclic]
    momenta = [d + i for i in system.dynamic_index]
    return tuple(shape + momenta + list(range(d + n, dyn.n_state)))


def layout(task, dyn: DiscreteDynamics) -> Layout:
    n_path = 0
    if task.path_constraints:
        z = jnp.zeros(task.system.n_config)
        obs, c = Node(z, z), jnp.zeros(task.system.n_controls)
        for con in task.path_constraints:
            n_path += jax.eval_shape(lambda con=con: con.residual(task.system, jnp.zeros(()), obs, c)).shape[
                0
            ]
    periodic = task.periodic is not None
    reduced = _reduced_indices(task, dyn) if periodic else ()
    return Layout(dyn.n_state, task.system.n_controls, n_path, reduced, periodic)


class _Parts:
    """The pieces of the stage functions of one task (closures over the task and its dynamics)."""

    def __init__(self, task, dyn: DiscreteDynamics, lay: Layout):
        self.task, self.dyn, self.lay = task, dyn, lay
        self.system = task.system
        self.scale = task.parameterization.scale
        self.h = task.h

    def node(self, x, c) -> Node:
        return Node(*self.dyn.node(x, c))

    def slacks(self, k, x, c) -> Array:
        if not self.lay.n_path:
            return jnp.zeros((0,), x.dtype)
        t = jnp.asarray(k, x.dtype) * self.h
        obs = self.node(x, c)
        return jnp.concatenate([con.residual(self.system, t, obs, c) for con in self.task.path_constraints])

    def start(self, z) -> Array:
        """The flat start of a periodic task from its reduced state ``z``."""
        x0 = jnp.zeros((self.lay.nx,), z.dtype)
        return x0.at[jnp.asarray(self.lay.reduced, int)].set(z)

    def q0(self, chi) -> Array:
        """The initial configuration the terminal terms measure from."""
        if not self.lay.periodic:
            return self.task.q0.astype(chi.dtype)
        return self.start(self.lay.split(chi)[3])[: self.system.n_config]


def problem_functions(task, dyn: DiscreteDynamics, *, curvature: DiscreteDynamics | None = None):
    """The task's problem in the stage form of :mod:`._kkt`: returns ``(functions, lo, hi, layout)``.

    ``curvature``: the discrete dynamics whose second derivatives stand in for ``dyn``'s in the
    Hessian of the Lagrangian (see :func:`ldap_jax.control.curvature_integrator`)."""
    lay = layout(task, dyn)
    parts = _Parts(task, dyn, lay)
    system, scale, h = task.system, parts.scale, parts.h
    objective = task.objective
    reads_nodes = any(t.reads_nodes for t in objective)

    def assemble(x, u, k, copies):
        return jnp.concatenate([x, u, parts.slacks(k, x, u * scale), *copies])

    def first(p):
        if lay.periodic:
            z, u0 = p[: lay.nz], p[lay.nz :]
            return assemble(parts.start(z), u0, 0, (z, u0))
        x0 = dyn.init(task.q0.astype(p.dtype), task.qdot0.astype(p.dtype), p * scale)
        return assemble(x0, p, 0, ())

    def stepper(discrete: DiscreteDynamics):
        def dynamics(chi, v, k):
            x, u, _, z, u0 = lay.split(chi)
            x1 = discrete.step(x, u * scale, v * scale, k)
            return assemble(x1, v, k + 1, (z, u0) if lay.periodic else ())

        return dynamics

    def stage_cost(chi, v):
        x, u, *_ = lay.split(chi)
        c0, c1 = u * scale, v * scale
        out = jnp.zeros((), chi.dtype)
        obs = parts.node(x, c0) if reads_nodes else None
        for t in objective:
            if t.reads_nodes:
                out = out + t.stage(system, obs, c0, h)
            out = out + t.interval(system, c0, c1, h)
        return out

    def terminal_cost(chi):
        x, u, *_ = lay.split(chi)
        c = u * scale
        obs = parts.node(x, c)
        q0 = parts.q0(chi)
        return sum(
            (t.stage(system, obs, c, h) + t.terminal(system, obs, q0) for t in objective),
            jnp.zeros((), chi.dtype),
        )

    def terminal(chi):
        x, u, _, z, u0 = lay.split(chi)
        obs = parts.node(x, u * scale)
        q0 = parts.q0(chi)
        out = [
            con.residual(system, obs, q0)
            for con in task.constraints
            if isinstance(con, AbstractTerminalConstraint)
        ]
        if lay.periodic:
            out += [x[jnp.asarray(lay.reduced, int)] - z, u - u0]
            start = parts.node(parts.start(z), u0 * scale)
            out += [
                con.residual(system, start, u0 * scale)
                for con in task.constraints
                if isinstance(con, AbstractInitialConstraint)
            ]
        return jnp.concatenate(out) if out else jnp.zeros((0,), chi.dtype)

    lo, hi = _stage_bounds(task, lay, scale)

    def perturbation(p, v, key, size):
        # uniform, ``size`` times the half-width of the control bounds (times 1 where infinite)
        v_lo, v_hi = lo[lay.nx : lay.nx + lay.m], hi[lay.nx : lay.nx + lay.m]
        half = jnp.where(jnp.isfinite(v_hi - v_lo), 0.5 * (v_hi - v_lo), 1.0)
        k1, k2 = jax.random.split(key)
        u0 = p[p.shape[0] - lay.m :]
        u0 = pushed(
            u0 + size * half * jax.random.uniform(k1, u0.shape, u0.dtype, -1.0, 1.0), v_lo, v_hi, 1e-2
        )
        noise = jax.random.uniform(k2, v.shape, v.dtype, -1.0, 1.0)
        v = pushed(v + size * half[None] * noise, v_lo[None], v_hi[None], 1e-2)
        return p.at[p.shape[0] - lay.m :].set(u0), v

    curved = None if curvature is None else stepper(curvature)
    fns = OCPFunctions(
        first=first,
        dynamics=stepper(dyn),
        stage_cost=stage_cost,
        terminal_cost=terminal_cost,
        terminal=terminal,
        curvature_dynamics=curved,
        perturbation=perturbation,
        n_passive=lay.n_passive,
    )
    return fns, lo, hi, lay


def _stage_bounds(task, lay: Layout, scale: Array) -> tuple[Array, Array]:
    """``lo``, ``hi`` (n,): the configuration bounds on ``x``'s ``q`` part, the control bounds
    (scaled) on ``u``, ``s <= 0`` on the path constraints, nothing on the rest."""
    b = task.bounds
    d = task.system.n_config
    dtype = b.q_lower.dtype
    inf = np.inf
    lo = jnp.concatenate(
        [
            b.q_lower,
            jnp.full(lay.nx - d, -inf, dtype),
            b.u_lower / scale,
            jnp.full(lay.n_path, -inf, dtype),
            jnp.full(lay.n_passive, -inf, dtype),
        ]
    )
    hi = jnp.concatenate(
        [
            b.q_upper,
            jnp.full(lay.nx - d, inf, dtype),
            b.u_upper / scale,
            jnp.zeros(lay.n_path, dtype),
            jnp.full(lay.n_passive, inf, dtype),
        ]
    )
    return lo, hi


def to_variables(lay: Layout, params) -> tuple[Array, Array]:
    """``(p, v)`` of a task's parameters: the initial parameters and the controls ``v_1 .. v_N``."""
    if lay.periodic:
        u = params.controls
        return jnp.concatenate([params.state, u[0]]), u[1:]
    return params[0], params[1:]


def from_variables(lay: Layout, p: Array, v: Array):
    """A task's parameters from ``(p, v)`` (the inverse of :func:`to_variables`)."""
    from ._task import GaitParams

    u = jnp.concatenate([p[p.shape[0] - lay.m :][None], v])
    return GaitParams(u, p[: lay.nz]) if lay.periodic else u
