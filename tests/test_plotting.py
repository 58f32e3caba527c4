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


# ----------------------------------------------------------------------------- from an audit
# Trajectories built from NumPy arrays (no rollout compiled): a circle of the car's dimension.
def _traj(n=11, *, t0=0.0, dt=0.1, failed_at=None, e0=1.0, work0=0.0, dtype=np.float64):
    t, q = _circle(n)
    t = (t0 + dt * np.arange(n)).astype(dtype)
    qdot = np.gradient(q, axis=0) if n > 1 else np.zeros_like(q)
    energy = e0 + 1e-6 * np.sin(np.arange(n))
    work = work0 + 1e-7 * np.arange(n)
    result = lj.RESULTS.successful
    if failed_at is not None:
        q[failed_at:] = qdot[failed_at:] = energy[failed_at:] = work[failed_at:] = np.nan
        result = lj.RESULTS.singular
    return lj.Trajectory(
        t=t,
        q=q.astype(dtype),
        qdot=qdot.astype(dtype),
        energy=energy.astype(dtype),
        work=work.astype(dtype),
        momentum=np.zeros((n, 1), dtype),
        constraint_residual=np.zeros(n, dtype),
        step_residual=np.zeros(n, dtype),
        converged=np.ones(n, bool),
        result=result,
        failure_index=np.array(n - 1 if failed_at is None else failed_at),
    )


def _solution(t, q):
    return lj.Solution(t=t, q=q, qdot=np.zeros_like(q), result=lj.RESULTS.successful, num_steps=np.array(1))


def _markers(ax, marker):
    return [line for line in ax.get_lines() if line.get_marker() == marker]


def _legend(ax):
    return [text.get_text() for text in ax.get_legend().get_texts()]


def test_two_point_curves_are_read_in_their_documented_form():
    """A list of two (h, error) pairs is two points (fitted order 2, not 1.2 from reading it
    transposed), a tuple of two lists is (xs, ys); the ambiguous 2 x 2 forms are refused."""
    fig = plot_convergence({"RDP": [(0.2, 1e-2), (0.1, 2.5e-3)]}, slopes=(2,))
    line = fig.axes[0].get_lines()[0]
    np.testing.assert_allclose(line.get_xdata(), [0.1, 0.2])
    np.testing.assert_allclose(line.get_ydata(), [2.5e-3, 1e-2])
    assert "fitted order 2.0" in line.get_label()
    fig = plot_convergence({"RDP": ([0.2, 0.1], [1e-2, 2.5e-3])}, slopes=(2,))  # (steps, errors)
    np.testing.assert_allclose(fig.axes[0].get_lines()[0].get_ydata(), [2.5e-3, 1e-2])
    fig = plot_work_precision({"RDP": ([1e-4, 2e-4], [5e-3, 1.2e-3])})  # (seconds, errors)
    line = fig.axes[0].get_lines()[0]
    np.testing.assert_allclose(line.get_xdata(), [1e-4, 2e-4])
    np.testing.assert_allclose(line.get_ydata(), [5e-3, 1.2e-3])
    fig = plot_work_precision({"RDP": [[1e-4, 5e-3], [2e-4, 1.2e-3]]})  # a list of pairs
    np.testing.assert_allclose(fig.axes[0].get_lines()[0].get_ydata(), [5e-3, 1.2e-3])
    h = [0.1, 0.05, 0.025]  # more points: either form
    for value in ((h, [1e-2, 2.5e-3, 6.25e-4]), list(zip(h, [1e-2, 2.5e-3, 6.25e-4]))):
        assert "fitted order 2.0" in plot_convergence({"a": value}).axes[0].get_lines()[0].get_label()
    for value in (((0.2, 1e-2), (0.1, 2.5e-3)), np.array([[0.2, 1e-2], [0.1, 2.5e-3]])):
        with pytest.raises(ValueError, match="'RDP'.*ambiguous"):
            plot_convergence({"RDP": value})
        with pytest.raises(ValueError, match="'RDP'.*ambiguous"):
            plot_work_precision({"RDP": value})


