"""A private CUDA Multi-Process Service (MPS) daemon: kernels of several processes on one GPU at once.

Without MPS a GPU runs the CUDA contexts of different processes in turns (time slices), so runs
in processes of their own on one GPU (``runner.run_in_process``) take the sum of their GPU times,
as they do from one process, where JAX runs a device's programs on one compute stream. One-seed
S-steps are chains of small kernels that use a few of the GPU's multiprocessors each; under MPS
the processes' kernels share the multiprocessors instead (benchmarks/RESULTS.md, twenty-ninth
session).

:func:`start` launches NVIDIA's control daemon (``nvidia-cuda-mps-control -d``) with a pipe and
log directory of its own in the temporary directory, and :func:`activate` points this process
(before it starts CUDA) and the processes it starts at it. Only processes with that
``CUDA_MPS_PIPE_DIRECTORY`` become its clients; other CUDA programs on the machine are not
affected. :func:`stop` shuts the daemon and its server down; a daemon whose command died without
stopping it is stopped by the next :func:`start` (:func:`stop_orphans`). Nothing here changes
the GPU's settings (compute mode, MIG).
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import pathlib
import shutil
import subprocess
import sys
import tempfile
import time
from typing import Iterator, NamedTuple

CONTROL = "nvidia-cuda-mps-control"
PIPE_VARIABLE, LOG_VARIABLE = "CUDA_MPS_PIPE_DIRECTORY", "CUDA_MPS_LOG_DIRECTORY"
DEFAULT_PIPE_DIRECTORY = "/tmp/nvidia-mps"
_PREFIX = "gmr-jax-mps-"
_OWNER = "owner"

# A client of the daemon in a process of its own: CUDA started, the devices counted and a context
# made on the first one (which starts the MPS server). Prints the device count; exits non-zero
# with the CUDA error's name where a step fails.
_PROBE = r"""
import ctypes, sys
try:
    cuda = ctypes.CDLL("libcuda.so.1")
except OSError as err:
    sys.exit(f"libcuda.so.1: {err}")
def check(rc, what):
    if rc:
        name = ctypes.c_char_p()
        cuda.cuGetErrorName(rc, ctypes.byref(name))
        sys.exit(f"{what}: {name.value.decode() if name.value else rc}")
