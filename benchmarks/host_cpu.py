"""Where a command's host CPU time goes: every thread of its process tree, sampled from /proc.

Runs the command given after ``--`` and reads ``/proc/<pid>/task/<tid>/stat`` of the command
and of all its descendants every ``--interval`` seconds (Linux only). Reports the command's
wall time, its CPU-seconds (user + system) in all, per thread-name group (the kernel's 15-character
thread name with trailing digits and separators removed: XLA's compiler and executor pools,
the runs' Python threads, C MuJoCo's workers) and per interval, so that one can tell whether
the host's cores were busy and with what::

    python -m benchmarks.host_cpu --out cpu.json -- python -m experiments.reach --out /tmp/s

``cpu_s_seen`` sums each thread's counters at its last sample: it misses the threads that start
and end between two samples, a thread's time after its last sample, processes that leave the
tree (a daemon's double fork) and whatever runs on after the command itself has ended.
``cpu_s_children`` is what the kernel credits to the command when it ends: its own time and
that of the descendants it (or they) waited for, so not the children of a ``multiprocessing``
forkserver, which nobody waits for. Either can be the larger. The command's exit status is
this command's (128 + N for a command killed by signal N, as a shell reports it).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import pathlib
import platform
import re
import shutil
import subprocess
import sys
import time

TICK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def _children(pid: int) -> list[int]:
    """The pids of ``pid``'s children (all its threads' ``children`` lists)."""
    out = []
    for tid in _tasks(pid):
        try:
            out += [int(c) for c in pathlib.Path(f"/proc/{pid}/task/{tid}/children").read_text().split()]
        except OSError:  # ended meanwhile
            pass
    return out


def _tasks(pid: int) -> list[str]:
    """The thread ids of ``pid`` (none once it has ended)."""
    try:
        return os.listdir(f"/proc/{pid}/task")
    except OSError:
        return []


def process_tree(pid: int) -> list[int]:
    """``pid`` and all its descendants alive now."""
    tree, todo = [], [pid]
    while todo:
        p = todo.pop()
        tree.append(p)
        todo += _children(p)
    return tree


def thread_times(pids) -> dict:
    """{(pid, tid, start tick): (thread name, CPU-seconds so far)} for every thread of ``pids``
    (the start time tells a reused thread id from the thread that had it before)."""
    out = {}
    for pid in pids:
        for tid in _tasks(pid):
            try:
                stat = pathlib.Path(f"/proc/{pid}/task/{tid}/stat").read_text()
            except OSError:  # ended meanwhile
                continue
            name = stat[stat.index("(") + 1:stat.rindex(")")]
            # the fields after the name, from the state (field 3 of proc(5)): utime 14, stime 15, starttime 22
            fields = stat[stat.rindex(")") + 2:].split()
            out[(pid, int(tid), int(fields[19]))] = (name, (int(fields[11]) + int(fields[12])) / TICK)
    return out


def group(name: str) -> str:
    """A thread name without its numbering: ``gmr-jax_3`` → ``gmr-jax``, ``XLAEigen/12`` → ``XLAEigen``."""
    return re.sub(r"[-_/:.]?\d+$", "", name) or name


def cpu_model() -> str:
    """The host CPU's model name (``/proc/cpuinfo``), else ``platform.machine()``."""
    try:
        lines = pathlib.Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        lines = []
    return next((line.split(":", 1)[1].strip() for line in lines if line.startswith("model name")),
                platform.machine())


def sample(cmd: list[str], interval: float) -> dict:
    """Run ``cmd`` and sample its threads every ``interval`` s; returns the report (see module)."""
    before = os.times()
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd)
    last: dict = {}
    series = []
    while True:
        done = proc.poll() is not None
        now = thread_times(process_tree(proc.pid)) if not done else {}
        if now:
            busy = sum(cpu - last.get(key, (None, 0.0))[1] for key, (_, cpu) in now.items())
            series.append([round(time.perf_counter() - t0, 2), round(busy, 2)])
            last.update(now)
        if done:
            break
        time.sleep(interval)
    wall = time.perf_counter() - t0
    groups: dict = {}
    for name, cpu in last.values():
        g = groups.setdefault(group(name), {"threads": 0, "cpu_s": 0.0})
        g["threads"] += 1
        g["cpu_s"] = round(g["cpu_s"] + cpu, 2)
    seen = sum(g["cpu_s"] for g in groups.values())
    after = os.times()
    children = (after.children_user - before.children_user) + (after.children_system - before.children_system)
    rc = proc.returncode
    return {"command": cmd, "returncode": 128 - rc if rc < 0 else rc, "wall_s": round(wall, 2),
            "cpu_s_seen": round(seen, 2), "cpu_s_children": round(children, 2),
            "cores": len(os.sched_getaffinity(0)), "cpu": cpu_model(),
            "groups": dict(sorted(groups.items(), key=lambda kv: -kv[1]["cpu_s"])),
            "interval_s": interval, "series": series}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--interval", type=float, default=0.5, help="seconds between samples (default 0.5)")
    parser.add_argument("--out", help="write the report as JSON here")
    parser.add_argument("command", nargs=argparse.REMAINDER, help="-- then the command to run")
    args = parser.parse_args(argv)
    cmd = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not cmd:
        parser.error("no command given: put it after --, e.g. -- python -m experiments.reach")
    if not pathlib.Path("/proc/self/task").exists():
        parser.error("this needs Linux's /proc; run it on Linux")
    if not (math.isfinite(args.interval) and args.interval > 0):
        parser.error(f"--interval {args.interval}: must be a positive number of seconds")
    if args.out and not pathlib.Path(args.out).resolve().parent.is_dir():
        parser.error(f"--out {args.out}: its folder does not exist; create it first")
    if shutil.which(cmd[0]) is None:
        parser.error(f"{cmd[0]}: no such command (not a file, not on PATH)")
    report = sample(cmd, args.interval)
    busy = max(report["cpu_s_children"], report["cpu_s_seen"])  # a forkserver's children are not waited for
    print(f"{' '.join(cmd)}\n  wall {report['wall_s']:.1f} s on {report['cores']} cores ({report['cpu']}); "
          f"CPU {report['cpu_s_children']:.1f} s in all (the waited-for processes), {report['cpu_s_seen']:.1f} s "
          f"in the threads sampled = {busy / max(report['wall_s'], 1e-9):.2f} cores busy on average")
    for name, g in report["groups"].items():
        if g["cpu_s"] >= 0.5:
            print(f"  {name:<18} {g['threads']:4d} threads {g['cpu_s']:8.1f} CPU-s")
    if args.out:
        pathlib.Path(args.out).write_text(json.dumps(report, indent=1))
    return report["returncode"]


if __name__ == "__main__":
    sys.exit(main())
