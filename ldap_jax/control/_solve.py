"""``lc.solve``: a task's optimal control problem with hard constraints, by the interior-point
method of :mod:`._ipm` on the discrete dynamics of the task's integrator."""

from __future__ import annotations

import dataclasses
import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._compilation_cache import jit
from .._discrete import DiscreteDynamics, discretize
from .._numerics import plain
from .._validation import check_array, check_positive_int, check_positive_number, is_concrete
from ..integrators import RDP, AbstractIntegrator
from ._costs import Node, TerminalRest, pose_error
from ._ipm import (
    SOLVER_RESULTS,
    IPMOptions,
    IPMState,
    OCPFunctions,
    _constraints,
    _derivatives,
    _pushed,
    _rollout,
    ipm_solve,
)
from ._parameterizations import SampledControls
from ._riccati import riccati_apply, riccati_factor
from ._tasks import Penalty, Task

__all__ = ["Solution", "solve", "problem_functions", "curvature_integrator"]


class Solution(eqx.Module):
    """The result of :func:`solve` (batched along leading axes under ``vmap``).

    Attributes:
        params: the optimal parameters, (N + 1, n_channels): ``task.controls(sol.params)`` are
            the controls.
        converged: the KKT error met ``tol``.
        iterations: interior-point iterations used.
        cost: the objective at the solution.
        max_violation: largest violation of the model's constraints at the solution (dynamics
            defects, terminal equalities, bounds; bounds are kept strictly by the method).
        kkt_error: the final scaled KKT error.
        result: a :data:`SOLVER_RESULTS` item (``SOLVER_RESULTS[sol.result]`` is the message).
        resets: how often the method restarted after a line search failed far from feasibility
            (see :mod:`ldap_jax.control._ipm`; from the second restart on with perturbed
            controls); 0 on most problems, 2 from rest.
        states: the flat states of the discrete dynamics at the nodes, (N + 1, n).
        multipliers: the dynamics multipliers (N + 1, n + n_channels) and the terminal ones (p,).
    """

    params: Float[Array, "K m"]
    converged: Bool[Array, ""]
    iterations: Int[Array, ""]
    cost: Float[Array, ""]
    max_violation: Float[Array, ""]
    kkt_error: Float[Array, ""]
    result: SOLVER_RESULTS
    resets: Int[Array, ""]
    states: Float[Array, "K n"]
    multipliers: tuple[Array, Array]


class _LazyNode:
    """A :class:`Node` computed on first use: a cost that reads neither ``q`` nor ``qdot`` (the
    control effort) adds no velocity recovery to the solver's program, whose derivatives of the
    costs (gradients, Hessians) would otherwise trace it several times over. Reads, unpacking and
    indexing go to the node, as for the NamedTuple itself."""

    def __init__(self, compute):
        self._compute = compute

    @functools.cached_property
    def _node(self) -> Node:
        return Node(*self._compute())

    def __getattr__(self, name):  # q, qdot and the NamedTuple's methods
        if name.startswith("__") or name in ("_compute", "_node"):
            raise AttributeError(name)
        return getattr(self._node, name)

    def __iter__(self):
        return iter(self._node)

    def __getitem__(self, i):
        return self._node[i]

    def __len__(self) -> int:
        return len(Node._fields)


