"""No silent failures: a battery of bad inputs and faults across the public API.

Every case asserts the specific error type and that the message names the argument (or flag), or
the specific result code (:data:`lj.RESULTS`), eagerly, under ``jax.jit`` and under ``jax.vmap``
where that applies. Nothing here can hang, by construction: every rollout has a fixed number of
steps, every ``reference`` solve a small ``max_steps`` (and stops at once on non-finite states
and at the singularity), and the scripts are run with bad flags only, with a stand-in ``jax``
module that fails on import, so a case passes only if the script rejects the flag before
importing JAX (and before any computation).

The runs share a few compiled programs (compiling dominates the cost): the traced cases of
``simulate`` are data fed to one jitted and one vmapped program (snakeboard, RDP, N = 10, every
input traced), the eager ones to one eager program; ``reference`` likewise (3 samples,
``max_steps=REF_MAX``). Run with ``-n 2 --dist loadgroup`` to compile each family once.
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import os
import subprocess
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ldap_jax as lj
from ldap_jax import _compilation_cache as cc
from ldap_jax import _simulate as simulate_module
from ldap_jax import control as lc
from ldap_jax import study

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
R = lj.RESULTS
NAN, INF = float("nan"), float("inf")

# ------------------------------------------------------------------------------- the problem
# the snakeboard and gait, from rest
SB = lj.Snakeboard(m=1.0, l=0.5, I=0.05, J=0.02)
CAR = lj.Car()
PARAMS = (1.0, 0.5, 0.05, 0.02)  # (m, l, I, J)
Z5 = jnp.zeros(5)
AMP = jnp.array([[0.1], [-0.048]])
FREQ = jnp.array([[1.0], [2.0]])
PHASE = jnp.array([[0.0], [-np.pi / 2]])
CTL = lj.Sinusoids(AMP, FREQ, PHASE)
#: a steering torque -0.2 cos(2 t): phi = 1.25 (cos 2t - 1) crosses -pi/2 (cos(phi) = 0) at 0.92 s
SINGULAR_AMP = jnp.array([[0.1], [0.2]])
HUGE_AMP = jnp.array([[1e160], [-0.048]])  # finite, but the energy overflows
SLIDE = jnp.array([0.0, 1.0, 0.0, 0.0, 0.0])  # sideways sliding: violates the constraints
N, TF = 10, 5.0
REF_MAX = 64  # reference: every solve is bounded by 64 steps
REF_TOL = 1e-8
TS = jnp.array([0.0, 0.25, 0.5])
TS_SINGULAR = jnp.array([0.0, 2.5, 5.0])
TS_LONG = jnp.array([0.0, 1e5, 1e6])


def code(result) -> int:
    return int(np.asarray(result._value if isinstance(result, R) else result))


def at(x, i, value):
    """``jnp.asarray(x).at[i].set(value)``, the copy made on the host (op by op, JAX compiles
    each operation)."""
    y = np.array(x)
    y[i] = value
    return jnp.asarray(y, y.dtype)


# ================================================================ simulate: every input at once
# One table, three variants. Each case is data for the same programs: ``eager`` builds the
# system, integrator and controls concretely (bad values raise, naming the argument), ``jit`` and
# ``vmap`` trace every input (a bad value fails that trajectory alone with a result code).
GOOD = dict(params=PARAMS, q0=Z5, qdot0=Z5, amp=AMP, t0=0.0, tf=TF, alpha=0.5)


def _case(**kw):
    return {**GOOD, **kw}


def _params(**kw):
    names = ("m", "l", "I", "J")
    return tuple(kw.get(n, v) for n, v in zip(names, PARAMS))


#: name -> (inputs, eager outcome: an (exception, match) pair or a result, traced result)
SIM_CASES = {
    "valid": (_case(), R.successful, R.successful),
    "m<0": (_case(params=_params(m=-1.0)), (ValueError, "'m'"), R.invalid_input),
    "m=0": (_case(params=_params(m=0.0)), (ValueError, "'m'"), R.invalid_input),
    "l=0": (_case(params=_params(l=0.0)), (ValueError, "'l'"), R.invalid_input),
    "I>ml^2": (_case(params=_params(I=1.0)), (ValueError, "'I'.*I < m l"), R.invalid_input),
    "J=nan": (_case(params=_params(J=NAN)), (ValueError, "'J'"), R.invalid_input),
    "m=inf": (_case(params=_params(m=INF)), (ValueError, "'m'"), R.invalid_input),
    "alpha=1.5": (_case(alpha=1.5), (ValueError, "'alpha'"), R.invalid_input),
    "alpha=-0.5": (_case(alpha=-0.5), (ValueError, "'alpha'"), R.invalid_input),
    "alpha=nan": (_case(alpha=NAN), (ValueError, "'alpha'"), R.invalid_input),
    "t_final<0": (_case(tf=-1.0), (ValueError, "'t_final'"), R.invalid_input),
    "t_final=0": (_case(tf=0.0), (ValueError, "'t_final'"), R.invalid_input),
    "t_final=nan": (_case(tf=NAN), (ValueError, "'t_final'"), R.invalid_input),
    "t_final=inf": (_case(tf=INF), (ValueError, "'t_final'"), R.invalid_input),
    "t0>t_final": (_case(t0=10.0), (ValueError, "'t_final' must exceed t0"), R.invalid_input),
    "t0=nan": (_case(t0=NAN), (ValueError, "'t0'"), R.invalid_input),
    "q0 nan": (_case(q0=at(Z5, 0, NAN)), (ValueError, "'q0' must be finite"), R.invalid_input),
    # the issue: theta = inf was blamed on qdot0
    "theta=inf": (_case(q0=at(Z5, 2, INF)), (ValueError, "'q0' must be finite"), R.invalid_input),
    "qdot0 nan": (_case(qdot0=at(Z5, 3, NAN)), (ValueError, "'qdot0' must be finite"), R.invalid_input),
    "qdot0 sliding": (_case(qdot0=SLIDE), (ValueError, "'qdot0' violates the constraints"), R.invalid_input),
    "amplitude nan": (
        _case(amp=at(AMP, (0, 0), NAN)),
        (ValueError, "'controls' must be finite.*amplitude"),
        R.invalid_input,
    ),
    "amplitude inf": (
        _case(amp=at(AMP, (1, 0), INF)),
        (ValueError, "'controls' must be finite.*amplitude"),
        R.invalid_input,
    ),
    # faults of valid inputs: the result says what happened
    "singular": (_case(amp=SINGULAR_AMP), R.singular, R.singular),
    "energy overflow": (_case(amp=HUGE_AMP), R.nonfinite, R.nonfinite),
}


def _run(params, q0, qdot0, amp, t0, tf, alpha):
    """The traced program: every input an argument."""
    m, l, i, j = params
    sb = lj.Snakeboard(m=m, l=l, I=i, J=j)
    traj = lj.simulate(
        sb,
        q0,
        qdot0,
        lj.Sinusoids(amp, FREQ, PHASE),
        t0=t0,
        t_final=tf,
        n_steps=N,
        integrator=lj.RDP(alpha=alpha),
    )
    finite = (
        jnp.all(jnp.isfinite(traj.q)) & jnp.all(jnp.isfinite(traj.energy)) & jnp.all(jnp.isfinite(traj.work))
    )
    return dict(
        result=traj.result._value,
        failure_index=traj.failure_index,
        finite=finite,
        all_nan=jnp.all(jnp.isnan(traj.q)),
        q_final=traj.q[-1],
    )


def _arrays(case):
    return dict(
        params=tuple(jnp.asarray(p, float) for p in case["params"]),
        q0=jnp.asarray(case["q0"], float),
        qdot0=jnp.asarray(case["qdot0"], float),
        amp=jnp.asarray(case["amp"], float),
        t0=jnp.asarray(case["t0"], float),
        tf=jnp.asarray(case["tf"], float),
        alpha=jnp.asarray(case["alpha"], float),
    )


SIM_JIT = jax.jit(_run)
SIM_VMAP = jax.jit(jax.vmap(_run))


@functools.cache
def _solo_good():
    return jax.tree_util.tree_map(np.asarray, SIM_JIT(**_arrays(GOOD)))


def _check_traced(out, expected, solo=None):
    assert code(out["result"]) == code(expected), int(out["result"])
    if expected == R.successful:
        assert bool(out["finite"]) and int(out["failure_index"]) == N
    elif expected == R.invalid_input:
        # reported for this trajectory, every node NaN, failing at node 0
        assert bool(out["all_nan"]) and int(out["failure_index"]) == 0
    else:
        assert not bool(out["finite"]) and 0 <= int(out["failure_index"]) < N


@pytest.mark.xdist_group("faults_simulate_eager")
@pytest.mark.parametrize("name", list(SIM_CASES))
def test_simulate_eager(name):
    case, eager, _ = SIM_CASES[name]
    if isinstance(eager, tuple):
        exc, match = eager
        with pytest.raises(exc, match=match):
            sb = lj.Snakeboard(*case["params"])
            lj.simulate(
                sb,
                case["q0"],
                case["qdot0"],
                lj.Sinusoids(case["amp"], FREQ, PHASE),
                t0=case["t0"],
                t_final=case["tf"],
                n_steps=N,
                integrator=lj.RDP(alpha=case["alpha"]),
            )
    else:
        traj = lj.simulate(
            SB, case["q0"], case["qdot0"], lj.Sinusoids(case["amp"], FREQ, PHASE), t_final=TF, n_steps=N
        )
        assert traj.result == eager, R[traj.result]
        q, energy = np.asarray(traj.q), np.asarray(traj.energy)
        if eager == R.successful:
            assert bool(np.all(np.isfinite(q))) and bool(np.all(np.isfinite(energy)))
        else:
            # NaN from the first failed node on; every returned diagnostic is finite before it
            k = int(traj.failure_index)
            assert bool(np.all(np.isnan(q[k + 1 :])))
            assert bool(np.all(np.isfinite(energy[: k + 1])))


@pytest.mark.xdist_group("faults_simulate_traced")
@pytest.mark.parametrize("name", list(SIM_CASES))
def test_simulate_jit(name):
    case, _, expected = SIM_CASES[name]
    _check_traced(SIM_JIT(**_arrays(case)), expected)


@pytest.mark.xdist_group("faults_simulate_traced")
@pytest.mark.parametrize("name", [n for n in SIM_CASES if n != "valid"])
def test_simulate_vmap_fails_the_bad_member_alone(name):
    """A batch [good, bad]: the bad member gets its own result; the good one is untouched
    (identical to a solo run), and nothing raises for the whole batch."""
    case, _, expected = SIM_CASES[name]
    batch = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), _arrays(GOOD), _arrays(case))
    out = jax.tree_util.tree_map(np.asarray, SIM_VMAP(**batch))
    first, second = (jax.tree_util.tree_map(lambda x: x[i], out) for i in (0, 1))
    _check_traced(second, expected)
    _check_traced(first, R.successful)
    np.testing.assert_allclose(first["q_final"], _solo_good()["q_final"], rtol=1e-12, atol=1e-14)


# --------------------------------------------------- simulate inside the user's jit (issue 1, 7)
@pytest.mark.xdist_group("faults_simulate_closure")
def test_jit_over_closed_over_valid_inputs():
    """The issue's case 1: closed-over (concrete) system, state and controls, traced t_final and
    alpha; the concrete inputs are checked at trace time, the traced ones in the run."""
    f = jax.jit(
        lambda tf, a: (
            lj.simulate(SB, Z5, Z5, CTL, t_final=tf, n_steps=N, integrator=lj.RDP(alpha=a)).result._value
        )
    )
    assert code(f(5.0, 0.5)) == code(R.successful)
    assert code(f(-1.0, 0.5)) == code(R.invalid_input)
    assert code(f(5.0, 1.5)) == code(R.invalid_input)
    g = eqx.filter_jit(lambda tf: lj.simulate(SB, Z5, Z5, CTL, t_final=tf, n_steps=N).result._value)
    assert code(g(jnp.asarray(5.0))) == code(R.successful)


CLOSED_OVER_BAD = {
    # concrete inputs closed over by the user's jit are checked at trace time, by name
    "qdot0 sliding": (dict(qdot0=SLIDE), ValueError, "'qdot0' violates"),
    "q0 nan": (dict(q0=at(Z5, 1, NAN)), ValueError, "'q0' must be finite"),
    "controls nan": (
        dict(controls=lj.Sinusoids(at(AMP, (0, 0), NAN), FREQ, PHASE)),
        ValueError,
        "'controls'",
    ),
    "t0 inf": (dict(t0=INF), ValueError, "'t0'"),
}


@pytest.mark.parametrize("name", list(CLOSED_OVER_BAD))
def test_jit_checks_closed_over_values_at_trace_time(name):
    kw, exc, match = CLOSED_OVER_BAD[name]
    args = dict(q0=Z5, qdot0=Z5, controls=CTL, t0=0.0) | kw
    with pytest.raises(exc, match=match):
        jax.jit(
            lambda tf: (
                lj.simulate(
                    SB, args["q0"], args["qdot0"], args["controls"], t0=args["t0"], t_final=tf, n_steps=N
                ).q
            )
        )(5.0)


# ---------------------------------------------------------------- simulate: arguments, eagerly
def _simulate(**kw):
    args = dict(system=SB, q0=Z5, qdot0=Z5, controls=CTL, t_final=TF, n_steps=N) | kw
    system, q0, qdot0, controls = (args.pop(k) for k in ("system", "q0", "qdot0", "controls"))
    return lj.simulate(system, q0, qdot0, controls, **args)


SIM_RAISES = {
    "system": (dict(system="snakeboard"), TypeError, "'system'"),
    "integrator": (dict(integrator="rdp"), TypeError, "'integrator'"),
    "controls function of t": (
        dict(controls=lambda t: jnp.zeros(2)),
        TypeError,
        "'controls'.*f\\(t, q, qdot\\)",
    ),
    "controls not callable": (dict(controls=np.zeros(2)), TypeError, "'controls'"),
    "controls channels": (dict(controls=lj.Constant(jnp.zeros(3))), ValueError, "'controls'"),
    # a batch of controls passed without jax.vmap: a broadcasting error deep inside before
    "controls batched": (
        dict(controls=lj.Constant(jnp.zeros((2, 2)))),
        ValueError,
        "'controls' gives values of shape \\(2, 2\\).*jax.vmap",
    ),
    "policy output shape": (
        dict(controls=lj.Policy(lambda t, q, qd: jnp.zeros(3), 2)),
        ValueError,
        "'controls'",
    ),
    "policy output nan": (
        dict(controls=lj.Policy(lambda t, q, qd: jnp.full(2, jnp.nan), 2)),
        ValueError,
        "'controls' must be finite.*policy",
    ),
    "policy gain columns": (dict(controls=lj.LinearPolicy(CTL, jnp.zeros((2, 4)))), ValueError, "'controls'"),
    "q0 shape": (dict(q0=jnp.zeros(4)), ValueError, "'q0'.*shape"),
    "q0 string": (dict(q0="zeros"), TypeError, "'q0'"),
    "q0 ragged": (dict(q0=[0.0, [1.0, 2.0]]), TypeError, "'q0'"),
    "q0 None": (dict(q0=None), TypeError, "'q0'"),
    "q0 float16": (dict(q0=jnp.zeros(5, jnp.float16)), ValueError, "'q0'.*float32 or float64"),
    "qdot0 bfloat16": (dict(qdot0=jnp.zeros(5, jnp.bfloat16)), ValueError, "'qdot0'.*float32 or float64"),
    "qdot0 complex": (dict(qdot0=jnp.zeros(5, jnp.complex64)), ValueError, "'qdot0'"),
    "qdot0 shape": (dict(qdot0=jnp.zeros((5, 1))), ValueError, "'qdot0'.*shape"),
    "n_steps 0": (dict(n_steps=0), ValueError, "'n_steps'"),
    "n_steps -3": (dict(n_steps=-3), ValueError, "'n_steps'"),
    "n_steps 2.5": (dict(n_steps=2.5), TypeError, "'n_steps'"),
    "n_steps str": (dict(n_steps="10"), TypeError, "'n_steps'"),
    "n_steps bool": (dict(n_steps=True), TypeError, "'n_steps'"),
    "t_final str": (dict(t_final="5"), TypeError, "'t_final'"),
    "t_final None": (dict(t_final=None), TypeError, "'t_final'"),
    "t_final vector": (dict(t_final=jnp.array([1.0, 2.0])), ValueError, "'t_final'"),
    "t0 str": (dict(t0="0"), TypeError, "'t0'"),
    "save name": (dict(save="some"), ValueError, "'save'"),
    "save stride": (dict(save=3), ValueError, "'save'"),
    "save 0": (dict(save=0), ValueError, "'save'"),
    "save unsorted": (dict(save=[5, 2]), ValueError, "'save'"),
    "save beyond": (dict(save=[N + 1]), ValueError, "'save'"),
    "checkpoint name": (dict(checkpoint="x"), ValueError, "'checkpoint'"),
    "checkpoint <0": (dict(checkpoint=-2), ValueError, "'checkpoint'"),
    "divergence <0": (dict(divergence=-1.0), ValueError, "'divergence'"),
    "divergence 0": (dict(divergence=0.0), ValueError, "'divergence'"),
    "divergence nan": (dict(divergence=NAN), ValueError, "'divergence'"),
    "divergence str": (dict(divergence="big"), TypeError, "'divergence'"),
    "divergence bool": (dict(divergence=True), TypeError, "'divergence'"),
    "sampled controls inf": (
        dict(controls=lj.Sampled(at(np.zeros((3, 2)), (1, 0), INF), t_final=TF)),
        ValueError,
        "'controls'.*values",
    ),
}


@pytest.mark.parametrize("name", list(SIM_RAISES))
def test_simulate_arguments(name):
    kw, exc, match = SIM_RAISES[name]
    with pytest.raises(exc, match=match):
        _simulate(**kw)


@pytest.mark.xdist_group("faults_simulate_eager")
def test_simulate_accepts_python_lists():
    """A weak case of the issue: Python lists for the state (a JAX-internal TypeError before)."""
    traj = _simulate(q0=[0.0] * 5, qdot0=[0, 0, 0, 0, 0])
    ref = _simulate()
    assert traj.result == R.successful
    np.testing.assert_array_equal(np.asarray(traj.q), np.asarray(ref.q))


# ================================================================== systems, integrators, controls
LAG = lambda r, u, xi: 0.5 * (xi @ xi + u @ u)  # noqa: E731
CONN = lambda r: jnp.zeros((3, 1))  # noqa: E731

CONSTRUCTOR_RAISES = {
    # physical parameters: the message names the parameter
    "Car m str": (lambda: lj.Car(m="heavy"), TypeError, "physical parameter 'm'"),
    "Car m None": (lambda: lj.Car(m=None), TypeError, "'m'"),
    "Car rho complex": (lambda: lj.Car(rho=1 + 2j), TypeError, "'rho'"),
    "Snakeboard I str": (lambda: lj.Snakeboard(I="light"), TypeError, "'I'"),
    "Car m<0": (lambda: lj.Car(m=-1.0), ValueError, "'m'"),
    "Car rho=0": (lambda: lj.Car(rho=0.0), ValueError, "'rho'"),
    "Car l=inf": (lambda: lj.Car(l=INF), ValueError, "'l'"),
    "Car K=nan": (lambda: lj.Car(K=NAN), ValueError, "'K'"),
    "Snakeboard J<0": (lambda: lj.Snakeboard(J=-0.02), ValueError, "'J'"),
    # integrators
    "RDP alpha>1": (lambda: lj.RDP(alpha=1.5), ValueError, "'alpha'"),
    "RDP alpha<0": (lambda: lj.RDP(alpha=-0.1), ValueError, "'alpha'"),
    # order 1 is what alpha != 1/2 gives: asked for at alpha = 1/2 it ran the order-2 step
    "RDP order 1 at alpha 1/2": (lambda: lj.RDP(order=1), ValueError, "'order' must be 2, 4, 6 or 8"),
    # the maps act on one element: out-of-range indices were clamped by JAX, the value returned
    "lie.exp shape": (lambda: lj.lie.exp(jnp.zeros(2)), ValueError, "lie.exp: 'v' must have shape \\(3,\\)"),
    "lie.compose shape": (
        lambda: lj.lie.compose(jnp.zeros(4), jnp.zeros(3)),
        ValueError,
        "lie.compose: 'g1'",
    ),
    "lie.vee shape": (lambda: lj.lie.vee(jnp.zeros(3)), ValueError, "lie.vee: 'xi_hat'"),
    # any other string meant the Cayley map
    "lie.retract name": (lambda: lj.lie.retract(jnp.zeros(3), "expo"), ValueError, "'retraction'"),
    "lie.dtau_inv name": (lambda: lj.lie.dtau_inv(jnp.zeros(3), "EXP"), ValueError, "'retraction'"),
    "lie.dtau_inv order 1.5": (lambda: lj.lie.dtau_inv(jnp.zeros(3), "exp", 1.5), ValueError, "'order'"),
    "lie.dtau_inv order True": (lambda: lj.lie.dtau_inv(jnp.zeros(3), "exp", True), ValueError, "'order'"),
    "GNI alpha nan": (lambda: lj.GNI(alpha=NAN), ValueError, "'alpha'"),
    # controls
    "Sinusoids 1-d": (
        lambda: lj.Sinusoids(jnp.zeros(2), jnp.zeros(2), jnp.zeros(2)),
        ValueError,
        "'amplitude'",
    ),
    "Sinusoids shapes": (lambda: lj.Sinusoids(jnp.zeros((2, 2)), FREQ, PHASE), ValueError, "shapes differ"),
    "Sinusoids str": (lambda: lj.Sinusoids("big", FREQ, PHASE), TypeError, "'amplitude'"),
    "Sinusoids complex": (
        lambda: lj.Sinusoids(AMP, FREQ, PHASE.astype(jnp.complex128)),
        TypeError,
        "'phase'",
    ),
    "Sampled one row": (lambda: lj.Sampled(jnp.zeros((1, 2)), t_final=1.0), ValueError, "'values'"),
    "Sampled t_final=t0": (lambda: lj.Sampled(jnp.zeros((3, 2)), t_final=0.0), ValueError, "'t_final'"),
    "Sampled t_final<t0": (
        lambda: lj.Sampled(jnp.zeros((3, 2)), t_final=1.0, t0=2.0),
        ValueError,
        "'t_final'",
    ),
    "Sampled t_final nan": (lambda: lj.Sampled(jnp.zeros((3, 2)), t_final=NAN), ValueError, "'t_final'"),
    "Sampled t_final inf": (lambda: lj.Sampled(jnp.zeros((3, 2)), t_final=INF), ValueError, "'t_final'"),
    "Constant scalar": (lambda: lj.Constant(0.0), ValueError, "'values'"),
    "Policy fn": (lambda: lj.Policy(3.0, 2), TypeError, "'fn'"),
    "Policy n_channels<0": (lambda: lj.Policy(lambda t, q, qd: q[:2], -1), ValueError, "'n_channels'"),
    "Policy n_channels float": (lambda: lj.Policy(lambda t, q, qd: q[:2], 1.5), TypeError, "'n_channels'"),
    "LinearPolicy feedforward": (
        lambda: lj.LinearPolicy("ctl", jnp.zeros((2, 10))),
        TypeError,
        "'feedforward'",
    ),
    "LinearPolicy gain": (lambda: lj.LinearPolicy(CTL, jnp.zeros((3, 10))), ValueError, "'gain'"),
    "LinearPolicy times": (lambda: lj.LinearPolicy(CTL, jnp.zeros((2, 10)), times=TS), ValueError, "'times'"),
    # System: the message names the argument, or the function that misbehaves
    "System n_shape<0": (lambda: lj.System(-1, LAG, CONN), ValueError, "'n_shape'"),
    "System n_shape float": (lambda: lj.System(1.5, LAG, CONN), TypeError, "'n_shape'"),
    "System lagrangian": (lambda: lj.System(1, 3.0, CONN), TypeError, "'lagrangian'"),
    "System connection": (lambda: lj.System(1, LAG, "A"), TypeError, "'connection'"),
    "System symmetry_basis": (
        lambda: lj.System(1, LAG, CONN, symmetry_basis="e"),
        TypeError,
        "'symmetry_basis'",
    ),
    "System lagrangian vector": (lambda: lj.System(1, lambda r, u, xi: xi, CONN), ValueError, "lagrangian"),
    "System lagrangian arity": (lambda: lj.System(1, lambda r, u: u @ u, CONN), TypeError, "lagrangian"),
    "System connection shape": (
        lambda: lj.System(1, LAG, lambda r: jnp.zeros((3, 2))),
        ValueError,
        "connection",
    ),
    "System symmetry shape": (
        lambda: lj.System(1, LAG, CONN, lambda r: jnp.zeros((2, 1))),
        ValueError,
        "symmetry_basis",
    ),
    "System constraints shape": (
        lambda: lj.System(1, LAG, CONN, None, lambda r: jnp.zeros((3, 3))),
        ValueError,
        "constraints",
    ),
    "System singularity": (
        lambda: lj.System(1, LAG, CONN, singularity=lambda r: r),
        ValueError,
        "singularity",
    ),
    "System kinematic": (lambda: lj.System(1, LAG, CONN, kinematic=(True, False)), ValueError, "'kinematic'"),
    "System shape_names": (
        lambda: lj.System(1, LAG, CONN, shape_names=("a", "b")),
        ValueError,
        "'shape_names'",
    ),
    "sleigh m<0": (lambda: lj.chaplygin_sleigh(m=-1.0), ValueError, "'m'"),
    "sleigh a str": (lambda: lj.chaplygin_sleigh(a="far"), TypeError, "'a'"),
    "sleigh I inf": (lambda: lj.chaplygin_sleigh(I=INF), ValueError, "'I'"),
    "racer d1=d2": (lambda: lj.roller_racer(d1=0.4, d2=0.4), ValueError, "'d1'"),
    "racer k=0": (lambda: lj.roller_racer(k=0.0), ValueError, "'k'"),
}


@pytest.mark.parametrize("name", list(CONSTRUCTOR_RAISES))
def test_constructors(name):
    make, exc, match = CONSTRUCTOR_RAISES[name]
    with pytest.raises(exc, match=match):
        make()


def test_system_without_full_view_under_dla():
    """A System without ``constraints`` cannot run DLA: the error names the missing argument at
    trace time (before compiling)."""
    sleigh = lj.System(
        0,
        lambda r, u, xi: 0.5 * (xi @ xi),
        lambda r: jnp.zeros((3, 0)),
        lambda r: jnp.eye(3, 2),
    )
    with pytest.raises(ValueError, match="constraints"):
        lj.simulate(sleigh, jnp.zeros(3), jnp.zeros(3), None, t_final=1.0, n_steps=N, integrator=lj.DLA())


# ====================================================================================== reference
def _reference(**kw):
    args = (
        dict(system=SB, q0=Z5, qdot0=Z5, controls=CTL, ts=TS, rtol=REF_TOL, atol=REF_TOL, max_steps=REF_MAX)
        | kw
    )
    system, q0, qdot0, controls, ts = (args.pop(k) for k in ("system", "q0", "qdot0", "controls", "ts"))
    return lj.reference(system, q0, qdot0, controls, ts, **args)


REF_RAISES = {
    "system": (dict(system="snakeboard"), TypeError, "'system'"),
    "controls policy": (dict(controls=lj.Policy(lambda t, q, qd: q[:2], 2)), TypeError, "'controls'"),
    "controls channels": (dict(controls=lj.Constant(jnp.zeros(3))), ValueError, "'controls'"),
    # a batch of controls passed without jax.vmap: a broadcasting error deep inside before
    "controls batched": (
        dict(controls=lj.Constant(jnp.zeros((2, 2)))),
        ValueError,
        "'controls' gives values of shape \\(2, 2\\).*jax.vmap",
    ),
    "controls nan": (
        dict(controls=lj.Sinusoids(at(AMP, (0, 0), NAN), FREQ, PHASE)),
        ValueError,
        "'controls'",
    ),
    "controls inf": (
        dict(controls=lj.Sinusoids(AMP, at(FREQ, (1, 0), INF), PHASE)),
        ValueError,
        "'controls'.*frequency",
    ),
    "q0 shape": (dict(q0=jnp.zeros(4)), ValueError, "'q0'"),
    "q0 string": (dict(q0="zeros"), TypeError, "'q0'"),
    "q0 float16": (dict(q0=jnp.zeros(5, jnp.float16)), ValueError, "'q0'"),
    "q0 nan": (dict(q0=at(Z5, 0, NAN)), ValueError, "'q0' must be finite"),
    "theta inf": (dict(q0=at(Z5, 2, INF)), ValueError, "'q0' must be finite"),
    "qdot0 nan": (dict(qdot0=at(Z5, 4, NAN)), ValueError, "'qdot0' must be finite"),
    # consistent with simulate: rejected, not silently projected
    "qdot0 sliding": (dict(qdot0=SLIDE), ValueError, "'qdot0' violates the constraints"),
    "ts 2-d": (dict(ts=jnp.zeros((2, 2))), ValueError, "'ts'"),
    "ts empty": (dict(ts=jnp.zeros(0)), ValueError, "'ts'"),
    "ts decreasing": (dict(ts=[0.0, 2.0, 1.0]), ValueError, "'ts' must be non-decreasing"),
    "ts before t0": (dict(ts=[0.5, 1.0], t0=1.0), ValueError, "'ts' must start"),
    "ts nan": (dict(ts=[0.0, NAN, 5.0]), ValueError, "'ts' must be finite"),
    "ts inf": (dict(ts=[0.0, INF]), ValueError, "'ts' must be finite"),
    "ts string": (dict(ts="0 to 5"), TypeError, "'ts'"),
    "ts complex": (dict(ts=jnp.array([0.0, 1.0 + 1j])), TypeError, "'ts'"),
    "t0 nan": (dict(t0=NAN), ValueError, "'t0'"),
    "t0 string": (dict(t0="0"), TypeError, "'t0'"),
    "rtol 0": (dict(rtol=0.0), ValueError, "'rtol'"),
    "rtol -1": (dict(rtol=-1.0), ValueError, "'rtol'"),
    "rtol nan": (dict(rtol=NAN), ValueError, "'rtol'"),
    "rtol inf": (dict(rtol=INF), ValueError, "'rtol'"),
    "rtol string": (dict(rtol="tight"), TypeError, "'rtol'"),
    "rtol bool": (dict(rtol=True), TypeError, "'rtol'"),
    "atol 0": (dict(atol=0.0), ValueError, "'atol'"),
    "atol -1e-9": (dict(atol=-1e-9), ValueError, "'atol'"),
    "max_steps 0": (dict(max_steps=0), ValueError, "'max_steps'"),
    "max_steps float": (dict(max_steps=2.5), TypeError, "'max_steps'"),
    "solver": (dict(solver="dopri8"), TypeError, "'solver'"),
}


@pytest.mark.parametrize("name", list(REF_RAISES))
def test_reference_arguments(name):
    kw, exc, match = REF_RAISES[name]
    with pytest.raises(exc, match=match):
        _reference(**kw)


def _ref_run(q0, qdot0, amp, ts):
    sol = lj.reference(
        SB, q0, qdot0, lj.Sinusoids(amp, FREQ, PHASE), ts, rtol=REF_TOL, atol=REF_TOL, max_steps=REF_MAX
    )
    return dict(
        result=sol.result._value,
        num_steps=sol.num_steps,
        finite=jnp.all(jnp.isfinite(sol.q)) & jnp.all(jnp.isfinite(sol.qdot)),
        all_nan=jnp.all(jnp.isnan(sol.q)),
        q_final=sol.q[-1],
    )


REF_JIT = jax.jit(_ref_run)
REF_VMAP = jax.jit(jax.vmap(_ref_run))
REF_GOOD = dict(q0=Z5, qdot0=Z5, amp=AMP, ts=TS)

#: traced inputs -> result. Every case is bounded: invalid inputs integrate nothing (num_steps 0),
#: non-finite states and the singularity stop the solve at once, and max_steps caps the rest.
REF_CASES = {
    "valid": (REF_GOOD, R.successful),
    "q0 nan": (REF_GOOD | dict(q0=at(Z5, 0, NAN)), R.invalid_input),
    "theta inf": (REF_GOOD | dict(q0=at(Z5, 2, INF)), R.invalid_input),
    "qdot0 nan": (REF_GOOD | dict(qdot0=at(Z5, 3, NAN)), R.invalid_input),
    "qdot0 sliding": (REF_GOOD | dict(qdot0=SLIDE), R.invalid_input),
    "ts nan": (REF_GOOD | dict(ts=jnp.array([0.0, NAN, 0.5])), R.invalid_input),
    "ts inf": (REF_GOOD | dict(ts=jnp.array([0.0, 0.25, INF])), R.invalid_input),
    "ts decreasing": (REF_GOOD | dict(ts=jnp.array([0.5, 0.25, 0.0])), R.invalid_input),
    "ts before t0": (REF_GOOD | dict(ts=jnp.array([-1.0, 0.0, 0.5])), R.invalid_input),
    "amplitude nan": (REF_GOOD | dict(amp=at(AMP, (1, 0), NAN)), R.invalid_input),
    "singular": (REF_GOOD | dict(amp=SINGULAR_AMP, ts=TS_SINGULAR), R.singular),
    "max_steps": (REF_GOOD | dict(ts=TS_LONG), R.max_steps_reached),
}


def _check_ref(out, expected):
    assert code(out["result"]) == code(expected), int(out["result"])
    assert int(out["num_steps"]) <= REF_MAX
    if expected == R.successful:
        assert bool(out["finite"])
    elif expected == R.invalid_input:
        assert bool(out["all_nan"]) and int(out["num_steps"]) == 0
    else:  # the samples the solve did not reach are NaN, not inf
        assert not bool(out["finite"]) and np.all(np.isnan(out["q_final"]))


@pytest.mark.xdist_group("faults_reference_traced")
@pytest.mark.parametrize("name", list(REF_CASES))
def test_reference_jit(name):
    inputs, expected = REF_CASES[name]
    _check_ref(jax.tree_util.tree_map(np.asarray, REF_JIT(**inputs)), expected)


@pytest.mark.xdist_group("faults_reference_traced")
@pytest.mark.parametrize("name", [n for n in REF_CASES if n != "valid"])
def test_reference_vmap_bad_member_costs_nothing(name):
    """A batch [good, bad]: the bad member gets its result; the good one is the solo solution, and
    an invalid member takes no step (so the batch does not pay for it)."""
    inputs, expected = REF_CASES[name]
    batch = jax.tree_util.tree_map(
        lambda a, b: jnp.stack([jnp.asarray(a, float), jnp.asarray(b, float)]), REF_GOOD, inputs
    )
    out = jax.tree_util.tree_map(np.asarray, REF_VMAP(**batch))
    first, second = (jax.tree_util.tree_map(lambda x: x[i], out) for i in (0, 1))
    _check_ref(second, expected)
    _check_ref(first, R.successful)
    solo = jax.tree_util.tree_map(np.asarray, REF_JIT(**REF_GOOD))
    np.testing.assert_allclose(first["q_final"], solo["q_final"], rtol=1e-12, atol=1e-14)


@pytest.mark.xdist_group("faults_reference_eager")
def test_reference_eager_runs():
    """Eager solves: Python lists are accepted; the singularity is reported as by simulate (the
    same maneuver gives RESULTS.singular in both); an exhausted budget fails fast and clearly."""
    ok = _reference(q0=[0.0] * 5, qdot0=[0.0] * 5, ts=[0.0, 0.25, 0.5])
    assert ok.result == R.successful and bool(np.all(np.isfinite(np.asarray(ok.q))))
    singular_ctl = lj.Sinusoids(SINGULAR_AMP, FREQ, PHASE)
    sol = _reference(controls=singular_ctl, ts=TS_SINGULAR)
    traj = lj.simulate(SB, Z5, Z5, singular_ctl, t_final=TF, n_steps=N)
    assert sol.result == R.singular and traj.result == R.singular
    assert int(sol.num_steps) <= REF_MAX and bool(np.all(np.isnan(np.asarray(sol.q)[-1])))
    long = _reference(ts=TS_LONG)
    assert long.result == R.max_steps_reached and int(long.num_steps) == REF_MAX
    assert bool(np.all(np.isnan(np.asarray(long.q)[-1])))
    assert "max_steps" in R[long.result]


# ============================================================== faults of valid inputs (4, 5, 6)
def _loss(amp):
    traj = lj.simulate(SB, Z5, Z5, lj.Sinusoids(amp, FREQ, PHASE), t_final=TF, n_steps=N)
    return jnp.sum(traj.q[-1] ** 2)


@pytest.mark.xdist_group("faults_simulate_eager")
def test_gradient_through_a_failed_trajectory_is_nan():
    """The issue's case 4: a loss through a run that hits cos(phi) = 0 gave (nan, zeros), and a
    failed member of a batch-sum loss silently contributed nothing. Now its gradient is NaN,
    while a good member's gradient stays finite."""
    amps = jnp.stack([AMP, SINGULAR_AMP])
    value, grad = jax.jit(jax.value_and_grad(lambda a: jnp.sum(jax.vmap(_loss)(a))))(amps)
    assert np.isnan(float(value))
    grad = np.asarray(grad)
    assert np.all(np.isfinite(grad[0])) and np.any(grad[0] != 0)
    assert np.all(np.isnan(grad[1]))


