"""An optimal control task: a system, a horizon, controls, an objective, constraints and bounds.

A :class:`Task` is built by :func:`~ldap_jax.control.make_task` from public pieces: objective terms
(:mod:`._terms`), constraint terms and :class:`~ldap_jax.control.Bounds` (:mod:`._constraints`), a
control parameterization and an integrator. :func:`~ldap_jax.control.solve` holds the constraints
exactly; :meth:`Task.loss` is the penalty form that :func:`~ldap_jax.control.optimize` minimises.

A task starts either at a fixed state ``(q0, qdot0)`` or, with the boundary condition
:class:`~ldap_jax.control.Periodic`, at a free start on the constraint manifold: a gait. Its
parameters are then :class:`GaitParams`, the node controls over one period and the start's
reduced state.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, PRNGKeyArray

from .._compilation_cache import asarray, compiled_unless_staged
from .._discrete import discretize
from .._simulate import Trajectory, simulate
from .._validation import check_positive_int
from ..integrators import AbstractIntegrator
from ..systems import AbstractSystem
from ._constraints import (
    AbstractConstraint,
    AbstractInitialConstraint,
    AbstractPathConstraint,
    AbstractTerminalConstraint,
    Bounds,
    Periodic,
    TerminalPose,
)
from ._parameterizations import AbstractParameterization, PeriodicControls, SampledControls, SinusoidGait
from ._terms import AbstractTerm, Node, evaluate_terms

__all__ = ["Task", "GaitParams", "Guess"]


class GaitParams(NamedTuple):
    """The parameters of a periodic task: ``controls`` (N + 1, n_channels), the scaled node
    controls over one period (``controls[N] = controls[0]`` at a solution), and ``state`` (nz,),
    the start's reduced state in the integrator's flat coordinates (see :meth:`Task.initial_state`)."""

    controls: Array
    state: Array


class Guess(eqx.Module):
    """How :meth:`Task.init` builds an initial guess.

    Attributes:
        amplitude: size of the guess's controls, as a fraction of their scale.
        gait: a sinusoid gait whose samples initialise per-step controls (or None).
        starts: number of starts of the default guess; above 1 :meth:`Task.init` returns a batch
            (a leading axis) of random guesses, which :func:`~ldap_jax.control.solve` runs one
            after another in one program, returning the best converged solution.
        seed: the seed of those random guesses.
        controls: explicit scaled node controls ``(N + 1, n_channels)`` for the deterministic
            guess (``key=None``, one start), or None.
    """

    amplitude: float = eqx.field(static=True, default=0.3)
    gait: SinusoidGait | None = None
    starts: int = eqx.field(static=True, default=1)
    seed: int = eqx.field(static=True, default=0)
    controls: Array | None = eqx.field(default=None, converter=lambda x: None if x is None else asarray(x))

    def __check_init__(self):
        check_positive_int("starts", self.starts)
        if isinstance(self.amplitude, bool) or not (
            isinstance(self.amplitude, (int, float, np.number)) and np.isfinite(self.amplitude)
        ):
            raise ValueError(f"Guess: 'amplitude' must be a finite number, got {self.amplitude!r}")


class Task(eqx.Module):
    """An optimal control problem through the discrete dynamics of an integrator.

    Build one with :func:`~ldap_jax.control.make_task` (which checks every piece) or take a
    built-in one (:func:`~ldap_jax.control.parallel_park`, :func:`~ldap_jax.control.drive_gait`, ...).

    Attributes:
        name: task name. system: the model. integrator: the dynamics model.
        t_final: horizon (s; for a gait, the period). n_steps: steps N (static).
        q0, qdot0: fixed initial state, or None for a periodic task.
        parameterization: params -> controls (per-step :class:`SampledControls` for ``solve``).
        objective: objective terms, summed. constraints: constraint terms.
        bounds: bounds at the nodes. guess: how :meth:`init` guesses.
        objective_weight: the objective's weight in the penalty form (:meth:`loss`).
        checkpoint: the rollout's memory policy in reverse mode (as for :func:`~ldap_jax.simulate`).
    """

    name: str = eqx.field(static=True)
    system: AbstractSystem
    integrator: AbstractIntegrator
    t_final: Array
    n_steps: int = eqx.field(static=True)
    q0: Array | None
    qdot0: Array | None
    parameterization: AbstractParameterization
    objective: tuple[AbstractTerm, ...]
    constraints: tuple[AbstractConstraint, ...]
    bounds: Bounds
    guess: Guess
    objective_weight: Array
    checkpoint: bool | str | int = eqx.field(static=True, default=False)

    # ------------------------------------------------------------------ views
    @property
    def h(self) -> Array:
        return self.t_final / self.n_steps

    @property
    def periodic(self) -> Periodic | None:
        """The task's :class:`Periodic` boundary condition, or None (a fixed start)."""
        return next((c for c in self.constraints if isinstance(c, Periodic)), None)

    @property
    def fixed_start(self) -> tuple[np.ndarray, np.ndarray] | None:
        """A periodic task's fixed start components: ``(indices, values)`` of the configuration
        (the group at the identity, ``x = y = theta = 0``, and the cyclic coordinates at 0), or
        None for a task with a fixed start (all of ``q0``)."""
        if self.periodic is None:
            return None
        cyclic = [3 + i for i, n in enumerate(self.system.shape_names) if n in self.periodic.cyclic]
        idx = np.asarray([0, 1, 2, *cyclic], int)
        return idx, np.zeros(idx.size)

    @property
    def path_constraints(self) -> tuple[AbstractPathConstraint, ...]:
        return tuple(c for c in self.constraints if isinstance(c, AbstractPathConstraint))

    @property
    def goal(self) -> Array | None:
        """The goal pose of a :class:`TerminalPose` constraint, or None."""
        pose = next((c for c in self.constraints if isinstance(c, TerminalPose)), None)
        return None if pose is None else pose.goal

    def _node_controls(self, params) -> Array:
        return params.controls if self.periodic is not None else params

    def controls(self, params):
        """The controls of ``params`` (for a gait, periodic beyond the period)."""
        ctl = self.parameterization.controls(self._node_controls(params))
        if self.periodic is not None:
            return PeriodicControls(ctl, self.t_final)
        return ctl

    def initial_state(self, params) -> tuple[Array, Array]:
        """``(q0, qdot0)``: the fixed start, or a gait's start from its reduced state: the group at
        the identity, the cyclic shape coordinates at 0, and the velocity whose momenta are the
        flat state's (the node velocity of the integrator)."""
        if self.periodic is None:
            return self.q0, self.qdot0
        if not isinstance(params, GaitParams):
            raise TypeError(
                "'params' of a periodic task must be lc.GaitParams(controls, state), got "
                f"{type(params).__name__}"
            )
        from ._stage_form import layout

        dyn = discretize(self.system, self.integrator, h=self.h)
        lay = layout(self, dyn)
        z = params.state
        x0 = jnp.zeros((lay.nx,), z.dtype).at[jnp.asarray(lay.reduced, int)].set(z)
        c0 = params.controls[0] * self.parameterization.scale
        return dyn.node(x0, c0)

    def rollout(self, params, *, start=None, save="all") -> Trajectory:
        """The optimizer's trajectory (``self.integrator``, ``n_steps`` steps; a gait: one period),
        from ``start = (q0, qdot0)`` (default ``self.initial_state(params)``), with ``simulate``'s
        ``save`` (default ``"all"``)."""
        q0, qdot0 = self.initial_state(params) if start is None else start
        return simulate(
            self.system,
            q0,
            qdot0,
            self.controls(params),
            t_final=self.t_final,
            n_steps=self.n_steps,
            integrator=self.integrator,
            checkpoint=self.checkpoint,
            save=save,
            check_constraints=False,
            divergence=None,
        )

    # ------------------------------------------------------------------ penalty form
    def objective_terms(self) -> dict[str, AbstractTerm]:
        names = [type(t).__name__.lower() for t in self.objective]
        return {
            n if names.count(n) == 1 else f"{n}{i}": t for i, (n, t) in enumerate(zip(names, self.objective))
        }

    @compiled_unless_staged
    def terms(self, traj: Trajectory, params) -> dict[str, Array]:
        """Every term on a trajectory: the objective terms (times ``objective_weight``) and each
        constraint's penalty (its ``weight`` times the squared residual; ``bounds``: the bounds'
        penalty)."""
        c = jax.vmap(self.controls(params))(traj.t)
        obs = Node(traj.q, traj.qdot)
        q0 = traj.q[0]
        out = {
            k: self.objective_weight * v
            for k, v in evaluate_terms(self.objective_terms(), self.system, obs, c, self.h, q0).items()
        }
        out.update(self._penalties(traj, c, obs, q0))
        scale = self.parameterization.scale
        out["bounds"] = jnp.sum(jax.vmap(lambda q, cc: self.bounds.penalty(q, cc, scale, self.h))(traj.q, c))
        return out

    def _penalties(self, traj, c, obs, q0) -> dict[str, Array]:
        last = jax.tree_util.tree_map(lambda x: x[-1], obs)
        first = jax.tree_util.tree_map(lambda x: x[0], obs)
        out = {}
        for i, con in enumerate(self.constraints):
            name = type(con).__name__.lower()
            name = name if sum(type(k) is type(con) for k in self.constraints) == 1 else f"{name}{i}"
            if isinstance(con, AbstractTerminalConstraint):
                out[name] = con.penalty(con.residual(self.system, last, q0))
            elif isinstance(con, AbstractPathConstraint):
                r = jax.vmap(lambda t, o, cc, con=con: con.residual(self.system, t, o, cc))(traj.t, obs, c)
                out[name] = self.h * con.penalty(r)
            elif isinstance(con, AbstractInitialConstraint):
                out[name] = con.penalty(con.residual(self.system, first, c[0]))
            elif isinstance(con, Periodic):
                out[name] = con.penalty(self._return_error(last, first, c))
        return out

    def _return_error(self, last: Node, first: Node, c: Array) -> Array:
        """A gait's return conditions on nodes: the non-cyclic shape, the minimal velocities and
        the controls at ``t_N`` against ``t_0``."""
        system = self.system
        keep = jnp.asarray(
            [3 + i for i, n in enumerate(system.shape_names) if n not in self.periodic.cyclic], int
        )
        v_n = system.velocities_from_qdot(last.q, last.qdot)
        v_0 = system.velocities_from_qdot(first.q, first.qdot)
        return jnp.concatenate([last.q[keep] - first.q[keep], v_n - v_0, c[-1] - c[0]])

    @compiled_unless_staged
    def loss(self, params) -> tuple[Array, dict]:
        """The penalty form ``(J, terms)``: the weighted objective plus the constraint penalties.

        Called on values (or under a top-level ``jax.grad``) it runs as one compiled program,
        compiled once for all later values; inside your ``jax.jit`` it is traced inline."""
        terms = self.terms(self.rollout(params), params)
        return sum(terms.values()), terms

    def value(self, params) -> Array:
        """The scalar penalty-form loss."""
        return self.loss(params)[0]

    # ------------------------------------------------------------------ guesses and options
    def init(self, key: PRNGKeyArray | None = None, *, amplitude: float | None = None) -> Any:
        """An initial guess: deterministic for ``key=None`` (a batch of ``guess.starts`` random
        guesses when that is above 1), random otherwise (vmap over keys for a batch)."""
        amplitude = self.guess.amplitude if amplitude is None else amplitude
        if key is None and self.guess.starts > 1:
            keys = jax.random.split(jax.random.PRNGKey(self.guess.seed), self.guess.starts)
            return _guesses(self, keys, amplitude)
        if key is None:
            host = _host_guess(self, amplitude)
            if host is not None:
                return host
        return _initial_guess(self, key, amplitude)

    def with_options(self, **changes) -> Task:
        """A copy with other pieces, checked as :func:`~ldap_jax.control.make_task` checks them:
        any of ``integrator``, ``system``, ``n_steps``, ``t_final``, ``checkpoint``, ``goal`` (the
        target of the :class:`TerminalPose` constraint), ``bounds``, ``objective``, ``constraints``,
        ``guess``.

        Raises:
            TypeError, ValueError: as :func:`~ldap_jax.control.make_task`.
        """
        from ._build import rebuild

        return rebuild(self, **changes)


