"""The Monte Carlo study (ldap_jax.study, scripts/sweep.py): its batched rollouts equal simulate
(save stride, integer result codes), a tiny study gives the CSV columns and finite numbers, and
the sharded run equals the unsharded one."""

import importlib.util
import os
import subprocess
import sys
import textwrap

import jax
import numpy as np
import pytest
from helpers import code, simulate_batch, systems

import ldap_jax as lj
from ldap_jax import study

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SYSTEMS = systems()


def test_maneuvers_reproducible_and_consistent():
    sb = SYSTEMS["snakeboard"]
    q0, qdot0, ctl = study.sample_maneuvers(sb, 16, seed=7)
    q0b, _, ctlb = study.sample_maneuvers(sb, 16, seed=7)
    np.testing.assert_array_equal(q0, q0b)
    np.testing.assert_array_equal(ctl.amplitude, ctlb.amplitude)
    # on the constraints, steering rate zero at t = 0, steering torque consistent with phidot(0)
    res = jax.vmap(sb.constraint_residual)(q0, qdot0)
    q0, qdot0, phase = (np.asarray(x) for x in (q0, qdot0, ctl.phase))  # host copies
    assert float(np.max(np.asarray(res))) < 1e-13
    assert float(np.max(np.abs(qdot0[:, 4]))) == 0.0
    assert float(np.max(np.abs(np.cos(phase[:, 1, 0])))) < 1e-15
    assert float(np.max(np.abs(q0[:, 4]))) < 1.0  # |phi(0)| <= |phi_c| + b <= max_steer
    with pytest.raises(ValueError, match="'n'"):
        study.sample_maneuvers(sb, 0, seed=0)