@pytest.mark.xdist_group("faults_divergence")
def test_divergence_is_not_success():
    """The issue's case 5: RK4 at h = 1e5 s ended at theta = -8e15 with result 0. Now it fails
    with RESULTS.diverged (energy balance) and NaN; the criterion is the user's to set."""
    cctl = lj.Sinusoids([[0.2], [0.3]], [[1.0], [0.7]], [[0.0], [0.0]])
    traj = lj.simulate(CAR, Z5, Z5, cctl, t_final=1e6, n_steps=N, integrator=lj.RK4())
    assert traj.result == R.diverged and int(traj.failure_index) < N
    assert bool(np.all(np.isnan(np.asarray(traj.q)[-1])))
    assert "divergence" in R[traj.result]
    loose = lj.simulate(CAR, Z5, Z5, cctl, t_final=1e6, n_steps=N, integrator=lj.RK4(), divergence=INF)
    assert loose.result == R.successful and float(np.max(np.abs(np.asarray(loose.q)[:, 2]))) > 1e12


# ======================================================= failures that were silent (issue 47)
Q0_SINGULAR = jnp.array([0.0, 0.0, 0.0, 0.0, np.pi / 2])  # cos(phi) = 0: fails at step 0

#: name -> keyword arguments of simulate: each fails at step 0 (a loss reading it must get NaN)
FIRST_STEP = {
    "default": {},
    "rk4 final sqrt": dict(integrator=lj.RK4(), save="final", checkpoint="sqrt"),
    "order 4": dict(integrator=lj.RDP(order=4)),
    "no diagnostics": dict(diagnostics=False, save="final"),
}