def problem_functions(
    task: Task, dyn: DiscreteDynamics, x0: Array, *, hessian: str = "exact"
) -> tuple[OCPFunctions, Array, Array]:
    """The task's problem in the solver's stage form: ``chi = (x, u)`` (flat state, scaled node
    controls), ``v`` the next node's scaled controls. Returns ``(functions, lo, hi)``.

    ``hessian="base"``: for a composition (``lj.RDP(order=4 or 6)``) the curvature term of the
    Lagrangian's Hessian comes from :func:`curvature_integrator`'s step (see :func:`solve`)."""
    system, scale, h = task.system, task.parameterization.scale, task.h
    n = dyn.n_state
    d = system.n_config
    terms = task.objective

    def split(chi):
        return chi[:n], chi[n:]

    def stage_dynamics(discrete: DiscreteDynamics):
        def f(chi, v):
            x, u = split(chi)
            return jnp.concatenate([discrete.step(x, u * scale, v * scale), v])

        return f

    dynamics = stage_dynamics(dyn)
    base = curvature_integrator(dyn.integrator) if hessian == "base" else dyn.integrator
    curved = None if base is dyn.integrator else stage_dynamics(discretize(system, base, h=dyn.h, t0=dyn.t0))

    def first(v):
        return jnp.concatenate([x0, v])

    def stage_cost(chi):
        x, u = split(chi)
        c = u * scale
        obs = _LazyNode(lambda: dyn.node(x, c))
        return sum((t.stage(system, obs, c, h) for t in terms), jnp.zeros((), chi.dtype))

    def terminal_cost(chi):
        x, u = split(chi)
        obs = _LazyNode(lambda: dyn.node(x, u * scale))
        return sum((t.terminal(system, obs, task.q0) for t in terms), jnp.zeros((), chi.dtype))

    def terminal(chi):
        x, u = split(chi)
        obs = Node(*dyn.node(x, u * scale))
        parts = []
        if task.goal is not None:
            parts.append(pose_error(obs.q, task.goal))
        if task.rest:
            parts.append(TerminalRest(task.rest).residual(system, obs))
        return jnp.concatenate(parts) if parts else jnp.zeros((0,), chi.dtype)

    inf = jnp.full(n - d, jnp.inf, x0.dtype)
    v_lo, v_hi = task.c_lower / scale, task.c_upper / scale
    lo = jnp.concatenate([task.q_lower.astype(x0.dtype), -inf, v_lo])
    hi = jnp.concatenate([task.q_upper.astype(x0.dtype), inf, v_hi])

    def perturbation(v, key, size):
        # uniform, ``size`` times the half-width of the control bounds (times 1 where infinite)
        half = jnp.where(jnp.isfinite(v_hi - v_lo), 0.5 * (v_hi - v_lo), 1.0)[None, :]
        noise = jax.random.uniform(key, v.shape, v.dtype, -1.0, 1.0)
        return _pushed(v + size * half * noise, v_lo[None, :], v_hi[None, :], 1e-2)

    fns = OCPFunctions(dynamics, first, stage_cost, terminal_cost, terminal, curved, perturbation)
    return fns, lo, hi


def curvature_integrator(integrator: AbstractIntegrator) -> AbstractIntegrator:
    """The integrator whose second derivatives stand in for ``integrator``'s in the Hessian of the
    Lagrangian under ``solve(..., hessian="base")``: for a composition ``lj.RDP(order=4 or 6)``
    its base step, ``lj.RDP(order=2)`` with the same settings, taking the whole step ``h``;
    otherwise ``integrator`` itself.

    Both steps approximate the same flow map on the same (minimal) state, so their second
    derivatives differ by ``O(h^3)``: ``O(h^2)`` relative to the curvature itself, which is ``O(h)``.
    The Newton steps use exact Jacobians and constraints (the solution is that of the composition),
    with a Hessian accurate to ``O(h^2)``: fast linear convergence instead of quadratic, at a
    fraction of the cost per iteration (one substep differentiated twice instead of five or nine)."""
    if isinstance(integrator, RDP) and integrator.order > 2:
        return dataclasses.replace(integrator, order=2, scheme=None)  # every other setting kept
    return integrator


