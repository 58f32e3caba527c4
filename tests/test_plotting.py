"""Figures and animations: a GIF per vehicle with the documented frame count, curve styles that
tell every method apart, and the figure helpers on plain arrays (no rollout is compiled here)."""

import matplotlib

matplotlib.use("Agg")
import numpy as np
import pytest
from PIL import Image

import ldap_jax as lj
from ldap_jax.plotting import animate, frame_indices, plot_convergence, plot_work_precision
from ldap_jax.plotting._common import is_reference, style_for


def _circle(n):
    t = np.linspace(0.0, 4.0, n)
    q = np.zeros((n, 5))
    q[:, 0], q[:, 1], q[:, 2] = np.cos(t) - 1.0, np.sin(t), t + np.pi / 2
    q[:, 4] = 0.2 * np.sin(t)
    return t, q


@pytest.mark.parametrize("system", [lj.Car(), lj.Snakeboard()], ids=["car", "snakeboard"])
def test_animation_writes_a_gif_with_one_frame_per_drawn_node(system, tmp_path):
    t, q = _circle(41)
    for every in (1, 3, 7):
        path = animate(
            q, system, tmp_path / f"a{every}.gif", t=t, every=every, goal=q[-1, :3], title="circle"
        )
        with Image.open(path) as gif:
            assert gif.n_frames == len(frame_indices(41, every))
    assert frame_indices(41, 7) == [0, 7, 14, 21, 28, 35, 40]
    # two trajectories with labels, capped by max_frames
    path = animate(
        [q, q + 0.01], system, tmp_path / "two.gif", t=t, labels=["model", "reference"], max_frames=10
    )
    with Image.open(path) as gif:
        assert gif.n_frames <= 11


def test_styles_tell_every_method_apart():
    labels = ["RDP2", "RDP4", "RDP6", "RDP6 cayley", "rdp_cayley", "RK2", "RK4", "DLA", "GNI"]
    labels += ["diffrax Tsit5", "diffrax Dopri8"]
    seen = {
        (s["color"], s["ls"], s.get("marker"))
        for s in (style_for(lb, i, markers=True) for i, lb in enumerate(labels))
    }
    assert len(seen) == len(labels)
    assert is_reference("reference replay (diffrax)") and not is_reference("RDP6 cayley")


def test_convergence_and_work_precision_figures_draw(tmp_path):
    h = np.array([0.1, 0.05, 0.025])
    fig = plot_convergence({"RDP": (h, 3.0 * h**2), "RK4": (h, h**4)}, slopes=(2, 4))
    fig.savefig(tmp_path / "c.png")
    fig = plot_work_precision({"RDP6": [(1e-4, 1e-6), (2e-4, 1e-8)], "RK4": [(1e-4, 1e-5), (2e-4, 1e-6)]})
    fig.savefig(tmp_path / "w.png")
    assert (tmp_path / "c.png").stat().st_size > 0 and (tmp_path / "w.png").stat().st_size > 0
