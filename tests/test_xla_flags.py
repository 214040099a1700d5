"""The command line's XLA flags reach XLA: they are in XLA_FLAGS before JAX is imported.

XLA reads XLA_FLAGS once; on a GPU a flag set after ``import jax`` is not seen (an H100 run
autotuned and two cold runs differed while the environment named autotuning off,
benchmarks/RESULTS.md). A CPU cannot show that, so these tests check the order of events and
the values; the GPU effect is measured by ``python -m benchmarks.determinism``.
"""

import os
import subprocess
import sys

import jax
import pytest

from experiments import cli, xla_flags

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _after_import(module: str, *argv: str, xla: str | None = None) -> tuple[str, str]:
    """(XLA_FLAGS, flags added after JAX's import) in a fresh process that imported ``module``
    with command-line arguments ``argv``."""
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    if xla is not None:
        env["XLA_FLAGS"] = xla
    code = (f"import os, {module}; from experiments import xla_flags; "
            "print(os.environ['XLA_FLAGS']); print(repr(xla_flags.added_after_jax))")
    out = subprocess.run([sys.executable, "-c", code, *argv], cwd=ROOT, env=env, check=True,
                         capture_output=True, text=True).stdout.splitlines()
    return out[-2], out[-1]


def test_the_cli_and_the_benchmarks_set_the_flags_before_jax():
    for module in ("experiments.reach", "benchmarks.determinism"):
        flags, late = _after_import(module)
        assert xla_flags.AUTOTUNE_OFF in flags.split() and xla_flags.DETERMINISTIC in flags.split(), module
        assert late == "''", f"{module}: flags added after JAX was imported: {late}"


def test_the_arguments_choose_the_flags_and_xla_flags_wins():
    flags, _ = _after_import("experiments", "--autotune", "--nondet")  # an abbreviation, as argparse allows
    assert flags == ""
    flags, _ = _after_import("experiments", "--nondeterministic")
    assert flags == xla_flags.AUTOTUNE_OFF
    flags, _ = _after_import("experiments", xla="--xla_gpu_autotune_level=2")
    assert flags.split() == ["--xla_gpu_autotune_level=2", xla_flags.DETERMINISTIC]


def test_setup_jax_refuses_flags_that_came_after_jax_on_a_gpu(monkeypatch):
    precision = "float64" if jax.config.jax_enable_x64 else "float32"
    monkeypatch.setenv("XLA_FLAGS", xla_flags.with_cli_flags(""))
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert cli.setup_jax(precision) == precision  # present before JAX: fine
    monkeypatch.setattr(xla_flags, "added_after_jax", xla_flags.DETERMINISTIC)
    with pytest.raises(RuntimeError, match="after JAX was imported"):
        cli.setup_jax(precision)
    monkeypatch.setattr(xla_flags, "added_after_jax", "")
    monkeypatch.setenv("XLA_FLAGS", "")
    with pytest.raises(RuntimeError, match="xla_gpu_autotune_level=0"):
        cli.setup_jax(precision)
    monkeypatch.setattr(jax, "default_backend", lambda: "cpu")
    assert cli.setup_jax(precision) == precision  # a CPU ignores the GPU flags
