"""The documentation runs as printed: every notebook in notebooks/, the README's quick example and
every example of the guide (docs/guide/*.md).

All of them run in one child process, one after the other, each in a fresh namespace, as a user's
session would run them (JAX's default numerics, not the suite's strict promotion). A guide page's
examples run in order in one namespace (a later example may use an earlier one's names), then the
test's checks for that page; a notebook's cells are likewise followed by its checks where it
computes a result that a test asserts on (the test worker would compute it again). Running
everything in one process lets the examples reuse the notebooks' compiled programs: measured at
the suite's code generation, the notebooks and four README examples in 73 s, against 64 s for the
notebooks alone and 22 s for the examples run in a test worker. Examples that expose one device
per core (``lj.use_cpu_cores()``) need a process of their own (the device count is fixed when JAX
starts) and run in their own test.

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
GUIDE = sorted((ROOT / "docs" / "guide").glob("*.md"))
#: a block that calls this needs a process of its own
ALL_CORES = "lj.use_cpu_cores()"


def _python_blocks(text: str) -> list[str]:
    return re.findall(r"```python\n(.*?)```", text, re.S)


BLOCKS = _python_blocks(README)

# README examples run in the child: (name, how the block is found, the checks run after it in its
# namespace). The checks are the test's, not the README's: they assert what the text promises.
EXAMPLES = {
    "quick": (
        lambda b: b == BLOCKS[0],
        """
assert not bool(traj.failed)
assert float(jnp.linalg.norm(traj.q[-1, :2] - ref.q[-1, :2])) < 1e-5  # order 4 at h = 0.1 s
assert bool(jnp.all(jnp.isfinite(jax.grad(distance)(ctl.amplitude))))
""",
    ),
    "control": (
        lambda b: "lc.drive_gait()" in b,
        """
import numpy as np
assert bool(sol.converged) and float(sol.max_violation) < 1e-9
assert -float(sol.cost) > 0.262  # the drive gait's distance per cycle (IPOPT's best: 0.2620924)
assert np.all(cycles["return_error"] < 1e-5) and cycles["stability"] == "neutrally stable"
""",
    ),
}

# The checks run after a guide page's examples, in their namespace (pages without an entry only
# have to run). They assert what the page's text says about its examples.
GUIDE_CHECKS = {
    "simulate.md": """
import equinox as eqx
import numpy as np
assert not bool(traj.failed) and traj.q.shape == (101, 5)
assert float(jnp.linalg.norm(traj.q[-1, :2] - ref.q[-1, :2])) < 1e-1
assert int(jnp.sum(batch.failed)) == 0 and grad.shape == ctl.amplitude.shape
assert bool(jnp.all(jnp.isfinite(grad)))
assert not bool(driven.failed) and abs(float(driven.q[-1, 4])) < 1e-3  # steered back
# the discrete dynamics: every node finite, and a method compiled alone is the same step
assert xs.shape[0] == 101 and bool(jnp.all(jnp.isfinite(xs)))
stepped = eqx.filter_jit(dyn.step)(xs[7], us[7], us[8])
np.testing.assert_allclose(np.asarray(stepped), np.asarray(xs[8]), rtol=1e-13, atol=1e-13)
# your own system: the sleigh against its reference, its energy conserved
assert not bool(glide.failed)
assert float(jnp.linalg.norm(glide.q[-1, :2] - glide_ref.q[-1, :2])) < 1e-2
assert float(jnp.ptp(glide.energy)) < 1e-8
""",
    "study.md": """
assert len(rows) == 6 and all(r["failures"] == 0 for r in rows)
by = {(r["method"], r["n_steps"]): r for r in rows}
# second order: halving h divides RDP's error by about 4; orders 4 beat order 2 at equal N
assert 3.0 < by["rdp", 100]["final_error_median"] / by["rdp", 200]["final_error_median"] < 5.0
assert by["rdp4", 100]["final_error_median"] < 1e-3 * by["rdp", 100]["final_error_median"]
assert len(again) == len(rows) and all(os.path.exists(p) for p in paths)
# the work-precision figure's x axis is in seconds: runtime_us / 1e6
line = next(l for l in fig.axes[0].get_lines() if "rdp4" in l.get_label())
want = sorted(r["runtime_us"] * 1e-6 for r in rows if r["method"] == "rdp4")
assert len(want) == 2 and all(abs(a / b - 1) < 1e-12 for a, b in zip(sorted(line.get_xdata()), want))
""",
    # the path constraint: the free path crossed the disc; the detour costs effort and holds at
    # the nodes on the model (to 1e-8 m inside), on the reference to the model error (1e-6 m), and
    # the goal is still reached on the reference to 1e-6 m
    "control.md": """
