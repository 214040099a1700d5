"""gmr_jax.mps and the CLI's --mps against a stand-in for nvidia-cuda-mps-control (a shell
script that logs its calls and leaves a control socket's file, which outlives the real daemon
too); the real daemon runs on GPU machines only (benchmarks/RESULTS.md, twenty-ninth session)."""

import os
import pathlib
import socket
import subprocess
import sys
import time

import pytest

from experiments import cli
from gmr_jax import mps, runner

FAKE = """#!/bin/sh
if [ "$1" = "-d" ]; then echo "$CUDA_MPS_PIPE_DIRECTORY -d" >> {log}; touch "$CUDA_MPS_PIPE_DIRECTORY/control"; exit {rc}; fi
read command; echo "$CUDA_MPS_PIPE_DIRECTORY $command" >> {log}
"""


def fake_control(tmp_path, rc: int = 0) -> tuple[str, pathlib.Path]:
    """A stand-in control program in its own folder and the file that logs its calls."""
    folder, log = tmp_path / "bin", tmp_path / "control.log"
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / mps.CONTROL
    path.write_text(FAKE.format(log=log, rc=rc))
    path.chmod(0o755)
    return str(path), log


def calls(log: pathlib.Path) -> list[list[str]]:
    return [line.split() for line in log.read_text().splitlines()] if log.exists() else []


def test_a_daemon_starts_serves_the_processes_started_after_activate_and_stops(tmp_path, monkeypatch):
    """start: the control program runs as a daemon with a pipe and log directory of its own,
    then a client in a process of its own reports the device count; activate: processes started
    afterwards see that directory (and so are its clients), and so do the runs' GPU processes
    (``runner.child_environment``); stop: "quit" reaches that daemon,
    the directory goes and this process's environment no longer names it."""
    control, log = fake_control(tmp_path)
    for name in (mps.PIPE_VARIABLE, mps.LOG_VARIABLE):  # absent again after the test, whatever happens
        monkeypatch.setenv(name, "")
        monkeypatch.delenv(name)
    daemon = mps.start(control, tmp=str(tmp_path), probe="import os; print(3 if os.environ['"
                       + mps.PIPE_VARIABLE + "'].endswith('/pipe') else 0)")
    pipe = daemon.directory / "pipe"
    assert daemon.devices == 3 and pipe.is_dir() and (daemon.directory / "log").is_dir()
    assert (daemon.directory / "owner").read_text() == str(os.getpid())
    assert calls(log) == [[str(pipe), "-d"]] and (pipe / "control").exists()
    mps.activate(daemon)
    seen = subprocess.run([sys.executable, "-c", f"import os; print(os.environ['{mps.PIPE_VARIABLE}'])"],
                          capture_output=True, text=True, check=True).stdout.strip()
    assert seen == str(pipe)
    # a run's process on the GPU gets them from the runner too (its process server may be older)
    assert runner.child_environment(None, "gpu")[mps.PIPE_VARIABLE] == str(pipe)
    assert mps.PIPE_VARIABLE not in runner.child_environment("cpu", "gpu")
    mps.stop(daemon)
    assert calls(log)[1:] == [[str(pipe), "quit"]]
    assert not daemon.directory.exists() and mps.PIPE_VARIABLE not in os.environ


def test_a_daemon_whose_client_fails_is_stopped_and_named_in_one_line(tmp_path, monkeypatch):
    """A client that cannot start CUDA (here: no device) or a control program that fails: one
    line naming the cause, and nothing left running or on disk."""
    control, log = fake_control(tmp_path)
    with pytest.raises(mps.Unavailable, match=r"^a CUDA client of the MPS daemon failed \(exit 1\): cuInit: CUDA_ERROR_NO_DEVICE$"):
        mps.start(control, tmp=str(tmp_path), probe="import sys; sys.exit('cuInit: CUDA_ERROR_NO_DEVICE')")
    assert [c[-1] for c in calls(log)] == ["-d", "quit"] and not list(tmp_path.glob("gmr-jax-mps-*"))
    failing, _ = fake_control(tmp_path / "other", rc=3)
    with pytest.raises(mps.Unavailable, match="exited with 3"):
        mps.start(failing, tmp=str(tmp_path), probe="print(1)")
    assert not list(tmp_path.glob("gmr-jax-mps-*"))
    monkeypatch.setattr(mps, "find_control", lambda: None)
    with pytest.raises(mps.Unavailable, match=f"^{mps.CONTROL} is not on PATH$"):
        mps.start(tmp=str(tmp_path))


