"""Run-time type checking: the library's annotations (jaxtyping shapes and dtypes) hold on its main
paths when every function is checked by beartype.

It runs in a child process because the import hook must see ``ldap_jax`` imported for the first
time, and because checked functions raise beartype's error first: in the rest of the suite the
library's own argument errors (tests/test_faults.py) are what a user sees and what is asserted.
"""

import subprocess
import sys

import pytest

SCRIPT = """
import jax
import jax.numpy as jnp
from jaxtyping import install_import_hook

jax.config.update("jax_enable_x64", True)
with install_import_hook("ldap_jax", "beartype.beartype"):
    import ldap_jax as lj
    from ldap_jax import control as lc

# the check is active: a pose of the wrong shape fails in the annotation, before the body runs
try:
    lj.lie.exp(jnp.zeros(4))
except Exception as err:
    assert "TypeCheckError" in type(err).__name__ or "BeartypeCall" in type(err).__name__, repr(err)
else:
    raise AssertionError("a pose of shape (4,) passed the type check")

# every integrator on one model at least, both models' kernels and continuous equations
integrators = {
    "Car": (lj.RDP(), lj.RDP(order=4), lj.RK4(), lj.DLA()),
    "Snakeboard": (lj.RDP(), lj.RDP(solver="newton"), lj.RK4(), lj.GNI()),
}
# The annotations are checked when a function is called, which under jit is at trace time: the
# rollouts are traced (jax.eval_shape) and not compiled, except one that runs.
for system in (lj.Car(), lj.Snakeboard()):
    q0, qdot0, ctl = system.sample_maneuver(jax.random.PRNGKey(0))
    for integrator in integrators[type(system).__name__]:
        out = jax.eval_shape(
            lambda: lj.simulate(system, q0, qdot0, ctl, t_final=0.5, n_steps=5, integrator=integrator)
        )
        assert out.q.shape == (6, 5), (type(system).__name__, integrator, out.q.shape)
    out = jax.eval_shape(lambda: lj.reference(system, q0, qdot0, ctl, jnp.linspace(0.0, 0.5, 3)))
    assert out.q.shape == (3, 5)
    dyn = lj.discretize(system, lj.RDP(order=4), h=0.1)

    def node():
        x1 = dyn.step(dyn.init(q0, qdot0, ctl(0.0)), ctl(0.0), ctl(0.1), 0)
        return dyn.observe(x1, ctl(0.1)).q

    assert jax.eval_shape(node).shape == (5,)
racer = lj.roller_racer()
gait = lj.Sinusoids([[0.4]], [[2.5]], [[0.0]])
traj = lj.simulate(racer, jnp.zeros(4), jnp.zeros(4), gait, t_final=0.5, n_steps=5)  # runs
assert traj.result == lj.RESULTS.successful
task = lc.parallel_park(n_steps=10)
assert jax.eval_shape(task.value, task.init()).shape == ()
print("OK")
"""


def test_annotations_hold_under_beartype():
    pytest.importorskip("beartype")
    res = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=900)
    assert res.returncode == 0, res.stderr[-4000:]
    assert res.stdout.strip().endswith("OK")
