"""The README's quick example runs as printed."""

import pathlib
import re


def test_readme_quick_example_runs():
    text = (pathlib.Path(__file__).parent.parent / "README.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, re.S)
    assert blocks, "README has no python example"
    namespace: dict = {}
    exec(compile(blocks[0], "README.md", "exec"), namespace)  # noqa: S102
    assert not bool(namespace["traj"].failed)
    assert float(namespace["jnp"].linalg.norm(namespace["traj"].q[-1, :2] - namespace["ref"].q[-1, :2])) < 1e-3
