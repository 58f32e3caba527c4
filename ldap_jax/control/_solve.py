"""``lc.solve``: a task's optimal control problem with hard constraints, by the interior-point
method of :mod:`._ipm` on the discrete dynamics of the task's integrator."""

from __future__ import annotations

import dataclasses
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._compilation_cache import asarray, jit
from .._discrete import discretize
from .._numerics import plain
from .._simulate import simulate
from .._validation import check_positive_int, check_positive_number, is_concrete
from ..integrators import RDP, AbstractIntegrator
from . import _export
from ._constraints import NetDisplacement
from ._ipm import SOLVER_RESULTS, IPMOptions, IPMState, ipm_solve
from ._kkt import objective, rollout
from ._parameterizations import SampledControls
from ._sensitivity import optimum
from ._sequential import one_after_another
from ._stage_form import from_variables, layout, problem_functions, to_variables
from ._task import GaitParams, Guess, Task

__all__ = ["Solution", "solve", "curvature_integrator", "setup"]


class Solution(eqx.Module):
    """The result of :func:`solve` (batched along leading axes under ``vmap``).

    Attributes:
        params: the optimal parameters: (N + 1, n_channels) scaled node controls, or for a
            periodic task :class:`~ldap_jax.control.GaitParams` (the controls and the start's
            reduced state); ``task.controls(sol.params)`` are the controls and
            ``task.initial_state(sol.params)`` the start.
        converged: the KKT error met ``tol``.
        iterations: interior-point iterations used.
        cost: the objective at the solution.
        max_violation: largest violation of the model's constraints at the solution (dynamics
            defects, terminal equalities; bounds are kept strictly by the method).
        kkt_error: the final scaled KKT error.
        result: a :data:`SOLVER_RESULTS` item (``SOLVER_RESULTS[sol.result]`` is the message).
        resets: how often the method restarted after a line search failed far from feasibility.
        states: the flat states of the discrete dynamics at the nodes, (N + 1, n).
        multipliers: the dynamics multipliers (N + 1, n_stage) and the terminal ones (p,).
        model_error: an estimate of how far the model itself is from the physics at the
            solution: ``(position [m], heading [rad])`` of the difference at ``t_N`` between the
            optimised controls rolled out with the task's integrator at its step ``h`` and at
            ``h/2`` (for an order-``p`` method this is the model's own error times ``1 - 2^-p``).
            ``lc.replay`` measures it against ``lj.reference``. The end point at ``h`` is the
            solution's last node, so for a solve that did not converge the estimate also holds
            its remaining dynamics defects. A diagnostic: its derivative is zero.
        starts: how many initial guesses were run (1, or the batch of ``params0``), and
            ``starts_converged`` how many of them converged.
    """

    params: object
    converged: Bool[Array, ""]
    iterations: Int[Array, ""]
    cost: Float[Array, ""]
    max_violation: Float[Array, ""]
    kkt_error: Float[Array, ""]
    result: SOLVER_RESULTS
    resets: Int[Array, ""]
    states: Float[Array, "K n"]
    multipliers: tuple[Array, Array]
    model_error: Float[Array, " 2"]
    starts: int = eqx.field(static=True, default=1)
    starts_converged: Int[Array, ""] | None = None


