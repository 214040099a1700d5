"""Test set-up: float64 numerics for every test, and one runner scheduler for the session."""

import jax
import pytest

# The persistent compilation cache stays off: executables that contain host callbacks (the
# C MuJoCo backend) are not safe to share through it, and every CI run starts from a clean clone.
jax.config.update("jax_enable_x64", True)


@pytest.fixture(scope="session")
def scheduler():
    """One runner scheduler for every test: runs of the same configuration share its compiled
    programs (each compilation costs tens of seconds on the CPU)."""
    from gmr_jax import runner

    with runner.Scheduler(compile_jobs=1) as shared:
        yield shared