def solve(
    task: Task,
    params0: Array | None = None,
    *,
    tol: float = 1e-8,
    max_iterations: int = 1000,
    hessian: str = "base",
    curvature_tol: float = 0.1,
) -> Solution:
    """Solve ``task``'s optimal control problem with hard constraints.

    Minimises the task's objective (e.g. the control effort ``sum_k h |c_k / scale|^2``) over the
    node controls, subject to the discrete dynamics of the task's integrator, the terminal pose
    and rest conditions as equalities, and the bounds at the nodes as inequalities, by a
    primal-dual interior-point method with the exact Hessian of the Lagrangian and a Riccati
    solve of each Newton step (:mod:`ldap_jax.control._ipm`). Multiple shooting: the initial
    states come from a rollout of ``params0``. One compilation per problem structure; jit-,
    vmap- and grad-able: ``jax.grad``/``jax.jacfwd`` of the solution with respect to the task's
    arrays (model parameters, goal) give the sensitivities of the optimum by the implicit function
    theorem at the solution (not by differentiating the iterations). A batch of problems
    (goals, model parameters, starts) under ``jax.vmap`` runs on one device; :func:`ldap_jax.shard_vmap`
    splits it over the devices (on a CPU, one per core).

    Args:
        task: a task with per-step sampled controls (:class:`SampledControls`).
        params0: initial guess, shape (N + 1, n_channels) (default ``task.init()``).
        tol: stopping tolerance on the scaled KKT error (> 0).
        max_iterations: iteration budget (a positive integer). The default, 1000, is spent only
            by hard problems (IPOPT's is 3000): on 16 random goals around each of parallel_park,
            u_turn and reach (three seeds, 144 problems), a budget of 200 left 1, 1 and 4 of the
            first 48 at the budget; with 1000 and the restart after a failed line search
            (``Solution.resets``) all 144 converge, in up to 437 iterations (and the same 144
            goals from rest, in up to 211).
        hessian: ``"base"`` (default): for ``lj.RDP(order=4 or 6)`` the curvature of the dynamics
            in the Hessian of the Lagrangian comes from the base step ``lj.RDP(order=2)`` over the
            same ``h`` (:func:`curvature_integrator`; accurate to ``O(h^2)`` relative, so the
            iteration converges fast-linearly to the same solution, with Jacobians and
            constraints exact): on the three goal tasks 1.4-2.2x faster per solve than
            ``"exact"`` and cheaper to compile. ``"exact"``: the step's own second derivatives.
            Other integrators use their own in both cases.
        curvature_tol: the dynamics' curvature enters the Hessian of the Lagrangian once the
            constraint violation ``|defects|_1 + |c_K|_1`` is at most this (> 0; ``inf``: from the
            first iteration); before, the Hessian is Gauss-Newton (the objective's and the
            barrier's curvature). Traced: another value does not recompile. The default, 0.1, was
            tuned on 288 problems for speed (20 / 52 / 71 iterations on parallel_park / u_turn /
            reach). Solves of nonconvex problems from the same guess may end in other local optima:
            with ``inf``, u_turn takes 282 iterations (0.60 s against 0.076 s) to an effort of
            24.890 against 35.461 (IPOPT: 35.518), reach 102 iterations to IPOPT's optimum 1.31649
            against 1.64512, parallel_park 42 to the same optimum.

    Returns:
        :class:`Solution`.

    Raises:
        TypeError: ``task`` is not a :class:`Task`; a non-numeric ``tol``, ``max_iterations`` or
            ``params0``.
        ValueError: a task without sampled controls, a bad guess shape or a non-finite guess, a
            non-positive ``tol``, ``max_iterations`` or ``curvature_tol``.
    """
    if not isinstance(task, Task):
        raise TypeError(f"'task' must be an lc.Task (e.g. lc.parallel_park()), got {type(task)}")
    if not isinstance(task.parameterization, SampledControls):
        raise ValueError(
            "solve needs per-step sampled controls (lc.SampledControls); this task uses "
            f"{type(task.parameterization).__name__}: optimise it with lc.optimize"
        )
    tol = check_positive_number("tol", tol)
    max_iterations = check_positive_int("max_iterations", max_iterations)
    if hessian not in ("base", "exact"):
        raise ValueError(f"'hessian' must be 'base' or 'exact', got {hessian!r}")
    curvature_tol = check_positive_number("curvature_tol", curvature_tol, allow_inf=True)
    shape = (task.n_steps + 1, task.system.n_controls)
    if params0 is None:
        params0 = task.init()
    params0 = check_array("params0", params0, shape, "(N + 1 nodes, channels)")
    with jax.ensure_compile_time_eval():
        if is_concrete(params0) and not bool(np.all(np.isfinite(np.asarray(params0)))):
            raise ValueError("'params0' must be finite (an initial guess with NaN or inf)")
    # tolerances and budget as arrays: new values must not recompile
    options = IPMOptions(
        tol=jnp.asarray(tol, task.q0.dtype),
        max_iterations=jnp.asarray(max_iterations, jnp.int32),
        hessian=hessian,
        exact_hessian_tol=jnp.asarray(curvature_tol, task.q0.dtype),
    )
    return _solve(task, params0, options)