def test_batches_are_refused_naming_the_argument_and_how_to_pick_a_member(tmp_path):
    import jax

    from ldap_jax import plotting

    tr = _traj()
    batch = jax.tree_util.tree_map(lambda *x: np.stack(x), tr, tr, tr)
    tail = r".*batch.*jax\.tree_util\.tree_map\(lambda x: x\[i\], traj\)"
    pick = "'batch'" + tail
    car = lj.Car()
    _, ax = matplotlib.pyplot.subplots()
    with pytest.raises(ValueError, match=pick):
        plotting.plot_energy_error({"batch": batch})
    with pytest.raises(ValueError, match=pick):
        plotting.plot_diagnostics({"batch": batch})
    with pytest.raises(ValueError, match="'traj'" + tail):
        plotting.plot_shape_loop(batch, car)
    with pytest.raises(ValueError, match=pick):
        plotting.plot_paths(ax, car, {"batch": batch})
    with pytest.raises(ValueError, match=pick):
        plotting.plot_position_error(ax, tr, {"batch": batch})
    with pytest.raises(ValueError, match=pick):
        animate({"batch": batch}, car, tmp_path / "b.gif")
    matplotlib.pyplot.close("all")


def test_a_single_saved_node_is_no_start_and_curves_over_time_need_two_nodes():
    """save="final" (one node): no "start" marker at the final pose; the curves over time refuse
    it. A first node after the run's start (nonzero work there) is not called "start" either."""
    from ldap_jax import plotting

    car = lj.Car()
    full = _traj()
    final = _traj(1, t0=1.0)
    final = lj.Trajectory(**{**vars(final), "q": full.q[-1:], "qdot": full.qdot[-1:]})
    _, ax = matplotlib.pyplot.subplots()
    plotting.plot_paths(ax, car, {"final": final, "full": full})
    (start,) = _markers(ax, "o")
    np.testing.assert_allclose([start.get_xdata()[0], start.get_ydata()[0]], full.q[0, :2])
    _, ax = matplotlib.pyplot.subplots()
    plotting.plot_paths(ax, car, {"final": final})
    assert not _markers(ax, "o") and "start" not in _legend(ax)
    for call in (
        lambda: plotting.plot_position_error(ax, _solution(full.t, full.q), {"final": final}),
        lambda: plotting.plot_energy_error({"final": final}),
        lambda: plotting.plot_diagnostics({"final": final}),
        lambda: plotting.plot_shape_loop(final, car),
    ):
        with pytest.raises(ValueError, match="'(final|traj)'.*needs at least two saved nodes"):
            call()
    later = _traj(t0=0.5, work0=0.3)  # e.g. save=[5, 6, ...]: the work since the start is not 0
    fig = plotting.plot_shape_loop(later, car)
    labels = [text for ax in fig.axes if ax.get_legend() for text in _legend(ax)]
    assert "start" not in labels and any("first saved node" in lab for lab in labels)
    _, ax = matplotlib.pyplot.subplots()
    plotting.plot_paths(ax, car, {"later": later, "full": full})
    np.testing.assert_allclose(_markers(ax, "o")[0].get_xdata(), full.q[0, :1])
    matplotlib.pyplot.close("all")


def test_a_failed_run_is_marked_where_it_failed_and_its_envelope_stops_there():
    from ldap_jax import plotting
    from ldap_jax.plotting._common import running_max

    np.testing.assert_array_equal(
        running_max(np.array([np.nan, 1, 3, 2, np.nan, 5])), [np.nan, 1, 3, 3] + [np.nan] * 2
    )
    car = lj.Car()
    failed = _traj(failed_at=6)
    with pytest.warns(UserWarning, match="failed"):
        fig = plotting.plot_energy_error({"failed": failed})
    (thick,) = [line for line in fig.axes[0].get_lines() if line.get_label() == "failed"]
    drawn = np.asarray(thick.get_xdata())[np.isfinite(thick.get_ydata())]
    assert drawn.max() < failed.t[6]
    _, ax = matplotlib.pyplot.subplots()
    with pytest.warns(UserWarning, match="failed"):
        plotting.plot_paths(ax, car, {"failed": failed, "ok": _traj()})
    (cross,) = _markers(ax, "x")
    np.testing.assert_allclose([cross.get_xdata()[0], cross.get_ydata()[0]], failed.q[5, :2])
    assert len(_markers(ax, "s")) == 1  # the end of "ok" only
    assert "failed (singular)" in _legend(ax)
    with pytest.warns(UserWarning, match="failed"):
        fig = plotting.plot_shape_loop(failed, car)
    path_legend = _legend(fig.axes[2])
    assert "failed (singular)" in path_legend and "end" not in path_legend
    matplotlib.pyplot.close("all")