def test_launch_returns_while_the_client_runs_finish_waits_and_abandon_stops_both(tmp_path):
    """launch: the daemon runs and its client is still running when it returns (the client here
    waits for a file that only this process writes afterwards); finish waits for the client and
    reads its device count; abandon stops a client that still runs and then the daemon."""
    control, log = fake_control(tmp_path)
    go = tmp_path / "go"
    waiting = (f"import os, sys, time\nend = time.monotonic() + 30\nwhile not os.path.exists({str(go)!r}):\n"
               "    time.sleep(0.01)\n    if time.monotonic() > end: sys.exit('no go')\nprint(2)")
    starting = mps.launch(control, tmp=str(tmp_path), probe=waiting)
    assert starting.client.poll() is None and calls(log) == [[str(starting.directory / "pipe"), "-d"]]
    go.touch()
    daemon = mps.finish(starting)
    assert daemon.devices == 2 and daemon.directory == starting.directory
    mps.stop(daemon)
    go.unlink()
    starting = mps.launch(control, tmp=str(tmp_path), probe=waiting)
    mps.abandon(starting)
    assert starting.client.returncode is not None and starting.client.returncode != 0
    assert calls(log)[-1] == [str(starting.directory / "pipe"), "quit"] and not starting.directory.exists()
    silent = mps.launch(control, tmp=str(tmp_path), probe="pass")
    with pytest.raises(mps.Unavailable, match="printed no device count"):
        mps.finish(silent)
    assert not silent.directory.exists()


def test_start_stops_the_daemons_of_commands_that_died(tmp_path):
    """A daemon left by a command that was killed (its owner's pid gone) is stopped and its
    directory removed by the next start; a live owner's daemon is left alone."""
    control, log = fake_control(tmp_path)
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    orphan, alive = tmp_path / "gmr-jax-mps-orphan", tmp_path / "gmr-jax-mps-alive"
    for folder, owner in ((orphan, dead.pid), (alive, os.getpid())):
        (folder / "pipe").mkdir(parents=True)
        (folder / "owner").write_text(str(owner))
    daemon = mps.start(control, tmp=str(tmp_path), probe="print(1)")
    assert [str(orphan / "pipe"), "quit"] in calls(log) and not orphan.exists()
    assert alive.exists() and not any(c[0] == str(alive / "pipe") for c in calls(log))
    mps.stop(daemon)