assert bool(sol.converged) and rp["final_position_error"] < 1e-6
assert bool(around.converged) and float(around.cost) > float(sol.cost)
closest = np.min(np.linalg.norm(q[:, :2] - np.asarray(center), axis=1))
assert closest >= 0.05 - 1e-8
assert np.min(np.linalg.norm(q_free[:, :2] - np.asarray(center), axis=1)) < 0.05
rp_around = lc.replay(task, around.params)
assert np.min(np.linalg.norm(rp_around["q_ref"][:, :2] - np.asarray(center), axis=1)) >= 0.05 - 1e-6
assert rp_around["final_position_error"] < 1e-6
assert bool(gait.converged) and np.all(cycles["return_error"] < 1e-5)
assert tracker.n_channels == 2 and np.isfinite(float(jax.grad(optimal_effort)(1.0)))
""",
    # the plotting guide's convergence figure: the orders fitted to the errors the page itself
    # computed (RDP 2, RK4 4) must come out within 10% of the methods' orders, so a figure drawn
    # from a broken integrator or a mislabelled curve fails here; and every figure file exists
    "plotting.md": """
assert 1.8 < plotting.fitted_order(steps, errors["RDP"], floor=1e-11) < 2.2
assert 3.6 < plotting.fitted_order(steps, errors["RK4"], floor=1e-11) < 4.4
for name in ("paths.png", "diagnostics.png", "convergence.png", "work_precision.png", "gait_loop.png"):
    assert os.path.getsize(os.path.join(folder, name)) > 0, name
assert gif.endswith("gait.gif") and os.path.getsize(gif) > 0
""",
}


# The checks run after a notebook's cells, in its namespace: what a test would otherwise compute
# again in a worker, asserted on the notebook's own results.
NOTEBOOK_CHECKS = {
    # The roller racer with rolling resistance (an ``lj.System`` with a dissipation function, the
    # general RDP step) through ``lc.make_gait`` (``lc.racer_gait()``): converged from its default
    # guess with its constraints met to 1e-9; 3 cycles on the reference return to within 1e-5 of
    # the model's orbit and move as the model's cycle does to 1e-6; every Floquet multiplier lies
    # inside the unit circle (asymptotically stable), and from a perturbed start the cycle map
    # returns to the orbit, the error shrinking every cycle.
    "06_roller_racer.ipynb": """
import equinox as eqx
assert bool(sol_r.converged), lc.SOLVER_RESULTS[sol_r.result]
assert float(sol_r.max_violation) <= 1e-9
assert -float(sol_r.cost) > 0.5  # metres per cycle
assert rp_r["reference_result"] == lj.RESULTS.successful
assert rp_r["model_return_error"] <= 1e-9
assert np.all(rp_r["return_error"] < 1e-5), rp_r["return_error"]
assert np.all(rp_r["displacement_error"] < 1e-6), rp_r["displacement_error"]
assert rp_r["stability"] == "asymptotically stable", rp_r["multipliers"]
assert np.max(np.abs(rp_r["multipliers"])) < 0.5
z0, _ = lc.monodromy(racer_task, sol_r.params)
P = eqx.filter_jit(lambda z: lc.cycle_map(racer_task, sol_r.params, z))
z, errors = np.asarray(z0) + np.array([0.05, -0.05, 0.05]), []
for _ in range(4):
    z = np.asarray(P(z))
    errors.append(np.linalg.norm(z - np.asarray(z0)))
assert np.all(np.diff(errors) < 0) and errors[-1] < 1e-4, errors
""",
}


#: The child process that runs the documents. It collects garbage as the test workers do
#: (tests/conftest.py): the young generation every 50000 allocations, not 700, so the full
#: collections do not walk JAX's caches dozens of times (notebooks 05 and 06 in one process, cold:
#: 5.6 s of collection -> 0.7 s).
RUNNER = """
import gc
import json
import sys
import traceback

gc.set_threshold(50_000, 20, 100)

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


def _guide_cells(path: pathlib.Path) -> list[str]:
    """A guide page's examples in order, without those that need a process of their own."""
    return [b for b in _python_blocks(path.read_text()) if ALL_CORES not in b]


#: The documents that solve what tests/conftest.py's chain of tests solves first (the drive gait,
#: parallel parking and the U-turn at N = 120): they run in a child process of their own after
#: those tests, on the same worker, and read their compiled programs from the shared cache. The
#: other documents run in another child, which the other worker can run meanwhile.
CHAIN = {
    "03_optimal_control.ipynb",
    "05_gaits.ipynb",
    "06_roller_racer.ipynb",
    "README:control",
    "guide:control.md",
}
CHAIN_GROUP = "gaits"  # tests/conftest.py's _DOCS_CHAIN


def _documents() -> dict[str, list[str]]:
    """Every notebook, README example and guide page: its code cells, then its checks."""
    documents = {p.name: _notebook_cells(p) + [NOTEBOOK_CHECKS.get(p.name, "")] for p in NOTEBOOKS}
    for name, (_, check) in EXAMPLES.items():
        if _found(name):  # else its test fails on the missing example
            documents[f"README:{name}"] = [_example(name), check]
    for path in GUIDE:
        documents[f"guide:{path.name}"] = _guide_cells(path) + [GUIDE_CHECKS.get(path.name, "")]
    return documents