def test_labels_matching_one_pattern_get_distinguishable_curves():
    from ldap_jax.plotting._common import styles_for

    labels = ["RDP h=0.1", "RDP h=0.05", "RDP h=0.025", "RK4", "RK4 float32"]
    for markers in (False, True):
        styles = styles_for(labels, markers=markers)
        seen = {
            (matplotlib.colors.to_hex(s["color"]), str(s["ls"]), s.get("marker")) for s in styles.values()
        }
        assert len(seen) == len(labels)
    assert styles_for(labels)["RDP h=0.1"] == style_for("RDP h=0.1")  # the first keeps its style
    h = np.array([0.1, 0.05])
    fig = plot_convergence({"RDP h=0.1": (h, h**2), "RDP h=0.05": (h, 2 * h**2)}, slopes=())
    a, b = fig.axes[0].get_lines()[:2]
    assert (a.get_color(), a.get_linestyle()) != (b.get_color(), b.get_linestyle())


def test_float32_times_match_a_float64_reference_on_the_same_grid():
    from ldap_jax import plotting

    n = 51
    t64 = np.linspace(0.0, 10.0, n)
    t32 = np.float32(0.0) + np.float32(0.2) * np.arange(n, dtype=np.float32)  # as a float32 run's nodes
    assert np.max(np.abs(t32 - t64)) > 1e-7  # beyond the former 1e-9 * 10 s
    f32 = lj.Trajectory(**{**vars(_traj(n, dt=0.2, dtype=np.float32)), "t": t32})
    ref = _solution(t64, np.asarray(f32.q, float) + 1e-3)
    _, ax = matplotlib.pyplot.subplots()
    plotting.plot_position_error(ax, ref, {"RDP f32": f32})
    (line,) = ax.get_lines()
    np.testing.assert_allclose(line.get_ydata(), 1e-3 * np.sqrt(2), rtol=1e-4)
    with pytest.raises(ValueError, match="not among the reference's"):  # another grid still refused
        plotting.plot_position_error(ax, _solution(t64 + 0.1, ref.q), {"RDP f32": f32})
    matplotlib.pyplot.close("all")


def test_relative_energy_error_from_rest_is_refused():
    from ldap_jax import plotting

    with pytest.raises(ValueError, match=r"'rest'.*undefined at E0 = 0.*relative=False"):
        plotting.plot_energy_error({"rest": _traj(e0=0.0)}, relative=True)
    fig = plotting.plot_energy_error({"rest": _traj(e0=0.0)})  # in joules it draws
    assert np.isfinite(fig.axes[0].get_lines()[1].get_ydata()).any()
    matplotlib.pyplot.close("all")