def test_the_command_starts_mps_where_runs_share_one_gpu(tmp_path, monkeypatch, capsys):
    """--mps auto starts a daemon only with one seed, several runs side by side in processes of
    their own and at most one device, and where the control program exists; on a GPU every run
    then trains there in a process of its own (none on the host CPU) and this process keeps no
    GPU pool; without a GPU backend the daemon is stopped again; a daemon already running is used;
    --mps on starts one wherever a GPU may be used and fails in one line where none can start or
    JAX has no GPU; a daemon that fails under auto is skipped with a note."""
    import jax

    control, log = fake_control(tmp_path)
    monkeypatch.setenv("PATH", f"{pathlib.Path(control).parent}{os.pathsep}{os.environ['PATH']}")
    monkeypatch.setattr(mps, "_PROBE", "print(1)")
    monkeypatch.setenv("TMPDIR", str(tmp_path))
    monkeypatch.setattr("tempfile.tempdir", None)
    for name in (mps.PIPE_VARIABLE, mps.LOG_VARIABLE, "XLA_PYTHON_CLIENT_PREALLOCATE", "JAX_PLATFORMS"):
        monkeypatch.setenv(name, "")  # restored to what it was (absent or set) after the test
        monkeypatch.delenv(name)
    monkeypatch.setattr(jax, "default_backend", lambda: "cpu")
    started, pools, nice = [], [], []

    def parse(argv):
        args = cli.parse_args("reach", ["--backend", "mujoco"] + argv, start_daemons=True)
        started.append(args.mps_state)
        nice.append({f"{s}/{a}": n for (s, a), n in args.niceness.items()})
        pools.append(os.environ.pop("XLA_PYTHON_CLIENT_PREALLOCATE", None))
        placed = ([f"{s}/{a}" for s, a in args.platforms], [f"{s}/{a}" for s, a in args.gpu_processes])
        cli.stop_mps(args)
        return placed

    def refused(argv, message):
        with pytest.raises(SystemExit) as exit_info:
            parse(argv)
        assert exit_info.value.code == cli.EXIT_USAGE
        assert capsys.readouterr().err.strip().splitlines()[-1].endswith(message)

    assert parse([]) == ([], []) and started[-1] is None  # a CPU: the daemon started and stopped again
    assert [c[-1] for c in calls(log)] == ["-d", "quit"]
    refused(["--mps", "on"], "error: --mps on: JAX has no GPU backend here; use --mps auto or off")
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    monkeypatch.setattr(jax, "local_devices", lambda *a, **k: [object()])
    assert parse([]) == ([], ["AB/gmr", "A/gmr", "AB/mdgps", "A/mdgps"]) and started[-1] == "started"
    assert pools[-1] == "false" and mps.PIPE_VARIABLE not in os.environ
    assert not list(tmp_path.glob("gmr-jax-mps-*"))
    # every run on the GPU in a process of its own: niceness by the runs' order, the longest first
    levels = runner.PROCESS_NICENESS
    assert nice[-1] == {"AB/gmr": levels[0], "A/gmr": levels[1], "AB/mdgps": levels[2], "A/mdgps": levels[-1]}
    parse(["--process-niceness", "off"])
    assert nice[-1] == {}
    parse(["--process-niceness", "0,1"])
    assert nice[-1] == {"AB/gmr": 0, "A/gmr": 1, "AB/mdgps": 1, "A/mdgps": 1}
    refused(["--process-niceness", "0,20"], "argument --process-niceness: niceness: 20 is not an integer from 0 "
                                           "to 19")
    refused(["--process-niceness", "low"], "argument --process-niceness: must be auto, off or comma-separated "
                                          "integers from 0 to 19, got 'low'")
    parse(["--mps", "off", "--process-niceness", "5"])  # given: the GPU runs in processes only
    assert nice[-1] == {"A/gmr": 5}
    before = len(calls(log))
    assert parse(["--mps", "off"]) == (["A/mdgps", "AB/mdgps"], ["A/gmr"]) and nice[-1] == {}
    assert parse(["--seeds", "2"]) == ([], [])
    assert parse(["--jobs", "1", "--cpu-runs", "none"]) == ([], [])
    assert parse(["--scenario", "A", "--algorithm", "gmr"]) == ([], [])
    assert parse(["--devices", "2"]) == (["A/mdgps", "AB/mdgps"], [])
    assert parse(["--gpu-runs-in-process", "none"]) == (["A/mdgps", "AB/mdgps"], [])
    assert started[-6:] == [None] * 6 and len(calls(log)) == before and pools[-6:] == [None] * 6
    # on: started where runs do not share one GPU too; this process keeps its pool (it trains them)
    assert parse(["--mps", "on", "--seeds", "2", "--cpu-runs", "none"]) == ([], []) and started[-1] == "started"
    assert pools[-1] is None
    monkeypatch.setenv("JAX_PLATFORMS", "cpu")
    assert parse([]) == (["A/mdgps", "AB/mdgps"], ["A/gmr"]) and started[-1] is None
    refused(["--mps", "on"], "error: --mps on: JAX_PLATFORMS=cpu leaves JAX no GPU; use --mps auto or off")
    monkeypatch.delenv("JAX_PLATFORMS")
    elsewhere = tmp_path / "system-mps"
    elsewhere.mkdir()
    (elsewhere / "control").touch()  # a daemon's leftover file: none runs
    monkeypatch.setenv(mps.PIPE_VARIABLE, str(elsewhere))
    assert parse([]) == ([], ["AB/gmr", "A/gmr", "AB/mdgps", "A/mdgps"]) and started[-1] == "started"
    assert os.environ[mps.PIPE_VARIABLE] == str(elsewhere)  # the user's setting is back
    (elsewhere / "control").unlink()
    before = len(calls(log))
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as server:
        server.bind(str(elsewhere / "control"))
        server.listen()
        assert parse([]) == ([], ["AB/gmr", "A/gmr", "AB/mdgps", "A/mdgps"]) and started[-1] == "running"
        assert pools[-1] == "false" and parse(["--seeds", "2"]) == ([], []) and started[-1] is None
    assert len(calls(log)) == before  # a running daemon is used, not started or stopped
    monkeypatch.delenv(mps.PIPE_VARIABLE)
    monkeypatch.setattr(mps, "_PROBE", "import sys; sys.exit('cuInit: CUDA_ERROR_NO_DEVICE')")
    assert parse([]) == (["A/mdgps", "AB/mdgps"], ["A/gmr"]) and started[-1] is None
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        "note: no CUDA MPS (a CUDA client of the MPS daemon failed (exit 1): cuInit: CUDA_ERROR_NO_DEVICE); "
        "runs on one GPU take turns on it (--mps off hides this)")
    refused(["--mps", "on"], "error: --mps on: a CUDA client of the MPS daemon failed (exit 1): "
                             "cuInit: CUDA_ERROR_NO_DEVICE; use --mps auto or off")
    assert not list(tmp_path.glob("gmr-jax-mps-*"))