def _setup(task: Task, v0: Array, hessian: str = "exact"):
    """The discrete dynamics, the initial state and the stage functions of ``task``."""
    scale = task.parameterization.scale
    dyn = discretize(task.system, task.integrator, h=task.h)
    x0 = dyn.init(task.q0, task.qdot0, v0 * scale)
    fns, lo, hi = problem_functions(task, dyn, x0, hessian=hessian)
    return dyn, x0, fns, lo, hi


def _stopped(tree):
    return jax.tree_util.tree_map(lambda x: jax.lax.stop_gradient(x) if eqx.is_inexact_array(x) else x, tree)


def _solver_view(task: Task) -> Task:
    """``task`` with the fields the solver never reads set to their defaults: its name, the
    penalty form's weights and memory policy, and the settings of its initial guess. They are
    static (part of a compiled program's key), so without this two tasks that differ only there
    compiled the interior-point program twice: ``parallel_park`` and ``u_turn`` on one grid
    (both a car, the same N and integrator) each compiled for 4.9 s."""
    defaults = {f.name: f.default for f in dataclasses.fields(Task) if f.name in _UNREAD_BY_SOLVER}
    return dataclasses.replace(task, name="", penalty=Penalty(), **defaults)


#: fields of a Task that only the penalty form and the initial guess read (each has a default)
_UNREAD_BY_SOLVER = ("guess", "checkpoint", "init_amplitude")


def _solve(task: Task, params0: Array, options: IPMOptions) -> Solution:
    task = _solver_view(task)
    # Two programs: the interior-point run, on the task with its derivatives stopped (the
    # iterations are not differentiated), and the optimum, whose derivatives come from the
    # implicit function theorem. Under jax.grad, jax.jvp or jax.jacfwd of a caller that nothing
    # stages, the run's arguments are then plain values and the run is the program an
    # undifferentiated solve of the same problem compiled (notebook 03's 120-step parallel_park:
    # the first gradient of the optimal effort after a solve, 36.6 -> 25.7 s; its compilation
    # 26.8 -> 18.4 s).
    st, violation = _run(_stopped(task), _stopped(params0), options)
    return _finish(task, st, violation)


@jit
def _run(task: Task, params0: Array, options: IPMOptions) -> tuple[IPMState, Array]:
    # the kernels as plain arithmetic: this program differentiates them twice
    with plain():
        dtype = task.q0.dtype
        params0 = params0.astype(dtype)
        _, _, fns, lo, hi = _setup(task, params0[0], options.hessian)
        # multiple shooting from the guess's own trajectory (the rollout a restart also uses)
        st: IPMState = ipm_solve(fns, _rollout(fns, params0), params0, lo, hi, options)
        defects, cK = _constraints(fns, st.chi, st.v)  # at the returned point
        violation = jnp.maximum(jnp.max(jnp.abs(defects)), jnp.max(jnp.abs(cK), initial=0.0))
        return st, violation


@jit
def _finish(task: Task, st: IPMState, violation: Array) -> Solution:
    with plain():
        v, chi_opt, cost = _optimum(task, st)
        n = chi_opt.shape[1] - v.shape[1]
        return Solution(
            params=v,
            converged=st.result == SOLVER_RESULTS.successful,
            iterations=st.iteration,
            cost=cost,
            max_violation=violation,
            kkt_error=st.error,
            result=st.result,
            resets=st.resets,
            states=chi_opt[:, :n],
            multipliers=(st.y, st.nu),
        )


@eqx.filter_custom_jvp
def _optimum(task: Task, st: IPMState):
    """The optimum ``(v, chi, cost)`` of a converged run; its derivatives with respect to the
    task's parameters come from the implicit function theorem (see :func:`_optimum_jvp`)."""
    _, _, fns, _, _ = _setup(task, st.v[0])
    cost = jnp.sum(jax.vmap(fns.stage_cost)(st.chi)) + fns.terminal_cost(st.chi[-1])
    return st.v, st.chi, cost


