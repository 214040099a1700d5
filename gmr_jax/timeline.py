"""Wall-clock marks of a command and of the processes it starts: where its start and end go.

With ``GMR_JAX_TIMELINE=FILE`` in the environment, :func:`mark` appends one line
``<unix time> <pid> <label>`` to FILE, in one ``write`` to a file opened for appending, so that
the command, the process server and the runs' processes (which get the variable from
``runner.run_in_process``) can share the file; without it, nothing is written.
``python -m benchmarks.timeline FILE`` prints a file's marks from the command's start
(benchmarks/RESULTS.md, thirty-first session). Imports no JAX, so that a command can mark its
first lines.
"""

from __future__ import annotations

import os
import time

VARIABLE = "GMR_JAX_TIMELINE"


def environment() -> dict:
    """The variable as this process has it ({} where unset), for the processes it starts."""
    return {VARIABLE: os.environ[VARIABLE]} if os.environ.get(VARIABLE) else {}


def mark(label: str, at: float | None = None) -> None:
    """Append ``label`` with the wall time (``at``, a ``time.time()`` value, else now) and this
    process's id to the timeline file, where ``GMR_JAX_TIMELINE`` names one."""
    path = os.environ.get(VARIABLE)
    if not path:
        return
    line = f"{time.time() if at is None else at:.6f} {os.getpid()} {label}\n".encode()
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        os.write(fd, line)
    finally:
        os.close(fd)


def read(path) -> list[tuple[float, int, str]]:
    """A timeline file's marks, (wall time, process id, label), in the order they were written."""
    marks = []
    with open(path) as f:
        for line in f:
            when, pid, label = line.rstrip("\n").split(" ", 2)
            marks.append((float(when), int(pid), label))
    return marks
