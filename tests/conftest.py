"""Test set-up: float64 numerics for every test, four CPU devices, and one runner scheduler."""

import ctypes.util
import os
import sys

# Four XLA CPU devices, so that the seed axis can be split over a device mesh
# (tests/test_sharding.py); every other computation runs on the first device as before. Set
# before JAX starts its backend.
_FLAGS = os.environ.get("XLA_FLAGS", "")
if "xla_force_host_platform_device_count" not in _FLAGS:
    os.environ["XLA_FLAGS"] = f"{_FLAGS} --xla_force_host_platform_device_count=4".strip()

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

