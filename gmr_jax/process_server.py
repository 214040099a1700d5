"""The server that runs in processes of their own are forked from (``runner.run_in_process``).

``multiprocessing``'s forkserver, started once per command with :data:`PRELOADED` imported: a
child starts without importing JAX, MuJoCo and this package again (about 2 s on an H100
machine's host, benchmarks/RESULTS.md, twenty-eighth session). This module imports nothing of
JAX, so that a command can start the server before it imports JAX itself: the two imports then
run at once (:func:`start_where_a_gpu_is`, thirty-first session).
"""

from __future__ import annotations

import multiprocessing
import multiprocessing.forkserver
import os
import pathlib
import signal
import threading

PRELOADED = ("gmr_jax.runner",)
"""The modules that the server imports once, before it forks children."""


def context():
    """The forkserver's context, or spawn's where the platform has no forkserver (Windows): the
    child applies its environment itself (``runner.child_environment``), so either way it
    computes the same."""
    if "forkserver" not in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context("spawn")
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(list(PRELOADED))  # only read when the server starts
    return ctx


def start() -> None:
    """Start the server (with :data:`PRELOADED` imported), so that it imports while this
    process prepares its runs; ``runner.run_in_process`` starts it itself otherwise (nothing to
    start without a forkserver). It inherits this process's environment (XLA_FLAGS: set it
    first), ends with this process, and idles until a child is asked for."""
    if context().get_start_method() != "forkserver":
        return
    if threading.current_thread() is not threading.main_thread():
        multiprocessing.forkserver.ensure_running()
        return
    # Started with SIGINT and SIGTERM ignored (kept across its exec): a Ctrl-C while it imports
    # reaches this process only, and a SIGTERM to the whole process group (``timeout``, a batch
    # system) leaves it alive: without it this process could no longer learn how its children
    # are (their exit code reads 255) and would take them for dead while they finish their
    # iteration. It ends with this process all the same.
    before = {sig: signal.signal(sig, signal.SIG_IGN) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        multiprocessing.forkserver.ensure_running()
    finally:
        for sig, handler in before.items():
            signal.signal(sig, handler)


def gpu_allowed() -> bool:
    """Whether JAX may start a CUDA backend here (``JAX_PLATFORMS`` unset or naming it)."""
    wanted = os.environ.get("JAX_PLATFORMS", "").lower()
    return not wanted or any(name in wanted for name in ("cuda", "gpu"))


def gpu_present(dev: str = "/dev") -> bool:
    """Whether JAX may find an NVIDIA GPU here: :func:`gpu_allowed`, ``CUDA_VISIBLE_DEVICES``
    not empty or -1, and a GPU's device file (``nvidia0``, …) exists. Reads no library: it
    answers before JAX is imported."""
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    if visible is not None and visible.strip() in ("", "-1"):
        return False
    return gpu_allowed() and any(pathlib.Path(dev).glob("nvidia[0-9]*"))


def start_where_a_gpu_is(argv: list[str]) -> bool:
    """:func:`start` where :func:`gpu_present` (the machines where the command line trains some
    runs in processes of their own by default) and the command's arguments ``argv`` do not ask
    for its help; returns whether it did. For a command's first lines, before it imports JAX:
    the server's imports then overlap the command's own (``experiments.reach``); where no run
    asks for a child, the server stays idle and ends with the command."""
    if any(a in ("-h", "--help") for a in argv) or not gpu_present():
        return False
    start()
    return True
