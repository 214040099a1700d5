"""gmr-jax: JAX-native mirror-descent Guided Policy Search with Generative Motor Reflexes."""

from gmr_jax import config, types

__all__ = ["config", "types"]
__version__ = "0.1.0"
