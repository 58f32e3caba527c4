"""CasADi + IPOPT baseline for the optimal-control benchmark: direct multiple shooting with RK4.

Formulation (one NLP per task, float64, default IPOPT options, printing silenced):

* Grid ``t_k = k h``, ``h = T / N``, ``k = 0..N``. Decision variables: the ODE states ``x_0..x_N``
  (multiple shooting) and the control node values ``c_0..c_N``; the controls are linearly
  interpolated between the nodes, exactly as in ``ldap_jax``'s sampled controls.
* Dynamics: ``x_{k+1} = RK4(x_k; c_k, c_{k+1})`` as equality constraints (shooting gaps), one
  classical RK4 step per interval whose stages see ``c_k`` at ``t_k``, ``(c_k + c_{k+1}) / 2`` at
  ``t_k + h/2`` and ``c_{k+1}`` at ``t_k + h``.
* Hard constraints: the initial state and the terminal conditions are fixed as equal lower and
  upper bounds of the node variables ``x_0`` and ``x_N``; the state and control bounds are simple
  bounds of the node variables (enforced at every node only; IPOPT's default
  ``bound_relax_factor = 1e-8`` lets an active bound be exceeded by about 1e-8).
* Objective (effort only): ``sum_{k=0}^{N} h sum_ch (c_k[ch] / scale[ch])^2``.

ODE states. Car (``m, I, K, rho, l``): ``x = (x, y, theta, psi, sigma, psidot)``, controls
``(f_psi, u_sigma)``::

    xdot = rho psidot cos theta,  ydot = rho psidot sin theta,  thetadot = (rho / l) sigma psidot,
    sigma_dot = u_sigma,
    (I + m rho^2 + K rho^2 sigma^2 / l^2) psi_ddot = f_psi - K rho^2 sigma u_sigma psidot / l^2.

Snakeboard (``m, l, I, J``): ``x = (x, y, theta, psi, phi, psidot, phidot, s)``, controls
``(f_psi, f_phi)``::

    xdot = -l cos(phi) cos(theta) s,  ydot = -l cos(phi) sin(theta) s,  thetadot = sin(phi) s,
    rhs = f_psi - I cos(phi) phidot s,  det = I (m l^2 - I sin^2 phi),
    psi_ddot = m l^2 rhs / det,  s_dot = -I sin(phi) rhs / det,  phi_ddot = f_phi / (2 J).

Initial guess: the initial state at every node and zero controls (what a new user would pass),
except for ``parallel_park``, where IPOPT stops at ``Infeasible_Problem_Detected`` from that guess
(at rest with zero controls the lateral motion is not controllable to first order); there the
states are linearly interpolated to the terminal values and the controls are a small sinusoid
(:func:`initial_guess`, :attr:`Problem.guess`).

The optimized controls are checked by replaying them (linear interpolation) on an independent
high-accuracy solution of the same ODE (``scipy.integrate.solve_ivp``, DOP853, ``rtol = atol =
1e-12``, interval by interval so that the kinks of the interpolation are resolved).

Timings are wall clock (``time.perf_counter``; the process CPU time is recorded too); the import of
CasADi is outside them. CasADi and SciPy are imported inside the functions: importing this module
needs only NumPy, so a benchmark can skip the baseline when CasADi is not installed.

    python scripts/casadi_baseline.py                      # all tasks, table on stdout
    python scripts/casadi_baseline.py u_turn --repeats 5
    python scripts/casadi_baseline.py --gaits [drive turn sideways] [--out gaits.json]

The periodic gaits (``--gaits``) are in ``scripts/casadi_gaits.py``.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import statistics
import time

import numpy as np
from _args import positive_int

__all__ = ["TASKS", "Problem", "problem", "rhs", "build", "initial_guess", "replay", "run_task"]

TASKS = ("parallel_park", "u_turn", "reach")

CAR = {"m": 1.0, "I": 0.1, "K": 0.2, "rho": 0.1, "l": 0.5}
SNAKEBOARD = {"m": 1.0, "l": 0.5, "I": 0.05, "J": 0.02}

_STATE_NAMES = {
    "car": ("x", "y", "theta", "psi", "sigma", "psidot"),
    "snakeboard": ("x", "y", "theta", "psi", "phi", "psidot", "phidot", "s"),
}
_CONTROL_NAMES = {"car": ("f_psi", "u_sigma"), "snakeboard": ("f_psi", "f_phi")}


@dataclasses.dataclass(frozen=True)
class Problem:
    """The constants of one task (everything another script needs to build the same problem).

    Attributes:
        name: task name. system: ``"car"`` or ``"snakeboard"``. params: the model's parameters.
        t_final: horizon T (s). n_steps: number of intervals N (N + 1 control nodes).
        state_names, control_names: the ODE state and the control channels, in order.
        x0: initial ODE state. terminal: ``{state name: value}``, equalities on ``x_N``.
        goal: goal pose ``(x, y, theta)``.
        state_bounds: ``{state name: b}``, ``|x_k[name]| <= b`` at every node.
        control_bounds: ``{control name: b}``, ``|c_k[name]| <= b`` at every node.
        scale: per-channel control scale of the effort.
        guess: the initial guess used by default (see :func:`initial_guess`).
    """

    name: str
    system: str
    params: dict
    t_final: float
    n_steps: int
    state_names: tuple[str, ...]
    control_names: tuple[str, ...]
    x0: tuple[float, ...]
    terminal: dict
    goal: tuple[float, float, float]
    state_bounds: dict
    control_bounds: dict
    scale: tuple[float, float]
    guess: str = "rest"

    @property
    def h(self) -> float:
        return self.t_final / self.n_steps

    @property
    def n_states(self) -> int:
        return len(self.state_names)


def problem(name: str) -> Problem:
    """The task ``name`` (one of :data:`TASKS`).

    * ``parallel_park`` (car): T = 10 s, N = 100, from rest at the origin to ``x = 0``,
      ``y = l / 2``, ``theta = 0`` at rest (``psidot = 0``); ``|sigma| <= 1``; ``psi`` free.
    * ``u_turn`` (car, lane width w = 1): T = 12 s, N = 120, from rest at ``(0, -w/4, 0)`` to
      ``(0, w/4, pi)`` at rest; ``|y| <= w/2``, ``|sigma| <= 1``.
    * ``reach`` (snakeboard): T = 16 s, N = 160, from rest at the origin to ``(2, 1, pi/2)`` with
      ``s = 0`` (so ``xdot = ydot = thetadot = 0``; rotor and steering rates free);
      ``|f_psi|, |f_phi| <= 0.1``, ``|phi| <= 1``.
    """
    car_scale = (CAR["I"] + CAR["m"] * CAR["rho"] ** 2, 0.5)
    if name == "parallel_park":
        goal = (0.0, CAR["l"] / 2, 0.0)
        return Problem(
            name=name,
            system="car",
            params=dict(CAR),
            t_final=10.0,
            n_steps=100,
            state_names=_STATE_NAMES["car"],
            control_names=_CONTROL_NAMES["car"],
            x0=(0.0,) * 6,
            terminal={"x": goal[0], "y": goal[1], "theta": goal[2], "psidot": 0.0},
            goal=goal,
            state_bounds={"sigma": 1.0},
            control_bounds={},
            scale=car_scale,
            guess="interpolated",  # IPOPT reports Infeasible_Problem_Detected from the rest guess
        )
    if name == "u_turn":
        w = 1.0
        goal = (0.0, w / 4, math.pi)
        return Problem(
            name=name,
            system="car",
            params=dict(CAR),
            t_final=12.0,
            n_steps=120,
            state_names=_STATE_NAMES["car"],
            control_names=_CONTROL_NAMES["car"],
            x0=(0.0, -w / 4, 0.0, 0.0, 0.0, 0.0),
            terminal={"x": goal[0], "y": goal[1], "theta": goal[2], "psidot": 0.0},
            goal=goal,
            state_bounds={"y": w / 2, "sigma": 1.0},
            control_bounds={},
            scale=car_scale,
        )
    if name == "reach":
        goal = (2.0, 1.0, math.pi / 2)
        return Problem(
            name=name,
            system="snakeboard",
            params=dict(SNAKEBOARD),
            t_final=16.0,
            n_steps=160,
            state_names=_STATE_NAMES["snakeboard"],
            control_names=_CONTROL_NAMES["snakeboard"],
            x0=(0.0,) * 8,
            terminal={"x": goal[0], "y": goal[1], "theta": goal[2], "s": 0.0},
            goal=goal,
            state_bounds={"phi": 1.0},
            control_bounds={"f_psi": 0.1, "f_phi": 0.1},
            scale=(0.1, 0.1),
        )
    raise ValueError(f"unknown task {name!r}; expected one of {TASKS}")


def rhs(system: str, params: dict, x, c, lib=math) -> list:
    """The ODE right-hand side as a list of scalar expressions.

    ``lib`` supplies ``sin`` and ``cos``: :mod:`math` for floats, ``casadi`` for symbols.
    """
    sin, cos = lib.sin, lib.cos
    if system == "car":
        m, inertia, kk, rho, l = (params[k] for k in ("m", "I", "K", "rho", "l"))
        _, _, th, _, sigma, psidot = (x[i] for i in range(6))
        f_psi, u_sigma = c[0], c[1]
        rv = rho * psidot
        inertia_eff = inertia + m * rho**2 + kk * rho**2 * sigma**2 / l**2
        psi_dd = (f_psi - kk * rho**2 * sigma * u_sigma * psidot / l**2) / inertia_eff
        return [rv * cos(th), rv * sin(th), rv * sigma / l, psidot, u_sigma, psi_dd]
    if system == "snakeboard":
        m, l, inertia, jj = (params[k] for k in ("m", "l", "I", "J"))
        _, _, th, _, phi, psidot, phidot, s = (x[i] for i in range(8))
        f_psi, f_phi = c[0], c[1]
        sp, cp = sin(phi), cos(phi)
        lcs = l * cp * s
        rhs_psi = f_psi - inertia * cp * phidot * s
        det = inertia * (m * l**2 - inertia * sp**2)
        psi_dd = m * l**2 * rhs_psi / det
        s_dot = -inertia * sp * rhs_psi / det
        return [-lcs * cos(th), -lcs * sin(th), sp * s, psidot, phidot, psi_dd, f_phi / (2 * jj), s_dot]
    raise ValueError(f"unknown system {system!r}")


def build(prob: Problem, options: dict | None = None):
    """Build the multiple-shooting NLP and its IPOPT solver (default options, printing off).

    ``options`` are extra ``nlpsol`` options (e.g. ``{"ipopt.print_level": 5}``), merged last.

    Returns:
        ``(solver, bounds, unpack)``: the ``casadi.nlpsol`` function, the dict of ``lbx, ubx,
        lbg, ubg`` and ``unpack(w) -> (states (N + 1, n_x), controls (N + 1, 2))``.
    """
    import casadi as ca

    nx, n = prob.n_states, prob.n_steps
    h = prob.h
    xs = ca.SX.sym("x", nx)
    cs = ca.SX.sym("c", 2)
    f = ca.Function("f", [xs, cs], [ca.vertcat(*rhs(prob.system, prob.params, xs, cs, ca))])
    x_k, c_a, c_b = ca.SX.sym("x_k", nx), ca.SX.sym("c_a", 2), ca.SX.sym("c_b", 2)
    c_m = 0.5 * (c_a + c_b)
    k1 = f(x_k, c_a)
    k2 = f(x_k + 0.5 * h * k1, c_m)
    k3 = f(x_k + 0.5 * h * k2, c_m)
    k4 = f(x_k + h * k3, c_b)
    step = ca.Function("rk4", [x_k, c_a, c_b], [x_k + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)])

    X = ca.SX.sym("X", nx, n + 1)
    C = ca.SX.sym("C", 2, n + 1)
    x_next = step.map(n)(X[:, :n], C[:, :n], C[:, 1:])
    gaps = ca.reshape(X[:, 1:] - x_next, -1, 1)
    scale = ca.DM(prob.scale)
    effort = h * ca.sumsqr(C / ca.repmat(scale, 1, n + 1))
    w = ca.vertcat(ca.reshape(X, -1, 1), ca.reshape(C, -1, 1))

    inf = np.inf
    lbx_x, ubx_x = np.full((nx, n + 1), -inf), np.full((nx, n + 1), inf)
    for name, b in prob.state_bounds.items():
        i = prob.state_names.index(name)
        lbx_x[i], ubx_x[i] = -b, b
    lbx_x[:, 0] = ubx_x[:, 0] = prob.x0
    for name, v in prob.terminal.items():
        i = prob.state_names.index(name)
        lbx_x[i, n] = ubx_x[i, n] = v
    lbx_c, ubx_c = np.full((2, n + 1), -inf), np.full((2, n + 1), inf)
    for name, b in prob.control_bounds.items():
        i = prob.control_names.index(name)
        lbx_c[i], ubx_c[i] = -b, b
    flat = lambda a: a.reshape(-1, order="F")  # noqa: E731  (CasADi is column-major)
    bounds = {
        "lbx": np.concatenate([flat(lbx_x), flat(lbx_c)]),
        "ubx": np.concatenate([flat(ubx_x), flat(ubx_c)]),
        "lbg": np.zeros(gaps.shape[0]),
        "ubg": np.zeros(gaps.shape[0]),
    }
    opts = {"ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes", **(options or {})}
    solver = ca.nlpsol("solver", "ipopt", {"x": w, "f": effort, "g": gaps}, opts)

    def unpack(w_opt):
        w_opt = np.asarray(w_opt, float).reshape(-1)
        states = w_opt[: nx * (n + 1)].reshape(n + 1, nx)
        controls = w_opt[nx * (n + 1) :].reshape(n + 1, 2)
        return states, controls

    return solver, bounds, unpack


def initial_guess(prob: Problem, kind: str | None = None) -> np.ndarray:
    """The flat initial guess ``w0`` (states then controls, column-major as in :func:`build`).

    * ``"rest"``: the initial state at every node, zero controls (what a new user would pass).
    * ``"interpolated"``: the states linearly interpolated from the initial state to the terminal
      values (components without a terminal value stay at their initial value), and small
      sinusoidal controls ``c_k[ch] = 0.1 scale[ch] sin(2 pi (ch + 1) t_k / T)``.
    """
    kind = prob.guess if kind is None else kind
    n, nx = prob.n_steps, prob.n_states
    x0 = np.asarray(prob.x0, float)
    t = np.linspace(0.0, prob.t_final, n + 1)
    if kind == "rest":
        states = np.tile(x0, (n + 1, 1))
        controls = np.zeros((n + 1, 2))
    elif kind == "interpolated":
        x_end = x0.copy()
        for name, v in prob.terminal.items():
            x_end[prob.state_names.index(name)] = v
        s = t[:, None] / prob.t_final
        states = (1 - s) * x0 + s * x_end
        controls = np.stack(
            [0.1 * prob.scale[i] * np.sin(2 * np.pi * (i + 1) * t / prob.t_final) for i in range(2)], axis=1
        )
    else:
        raise ValueError(f"unknown guess {kind!r}; expected 'rest' or 'interpolated'")
    assert states.shape == (n + 1, nx)
    return np.concatenate([states.reshape(-1), controls.reshape(-1)])


def replay(prob: Problem, controls: np.ndarray, x0: np.ndarray | None = None) -> np.ndarray:
    """The ODE states at the nodes ``(N + 1, n_x)`` under the linearly interpolated ``controls``,
    from ``x0`` (default :attr:`Problem.x0`), by ``solve_ivp`` (DOP853, ``rtol = atol = 1e-12``)
    interval by interval. ``prob`` needs ``system``, ``params``, ``h`` and ``n_steps`` (a gait's
    description will do)."""
    from scipy.integrate import solve_ivp

    controls = np.asarray(controls, float)
    h = prob.h
    out = [np.asarray(prob.x0 if x0 is None else x0, float)]
    for k in range(prob.n_steps):
        t0, c0, c1 = k * h, controls[k], controls[k + 1]

        def fun(t, x, t0=t0, c0=c0, c1=c1):
            a = (t - t0) / h
            return rhs(prob.system, prob.params, x, (1 - a) * c0 + a * c1)

        sol = solve_ivp(fun, (t0, t0 + h), out[-1], method="DOP853", rtol=1e-12, atol=1e-12)
        if not sol.success:
            raise RuntimeError(f"replay failed on interval {k}: {sol.message}")
        out.append(sol.y[:, -1])
    return np.stack(out)


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def _errors(prob: Problem, states: np.ndarray, controls: np.ndarray) -> dict:
    """Terminal errors and the largest bound violation of a trajectory at the nodes."""
    x_n = states[-1]
    pos = float(math.hypot(x_n[0] - prob.goal[0], x_n[1] - prob.goal[1]))
    heading = abs(_wrap(float(x_n[2] - prob.goal[2])))
    qdot = np.asarray(rhs(prob.system, prob.params, x_n, controls[-1]))[:3]
    if prob.system == "car":
        speed = abs(prob.params["rho"] * x_n[5])
    else:
        speed = float(np.linalg.norm(qdot))
    viol = 0.0
    for name, b in prob.state_bounds.items():
        viol = max(viol, float(np.max(np.abs(states[:, prob.state_names.index(name)]) - b)))
    for name, b in prob.control_bounds.items():
        viol = max(viol, float(np.max(np.abs(controls[:, prob.control_names.index(name)]) - b)))
    terminal = max(abs(x_n[prob.state_names.index(k)] - v) for k, v in prob.terminal.items())
    return {
        "position_error": pos,
        "heading_error": heading,
        "terminal_speed": speed,
        "terminal_qdot_norm": float(np.linalg.norm(qdot)),
        "terminal_max_error": float(terminal),
        "max_violation": max(viol, 0.0),
    }


def run_task(name: str, repeats: int = 3, guess: str | None = None) -> dict:
    """Build, solve and check the task ``name`` with CasADi + IPOPT.

    Args:
        name: one of :data:`TASKS`. repeats: re-solves (from the same guess) for the repeat time.
        guess: initial guess (``"rest"`` or ``"interpolated"``); default: the task's
            :attr:`Problem.guess`, the one that converges (see :func:`initial_guess`).

    Returns:
        A dict with ``build_time`` (symbolic construction + ``nlpsol``), ``first_solve_time``,
        ``first_call`` (their sum), ``repeat_time`` (median of ``repeats`` re-solves),
        ``repeat_times``, ``cpu_time`` (the same in process CPU time), ``iterations``,
        ``success``, ``return_status``, ``objective``, ``controls`` (N + 1, 2), ``states`` (the
        optimizer's nodes, (N + 1, n_x)), ``replay_states`` and, from the replay,
        ``position_error`` [m], ``heading_error`` [rad], ``terminal_speed`` (car
        ``|rho psidot|``, snakeboard ``|(xdot, ydot, thetadot)|``), ``terminal_qdot_norm``,
        ``terminal_max_error`` (largest error of a terminal equality) and ``max_violation``
        (largest ``(|value| - bound)_+`` at the nodes); ``optimizer_errors`` holds the same
        quantities on the optimizer's own RK4 nodes, and ``replay_defect`` the
        largest node state difference between the optimizer and the replay.
    """
    import casadi  # noqa: F401  (imported outside the timings)

    prob = problem(name)
    guess = prob.guess if guess is None else guess
    w0 = initial_guess(prob, guess)

    t0, p0 = time.perf_counter(), time.process_time()
    solver, bounds, unpack = build(prob)
    t1, p1 = time.perf_counter(), time.process_time()
    sol = solver(x0=w0, **bounds)
    t2, p2 = time.perf_counter(), time.process_time()
    stats = solver.stats()
    repeat_times, repeat_cpu = [], []
    for _ in range(repeats):
        s0, q0 = time.perf_counter(), time.process_time()
        solver(x0=w0, **bounds)
        repeat_times.append(time.perf_counter() - s0)
        repeat_cpu.append(time.process_time() - q0)

    states, controls = unpack(sol["x"])
    replayed = replay(prob, controls)
    out = {
        "name": name,
        "system": prob.system,
        "guess": guess,
        "build_time": t1 - t0,
        "first_solve_time": t2 - t1,
        "first_call": t2 - t0,
        "repeat_time": statistics.median(repeat_times) if repeat_times else float("nan"),
        "repeat_times": repeat_times,
        "cpu_time": {
            "build": p1 - p0,
            "first_solve": p2 - p1,
            "first_call": p2 - p0,
            "repeat": statistics.median(repeat_cpu) if repeat_cpu else float("nan"),
        },
        "iterations": int(stats["iter_count"]),
        "success": bool(stats["success"]),
        "return_status": str(stats["return_status"]),
        "objective": float(sol["f"]),
        "controls": controls,
        "states": states,
        "replay_states": replayed,
        "replay_defect": float(np.max(np.abs(replayed - states))),
        "optimizer_errors": _errors(prob, states, controls),
    }
    out.update(_errors(prob, replayed, controls))
    return out


def _table(results: list[dict]) -> str:
    cols = [
        ("task", lambda r: r["name"]),
        ("guess", lambda r: r["guess"]),
        ("first call [s]", lambda r: f"{r['first_call']:.3f}"),
        ("build [s]", lambda r: f"{r['build_time']:.3f}"),
        ("first solve [s]", lambda r: f"{r['first_solve_time']:.3f}"),
        ("repeat [s]", lambda r: f"{r['repeat_time']:.3f}"),
        (
            "CPU first/repeat [s]",
            lambda r: f"{r['cpu_time']['first_call']:.2f}/{r['cpu_time']['repeat']:.2f}",
        ),
        ("iters", lambda r: str(r["iterations"])),
        ("status", lambda r: r["return_status"]),
        ("objective", lambda r: f"{r['objective']:.6g}"),
        ("pos err [m]", lambda r: f"{r['position_error']:.1e}"),
        ("heading err [rad]", lambda r: f"{r['heading_error']:.1e}"),
        ("speed", lambda r: f"{r['terminal_speed']:.1e}"),
        ("violation", lambda r: f"{r['max_violation']:.1e}"),
        ("RK4 vs replay", lambda r: f"{r['replay_defect']:.1e}"),
    ]
    rows = [[c[0] for c in cols]] + [[f(r) for _, f in cols] for r in results]
    widths = [max(len(row[i]) for row in rows) for i in range(len(cols))]
    fmt = lambda row: "| " + " | ".join(v.ljust(w) for v, w in zip(row, widths)) + " |"  # noqa: E731
    return "\n".join(
        [fmt(rows[0]), "|" + "|".join("-" * (w + 2) for w in widths) + "|"] + [fmt(r) for r in rows[1:]]
    )


def require_casadi(parser: argparse.ArgumentParser) -> None:
    """Stop with a clear message (before any work) when CasADi is not installed."""
    try:
        import casadi  # noqa: F401
    except ModuleNotFoundError:
        parser.error("CasADi is not installed: pip install -e '.[bench]' (make demo installs it)")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    parser.add_argument(
        "tasks", nargs="*", metavar="TASK", help=f"tasks to run (default: all of {', '.join(TASKS)})"
    )
    parser.add_argument("--repeats", type=positive_int, default=3)
    parser.add_argument("--guess", choices=("rest", "interpolated"), default=None)
    parser.add_argument(
        "--gaits",
        action="store_true",
        help="run the periodic gaits instead (scripts/casadi_gaits.py; TASK: drive, turn, sideways)",
    )
    parser.add_argument("--out", default=None, help="with --gaits: write the results as JSON to this file")
    import casadi_gaits  # here: the gait baseline imports this module

    casadi_gaits.add_arguments(parser, positional=False)
    args = parser.parse_args(argv)
    require_casadi(parser)
    if args.gaits:
        casadi_gaits.run_cli(parser, args, args.tasks)
        return
    for t in args.tasks:
        if t not in TASKS:
            parser.error(f"unknown task {t!r}; expected one of {', '.join(TASKS)}")
    results = [run_task(t, repeats=args.repeats, guess=args.guess) for t in args.tasks or TASKS]
    print(_table(results))


if __name__ == "__main__":
    main()