check(cuda.cuInit(0), "cuInit")
count, device, context = ctypes.c_int(), ctypes.c_int(), ctypes.c_void_p()
check(cuda.cuDeviceGetCount(ctypes.byref(count)), "cuDeviceGetCount")
check(cuda.cuDeviceGet(ctypes.byref(device), 0), "cuDeviceGet")
check(cuda.cuDevicePrimaryCtxRetain(ctypes.byref(context), device), "cuDevicePrimaryCtxRetain")
cuda.cuDevicePrimaryCtxRelease(device)
print(count.value)
"""


class Daemon(NamedTuple):
    """A running private MPS daemon: its ``directory`` (pipes, logs, the owner's pid), the
    control program and the number of GPUs its clients see."""

    directory: pathlib.Path
    control: str
    devices: int

    @property
    def environment(self) -> dict:
        """The variables that make a process a client of this daemon."""
        return environment(self.directory)


class Unavailable(RuntimeError):
    """MPS could not be started here (no control program, no GPU, a failing client); the message
    is one line."""


def environment(directory) -> dict:
    directory = pathlib.Path(directory)
    return {PIPE_VARIABLE: str(directory / "pipe"), LOG_VARIABLE: str(directory / "log")}


def find_control() -> str | None:
    """The path of ``nvidia-cuda-mps-control`` on PATH, or None."""
    return shutil.which(CONTROL)


def _listening(path: pathlib.Path, unix_sockets: str = "/proc/net/unix") -> bool:
    """Whether a Unix socket is bound at ``path`` (the control socket's file outlives its daemon);
    where ``unix_sockets`` cannot be read, whether the file exists."""
    try:
        table = pathlib.Path(unix_sockets).read_text()
    except OSError:
        return path.exists()
    return any(line.split()[-1] == str(path) for line in table.splitlines()[1:] if len(line.split()) > 7)


def running_elsewhere(env=None) -> bool:
    """Whether an MPS daemon that this process would be a client of already runs (its control
    socket is listening): the one that ``CUDA_MPS_PIPE_DIRECTORY`` names, else the system's
    default (``/tmp/nvidia-mps``)."""
    env = os.environ if env is None else env
    return _listening(pathlib.Path(env.get(PIPE_VARIABLE) or DEFAULT_PIPE_DIRECTORY) / "control")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def daemon_processes(directory, proc: str = "/proc", names: tuple[str, ...] = ("nvidia-cuda-mps",)) -> list[int]:
    """The pids of the MPS processes (the control daemon and its server: names starting with
    ``names``, as ``proc``'s ``comm`` shortens them) of this user started with ``directory``'s
    pipe directory as ``CUDA_MPS_PIPE_DIRECTORY``; empty where ``proc`` cannot be read. An
    exited control daemon that its starter has not reaped yet (a zombie) is not among them: a
    zombie's ``environ`` reads empty."""
    wanted = f"{PIPE_VARIABLE}={environment(directory)[PIPE_VARIABLE]}".encode()
    found = []
    for entry in pathlib.Path(proc).glob("[0-9]*"):
        with contextlib.suppress(OSError):
            if (entry.stat().st_uid == os.getuid() and (entry / "comm").read_text().strip().startswith(names)
                    and wanted in (entry / "environ").read_bytes().split(b"\0")):
                found.append(int(entry.name))
    return sorted(found)


def _quit(control: str, directory: pathlib.Path, wait: float = 3.0) -> None:
    """Ask the daemon to shut down (it does once its clients have exited), wait up to ``wait``
    seconds for its processes to end, and remove ``directory``; a daemon that still serves a
    client (this process, say) keeps it, and the next :func:`start` removes it once its owner
    has exited (:func:`stop_orphans`)."""
    env = {**os.environ, **environment(directory)}
    with contextlib.suppress(OSError, subprocess.SubprocessError):
        subprocess.run([control], input=b"quit\n", env=env, stdout=subprocess.DEVNULL,
                       stderr=subprocess.DEVNULL, timeout=30, check=False)
    deadline = time.monotonic() + wait
    while (alive := daemon_processes(directory)) and time.monotonic() < deadline:
        time.sleep(0.05)
    if not alive:
        shutil.rmtree(directory, ignore_errors=True)


def stop_orphans(control: str, tmp: str | None = None) -> list[pathlib.Path]:
    """Stop the private daemons (of this user's earlier commands) whose owner process has died
    without stopping them; returns their directories."""
    stopped = []
    for directory in sorted(pathlib.Path(tmp or tempfile.gettempdir()).glob(f"{_PREFIX}*")):
        try:  # another command may be removing it at the same moment
            if directory.stat().st_uid != os.getuid() or _alive(int((directory / _OWNER).read_text())):
                continue
        except (OSError, ValueError):
            continue
        _quit(control, directory, wait=1.0)
        stopped.append(directory)
    return stopped


class Starting(NamedTuple):
    """A private daemon started by :func:`launch` whose client (``client``, the probe) may still
    be running: :func:`finish` waits for it, :func:`abandon` stops both."""

    directory: pathlib.Path
    control: str
    client: subprocess.Popen


def launch(control: str | None = None, tmp: str | None = None, probe: str | None = None) -> Starting:
    """The first half of :func:`start`: the daemon, and its client started but not waited for,
    so that this process can start its own CUDA backend meanwhile. Raises :class:`Unavailable`
    (the daemon stopped again) where the control program is missing or fails."""
    control = control or find_control()
    if control is None:
        raise Unavailable(f"{CONTROL} is not on PATH")
    stop_orphans(control, tmp)
    directory = pathlib.Path(tempfile.mkdtemp(prefix=_PREFIX, dir=tmp))
    try:
        (directory / _OWNER).write_text(str(os.getpid()))
        env = {**os.environ, **environment(directory)}
        for name in (PIPE_VARIABLE, LOG_VARIABLE):
            pathlib.Path(env[name]).mkdir()
        started = subprocess.run([control, "-d"], env=env, capture_output=True, timeout=30, check=False)
        if started.returncode != 0:
            raise Unavailable(f"{CONTROL} -d exited with {started.returncode}: "
                              f"{_last_line(started.stderr or started.stdout)}")
        client = subprocess.Popen([sys.executable, "-c", probe or _PROBE], env=env, stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE)
        return Starting(directory, control, client)
    except BaseException as err:  # Ctrl-C too: no daemon left behind
        _quit(control, directory)
        if isinstance(err, (OSError, subprocess.SubprocessError)):
            raise Unavailable(f"{CONTROL}: {type(err).__name__}: {err}") from err
        raise


def finish(starting: Starting, timeout: float = 60.0) -> Daemon:
    """Wait for the client of :func:`launch` (at most ``timeout`` seconds) and return the
    running daemon; raises :class:`Unavailable` (the daemon stopped again) where it failed."""
    try:
        try:
            out, err = starting.client.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            raise Unavailable(f"a CUDA client of the MPS daemon did not start within {timeout:g} s") from None
        if starting.client.returncode != 0:
            raise Unavailable(f"a CUDA client of the MPS daemon failed (exit {starting.client.returncode}): "
                              f"{_last_line(err)}")
        return Daemon(starting.directory, starting.control, int(out.decode().split()[-1]))
    except BaseException as error:  # Ctrl-C too: no daemon (and GPU context) left behind
        abandon(starting)
        if isinstance(error, (ValueError, IndexError)):
            raise Unavailable(f"{CONTROL}: the client printed no device count: {type(error).__name__}: "
                              f"{error}") from error
        if isinstance(error, OSError):
            raise Unavailable(f"{CONTROL}: {type(error).__name__}: {error}") from error
        raise


def abandon(starting: Starting) -> None:
    """Stop the client of :func:`launch` if it still runs, then the daemon."""
    if starting.client.poll() is None:
        starting.client.kill()
    starting.client.communicate()
    _quit(starting.control, starting.directory)


def start(control: str | None = None, tmp: str | None = None, probe_timeout: float = 60.0,
          probe: str | None = None) -> Daemon:
    """Start a private MPS daemon and check it with a client in a process of its own (which also
    starts the MPS server, so the processes that use it do not wait for it): :func:`launch` then
    :func:`finish`. Raises :class:`Unavailable` (the daemon stopped again). Nothing is a client
    until :func:`activate`. ``probe``: the client's Python code (default: the CUDA driver's,
    which prints the device count); ``tmp``: where the daemon's directory goes (default: the
    temporary directory)."""
    return finish(launch(control, tmp, probe), probe_timeout)


def device_count() -> int | None:
    """The number of GPUs that CUDA's driver shows this process (``cuInit``, then
    ``cuDeviceGetCount``: no context, so this process is no MPS client for it; JAX's backend
    would start the driver anyway), or None where the driver or a device is missing."""
    try:
        cuda = ctypes.CDLL("libcuda.so.1")
    except OSError:
        return None
    count = ctypes.c_int()
    if cuda.cuInit(0) or cuda.cuDeviceGetCount(ctypes.byref(count)):
        return None
    return count.value


def _last_line(output: bytes) -> str:
    lines = output.decode(errors="replace").strip().splitlines()
    return lines[-1].strip() if lines else "no message"


_PREVIOUS: dict[pathlib.Path, dict] = {}


def activate(daemon: Daemon) -> None:
    """Make every process that this one starts from now on, and this one if it has not started
    CUDA yet, clients of ``daemon``. A process that started CUDA before stays outside: the
    daemon then shuts down as soon as the other clients have exited (:func:`stop`)."""
    _PREVIOUS.setdefault(daemon.directory, {name: os.environ.get(name) for name in daemon.environment})
    os.environ.update(daemon.environment)


def stop(daemon: Daemon) -> None:
    """Shut ``daemon`` and its server down (once its clients have exited: call it after the
    processes that used it) and remove its directory; this process's environment gets back what
    it held before :func:`activate`."""
    for name, value in _PREVIOUS.pop(daemon.directory, {}).items():
        if value is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = value
    _quit(daemon.control, daemon.directory)


@contextlib.contextmanager
def running(control: str | None = None) -> Iterator[Daemon]:
    """``start``, ``activate``; ``stop`` at the end of the block: the processes started inside
    it are clients (``runner.run_all(..., processes=...)`` passes the daemon's variables to its
    runs' processes, ``runner.child_environment``). Start this process's backend first
    (``jax.devices()``): a process that starts CUDA inside the block is a client too, and the
    daemon then outlives the block until that process exits."""
    daemon = start(control)
    activate(daemon)
    try:
        yield daemon
    finally:
        stop(daemon)
