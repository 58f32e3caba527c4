"""The README's quick example runs as printed."""

import os
import pathlib
import re
import subprocess
import sys

import equinox as eqx
import numpy as np


def test_readme_quick_example_runs():
    text = (pathlib.Path(__file__).parent.parent / "README.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, re.S)
    assert blocks, "README has no python example"
    namespace: dict = {}
    exec(compile(blocks[0], "README.md", "exec"), namespace)  # noqa: S102
    assert not bool(namespace["traj"].failed)
    traj, ref = namespace["traj"], namespace["ref"]
    assert float(namespace["jnp"].linalg.norm(traj.q[-1, :2] - ref.q[-1, :2])) < 1e-3


def test_readme_bring_your_own_system_example_runs():
    text = (pathlib.Path(__file__).parent.parent / "README.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, re.S)
    assert len(blocks) >= 2 and "lj.System(" in blocks[1]
    assert len(blocks[1].strip().splitlines()) < 40
    namespace: dict = {}
    exec(compile(blocks[1], "README.md", "exec"), namespace)  # noqa: S102
    jnp = namespace["jnp"]
    traj, ref = namespace["traj"], namespace["ref"]
    assert not bool(traj.failed)
    assert float(jnp.linalg.norm(traj.q[-1, :2] - ref.q[-1, :2])) < 1e-2
    assert float(jnp.ptp(traj.energy)) < 1e-8


def test_readme_optimal_control_example_runs():
    """lc.solve with RDP(order=4) meets the goal on the reference; the sensitivity is finite."""
    text = (pathlib.Path(__file__).parent.parent / "README.md").read_text()
    blocks = [b for b in re.findall(r"```python\n(.*?)```", text, re.S) if "lc.solve" in b]
    assert blocks
    namespace: dict = {}
    exec(compile(blocks[0], "README.md", "exec"), namespace)  # noqa: S102
    assert bool(namespace["sol"].converged)
    assert namespace["replay"]["final_position_error"] < 1e-6


def test_readme_discrete_dynamics_example_runs():
    text = (pathlib.Path(__file__).parent.parent / "README.md").read_text()
    blocks = [b for b in re.findall(r"```python\n(.*?)```", text, re.S) if "lj.discretize" in b]
    assert blocks
    namespace: dict = {}
    exec(compile(blocks[0], "README.md", "exec"), namespace)  # noqa: S102
    xs = namespace["xs"]
    assert xs.shape[0] == 101 and bool(namespace["jnp"].all(namespace["jnp"].isfinite(xs)))
    # the text below the example: a method compiled alone with eqx.filter_jit is the same step
    dyn, us = namespace["dyn"], namespace["us"]
    stepped = eqx.filter_jit(dyn.step)(xs[7], us[7], us[8])
    np.testing.assert_allclose(np.asarray(stepped), np.asarray(xs[8]), rtol=1e-13, atol=1e-13)


def test_readme_all_cores_example_runs_sharded():
    """The all-cores snippet, in a fresh interpreter (the device count is fixed when JAX starts): on 2
    host devices lj.shard_vmap splits a batch of 7 (padded to 8) and returns every member's
    trajectory, equal to an unsharded vmap of the same members."""
    text = (pathlib.Path(__file__).parent.parent / "README.md").read_text()
    blocks = [b for b in re.findall(r"```python\n(.*?)```", text, re.S) if "shard_vmap" in b]
    assert blocks
    code = (
        blocks[0]
        .replace("lj.use_cpu_cores()", "lj.use_cpu_cores(2)")
        .replace("PRNGKey(0), 1000)", "PRNGKey(0), 7)")
    )  # small; 2 devices anywhere
    assert "lj.use_cpu_cores(2)" in code
    # compiled with the suite's code generation (conftest); the snippet adds the device count
    flags = "import os\nos.environ['XLA_FLAGS'] = os.environ.get('LDAP_JAX_TEST_FLAGS', '')\n"
    code = flags + code
    check = """
import numpy as np
out = run(q0, qdot0, ctl)
assert len(jax.devices()) == 2 and len(out.sharding.device_set) == 2, out.sharding
ref = jax.vmap(lambda a, b, c: lj.simulate(sb, a, b, c, t_final=10.0, n_steps=1000).q)(q0, qdot0, ctl)
assert out.shape == (7, 1001, 5), out.shape
np.testing.assert_allclose(np.asarray(out), np.asarray(ref), rtol=0, atol=1e-12)
print("OK")
"""
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    res = subprocess.run(
        [sys.executable, "-c", code + check], capture_output=True, text=True, env=env, timeout=600
    )
    assert res.returncode == 0, res.stderr[-3000:]
    assert res.stdout.strip().endswith("OK")