def _first_step_loss(amp, tf=TF, m=1.0, q0=Q0_SINGULAR, **kw):
    sb = lj.Snakeboard(m=m, l=0.5, I=0.05, J=0.02)
    traj = lj.simulate(sb, q0, Z5, lj.Sinusoids(amp, FREQ, PHASE), t_final=tf, n_steps=N, **kw)
    return jnp.sum(traj.q[-1] ** 2), traj


@pytest.mark.xdist_group("faults_issue47")
@pytest.mark.parametrize("name", list(FIRST_STEP))
def test_gradient_through_a_first_step_failure_is_nan(name):
    """A run that fails at step 0 froze at q0, which the controls do not move: the gradient was
    an exact 0. Now a loss that reads a failed run gets NaN, eagerly, under jit and for a member
    of a vmapped batch (whose healthy member keeps a finite gradient)."""
    kw = FIRST_STEP[name]
    _, traj = _first_step_loss(AMP, **kw)
    assert traj.result == R.singular and int(traj.failure_index) == 0
    grad = jax.grad(lambda a: _first_step_loss(a, **kw)[0])
    assert np.all(np.isnan(np.asarray(grad(AMP))))
    assert np.all(np.isnan(np.asarray(jax.jit(grad)(AMP))))
    q0s = jnp.stack([Z5, Q0_SINGULAR])
    batch = jax.grad(
        lambda a: jnp.sum(jax.vmap(lambda q: _first_step_loss(a[0] + 0 * a[1], q0=q, **kw)[0])(q0s))
    )
    both = jax.vmap(lambda a, q: jax.grad(lambda aa: _first_step_loss(aa, q0=q, **kw)[0])(a))(
        jnp.stack([AMP, AMP]), q0s
    )
    both = np.asarray(both)
    assert np.all(np.isfinite(both[0])) and np.any(both[0] != 0) and np.all(np.isnan(both[1]))
    assert np.all(np.isnan(np.asarray(batch(jnp.stack([AMP, AMP])))))