def curvature_integrator(integrator: AbstractIntegrator) -> AbstractIntegrator:
    """The integrator whose second derivatives stand in for ``integrator``'s in the Hessian of the
    Lagrangian under ``solve(..., hessian="base")``: for a composition ``lj.RDP(order=4, 6 or 8)``
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


def setup(task: Task, hessian: str = "exact"):
    """The discrete dynamics and the stage form of ``task``: ``(dyn, fns, lo, hi, layout)``."""
    dyn = discretize(task.system, task.integrator, h=task.h)
    base = curvature_integrator(task.integrator) if hessian == "base" else task.integrator
    curved = None if base is task.integrator else discretize(task.system, base, h=task.h)
    fns, lo, hi, lay = problem_functions(task, dyn, curvature=curved)
    return dyn, fns, lo, hi, lay


#: The initial barrier parameter of a warm start from a :class:`Solution`: small enough that a
#: solve of the same task stays at that solution's optimum. From the solution's ``params`` with the
#: gaits' 1e-3, the first iterates leave it: the drive gait re-solved ends 8.5e-5 m per cycle lower
#: at another optimum (0.2620069 against 0.2620924), the turn gait at the trivial cycle (0 rad);
#: from 1e-4 down to 1e-8 both stay, in 13-18 iterations from 1e-6. On a task moved away from the
#: solution (another goal, period or bound) neither value reaches the better optimum every time.
WARM_BARRIER = 1e-6

#: The bound push of a warm start from a :class:`Solution` (IPOPT's ``warm_start_bound_push``;
#: a cold start's is 1e-2): the solution's states lie 1e-10 to 1e-7 inside their active bounds,
#: and 1e-2 moved them far from the optimum for so small a barrier. A custom snakeboard gait
#: (displacement along the diagonal, RDP order 2) re-solved from its own Solution spent its 1000
#: iterations at a KKT error of 2.8e-8 with the push at 1e-2, and converged in 13 with 1e-9.
WARM_PUSH = 1e-9


def solve(
    task: Task,
    params0=None,
    *,
    tol: float | None = None,
    max_iterations: int = 1000,
    hessian: str = "base",
    curvature_tol: float = 0.1,
    barrier: float | None = None,
) -> Solution:
    """Solve ``task``'s optimal control problem with hard constraints.

    Minimises the task's objective over the node controls (and a gait's start), subject to the
    discrete dynamics of the task's integrator, its constraints (terminal and initial equalities,
    a gait's return conditions, path inequalities) and its bounds at the nodes, by a primal-dual
    interior-point method (Gauss-Newton Hessian until the constraints are met to
    ``curvature_tol``, then the dynamics' curvature too, ``hessian``) and a Riccati solve of each
    Newton step (:mod:`ldap_jax.control._ipm`). Multiple shooting: the initial states come from a
    rollout of ``params0``. One compilation per problem structure; jit-, vmap- and grad-able:
    ``jax.grad``/``jax.jacfwd`` of the solution with respect to the task's arrays (model
    parameters, goal, bounds, a gait's period through ``task.with_options(t_final=T)``) give the
    sensitivities of the optimum by the implicit function theorem at the solution (not by
    differentiating the iterations; for the drive gait, with respect to the torque bound, the
    mass and the period, they match central differences of re-solves). Derivatives of a
    solve that did not converge are NaN. A batch of problems under ``jax.vmap`` (a family over a
    bound, a goal, a model parameter) runs on one device, its members one after another, each for
    its own iterations; :func:`ldap_jax.shard_vmap` splits it over the devices. For a family along
    a parameter, continuation (``lax.scan``, each member from its neighbour's solution) takes
    fewer iterations than one common warm start. With JAX's persistent
    compilation cache on (:func:`ldap_jax.enable_compilation_cache`), the solver's programs are
    also kept traced (``jax.export``, in the cache folder): a new process that solves a problem of
    the same structure (other goal, bounds, model parameters or tolerances) neither traces nor
    compiles them (``LDAP_JAX_EXPORT=0`` turns this off). So are, under a top-level ``jax.grad``
    or ``jax.jvp``, the derivative's: the solution's Jacobian with respect to the task's arrays.
    A process's first solve (with the cache on, the first process to solve a structure) compiles
    its interior-point program quickly first (XLA's LLVM passes off: its first solves run about 3x
    slower, for the few seconds the optimised program takes to compile behind them in another
    thread; the solutions agree to 1e-13), with or without the cache. With the cache on it stores
    the optimised one for later processes; without it, the optimised compilation starts at the
    process's second solve, so a script that solves once exits after its answer
    (``LDAP_JAX_QUICK_FIRST=0``: the optimised program only).

    Args:
        task: a task with per-step sampled controls (:class:`SampledControls`).
        params0: initial guess (default ``task.init()``): (N + 1, n_channels) scaled controls, or
            :class:`~ldap_jax.control.GaitParams` for a periodic task. A leading batch axis
            (``task.init()`` gives one when ``task.guess.starts > 1``) runs every guess (one
            after another in one program) and returns the converged solution of least cost
            (``Solution.starts``). A previous :class:`Solution` is a warm start: its ``params``,
            with the barrier starting at 1e-6 unless ``barrier`` is given and the states moved
            off their bounds by 1e-9 (not 1e-2), so that a solve of the same task (a
            sensitivity, a tighter ``tol``) stays at its optimum. Its ``params``
            alone start from the default barrier, which can lead a gait to another local optimum
            (the drive gait 8.5e-5 m per cycle lower, the turn gait to standing still).
        tol: stopping tolerance on the scaled KKT error (> 0; default ``None``: 1e-8 in float64,
            1e-5 in float32, whose round-off puts 1e-8 out of reach).
        max_iterations: iteration budget (a positive integer; default 1000, IPOPT's is 3000).
        hessian: ``"base"`` (default): for ``lj.RDP(order=4, 6 or 8)`` the curvature of the dynamics
            comes from the base step ``lj.RDP(order=2)`` over the same ``h``
            (:func:`curvature_integrator`; the iteration converges fast-linearly to the same
            solution, with Jacobians and constraints exact; 1.4-2.2x faster per solve than
            ``"exact"``). ``"exact"``: the step's own second derivatives.
        curvature_tol: the dynamics' curvature enters the Hessian of the Lagrangian once the
            constraint violation ``|defects|_1 + |c_K|_1`` is at most this (> 0, default 0.1;
            ``inf``: from the first iteration); before, the Hessian is Gauss-Newton. Traced: another
            value does not recompile.
        barrier: the initial barrier parameter ``mu_0`` (> 0; default ``None``: 0.1 for a
            point-to-point task, 1e-3 for a periodic one, 1e-6 from a :class:`Solution`). A gait's
            trivial cycle (standing still) lies deep inside the bounds, where a large barrier pulls
            the first iterates;
            from 1e-3 the drive gait converged in 19-70 iterations, from 0.1 it collapsed to the
            trivial cycle. On the point-to-point tasks 0.1 took the fewest iterations. Traced.

    Returns:
        :class:`Solution`.

    Raises:
        TypeError: ``task`` is not a :class:`Task`; a non-numeric setting.
        ValueError: a task without sampled controls, a bad guess shape or a non-finite guess, a
            non-positive ``tol``, ``max_iterations`` or ``curvature_tol``.

    Warns:
        UserWarning: when the task runs in float32 with a ``tol`` below 1e-6: that KKT tolerance is
            out of reach and the line search fails near the solution.
    """
    options, params0, batched = _checked(task, params0, tol, max_iterations, hessian, curvature_tol, barrier)
    task = _solver_view(task)
    if batched:
        args = (_stopped(task), _stopped(params0), options)
        runs = _export.call("run_batch", _run_batch.__wrapped__, args, lambda: (*_run_template(), 0))
        st, violation, cost = _run_batch(*args) if runs is NotImplemented else runs
        st, violation, n_ok = _best(st, violation, cost)
        sol = _finished(task, st, violation, params0)
        return dataclasses.replace(
            sol, starts=int(jax.tree_util.tree_leaves(params0)[0].shape[0]), starts_converged=n_ok
        )
    return _solve_one(task, params0, options)


def _solve_one(task: Task, params0, options: IPMOptions) -> Solution:
    # With the persistent cache on, the run and the finish are the programs an earlier process
    # exported (_export: no tracing). The run's inputs are cut from differentiation, so it can be
    # the exported program under grad too; the finish (the IFT step) only at the top level.
    args = (_stopped(task), _stopped(params0), options)
    shapes = _export.prepare("run", _run_one, args, _run_template, quick=True)
    if shapes is not None:  # the finish exported (or loaded) while XLA compiles the run
        _export.prepare("finish", _finish.__wrapped__, (task, *shapes), lambda: _template(params0))
    run = _export.call("run", _run_one, args, _run_template)
    st, violation = _run(*args) if run is NotImplemented else run
    return _finished(task, st, violation, params0)


def _finished(task: Task, st: IPMState, violation: Array, params0) -> Solution:
    """:func:`_finish` through its exported program where it can be: at the top level, and under a
    top-level ``grad``/``jvp`` (the sensitivities) with its exported Jacobian."""
    args = (task, st, violation)
    sol = _export.call("finish", _finish.__wrapped__, args, lambda: _template(params0), top_level=True)
    if sol is NotImplemented:
        sol = _export.differentiated("finish", _finish.__wrapped__, args, lambda: _template(params0))
    return _finish(*args) if sol is NotImplemented else sol


def _run_template():
    """A pytree of the structure :func:`_run_one` returns."""
    z = 0
    return IPMState(*([z] * (len(IPMState._fields) - 1)), SOLVER_RESULTS.successful), z


def _template(params0) -> Solution:
    """A :class:`Solution` of the structure :func:`_finish` returns for ``params0``."""
    z = 0
    return Solution(params0, z, z, z, z, z, SOLVER_RESULTS.successful, z, z, (z, z), z)


def _checked(task, params0, tol, max_iterations, hessian, curvature_tol, barrier):
    if not isinstance(task, Task):
        raise TypeError(f"'task' must be an lc.Task (e.g. lc.parallel_park()), got {type(task)}")
    if not isinstance(task.parameterization, SampledControls):
        raise ValueError(
            "solve needs per-step sampled controls (lc.SampledControls); this task uses "
            f"{type(task.parameterization).__name__}: optimise it with lc.optimize"
        )
    dtype = task.bounds.q_lower.dtype
    tol = (1e-5 if dtype == jnp.float32 else 1e-8) if tol is None else check_positive_number("tol", tol)
    max_iterations = check_positive_int("max_iterations", max_iterations)
    if hessian not in ("base", "exact"):
        raise ValueError(f"'hessian' must be 'base' or 'exact', got {hessian!r}")
    curvature_tol = check_positive_number("curvature_tol", curvature_tol, allow_inf=True)
    if barrier is None:
        barrier = WARM_BARRIER if isinstance(params0, Solution) else 0.1 if task.periodic is None else 1e-3
    barrier = check_positive_number("barrier", barrier)
    if dtype == jnp.float32 and tol < 1e-6:
        why = "because jax_enable_x64 is off" if not jax.config.jax_enable_x64 else "(a float32 task)"
        warnings.warn(
            f"lc.solve runs in float32 {why}: its KKT tolerance ({tol:g}) is below float32 round-off "
            "and the line search will fail near the solution; use tol >= 1e-5 (the float32 default) or "
            'float64 (jax.config.update("jax_enable_x64", True))',
            stacklevel=3,
        )
    if params0 is None:
        params0 = task.init()
    warm = isinstance(params0, Solution)
    if warm:  # a previous solve as the warm start: its parameters
        params0 = params0.params
    params0, batched = _check_guess(task, params0)
    # tolerances and budget as arrays: new values must not recompile
    options = IPMOptions(
        tol=asarray(tol, dtype),
        max_iterations=asarray(np.int32(max_iterations)),
        hessian=hessian,
        exact_hessian_tol=asarray(curvature_tol, dtype),
        mu0=asarray(barrier, dtype),
        bound_push=asarray(WARM_PUSH if warm else IPMOptions._field_defaults["bound_push"], dtype),
    )
    return options, params0, batched


def checked_params(task: Task, params, where: str):
    """One solution's ``params`` of ``task``, checked as :func:`solve` checks its guess (a
    ``TypeError`` or ``ValueError`` naming ``where``'s argument) when the task has per-step
    controls; a :class:`Solution` counts as its ``params``, with a warning when it did not
    converge."""
    if not isinstance(task, Task):
        raise TypeError(f"{where}: 'task' must be an lc.Task (e.g. lc.drive_gait()), got {type(task)}")
    if isinstance(params, Solution):
        ok, result = params.converged, params.result
        if is_concrete((ok, result)) and np.ndim(ok) == 0 and not bool(ok):
            warnings.warn(
                f"{where}: the solution did not converge ({SOLVER_RESULTS[result]}); for a periodic task "
                "its start is not a periodic orbit",
                stacklevel=3,
            )
        params = params.params
    if not isinstance(task.parameterization, SampledControls):
        return params  # another parameterization checks its own parameters when it reads them
    params, batched = _check_guess(task, params, "params")
    if batched:
        raise ValueError(f"{where}: 'params' must be one solution's parameters, got a batch of them")
    return params


def _check_guess(task: Task, params0, name: str = "params0"):
    shape = (task.n_steps + 1, task.system.n_controls)
    periodic = task.periodic is not None
    if periodic and not isinstance(params0, GaitParams):
        raise TypeError(
            f"'{name}' of a periodic task must be lc.GaitParams(controls, state), "
            f"got {type(params0).__name__}"
        )
    if not periodic and isinstance(params0, GaitParams):
        raise TypeError(
            f"'{name}' of a task with a fixed start is an array of node controls {shape}, got lc.GaitParams "
            "(the parameters of a periodic task)"
        )
    if not periodic and isinstance(params0, (list, tuple)):
        try:
            params0 = np.asarray(params0, float)
        except (TypeError, ValueError) as err:
            raise TypeError(f"'{name}' must be an array of numbers {shape}, got {type(params0)}") from err
    if periodic and isinstance(params0.controls, (list, tuple)):
        params0 = params0._replace(controls=np.asarray(params0.controls, float))
    if periodic and isinstance(params0.state, (list, tuple)):
        params0 = params0._replace(state=np.asarray(params0.state, float))
    controls = params0.controls if periodic else params0
    try:
        if isinstance(controls, (str, bytes)):
            raise TypeError
        cshape = tuple(jnp.shape(controls))
    except TypeError as err:
        raise TypeError(f"'{name}' must be an array of numbers, got {type(controls)}") from err
    batched = len(cshape) == 3 and cshape[1:] == shape
    if cshape[-2:] != shape or len(cshape) not in (2, 3):
        raise ValueError(
            f"'{name}' must have shape {shape} (N + 1 nodes, channels), or a batch of them, got {cshape}"
        )
    if periodic:
        nz = layout(task, discretize(task.system, task.integrator, h=task.h)).nz
        want = (*cshape[:-2], nz)
        if tuple(jnp.shape(params0.state)) != want:
            raise ValueError(
                f"'{name}.state' must have shape {want} (the start's reduced state), "
                f"got {jnp.shape(params0.state)}"
            )
    params0 = jax.tree_util.tree_map(lambda x: asarray(x, task.bounds.q_lower.dtype), params0)
    with jax.ensure_compile_time_eval():
        leaves = jax.tree_util.tree_leaves(params0)
        if is_concrete(leaves) and not all(bool(np.all(np.isfinite(np.asarray(x)))) for x in leaves):
            raise ValueError(f"'{name}' must be finite (NaN or inf found)")
    return params0, batched


def _stopped(tree):
    return jax.tree_util.tree_map(lambda x: jax.lax.stop_gradient(x) if eqx.is_inexact_array(x) else x, tree)


def _solver_view(task: Task) -> Task:
    """``task`` with the fields the solver never reads set to their defaults: its name, the
    penalty form's weight and memory policy, and its guess settings. They are static (part of a
    compiled program's key), so without this two tasks that differ only there compiled the
    interior-point program twice."""
    w = task.objective_weight
    # a known weight's ones on the host: jnp.ones_like is an eager operation (a compilation)
    ones = asarray(np.ones(np.shape(w), w.dtype)) if is_concrete(w) else jnp.ones_like(w)
    return dataclasses.replace(task, name="", guess=Guess(), checkpoint=False, objective_weight=ones)


def valid_task(task: Task) -> Array:
    """Whether the task's values, traced or not, are valid (what :func:`make_task` checks on known
    values): the model's parameter checks, a positive finite horizon, bounds with lower below upper
    (no NaN), a finite start strictly inside the bounds (a gait's fixed components of it too), a
    finite goal within the bounds and finite prescribed displacements."""
    ok = jnp.isfinite(task.t_final) & (task.t_final > 0)
    for _, cond in task.system.parameter_checks():
        ok = ok & jnp.all(cond)
    b = task.bounds
    # lower < upper is false for a NaN bound, too
    ok = ok & jnp.all(b.q_lower < b.q_upper) & jnp.all(b.u_lower < b.u_upper)
    if task.q0 is not None:
        ok = ok & jnp.all(jnp.isfinite(task.q0)) & jnp.all(jnp.isfinite(task.qdot0))
        ok = ok & jnp.all(task.q0 > b.q_lower) & jnp.all(task.q0 < b.q_upper)
    if task.fixed_start is not None:
        idx, val = task.fixed_start
        ok = ok & jnp.all(val > b.q_lower[idx]) & jnp.all(val < b.q_upper[idx])
    if task.goal is not None:
        g = task.goal
        ok = ok & jnp.all(jnp.isfinite(g)) & jnp.all(g >= b.q_lower[:3]) & jnp.all(g <= b.q_upper[:3])
    for con in task.constraints:
        if isinstance(con, NetDisplacement):
            ok = ok & jnp.all(jnp.isfinite(con.target))
    return ok


def _run_one(task: Task, params0, options: IPMOptions, with_cost: bool = False):
    """The interior-point run from ``params0``: ``(state, violation)``, and with ``with_cost``
    the objective at the returned point (the batch picks its best start by it)."""
    # the kernels as plain arithmetic: this program differentiates them twice
    with plain():
        _, fns, lo, hi, lay = setup(task, options.hessian)
        p, v = to_variables(lay, params0)
        # multiple shooting from the guess's own trajectory (the rollout a restart also uses)
        st = ipm_solve(fns, p, rollout(fns, p, v), v, lo, hi, options)
        ok = valid_task(task)
        # st.violation: the largest defect or terminal residual at the returned point
        st = st._replace(result=SOLVER_RESULTS.where(ok, st.result, SOLVER_RESULTS.invalid_input))
        if with_cost:
            return st, st.violation, objective(fns, st.chi, st.v)
        return st, st.violation


_run = one_after_another(jit(_run_one))


@jit
def _run_batch(task: Task, params0, options: IPMOptions):
    """Every guess of a batch, one after another (``lax.map``): a ``vmap``-ped while loop runs
    every member for as many iterations as the slowest needs, where this costs the sum of their
    own (4 sideways-gait starts of 70, 64, 133 and 149 iterations: 2.2 s against 3.2 s)."""
    return jax.lax.map(lambda g: _run_one(task, g, options, True), params0)


@jax.jit
def _best(st: IPMState, violation: Array, cost: Array):
    """The converged start of least cost (the least KKT error if none converged)."""
    ok = st.result == SOLVER_RESULTS.successful
    i = jnp.where(jnp.any(ok), jnp.argmin(jnp.where(ok, cost, jnp.inf)), jnp.argmin(st.error))
    return jax.tree_util.tree_map(lambda x: x[i], st), violation[i], jnp.sum(ok)


@jit
def _finish(task: Task, st: IPMState, violation: Array) -> Solution:
    with plain():
        dyn, _, _, _, lay = setup(task)
        p, chi, v, cost = optimum(task, st)
        return Solution(
            params=from_variables(lay, p, v),
            converged=st.result == SOLVER_RESULTS.successful,
            iterations=st.iteration,
            cost=cost,
            max_violation=violation,
            kkt_error=st.error,
            result=st.result,
            resets=st.resets,
            states=chi[:, : lay.nx],
            multipliers=(st.y, st.nu),
            model_error=_model_error(task, dyn, lay, (from_variables(lay, p, v), chi[-1])),
        )


def _model_error(task: Task, dyn, lay, solution) -> Array:
    """``(position, heading)`` difference at ``t_N`` between the task's model at ``h`` and ``h/2``.

    The end point at ``h`` is the solution's own last node (its multiple-shooting defects are
    below the solver's tolerance); the one at ``h/2`` a rollout of ``2 N`` steps. A diagnostic:
    nothing in it is differentiated (the rollout's failure mask has no forward mode, and a
    ``jax.jvp`` of :func:`solve` with respect to the model or the period reached it)."""
    task, solution = _stopped(task), jax.lax.stop_gradient(solution)
    params, chi_last = solution
    q0, qdot0 = task.initial_state(params)
    controls = task.controls(params)
    d = task.system.n_config
    x, u, *_ = lay.split(chi_last)
    a = dyn.node(x, u * task.parameterization.scale)[0]
    traj = simulate(
        task.system,
        q0,
        qdot0,
        controls,
        t_final=task.t_final,
        n_steps=2 * task.n_steps,
        integrator=task.integrator,
        save="final",
        check_constraints=False,
        divergence=None,
    )
    b = traj.q.reshape(-1, d)[-1]
    heading = jnp.abs(jnp.remainder(a[2] - b[2] + jnp.pi, 2 * jnp.pi) - jnp.pi)
    return jnp.stack([jnp.linalg.norm(a[:2] - b[:2]), heading])
