"""Every notebook in notebooks/ executes without error (so none can rot).

Each notebook runs in a child process, cell by cell, in an IPython shell (what a Jupyter kernel
runs code in) without the kernel's ZeroMQ channels: with nbclient, shutting a kernel down on a
loaded machine could leave jupyter_client's heartbeat thread blocked on a socket whose peer had
exited, and the test hung for good (seen once in a full run). A hang here now ends in the timeout
as a failure.
"""

import pathlib
import subprocess
import sys

import pytest

NOTEBOOKS = sorted((pathlib.Path(__file__).parent.parent / "notebooks").glob("*.ipynb"))

RUNNER = """
import sys

import nbformat
from IPython.core.interactiveshell import InteractiveShell

nb = nbformat.read(sys.argv[1], as_version=4)
shell = InteractiveShell.instance(colors="nocolor")
for i, cell in enumerate(c for c in nb.cells if c.cell_type == "code"):
    result = shell.run_cell(cell.source)
    if not result.success:
        print(f"code cell {i} failed", file=sys.stderr)
        sys.exit(1)
print("OK")
"""


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_executes(path, monkeypatch):
    monkeypatch.setenv("MPLBACKEND", "Agg")
    monkeypatch.setenv("LDAP_JAX_NOTEBOOK_TEST", "1")
    res = subprocess.run(
        [sys.executable, "-c", RUNNER, str(path)],
        cwd=path.parent,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert res.returncode == 0, (res.stdout[-3000:], res.stderr[-3000:])
    assert res.stdout.strip().endswith("OK")
