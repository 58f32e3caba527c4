"""The study over several JAX processes (ldap_jax.launch, scripts/sweep.py's process options): a
2-process run on localhost gives the 1-process rows, a process started with a wrong
--num-processes fails within its timeout naming the option, a stopped study resumes without
computing its finished points again, and the launcher stops the others when one fails.

Each multi-process test starts its processes as subprocesses on a free port, bounded by a timeout.
"""

import json
import math
import os
import subprocess
import sys
import time

import jax
import numpy as np
import pytest

from ldap_jax import launch, study

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SWEEP = os.path.join(ROOT, "scripts", "sweep.py")
# a part of test_study's car study: the 1-process run, in the worker, reuses its compiled programs
# (the padding of a batch over devices is checked in test_study's 4-device process)
SMALL = "--model car --methods rdp --resolutions 20 --runs 4 --duration 2s --repeats 1".split()
COUNTS = ("n_steps", "runs", "failures", "nonfinite", "singular", "not_converged", "blowup")


def _chunks(out) -> dict:
    """The rows a sweep kept under ``out/chunks``, by file name."""
    (folder,) = (out / "chunks").iterdir()
    return {p.name: json.loads(p.read_text()) for p in sorted(folder.glob("car_*.json"))}


def _assert_same_rows(a: dict, b: dict) -> None:
    """Equal counts, errors equal to round-off; runtimes are measured, not compared."""
    assert a.keys() == b.keys() and a
    for name in a:
        for col in study.CSV_COLUMNS:
            x, y = a[name][col], b[name][col]
            if col in COUNTS or col in ("model", "method", "duration", "h"):
                assert x == y, (name, col, x, y)
            elif col != "runtime_us":
                close = math.isclose(x, y, rel_tol=1e-10, abs_tol=1e-15)
                assert math.isfinite(x) and close, (name, col, x, y)


def _sweep(argv, tmp_path, timeout: float = 120.0, env=None):
    return subprocess.run(
        [sys.executable, *argv],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=timeout,
        env=env,
    )


@pytest.mark.xdist_group("car_study")  # the 1-process run reuses test_study's compiled programs
def test_two_processes_give_the_one_process_rows(tmp_path, monkeypatch, capsys):
    two = tmp_path / "two"
    launch_line = ["-m", "ldap_jax.launch", "-n", "2", "--", sys.executable, SWEEP]
    run = _sweep([*launch_line, *SMALL, "--out", str(two)], tmp_path)
    assert run.returncode == 0, run.stderr[-3000:]
    assert "in 2 process(es)" in run.stdout  # process 0 prints; process 1 prints nothing
    assert run.stdout.count("study time") == 1
    # the 1-process run, in this worker (its one device)
    monkeypatch.delenv("EQX_ON_ERROR", raising=False)
    monkeypatch.setenv("XLA_FLAGS", os.environ.get("XLA_FLAGS", ""))
    sweep = _load_sweep()
    one = tmp_path / "one"
    assert sweep.main([*SMALL, "--cpu-devices", "1", "--out", str(one)]) == 0
    capsys.readouterr()
    _assert_same_rows(_chunks(one), _chunks(two))
    # the files process 0 wrote: the same table (full precision: errors equal to round-off,
    # runtimes aside) and figures
    rows_one, rows_two = study.read_csv(one / "sweep.csv"), study.read_csv(two / "sweep.csv")
    assert len(rows_one) == len(rows_two)

    def keyed(rows):
        return {(r["model"], r["duration"], r["method"], r["n_steps"]): r for r in rows}

    _assert_same_rows(keyed(rows_one), keyed(rows_two))
    assert sorted(p.name for p in two.iterdir()) == sorted(p.name for p in one.iterdir())


