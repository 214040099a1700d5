"""Test set-up: float64 numerics and a persistent compilation cache (MJX compiles slowly on CPU)."""

import os
import pathlib

import jax

jax.config.update("jax_enable_x64", True)
_cache = pathlib.Path(os.environ.get("GMR_JAX_TEST_CACHE", pathlib.Path(__file__).parent.parent / ".jax_cache"))
jax.config.update("jax_compilation_cache_dir", str(_cache))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
