"""Every notebook in notebooks/ executes without error (so none can rot).

The notebooks run in a child process, cell by cell, in an IPython shell (what a Jupyter kernel
runs code in) without the kernel's ZeroMQ channels: with nbclient, shutting a kernel down on a
loaded machine could leave jupyter_client's heartbeat thread blocked on a socket whose peer had
exited, and the test hung for good (seen once in a full run). A hang here now ends in the timeout
as a failure.
"""

import json
import os
import pathlib
import shutil
import subprocess
import sys

import pytest

NOTEBOOKS = sorted((pathlib.Path(__file__).parent.parent / "notebooks").glob("*.ipynb"))

# All notebooks run in one child process, one after the other, each in a fresh namespace (the
# shell's reset) with its figures closed: a process per notebook paid the imports and JAX's start
# again, and compiled again what the notebooks share (measured: notebooks 01, 02 and 04 in 36.7 s
# as three processes, 31.1 s in one). A notebook that fails is reported and the next one still runs.
RUNNER = """
import json
import sys
import traceback

import nbformat
from IPython.core.interactiveshell import InteractiveShell

shell = InteractiveShell.instance(colors="nocolor")
report = {}
for path in sys.argv[2:]:
    shell.reset(new_session=True)
    nb = nbformat.read(path, as_version=4)
    status = "OK"
    for i, cell in enumerate(c for c in nb.cells if c.cell_type == "code"):
        try:
            result = shell.run_cell(cell.source)
        except BaseException:  # the shell itself failed
            status = f"code cell {i} failed: {traceback.format_exc()}"
            break
        if not result.success:
            err = result.error_in_exec or result.error_before_exec
            status = f"code cell {i} failed: {err!r}"
            break
    if "matplotlib.pyplot" in sys.modules:
        sys.modules["matplotlib.pyplot"].close("all")
    report[path] = status
    print(f"== {path}: {status}", flush=True)
with open(sys.argv[1], "w") as f:
    json.dump(report, f)
"""


@pytest.fixture(scope="module")
def notebook_report(tmp_path_factory):
    """Runs every notebook in one child process, on copies in a temporary working directory (the
    files the notebooks write, e.g. their animations, do not touch the checkout)."""
    work = tmp_path_factory.mktemp("notebooks")
    for path in NOTEBOOKS:
        shutil.copy(path, work / path.name)
    out = work / "report.json"
    env = dict(os.environ, MPLBACKEND="Agg")
    res = subprocess.run(
        [sys.executable, "-c", RUNNER, str(out), *(p.name for p in NOTEBOOKS)],
        cwd=work,
        env=env,
        capture_output=True,
        text=True,
        timeout=900 * len(NOTEBOOKS),
    )
    report = json.loads(out.read_text()) if out.exists() else {}
    return report, res


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_executes(path, notebook_report):
    report, res = notebook_report
    assert report.get(path.name) == "OK", (report.get(path.name), res.stdout[-3000:], res.stderr[-3000:])