def _load_sweep():
    import importlib.util

    spec = importlib.util.spec_from_file_location("sweep_script_distributed", SWEEP)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_wrong_num_processes_fails_fast_naming_it(tmp_path):
    """Process 1 started with --num-processes 3 in a run of 2: both processes stop with a message
    naming --num-processes, long before the timeout, and process 1 writes nothing."""
    address = f"127.0.0.1:{launch.free_port()}"
    common = [SWEEP, *SMALL, "--cpu-devices", "1", "--coordinator", address, "--init-timeout", "60"]
    procs = [
        subprocess.Popen(
            [sys.executable, *common, "--num-processes", n, "--process-id", i, "--out", f"out{i}"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            cwd=tmp_path,
        )
        for i, n in (("0", "2"), ("1", "3"))
    ]
    try:
        errs = [p.communicate(timeout=90)[1] for p in procs]
    finally:
        for p in procs:
            p.kill()
    for p, err in zip(procs, errs):
        assert p.returncode == 2, err[-2000:]
        assert "argument --num-processes:" in err and "different settings" in err, err[-2000:]
        assert "Traceback" not in err
    assert "is 3 in this process (1)" in errs[1]
    assert not (tmp_path / "out1").exists()  # only process 0 creates --out


def test_lone_process_times_out_naming_the_coordinator(tmp_path):
    """Process 0 of a run of 2 whose other process never comes: it stops after --init-timeout with
    a message naming the coordinator's address and --num-processes (JAX alone would abort without
    one)."""
    address = f"127.0.0.1:{launch.free_port()}"
    argv = [SWEEP, *SMALL, "--cpu-devices", "1", "--out", str(tmp_path / "out"), "--init-timeout", "2"]
    argv += ["--coordinator", address, "--num-processes", "2", "--process-id", "0"]
    run = _sweep(argv, tmp_path, timeout=60)
    assert run.returncode == 3, run.stderr[-2000:]
    assert address in run.stderr and "--num-processes" in run.stderr and "within 2 s" in run.stderr


@pytest.mark.xdist_group("car_study")
def test_stopped_study_resumes_without_recomputing(tmp_path):
    """A study stopped after two of its four points keeps their rows; started again it computes
    the two others only (a kept row, marked, comes back as it was kept), and a third start
    computes nothing, not even the reference."""
    config = study.StudyConfig(
        models=("car",), durations=(2.0,), methods=("rdp", "rk2"), resolutions=(20, 40), runs=4, repeats=1
    )

    def stop_after(k):
        def progress(tasks):
            for i, task in enumerate(tasks):
                if i == k:
                    raise KeyboardInterrupt  # a stop between points
                yield task

        return progress

    with pytest.raises(KeyboardInterrupt):
        study.run_study(config, chunks=tmp_path, progress=stop_after(2))
    (folder,) = tmp_path.iterdir()
    kept = sorted(p.name for p in folder.glob("car_*.json"))
    assert kept == ["car_2s_rdp_N20.json", "car_2s_rdp_N40.json"]
    marked = folder / "car_2s_rdp_N40.json"
    row = json.loads(marked.read_text())
    row["final_error_max"] = 123.0
    marked.write_text(json.dumps(row))
    log = []
    rows = study.run_study(config, chunks=tmp_path, log=log.append)
    assert log[0].startswith("resumed 2 of 4 points")
    assert sum("reference" in m for m in log) == 1  # the rk2 points needed it
    assert [r["method"] for r in rows] == ["rdp", "rdp", "rk2", "rk2"]
    assert rows[1]["final_error_max"] == 123.0  # read, not computed again
    assert all(0 < r["final_error_median"] < 1e-2 for r in rows)
    assert len(list(folder.glob("car_*.json"))) == 4
    log.clear()
    again = study.run_study(config, chunks=tmp_path, log=log.append)
    assert log == [f"resumed 4 of 4 points from {folder}"]  # no reference computed
    assert again == rows
    # other settings: other rows (none of these is taken)
    other = study.ChunkStore(tmp_path, study.StudyConfig(**{**config.__dict__, "runs": 5}))
    assert other.load([("car", 2.0, "rdp", 20)]) == {}


def test_global_batch_builds_each_device_rows_and_pads():
    """lj.global_batch calls `make` per device with the global indices of its rows (padded with
    the last member), and gives global arrays; the study's maneuvers are sample_maneuvers'."""
    import ldap_jax as lj

    calls = []

    def make(idx):
        calls.append(idx.tolist())
        return {"i": idx.astype(np.int64), "x": np.stack([idx, -idx], axis=1).astype(float)}

    batch = lj.global_batch(make, 3)
    n_dev = jax.device_count()
    size = -(-3 // n_dev) * n_dev
    assert batch["i"].shape == (size,) and batch["x"].shape == (size, 2)
    assert sorted(sum(calls, [])) == sorted([0, 1, 2] + [2] * (size - 3))
    np.testing.assert_array_equal(np.asarray(batch["x"])[:3], [[0, 0], [1, -1], [2, -2]])
    with pytest.raises(ValueError, match="'n'"):
        lj.global_batch(make, 0)
    with pytest.raises(ValueError, match="leading size"):
        lj.global_batch(lambda idx: np.zeros((len(idx) + 1, 2)), 3)
    car = study.MODELS["car"]()
    q0, qdot0, ctl = study.sample_maneuvers(car, 5, 4)
    q0g, qdot0g, ctlg = study.global_maneuvers(car, 5, 4)
    np.testing.assert_allclose(np.asarray(q0g)[:5], q0, rtol=1e-15)
    np.testing.assert_allclose(np.asarray(qdot0g)[:5], qdot0, rtol=1e-15)
    np.testing.assert_allclose(np.asarray(ctlg.amplitude)[:5], ctl.amplitude, rtol=1e-15)


def test_point_statistics_ignore_padding_and_match_numpy():
    """The row's numbers, reduced on the devices, are NumPy's over the first n members: the
    padding (here a blow-up and a failure) counts for nothing."""
    rng = np.random.default_rng(0)
    q_ref = rng.normal(size=(6, 4, 5))
    q = q_ref + 1e-3 * rng.normal(size=(6, 4, 5))
    code = np.array([0, 0, 3, 0, 0, 1])
    q[1] += 100.0  # a blow-up among the members
    q[4] += 100.0  # and one in the padding
    stats = study.point_statistics(q, code, q_ref, np.zeros(6, int), 4, 10.0)
    err = np.linalg.norm(q[:4, :, :2] - q_ref[:4, :, :2], axis=-1)
    ok = np.array([True, False, False, True])
    assert int(stats["failures"]) == 2 and int(stats["blowup"]) == 1
    assert int(stats["not_converged"]) == 1 and int(stats["nonfinite"]) == 0
    np.testing.assert_allclose(float(stats["final_error_mean"]), np.mean(err[ok, -1]), rtol=1e-14)
    np.testing.assert_allclose(float(stats["max_error_median"]), np.median(err[ok].max(1)), rtol=1e-14)
    np.testing.assert_allclose(float(stats["final_error_max"]), np.max(err[ok, -1]), rtol=1e-14)


def test_launcher_stops_the_others_when_one_fails(tmp_path, capfd):
    """The launcher gives each process its options; when one fails it names it, stops the others
    and returns that status; when all succeed it returns 0."""
    child = (
        "import sys, time, pathlib\n"
        "argv = sys.argv[1:]\n"
        "i = argv[argv.index('--process-id') + 1]\n"
        f"root = pathlib.Path(r'{tmp_path}')\n"
        "(root / ('.p' + i)).write_text(' '.join(argv))\n"
        "(root / ('.p' + i)).rename(root / ('p' + i))\n"  # whole when it appears
        # process 1 fails once the others have started (have written their options): failing
        # earlier, it had the launcher stop process 2 before its interpreter got that far
        "end = time.monotonic() + 20\n"
        "while sys.argv[1] == 'fail' and i == '1' and time.monotonic() < end and not all(\n"
        "    (root / f'p{j}').exists() for j in '02'):\n"
        "    time.sleep(0.05)\n"
        "if sys.argv[1] == 'fail' and i == '1': sys.exit(5)\n"
        "if sys.argv[1] == 'fail': time.sleep(60)\n"
    )
    start = time.monotonic()
    assert launch.launch([sys.executable, "-c", child, "fail"], 3, cpu_devices=2) == 5
    assert time.monotonic() - start < 30  # process 0 and 2 were stopped, not waited for
    assert "process 1 (pid " in capfd.readouterr().err.split("ldap_jax.launch: ")[-1]
    argv = (tmp_path / "p2").read_text().split()
    assert argv[argv.index("--num-processes") + 1] == "3" and argv[argv.index("--cpu-devices") + 1] == "2"
    host, port = argv[argv.index("--coordinator") + 1].rsplit(":", 1)
    assert host == "127.0.0.1" and port.isdigit()
    assert launch.launch([sys.executable, "-c", child, "ok"], 2) == 0
    assert launch.main(["-n", "2", "--", sys.executable, "-c", child, "ok"]) == 0
    with pytest.raises(SystemExit):
        launch.main(["-n", "0", "--", "true"])
    # a command that is not a program: argparse's error naming it, not a traceback from Popen
    with pytest.raises(SystemExit) as exit_info:
        launch.main(["-n", "2", "--", "no_such_program_ldap_jax"])
    assert exit_info.value.code == 2
    # the launcher gives each process its --cpu-devices: a command's own would silently lose
    capfd.readouterr()
    with pytest.raises(SystemExit) as exit_info:
        launch.main(["-n", "2", "--", sys.executable, "-c", child, "ok", "--cpu-devices=2"])
    assert exit_info.value.code == 2 and "'--cpu-devices=2'" in capfd.readouterr().err


def test_launcher_stops_its_processes_on_sigterm(tmp_path):
    """A supervisor's SIGTERM to the launcher stops its processes too (status 128 + 15), as Ctrl-C
    does: they do not run on, orphaned, writing the run's files after it has "stopped". Processes
    that ignore SIGTERM are killed after the grace period, even if a second SIGTERM arrives
    while the launcher stops them (it cut the stopping short, leaving them running)."""
    child = (
        "import os, signal, sys, time, pathlib\n"
        "signal.signal(signal.SIGTERM, signal.SIG_IGN)\n"
        "i = sys.argv[sys.argv.index('--process-id') + 1]\n"
        f"pathlib.Path(r'{tmp_path}', 'pid' + i).write_text(str(os.getpid()))\n"
        "time.sleep(60)\n"
    )
    cmd = [sys.executable, "-m", "ldap_jax.launch", "-n", "2", "--", sys.executable, "-c", child]
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True)
    try:
        end = time.monotonic() + 30
        while len(list(tmp_path.glob("pid*"))) < 2 and time.monotonic() < end:
            time.sleep(0.05)
        pids = [int(f.read_text()) for f in tmp_path.glob("pid*") if f.read_text()]
        assert len(pids) == 2
        time.sleep(0.2)  # the pid files are written before the children's sleep
        proc.terminate()
        time.sleep(0.5)
        proc.terminate()
        err = proc.communicate(timeout=20)[1]
        assert proc.returncode == 128 + 15, err
    finally:
        proc.kill()
        proc.communicate()
    end = time.monotonic() + 10
    while any(_alive(p) for p in pids) and time.monotonic() < end:
        time.sleep(0.05)
    assert not any(_alive(p) for p in pids)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a finished child of an ended parent is reaped by init; a zombie still answers kill(0)
    with open(f"/proc/{pid}/stat") as fh:
        return fh.read().split(")")[-1].split()[0] != "Z"


def test_a_busy_coordinator_port_and_unequal_device_counts_are_named(monkeypatch):
    """Process 0 whose coordinator port is taken: a message naming it, before JAX's coordinator
    would crash the process. Processes holding different numbers of devices: a mismatch named
    --cpu-devices (JAX's gather of the settings failed with a reshape error)."""
    import socket
    from types import SimpleNamespace

    from ldap_jax import _distributed

    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        port = held.getsockname()[1]
        with pytest.raises(_distributed.CoordinatorBusy, match=f"port {port} is in use"):
            _distributed.initialize(f"127.0.0.1:{port}", 2, 0, timeout=5.0)
    devices = [SimpleNamespace(process_index=p) for p in (0, 1, 1)]
    monkeypatch.setattr(jax, "devices", lambda: devices)
    with pytest.raises(_distributed.SettingsMismatch, match="process 0: 1, process 1: 2") as info:
        _distributed._same_device_counts()
    assert info.value.names == ("--cpu-devices",)
    devices.pop()
    _distributed._same_device_counts()


def test_cluster_processes_leave_out_to_process_zero(tmp_path, monkeypatch):
    """Under --cluster no process knows its index before JAX starts, so none checks --out then
    (process 0 does once it knows: the others may run where --out cannot be made)."""
    monkeypatch.delenv("EQX_ON_ERROR", raising=False)  # the script sets it: removed afterwards
    sweep = _load_sweep()
    (tmp_path / "afile").write_text("")
    args = sweep.parse_args(["--cluster", "auto", "--out", str(tmp_path / "afile" / "out")])
    assert args.distributed and args.process_id is None
    with pytest.raises(SystemExit):
        sweep.parse_args(["--out", str(tmp_path / "afile" / "out")])


def test_chunks_keep_float32_rows_and_close_durations_apart(tmp_path):
    """A study's rows kept per point: float32 rows in a folder of their own (a float64 study
    resumed 10-70% off values from them), a duration that 6 digits do not tell apart in a file
    of its own, and a file whose row is another point's not taken."""
    durations = (600.0, 600.0004)
    config = study.StudyConfig(models=("car",), durations=durations, methods=("rdp",), resolutions=(20,))
    store = study.ChunkStore(tmp_path, config)
    with jax.enable_x64(False):
        assert study.ChunkStore(tmp_path, config).folder != store.folder
    assert store.path(("car", 600.0, "rdp", 20)).endswith("car_600s_rdp_N20.json")
    assert store.path(("car", 600.0004, "rdp", 20)) != store.path(("car", 600.0, "rdp", 20))
    row = dict.fromkeys(study.CSV_COLUMNS, 1) | dict(model="car", method="rdp", duration=600.0, n_steps=20)
    store.save(("car", 600.0, "rdp", 20), row)
    assert list(store.load([("car", 600.0, "rdp", 20)])) == [0]
    os.replace(store.path(("car", 600.0, "rdp", 20)), store.path(("car", 600.0, "rdp", 40)))
    assert store.load([("car", 600.0, "rdp", 40)]) == {}


@pytest.mark.parametrize(
    "argv, env, flag",
    [
        (["--num-processes", "2", "--process-id", "0"], {}, "--coordinator"),
        (["--coordinator", "localhost:1", "--num-processes", "2", "--process-id", "2"], {}, "--process-id"),
        (["--coordinator", "localhost", "--num-processes", "2", "--process-id", "0"], {}, "--coordinator"),
        (["--coordinator", "h:1", "--process-id", "0"], {"JAX_NUM_PROCESSES": "two"}, "JAX_NUM_PROCESSES"),
        (["--cluster", "auto", "--process-id", "0"], {}, "--cluster"),
        (["--init-timeout", "0"], {}, "--init-timeout"),
    ],
)
def test_process_options_are_checked_before_jax(argv, env, flag, tmp_path):
    """Bad or missing process options fail at once (status 2, the option named), before JAX is
    imported (here it cannot be) and before any process waits for another."""
    (tmp_path / "fakejax").mkdir()
    (tmp_path / "fakejax" / "jax.py").write_text("raise ImportError('jax imported before the flags')\n")
    environ = {k: v for k, v in os.environ.items() if not k.startswith("JAX_")}
    environ.update(env, PYTHONPATH=str(tmp_path / "fakejax"))
    run = _sweep([SWEEP, *argv, "--out", str(tmp_path / "out")], tmp_path, timeout=60, env=environ)
    assert run.returncode == 2 and flag in run.stderr, run.stderr[-2000:]
    assert "Traceback" not in run.stderr


@pytest.mark.parametrize(
    "argv, flag",
    [
        (["--coordinator", "h:1", "--num-processes", "2", "--process-id", "0"], "--num-processes"),
        (["--family", "2", "--solver", "optimize"], "--family"),
        (
            ["--family", "2", "--coordinator", "h:1", "--num-processes", "2", "--process-id", "5"],
            "--process-id",
        ),
    ],
)
def test_optimize_family_options_are_checked_before_jax(argv, flag, tmp_path):
    """scripts/optimize.py: several processes run only a --family (lc.solve), and the process
    options are checked as sweep.py's are, before JAX is imported."""
    (tmp_path / "fakejax").mkdir()
    (tmp_path / "fakejax" / "jax.py").write_text("raise ImportError('jax imported before the flags')\n")
    environ = {k: v for k, v in os.environ.items() if not k.startswith("JAX_")}
    environ.update(PYTHONPATH=str(tmp_path / "fakejax"))
    script = os.path.join(ROOT, "scripts", "optimize.py")
    argv = [script, "--model", "car", "--task", "parallel_park", *argv, "--out", str(tmp_path / "out")]
    run = _sweep(argv, tmp_path, timeout=60, env=environ)
    assert run.returncode == 2 and f"argument {flag}" in run.stderr, run.stderr[-2000:]
    assert "Traceback" not in run.stderr