def _host_guess(task: Task, amplitude: Any) -> Array | None:
    """The deterministic default guess of per-step controls (:meth:`SampledControls.fixed_init`,
    what :meth:`SampledControls.init` gives for ``key=None``), computed with NumPy; ``None`` where
    :func:`_initial_guess` is needed (a periodic task, a gait or explicit guess, another
    parameterization, a traced amplitude). In a new process the compiled
    :func:`_initial_guess` cost a trace and a cache read (20-60 ms)."""
    p = task.parameterization
    if (
        task.periodic is not None
        or task.guess.controls is not None
        or task.guess.gait is not None
        or type(p) is not SampledControls
        or isinstance(amplitude, bool)
        or not isinstance(amplitude, (int, float))
    ):
        return None
    return asarray(p.fixed_init(amplitude, xp=np), jnp.result_type(float))


@eqx.filter_jit
def _initial_guess(task: Task, key: PRNGKeyArray | None, amplitude: float) -> Any:
    # one compiled program (op by op, a guess compiled some 15 small programs on a first call)
    p = task.parameterization
    if task.guess.controls is not None and key is None:
        controls = jnp.asarray(task.guess.controls, p.scale.dtype)
    elif task.guess.gait is not None and isinstance(p, SampledControls):
        gp = task.guess.gait.init(key, amplitude=amplitude)
        ts = p.t0 + (p.t_final - p.t0) * jnp.linspace(0.0, 1.0, p.n_steps + 1)
        controls = jax.vmap(task.guess.gait.controls(gp))(ts) / p.scale[None, :]
    else:
        controls = p.init(key, amplitude=amplitude, periodic=task.periodic is not None)
    if task.periodic is None:
        return controls
    from ._stage_form import layout

    lay = layout(task, discretize(task.system, task.integrator, h=task.h))
    return GaitParams(controls, jnp.zeros((lay.nz,), controls.dtype))


@eqx.filter_jit
def _guesses(task: Task, keys: Array, amplitude: float) -> Any:
    return jax.vmap(lambda k: _initial_guess(task, k, amplitude))(keys)