def test_a_start_at_the_singularity_moving_away_is_singular():
    """The snakeboard started at |phi| = pi/2 (or within eps^(1/4) of it) with the steering moving
    away: the steps test their ends only, which are clear of it, and every integrator and the
    reference reported success. The start is tested too: singular, eagerly, under jit and vmap."""
    sb = lj.Snakeboard(m=1.0, l=0.5, I=0.05, J=0.02)
    qdot0 = jnp.zeros(5).at[4].set(-0.5)
    for phi0 in (np.pi / 2, np.pi / 2 - 1e-5, -np.pi / 2 + 1e-6):
        q0 = Z5.at[4].set(phi0)
        for integrator in (lj.RDP(), lj.RDP(order=4), lj.RK4()):

            def run(q, integrator=integrator):
                return lj.simulate(sb, q, qdot0, None, t_final=1.0, n_steps=10, integrator=integrator).result

            assert run(q0) == R.singular and jax.jit(run)(q0) == R.singular, (phi0, integrator)
            codes = jax.vmap(run)(jnp.stack([Z5, q0]))
            assert np.asarray(codes._value).tolist() == [code(R.successful), code(R.singular)]
        ref = lj.reference(sb, q0, qdot0, None, jnp.linspace(0.0, 1.0, 3))
        assert ref.result == R.singular, phi0


def test_rk4_stages_past_the_singularity_are_singular():
    """The steering phi(t) = c + b sin(w t + p) peaks 0.02 rad past pi/2 halfway between two steps'
    ends (h = 0.5 s): the ends keep cos(phi) > 0, but RK4 evaluates the equations at its stages
    past the singularity. It reported success; the stages are tested now, as the reference's
    event is (13 of 27 such maneuvers were missed)."""
    sb = lj.Snakeboard(m=1.0, l=0.5, I=0.05, J=0.02)
    w, b, h = 2 * np.pi / 3, 0.3, 0.5
    p = np.pi / 2 - w * 0.5 * h
    ctl = lj.Sinusoids([[0.0], [-2 * 0.02 * b * w**2]], [[1.0], [w]], [[0.0], [p]])
    q0 = Z5.at[4].set(np.pi / 2 + 0.02 - b + b * np.sin(p))
    qdot0 = jnp.zeros(5).at[4].set(b * w * np.cos(p))
    assert lj.reference(sb, q0, qdot0, ctl, jnp.linspace(0.0, 12.0, 25)).result == R.singular
    traj = lj.simulate(sb, q0, qdot0, ctl, t_final=12.0, n_steps=24, integrator=lj.RK4())
    phi = np.asarray(traj.q)[: int(traj.failure_index) + 1, 4]
    assert traj.result == R.singular and np.all(np.cos(phi) > 0)  # every step's end clear of it


@pytest.mark.xdist_group("faults_issue47")
def test_gradient_through_a_first_step_failure_is_nan_for_times_and_parameters():
    """With respect to ``t_final`` (eagerly), and to a traced invalid mass under ``jit(grad)``."""
    g_tf = jax.grad(lambda tf: _first_step_loss(AMP, tf=tf)[0])(TF)
    assert np.isnan(float(g_tf))
    g_m = jax.jit(jax.grad(lambda m: _first_step_loss(AMP, m=m, q0=Z5)[0]))(-1.0)
    assert np.isnan(float(g_m))
    # eagerly the bad mass is known: a clear error naming it (was TracerArrayConversionError)
    with pytest.raises(ValueError, match="'m' must be positive"):
        jax.grad(lambda m: _first_step_loss(AMP, m=m, q0=Z5)[0])(-1.0)


#: per-member offsets of the shared amplitude: member 1 crosses cos(phi) = 0 (SINGULAR_AMP)
DELTAS = jnp.stack([jnp.zeros((2, 1)), SINGULAR_AMP - AMP, jnp.array([[0.05], [0.0]])])


def _masked_member(params, delta, q0, fill, **kw):
    m, amp = params
    sb = lj.Snakeboard(m=m, l=0.5, I=0.05, J=0.02)
    traj = lj.simulate(sb, q0, Z5, lj.Sinusoids(amp + delta, FREQ, PHASE), t_final=TF, n_steps=N, **kw)
    if fill:
        traj = traj.filled()
        q, e = traj.q, traj.energy
    else:
        q, e = jnp.where(traj.failed, 0.0, traj.q), jnp.where(traj.failed, 0.0, traj.energy)
    return jnp.sum(q[-1] ** 2) + jnp.sum(e), traj.failed


