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
    text = (pathlib.Path(__file__).parent.parent / "README.md").read_text()
    blocks = [b for b in re.findall(r"```python\n(.*?)```", text, re.S) if "lc.optimize" in b]
    assert blocks
    namespace: dict = {}
    exec(compile(blocks[0], "README.md", "exec"), namespace)  # noqa: S102
    assert namespace["replay"]["final_position_error"] < 0.02
