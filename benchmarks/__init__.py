"""Benchmarks of gmr_jax (``python -m benchmarks.<name>``); raw results beside RESULTS.md."""

# The command line's XLA flags go into XLA_FLAGS before a benchmark imports JAX
# (experiments/xla_flags.py).
import experiments  # noqa: F401