@pytest.mark.xdist_group("faults_issue47")
@pytest.mark.parametrize("where", ["step 0", "later"])
@pytest.mark.parametrize("fill", [False, True])
def test_masked_failed_member_leaves_healthy_gradients_exact(where, fill):
    """A batched loss that masks its failed member out (double ``where`` on the outputs, or
    ``Trajectory.filled``): the shared parameters' gradient equals that of the batch without the
    failed member (it was NaN for the whole batch), for a failure at step 0 or later."""
    q0s = jnp.stack([Z5, Q0_SINGULAR if where == "step 0" else Z5, Z5])
    deltas = DELTAS.at[1].set(0.0) if where == "step 0" else DELTAS
    params = (jnp.asarray(1.0), AMP)

    def loss(p, d, q):
        return jnp.sum(jax.vmap(lambda dd, qq: _masked_member(p, dd, qq, fill)[0])(d, q))

    failed = jax.vmap(lambda dd, qq: _masked_member(params, dd, qq, fill)[1])(deltas, q0s)
    assert np.asarray(failed).tolist() == [False, True, False]
    full = jax.jit(jax.grad(loss))(params, deltas, q0s)
    # differentiated outside the user's jit too: the failed state is kept frozen in either order
    outer = jax.grad(jax.jit(loss))(params, deltas, q0s)
    healthy = jax.grad(loss)(params, deltas[::2], q0s[::2])
    for a, o, b in zip(full, outer, healthy):
        assert np.all(np.isfinite(np.asarray(a)))
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(np.asarray(o), np.asarray(b), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("order", [4, 6, 8])
def test_a_composed_step_reports_what_its_substeps_met(order):
    """A composition of the closed-form step tests its state once per composed step and ORs its
    substeps' singularity flags: the steering torque of SINGULAR_AMP crosses cos(phi) = 0 at
    0.92 s, in the composed step [0.5, 1] s (``singular``); HUGE_AMP overflows the state in the
    first step (``nonfinite``, with the energy test off). Eagerly and under ``jit``."""
    integ = lj.RDP(order=order)

    def run(amp):
        traj = lj.simulate(
            SB,
            Z5,
            Z5,
            lj.Sinusoids(amp, FREQ, PHASE),
            t_final=TF,
            n_steps=N,
            integrator=integ,
            diagnostics=False,
        )
        return traj.result, traj.failure_index

    for amp, expected, index in ((SINGULAR_AMP, R.singular, 1), (HUGE_AMP, R.nonfinite, 0)):
        for result, k in (run(amp), jax.jit(run)(amp)):
            assert result == expected and int(k) == index, (order, R[result], int(k))


def test_a_failed_state_is_frozen_only_when_differentiated():
    """The carry update of an explicit step (``_rollout._advance``): the new state as it is in a
    program that is not differentiated; the last good state where ``keep`` is False in one that
    is, in forward and in reverse mode, under ``vmap`` too, with the tangent (and so the cotangent)
    routed the same way."""
    from ldap_jax._rollout import _advance

    keep = jnp.array([True, False, True])
    new = (jnp.array([1.0, NAN, 3.0]), jnp.array([1, 2, 3]))
    old = (jnp.array([-1.0, -2.0, -3.0]), jnp.array([4, 5, 6]))
    out = _advance(keep, new, old)
    assert np.isnan(float(out[0][1])) and np.asarray(out[1]).tolist() == [1, 2, 3]
    frozen = np.array([1.0, -2.0, 3.0])

    def f(x, y):
        return _advance(keep, (x, new[1]), (y, old[1]))[0]

    primal, tangent = jax.jvp(f, (new[0], old[0]), (jnp.ones(3), 2 * jnp.ones(3)))
    np.testing.assert_array_equal(np.asarray(primal), frozen)
    np.testing.assert_array_equal(np.asarray(tangent), [1.0, 2.0, 1.0])
    gx, gy = jax.grad(lambda x, y: jnp.sum(f(x, y) * jnp.array([1.0, 0.0, 1.0])), argnums=(0, 1))(
        new[0], old[0]
    )
    np.testing.assert_array_equal(np.asarray(gx), [1.0, 0.0, 1.0])
    np.testing.assert_array_equal(np.asarray(gy), [0.0, 0.0, 0.0])
    member = jax.vmap(lambda k, a, b: jax.jvp(lambda x: _advance(k, x, b), (a,), (1.0,)))
    primal, tangent = member(keep, new[0], old[0])
    np.testing.assert_array_equal(np.asarray(primal), frozen)
    np.testing.assert_array_equal(np.asarray(tangent), [1.0, 0.0, 1.0])


#: car maneuvers (``study.sample_maneuvers(CAR, 16, 0)``): member 0 ends ``diverged`` with RK4 at
#: h = 6 s (its state finite there, blowing up after), members 1 and 2 stay ``successful``
CAR_MEMBERS = np.array([1, 0, 2])


@pytest.mark.xdist_group("faults_divergence")
@pytest.mark.parametrize("shared", ["mass", "gain"])
@pytest.mark.parametrize("integrator", ["rk4", "rdp"])
def test_a_failed_state_that_runs_on_leaves_shared_gradients_exact(integrator, shared):
    """An explicit step's failed state runs on (no copy of the last good state is kept: 1.12-1.22x
    faster) unless the run is differentiated with respect to a parameter its steps read directly
    (the car's mass), when it stays frozen. Either way the outputs are the same: the result, the
    failure index, the NaN nodes after it, the failed step's residual at the next node and NaN
    after; and a batch that masks its failed member out keeps the gradient of what its members
    share (the car's mass, or a gain on every member's controls, with the mass a constant) equal
    to the healthy members' alone, in either order of ``jit`` and ``grad``."""
    integ = lj.RK4() if integrator == "rk4" else lj.RDP()
    q0, qd0, ctl = jax.tree_util.tree_map(lambda x: x[CAR_MEMBERS], study.sample_maneuvers(CAR, 16, 0))
    # RDP's energy stays bounded at this step: member 0's controls 10x larger make it diverge
    scales = jnp.array([1.0, 1.0 if integrator == "rk4" else 10.0, 1.0])

    def member(x, a, b, c, scale):
        m, gain = (x, 1.0) if shared == "mass" else (1.0, x)
        c = eqx.tree_at(lambda s: s.amplitude, c, c.amplitude * scale * gain)
        traj = lj.simulate(lj.Car(m=m), a, b, c, t_final=600.0, n_steps=100, integrator=integ)
        return jnp.sum(jnp.where(traj.failed, 0.0, traj.q)[-1, :2] ** 2) * 1e-3, traj

    def loss(x, members):
        return jnp.sum(jax.vmap(lambda a, b, c, s: member(x, a, b, c, s)[0])(*members))

    members = (q0, qd0, ctl, scales)
    plain = jax.jit(jax.vmap(lambda a, b, c, s: member(1.0, a, b, c, s)[1]))(*members)

    def positions(x):
        return jax.vmap(lambda a, b, c, s: member(x, a, b, c, s)[1].q)(*members)

    primal = jax.jit(lambda x: jax.jvp(positions, (x,), (1.0,))[0])(1.0)
    failed = np.asarray(plain.failed)
    assert failed.tolist() == [False, True, False], (np.asarray(plain.result._value), failed)
    np.testing.assert_array_equal(np.asarray(plain.q), np.asarray(primal))
    k = int(plain.failure_index[1])
    assert np.all(np.isnan(np.asarray(plain.q[1, k + 1 :])))
    residual = np.asarray(plain.step_residual[1])
    assert np.all(np.isfinite(residual[: k + 2])) and np.all(np.isnan(residual[k + 2 :]))
    healthy = jax.grad(loss)(1.0, jax.tree_util.tree_map(lambda x: x[::2], members))
    for g in (jax.jit(jax.grad(loss))(1.0, members), jax.grad(jax.jit(loss))(1.0, members)):
        assert np.isfinite(float(g))
        np.testing.assert_allclose(float(g), float(healthy), rtol=1e-12)


def test_trajectory_filled_keeps_the_result():
    _, traj = _first_step_loss(AMP)
    filled = traj.filled(-1.0)
    assert filled.result == R.singular and int(filled.failure_index) == 0
    assert np.all(np.asarray(filled.q) == -1.0) and np.all(np.asarray(filled.energy) == -1.0)
    good = lj.simulate(SB, Z5, Z5, CTL, t_final=TF, n_steps=N)
    np.testing.assert_array_equal(np.asarray(good.filled().q), np.asarray(good.q))


@pytest.mark.xdist_group("faults_divergence")
@pytest.mark.parametrize("integrator", ["gni folded", "rk4"])
def test_car_blow_up_at_a_huge_step_is_diverged(integrator):
    """The car at h = 6 s (t_final = 600, N = 100; the motion's periods are a few seconds): the
    scale of the divergence test was ``|E_0| + int |P| dt``, and a blown-up run's absolute work
    grows with it, so runs ending 100x off the true path (positions of 1.8e3 m where the true
    motion stays within 11 m) were ``successful``. Now the scale is capped by the energy the
    controls' impulse can give the car, a value of the inputs: these runs end ``diverged``,
    eagerly, under jit and as members of a batch."""
    integ = lj.GNI(variant="folded") if integrator == "gni folded" else lj.RK4()
    members = [8, 10] if integrator == "gni folded" else [0, 6, 8]
    q0, qd0, ctl = study.sample_maneuvers(CAR, 16, 0)

    def run(a, b, c):
        traj = lj.simulate(CAR, a, b, c, t_final=600.0, n_steps=100, integrator=integ)
        return traj.result._value

    batch = np.asarray(jax.jit(jax.vmap(run))(q0, qd0, ctl))
    for i in members:
        one = jax.tree_util.tree_map(lambda x: x[i], (q0, qd0, ctl))
        assert batch[i] == code(R.diverged)
        assert code(run(*one)) == code(R.diverged) == code(jax.jit(run)(*one))
    # the same maneuvers at a step that resolves them stay successful
    fine = jax.jit(
        jax.vmap(
            lambda a, b, c: (
                lj.simulate(
                    CAR, a, b, c, t_final=600.0, n_steps=6000, save="final", integrator=integ
                ).result._value
            )
        )
    )
    assert np.all(np.asarray(fine(q0, qd0, ctl)) == code(R.successful))


@pytest.mark.xdist_group("faults_issue47")
def test_composition_with_a_traced_alpha_other_than_half_is_invalid():
    """``RDP(order=4, alpha=a)`` composes symmetric steps: eagerly ``a != 1/2`` raises, and a
    traced one was run (order 1.03, ``successful``). Now it is ``invalid_input``."""
    with pytest.raises(ValueError, match="alpha = 1/2"):
        lj.RDP(order=4, alpha=0.3)

    def run(a):
        traj = lj.simulate(SB, Z5, Z5, CTL, t_final=TF, n_steps=N, integrator=lj.RDP(order=4, alpha=a))
        return traj.result._value, jnp.all(jnp.isnan(traj.q))

    res, nan = (np.asarray(x) for x in jax.vmap(run)(jnp.array([0.5, 0.3])))
    assert res.tolist() == [code(R.successful), code(R.invalid_input)] and nan.tolist() == [False, True]
    assert code(jax.jit(run)(0.3)[0]) == code(R.invalid_input)


@pytest.mark.xdist_group("faults_issue47")
def test_discretize_flags_a_traced_nonpositive_step():
    """``lj.discretize`` under ``jit`` took a traced ``h <= 0`` and reported ``successful``."""

    @jax.jit
    def step(h):
        dyn = lj.discretize(CAR, lj.RDP(), h=h)
        x0 = dyn.init(Z5, Z5, jnp.ones(2))
        x1, info = dyn.step_with_info(x0, jnp.ones(2), jnp.ones(2))
        return x1, info.result._value

    x1, res = step(0.1)
    assert code(res) == code(R.successful) and np.all(np.isfinite(np.asarray(x1)))
    for bad in (-0.1, 0.0, NAN):
        x1, res = step(bad)
        assert code(res) == code(R.invalid_input) and np.all(np.isnan(np.asarray(x1)))
    with pytest.raises(ValueError, match="'h'"):
        lj.discretize(CAR, lj.RDP(), h=-0.1)


@pytest.mark.xdist_group("faults_issue47")
def test_save_indices_must_be_integers_and_may_be_jax_arrays():
    with pytest.raises(ValueError, match="'save'.*integers"):
        lj.simulate(SB, Z5, Z5, CTL, t_final=TF, n_steps=N, save=[0.5, 10])
    a = lj.simulate(SB, Z5, Z5, CTL, t_final=TF, n_steps=N, save=jnp.array([0, 5, 10]))
    b = lj.simulate(SB, Z5, Z5, CTL, t_final=TF, n_steps=N, save=np.array([0, 5, 10]))
    np.testing.assert_array_equal(np.asarray(a.q), np.asarray(b.q))
    assert a.q.shape == (3, 5)


def _policy_loss(k):
    pol = lambda t, q, qd: jnp.stack([1.0 - k * qd[3], 0.1 * jnp.cos(t)])  # noqa: E731
    traj = lj.simulate(CAR, Z5, Z5, pol, t_final=2.0, n_steps=20)
    return jnp.sum(traj.q[-1] ** 2)


@pytest.mark.xdist_group("faults_issue47")
def test_plain_function_policy_with_a_captured_gain_under_jit_and_grad():
    """A plain-function policy closing over a gain: ``jit`` over the gain raised
    ``TracerBoolConversionError`` (the initial check took the policy for a constant), ``grad`` a
    leaked tracer. Now both work and agree with the eager values and finite differences."""
    value = float(_policy_loss(0.5))
    assert float(jax.jit(_policy_loss)(0.5)) == pytest.approx(value, rel=1e-12)
    g = float(jax.grad(_policy_loss)(0.5))
    assert float(jax.jit(jax.grad(_policy_loss))(0.5)) == pytest.approx(g, rel=1e-10)
    eps = 1e-6
    fd = (float(_policy_loss(0.5 + eps)) - float(_policy_loss(0.5 - eps))) / (2 * eps)
    assert g == pytest.approx(fd, rel=1e-6) and g != 0


@pytest.mark.xdist_group("faults_issue47")
def test_throw_under_vmap_raises_with_the_failures_message():
    """Documented: under vmap, ``throw=True`` raises when any member fails, with the failure's
    message (it cannot name the member from inside the batched program)."""

    def run(amp):
        return lj.simulate(SB, Z5, Z5, lj.Sinusoids(amp, FREQ, PHASE), t_final=TF, n_steps=N, throw=True).q

    with pytest.raises(Exception, match="singular configuration"):
        jax.vmap(run)(jnp.stack([AMP, SINGULAR_AMP]))
    assert "does not say which one" in " ".join(lj.simulate.__doc__.split())


@pytest.mark.xdist_group("faults_issue47")
def test_forward_mode_through_simulate():
    """The custom VJP that masks failed nodes has no forward mode: simulate sees a forward-mode
    transformation of its inputs and masks them linearly instead. ``jacfwd`` equals ``jacrev``, a
    Hessian compiles, and a step-0 failure gives NaN in forward mode too."""

    def f(a, q0=Z5):
        return _first_step_loss(a, q0=q0)[1].q[-1]

    np.testing.assert_allclose(
        np.asarray(jax.jacfwd(f)(AMP)), np.asarray(jax.jacrev(f)(AMP)), rtol=1e-10, atol=1e-12
    )
    hess = jax.jit(jax.hessian(lambda a: jnp.sum(f(a) ** 2)))(AMP)
    assert hess.shape == (2, 1, 2, 1) and np.all(np.isfinite(np.asarray(hess)))
    assert np.all(np.isnan(np.asarray(jax.jacfwd(lambda a: _first_step_loss(a)[0])(AMP))))


# ===================================================================================== control
PARK = lc.parallel_park(n_steps=N)
GAIT = lc.forward_gait(n_steps=N)
DYN = lj.discretize(CAR, lj.RDP(), h=0.1)


def _make_task(**kw):
    args = (
        dict(
            name="t",
            t_final=1.0,
            n_steps=N,
            q0=np.zeros(5),
            qdot0=np.zeros(5),
            controls=lc.SampledControls(1.0, N, np.ones(2)),
            objective=(lc.Effort(jnp.ones(2)),),
        )
        | kw
    )
    return lc.make_task(args.pop("system", CAR), **args)


def _bounds(**kw):
    b = lc.Bounds.of(CAR)
    return dataclasses.replace(b, **{k: jnp.asarray(v, float) for k, v in kw.items()})


TASK_RAISES = {
    # the shipped tasks name their own argument (the bound they build named 'y' or 'sigma')
    "u_turn width": (lambda: lc.u_turn(width=-1.0), ValueError, "u_turn: 'width'"),
    "parallel_park max_steer": (
        lambda: lc.parallel_park(max_steer=0.0),
        ValueError,
        "parallel_park: 'max_steer'",
    ),
    "system": (lambda: _make_task(system="car"), TypeError, "'system'"),
    "controls": (lambda: _make_task(controls="sampled"), TypeError, "'controls'"),
    "integrator": (lambda: _make_task(integrator="rk4"), TypeError, "'integrator'"),
    "objective": (lambda: _make_task(objective=(3.0,)), TypeError, "'objective'"),
    "constraints": (lambda: _make_task(constraints=({"rest": 1.0},)), TypeError, "'constraints'"),
    "q0 shape": (lambda: _make_task(q0=np.zeros(4)), ValueError, "'q0'"),
    "q0 nan": (lambda: _make_task(q0=np.full(5, NAN)), ValueError, "'q0'"),
    "q0 missing": (lambda: _make_task(q0=None), ValueError, "'q0'"),
    "qdot0 sliding": (lambda: _make_task(qdot0=np.asarray(SLIDE)), ValueError, "'qdot0'"),
    "n_steps 0": (lambda: _make_task(n_steps=0), ValueError, "'n_steps'"),
    "n_steps float": (lambda: _make_task(n_steps=2.5), TypeError, "'n_steps'"),
    "t_final 0": (lambda: _make_task(t_final=0.0), ValueError, "'t_final'"),
    "t_final nan": (lambda: _make_task(t_final=NAN), ValueError, "'t_final'"),
    "t_final str": (lambda: _make_task(t_final="1"), TypeError, "'t_final'"),
    "channels": (
        lambda: _make_task(controls=lc.SampledControls(1.0, N, np.ones(3))),
        ValueError,
        "'controls'",
    ),
    "controls steps": (
        lambda: _make_task(controls=lc.SampledControls(1.0, 2 * N, np.ones(2))),
        ValueError,
        "'controls'",
    ),
    "bounds empty": (
        lambda: _make_task(bounds=_bounds(q_lower=np.ones(5), q_upper=np.zeros(5))),
        ValueError,
        "'bounds'",
    ),
    "bounds shape": (lambda: _make_task(bounds=_bounds(q_lower=np.zeros(3))), ValueError, "bounds.q_lower"),
    "bounds by name": (lambda: lc.Bounds.of(CAR, q={"z": 1.0}), ValueError, "z"),
    "q0 outside": (
        lambda: _make_task(bounds=_bounds(q_lower=np.full(5, 1.0), q_upper=np.full(5, 2.0))),
        ValueError,
        "'q0'",
    ),
    "goal shape": (lambda: _make_task(constraints=(lc.TerminalPose([1.0, 2.0]),)), ValueError, "'goal'"),
    "goal nan": (lambda: _make_task(constraints=(lc.TerminalPose([1.0, NAN, 0.0]),)), ValueError, "'goal'"),
    "goal outside": (
        lambda: _make_task(
            constraints=(lc.TerminalPose([5.0, 0.0, 0.0]),),
            bounds=_bounds(q_lower=np.full(5, -1.0), q_upper=np.full(5, 1.0)),
        ),
        ValueError,
        "'goal'",
    ),
    "initial without periodic": (
        lambda: _make_task(constraints=(lc.InitialRest((0,)),)),
        ValueError,
        "'constraints'",
    ),
    "objective_weight": (lambda: _make_task(objective_weight=-1.0), ValueError, "'objective_weight'"),
    "checkpoint": (lambda: _make_task(checkpoint="often"), ValueError, "'checkpoint'"),
    "gait period": (lambda: lc.drive_gait(period=0.0), ValueError, "'period'"),
    "gait n_steps": (lambda: lc.drive_gait(n_steps=1), ValueError, "'n_steps'"),
    "gait start given": (
        lambda: lc.make_task(
            SB, t_final=1.0, n_steps=N, q0=np.zeros(5), qdot0=np.zeros(5), constraints=(lc.Periodic(),)
        ),
        ValueError,
        "'q0'",
    ),
    "parallel_park t_final": (lambda: lc.parallel_park(t_final=-1.0), ValueError, "'t_final'"),
    "parallel_park n_steps": (lambda: lc.parallel_park(n_steps=0), ValueError, "'n_steps'"),
    "reach goal": (lambda: lc.reach(goal=(1.0, 2.0, NAN)), ValueError, "'goal'"),
    "with_options n_steps": (lambda: PARK.with_options(n_steps=0), ValueError, "'n_steps'"),
    "with_options integrator": (lambda: PARK.with_options(integrator="rk4"), TypeError, "'integrator'"),
    "with_options goal": (lambda: PARK.with_options(goal=[1.0, 2.0]), ValueError, "'goal'"),
    "with_options system": (lambda: PARK.with_options(system=SB), TypeError, "'system'"),
    # the interior-point solver holds bounds strictly: a start on a bound; a gait's fixed start
    # (x = y = theta = 0, the cyclic coordinates at 0) outside its bounds; controls that do not
    # start at the task's t = 0 (the solver's node k is at k h)
    "q0 on a bound": (
        lambda: PARK.with_options(bounds=lc.Bounds.of(CAR, q={"sigma": 1.0, "x": (0.0, 1.0)})),
        ValueError,
        "'q0'.*on or outside the bounds",
    ),
    "gait bounds exclude the start": (
        lambda: lc.drive_gait(n_steps=N).with_options(
            bounds=lc.Bounds.of(SB, q={"phi": 1.0, "x": (1.0, 2.0)})
        ),
        ValueError,
        "'bounds'.*fixed start.*'x'",
    ),
    "gait bounds exclude a cyclic start": (
        lambda: lc.drive_gait(n_steps=N).with_options(
            bounds=lc.Bounds.of(SB, q={"phi": 1.0, "psi": (1.0, 2.0)})
        ),
        ValueError,
        "'bounds'.*fixed start.*'psi'",
    ),
    # messages naming the argument (an audit of the control package, seventeenth session)
    "TerminalPose goal str": (lambda: lc.TerminalPose("abc"), TypeError, "'goal'"),
    "TerminalPose w_heading": (
        lambda: lc.TerminalPose([0.0, 0.1, 0.0], w_heading=-1.0),
        ValueError,
        "'w_heading'",
    ),
    "Bounds.of str": (lambda: lc.Bounds.of(CAR, q={"sigma": "big"}), ValueError, "bound of 'sigma'"),
    "Bounds.of list": (lambda: lc.Bounds.of(CAR, q=[1.0] * 5), TypeError, "'q' must be a dict"),
    "make_gait bounds dict": (
        lambda: lc.make_gait(SB, period=1.0, n_steps=N, objective=lc.Rotation(), bounds={"phi": 1.0}),
        TypeError,
        "'bounds'",
    ),
    "parallel_park system": (lambda: lc.parallel_park(system=SB), TypeError, "'system' must be an lj.Car"),
    "drive_gait system": (lambda: lc.drive_gait(system=CAR), TypeError, "'system' must be an lj.Snakeboard"),
    "Displacement direction": (lambda: lc.Displacement(direction=(0.0, 0.0)), ValueError, "unit vector"),
    "SinusoidGait frequency": (lambda: lc.forward_gait(frequency=NAN), ValueError, "'frequency'"),
    "gait initial_state array": (
        lambda: lc.drive_gait(n_steps=N).initial_state(np.zeros((N + 1, 2))),
        TypeError,
        "'params'.*GaitParams",
    ),
    "controls t0": (
        lambda: _make_task(controls=lc.SampledControls(1.0, N, np.ones(2), t0=0.5)),
        ValueError,
        "'controls' start at t0=0.5",
    ),
    # lc.solve: input checks (before compiling)
    "solve task": (lambda: lc.solve("parallel_park"), TypeError, "'task'"),
    "solve gait": (lambda: lc.solve(GAIT), ValueError, "SampledControls"),
    "solve barrier": (lambda: lc.solve(PARK, barrier=0.0), ValueError, "'barrier'"),
    "solve tol 0": (lambda: lc.solve(PARK, tol=0.0), ValueError, "'tol'"),
    "solve tol nan": (lambda: lc.solve(PARK, tol=NAN), ValueError, "'tol'"),
    "solve tol str": (lambda: lc.solve(PARK, tol="1e-8"), TypeError, "'tol'"),
    "solve max_iterations 0": (lambda: lc.solve(PARK, max_iterations=0), ValueError, "'max_iterations'"),
    "solve max_iterations float": (lambda: lc.solve(PARK, max_iterations=2.5), TypeError, "'max_iterations'"),
    "solve params0 shape": (lambda: lc.solve(PARK, jnp.zeros((N, 2))), ValueError, "'params0'"),
    "solve params0 nan": (lambda: lc.solve(PARK, jnp.full((N + 1, 2), NAN)), ValueError, "'params0'"),
    "solve params0 str": (lambda: lc.solve(PARK, "zeros"), TypeError, "'params0'"),
    # parameters of the wrong shape, wherever they enter (checked when traced)
    "replay params shape": (lambda: lc.replay(PARK, jnp.zeros(3)), ValueError, "'params'.*N \\+ 1"),
    "value params shape": (lambda: PARK.value(jnp.zeros((N, 2))), ValueError, "'params'"),
    "gait params": (lambda: GAIT.controls((jnp.zeros((2, 1)),)), ValueError, "'params'.*amplitudes"),
    "gait params shape": (
        lambda: GAIT.value(jax.tree_util.tree_map(lambda x: x[:1], GAIT.init())),
        ValueError,
        "'params'",
    ),
    # lj.discretize and the discrete-time dynamics: checked when traced
    "discretize h 0": (lambda: lj.discretize(CAR, h=0.0), ValueError, "'h'"),
    "discretize h<0": (lambda: lj.discretize(CAR, h=-0.1), ValueError, "'h'"),
    "discretize h nan": (lambda: lj.discretize(CAR, h=NAN), ValueError, "'h'"),
    "discretize t0 inf": (lambda: lj.discretize(CAR, h=0.1, t0=np.inf), ValueError, "'t0'"),
    "discretize system": (lambda: lj.discretize("car", h=0.1), TypeError, "'system'"),
    "dynamics init q0": (
        lambda: DYN.init(np.zeros(4), np.zeros(5), np.zeros(2)),
        ValueError,
        "'q0'.*n_config",
    ),
    "dynamics init u0": (
        lambda: DYN.init(np.zeros(5), np.zeros(5), np.zeros(3)),
        ValueError,
        "'u0'.*n_controls",
    ),
    "dynamics step x": (lambda: DYN.step(np.zeros(3), np.zeros(2), np.zeros(2)), ValueError, "'x'.*n_state"),
    "dynamics step u1": (
        lambda: DYN.step(np.zeros(DYN.n_state), np.zeros(2), np.zeros(1)),
        ValueError,
        "'u1'",
    ),
    "dynamics observe x": (lambda: DYN.observe(np.zeros(DYN.n_state + 1), np.zeros(2)), ValueError, "'x'"),
    "dynamics node u": (lambda: DYN.node(np.zeros(DYN.n_state), np.zeros((1, 2))), ValueError, "'u'"),
    "dynamics rollout us": (lambda: DYN.rollout(np.zeros(DYN.n_state), np.zeros(4)), ValueError, "'us'"),
    "dynamics rollout us channels": (
        lambda: DYN.rollout(np.zeros(DYN.n_state), np.zeros((5, 3))),
        ValueError,
        r"'us' must be \(K, 2\)",
    ),
    # lc.optimize / lc.multistart: input checks (before compiling)
    "optimize n_iterations 0": (
        lambda: lc.optimize(PARK.value, PARK.init(), n_iterations=0),
        ValueError,
        "'n_iterations'",
    ),
    "optimize n_iterations float": (
        lambda: lc.optimize(PARK.value, PARK.init(), n_iterations=2.5),
        TypeError,
        "'n_iterations'",
    ),
    "optimize chunk 0": (
        lambda: lc.optimize(PARK.value, PARK.init(), n_iterations=4, chunk=0),
        ValueError,
        "'chunk'",
    ),
    "optimize tol<0": (
        lambda: lc.optimize(PARK.value, PARK.init(), n_iterations=4, tol=-1.0),
        ValueError,
        "'tol'",
    ),
    "optimize tol nan": (
        lambda: lc.optimize(PARK.value, PARK.init(), n_iterations=4, tol=NAN),
        ValueError,
        "'tol'",
    ),
    "optimize optimizer": (
        lambda: lc.optimize(PARK.value, PARK.init(), n_iterations=4, optimizer="adam"),
        TypeError,
        "'optimizer'",
    ),
    "optimize loss_fn": (lambda: lc.optimize(3.0, PARK.init(), n_iterations=4), TypeError, "'loss_fn'"),
    "optimize params0 empty": (lambda: lc.optimize(PARK.value, {}, n_iterations=4), ValueError, "'params0'"),
    "optimize params0 int": (
        lambda: lc.optimize(PARK.value, jnp.zeros(3, int), n_iterations=4),
        TypeError,
        "'params0'",
    ),
    "multistart n_iterations": (
        lambda: lc.multistart(PARK.value, PARK.init()[None], n_iterations=0),
        ValueError,
        "'n_iterations'",
    ),
    "multistart tol": (
        lambda: lc.multistart(PARK.value, PARK.init()[None], n_iterations=2, tol=-1.0),
        ValueError,
        "'tol'",
    ),
    # the pieces of a task (a second battery, on the control and gait API): each was accepted and
    # either clamped, truncated, dropped or failed later with a message that did not name it
    "rest index out of range": (
        lambda: _make_task(constraints=(lc.TerminalRest((7,)),)),
        ValueError,
        "TerminalRest: 'indices' \\[7\\] out of range: Car has 1",
    ),
    "rest index float": (lambda: lc.InitialRest((1.5,)), TypeError, "'indices'"),
    "rest weight nan": (lambda: lc.TerminalRest((0,), weight=NAN), ValueError, "'weight'"),
    "bound triple": (lambda: lc.Bounds.of(CAR, q={"sigma": (-1.0, 1.0, 5.0)}), ValueError, "'sigma'.*pair"),
    "bound single": (lambda: lc.Bounds.of(CAR, q={"sigma": (1.0,)}), ValueError, "'sigma'.*pair"),
    "bounds weight<0": (lambda: lc.Bounds.of(CAR, weight=-5.0), ValueError, "Bounds: 'weight'"),
    "gait max_torque one": (lambda: lc.drive_gait(max_torque=(0.1,)), ValueError, "'max_torque'"),
    "gait max_torque three": (lambda: lc.drive_gait(max_torque=(0.1, 0.1, 0.1)), ValueError, "'max_torque'"),
    "gait n_steps float": (lambda: lc.drive_gait(n_steps=40.0), TypeError, "'n_steps'"),
    "guess starts 0": (lambda: lc.Guess(starts=0), ValueError, "'starts'"),
    "guess amplitude nan": (lambda: lc.Guess(amplitude=NAN), ValueError, "'amplitude'"),
    "guess controls shape": (
        lambda: _make_task(guess=lc.Guess(controls=np.zeros((5, 2)))),
        ValueError,
        "'guess'.*\\(11, 2\\)",
    ),
    "effort channels": (lambda: _make_task(objective=(lc.Effort(np.ones(3)),)), ValueError, "Effort's scale"),
    "effort scale 0": (lambda: lc.Effort(np.array([0.0, 0.5])), ValueError, "Effort: 'scale'"),
    "effort weight<0": (lambda: lc.Effort(np.ones(2), weight=-1.0), ValueError, "Effort: 'weight'"),
    "displacement nan": (lambda: lc.Displacement(direction=(NAN, 0.0)), ValueError, "'direction'"),
    "net displacement nan": (lambda: lc.NetDisplacement(dx=NAN), ValueError, "finite"),
    "sampled scale 0": (lambda: lc.SampledControls(1.0, N, np.zeros(2)), ValueError, "'scale'"),
    "path constraint arity": (lambda: lc.PathConstraint(lambda q: q[0]), TypeError, "4 arguments"),
    "terminal constraint matrix": (
        lambda: _make_task(constraints=(lc.TerminalConstraint(lambda q, qd: jnp.zeros((2, 2))),)).value(
            jnp.zeros((N + 1, 2))
        ),
        ValueError,
        "scalar or a vector",
    ),
    "solve gait params": (
        lambda: lc.solve(PARK, lc.GaitParams(jnp.zeros((N + 1, 2)), jnp.zeros(4))),
        TypeError,
        "'params0'.*GaitParams",
    ),
    "replay gait params": (
        lambda: lc.replay(PARK, lc.GaitParams(jnp.zeros((N + 1, 2)), jnp.zeros(4))),
        TypeError,
        "'params'.*GaitParams",
    ),
    "monodromy not periodic": (lambda: lc.monodromy(PARK, PARK.init()), ValueError, "periodic"),
    "cycle_map not periodic": (lambda: lc.cycle_map(PARK, PARK.init(), jnp.zeros(4)), ValueError, "periodic"),
    "n_steps traced": (
        lambda: jax.jit(lambda n: PARK.with_options(n_steps=n))(8),
        TypeError,
        "'n_steps'.*traced",
    ),
}


#: A third battery (systems, policies, the discrete dynamics, the study and the figures): each
#: case was accepted and ran on, or failed deep inside NumPy or JAX without naming its argument.
_TS5 = np.linspace(0.0, 2.0, 5)
E2 = np.eye(3, 2)
_K = np.zeros((2, 10))
OTHER_RAISES = {
    "policy times decreasing": (
        lambda: lj.LinearPolicy(lj.Constant(np.zeros(2)), _K, np.zeros((5, 10)), _TS5[::-1]),
        ValueError,
        "'times' must be finite and strictly increasing",
    ),
    "policy gain per time": (
        lambda: lj.LinearPolicy(lj.Constant(np.zeros(2)), np.stack([_K] * 3), np.zeros((5, 10)), _TS5),
        ValueError,
        "one matrix per time: 3 for 5",
    ),
    "policy reference per time": (
        lambda: lj.LinearPolicy(lj.Constant(np.zeros(2)), _K, np.zeros((5, 10)), _TS5[:4]),
        ValueError,
        "'reference' has 5 samples but 'times' has 4",
    ),
    "dynamics init qdot0 off": (
        lambda: DYN.init(np.zeros(5), np.asarray(SLIDE), np.zeros(2)),
        ValueError,
        "'qdot0' violates",
    ),
    "dynamics init qdot0 nan": (
        lambda: DYN.init(np.zeros(5), np.full(5, NAN), np.zeros(2)),
        ValueError,
        "'qdot0' must be finite",
    ),
    "dynamics rollout no nodes": (
        lambda: DYN.rollout(np.zeros(DYN.n_state), np.zeros((0, 2))),
        ValueError,
        "'us'.*K >= 1",
    ),
    "study resolutions repeated": (
        lambda: study.StudyConfig(models=("car",), resolutions=(100, 100)),
        ValueError,
        "'resolutions' must be distinct",
    ),
    "run_study dict": (lambda: study.run_study({"models": ("car",)}), TypeError, "'config'"),
    "runtime_ratios error": (
        lambda: study.runtime_ratios([{"model": "car", "final_error_median": 1.0}], error="bogus"),
        ValueError,
        "'error'",
    ),
    "fitted_order lengths": (
        lambda: lj.plotting.fitted_order([0.1, 0.05, 0.025], [1e-3, 2.5e-4]),
        ValueError,
        "one length",
    ),
    "plot_paths one trajectory": (
        lambda: lj.plotting.plot_paths(None, CAR, np.zeros((3, 5))),
        TypeError,
        "'paths' must be a mapping",
    ),
    "plot_diagnostics empty": (lambda: lj.plotting.plot_diagnostics({}), ValueError, "'trajectories'"),
    "runtime_ratios pair missing": (
        lambda: study.runtime_ratios([{"model": "car", "method": "rdp"}], pairs=(("rdp", "rk9"),)),
        ValueError,
        "'pairs'.*'rk9'",
    ),
    "optimize vector loss": (
        lambda: lc.optimize(lambda p: (p - 3.0) ** 2, jnp.zeros(2), n_iterations=2),
        TypeError,
        "'loss_fn' must return a real scalar loss",
    ),
    "optimize three outputs": (
        lambda: lc.optimize(lambda p: (jnp.sum(p**2), 1.0, 2.0), jnp.zeros(2), n_iterations=2),
        TypeError,
        "'loss_fn'",
    ),
    "System lagrangian int": (
        lambda: lj.System(0, lambda r, u, xi: jnp.array(1), lambda r: jnp.zeros((3, 0)), lambda r: E2),
        TypeError,
        "lagrangian.*floating scalar",
    ),
    # a fourth battery (devices, the cache, save, multistart)
    "device_mesh string": (lambda: lj.device_mesh("cpu"), TypeError, "'devices'"),
    "device_mesh empty": (lambda: lj.device_mesh([]), ValueError, "'devices'.*non-empty"),
    "device_mesh repeated": (lambda: lj.device_mesh(jax.devices()[:1] * 2), ValueError, "distinct"),
    "shard_vmap mesh list": (lambda: lj.shard_vmap(jnp.sin, mesh=jax.devices()), TypeError, "'mesh'"),
    "shard_vmap mesh axis": (
        lambda: lj.shard_vmap(jnp.sin, mesh=jax.sharding.Mesh(np.asarray(jax.devices()), ("x",))),
        ValueError,
        "'mesh'.*'batch'",
    ),
    "cache path empty": (lambda: lj.enable_compilation_cache(""), ValueError, "'path'"),
    "cache min seconds": (
        lambda: lj.enable_compilation_cache("unused", min_compile_seconds=NAN),
        ValueError,
        "'min_compile_seconds'",
    ),
    "trim threshold str": (lambda: lj.trim_compilation_cache("0.5"), TypeError, "'threshold'"),
    "save mask": (
        lambda: lj.simulate(CAR, Z5, Z5, None, t_final=1.0, n_steps=N, save=[False, True]),
        ValueError,
        "boolean mask",
    ),
    "multistart no starts": (
        lambda: lc.multistart(lambda p: jnp.sum(p**2), jnp.zeros((0, 2)), n_iterations=2),
        ValueError,
        "'params0' must be a batch of starts",
    ),
}


def test_a_relative_cache_path_is_made_absolute(tmp_path, monkeypatch):
    """JAX read a relative cache folder against the working folder of each write: the library
    makes it absolute when it is enabled (JAX's configuration recorded, not changed)."""
    calls = []
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(jax.config, "update", lambda *args: calls.append(args))
    path = lj.enable_compilation_cache("relcache")
    assert path == str(tmp_path / "relcache") and os.path.isdir(path)
    assert ("jax_compilation_cache_dir", path) in calls


def test_read_csv_refuses_a_file_that_is_not_a_study(tmp_path):
    path = tmp_path / "other.csv"
    path.write_text("a,b\n1,2\n")
    with pytest.raises(ValueError, match="not a study CSV: no column \\['model', 'method', 'n_steps'\\]"):
        study.read_csv(path)


def test_discrete_rollout_marks_a_failed_step_and_a_nan_singularity_fails():
    """``dyn.rollout`` of the snakeboard steered through ``cos(phi) = 0`` (phi from 1.5 at 0.5
    rad/s, h = 0.1 s): the states equal ``dyn.step``'s up to the step that crosses it, which
    ``step_with_info`` reports ``singular``, and are NaN from it on (finite before: the rollout
    ran on past it). A system's singularity function that returns NaN at a finite configuration
    is a singularity (``successful`` before); plotting that failed run warns."""
    dyn = lj.discretize(SB, lj.RDP(), h=0.1)
    x0 = dyn.init(jnp.array([0.0, 0.0, 0.0, 0.0, 1.5]), jnp.array([0.0, 0.0, 0.0, 0.0, 0.5]), jnp.zeros(2))
    xs = np.asarray(dyn.rollout(x0, jnp.zeros((8, 2))))
    bad = int(np.argmax(~np.isfinite(xs[:, 0])))
    assert bad >= 2 and np.all(np.isnan(xs[bad:])) and np.all(np.isfinite(xs[:bad])), xs[:, 4]
    np.testing.assert_array_equal(np.asarray(dyn.step(xs[bad - 2], jnp.zeros(2), jnp.zeros(2))), xs[bad - 1])
    _, info = dyn.step_with_info(xs[bad - 1], jnp.zeros(2), jnp.zeros(2))
    assert info.result == R.singular
    sleigh = lj.chaplygin_sleigh()
    nan_sleigh = eqx.tree_at(
        lambda s: s.singularity_fn, sleigh, lambda p, r: jnp.nan, is_leaf=lambda x: x is None
    )
    traj = lj.simulate(nan_sleigh, jnp.zeros(3), jnp.zeros(3), None, t_final=1.0, n_steps=4)
    assert traj.result == R.singular
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots()
    with pytest.warns(UserWarning, match="failed.*singular"):
        lj.plotting.plot_paths(ax, nan_sleigh, {"nan": traj})
    plt.close("all")


def test_sampled_controls_that_miss_part_of_the_run_warn():
    """Samples over [0, 1] s or [5, 7] s driving a run over [0, 2] s are held at their end values
    where they miss it (a silent ``successful`` before); samples that cover the run do not warn."""
    import warnings

    ramp = np.stack([np.linspace(0.0, 1.0, N + 1), np.full(N + 1, 0.1)], axis=1)
    run = functools.partial(lj.simulate, CAR, Z5, Z5, t_final=2.0, n_steps=N, diagnostics=False)
    for window in (dict(t_final=1.0), dict(t_final=7.0, t0=5.0)):
        with pytest.warns(UserWarning, match="held at their end values"):
            run(lj.Sampled(ramp, **window))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        run(lj.Sampled(ramp, 2.0))


def test_a_system_whose_constraints_contradict_its_symmetry_basis_is_refused():
    """The sleigh with its constraint turned to ``v_x = 0`` while its symmetry basis still allows
    ``v_x``: the two views of the system disagree, and each integrator went its own way
    (``successful`` from RDP, RK4 and DLA, three different motions). Refused by name; the sleigh
    itself runs."""
    sleigh = lj.chaplygin_sleigh()
    bad = eqx.tree_at(lambda s: s.constraints_fn, sleigh, lambda p, r: jnp.array([[0.0, 1.0, 0.0]], r.dtype))
    with pytest.raises(ValueError, match="'system': its constraints C\\(r\\) and its symmetry basis"):
        lj.simulate(bad, jnp.zeros(3), jnp.zeros(3), None, t_final=1.0, n_steps=4, diagnostics=False)
    good = lj.simulate(sleigh, jnp.zeros(3), jnp.array([1.0, 0.0, 0.1]), None, t_final=1.0, n_steps=4)
    assert good.result == R.successful
    # without a symmetry basis (c = 0, the car's case) the connection is checked against the
    # constraints too (a sign flipped in it ran 'successful' with a constraint residual of 2.8)
    lag = lambda r, u, xi: 0.5 * (u[0] ** 2 + u[1] ** 2 + xi[0] ** 2 + xi[1] ** 2 + xi[2] ** 2)  # noqa: E731
    conn = jnp.array([[0.2, -0.2], [0.5, 0.5], [0.0, 0.0]])
    cons = lambda sign: lambda r: jnp.concatenate([jnp.eye(3), sign * conn], axis=1)  # noqa: E731
    drive = functools.partial(lj.System, 2, lag, lambda r: conn)
    for sign, ok in ((1.0, True), (-1.0, False)):
        system = drive(constraints=cons(sign))
        run = functools.partial(lj.simulate, system, jnp.zeros(5), jnp.zeros(5), None, t_final=1.0, n_steps=4)
        if ok:
            assert run().result == R.successful
        else:
            with pytest.raises(ValueError, match="'system': its constraints C\\(r\\)"):
                run()


#: every construction-time case: the control API's, then the others'
CONSTRUCTION_RAISES = {**TASK_RAISES, **OTHER_RAISES}
assert len(CONSTRUCTION_RAISES) == len(TASK_RAISES) + len(OTHER_RAISES)  # no name in both


@pytest.mark.parametrize("name", list(CONSTRUCTION_RAISES))
def test_construction_arguments(name):
    make, exc, match = CONSTRUCTION_RAISES[name]
    with pytest.raises(exc, match=match):
        make()


def test_task_pieces_known_integers_and_resampled_guesses():
    """Known JAX integers count as their values (``n_steps``, ``cycles``, ``max_iterations``); a
    Python list is a guess like an array; a scalar torque bound is every channel's; a gait whose
    ``n_steps`` changes keeps its own guess, resampled to the new nodes (against the guess built
    at those nodes: within linear interpolation's error bound for its sinusoids, 1.8e-3);
    and a NaN bound makes a task invalid when traced, as lower > upper does (``lc.solve`` reports
    ``invalid_input``; NaN compared false, and the bound was silently dropped)."""
    from ldap_jax.control._solve import _checked, valid_task

    assert lc.parallel_park(n_steps=jnp.array(N)).n_steps == N
    _, from_list, _ = _checked(PARK, PARK.init().tolist(), 1e-8, jnp.array(5), "base", 0.1, None)
    np.testing.assert_array_equal(np.asarray(from_list), np.asarray(PARK.init()))
    np.testing.assert_array_equal(np.asarray(lc.drive_gait(max_torque=0.1).bounds.u_upper), [0.1, 0.1])
    moved = lc.drive_gait(n_steps=100).with_options(n_steps=30)
    built = lc.drive_gait(n_steps=30)
    assert moved.guess.controls.shape == built.guess.controls.shape == (31, 2)
    # linear interpolation on a grid of 1/100: at most h^2/8 max|f''| = 1e-4/8 * 0.9 (4 pi)^2
    bound = 1e-4 / 8 * 0.9 * (4 * np.pi) ** 2
    assert 0 < np.max(np.abs(np.asarray(moved.guess.controls) - np.asarray(built.guess.controls))) < bound
    b = PARK.bounds
    valid = jax.jit(
        lambda lo: valid_task(PARK.with_options(bounds=lc.Bounds(lo, b.q_upper, b.u_lower, b.u_upper)))
    )
    assert [bool(valid(x)) for x in (b.q_lower, b.q_lower.at[4].set(NAN), b.q_upper)] == [True, False, False]


def test_optimize_warns_when_the_loss_is_never_finite():
    """A weak case of the issue: an always-NaN loss returned the start with no warning."""
    p0 = jnp.array([1.0, 2.0])
    with pytest.warns(UserWarning, match="never finite"):
        res = lc.optimize(lambda p: jnp.sum(p**2) * jnp.nan, p0, n_iterations=2)
    assert not np.isfinite(float(res.loss))
    np.testing.assert_array_equal(np.asarray(res.params), np.asarray(p0))


# ============================================================== the compilation cache (weak case)
def test_library_trims_the_compilation_cache_as_it_compiles(monkeypatch):
    """Every new n_steps compiles a new program (hundreds of memory mappings); simulate counts
    them and trims JAX's caches every CHECK_EVERY new programs, outside any trace."""
    calls = []
    monkeypatch.setattr(cc, "trim_compilation_cache", lambda threshold=0.5: calls.append(threshold) or False)
    monkeypatch.setattr(cc, "_seen", set())
    monkeypatch.setattr(cc, "_new_programs", 0)
    # the rollout itself is stubbed out (it raises once the bookkeeping is done): this test
    # checks the bookkeeping, not XLA

    class Stop(Exception):
        pass

    def stub(*args, **kw):
        raise Stop

    monkeypatch.setattr(simulate_module, "_simulate", stub)

    def run(n):
        with pytest.raises(Stop):
            _simulate(n_steps=n)

    for n in range(1, 2 * cc.CHECK_EVERY + 1):
        run(n)
    assert len(calls) == 2
    for n in range(1, 2 * cc.CHECK_EVERY + 1):  # the same programs again: nothing new
        run(n)
    assert len(calls) == 2
    # inside a trace nothing is counted (clearing caches while tracing is unsafe)
    jax.jit(lambda x: (cc.note_program(("traced", 0)), x)[1])(1.0)
    assert ("traced", 0) not in cc._seen


# ======================================================================================== scripts
FAKE_JAX = "raise ImportError('the script imported jax before checking its flags')\n"


@pytest.fixture(scope="module")
def script_env(tmp_path_factory):
    """An environment in which ``import jax`` fails, and an existing file to pass as a folder."""
    root = tmp_path_factory.mktemp("scripts")
    (root / "fakejax").mkdir()
    (root / "fakejax" / "jax.py").write_text(FAKE_JAX)
    existing = root / "a_file.csv"
    existing.write_text("precious results\n")
    env = dict(os.environ)
    env["PYTHONPATH"] = str(root / "fakejax")
    return env, str(existing)


FILE = "<existing file>"
SCRIPT_CASES = {
    "sweep --out file": ("sweep.py", ["--out", FILE], "--out"),
    "sweep --cpu-devices 0": ("sweep.py", ["--cpu-devices", "0"], "--cpu-devices"),
    "sweep --cpu-devices two": ("sweep.py", ["--cpu-devices", "two"], "--cpu-devices"),
    "sweep --runs 0": ("sweep.py", ["--runs", "0"], "--runs"),
    "sweep --runs many": ("sweep.py", ["--runs", "many"], "--runs"),
    "sweep --resolutions 100,x": ("sweep.py", ["--resolutions", "100,x"], "--resolutions"),
    "sweep --resolutions 0": ("sweep.py", ["--resolutions", "0"], "--resolutions"),
    "sweep --resolutions 100,,200": ("sweep.py", ["--resolutions", "100,,200"], "--resolutions"),
    "sweep --duration 10q": ("sweep.py", ["--duration", "10q"], "--duration"),
    "sweep --duration -5s": ("sweep.py", ["--duration=-5s"], "--duration"),
    "sweep --duration inf": ("sweep.py", ["--duration", "inf"], "--duration"),
    "sweep --reference-step 0": ("sweep.py", ["--reference-step", "0"], "--reference-step"),
    "sweep --reference-step nan": ("sweep.py", ["--reference-step", "nan"], "--reference-step"),
    "sweep --repeats 0": ("sweep.py", ["--repeats", "0"], "--repeats"),
    "sweep --seed x": ("sweep.py", ["--seed", "x"], "--seed"),
    "sweep --methods rk5": ("sweep.py", ["--methods", "rdp,rk5"], "--methods"),
    "sweep --methods empty": ("sweep.py", ["--methods", ""], "--methods"),
    "sweep --model bicycle": ("sweep.py", ["--model", "bicycle"], "--model"),
    "sweep unknown flag": ("sweep.py", ["--bogus"], "--bogus"),
    "optimize --iterations 0": (
        "optimize.py",
        ["--model", "car", "--task", "parallel_park", "--iterations", "0"],
        "--iterations",
    ),
    "optimize --iterations x": (
        "optimize.py",
        ["--model", "car", "--task", "parallel_park", "--iterations", "x"],
        "--iterations",
    ),
    "optimize --starts 0": (
        "optimize.py",
        ["--model", "snakeboard", "--task", "forward_gait", "--starts", "0"],
        "--starts",
    ),
    "optimize --starts with solve": (
        "optimize.py",
        ["--model", "car", "--task", "u_turn", "--starts", "4"],
        "--starts",
    ),
    "optimize --n-steps 0": (
        "optimize.py",
        ["--model", "car", "--task", "parallel_park", "--n-steps", "0"],
        "--n-steps",
    ),
    "optimize --task of other model": ("optimize.py", ["--model", "car", "--task", "reach"], "--task"),
    "optimize --model bicycle": ("optimize.py", ["--model", "bicycle", "--task", "reach"], "--model"),
    "optimize --task missing": ("optimize.py", ["--model", "car"], "--task"),
    "optimize --solver solve gait": (
        "optimize.py",
        ["--model", "snakeboard", "--task", "forward_gait", "--solver", "solve"],
        "--solver",
    ),
    "optimize --integrator rk5": (
        "optimize.py",
        ["--model", "car", "--task", "u_turn", "--integrator", "rk5"],
        "--integrator",
    ),
    "optimize --out file": ("optimize.py", ["--model", "car", "--task", "u_turn", "--out", FILE], "--out"),
    "optimize --cache file": (
        "optimize.py",
        ["--model", "car", "--task", "u_turn", "--cache", FILE],
        "--cache",
    ),
    "optimize --seed 1.5": ("optimize.py", ["--model", "car", "--task", "u_turn", "--seed", "1.5"], "--seed"),
    "bench_control --repeats 0": ("bench_control.py", ["--repeats", "0"], "--repeats"),
    "bench_control --repeats x": ("bench_control.py", ["--repeats", "x"], "--repeats"),
    "bench_control --out file": ("bench_control.py", ["--out", FILE], "--out"),
    "bench_control --integrator rk5": ("bench_control.py", ["--integrator", "rk5"], "--integrator"),
    "bench_control --robustness 0,x": ("bench_control.py", ["--robustness", "0,x"], "--robustness"),
    "bench_control --robustness -1": ("bench_control.py", ["--robustness=-1"], "--robustness"),
    "time_notebooks 99": ("time_notebooks.py", ["99"], "notebooks"),
    "time_notebooks 0": ("time_notebooks.py", ["0"], "notebooks"),
    "time_notebooks --cache file": ("time_notebooks.py", ["01", "--cache", FILE], "--cache"),
    # a third battery: each ran on (a whole quick run, or files written into the working folder)
    "quickstart --jobs 0": ("quickstart.py", ["--jobs", "0"], "--jobs"),
    "quickstart --out empty": ("quickstart.py", ["--out", ""], "--out"),
    "demo --out file": ("demo.py", ["--out", FILE, "--only", "quickstart"], "--out"),
    "optimize --family --compare-integrators": (
        "optimize.py",
        ["--model", "car", "--task", "parallel_park", "--family", "2", "--compare-integrators"],
        "--compare-integrators",
    ),
    "first_solve --runs -1": ("first_solve.py", ["--runs=-1"], "--runs"),
    "first_solve --hlo without --program": ("first_solve.py", ["--hlo", "h.txt"], "--hlo"),
    "first_solve --cache with --no-cache": ("first_solve.py", ["--no-cache", "--cache", "c"], "--cache"),
}
#: the scripts that write no files (no ``--out``)
NO_OUT = {"time_notebooks.py", "first_solve.py"}


@pytest.mark.parametrize("name", list(SCRIPT_CASES))
def test_script_rejects_bad_flags_before_any_work(name, script_env, tmp_path):
    script, argv, flag = SCRIPT_CASES[name]
    env, existing = script_env
    argv = [existing if a == FILE else a for a in argv]
    if "--out" not in argv and script not in NO_OUT:
        argv = [*argv, "--out", str(tmp_path / "out")]  # never the working directory
    out = subprocess.run(
        [sys.executable, os.path.join(ROOT, "scripts", script), *argv],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 2, out.stderr[-2000:]
    assert flag in out.stderr, out.stderr[-2000:]
    assert "Traceback" not in out.stderr
    with open(existing) as f:  # an existing file passed as --out is left alone
        assert f.read() == "precious results\n"


def _literal(script: str, name: str):
    """A module-level constant of a script, read without running it."""
    with open(os.path.join(ROOT, "scripts", script)) as f:
        tree = ast.parse(f.read())
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == name for t in node.targets):
            return ast.literal_eval(node.value)
    raise KeyError(name)


def test_script_name_lists_match_the_library():
    """The scripts spell out the names they accept (to check flags before importing JAX)."""
    assert _literal("sweep.py", "METHOD_NAMES") == tuple(study.METHODS)
    assert _literal("sweep.py", "MODEL_NAMES") == tuple(study.MODELS)
    tasks = _literal("optimize.py", "MODEL_TASKS")
    assert {(m, t) for m, ts in tasks.items() for t in ts} == set(lc.TASKS)
    periodic = {
        t for (_, t), make in lc.TASKS.items() if not isinstance(make().parameterization, lc.SampledControls)
    }
    assert set(_literal("optimize.py", "PERIODIC_TASKS")) == periodic
    assert _literal("bench_control.py", "TASK_NAMES") == ("parallel_park", "u_turn", "reach")


# ============================================================================ the result messages
def test_every_failure_result_says_what_to_do():
    for item in (R.nonfinite, R.singular, R.not_converged, R.diverged, R.invalid_input, R.max_steps_reached):
        message = R[item]
        assert len(message) > 60 and any(w in message for w in ("Reduce", "reduce", "Raise", "call", "Keep"))
    assert "controls" in R[R.invalid_input] and "qdot0" in R[R.invalid_input]


@pytest.mark.xdist_group("faults_issue47")
@pytest.mark.parametrize("amp", ["healthy", "fails later"])
def test_save_all_equals_every_node_selected_by_index(amp):
    """``save="all"`` equals the same nodes given as indices: the values bit for bit, the gradients
    to 1e-12 (a loss reading the failed run gets NaN, one masking it out a finite gradient)."""
    a = AMP if amp == "healthy" else SINGULAR_AMP

    def run(amp_, save):
        return lj.simulate(SB, Z5, Z5, lj.Sinusoids(amp_, FREQ, PHASE), t_final=TF, n_steps=N, save=save)

    written, selected = run(a, "all"), run(a, list(range(N + 1)))
    assert (written.result == R.successful) == (amp == "healthy")
    for x, y in zip(jax.tree_util.tree_leaves(written), jax.tree_util.tree_leaves(selected)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))

    def loss(amp_, save, masked):
        traj = run(amp_, save)
        e = jnp.where(traj.failed, 0.0, traj.energy) if masked else traj.energy
        return jnp.sum(e) + jnp.sum(traj.qdot[N // 2] ** 2 if not masked else 0.0)

    for masked in (False, True):
        g_w = np.asarray(jax.jit(jax.grad(lambda x, m=masked: loss(x, "all", m)))(a))
        g_s = np.asarray(jax.jit(jax.grad(lambda x, m=masked: loss(x, list(range(N + 1)), m)))(a))
        np.testing.assert_allclose(g_w, g_s, rtol=1e-12, atol=0)
        if amp == "fails later" and not masked:
            assert np.all(np.isnan(g_w))
        else:
            assert np.all(np.isfinite(g_w))


def test_make_gait_takes_one_term_or_constraint_as_well_as_tuples():
    """A single objective term or constraint (not in a tuple) builds the same task as the tuple."""
    one = lc.make_gait(SB, period=1.0, n_steps=N, objective=lc.Rotation(), constraints=lc.InitialRest((0, 2)))
    many = lc.make_gait(
        SB, period=1.0, n_steps=N, objective=(lc.Rotation(),), constraints=(lc.InitialRest((0, 2)),)
    )
    assert one.objective == many.objective and one.constraints == many.constraints
