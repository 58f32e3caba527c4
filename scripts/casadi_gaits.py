"""CasADi + IPOPT baseline for the periodic gaits (``lc.drive_gait``, ``lc.turn_gait``,
``lc.sideways_gait``): RK4 multiple shooting in ``casadi.Opti``, one period per NLP.

Formulation (float64, default IPOPT options, printing silenced, ``expand = True``: the ``Opti``
(MX) functions expanded to SX, as :mod:`casadi_baseline` builds them; the ODE and the RK4 step are
those of :mod:`casadi_baseline`):

* Grid ``t_k = k h``, ``h = T / N``, ``N = 100``. Decision variables: the node states
  ``X_0..X_N`` (the full ODE state of :func:`casadi_baseline.rhs`: car ``(x, y, theta, psi,
  sigma, psidot)``, snakeboard ``(x, y, theta, psi, phi, psidot, phidot, s)``) and the node
  controls ``c_0..c_N`` (physical units), linearly interpolated between the nodes; one RK4 step
  per interval, its stages seeing ``c_k``, ``(c_k + c_{k+1}) / 2`` and ``c_{k+1}``.
* Start: ``x = y = theta = 0`` and the cyclic coordinate ``psi = 0`` (rotor angle, rear wheel
  angle); the rest of ``X_0`` is free.
* Periodicity: every entry of ``X_N`` except ``x, y, theta, psi`` equals that of ``X_0`` (the
  shape ``phi`` / ``sigma`` and all the velocities), and ``c_N = c_0``.
* Anchor: snakeboard ``psidot_0 = s_0 = 0`` (``lc.InitialRest((0, 2))``: the rotor rate and the
  board speed); car ``psidot_0 = 0`` (the rear wheel at rest, ``lc.InitialRest((0,))``).
* Bounds at every node: snakeboard ``|f_psi|, |f_phi| <= 0.1`` N m, ``|phi| <= 1``; car
  ``|f_psi| <= 0.4`` N m, ``|sigma| <= 1`` (``u_sigma`` unbounded, as ``lc.sideways_gait``).
* Tasks: ``drive`` (snakeboard, T = pi): maximise ``x_N`` with ``theta_N = 0``; ``turn``
  (snakeboard, T = pi): maximise ``theta_N`` with ``x_N = y_N = 0``; ``sideways`` (car, T = 4):
  minimise the exact effort of the piecewise-linear controls,
  ``sum_k h/3 (U_k^2 + U_k U_{k+1} + U_{k+1}^2)``, ``U = c / scale``, ``scale = (I + m rho^2,
  0.5)`` (``lc.car_effort_scale``), with ``x_N = 0``, ``y_N = 0.05``, ``theta_N = 0``.
* Initial guesses: ``starts`` per task (drive 5, turn 25, sideways 5), each a smooth periodic
  control guess (the drive gait's first one is ``f_psi = 0.09 sin(4 pi t / T)``, ``f_phi = -0.09
  cos(2 pi t / T)``, ``lc.drive_gait``'s default guess; the others random: three harmonics with
  random coefficients, scaled to ``amplitude * scale`` at their peak) with the states of an RK4
  rollout of it from rest at the origin. The best converged start is reported.

Reported per task: the objective (displacement per cycle m, rotation per cycle rad, effort), its
value on a replay of the controls (``scipy.integrate.solve_ivp``, DOP853, ``rtol = atol = 1e-12``,
from the optimizer's ``X_0``), IPOPT's iterations and status, the largest constraint violation
(of every NLP constraint, at the solution), the times: ``build`` (the ``Opti`` problem),
``first_call`` (build + the first start's solve, which also creates the IPOPT solver),
``all_starts`` (build + every start), ``repeat`` (median of re-solves of the best start from its
guess with the same ``Opti``), and the objective of every start. Wall clock
(``time.perf_counter``; the process CPU time is recorded too).
The bounds are constraints of the NLP (``Opti.bounded``), so IPOPT's default ``bound_relax_factor =
1e-8`` lets an active bound be exceeded by about 1e-8 (the sideways gait's ``|f_psi| = 0.4``): the
reported violation includes that. A start where IPOPT fails keeps its last iterate (``opti.debug``)
and counts as not converged.

    python scripts/casadi_baseline.py --gaits                 # all three, table on stdout
    python scripts/casadi_gaits.py drive --out gaits.json    # the same, directly
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import statistics
import time

import numpy as np
from _args import positive_int
from casadi_baseline import _CONTROL_NAMES, _STATE_NAMES, CAR, SNAKEBOARD, require_casadi, rhs
from casadi_baseline import replay as cb_replay

__all__ = ["GAITS", "Gait", "gait", "build_gait", "guesses", "rollout", "replay_gait", "run_gait"]

GAITS = ("drive", "turn", "sideways")

#: ODE state entries that are not periodic: the group (x, y, theta) and the cyclic coordinate psi.
_NOT_PERIODIC = ("x", "y", "theta", "psi")


@dataclasses.dataclass(frozen=True)
class Gait:
    """The constants of one gait task.

    Attributes:
        name: task name. system: ``"car"`` or ``"snakeboard"``. params: the model's parameters.
        period: T (s). n_steps: N. state_names, control_names: as :mod:`casadi_baseline`.
        anchor: state names that vanish at the start (besides ``x, y, theta, psi``).
        terminal: ``{state name: value}``, equalities on ``X_N``.
        maximise: the state whose final value is maximised, or None (minimise the effort).
        state_bounds, control_bounds: ``{name: b}``, ``|value| <= b`` at every node.
        scale: per-channel control scale of the effort (and of the random guesses).
        starts: number of initial guesses. amplitude: random guesses' peak, fraction of ``scale``.
    """

    name: str
    system: str
    params: dict
    period: float
    n_steps: int
    state_names: tuple[str, ...]
    control_names: tuple[str, ...]
    anchor: tuple[str, ...]
    terminal: dict
    maximise: str | None
    state_bounds: dict
    control_bounds: dict
    scale: tuple[float, float]
    starts: int
    amplitude: float

    @property
    def h(self) -> float:
        return self.period / self.n_steps

    @property
    def n_states(self) -> int:
        return len(self.state_names)

    @property
    def objective_name(self) -> str:
        return {"x": "displacement [m/cycle]", "theta": "rotation [rad/cycle]", None: "effort"}[self.maximise]


def gait(name: str, n_steps: int = 100, starts: int | None = None) -> Gait:
    """The gait task ``name`` (one of :data:`GAITS`); ``starts`` overrides the number of guesses."""
    if name in ("drive", "turn"):
        common = dict(
            system="snakeboard",
            params=dict(SNAKEBOARD),
            period=math.pi,
            n_steps=n_steps,
            state_names=_STATE_NAMES["snakeboard"],
            control_names=_CONTROL_NAMES["snakeboard"],
            anchor=("psidot", "s"),
            state_bounds={"phi": 1.0},
            control_bounds={"f_psi": 0.1, "f_phi": 0.1},
            scale=(0.1, 0.1),
            amplitude=0.7,
        )
        if name == "drive":
            return Gait(name=name, terminal={"theta": 0.0}, maximise="x", starts=starts or 5, **common)
        return Gait(name=name, terminal={"x": 0.0, "y": 0.0}, maximise="theta", starts=starts or 25, **common)
    if name == "sideways":
        return Gait(
            name=name,
            system="car",
            params=dict(CAR),
            period=4.0,
            n_steps=n_steps,
            state_names=_STATE_NAMES["car"],
            control_names=_CONTROL_NAMES["car"],
            anchor=("psidot",),
            terminal={"x": 0.0, "y": 0.05, "theta": 0.0},
            maximise=None,
            state_bounds={"sigma": 1.0},
            control_bounds={"f_psi": 0.4},
            scale=(CAR["I"] + CAR["m"] * CAR["rho"] ** 2, 0.5),
            starts=starts or 5,
            amplitude=0.3,
        )
    raise ValueError(f"unknown gait {name!r}; expected one of {GAITS}")


def exact_effort(controls: np.ndarray, scale, h: float) -> float:
    """``sum_k h/3 (U_k^2 + U_k U_{k+1} + U_{k+1}^2)``, ``U = controls / scale``: the integral of
    ``|c(t) / scale|^2`` for the linear interpolation of the node controls ``(N + 1, 2)``."""
    u = np.asarray(controls, float) / np.asarray(scale, float)
    a, b = u[:-1], u[1:]
    return float(h / 3 * np.sum(a * a + a * b + b * b))


def _rk4_numpy(g: Gait, x, c0, c1):
    h = g.h
    f = lambda x, c: np.asarray(rhs(g.system, g.params, x, c), float)  # noqa: E731
    cm = 0.5 * (c0 + c1)
    k1 = f(x, c0)
    k2 = f(x + 0.5 * h * k1, cm)
    k3 = f(x + 0.5 * h * k2, cm)
    k4 = f(x + h * k3, c1)
    return x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


def rollout(g: Gait, controls: np.ndarray, x0=None) -> np.ndarray:
    """The RK4 node states ``(N + 1, n_x)`` (the optimizer's discretisation) under ``controls``,
    from ``x0`` (default: rest at the origin)."""
    x = np.zeros(g.n_states) if x0 is None else np.asarray(x0, float)
    out = [x]
    for k in range(g.n_steps):
        out.append(_rk4_numpy(g, out[-1], controls[k], controls[k + 1]))
    return np.stack(out)


def guesses(g: Gait, seed: int = 0) -> list[np.ndarray]:
    """The ``g.starts`` control guesses, each ``(N + 1, 2)`` node values, periodic (``c_N = c_0``).

    The drive gait's first guess is ``lc.drive_gait``'s default (``0.09 sin(4 pi t / T)``,
    ``-0.09 cos(2 pi t / T)``); the others are random: per channel ``sum_{j=1}^{3} (a_j cos(2 pi
    j t / T) + b_j sin(2 pi j t / T)) / j`` with standard normal ``a_j, b_j``, scaled to the peak
    ``amplitude * scale``."""
    rng = np.random.default_rng(seed)
    s = np.linspace(0.0, 1.0, g.n_steps + 1)
    out = []
    if g.name == "drive":
        out.append(np.stack([0.09 * np.sin(4 * np.pi * s), -0.09 * np.cos(2 * np.pi * s)], axis=1))
    while len(out) < g.starts:
        chans = []
        for ch in range(2):
            a, b = rng.standard_normal(3), rng.standard_normal(3)
            w = 2 * np.pi * s
            v = sum((a[j] * np.cos((j + 1) * w) + b[j] * np.sin((j + 1) * w)) / (j + 1) for j in range(3))
            chans.append(g.amplitude * g.scale[ch] * v / np.max(np.abs(v)))
        out.append(np.stack(chans, axis=1))
    return out


def build_gait(g: Gait, options: dict | None = None):
    """The ``casadi.Opti`` problem of the gait ``g`` with IPOPT attached (printing off;
    ``options`` are extra ``Opti.solver`` plugin options, merged last).

    Returns:
        ``(opti, X, C, objective, effort)``: the problem, the node states ``(n_x, N + 1)``, the
        node controls ``(2, N + 1)``, the objective as reported (``x_N``, ``theta_N`` or the
        effort) and the exact effort expression.
    """
    import casadi as ca

    nx, n, h = g.n_states, g.n_steps, g.h
    xs, cs = ca.SX.sym("x", nx), ca.SX.sym("c", 2)
    f = ca.Function("f", [xs, cs], [ca.vertcat(*rhs(g.system, g.params, xs, cs, ca))])
    x_k, c_a, c_b = ca.SX.sym("x_k", nx), ca.SX.sym("c_a", 2), ca.SX.sym("c_b", 2)
    c_m = 0.5 * (c_a + c_b)
    k1 = f(x_k, c_a)
    k2 = f(x_k + 0.5 * h * k1, c_m)
    k3 = f(x_k + 0.5 * h * k2, c_m)
    k4 = f(x_k + h * k3, c_b)
    step = ca.Function("rk4", [x_k, c_a, c_b], [x_k + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)])

    opti = ca.Opti()
    X = opti.variable(nx, n + 1)
    C = opti.variable(2, n + 1)
    idx = g.state_names.index
    opti.subject_to(X[:, 1:] == step.map(n)(X[:, :n], C[:, :n], C[:, 1:]))
    for name in ("x", "y", "theta", "psi", *g.anchor):
        opti.subject_to(X[idx(name), 0] == 0)
    periodic = [i for i, name in enumerate(g.state_names) if name not in _NOT_PERIODIC]
    for i in periodic:
        opti.subject_to(X[i, n] == X[i, 0])
    opti.subject_to(C[:, n] == C[:, 0])
    for name, v in g.terminal.items():
        opti.subject_to(X[idx(name), n] == v)
    for name, b in g.state_bounds.items():
        opti.subject_to(opti.bounded(-b, X[idx(name), :], b))
    for name, b in g.control_bounds.items():
        opti.subject_to(opti.bounded(-b, C[g.control_names.index(name), :], b))
    u = C / ca.repmat(ca.DM(g.scale), 1, n + 1)
    ua, ub = u[:, :n], u[:, 1:]
    effort = h / 3 * ca.sum2(ca.sum1(ua * ua + ua * ub + ub * ub))
    if g.maximise is None:
        objective = effort
        opti.minimize(effort)
    else:
        objective = X[idx(g.maximise), n]
        opti.minimize(-objective)
    opts = {
        "ipopt.print_level": 0,
        "print_time": False,
        "ipopt.sb": "yes",
        "expand": True,
    }
    opti.solver("ipopt", {**opts, **(options or {})})
    return opti, X, C, objective, effort


def replay_gait(g: Gait, x0: np.ndarray, controls: np.ndarray) -> np.ndarray:
    """The node states ``(N + 1, n_x)`` under the linearly interpolated ``controls`` from ``x0``
    (:func:`casadi_baseline.replay`: ``solve_ivp``, DOP853, ``rtol = atol = 1e-12``)."""
    return cb_replay(g, controls, x0)


def _violation(opti, sol_or_debug) -> float:
    """The largest violation of the NLP's constraints ``lbg <= g <= ubg`` at the solution."""
    g = np.asarray(sol_or_debug.value(opti.g), float).reshape(-1)
    lo = np.asarray(sol_or_debug.value(opti.lbg), float).reshape(-1)
    hi = np.asarray(sol_or_debug.value(opti.ubg), float).reshape(-1)
    return float(max(np.max(lo - g, initial=0.0), np.max(g - hi, initial=0.0), 0.0))


def _boundary_errors(g: Gait, states: np.ndarray, controls: np.ndarray) -> dict:
    """On a trajectory (e.g. the replay): the largest error of the terminal equalities and of the
    periodicity of the state, the reported objective, and the largest bound violation."""
    idx = g.state_names.index
    periodic = [i for i, name in enumerate(g.state_names) if name not in _NOT_PERIODIC]
    terminal = max(abs(states[-1, idx(k)] - v) for k, v in g.terminal.items())
    period = float(np.max(np.abs(states[-1, periodic] - states[0, periodic])))
    viol = 0.0
    for name, b in g.state_bounds.items():
        viol = max(viol, float(np.max(np.abs(states[:, idx(name)]) - b)))
    for name, b in g.control_bounds.items():
        viol = max(viol, float(np.max(np.abs(controls[:, g.control_names.index(name)]) - b)))
    if g.maximise is None:
        obj = exact_effort(controls, g.scale, g.h)
    else:
        obj = float(states[-1, idx(g.maximise)])
    return {
        "objective": obj,
        "terminal_error": float(terminal),
        "periodicity_error": period,
        "bound_violation": max(viol, 0.0),
    }


def run_gait(
    name: str, repeats: int = 3, starts: int | None = None, seed: int = 0, n_steps: int = 100
) -> dict:
    """Build the gait ``name``, solve it from every guess of :func:`guesses`, keep the best
    converged start, re-solve it ``repeats`` times for the repeat time and replay it.

    Returns:
        A dict: ``objective`` (best start, as reported: displacement, rotation or effort),
        ``effort`` (its exact effort), ``iterations``, ``return_status``, ``success``,
        ``violation`` (largest NLP constraint violation), ``best_start``, ``starts`` (per start:
        ``objective``, ``iterations``, ``return_status``, ``success``, ``solve_time``, ``solve_cpu``,
        ``violation``), ``build_time``, ``first_call`` (build + the first start's solve),
        ``all_starts`` (build + every start), ``best_first_call`` (build + the best start's
        solve), ``repeat_time`` (median of the re-solves), ``repeat_times``, ``cpu_time`` (the
        same in process CPU time), ``replay`` (the
        objective, terminal and periodicity errors and bound violation of the replayed
        controls), ``replay_defect`` (largest node state difference RK4 vs replay), ``x0``,
        ``controls``, ``states``.
    """
    import casadi  # noqa: F401  (imported outside the timings)

    g = gait(name, n_steps=n_steps, starts=starts)
    cands = guesses(g, seed)
    t0, p0 = time.perf_counter(), time.process_time()
    opti, X, C, objective, effort = build_gait(g)
    build_time, build_cpu = time.perf_counter() - t0, time.process_time() - p0

    def solve(controls):
        opti.set_initial(C, controls.T)
        opti.set_initial(X, rollout(g, controls).T)
        s0, q0 = time.perf_counter(), time.process_time()
        try:
            opti.solve()
        except RuntimeError:  # Opti raises when IPOPT fails; the last iterate is in opti.debug
            pass
        return opti.debug, (time.perf_counter() - s0, time.process_time() - q0)

    per_start, best, best_key = [], None, None
    for i, controls in enumerate(cands):
        sol, dt = solve(controls)
        stats = sol.stats()
        viol = _violation(opti, sol)
        rec = {
            "objective": float(sol.value(objective)),
            "iterations": int(stats["iter_count"]),
            "return_status": str(stats["return_status"]),
            "success": bool(stats["success"]),
            "solve_time": dt[0],
            "solve_cpu": dt[1],
            "violation": viol,
        }
        per_start.append(rec)
        # best: converged first, then the objective (maximised or minimised)
        sign = 1.0 if g.maximise is not None else -1.0
        key = (rec["success"] and viol < 1e-6, sign * rec["objective"])
        if best is None or key > best_key:
            best, best_key = (i, sol.value(X).T.copy(), sol.value(C).T.copy(), float(sol.value(effort))), key
    all_starts = build_time + sum(r["solve_time"] for r in per_start)
    i_best, states, controls, eff = best

    repeat_times, repeat_cpu = [], []
    for _ in range(repeats):
        sol, dt = solve(cands[i_best])
        repeat_times.append(dt[0])
        repeat_cpu.append(dt[1])

    replayed = replay_gait(g, states[0], controls)
    rb = per_start[i_best]
    return {
        "name": name,
        "system": g.system,
        "objective_name": g.objective_name,
        "objective": rb["objective"],
        "effort": eff,
        "iterations": rb["iterations"],
        "return_status": rb["return_status"],
        "success": rb["success"],
        "violation": rb["violation"],
        "best_start": i_best,
        "n_starts": len(cands),
        "n_converged": sum(r["success"] for r in per_start),
        "starts": per_start,
        "build_time": build_time,
        "first_call": build_time + per_start[0]["solve_time"],
        "best_first_call": build_time + rb["solve_time"],
        "all_starts": all_starts,
        "repeat_time": statistics.median(repeat_times) if repeat_times else float("nan"),
        "repeat_times": repeat_times,
        "cpu_time": {
            "build": build_cpu,
            "first_call": build_cpu + per_start[0]["solve_cpu"],
            "best_first_call": build_cpu + rb["solve_cpu"],
            "all_starts": build_cpu + sum(r["solve_cpu"] for r in per_start),
            "repeat": statistics.median(repeat_cpu) if repeat_cpu else float("nan"),
        },
        "replay": _boundary_errors(g, replayed, controls),
        "replay_defect": float(np.max(np.abs(replayed - states))),
        "x0": states[0],
        "controls": controls,
        "states": states,
    }


def table(results: list[dict]) -> str:
    """A markdown table of :func:`run_gait` results."""
    cols = [
        ("gait", lambda r: r["name"]),
        ("objective", lambda r: r["objective_name"]),
        ("value", lambda r: f"{r['objective']:.8g}"),
        ("replayed", lambda r: f"{r['replay']['objective']:.8g}"),
        ("iters", lambda r: str(r["iterations"])),
        ("status", lambda r: r["return_status"]),
        ("violation", lambda r: f"{r['violation']:.1e}"),
        ("best start", lambda r: f"{r['best_start']} of {r['n_starts']} ({r['n_converged']} conv.)"),
        ("build [s]", lambda r: f"{r['build_time']:.3f}"),
        ("first call [s]", lambda r: f"{r['first_call']:.3f}"),
        ("best's first [s]", lambda r: f"{r['best_first_call']:.3f}"),
        ("all starts [s]", lambda r: f"{r['all_starts']:.3f}"),
        ("repeat [s]", lambda r: f"{r['repeat_time']:.3f}"),
        (
            "CPU first/all/repeat [s]",
            lambda r: "/".join(f"{r['cpu_time'][k]:.2f}" for k in ("first_call", "all_starts", "repeat")),
        ),
        (
            "replay: period/terminal err",
            lambda r: f"{r['replay']['periodicity_error']:.1e}/{r['replay']['terminal_error']:.1e}",
        ),
    ]
    rows = [[c[0] for c in cols]] + [[f(r) for _, f in cols] for r in results]
    widths = [max(len(row[i]) for row in rows) for i in range(len(cols))]
    fmt = lambda row: "| " + " | ".join(v.ljust(w) for v, w in zip(row, widths)) + " |"  # noqa: E731
    lines = [fmt(rows[0]), "|" + "|".join("-" * (w + 2) for w in widths) + "|"] + [fmt(r) for r in rows[1:]]
    for r in results:
        objs = ", ".join(f"{s['objective']:.6g}{'' if s['success'] else '*'}" for s in r["starts"])
        lines.append(f"\n{r['name']} per start (* = not converged): {objs}")
    return "\n".join(lines)


def _jsonable(x):
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    return x


def write_json(results: list[dict], path: str) -> None:
    with open(path, "w") as fh:
        json.dump(_jsonable(results), fh, indent=1)
        fh.write("\n")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    add_arguments(parser)
    args = parser.parse_args(argv)
    require_casadi(parser)
    run_cli(parser, args, args.gaits_list)


def add_arguments(parser: argparse.ArgumentParser, positional: bool = True) -> None:
    if positional:
        parser.add_argument(
            "gaits_list", nargs="*", metavar="GAIT", help=f"gaits to run (default: all of {', '.join(GAITS)})"
        )
        parser.add_argument("--repeats", type=positive_int, default=3)
        parser.add_argument("--out", default=None, help="write the results as JSON to this file")
    parser.add_argument(
        "--starts",
        type=positive_int,
        default=None,
        help="initial guesses per gait (default: drive 5, turn 25, sideways 5)",
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the random guesses")


def run_cli(parser, args, names) -> list[dict]:
    for t in names:
        if t not in GAITS:
            parser.error(f"unknown gait {t!r}; expected one of {', '.join(GAITS)}")
    results = [run_gait(t, repeats=args.repeats, starts=args.starts, seed=args.seed) for t in names or GAITS]
    print(table(results))
    if args.out:
        write_json(results, args.out)
    return results


if __name__ == "__main__":
    main()
