"""The documentation runs as printed: every notebook in notebooks/ and every example in the README.

All of them run in one child process, one after the other, each in a fresh namespace, as a user's
session would run them (JAX's default numerics, not the suite's strict promotion). The README's
examples repeat what the notebooks do (its optimal control example is notebook 03's parallel
parking and its sensitivity), so in one process they reuse the notebooks' compiled programs:
measured at the suite's code generation, the notebooks and the four examples in 73 s, against 64 s
for the notebooks alone and 22 s for the examples run in a test worker. The README's all-cores
example needs a process of its own (the device count is fixed when JAX starts).

The child runs the code in an IPython shell (what a Jupyter kernel runs code in) without the
kernel's ZeroMQ channels: with nbclient, shutting a kernel down on a loaded machine could leave
jupyter_client's heartbeat thread blocked on a socket whose peer had exited, and the test hung for
good (seen once in a full run). A hang here now ends in the timeout as a failure. A document that
fails is reported and the next one still runs.
"""

from __future__ import annotations

import json
import os
import pathlib
import re
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).parent.parent
NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.ipynb"))
README = (ROOT / "README.md").read_text()
BLOCKS = re.findall(r"```python\n(.*?)```", README, re.S)

# README examples run in the child: (name, how the block is found, the checks run after it in its
# namespace). The checks are the test's, not the README's: they assert what the text promises.
EXAMPLES = {
    "quick": (
        lambda b: b == BLOCKS[0],
        """
assert not bool(traj.failed)
assert float(jnp.linalg.norm(traj.q[-1, :2] - ref.q[-1, :2])) < 1e-3
""",
    ),
    "bring_your_own_system": (
        lambda b: "lj.System(" in b,
        """
assert not bool(traj.failed)
assert float(jnp.linalg.norm(traj.q[-1, :2] - ref.q[-1, :2])) < 1e-2
assert float(jnp.ptp(traj.energy)) < 1e-8
""",
    ),
    "optimal_control": (
        lambda b: "lc.solve" in b,
        """
assert bool(sol.converged)
assert replay["final_position_error"] < 1e-6
""",
    ),
    "discrete_dynamics": (
        lambda b: "lj.discretize" in b,
        """
import equinox as eqx
import numpy as np
assert xs.shape[0] == 101 and bool(jnp.all(jnp.isfinite(xs)))
# the text below the example: a method compiled alone with eqx.filter_jit is the same step
stepped = eqx.filter_jit(dyn.step)(xs[7], us[7], us[8])
np.testing.assert_allclose(np.asarray(stepped), np.asarray(xs[8]), rtol=1e-13, atol=1e-13)
""",
    ),
}

RUNNER = """
import json
import sys
import traceback

from IPython.core.interactiveshell import InteractiveShell

with open(sys.argv[2]) as f:
    documents = json.load(f)
shell = InteractiveShell.instance(colors="nocolor")
report = {}
for name, cells in documents.items():
    shell.reset(new_session=True)
    status = "OK"
    for i, source in enumerate(cells):
        try:
            result = shell.run_cell(source)
        except BaseException:  # the shell itself failed
            status = f"code cell {i} failed: {traceback.format_exc()}"
            break
        if not result.success:
            err = result.error_in_exec or result.error_before_exec
            status = f"code cell {i} failed: {err!r}"
            break
    if "matplotlib.pyplot" in sys.modules:
        sys.modules["matplotlib.pyplot"].close("all")
    report[name] = status
    print(f"== {name}: {status}", flush=True)
with open(sys.argv[1], "w") as f:
    json.dump(report, f)
"""


def _found(name: str) -> list[str]:
    """The README's blocks that are the example ``name``."""
    return [b for b in BLOCKS if EXAMPLES[name][0](b)]


def _example(name: str) -> str:
    found = _found(name)
    assert found, f"README has no {name} example"
    return found[0]


def _notebook_cells(path: pathlib.Path) -> list[str]:
    cells = json.loads(path.read_text())["cells"]
    return ["".join(c["source"]) for c in cells if c["cell_type"] == "code"]


@pytest.fixture(scope="module")
def docs_report(tmp_path_factory):
    """Runs every notebook, then every README example with its checks, in one child process in a
    temporary working directory (the files the notebooks write, e.g. their animations, do not touch
    the checkout)."""
    work = tmp_path_factory.mktemp("docs")
    documents = {p.name: _notebook_cells(p) for p in NOTEBOOKS}
    for name, (_, check) in EXAMPLES.items():
        if _found(name):  # else its test fails on the missing example
            documents[f"README:{name}"] = [_example(name), check]
    spec = work / "documents.json"
    spec.write_text(json.dumps(documents))
    out = work / "report.json"
    res = subprocess.run(
        [sys.executable, "-c", RUNNER, str(out), str(spec)],
        cwd=work,
        env=dict(os.environ, MPLBACKEND="Agg"),
        capture_output=True,
        text=True,
        timeout=900 * len(documents),
    )
    report = json.loads(out.read_text()) if out.exists() else {}
    return report, res


def _assert_ran(name, docs_report):
    report, res = docs_report
    assert report.get(name) == "OK", (report.get(name), res.stdout[-3000:], res.stderr[-3000:])


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_executes(path, docs_report):
    _assert_ran(path.name, docs_report)


@pytest.mark.parametrize("name", list(EXAMPLES))
def test_readme_example_runs(name, docs_report):
    """The README's examples run as printed, and do what the text around them says."""
    block = _example(name)
    if name == "bring_your_own_system":
        assert len(block.strip().splitlines()) < 40
    if name == "quick":
        assert "lj.simulate" in block and "lj.reference" in block
    _assert_ran(f"README:{name}", docs_report)


def test_readme_all_cores_example_runs_sharded():
    """The all-cores snippet, in a fresh interpreter (the device count is fixed when JAX starts): on 2
    host devices lj.shard_vmap splits a batch of 7 (padded to 8) and returns every member's
    trajectory, equal to an unsharded vmap of the same members."""
    blocks = [b for b in BLOCKS if "shard_vmap" in b]
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
