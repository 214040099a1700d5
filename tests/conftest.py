"""Test set-up: float64 numerics for every test, four CPU devices, a fast-compiling CPU code
generator, and one runner scheduler."""

import ctypes.util
import importlib.metadata
import importlib.util
import os
import re
import sys

# Four XLA CPU devices, so that the seed axis can be split over a device mesh
# (tests/test_sharding.py); every other computation runs on the first device as before. Set
# before JAX starts its backend.
#
# The suite's time on a CPU is mostly XLA's compilation of hundreds of small programs, and most of
# that is LLVM optimising the generated code. The tests compile with LLVM's optimisation level 0
# and without XLA's CPU fusion emitters (the option the runner compiles its CPU programs with,
# ``sharding.CPU_COMPILER_OPTIONS``): the suite takes less than half the time (benchmarks/RESULTS.md,
# thirty-fourth session). Both change how XLA generates code, so round-off may differ from the
# default code generator's; the suite compares programs compiled the same way, or within a
# tolerance measured from the computation, and the tests whose property is about the default code
# generator compile with it (``tolerances.XLA_DEFAULT_CPU_CODEGEN``). A flag already in XLA_FLAGS
# wins (e.g. ``XLA_FLAGS=--xla_backend_optimization_level=3``, XLA's default).
_TEST_FLAGS = {"xla_force_host_platform_device_count": "4",
               "xla_backend_optimization_level": "0",
               "xla_cpu_use_fusion_emitters": "false"}
# A GPU plugin's XLA (jax-cuda12/13-plugin: the ``jax_plugins`` namespace or entry points) parses
# XLA_FLAGS too and aborts on a flag it does not know, the CPU code generator's included, before a
# test runs. The GPU-only tests (run by hand on a GPU) then keep XLA's default CPU code generator.
if importlib.util.find_spec("jax_plugins") is not None or importlib.metadata.entry_points(group="jax_plugins"):
    del _TEST_FLAGS["xla_cpu_use_fusion_emitters"]
_FLAGS = os.environ.get("XLA_FLAGS", "")
os.environ["XLA_FLAGS"] = " ".join([_FLAGS] + [f"--{name}={value}" for name, value in _TEST_FLAGS.items()
                                               if not re.search(rf"--{name}(=|\s|$)", _FLAGS)]).strip()

# Offscreen rendering (gmr_jax.render) needs the backend chosen before MuJoCo's first import.
# Only where libEGL exists: without it PyOpenGL's EGL import raises inside ``import mujoco``.
if sys.platform.startswith("linux") and ctypes.util.find_library("EGL"):
    os.environ.setdefault("MUJOCO_GL", "egl")

import experiments  # noqa: E402,F401  (the CLI's XLA flags, before JAX: experiments/xla_flags.py)
import jax  # noqa: E402
import pytest  # noqa: E402

# The persistent compilation cache stays off: executables that contain host callbacks (the
# C MuJoCo backend) are not safe to share through it, and every CI run starts from a clean clone.
jax.config.update("jax_enable_x64", True)


@pytest.fixture(scope="session")
def scheduler():
    """One runner scheduler for every test of a test process (the README's command runs two,
    pytest-xdist's workers): runs of the same configuration share its compiled programs (each
    compilation costs tens of seconds on the CPU)."""
    from gmr_jax import runner

    with runner.Scheduler(compile_jobs=1, devices=1) as shared:
        yield shared


@pytest.fixture(scope="module", autouse=True)
def _release_compiled_programs():
    """Drop JAX's compiled programs after each test module. The suite compiles hundreds of
    programs (MJX rollouts among them); holding all of them for the whole session, the full suite
    aborted inside XLA while compiling at about 85 % (twice, at the same test, which passes alone
    and after the modules before it in smaller groups)."""
    yield
    import gc

    jax.clear_caches()
    gc.collect()

