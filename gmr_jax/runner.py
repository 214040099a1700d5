"""The resumable training loop: run configurations for given seeds into folders.

:func:`run` trains one configuration for several seeds in parallel (``jax.vmap`` over PRNG
keys), one jitted iteration at a time, checkpoints the whole training state atomically after
every iteration, and reports through a callback. With ``resume=True`` it continues from the
newest intact checkpoint (a corrupt one is renamed and reported, never deleted), and a run whose
configuration asks for more iterations than its checkpoints hold is extended; any other changed
setting is refused, naming the fields. An interrupted and resumed run equals an uninterrupted
one (``mdgps.iteration_keys``).

:func:`run_all` trains several configurations side by side in one process. A :class:`Scheduler`
orders their Python tracing, bounds how many XLA compilations run at once, keeps the compiled
programs for reuse, and carries the stop request of Ctrl-C / SIGTERM: every run then finishes
the iteration in flight, writes its checkpoint and raises :class:`Interrupted`.

:func:`run_in_process` trains a run in a process of its own (``run_all``'s ``processes``), on
the host CPU or on this process's devices, forked from a server that has imported this package
once, so that its Python work (tracing, host callbacks, checkpoints) does not share the GIL
with the other runs.

Progress is reported through ``progress_fn(event)``, an event being a dict with ``run`` (the
run's label) and either ``iteration``, ``iterations`` and ``metrics`` (host numpy arrays, after
every iteration) or ``message`` (resumed, a corrupt checkpoint set aside). Nothing here prints.
A split run's loop calls each iteration before it reads the one before (``_train_loop``), so
its event of iteration i comes while iteration i + 1 is under way: a callback reports, it
cannot count on changing the next iteration.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
import functools
import gc
import json
import multiprocessing
import numbers
import os
import pathlib
import pickle
import queue
import signal
import sys
import threading
import time
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from gmr_jax import checkpoint, config, evaluate, mdgps, mps, policies, sharding, tasks
from gmr_jax import process_server
from gmr_jax import program_store as program_store_lib
from gmr_jax import sim as sim_lib
from gmr_jax import stability as stability_lib
from gmr_jax import timeline

ProgressFn = Callable[[dict], None]


class TrainingError(RuntimeError):
    """A run cannot go on: a C-step or S-step produced non-finite values or η hit its limit."""


class Interrupted(RuntimeError):
    """The runs stopped on request (Ctrl-C, SIGTERM) after writing their checkpoints."""


class FolderTaken(RuntimeError):
    """A fresh run was asked into a folder that already holds checkpoints."""


def jsonable(tree):
    """Nested numpy/jax values → plain JSON types (non-finite floats become NaN)."""
    if isinstance(tree, dict):
        return {k: jsonable(v) for k, v in tree.items()}
    if isinstance(tree, (list, tuple)):
        return [jsonable(v) for v in tree]
    if tree is None or isinstance(tree, (str, bool, int)):
        return tree
    arr = np.asarray(tree)
    if arr.dtype == bool:
        return arr.tolist()
    if np.issubdtype(arr.dtype, np.integer):
        return arr.astype(int).tolist()
    return np.where(np.isfinite(arr), arr, np.nan).astype(float).tolist() if arr.ndim else float(arr)


def _host(tree):
    return jax.tree_util.tree_map(np.asarray, tree)


_gc_lock = threading.Lock()
_gc_pauses = {"depth": 0, "was_enabled": True}


@contextlib.contextmanager
def gc_paused():
    """Python's cyclic garbage collector paused (reference counting goes on) for the ``with``
    block: a trace allocates many objects that live until it ends, so the collector's passes
    during tracing and lowering find little and took a fifth of their time
    (benchmarks/RESULTS.md, thirtieth session). For tracing and lowering only: the pause holds
    for the whole process (every thread's garbage waits). Nested and concurrent blocks (threads)
    keep it paused until the last one ends; it is enabled again only if it was enabled before
    the first."""
    with _gc_lock:
        if _gc_pauses["depth"] == 0:
            _gc_pauses["was_enabled"] = gc.isenabled()
            gc.disable()
        _gc_pauses["depth"] += 1
    try:
        yield
    finally:
        with _gc_lock:
            _gc_pauses["depth"] -= 1
            if _gc_pauses["depth"] == 0 and _gc_pauses["was_enabled"]:
                gc.enable()


class Timer(dict):
    """Wall seconds per phase name (``with timer("compile_s"): ...``); repeated phases add up."""

    @contextlib.contextmanager
    def __call__(self, name: str):
        t = time.perf_counter()
        try:
            yield
        finally:
            self[name] = self.get(name, 0.0) + time.perf_counter() - t


class TracingTurns:
    """Side-by-side runs trace one at a time, in the order of their tickets.

    Tracing and lowering are Python work under the GIL: concurrent traces only delay each other.
    One at a time, the first run's compilation (which releases the GIL) starts sooner, and with
    tickets the runs that train longest go first. Each of ``runs`` runs holds ticket i for its
    iteration program and ticket :meth:`later` (i) = i + ``runs`` for its evaluation program,
    so that every iteration program is traced before any evaluation program. ``ticket=None``
    only excludes the others. A ticket is used up when its turn ends or by :meth:`release`, so
    that a run that fails before its turn does not hold the others up (a released ticket that
    still asks for its turn gets any free one).
    """

    def __init__(self):
        self._cv = threading.Condition()
        self._used: set[int] = set()
        self._next = 0
        self._runs = 0
        self._busy = False

    def reset(self, runs: int = 0):
        """Start a new set of ``runs`` runs side by side (tickets 0 … 2·runs − 1); 0: runs that
        do not all start at once, whose evaluation programs then take any free turn (a second
        round would wait for runs that start only after them)."""
        with self._cv:
            self._used, self._next, self._runs = set(), 0, runs

    def later(self, ticket: int | None) -> int | None:
        """The ticket of the second round (evaluation programs) of the run holding ``ticket``."""
        return None if ticket is None or not self._runs else ticket + self._runs

    def release(self, *tickets: int | None) -> None:
        """Use up ``tickets`` without a turn (those already used stay used)."""
        with self._cv:
            self._used.update(t for t in tickets if t is not None)
            while self._next in self._used:
                self._next += 1
            self._cv.notify_all()

    @contextlib.contextmanager
    def __call__(self, ticket: int | None):
        with self._cv:
            # a released ticket (its run failed) takes any free turn: its own has passed
            self._cv.wait_for(lambda: not self._busy and (ticket is None or self._next == ticket
                                                          or ticket in self._used))
            self._busy = True
        try:
            yield
        finally:
            with self._cv:
                self._busy = False
            self.release(ticket)


SWITCH_INTERVAL_S = 5e-4
"""Python's thread switch interval while runs train side by side. A host callback of a run (the C
MuJoCo rollouts, one per control step of a policy rollout) needs the GIL, and while another
thread holds it for Python work (tracing another run's programs) it waits up to the interval
for it: at Python's 5 ms, the default study's first iterations took 8–11 s instead of about 3 s
with a warm compilation cache (benchmarks/RESULTS.md, twentieth session)."""


@contextlib.contextmanager
def switch_interval(seconds: float | None):
    """``sys.setswitchinterval(seconds)`` inside the block (None: unchanged), restored after."""
    if seconds is None:
        yield
        return
    before = sys.getswitchinterval()
    sys.setswitchinterval(seconds)
    try:
        yield
    finally:
        sys.setswitchinterval(before)


ITERATION_PROGRAMS = ("auto", "whole", "parts", "split")
"""How the runner compiles a run's iteration (``Scheduler.iteration_programs``): "whole" as one
program (``mdgps.iteration``); "parts" as the programs of ``ITERATION_PARTS``, traced one after
the other and compiled in parallel threads; "split" as the programs of ``SPLIT_PARTS``, those of
``HOST_PARTS`` compiled for and run on the host's CPU (for a run of one seed on one GPU with the
C MuJoCo backend, where the process has a CPU device; other runs take parts); "auto": for the
runs of a policy on a GPU, split where split applies, else parts; for a policy's run in a process
of its own on the host (:func:`run_in_process`), parts; whole elsewhere."""

ITERATION_PARTS = (("rollouts",), ("model",), ("catch_up",), ("anchor", "cstep"), ("sstep",), ("curve",))
"""The groups of ``mdgps.ITERATION_PARTS`` that the runner compiles as programs of their own
(``iteration_programs`` "parts"): every part alone but the KL anchor with the C-step, so that
the first iteration's catch-up S-step compiles apart from the S-step, and the parts with host
callbacks (the C MuJoCo rollouts) apart from those that a ``ProgramStore`` can keep
(benchmarks/RESULTS.md, twenty-third session)."""

SPLIT_PARTS = (("rollouts",), ("model",), ("catch_up",), ("anchor",), ("cstep",), ("sstep",), ("curve",))
"""The groups of ``iteration_programs`` "split": every part alone, those of ``HOST_PARTS`` on
the host's CPU, the others on the run's device."""

HOST_PARTS = (("rollouts",), ("cstep",), ("curve",))
"""The groups of ``SPLIT_PARTS`` that ``iteration_programs`` "split" runs on the host's CPU: the
C MuJoCo rollouts (host callbacks; the learning curve's policy makes one per control step, and
on a GPU each holds its one compute stream, which the other runs' S-steps wait for) and the
step size with the C-step (small sequential factorisations). The dynamics fit and the policy's
linearisation stay on the GPU: on the host they take many times longer (one GMR seed on an H100
machine, benchmarks/RESULTS.md, twenty-fifth session)."""


def _check_iteration_programs(choice: str) -> None:
    if choice not in ITERATION_PROGRAMS:
        raise ValueError(f"iteration_programs: {choice!r} is not one of {', '.join(ITERATION_PROGRAMS)}")


def host_cpu_available() -> bool:
    """Whether this process has a CPU device beside its default backend (not with, e.g.,
    ``JAX_PLATFORMS=cuda``)."""
    try:
        return bool(jax.local_devices(backend="cpu"))
    except RuntimeError:
        return False


def iteration_programs_for(choice: str, cfg: config.Config, platform: str, num_seeds: int = 1,
                           devices: int = 1) -> str:
    """"whole", "parts" or "split": ``choice`` (one of ``ITERATION_PROGRAMS``) for a run of
    ``cfg`` with ``num_seeds`` seeds on ``devices`` devices of ``platform``."""
    _check_iteration_programs(choice)
    if choice in ("whole", "parts"):
        return choice
    if choice == "auto" and (platform != "gpu" or policies.spec_for(cfg) is None):
        return "whole"
    split = (num_seeds == 1 and devices == 1 and platform != "cpu" and cfg.sim.backend == "mujoco"
             and host_cpu_available())
    return "split" if split else "parts"


class Scheduler:
    """Compile scheduling and the stop request of runs trained in one process.

    Attributes:
      tracing: :class:`TracingTurns` of the runs.
      compile_jobs, compile_slots: at most ``compile_jobs`` programs (iterations, evaluations)
        compile at once (a run in its own process, :func:`run_in_process`, gets as many)
        (XLA spreads one compilation over the cores, so many at once mostly slow each other
        down). Waiters get a slot in the order they asked (``threading.Condition`` is FIFO), so
        the iteration programs traced first compile before the evaluation programs that runs
        request when they start training.
      programs: compiled programs per (kind, config, number of seeds, platform and devices): a
        resumed, extended or repeated run of the same configuration reuses its executables.
      mesh: the 1-D device mesh the runs split their seeds over (``devices``: the first n local
        devices; default all, see :mod:`gmr_jax.sharding`); a run placed on another platform
        (``run``'s ``platform``) uses that platform's mesh, :meth:`mesh_for`.
      pool: background threads (initial states, robustness programs, the caller's work); a
        robustness program waits in its thread for its tracing turn.
      stop: set by :meth:`request_stop` (e.g. from a signal handler); runs end after the
        iteration in flight.
      switch_interval: Python's thread switch interval (seconds, ``sys.setswitchinterval``)
        while :func:`run_all` trains runs side by side; None leaves Python's (5 ms).
      iteration_programs: one of ``ITERATION_PROGRAMS`` (the iteration as one program, in
        parts, or in parts some of which run on the host; a run in parts takes one compile slot
        for all its parts).
      program_store: a ``program_store.ProgramStore`` that the programs of one-device runs are
        lowered from (traced and stored the first time), or None: traced in every process.
    """

    def __init__(self, compile_jobs: int = 2, devices: int | None = None, workers: int = 16,
                 switch_interval: float | None = SWITCH_INTERVAL_S, iteration_programs: str = "auto",
                 program_store: program_store_lib.ProgramStore | None = None):
        config.check_positive_int("compile_jobs", compile_jobs)
        _check_iteration_programs(iteration_programs)
        self.iteration_programs = iteration_programs
        self.program_store = program_store
        self.compile_jobs = compile_jobs
        if switch_interval is not None:
            config.check_positive("switch_interval", switch_interval)
        self.switch_interval = switch_interval
        self.mesh = sharding.seed_mesh(devices)
        self.tracing = TracingTurns()
        self.compile_slots = threading.BoundedSemaphore(compile_jobs)
        self.programs: dict = {}
        self._meshes: dict = {}
        self.pool = concurrent.futures.ThreadPoolExecutor(max_workers=workers, thread_name_prefix="gmr-jax")
        # The training loops' own work (checkpoint writes, a split step's host parts), apart from
        # the pool's tasks that wait for tracing turns and compile slots.
        self.loop_pool = concurrent.futures.ThreadPoolExecutor(max_workers=workers, thread_name_prefix="gmr-jax-loop")
        self.stop = threading.Event()

    def request_stop(self) -> None:
        self.stop.set()

    def mesh_for(self, platform: str | None):
        """The mesh of runs placed on ``platform`` ("cpu": the host; None: :attr:`mesh`). A
        platform other than the default backend's gets all its local devices (the host's CPU
        is one device)."""
        if platform is None or platform == self.mesh.devices.flat[0].platform:
            return self.mesh
        if platform not in self._meshes:
            try:
                self._meshes[platform] = sharding.seed_mesh(None, platform)
            except RuntimeError as err:
                raise ValueError(f"platform {platform!r}: no such devices here ({err})") from err
        return self._meshes[platform]

    def host_mesh(self):
        """The one-device mesh of the host's first CPU device, where split iterations run their
        ``HOST_PARTS`` (one seed: however many CPU devices the host has)."""
        if "host" not in self._meshes:
            self._meshes["host"] = sharding.seed_mesh(1, "cpu")
        return self._meshes["host"]

    def close(self) -> None:
        self.pool.shutdown(wait=True, cancel_futures=True)
        self.loop_pool.shutdown(wait=True, cancel_futures=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _robustness(cfg: config.Config, params):
    """The task's fixed random states, its disturbance sweep and the rollouts from the training
    states: one program with one batch of rollouts."""
    ev = evaluate.evaluation(cfg, params)
    return ev.robustness, ev.sweep[:2], ev.training.X


# Seeds whose policy rollouts ``run`` keeps for pictures (``ROLLOUTS_FILE``): the first ones.
PICTURE_SEEDS = 16
PICTURE_RANDOM_STATES = 3
ROLLOUTS_FILE = "policy_rollouts.npz"


def write_policy_rollouts(run_dir, seeds, training_X, random_X) -> pathlib.Path:
    """Keep the trained policies' noiseless rollouts for pictures in ``run_dir/ROLLOUTS_FILE``
    (written atomically): the first ``PICTURE_SEEDS`` seeds' states [S, M, T, dX] from the
    training states and [S, PICTURE_RANDOM_STATES, T, dX] from the first robustness states.
    ``experiments.video`` renders them without recomputing anything."""
    n = min(len(seeds), PICTURE_SEEDS)
    path = pathlib.Path(run_dir) / ROLLOUTS_FILE
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez(tmp, seeds=np.asarray(seeds[:n]), training=np.asarray(training_X[:n]),
             random=np.asarray(random_X[:n, :PICTURE_RANDOM_STATES]))
    tmp.replace(path)
    return path


def _program(kind: str, mesh):
    """The jitted seed-vmapped program ``kind`` on ``mesh`` (one per process, see
    ``sharding.seed_program``): "init" (cfg, keys), "step" (cfg, state, keys, first) and
    "robustness" (cfg, params). The first-iteration flag is shared by all seeds: one program
    serves every iteration."""
    fn, batched = {"init": (mdgps.init, (True,)), "step": (mdgps.iteration, (True, True, False)),
                   "robustness": (_robustness, (True,))}[kind]
    return sharding.seed_program(fn, mesh, batched)


class _Layout(NamedTuple):
    """How a run's S seeds lie on the scheduler's mesh (padded to a multiple of its devices)."""

    mesh: Any
    num: int

    def device(self, tree):
        """Host or device leaves [S, ...] → padded [S', ...], split over the mesh."""
        return sharding.place(sharding.pad(tree, self.num, self.mesh), self.mesh)

    def real(self, tree):
        """Leaves [S', ...] → the real seeds' [S, ...]."""
        return sharding.unpad(tree, self.num)


@functools.partial(jax.jit, static_argnums=1)
def _seed_keys(seeds: jax.Array, iterations: int) -> tuple[jax.Array, jax.Array]:
    return jax.vmap(lambda s: mdgps.iteration_keys(jax.random.PRNGKey(s), iterations))(seeds)


def seed_keys(cfg: config.Config, seeds) -> tuple[np.ndarray, np.ndarray]:
    """(init keys [S], iteration keys [S, iterations]) of the seeds, as ``mdgps.train`` uses them,
    as host arrays. Derived by one program, on the host CPU where JAX has one and the keys are
    threefry's (the default ``jax_default_prng_impl``: integer arithmetic, the same bits on every
    platform; other implementations on the default device): a run's first computation, which
    one-by-one operations on a GPU compiled as several programs before its tracing could start
    (benchmarks/RESULTS.md, thirty-first session)."""
    device = jax.local_devices()[0]
    if jax.config.jax_default_prng_impl == "threefry2x32":
        try:
            device = jax.local_devices(backend="cpu")[0]
        except RuntimeError:  # JAX_PLATFORMS without the host CPU
            pass
    with jax.default_device(device):
        return jax.device_get(_seed_keys(jnp.asarray([int(s) for s in seeds]), cfg.iterations))


def initial_state(cfg: config.Config, seeds) -> mdgps.TrainState:
    """The batched initial TrainState of the seeds on one device (the template of their
    checkpoints)."""
    return _program("init", sharding.seed_mesh(1))(program_config(cfg), seed_keys(cfg, seeds)[0])


def restore_run(run_dir) -> tuple[config.Config, list, mdgps.TrainState]:
    """(configuration, seeds, newest intact TrainState [S]) of a finished or interrupted run
    folder (its ``config.json`` and ``checkpoints/``).

    Raises:
      ValueError: the folder holds no run's ``config.json``.
      checkpoint.CheckpointError: no intact checkpoint.
    """
    run_dir = pathlib.Path(run_dir)
    try:
        meta = json.loads((run_dir / "config.json").read_text())
        cfg, seeds = config.from_dict(meta["config"]), meta["seeds"]
    except (OSError, ValueError, KeyError) as err:
        raise ValueError(f"{run_dir}: not a run folder of a study ({err})") from err
    state, _ = checkpoint.restore(run_dir / "checkpoints", initial_state(cfg, seeds))
    return cfg, seeds, state


def program_config(cfg: config.Config) -> config.Config:
    """``cfg`` as the compiled programs see it: an iteration, the initial state and the
    robustness evaluation do not depend on the number of iterations, so runs that differ only
    in it (an extended run, a shorter test) share their programs."""
    return dataclasses.replace(cfg, iterations=1)


_TIMER_PREFIX = {"step": "", "robustness": "robustness_"}


def _platform(mesh) -> str:
    return mesh.devices.flat[0].platform


def _program_name(kind: str, cfg: config.Config, num_seeds: int, mesh) -> tuple:
    return kind, program_config(cfg), num_seeds, _platform(mesh), mesh.size


def _lowered(kind: str, cfg: config.Config, args, timer: Timer, scheduler: Scheduler, mesh):
    """The scheduler's compiled ``kind`` program ("step" or "robustness") for ``cfg`` and this
    seed batch on ``mesh``, or else the program traced and lowered (timed; compile it with
    :func:`_compiled`): a ``jax.stages.Lowered`` (a ``program_store.StoredLowered`` where the
    scheduler's program store holds it), or for an iteration in parts
    (``Scheduler.iteration_programs``) a :class:`_LoweredParts` of those.
    ``args``: the program's array arguments (or their shapes), seeds first. It is traced and
    lowered with ``mesh``'s first device as JAX's default device, so that choices made while
    tracing (``sharding.target_platform``) follow the run's platform, and arguments given as
    shapes are placed there."""
    name = _program_name(kind, cfg, jax.tree_util.tree_leaves(args[0])[0].shape[0], mesh)
    if name in scheduler.programs:
        return scheduler.programs[name]
    prefix = _TIMER_PREFIX[kind]
    with jax.default_device(mesh.devices.flat[0]):  # also where arguments given as shapes lie
        mode = "whole" if kind != "step" else iteration_programs_for(
            scheduler.iteration_programs, cfg, _platform(mesh), name[2], mesh.size)
        if mode == "parts":
            return _lowered_parts(cfg, args, timer, scheduler, ITERATION_PARTS, (mesh,) * len(ITERATION_PARTS))
        if mode == "split":
            host = scheduler.host_mesh()
            return _lowered_parts(cfg, args, timer, scheduler, SPLIT_PARTS,
                                  tuple(host if names in HOST_PARTS else mesh for names in SPLIT_PARTS))
        return _traced_and_lowered(kind, _program(kind, mesh), cfg, args, timer, scheduler, mesh, prefix)


def _part_program_name(names) -> str:
    return "step:" + "+".join(names)


_ROLLOUT_PROGRAMS = ("step", "robustness") + tuple(
    _part_program_name(names) for names in ITERATION_PARTS if set(names) & set(mdgps.ROLLOUT_PARTS))
"""The programs that roll the plant out (the whole iteration, the part programs with
``mdgps.ROLLOUT_PARTS``, the evaluation)."""


def _with_host_callbacks(name: str, cfg: config.Config) -> bool:
    """Whether program ``name`` of ``cfg`` calls C MuJoCo through host callbacks (traced for the
    current default device), which ``jax.export`` cannot serialize: the program store would trace
    it once more only to find that out. Any other program that cannot be stored is found by
    the store itself (and remembered)."""
    return name in _ROLLOUT_PROGRAMS and sim_lib.make_sim(cfg.sim).backend == "mujoco"


def _traced_and_lowered(name: str, program, cfg: config.Config, args, timer: Timer, scheduler: Scheduler, mesh,
                        prefix: str = ""):
    """``program(program_config(cfg), *args)`` lowered: from the scheduler's program store where
    it has one and the program runs on one device, else traced (``{prefix}trace_s``,
    ``{prefix}lower_s``), with the garbage collector paused (:func:`gc_paused`). Call it under
    the program's ``jax.default_device``."""
    with gc_paused():
        if scheduler.program_store is not None and mesh.size == 1 and not _with_host_callbacks(name, cfg):
            stored = scheduler.program_store.lower(name, program, program_config(cfg), args, _platform(mesh),
                                                   timer, prefix)
            if stored is not None:
                return stored
        with timer(f"{prefix}trace_s"):
            traced = program.trace(program_config(cfg), *args)
        with timer(f"{prefix}lower_s"):
            return traced.lower()


def _compile_options(num_seeds: int, mesh) -> dict | None:
    return sharding.compiler_options(sharding.seeds_per_device(num_seeds, mesh.size), _platform(mesh)) or None


def _reads(program) -> tuple[bool, ...]:
    """Per flat argument of a compiled program (the leaves of its arguments): whether it reads it
    (JAX drops the others from the program: ``input_shardings`` None)."""
    if isinstance(program, program_store_lib.StoredCompiled):
        return program.reads
    return tuple(s is not None for s in program.in_tree.flatten_up_to(program.input_shardings))


class _PartsStep:
    """An iteration's compiled parts (``ITERATION_PARTS`` or ``SPLIT_PARTS``), called as its
    whole program: ``step(state, keys, first) -> (new state, metrics)``.

    Without ``devices`` every part runs where its arguments lie. With ``devices`` (the one device
    of each part), each part gets the carry's arrays that it reads, those from other devices
    copied to its own, and is called once they are complete: a device runs its programs in the
    order they were called, so a program waiting for another device's results would hold back
    every program called after it there (the next iteration's rollouts, another run's parts). The
    new state's entries stay where their parts computed them (``mdgps.new_state``). The parts
    after the first ``state_after`` (those that only add metrics: the learning curve) are then
    called from a thread of ``pool`` and the metrics are a ``concurrent.futures.Future`` of the
    dict, so that the next iteration can be called at once (``asynchronous``: the runner does).

    Given the next iteration's keys (``next_keys``) and a run's dict ``prefetched``, the next
    iteration's rollouts are called from a thread of ``pool`` as soon as the controllers they
    sample are computed (the C-step), where they read nothing else of the state: on a GPU the call
    of a program with loops (the S-step) returns only when the GPU has nearly finished it (XLA's
    GPU loops are driven from the calling thread), so the rollouts would otherwise wait for it.
    ``prefetched`` then holds the controllers, the keys and the future of the samples; the next
    call with that dict, that state's controllers and those keys (the same objects) takes them."""

    def __init__(self, programs, devices=None, state_after: int | None = None, pool=None):
        self.programs = tuple(programs)
        self.devices = None if devices is None else tuple(devices)
        self.asynchronous = devices is not None
        self.reads = None if devices is None else tuple(_reads(p) for p in self.programs)
        self.state_after = len(self.programs) if state_after is None or devices is None else state_after
        self.pool = pool
        self._rollouts_read_only_controllers = None

    def __call__(self, state, keys, first, next_keys=None, prefetched: dict | None = None):
        carry = {"state": state, "key": keys}
        if self.devices is None:
            for program in self.programs:
                carry.update(program(carry, first))
            return mdgps.iteration_result(carry)
        copies: dict = {}
        if self._rollouts_read_only_controllers is None:
            paths = jax.tree_util.tree_flatten_with_path((carry, first))[0]
            self._rollouts_read_only_controllers = all(
                jax.tree_util.keystr(path).startswith(("[0]['state'].traj.", "[0]['key']"))
                for (path, _), read in zip(paths, self.reads[0], strict=True) if read)
        start = 0
        if prefetched:
            found = dict(prefetched)
            prefetched.clear()
            if found["traj"] is state.traj and found["keys"] is keys and not bool(first):
                carry.update(found["samples"].result())
                start = 1
            else:
                _wait_quietly(found["samples"])
        prefetch = next_keys is not None and prefetched is not None and self._rollouts_read_only_controllers
        for index in range(start, self.state_after):
            carry.update(self._call(index, carry, first, copies))
            if prefetch and "traj" in carry:
                prefetch = False
                upcoming = mdgps.new_state(carry, before=state)  # the rollouts read only what is computed
                prefetched.update(traj=carry["traj"], keys=next_keys, samples=self.pool.submit(
                    self._call, 0, {"state": upcoming, "key": next_keys}, jnp.asarray(False), {}))
        later = range(self.state_after, len(self.programs))
        if not later:
            return mdgps.iteration_result(carry)

        def metrics(carry: dict) -> dict:
            for index in later:
                carry.update(self._call(index, carry, first, copies))
            return mdgps.iteration_result(carry)[1]
        return mdgps.new_state(carry), self.pool.submit(metrics, dict(carry))

    def _call(self, index: int, carry: dict, first, copies: dict) -> dict:
        """Part ``index`` called with the arrays it reads on its device (host arrays put there),
        once they are complete (``copies``: the copies made so far in this iteration, by (array
        id, device))."""
        device = self.devices[index]
        leaves, tree = jax.tree_util.tree_flatten((carry, first))
        moved = []
        for i, read in enumerate(self.reads[index]):
            if read and (not isinstance(leaves[i], jax.Array) or leaves[i].devices() != {device}):
                key = id(leaves[i]), device
                if key not in copies:
                    copies[key] = (jax.device_put(leaves[i], device), leaves[i])  # the original kept alive
                leaves[i] = copies[key][0]
                moved.append(leaves[i])
        jax.block_until_ready(moved)
        return self.programs[index](*jax.tree_util.tree_unflatten(tree, leaves))


class _LoweredParts(NamedTuple):
    """An iteration's parts lowered, to be compiled together, the mesh of each, and how many of
    them compute the new state (``mdgps.STATE_ENTRIES``; the others only add metrics)."""

    parts: tuple
    meshes: tuple
    state_after: int


def _lowered_parts(cfg: config.Config, args, timer: Timer, scheduler: Scheduler, groups, meshes) -> _LoweredParts:
    """The iteration's parts (``groups`` of ``mdgps.ITERATION_PARTS``, each a program) traced and
    lowered one after the other (``trace_s``, ``lower_s``), each from the shapes of the carry that
    the parts before it leave, for its mesh (``meshes``, one per group; where they differ, every
    part's arguments are taken as shapes on that mesh's first device). ``args``: (state, keys,
    first) or their shapes."""
    state, keys, first = args
    carry, parts, state_after = {"state": state, "key": keys}, [], None
    mixed = len({id(m) for m in meshes}) > 1
    for names, mesh in zip(groups, meshes, strict=True):
        program = sharding.seed_program(mdgps.part_program(names), mesh, (True, False))
        part_args = program_store_lib.abstract((carry, first)) if mixed else (carry, first)
        with jax.default_device(mesh.devices.flat[0]):
            parts.append(_traced_and_lowered(_part_program_name(names), program, cfg, part_args, timer,
                                             scheduler, mesh))
        carry.update(parts[-1].out_info)
        if state_after is None and set(mdgps.STATE_ENTRIES.values()) <= set(carry):
            state_after = len(parts)
    return _LoweredParts(tuple(parts), tuple(meshes), state_after)


def _compiled(kind: str, cfg: config.Config, num_seeds: int, program, timer: Timer,
              scheduler: Scheduler, slot: bool, mesh):
    """``program`` (for ``mesh``) compiled (in a compile slot if ``slot``) and kept by the
    scheduler; an already compiled one is returned as it is. The parts of an iteration
    (:class:`_LoweredParts`) compile in parallel threads, in one slot."""
    if not isinstance(program, (jax.stages.Lowered, program_store_lib.StoredLowered, _LoweredParts)):
        return program
    with scheduler.compile_slots if slot else contextlib.nullcontext(), timer(f"{_TIMER_PREFIX[kind]}compile_s"):
        if isinstance(program, _LoweredParts):
            with concurrent.futures.ThreadPoolExecutor(len(program.parts), thread_name_prefix="gmr-jax-compile") as pool:
                compiled = list(pool.map(
                    lambda part, m: part.compile(compiler_options=_compile_options(num_seeds, m)),
                    program.parts, program.meshes))
            devices = [m.devices.flat[0] for m in program.meshes]
            compiled = (_PartsStep(compiled, devices, program.state_after, scheduler.loop_pool)
                        if len(set(devices)) > 1 else _PartsStep(compiled))
        else:
            compiled = program.compile(compiler_options=_compile_options(num_seeds, mesh))
    scheduler.programs[_program_name(kind, cfg, num_seeds, mesh)] = compiled
    return compiled


def evaluate_robustness(cfg: config.Config, params, timer: Timer | None = None, program=None,
                        layout: _Layout | None = None) -> dict:
    """Robustness of every seed's policy (leading seed axis of ``params``): the task's fixed
    random states and its disturbance sweep (keys ``robustness`` and ``sweep``), and the
    policies' rollouts from the training states (``training_X`` [S, M, T, dX]). ``program``:
    the compiled robustness program, or a future of it (default: compiled here); ``layout``:
    how ``params`` lie on the devices (default: one device, unpadded)."""
    timer = Timer() if timer is None else timer
    if program is None:
        program = functools.partial(_program("robustness", sharding.seed_mesh(1)), program_config(cfg))
    if isinstance(program, concurrent.futures.Future):
        with timer("robustness_wait_s"):
            program = program.result()
    with timer("robustness_run_s"):
        out = program(params)
        rob, (rate, rate_loose), training_X = _host(out if layout is None else layout.real(out))
    radii = [float(r) for r in tasks.of(cfg).sweep_radii]
    return {"robustness": rob._asdict(), "sweep": {"radii": radii, "success_rate": np.asarray(rate),
                                                     "success_rate_loose": np.asarray(rate_loose)},
            "training_X": training_X}


def _set_aside(ckpt_dir: pathlib.Path, step: int) -> pathlib.Path:
    """Rename checkpoint ``step`` to ``<step>.corrupt[.n]`` (kept for inspection, invisible to
    the checkpoint manager)."""
    src = ckpt_dir / str(step)
    dst = ckpt_dir / f"{step}.corrupt"
    n = 1
    while dst.exists():
        dst = ckpt_dir / f"{step}.corrupt.{n}"
        n += 1
    src.rename(dst)
    return dst


def _restore(cfg: config.Config, seeds, ckpt_dir: pathlib.Path, template, report: Callable[[str], None]):
    """(state, history) from the newest intact checkpoint, or (None, []) if there is none.

    Corrupt checkpoints are set aside (renamed) and reported; a checkpoint written with other
    settings than ``cfg`` — except fewer iterations, which extends the run — raises
    ``checkpoint.CheckpointError`` naming the fields.
    """
    for step in reversed(checkpoint.all_steps(ckpt_dir)):
        try:
            stored = checkpoint.read_metadata(ckpt_dir, step)
            done = len(stored.get("history", []))
            planned = stored.get("config", {}).get("iterations", cfg.iterations)
            if done > cfg.iterations:
                raise checkpoint.CheckpointError(
                    f"{ckpt_dir} holds {done} iterations, more than iterations={cfg.iterations}; "
                    f"resume with at least {done} iterations")
            expect = {"config": config.to_dict(dataclasses.replace(cfg, iterations=planned)),
                      "seeds": list(seeds)}
            state, saved = checkpoint.restore(ckpt_dir, template, step=step, expect=jsonable(expect),
                                              fill={"config": _with_defaults})
        except checkpoint.CorruptCheckpointError as err:
            moved = _set_aside(ckpt_dir, step)
            report(f"checkpoint step {step} is corrupt ({err}); set aside as {moved.name}")
            continue
        return state, history_from_metadata(saved)
    return None, []


def _with_defaults(stored: dict) -> dict:
    """A checkpoint's configuration with the fields it predates set to their defaults (a
    configuration that ``config.from_dict`` refuses is compared as it is, and its differences
    named)."""
    try:
        return config.to_dict(config.from_dict(stored))
    except (ValueError, TypeError):
        return stored


def history_metadata(history) -> dict:
    """A checkpoint's record of the metrics so far: ``history`` (one JSON dict per iteration) and
    ``history_dtypes`` (each metric's dtype, which JSON's numbers do not keep)."""
    dtypes = {k: np.asarray(v).dtype.str for k, v in history[-1].items()} if history else {}
    return {"history": [jsonable(h) for h in history], "history_dtypes": dtypes}


def history_from_metadata(saved: dict) -> list[dict]:
    """``history_metadata``'s inverse: the iterations' metrics as numpy arrays of their own
    dtypes, so that a resumed run's history (and every mean of it) is the uninterrupted run's
    bit for bit, except that non-finite values come back as NaN (``jsonable``); checkpoints
    written before dtypes were recorded give numpy's defaults."""
    dtypes = saved.get("history_dtypes", {})
    return [{k: np.asarray(v, dtype=dtypes.get(k)) for k, v in h.items()} for h in saved["history"]]


def check_fresh(run_dirs) -> None:
    """Raise :class:`FolderTaken` if any of ``run_dirs`` already holds checkpoints (checked
    before anything is written: a fresh run never replaces another run's files)."""
    taken = [str(pathlib.Path(d) / "checkpoints") for d in run_dirs
             if checkpoint.latest(pathlib.Path(d) / "checkpoints") is not None]
    if taken:
        raise FolderTaken(f"{', '.join(taken)} already hold(s) checkpoints; resume those runs "
                          "(--resume), or choose another output folder")


def check_checkpoint_every(checkpoint_every) -> None:
    """Raises ValueError unless ``checkpoint_every`` is a positive integer (NumPy's too)."""
    if (isinstance(checkpoint_every, bool) or not isinstance(checkpoint_every, numbers.Integral)
            or checkpoint_every < 1):
        raise ValueError(f"checkpoint_every: {checkpoint_every!r} is not a positive integer (1: after every "
                         "iteration)")


def run(cfg: config.Config, seeds, run_dir, *, resume: bool = False, stop_after: int | None = None,
        progress_fn: ProgressFn | None = None, scheduler: Scheduler | None = None,
        ticket: int | None = None, label: str = "", stability: bool = True,
        platform: str | None = None, checkpoint_every: int = 1) -> dict:
    """Train ``cfg`` for ``seeds`` in parallel into ``run_dir``; checkpoint after every iteration
    (or every ``checkpoint_every``-th).

    Args:
      cfg: the run's configuration.
      seeds: integer seeds (PRNG keys ``jax.random.PRNGKey(seed)``), trained side by side.
      run_dir: the run's folder (``config.json``, ``checkpoints/`` and, once a policy's run is
        finished, its rollouts for pictures, :func:`write_policy_rollouts`, are written there).
      resume: continue from the newest intact checkpoint (or start if there is none); without
        it, a folder that holds checkpoints raises :class:`FolderTaken`.
      stop_after: end after this many iterations, as an interruption would.
      progress_fn: receives the events described in the module docstring.
      scheduler: shared by side-by-side runs (default: a private one).
      ticket: this run's place in the tracing order of side-by-side runs (None: any).
      label: the run's name in progress events.
      stability: also measure the trained policies' closed-loop stability
        (``gmr_jax.stability``) along the robustness rollouts.
      platform: where the run computes: None for the scheduler's devices, or another platform
        of this process, e.g. "cpu" for the host (``Scheduler.mesh_for``). Its programs are
        traced and compiled for that platform (the S-step's form, compiler options).
      checkpoint_every: write the checkpoint of every n-th iteration and of the last one (a stop
        request or an error writes the last finished iteration's too); the others are not kept,
        so ``resume`` continues from the newest written. A many-seed run's checkpoints are
        large (about 1.6 MB per seed for GMR on A,B) and their writes slow its iterations
        (benchmarks/RESULTS.md, thirty-second session).
    Returns:
      dict with ``history`` (stacked metrics, leading axes [iteration, seed, ...]),
      ``iteration_s`` (seconds from the first call, or from the last iteration's metrics, to each
      iteration's metrics: a split run calls the next iteration before it reads one, so its
      first entry holds part of the second iteration and its last is short), ``wall_s``,
      ``timing`` (seconds per phase) and, for policies once every iteration is done,
      ``robustness``, ``sweep`` and (with ``stability``) ``stability``.
    Raises:
      TrainingError: non-finite values or a failed η search in the first iteration or for every
        seed still running; the checkpoints of the iterations before are intact. A seed that fails
        while others go on is frozen instead: its state and metrics stay those of its last good
        iteration, the metric ``seed_failed`` [S] marks it from then on, and a message event
        names it. Interrupted: the scheduler's stop was requested (checkpoint written).
      checkpoint.CheckpointError: a checkpoint cannot be written or belongs to other settings.
        The last one is written while the policies are evaluated: its failure is raised after
        the evaluation (whose rollouts file, ``ROLLOUTS_FILE``, ``--resume`` then removes).
    """
    check_checkpoint_every(checkpoint_every)
    if scheduler is None:
        with Scheduler() as own:
            return run(cfg, seeds, run_dir, resume=resume, stop_after=stop_after, progress_fn=progress_fn,
                       scheduler=own, ticket=ticket, label=label, stability=stability, platform=platform,
                       checkpoint_every=checkpoint_every)
    report = (lambda text: progress_fn({"run": label, "message": text})) if progress_fn else (lambda text: None)
    run_dir = pathlib.Path(run_dir)
    ckpt_dir = run_dir / "checkpoints"
    try:
        timeline.mark(f"run entry {label}")
        layout = _Layout(scheduler.mesh_for(platform), len(seeds))  # an unknown platform: before any write
        if not resume:
            check_fresh([run_dir])
        run_dir.mkdir(parents=True, exist_ok=True)
        (run_dir / "config.json").write_text(json.dumps({"seeds": list(seeds), "config": config.to_dict(cfg)},
                                                        indent=1))
        k_init, it_keys = (layout.device(k) for k in seed_keys(cfg, seeds))
        meta = jsonable({"config": config.to_dict(cfg), "seeds": list(seeds)})
        t0 = time.perf_counter()
        timeline.mark(f"run clock {label}")
        timer = Timer()
        stop = cfg.iterations if stop_after is None else min(stop_after, cfg.iterations)
        state, history, step, robustness = _prepare(cfg, seeds, layout, k_init, it_keys, ckpt_dir, resume, stop,
                                                    timer, scheduler, ticket, report, stability)
    except BaseException:
        scheduler.tracing.release(ticket, scheduler.tracing.later(ticket))  # the other runs' turns go on
        raise
    if step is not None:  # kept rollouts of an earlier, shorter run would outlive its policy
        (run_dir / ROLLOUTS_FILE).unlink(missing_ok=True)
    state, history, iteration_s, last_write = _train_loop(cfg, step, state, history, it_keys, stop, ckpt_dir, meta,
                                                          layout, timer, scheduler, progress_fn, label, t0,
                                                          checkpoint_every)
    with _written_after(last_write):  # the last checkpoint is written while the policies are evaluated
        timer["iterations_s"] = float(np.sum(iteration_s))
        stacked = {k: np.stack([np.asarray(h[k]) for h in history]) for k in history[0]} if history else {}
        result = {"history": stacked, "iteration_s": iteration_s}
        if robustness is not None and len(history) == cfg.iterations:
            result.update(evaluate_robustness(cfg, state.policy.params, timer, robustness, layout))
            write_policy_rollouts(run_dir, list(seeds), result.pop("training_X"), result["robustness"]["X"])
            if stability:
                with timer("stability_s"):
                    params = jax.device_get(layout.real(state.policy.params))
                    result["stability"] = stability_lib.measure(cfg, params, result["robustness"]["X"])._asdict()
    result["wall_s"] = time.perf_counter() - t0
    timeline.mark(f"run end {label}")
    result["timing"] = dict(timer)
    return result


def _prepare(cfg, seeds, layout: _Layout, k_init, it_keys, ckpt_dir, resume, stop, timer, scheduler, ticket,
             report, stability: bool = False):
    """The run's starting point and programs: (state on the devices, history, compiled step
    program or None, future of the compiled robustness program or None).

    The initial state is computed in the background while this run, in its tracing turn,
    restores its checkpoint (validated before anything compiles) and traces its step program
    from the state's shapes; the step program then compiles in a compile slot. The robustness
    program is traced in the background in the run's later turn (after every run's step
    program: ``TracingTurns.later``) and compiled while the run trains (in a compile slot too,
    after the programs already waiting for one), and then, with ``stability``, the stability
    measurement's policy program is prepared in the background (``stability.warm_up``)."""
    init_program = _program("init", layout.mesh)
    init = functools.partial(init_program, program_config(cfg))

    def make_initial():
        with timer("init_s"):
            with jax.default_device(layout.mesh.devices.flat[0]):
                lowered = _traced_and_lowered("init", init_program, cfg, (k_init,), Timer(), scheduler, layout.mesh)
            compiled = lowered.compile(compiler_options=_compile_options(k_init.shape[0], layout.mesh))
            return jax.block_until_ready(compiled(k_init))
    state_future = scheduler.pool.submit(make_initial)
    num = k_init.shape[0]
    step = robustness = None
    with scheduler.tracing(ticket):
        with gc_paused():
            shapes = jax.eval_shape(init, k_init)
        state, history = None, []
        if resume:  # the real seeds' shapes are the template: no wait for the initial state
            real = jax.tree_util.tree_map(lambda a: jax.ShapeDtypeStruct((layout.num,) + a.shape[1:], a.dtype),
                                          shapes)
            state, history = _restore(cfg, seeds, ckpt_dir, real, report)
        if history:
            report(f"resumed from iteration {len(history)}")
            state = layout.device(state)
        if len(history) < stop:
            step = _lowered("step", cfg, (shapes, it_keys[:, 0], jnp.asarray(True)), timer, scheduler,
                            layout.mesh)
    later = scheduler.tracing.later(ticket)
    if policies.spec_for(cfg) is not None and stop == cfg.iterations:
        def robustness_program():
            with scheduler.tracing(later):
                lowered = _lowered("robustness", cfg, (shapes.policy.params,), timer, scheduler, layout.mesh)
            # In a slot: beside training, but after the other runs' iteration programs, which then
            # compile with fewer competitors (benchmarks/RESULTS.md, twelfth session).
            compiled = _compiled("robustness", cfg, num, lowered, timer, scheduler, slot=True, mesh=layout.mesh)
            if stability:
                scheduler.pool.submit(warm_up_stability)
            return compiled

        def warm_up_stability():
            try:
                with timer("stability_warm_up_s"):
                    stability_lib.warm_up(cfg, shapes.policy.params)
            except Exception:  # noqa: BLE001 (only a head start: the measurement raises it again)
                pass
        robustness = scheduler.pool.submit(robustness_program)
    else:
        scheduler.tracing.release(later)
    if step is not None:
        step = _compiled("step", cfg, num, step, timer, scheduler, slot=True, mesh=layout.mesh)
    return (state_future.result() if state is None else state), history, step, robustness


def _failure(cfg: config.Config, it: int, metrics: dict, ckpt_dir: pathlib.Path) -> TrainingError:
    bad = np.argwhere(~np.asarray(metrics["ok"])).tolist()
    return TrainingError(
        f"iteration {it}: non-finite values or η at its limit in the C-step or S-step for "
        f"(seed index, condition) {bad}; the checkpoints of iterations ≤ {it - 1} in {ckpt_dir} "
        "are intact (try --precision float64, or other settings)")


def _seed_ok(metrics: dict) -> np.ndarray:
    """[S] bool: the seed's iteration succeeded for every condition."""
    ok = np.asarray(metrics["ok"])
    return ok.reshape(ok.shape[0], -1).all(axis=1)


def _kept(frozen: np.ndarray, new_state, state, layout: _Layout):
    """The state of the frozen seeds (``frozen`` [S]) from ``state``, the others' from ``new_state``."""
    keep = layout.device(jnp.asarray(~frozen))

    def pick(new, old):
        return jnp.where(keep.reshape(keep.shape + (1,) * (new.ndim - 1)), new, old)

    return jax.tree_util.tree_map(pick, new_state, state)


def _freeze(frozen: np.ndarray, new_state, state, metrics: dict, last: dict, layout: _Layout):
    """The failed seeds (``frozen`` [S]) keep their state and metrics of the last iteration; the
    others take the new ones. Returns (state, metrics)."""
    metrics = {k: np.where(frozen.reshape(frozen.shape + (1,) * (np.ndim(v) - 1)), np.asarray(last[k]), v)
               if k in last else v for k, v in metrics.items()}
    return _kept(frozen, new_state, state, layout), metrics


def _resolved(metrics):
    """The metrics of a step: a dict, or a future of one (:class:`_PartsStep`)."""
    return metrics.result() if isinstance(metrics, concurrent.futures.Future) else metrics


def _wait_quietly(*work) -> None:
    """Wait for work whose results will not be used (arrays, futures), so that none of it outlives
    its run; its own errors (e.g. from a state that failed) are not the run's."""
    try:
        jax.block_until_ready([w.result() if isinstance(w, concurrent.futures.Future) else w for w in work])
    except Exception:  # noqa: BLE001
        pass


@contextlib.contextmanager
def _written_after(write: concurrent.futures.Future | None):
    """Waits for ``write`` (a checkpoint's, or None) when the block ends; its error is raised, or
    added as a note to the block's own."""
    try:
        yield
    except BaseException as err:
        if write is not None:
            try:
                write.result()
            except Exception as write_error:  # noqa: BLE001 (the block's error goes on)
                err.add_note(f"also, writing a checkpoint failed: {write_error}")
        raise
    if write is not None:
        write.result()


def _train_loop(cfg, step, state, history, it_keys, stop, ckpt_dir, meta, layout: _Layout, timer, scheduler,
                progress_fn, label, t0, checkpoint_every: int = 1):
    """Iterations ``len(history) … stop − 1``: (state, history, iteration_s, last_write).

    An asynchronous step (``_PartsStep.asynchronous``: a split run's, whose host work runs in
    worker threads) is called for iteration i + 1 before iteration i's metrics are read, so that
    the devices get its programs while the host waits, reports and checkpoints; given the next
    keys it also calls the next rollouts ahead. Other steps are called one iteration at a time:
    their calls return only when their work is nearly done (a GPU's loops are driven from the
    calling thread; a CPU program with host callbacks runs in it), and a progress event then comes
    before the next iteration starts.

    A seed that fails is frozen: its state and metrics stay those of its last good iteration. An
    iteration called before the failure was known runs that seed from its failed state; its part
    is replaced (the seeds are independent), and later iterations run it from its kept state.

    The checkpoint of every ``checkpoint_every``-th iteration and of iteration ``stop`` is written
    by a thread of the scheduler's loop pool while the loop goes on, one at a time, in order; a
    failed write raises at the next one or at the end, and no later checkpoint is written. When
    every iteration up to ``stop`` is done, iteration ``stop``'s write may still be under way:
    ``last_write`` is its future (None where nothing is left to write), for which the caller
    waits (:func:`_written_after`) after the work that can go on beside it. A stop request lets
    the iteration under way finish and be checkpointed before this returns. An exception still
    writes the last finished iteration's checkpoint (a failed write then becomes a note of that
    exception), then waits for the iteration under way."""
    ahead_ok = getattr(step, "asynchronous", False)
    iteration_s, pending, ahead, writing, error, prefetched = [], None, None, None, None, {}
    finished, submitted = None, len(history)  # the last finished iteration's (step, state, history); written step
    keys = {it: it_keys[:, it] for it in range(len(history), stop)}  # one array each: prefetches match by identity

    def save(done: int, st, hist):
        with timer("checkpoint_s"):
            checkpoint.save(ckpt_dir, layout.real(st), step=done,
                            metadata={**meta, **history_metadata(hist)})

    def written():
        """Wait for the checkpoint being written; raises its error."""
        nonlocal writing
        if writing is not None:
            job, writing = writing, None
            job.result()

    def call(it: int, st):
        if ahead_ok and it + 1 < stop:
            return step(st, keys[it], jnp.asarray(it == 0), next_keys=keys[it + 1], prefetched=prefetched)
        return step(st, keys[it], jnp.asarray(it == 0))

    try:
        t_it = None
        for it in range(len(history), stop):
            if ahead is None:
                if scheduler.stop.is_set():
                    break
                t_it = time.perf_counter()
                if not iteration_s:  # the run's start-up (waits for its turns and slots included)
                    timer["training_start_s"] = t_it - t0
                ahead = call(it, state)
            (new_state, metrics), ahead = ahead, None
            failed = np.asarray(history[-1]["seed_failed"]) if history and "seed_failed" in history[-1] \
                else np.zeros(layout.num, bool)
            if ahead_ok and it + 1 < stop and not scheduler.stop.is_set():
                ahead = call(it + 1, _kept(failed, new_state, state, layout) if failed.any() else new_state)
            if pending is not None:  # cleared (and counted) first: after a failed write it is not tried below
                job, pending = pending, None
                submitted = job[0]
                written()
                writing = scheduler.loop_pool.submit(save, *job)
            metrics = _host(layout.real(_resolved(metrics)))
            iteration_s.append(time.perf_counter() - t_it)
            t_it += iteration_s[-1]
            frozen = failed | ~_seed_ok(metrics)
            if frozen.all() or (frozen.any() and not history):
                raise _failure(cfg, it + 1, metrics, ckpt_dir)
            if frozen.any():
                for i in np.flatnonzero(frozen & ~failed):
                    if progress_fn is not None:
                        progress_fn({"run": label, "message": (
                            f"seed {meta['seeds'][i]} failed in iteration {it + 1} (non-finite values or η "
                            f"at its limit); it stays at iteration {it} while the other seeds go on")})
                new_state, metrics = _freeze(frozen, new_state, state, metrics, history[-1], layout)
            metrics["seed_failed"] = frozen
            state = new_state
            history.append(metrics)
            finished = (it + 1, state, list(history))
            if (it + 1) % checkpoint_every == 0 or it + 1 == stop:
                pending = finished
            if progress_fn is not None:
                progress_fn({"run": label, "iteration": it + 1, "iterations": cfg.iterations,
                             "metrics": metrics})
    except BaseException as err:
        error = err
        raise
    finally:
        try:
            if error is None and len(history) == stop and pending is not None:  # done: the caller waits
                job, pending = pending, None
                submitted = job[0]
                written()
                writing = scheduler.loop_pool.submit(save, *job)
            else:
                written()
            if finished is not None and finished[0] != submitted:  # a stop's or error's
                submitted = finished[0]
                save(*finished)
        except Exception as write_error:
            if error is None:
                raise
            error.add_note(f"also, writing a checkpoint failed: {write_error}")
        finally:
            _wait_quietly(*(ahead or ()), *prefetched.values())
    if scheduler.stop.is_set() and len(history) < stop:
        if not history:
            raise Interrupted("stopped before its first iteration, with no checkpoint (--resume starts it "
                              "from the beginning)")
        raise Interrupted(f"stopped after iteration {len(history)} of {cfg.iterations}; "
                          f"its checkpoint is in {ckpt_dir}")
    return state, history, iteration_s, writing


def run_folder(out, scenario: str, algorithm: str) -> pathlib.Path:
    """The folder of one run inside a study's output folder ``out``."""
    return pathlib.Path(out) / f"{scenario}_{algorithm}"


class _ChildResult(NamedTuple):
    """The end of a run in its own process: its result, or the exception it raised."""

    result: dict | None
    error: BaseException | None


def _child_run(job: dict, events, stop_event) -> None:
    """A run in a process of its own (started by :func:`run_in_process`, with its
    :func:`child_environment`): progress events and then a :class:`_ChildResult` go to
    ``events``; ``stop_event`` carries the parent's stop request. Ctrl-C reaches the parent
    only (the child ignores SIGINT); SIGTERM (e.g. sent to the whole process group by ``timeout``
    or a batch system) and the parent's end are stop requests too: the child finishes its
    iteration in flight like the runs in the parent."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    os.environ.update(job["environment"])
    timeline.mark(f"process entry {job['label']}")  # read when JAX starts its backends
    if "JAX_PLATFORMS" in job["environment"]:  # read when JAX was imported (in the server)
        jax.config.update("jax_platforms", job["environment"]["JAX_PLATFORMS"])
    for name, value in job["jax_config"].items():
        jax.config.update(name, value)
    try:
        if job["niceness"]:
            os.nice(job["niceness"])
        store = None if job["program_store"] is None else program_store_lib.ProgramStore(job["program_store"])
        with Scheduler(job["compile_jobs"], job["devices"], switch_interval=None,
                       iteration_programs=job["iteration_programs"], program_store=store) as scheduler:
            parent = multiprocessing.parent_process()

            def forward_stop():
                # polled: a process that exits while waiting on a multiprocessing Event leaves the
                # parent's ``set`` waiting for it forever
                while not stop_event.is_set() and (parent is None or parent.is_alive()):
                    time.sleep(0.2)
                scheduler.request_stop()
            signal.signal(signal.SIGTERM, lambda signum, frame: scheduler.request_stop())
            threading.Thread(target=forward_stop, daemon=True).start()
            result = run(job["cfg"], job["seeds"], job["run_dir"], resume=job["resume"], progress_fn=events.put,
                         scheduler=scheduler, label=job["label"], stability=job["stability"],
                         checkpoint_every=job["checkpoint_every"])
        events.put(_ChildResult(result, None))
    except BaseException as err:  # noqa: BLE001 (raised again in the parent)
        try:
            pickle.dumps(err)
        except Exception:  # noqa: BLE001
            err = RuntimeError(f"{type(err).__name__}: {err}")
        events.put(_ChildResult(None, err))


def in_process_iteration_programs(choice: str, cfg: config.Config, platform: str = "cpu") -> str:
    """The ``iteration_programs`` of a run in a process of its own on ``platform``: on the host
    ("cpu"), "auto" is "parts" for a policy's run, else the choice as it is (the child resolves
    "auto" as this process would). With a program store (the CLI's default) every part but the
    two with host callbacks (rollouts, learning curve) then comes from the store instead of being
    traced in each new process: warm, the default run's MDGPS runs start training after ~2 s
    instead of ~5–6 s (benchmarks/RESULTS.md, twenty-fifth session)."""
    _check_iteration_programs(choice)
    if platform == "cpu" and choice == "auto" and policies.spec_for(cfg) is not None:
        return "parts"
    return choice


PROCESS_NICENESS = (0, 4, 10)
"""The niceness added to the processes of runs that share one GPU, by their place in
:func:`run_order` (:func:`niceness_by_order`). Their processes fill the host's cores only while
they compile; then the longest run gets the cores first and reaches the GPU sooner, and the
shorter runs, which compile later, still finish first. Their training uses the host too (C MuJoCo
rollouts, the split runs' host parts) but leaves cores free, so the lower priority did not slow
it (benchmarks/RESULTS.md, thirtieth session)."""

MAX_NICENESS = 19
"""The largest niceness a process can have (Linux): ``os.nice`` caps the sum there."""


def check_niceness(niceness) -> None:
    """Raises ValueError unless ``niceness`` is an integer 0 … :data:`MAX_NICENESS` (an increment
    for ``os.nice``) and this system can lower a process's priority (``os.nice`` exists)."""
    if isinstance(niceness, bool) or not isinstance(niceness, int) or not 0 <= niceness <= MAX_NICENESS:
        raise ValueError(f"niceness: {niceness!r} is not an integer from 0 to {MAX_NICENESS}")
    if niceness and not hasattr(os, "nice"):
        raise ValueError(f"niceness: {niceness}: this system has no os.nice; use 0")


def niceness_by_order(keys, levels=PROCESS_NICENESS) -> dict:
    """{key: niceness}: ``levels[i]`` for the i-th of ``keys`` (runs in :func:`run_order`, the
    longest first), the last level for every later one (``run_all``'s ``niceness``)."""
    if not levels:
        raise ValueError("niceness levels: none given")
    return {key: levels[min(i, len(levels) - 1)] for i, key in enumerate(keys)}


def run_order(configs) -> list:
    """The keys of ``configs`` ({(scenario, algorithm): Config}) in the order :func:`run_all`
    starts them: the longest runs first (a policy's S-step is the slowest, more conditions mean
    more data), so that they trace first and reach the device first."""
    return sorted(configs, key=lambda k: (configs[k].algorithm != "gmr", -configs[k].task.num_conditions))


def child_environment(platform: str | None, default_platform: str) -> dict:
    """The environment variables that a run in a process of its own on ``platform`` ("cpu", or
    None: this process's default devices, of ``default_platform``) starts with: JAX on the CPU
    only for the host; beside this process on a GPU, no preallocated pool (XLA's allocator takes
    what the run uses from the memory that this process's pool left free, a quarter of the GPU
    by default: ``XLA_PYTHON_CLIENT_MEM_FRACTION`` set before the command starts leaves more),
    and this process's CUDA MPS daemon as it is now (``gmr_jax.mps``: the process server may
    have started before the daemon)."""
    if platform == "cpu":
        return {"JAX_PLATFORMS": "cpu"}
    if default_platform == "gpu":
        return {"XLA_PYTHON_CLIENT_PREALLOCATE": "false",
                **{name: os.environ[name] for name in (mps.PIPE_VARIABLE, mps.LOG_VARIABLE) if name in os.environ}}
    return {}


# JAX settings a child run takes from its parent (the CLI sets them before the first computation):
# the compilation cache's, and every setting that changes what a trace computes, so that a run in a
# process of its own computes what it would here.
_CHILD_JAX_CONFIG = tuple(dict.fromkeys(("jax_compilation_cache_dir", "jax_persistent_cache_min_compile_time_secs")
                                        + program_store_lib.TRACE_SETTINGS))

def run_in_process(cfg: config.Config, seeds, run_dir, *, resume: bool = False,
                   progress_fn: ProgressFn | None = None, scheduler: Scheduler | None = None,
                   label: str = "", stability: bool = True, devices: int = 1,
                   platform: str | None = "cpu", niceness: int = 0, checkpoint_every: int = 1) -> dict:
    """:func:`run` in a process of its own (forked from ``multiprocessing``'s forkserver,
    ``process_server.start``; this process's JAX settings that change a trace (precision,
    matmul precision, PRNG), compilation cache and program store): its Python work (tracing,
    host callbacks, checkpoints) then does not share this interpreter's GIL with the other runs.
    Progress events come back to ``progress_fn``; the scheduler's stop request reaches the child
    (which finishes its iteration in flight); the child's exception is raised here.

    ``platform`` "cpu": JAX restricted to the host CPU there, the same computation as
    ``run(..., platform="cpu")`` on ``devices`` CPU devices. None: on the first ``devices`` of
    this process's default backend, as ``run`` here (a GPU's processes share it; the child's
    memory as :func:`child_environment` says). The iteration's programs as
    :func:`in_process_iteration_programs` resolves the scheduler's choice. ``niceness``: added
    to the child's, which is this process's (``os.nice``; the sum capped at 19): a lower share of
    the host's cores while the processes compete for them (:data:`PROCESS_NICENESS`).
    ``checkpoint_every``: see :func:`run`."""
    if platform not in ("cpu", None):
        raise ValueError(f"platform: {platform!r} is neither 'cpu' nor None (this process's devices)")
    check_niceness(niceness)
    check_checkpoint_every(checkpoint_every)
    default_platform = jax.default_backend()
    ctx = process_server.context()
    events, stop_event = ctx.Queue(), ctx.Event()
    job = {"cfg": cfg, "seeds": list(seeds), "run_dir": str(run_dir), "resume": resume, "label": label,
           "stability": stability, "devices": devices, "niceness": niceness, "checkpoint_every": checkpoint_every,
           "environment": {**child_environment(platform, default_platform), **timeline.environment()},
           "compile_jobs": 2 if scheduler is None else scheduler.compile_jobs,
           "iteration_programs": in_process_iteration_programs(
               "auto" if scheduler is None else scheduler.iteration_programs, cfg, platform or default_platform),
           "program_store": None if scheduler is None or scheduler.program_store is None
           else str(scheduler.program_store.directory),
           "jax_config": {name: getattr(jax.config, name) for name in _CHILD_JAX_CONFIG}}
    child = ctx.Process(target=_child_run, args=(job, events, stop_event), name=f"gmr-jax {label}", daemon=True)
    timeline.mark(f"process asked {label}")
    child.start()
    timeline.mark(f"process started {label}")
    finished = False
    try:
        while True:
            if scheduler is not None and scheduler.stop.is_set():
                stop_event.set()
            try:
                item = events.get(timeout=0.2)
            except queue.Empty:
                if not child.is_alive() and events.empty():
                    raise RuntimeError(f"{label or run_dir}: its process ended (exit code {child.exitcode}) "
                                       "without a result") from None
                continue
            if isinstance(item, _ChildResult):
                if item.error is not None:
                    raise item.error
                finished = True
                timeline.mark(f"result received {label}")
                return item.result
            if progress_fn is not None:
                progress_fn(item)
    finally:
        stop_event.set()
        if not finished:
            child.join(timeout=60)
        # else the child has written everything and sent its result; its interpreter's exit
        # (about a second) is no part of the run: multiprocessing reaps it later.


def run_all(configs: dict, seeds, out, *, resume: bool = False, jobs: int = 0,
            scheduler: Scheduler | None = None, progress_fn: ProgressFn | None = None,
            stability: bool = True, platforms: dict | None = None, processes=(),
            niceness: dict | None = None, checkpoint_every: int = 1) -> dict:
    """Train several configurations side by side (threads), each into ``run_folder(out, …)``.

    Args:
      configs: {(scenario, algorithm): Config}.
      seeds: the seeds of every run.
      out: the study's output folder.
      resume: see :func:`run`; without it every run folder must be free of checkpoints.
      jobs: runs trained at once (0: all). Side by side, the runs' XLA compilations use several
        cores and their iterations interleave on the device.
      scheduler: default a private one with 2 compile jobs; Python's thread switch interval is
        its ``switch_interval`` until the runs end.
      progress_fn: see the module docstring; events carry "scenario/algorithm" as ``run``.
      stability: see :func:`run`.
      platforms: {(scenario, algorithm): platform} for runs placed elsewhere than on the
        scheduler's devices (:func:`run`'s ``platform``, e.g. "cpu"); the others stay there.
      processes: the (scenario, algorithm) of runs trained in a process of their own
        (:func:`run_in_process`): on the host CPU where their ``platforms`` entry is "cpu", on
        the scheduler's devices where they have none.
      niceness: {(scenario, algorithm): niceness} added to the processes of runs among
        ``processes`` (``run_in_process``; e.g. ``niceness_by_order(run_order(configs))``); the
        others keep this process's.
      checkpoint_every: see :func:`run`.
    Returns:
      {(scenario, algorithm): the result of :func:`run`}.
    Raises:
      FolderTaken, TrainingError, Interrupted, checkpoint.CheckpointError (the first failing run's).
    """
    if not resume:
        check_fresh([run_folder(out, *key) for key in configs])
    processes = set(processes)
    bad = sorted(f"{s}/{a}" for s, a in processes if (s, a) not in configs or (platforms or {}).get((s, a), "cpu") != "cpu")
    if bad:
        raise ValueError(f"processes: {', '.join(bad)} not among the runs, or with a platforms entry other than "
                         "'cpu' (a process run on the scheduler's devices has none)")
    niceness = dict(niceness or {})
    apart = sorted(f"{s}/{a}" for s, a in niceness if (s, a) not in processes)
    if apart:
        raise ValueError(f"niceness: {', '.join(apart)} not trained in a process of its own (processes)")
    for value in niceness.values():
        check_niceness(value)
    check_checkpoint_every(checkpoint_every)
    if processes:
        process_server.start()  # in this thread (the main one, where signals can be set), not a run's
    if scheduler is None:
        with Scheduler() as own:
            return run_all(configs, seeds, out, resume=resume, jobs=jobs, scheduler=own,
                           progress_fn=progress_fn, stability=stability, platforms=platforms,
                           processes=processes, niceness=niceness, checkpoint_every=checkpoint_every)
    order = run_order(configs)
    scheduler.tracing.reset(len(configs) if not jobs or jobs >= len(configs) else 0)
    with (switch_interval(scheduler.switch_interval),
          concurrent.futures.ThreadPoolExecutor(max_workers=jobs or len(configs)) as pool):
        futures = {}
        for i, key in enumerate(order):
            label = f"{key[0]}/{key[1]}"
            if key in processes:  # traces in its own process: its turns here pass
                scheduler.tracing.release(i, scheduler.tracing.later(i))
                where = (platforms or {}).get(key)
                futures[key] = pool.submit(run_in_process, configs[key], seeds, run_folder(out, *key),
                                           resume=resume, progress_fn=progress_fn, scheduler=scheduler,
                                           label=label, stability=stability,
                                           devices=scheduler.mesh_for(where).size, platform=where,
                                           niceness=niceness.get(key, 0), checkpoint_every=checkpoint_every)
            else:
                futures[key] = pool.submit(run, configs[key], seeds, run_folder(out, *key), resume=resume,
                                           progress_fn=progress_fn, scheduler=scheduler, ticket=i, label=label,
                                           stability=stability, platform=(platforms or {}).get(key),
                                           checkpoint_every=checkpoint_every)
        try:
            return {key: futures[key].result() for key in configs}
        except Interrupted:
            # every run stops after its iteration in flight
            concurrent.futures.wait(futures.values())
            raise stopped_study_error({f"{key[0]}/{key[1]}": futures[key] for key in order}) from None
        except BaseException:
            scheduler.request_stop()  # the other runs end after their iteration in flight
            raise


def stopped_study_error(runs: dict) -> BaseException:
    """What a study raises once its runs have ended after a stop request; ``runs``: {label:
    finished future}. A run that failed (not stopped) is raised, so that its error is not taken
    for an interruption, with where every run stands as a note; otherwise an
    :class:`Interrupted` that says where each run stands."""
    parts, failed = [], None
    for label, future in runs.items():
        err = future.exception()
        if err is None:
            parts.append(f"{label} finished")
        elif isinstance(err, Interrupted):
            parts.append(f"{label} {err}")
        else:
            parts.append(f"{label} failed: {type(err).__name__}: {err}")
            failed = err if failed is None else failed
    if failed is not None:
        failed.add_note("; ".join(parts))
        return failed
    return Interrupted("; ".join(parts))


timeline.mark("runner imported")  # in the process server: its imports are done