def test_the_daemons_client_runs_while_the_command_starts_its_backend(tmp_path, monkeypatch):
    """The command starts its own CUDA backend while the daemon's client runs (the client here
    finishes only once the stand-in backend has started: a command that waited for it first
    would find no MPS); the GPUs are counted by the driver in this process, and under auto a
    count of two stops the daemon again (the runs do not share one GPU) and leaves this
    process's GPU pool alone; a Ctrl-C while counting leaves no daemon behind."""
    import jax

    control, log = fake_control(tmp_path)
    monkeypatch.setenv("PATH", f"{pathlib.Path(control).parent}{os.pathsep}{os.environ['PATH']}")
    monkeypatch.setenv("TMPDIR", str(tmp_path))
    monkeypatch.setattr("tempfile.tempdir", None)
    for name in (mps.PIPE_VARIABLE, mps.LOG_VARIABLE, "XLA_PYTHON_CLIENT_PREALLOCATE", "JAX_PLATFORMS"):
        monkeypatch.setenv(name, "")
        monkeypatch.delenv(name)
    backend = tmp_path / "backend started"
    monkeypatch.setattr(mps, "_PROBE", f"import os, sys, time\nend = time.monotonic() + 30\n"
                        f"while not os.path.exists({str(backend)!r}):\n    time.sleep(0.01)\n"
                        "    if time.monotonic() > end: sys.exit('the backend never started')\nprint(1)")

    def default_backend():
        backend.touch()
        return "gpu"

    monkeypatch.setattr(jax, "default_backend", default_backend)
    monkeypatch.setattr(jax, "local_devices", lambda *a, **k: [object()])
    monkeypatch.setattr(mps, "device_count", lambda: 1)
    args = cli.parse_args("reach", ["--backend", "mujoco"], start_daemons=True)
    try:
        assert args.mps_state == "started" and isinstance(args.mps_daemon, mps.Daemon)
        assert os.environ[mps.PIPE_VARIABLE] == str(args.mps_daemon.directory / "pipe")
        assert os.environ.pop("XLA_PYTHON_CLIENT_PREALLOCATE") == "false"
    finally:
        cli.stop_mps(args)
    assert [c[-1] for c in calls(log)] == ["-d", "quit"]
    monkeypatch.setattr(mps, "device_count", lambda: 2)
    args = cli.parse_args("reach", ["--backend", "mujoco"], start_daemons=True)
    assert args.mps_state is None and args.mps_daemon is None and args.gpu_processes == [("A", "gmr")]
    assert "XLA_PYTHON_CLIENT_PREALLOCATE" not in os.environ
    assert [c[-1] for c in calls(log)] == ["-d", "quit", "-d", "quit"]
    assert not list(tmp_path.glob("gmr-jax-mps-*"))

    def interrupted():
        raise KeyboardInterrupt

    monkeypatch.setattr(mps, "device_count", interrupted)  # Ctrl-C while the GPUs are counted
    with pytest.raises(KeyboardInterrupt):
        cli.parse_args("reach", ["--backend", "mujoco"], start_daemons=True)
    assert [c[-1] for c in calls(log)] == ["-d", "quit"] * 3 and not list(tmp_path.glob("gmr-jax-mps-*"))


def test_the_daemon_processes_are_found_by_name_and_pipe_directory(tmp_path):
    """``daemon_processes``: a process of the MPS programs' name started with the daemon's pipe
    directory is found (stop waits for it to end); one of another name with the same directory (a
    run's process) or of the same name with another directory is not."""
    env = {**os.environ, **mps.environment(tmp_path / "mine")}
    other = {**os.environ, **mps.environment(tmp_path / "other")}
    processes = [subprocess.Popen(["sleep", "30"], env=e) for e in (env, other, env)]
    try:
        deadline = time.monotonic() + 30  # Popen returns before the child's exec has renamed it
        while any(pathlib.Path(f"/proc/{p.pid}/comm").read_text().strip() != "sleep" for p in processes):
            assert time.monotonic() < deadline
            time.sleep(0.01)
        found = mps.daemon_processes(tmp_path / "mine", names=("sleep",))
        assert found == sorted(p.pid for p in (processes[0], processes[2]))
        assert mps.daemon_processes(tmp_path / "mine") == []  # none named like the MPS programs
        processes[0].kill()
        processes[0].wait()
        assert mps.daemon_processes(tmp_path / "mine", names=("sleep",)) == [processes[2].pid]
    finally:
        for p in processes:
            p.kill()
            p.wait()


def test_a_daemon_counts_as_running_only_while_its_control_socket_listens(tmp_path):
    """The control socket's file outlives a daemon: only a listening socket means one runs."""
    pipe = tmp_path / "pipe"
    pipe.mkdir()
    env = {mps.PIPE_VARIABLE: str(pipe)}
    assert not mps.running_elsewhere(env)
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as server:
        server.bind(str(pipe / "control"))
        server.listen()
        assert mps.running_elsewhere(env)
    assert (pipe / "control").exists() and not mps.running_elsewhere(env)