def _run_documents(work: pathlib.Path, documents: dict[str, list[str]]):
    """Runs the documents, each with its checks, in one child process in the temporary working
    directory ``work`` (the files the notebooks write, e.g. their animations, do not touch the
    checkout); returns the child's report (document -> "OK" or the failure) and its output."""
    spec = work / "documents.json"
    spec.write_text(json.dumps(documents))
    out = work / "report.json"
    res = subprocess.run(
        [sys.executable, "-c", RUNNER, str(out), str(spec)],
        cwd=work,
        env=_docs_env(),
        capture_output=True,
        text=True,
        timeout=900 * len(documents),
    )
    report = json.loads(out.read_text()) if out.exists() else {}
    return report, res


@pytest.fixture(scope="module")
def docs_report(tmp_path_factory):
    """The documents outside :data:`CHAIN`, in one child process."""
    documents = {k: v for k, v in _documents().items() if k not in CHAIN}
    return _run_documents(tmp_path_factory.mktemp("docs"), documents)


@pytest.fixture(scope="module")
def docs_chain_report(tmp_path_factory):
    """The documents of :data:`CHAIN`, in one child process."""
    documents = {k: v for k, v in _documents().items() if k in CHAIN}
    return _run_documents(tmp_path_factory.mktemp("docs_chain"), documents)


def _param(document: str, value, id: str):
    """A test's parameter for ``document``, in the xdist group of the child that runs it."""
    group = CHAIN_GROUP if document in CHAIN else "docs"
    return pytest.param(value, id=id, marks=pytest.mark.xdist_group(group))


def _docs_env() -> dict:
    """The child's environment: the notebooks' ``lj.enable_compilation_cache()`` uses the suite's
    cache folder (``$LDAP_JAX_CACHE``; conftest passes it as ``JAX_COMPILATION_CACHE_DIR``), so the
    documents share compiled and exported programs with the test workers (``lc.solve`` of the
    same problem structure: the programs a worker exported, see ``ldap_jax/control/_export.py``)
    instead of compiling into the user's cache."""
    env = dict(os.environ, MPLBACKEND="Agg")
    if env.get("JAX_COMPILATION_CACHE_DIR"):
        env["LDAP_JAX_CACHE"] = env["JAX_COMPILATION_CACHE_DIR"]
    return env


def _assert_ran(name, request):
    report, res = request.getfixturevalue("docs_chain_report" if name in CHAIN else "docs_report")
    assert report.get(name) == "OK", (report.get(name), res.stdout[-3000:], res.stderr[-3000:])


@pytest.mark.parametrize("path", [_param(p.name, p, p.name) for p in NOTEBOOKS])
def test_notebook_executes(path, request):
    _assert_ran(path.name, request)


@pytest.mark.parametrize("name", [_param(f"README:{n}", n, n) for n in EXAMPLES])
def test_readme_example_runs(name, request):
    """The README's examples run as printed, and do what the text around them says."""
    block = _example(name)
    if name == "quick":
        assert "lj.simulate" in block and "lj.reference" in block
    _assert_ran(f"README:{name}", request)


@pytest.mark.parametrize("path", [_param(f"guide:{p.name}", p, p.name) for p in GUIDE])
def test_guide_examples_run(path, request):
    """Every example of every guide page runs as printed (in order, in one namespace) and does what
    the page says (GUIDE_CHECKS)."""
    assert _python_blocks(path.read_text()), f"{path.name} has no example"
    _assert_ran(f"guide:{path.name}", request)


def test_guide_pages_have_checks():
    """The four guide pages the README links to exist, each with checks here."""
    names = {p.name for p in GUIDE}
    assert {"simulate.md", "control.md", "study.md", "plotting.md"} <= names, names
    assert set(GUIDE_CHECKS) <= names
    assert set(NOTEBOOK_CHECKS) <= {p.name for p in NOTEBOOKS}


def test_readme_is_short_and_links_exist():
    """The README teaches in at most 250 lines, and the links of the README, the guide and the
    results and development pages to files in the repository resolve."""
    assert len(README.splitlines()) <= 250, len(README.splitlines())
    pages = [ROOT / "README.md", ROOT / "docs" / "results.md", ROOT / "docs" / "development.md", *GUIDE]
    missing = []
    for page in pages:
        for target in re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", page.read_text()):
            path = (page.parent / target).resolve()
            if "://" not in target and not path.exists():
                missing.append(f"{page.relative_to(ROOT)}: {target}")
    assert not missing, missing


def test_all_cores_example_runs_sharded():
    """The all-cores example of the simulate guide, in a fresh interpreter (the device count is
    fixed when JAX starts): on 2 host devices lj.shard_vmap splits a batch of 7 (padded to 8) and
    returns every member's trajectory, equal to an unsharded vmap of the same members."""
    guide = (ROOT / "docs" / "guide" / "simulate.md").read_text()
    blocks = [b for b in _python_blocks(guide) if ALL_CORES in b and "shard_vmap" in b]
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