@pytest.mark.parametrize("method", ["rdp", "dla"])
def test_batch_rollout_equals_simulate(method):
    """batch_rollout is simulate with save stride N / n_out (positions only); its integer codes
    are the trajectories' result codes."""
    sb = SYSTEMS["snakeboard"]
    man = study.sample_maneuvers(sb, 3, seed=1)
    integrator = study.make_integrator(method)
    q_out, codes, seconds = study.batch_rollout(sb, integrator, man, 4.0, 80, n_out=20)
    assert q_out.shape == (3, 21, 5) and codes.dtype.kind == "i" and np.isnan(seconds)
    traj = simulate_batch(sb, integrator, man, 4.0, 80, save=4)
    np.testing.assert_allclose(q_out, traj.q, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(codes, code(traj.result))
    np.testing.assert_array_equal(codes, 0)
    with pytest.raises(ValueError, match="'n_steps'"):
        study.batch_rollout(sb, integrator, man, 4.0, 80, n_out=30)


def test_batch_rollout_reports_failures_like_simulate():
    sb = SYSTEMS["snakeboard"]
    man = study.sample_maneuvers(sb, 8, seed=5)
    q_out, codes, _ = study.batch_rollout(sb, lj.DLA(), man, 60.0, 20, n_out=20)
    traj = simulate_batch(sb, lj.DLA(), man, 60.0, 20)
    np.testing.assert_array_equal(codes, code(traj.result))
    assert bool(np.any(codes != 0))  # h = 3 s: some runs fail, and are reported
    for i in range(8):
        assert (codes[i] == 0) == (code(traj.result)[i] == code(lj.RESULTS.successful))
        np.testing.assert_array_equal(np.isnan(q_out[i]), np.isnan(np.asarray(traj.q)[i]))


# The script's configuration below is a part of this study (the car, rdp and rk2, N = 20 and 40,
# 4 maneuvers of 2 s): on the same worker it reuses the study's compiled programs (measured: the
# script's test 4.8 s after other tests, 0.7 s after this one).
@pytest.mark.xdist_group("car_study")
def test_tiny_study(tmp_path):
    # one model (the study's code is the same for both; the snakeboard's maneuvers are checked above)
    config = study.StudyConfig(
        models=("car",),
        durations=(2.0,),
        methods=("rdp", "gni", "dla", "rk2"),
        resolutions=(20, 40),
        runs=4,
        repeats=1,
        reference_check=2,
    )
    assert config.output_nodes == 20
    rows = study.run_study(config)
    assert len(rows) == 4 * 2
    path = tmp_path / "sweep.csv"
    study.write_csv(rows, path)
    back = study.read_csv(path)
    assert list(back[0]) == list(study.CSV_COLUMNS)
    assert back == [{c: r[c] for c in study.CSV_COLUMNS} for r in rows]  # read back exactly
    assert {r["method"] for r in back} == {"rdp", "gni", "dla", "rk2"}
    for r in back:
        for col in study.CSV_COLUMNS:
            if col not in ("model", "method"):
                assert np.isfinite(r[col]), (col, r)
        assert r["failures"] == 0 and r["blowup"] == 0
        assert r["runtime_us"] > 0
        assert r["reference_error"] < 1e-8
        # second order methods at h = 0.05 over 2 s: small but nonzero errors
        assert 0 < r["final_error_median"] < 1e-2
    ratios = study.runtime_ratios(back)
    assert {r["ratio"] for r in ratios} == {"rdp/rk2", "gni/rdp", "dla/rdp"}
    assert all(np.isfinite(r["equal_n"]) for r in ratios)
    figs = study.plot_study(back, tmp_path)
    assert len(figs) == 1 and all(os.path.getsize(f) > 0 for f in figs)
    assert "| rdp |" in study.format_table(back)
    # an empty study still writes the header
    study.write_csv([], tmp_path / "empty.csv")
    assert (tmp_path / "empty.csv").read_text().splitlines() == [",".join(study.CSV_COLUMNS)]


@pytest.mark.xdist_group("car_study")
def test_a_point_is_checked_maneuver_by_maneuver():
    """``study.study_maneuvers`` gives the maneuvers a point ran: rolled out with ``lj.simulate``
    and compared with ``lj.reference`` (diffrax), their final errors give the row's mean, median
    and max to 1e-6 relative (the study's reference is a fine RK4 run, 1e-12 m apart). The timed
    program, compiled with XLA's defaults, gives the positions of the library's to 1e-12."""
    config = study.StudyConfig(
        models=("snakeboard", "car"), durations=(2.0,), methods=("rdp",), resolutions=(20,), runs=4, repeats=1
    )
    rows = study.run_study(config)
    for model in config.models:
        (row,) = [r for r in rows if r["model"] == model]
        q0, qdot0, ctl = study.study_maneuvers(config, model)
        system = study.MODELS[model]()
        final = []
        for i in range(config.runs):
            c = jax.tree_util.tree_map(lambda x, i=i: x[i], ctl)
            traj = lj.simulate(system, q0[i], qdot0[i], c, t_final=2.0, n_steps=20, save="final")
            ref = lj.reference(system, q0[i], qdot0[i], c, np.array([0.0, 2.0]))
            final.append(np.linalg.norm(np.asarray(traj.q)[-1, :2] - np.asarray(ref.q)[-1, :2]))
        for stat, value in (("mean", np.mean(final)), ("median", np.median(final)), ("max", np.max(final))):
            np.testing.assert_allclose(row[f"final_error_{stat}"], value, rtol=1e-6)
    with pytest.raises(ValueError, match="'model'"):
        study.study_maneuvers(config, "sleigh")
    mesh = study.device_mesh()
    man, _ = study.shard_batch(study.study_maneuvers(config, "car"), mesh)
    system, integrator = study.MODELS["car"](), study.make_integrator("rdp")
    fast, _ = study.rollout_nodes(system, integrator, man, 2.0, 20, n_out=20, mesh=mesh)
    plain, _ = study.rollout_nodes(system, integrator, man, 2.0, 20, n_out=20, mesh=mesh, xla_defaults=True)
    np.testing.assert_allclose(np.asarray(plain), np.asarray(fast), rtol=1e-12, atol=1e-12)


def test_resolutions_without_a_common_factor_warn():
    with pytest.warns(UserWarning, match="common factor"):
        config = study.StudyConfig(resolutions=(7, 11, 13))
    assert config.output_nodes == 1


def test_every_method_has_its_own_style_and_its_integrator():
    """The figures draw every method of study.METHODS in a style of its own, and each name builds
    the integrator it stands for (the compositions of order 4, 6 and 8 among them)."""
    from ldap_jax.study._report import STYLES

    styles = [STYLES[name] for name in study.METHODS]
    assert len(set(styles)) == len(styles)
    for name, order in (("rdp", 2), ("rdp4", 4), ("rdp6", 6), ("rdp8", 8)):
        assert study.make_integrator(name).order == order


def test_config_errors():
    with pytest.raises(ValueError, match="'methods'"):
        study.StudyConfig(methods=("rk5",))
    with pytest.raises(ValueError, match="'resolutions'"):
        study.StudyConfig(resolutions=(100, 150), n_out=100)
    with pytest.raises(ValueError, match="'method'"):
        study.make_integrator("euler")


SHARDED = textwrap.dedent(
    """
    import jax
    jax.config.update("jax_enable_x64", True)
    import numpy as np
    from ldap_jax import study
    assert len(jax.devices()) == 4, jax.devices()
    # the closed-form kernel, and an implicit method (a Newton loop per step: its iteration count
    # differs between the members each device holds)
    for model, method in (("snakeboard", "rdp"), ("car", "dla")):
        system = study.MODELS[model]()
        man = study.sample_maneuvers(system, 6, seed=3)  # 6: padded to 8 on 4 devices
        q4, c4, _ = study.batch_rollout(system, study.make_integrator(method), man, 3.0, 60, n_out=10)
        one = study.device_mesh(jax.devices()[:1])
        q1, c1, _ = study.batch_rollout(system, study.make_integrator(method), man, 3.0, 60, n_out=10,
                                         mesh=one)
        assert q4.shape == (6, 11, 5), q4.shape
        np.testing.assert_allclose(q4, q1, rtol=1e-13, atol=1e-13)
        np.testing.assert_array_equal(c4, c1)
    (sharded, n) = study.shard_batch(man, study.device_mesh())
    assert n == 6 and len(sharded[0].sharding.device_set) == 4 and sharded[0].shape[0] == 8
    # the same batch built by each device from its member indices (lj.global_batch): padded with
    # the last member, the maneuvers of sample_maneuvers
    q0g, qdot0g, ctlg = study.global_maneuvers(system, 6, seed=3)
    assert q0g.shape[0] == 8 and len(q0g.sharding.device_set) == 4
    np.testing.assert_allclose(np.asarray(q0g), np.asarray(sharded[0]), rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(np.asarray(ctlg.phase), np.asarray(sharded[2].phase), rtol=1e-14, atol=1e-15)
    # a point's numbers reduced over the devices: the padding (members 6, 7) counts for nothing
    q, c = study.rollout_nodes(system, study.make_integrator("dla"), (q0g, qdot0g, ctlg), 3.0, 60,
                               n_out=10, mesh=study.device_mesh())  # the car's DLA program above
    q_ref = q.at[6:].add(1e3)  # the padding "blows up" and fails
    c = c.at[7].set(3)
    stats = study.point_statistics(q, c, q_ref, c * 0, 6, 10.0)
    assert int(stats["failures"]) == 0 and float(stats["final_error_max"]) == 0.0
    stats = study.point_statistics(q, c, q_ref, c * 0, 8, 10.0)
    assert int(stats["failures"]) == 2 and int(stats["blowup"]) == 1
    # batch_rollout splits the batch with lj.shard_vmap: 6 members padded to 8, two per device
    import jax.numpy as jnp
    import ldap_jax as lj
    split = lj.shard_vmap(jnp.sin)(jnp.arange(6.0))
    assert split.shape == (6,) and len(split.sharding.device_set) == 4, split.sharding
    # reverse mode: the gradient of an argument given once (replicated) sums over the devices
    def loss(batched):
        f = batched(lambda a, x: jnp.sin(a * x) * a, in_axes=(None, 0))
        return lambda a: jnp.sum(f(a, jnp.linspace(0.0, 1.0, 6)) ** 2)
    np.testing.assert_allclose(jax.grad(loss(lj.shard_vmap))(0.7), jax.grad(loss(jax.vmap))(0.7), rtol=1e-13)
    # a member that raises in a batch the devices do not divide: an exception, not the others
    # waiting in the padding's removal until XLA aborts the process
    import equinox as eqx
    try:
        lj.shard_vmap(lambda x: eqx.error_if(x, x == 2.0, "member 2 failed"))(jnp.arange(6.0))
    except Exception as err:
        assert "member 2 failed" in str(err), err
    else:
        raise AssertionError("no error raised")
    print("OK")
    """
)


def test_sharded_equals_unsharded():
    env = dict(os.environ)
    env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=4").strip()
    env["JAX_PLATFORMS"] = "cpu"
    env["EQX_ON_ERROR"] = "raise"  # equinox's default, whatever a script run in this worker set
    out = subprocess.run(
        [sys.executable, "-c", SHARDED], env=env, cwd=ROOT, capture_output=True, text=True, timeout=600
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert "OK" in out.stdout


def _sweep_script():
    """scripts/sweep.py as a module (its ``main`` runs here, in the test worker: a process of its
    own paid JAX's start and compiled the study's programs again)."""
    spec = importlib.util.spec_from_file_location("sweep_script", os.path.join(ROOT, "scripts", "sweep.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.xdist_group("car_study")  # with test_tiny_study
def test_script_quick_configuration(tmp_path, monkeypatch, capsys):
    # the script sets EQX_ON_ERROR and XLA_FLAGS for its own process: both are restored afterwards
    monkeypatch.delenv("EQX_ON_ERROR", raising=False)
    monkeypatch.setenv("XLA_FLAGS", os.environ.get("XLA_FLAGS", ""))
    sweep = _sweep_script()
    argv = "--model car --methods rdp,rk2 --resolutions 20,40 --runs 4 --duration 2s --repeats 1"
    assert sweep.main([*argv.split(), "--out", str(tmp_path)]) == 0
    rows = study.read_csv(tmp_path / "sweep.csv")
    assert [r["method"] for r in rows] == ["rdp", "rdp", "rk2", "rk2"]
    assert os.path.exists(tmp_path / "sweep_car_2s.png")
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_:
        sweep.main(["--methods", "rk5", "--out", str(tmp_path)])
    assert exit_.value.code == 2 and "rk5" in capsys.readouterr().err
