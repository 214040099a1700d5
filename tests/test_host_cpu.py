"""The host CPU sampler (benchmarks.host_cpu): thread names grouped without their numbers, and
the CPU time of a grandchild's thread seen as the thread itself measured it."""

import pathlib
import sys
import textwrap

import pytest

from benchmarks import host_cpu

pytestmark = pytest.mark.skipif(not pathlib.Path("/proc/self/task").exists(), reason="needs Linux's /proc")


@pytest.mark.parametrize("name, expected", [("gmr-jax_3", "gmr-jax"), ("tf_XLAEigen", "tf_XLAEigen"),
                                            ("XLAEigen/12", "XLAEigen"), ("python", "python"), ("7", "7")])
def test_thread_names_are_grouped_without_their_numbers(name, expected):
    assert host_cpu.group(name) == expected


def test_a_command_killed_by_a_signal_exits_as_a_shell_reports_it():
    report = host_cpu.sample([sys.executable, "-c", "import os, signal; os.kill(os.getpid(), signal.SIGTERM)"], 0.05)
    assert report["returncode"] == 128 + 15


def test_a_grandchild_threads_cpu_time_is_seen(tmp_path):
    burnt = tmp_path / "burnt"
    grandchild = textwrap.dedent(f"""
        import pathlib, time
        pathlib.Path("/proc/self/comm").write_text("burner-7")
        x = 0
        while time.thread_time() < 0.4:
            x += 1
        pathlib.Path({str(burnt)!r}).write_text(repr(time.thread_time()))
        time.sleep(0.6)  # sampled again after the burn
    """)
    child = f"import subprocess, sys; subprocess.run([sys.executable, '-c', {grandchild!r}], check=True)"
    report = host_cpu.sample([sys.executable, "-c", child], interval=0.05)
    assert report["returncode"] == 0
    measured = float(burnt.read_text())
    tick = 1 / host_cpu.TICK
    # /proc counts whole clock ticks per thread; the thread measured itself before its last tick
    assert report["groups"]["burner"]["cpu_s"] >= measured - 2 * tick
    # and not counted twice: after measuring itself the thread only writes a file and sleeps
    assert report["groups"]["burner"]["cpu_s"] <= measured + 0.1
    threads = sum(g["threads"] for g in report["groups"].values())
    # every thread seen belongs to a process this one waited for, so its time is in the children's
    assert report["cpu_s_seen"] <= report["cpu_s_children"] + threads * tick
