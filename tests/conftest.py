"""Test set-up: float64 numerics for every test."""

import jax

# The persistent compilation cache stays off: executables that contain host callbacks (the
# C MuJoCo backend) are not safe to share through it, and every CI run starts from a clean clone.
jax.config.update("jax_enable_x64", True)
