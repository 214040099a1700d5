"""gmr-jax: JAX-native mirror-descent Guided Policy Search with Generative Motor Reflexes."""

import importlib

from gmr_jax import config

__all__ = ["config", "types"]
__version__ = "0.1.0"


def __getattr__(name: str):
    # ``types`` imports JAX: loaded when first used, so that the package's JAX-free modules
    # (``config``, ``mps``, ``process_server``) import without it
    if name == "types":
        return importlib.import_module("gmr_jax.types")
    raise AttributeError(f"module 'gmr_jax' has no attribute {name!r}")