def test_plausible_misuse_names_the_argument(tmp_path, monkeypatch):
    import ldap_jax.plotting._animate as anim
    from ldap_jax import plotting

    car = lj.Car()
    tr = _traj()
    ref = _solution(tr.t, tr.q)
    _, ax = matplotlib.pyplot.subplots()
    cases = [
        (TypeError, "'trajectories' must be a mapping", lambda: plotting.plot_position_error(ax, ref, tr)),
        (TypeError, "'trajectories' must be a mapping", lambda: plotting.plot_diagnostics(tr)),
        (TypeError, "'trajs' must be a mapping", lambda: plotting.plot_energy_error(tr)),
        (
            TypeError,
            "'references' must be \\(system, Solution\\)",
            lambda: plotting.plot_diagnostics({"a": tr}, references=ref),
        ),
        (
            TypeError,
            "'references' must be",
            lambda: plotting.plot_diagnostics({"a": tr}, references=(ref, car)),
        ),
        (
            ValueError,
            "'references' has \\['car'\\]",
            lambda: plotting.plot_diagnostics({"a": tr}, references={"car": (car, ref)}),
        ),
        (TypeError, "'results' must be a mapping", lambda: plot_convergence([(0.1, 1e-3), (0.2, 4e-3)])),
        (
            TypeError,
            "labels must be strings, got 1",
            lambda: plot_convergence({1: ([0.1, 0.2], [1e-3, 4e-3])}),
        ),
        (TypeError, "'paths': labels must be strings", lambda: plotting.plot_paths(ax, car, {1: tr})),
        (
            TypeError,
            "'traj' must be a Trajectory.*task.rollout",
            lambda: plotting.plot_shape_loop(_control_solution(), car),
        ),
        (ValueError, "'scale'", lambda: plotting.plot_paths(ax, car, {"a": tr}, scale=-1.0)),
        (
            ValueError,
            "'annotations' 'R': 1 texts for 2 points",
            lambda: plot_work_precision({"R": [(1e-4, 5e-3), (2e-4, 1e-3)]}, annotations={"R": ["a"]}),
        ),
        (
            ValueError,
            "'converged'",
            lambda: plotting.plot_gait_family([1, 2, 3], [1, 2, 3], [1, 2, 3], converged=[True, False]),
        ),
        (
            TypeError,
            "'system'.*animate\\(trajectory, system, path\\)",
            lambda: animate(tr, str(tmp_path / "x.gif"), car),
        ),
        (ValueError, "'max_frames'", lambda: animate(tr, car, tmp_path / "x.gif", max_frames=0)),
    ]
    for error, match, call in cases:
        with pytest.raises(error, match=match):
            call()
    # the file name is checked before any frame is drawn
    monkeypatch.setattr(anim, "frame_indices", lambda *a: pytest.fail("frames drawn before the check"))
    with pytest.raises(ValueError, match="'path' must end in .gif"):
        animate(tr, car, tmp_path / "x.mp4", every=10)
    monkeypatch.undo()
    path = animate(tr, car, tmp_path / "x.gif", every=np.int64(5))  # NumPy integers are integers
    with Image.open(path) as gif:
        assert gif.n_frames == len(frame_indices(11, 5))
    matplotlib.pyplot.close("all")


def _control_solution():
    """Something shaped like an lc.Solution (params, no t/q) without solving one."""

    class Solution:
        params = np.zeros((3, 2))
        converged = True

    return Solution()


def test_gait_family_axes_have_units():
    from ldap_jax.plotting import plot_gait_family

    fig = plot_gait_family([0.06, 0.09, 0.12], [0.2, 0.24, 0.26], [1.0, 1.5, 2.0])
    ax0, ax1 = fig.axes[:2]
    assert ax0.get_xlabel() == "effort per cycle [(scaled controls)$^2$ s]"
    assert ax1.get_ylabel() == "displacement per unit effort [m / ((scaled controls)$^2$ s)]"
    fig = plot_gait_family([1.0, 2.0], [0.1, 0.2], [1.0, 1.0], displacement_label="rotation per cycle [rad]")
    assert fig.axes[1].get_ylabel().startswith("displacement per unit effort [rad / ")
    matplotlib.pyplot.close("all")


def test_the_guide_names_every_figure_and_says_what_the_code_does():
    """docs/guide/plotting.md: every figure function in its table; the automatic scale as drawn
    (a short path shows the vehicle smaller than true size); only notebooks that use the package."""
    import json
    import pathlib

    from ldap_jax import plotting
    from ldap_jax.plotting._paths import auto_scale

    root = pathlib.Path(__file__).parent.parent
    guide = (root / "docs" / "guide" / "plotting.md").read_text()
    table = [line for line in guide.splitlines() if line.startswith("| `")]
    for name in plotting.__all__:
        if name.startswith(("plot_", "animate")):
            assert any(f"`{name}(" in line for line in table), name
    sb = lj.Snakeboard(m=1.0, l=0.5, I=0.05, J=0.02)
    assert auto_scale(sb, np.array([[0.0, 0.0], [0.5, 0.0]])) < 0.1
    assert auto_scale(sb, np.array([[0.0, 0.0], [10.0, 0.0]])) == 1.0
    assert "short path shows the vehicle at true" not in " ".join(guide.split())
    for number in re_notebooks(guide):
        (nb,) = (root / "notebooks").glob(f"{number}_*.ipynb")
        assert "ldap_jax.plotting" in json.dumps(json.loads(nb.read_text())["cells"]), nb.name


def re_notebooks(text):
    import re

    match = re.search(r"notebooks? ([\d ,and]+) shows?", " ".join(text.split()))
    assert match, "the guide names the notebooks that show the figures"
    return re.findall(r"\d\d", match.group(1))