@_optimum.def_jvp
def _optimum_jvp(primals, tangents):
    """Implicit function theorem at the solution: the barrier problem's KKT conditions
    ``G(z, lambda; theta) = 0`` (with the bound multipliers eliminated, ``zeta = mu / slack``) give
    ``[[W + Sigma, J^T], [J, 0]] (dz, dlambda) = -(d_theta grad L, d_theta c) dtheta``: the same
    structured system as a Newton step, solved by the same Riccati recursion with the exact
    Hessian of the Lagrangian at the solution."""
    task, st = primals
    t_task, _ = tangents
    v, chi, cost = _optimum(task, st)
    K, n = chi.shape
    m = v.shape[1]
    dtype = chi.dtype
    if t_task is None:
        zero = (jnp.zeros_like(v), jnp.zeros_like(chi), jnp.zeros_like(cost))
        return (v, chi, cost), zero
    diff, static = eqx.partition(task, eqx.is_inexact_array)
    t_diff = jax.tree_util.tree_map(
        lambda x, t: None if x is None else (jnp.zeros_like(x) if t is None else t),
        diff,
        t_task,
        is_leaf=lambda x: x is None,
    )
    mu = st.mu

    def residuals(diff_):
        task_ = eqx.combine(diff_, static)
        _, _, fns_, lo_, hi_ = _setup(task_, v[0])

        lo_, hi_ = jnp.broadcast_to(lo_, chi.shape), jnp.broadcast_to(hi_, chi.shape)

        def lagrangian(chi_, v_):
            defects = jnp.concatenate(
                [(fns_.first(v_[0]) - chi_[0])[None], jax.vmap(fns_.dynamics)(chi_[:-1], v_[1:]) - chi_[1:]]
            )
            f = jnp.sum(jax.vmap(fns_.stage_cost)(chi_)) + fns_.terminal_cost(chi_[-1])
            sl = jnp.where(jnp.isfinite(lo_), chi_ - lo_, 1.0)
            su = jnp.where(jnp.isfinite(hi_), hi_ - chi_, 1.0)
            barrier = -mu * (
                jnp.sum(jnp.where(jnp.isfinite(lo_), jnp.log(sl), 0.0))
                + jnp.sum(jnp.where(jnp.isfinite(hi_), jnp.log(su), 0.0))
            )
            return f + barrier + jnp.sum(st.y * defects) + st.nu @ fns_.terminal(chi_[-1]), defects

        (g_chi, g_v), defects = jax.grad(lagrangian, argnums=(0, 1), has_aux=True)(chi, v)
        return g_chi, g_v, defects, fns_.terminal(chi[-1])

    _, (r_chi, r_v, e, c) = jax.jvp(residuals, (diff,), (t_diff,))
    _, _, fns, lo, hi = _setup(task, v[0])
    lo, hi = jnp.broadcast_to(lo, chi.shape), jnp.broadcast_to(hi, chi.shape)
    d = _derivatives(fns, st, jnp.asarray(jnp.inf, dtype), False)
    sl = jnp.where(jnp.isfinite(lo), chi - lo, 1.0)
    su = jnp.where(jnp.isfinite(hi), hi - chi, 1.0)
    sigma = jnp.where(jnp.isfinite(lo), st.zl / sl, 0.0) + jnp.where(jnp.isfinite(hi), st.zu / su, 0.0)
    diag = jax.vmap(jnp.diag)(jnp.concatenate([jnp.zeros((1, n), dtype), sigma[:-1]]))
    # the matrices belong to the solution (no tangent flows through them); the map from the
    # right-hand side to the step is linear, so forward and reverse mode both go through it
    fac = jax.lax.stop_gradient(
        riccati_factor(
            d.W.at[:, :n, :n].add(diag), d.Z, d.QK + jnp.diag(sigma[-1]), d.CK, jnp.zeros((), dtype)
        )
    )
    w = jnp.concatenate([jnp.concatenate([jnp.zeros((1, n), dtype), r_chi[:-1]]), r_v], axis=1)
    sol = riccati_apply(fac, w, e, r_chi[-1], c)
    dchi, dv = sol.dx[1:], sol.dv

    def objective(chi_, diff_):
        task_ = eqx.combine(diff_, static)
        _, _, fns_, _, _ = _setup(task_, v[0])
        return jnp.sum(jax.vmap(fns_.stage_cost)(chi_)) + fns_.terminal_cost(chi_[-1])

    _, dcost = jax.jvp(objective, (chi, diff), (dchi, t_diff))
    del m, K
    return (v, chi, cost), (dv, dchi, dcost)
