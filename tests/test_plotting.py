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
    labels = ["RDP2", "RDP4", "RDP6", "RDP6 cayley", "RDP8", "rdp_cayley", "RK2", "RK4", "DLA", "GNI"]
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


def test_animation_scales_the_vehicle_as_plot_paths_does(tmp_path, monkeypatch):
    """By default the vehicle is drawn at plot_paths' automatic scale (12% of the paths' extent,
    at most true size): over a 1 m path the 1.15 m board is drawn far smaller, over a 40 m path
    at true size; ``scale=1.0`` draws true size."""
    import ldap_jax.plotting._animate as anim
    from ldap_jax.plotting._paths import auto_scale

    scales = []
    drawn = anim.vehicle_parts

    def recording(system, q, *, scale=1.0, vehicle=None):
        scales.append(scale)
        return drawn(system, q, scale=scale, vehicle=vehicle)

    monkeypatch.setattr(anim, "vehicle_parts", recording)
    sb = lj.Snakeboard()
    t, q = _circle(9)  # a path of about 1.4 m by 1.7 m
    animate(q, sb, tmp_path / "small.gif", t=t)
    expected = auto_scale(sb, q[:, :2])
    assert expected < 0.3 and set(scales) == {expected}
    scales.clear()
    big = q.copy()
    big[:, :2] *= 20.0
    animate(big, sb, tmp_path / "big.gif", t=t)
    assert set(scales) == {1.0}
    scales.clear()
    animate(q, sb, tmp_path / "true.gif", t=t, scale=1.0)
    assert set(scales) == {1.0}
    with pytest.raises(ValueError, match="'scale'"):
        animate(big, sb, tmp_path / "bad.gif", t=t, scale="large")


def test_work_precision_takes_study_rows_with_runtimes_in_seconds():
    """Study rows (runtime in microseconds) plug into plot_work_precision as they are: one curve
    per method, the runtime axis in seconds, every point labelled with its N."""
    from ldap_jax.plotting import study_curves

    rows = [
        dict(model="car", duration=10.0, method=m, n_steps=n, runtime_us=us, final_error_median=e)
        for m, pts in {"rdp": [(500, 80.0, 1e-4), (250, 40.0, 4e-4)], "rk4": [(250, 60.0, 1e-7)]}.items()
        for n, us, e in pts
    ]
    fig = plot_work_precision(rows)
    ax = fig.axes[0]
    lines = {line.get_label(): line for line in ax.get_lines()}
    np.testing.assert_allclose(lines["rdp"].get_xdata(), [40e-6, 80e-6])  # sorted by runtime
    np.testing.assert_allclose(lines["rdp"].get_ydata(), [4e-4, 1e-4])
    np.testing.assert_allclose(lines["rk4"].get_xdata(), [60e-6])
    assert "[s]" in ax.get_xlabel() and "final error median [m]" == ax.get_ylabel()
    assert sorted(t.get_text() for t in ax.texts) == ["N=250", "N=250", "N=500"]
    # rows of several models and durations: each curve names its case
    curves, notes = study_curves(rows + [dict(rows[0], model="snakeboard")])
    assert set(curves) == {"car, 10 s: rdp", "car, 10 s: rk4", "snakeboard, 10 s: rdp"}
    assert notes["snakeboard, 10 s: rdp"] == ["N=500"]
    with pytest.raises(ValueError, match="runtime_us"):
        plot_work_precision([{"model": "car", "duration": 10.0, "method": "rdp", "n_steps": 1}])
