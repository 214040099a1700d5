"""The studies and tools on top of ``gmr_jax`` (``python -m experiments.<name>``)."""

import ctypes.util
import os
import sys

from experiments import xla_flags

# XLA reads XLA_FLAGS when JAX loads its GPU plugin (at ``import jax``): the CLI's GPU flags must be
# there before any module of the package imports JAX (experiments/xla_flags.py).
xla_flags.set_before_jax(sys.argv[1:])

# MuJoCo picks its OpenGL backend when first imported: offscreen EGL (a GPU's, or Mesa's on a CPU)
# for the rollout pictures (gmr_jax.render), unless the user chose one.
# Only where libEGL exists: without it PyOpenGL's EGL import raises inside ``import mujoco``.
if sys.platform.startswith("linux") and ctypes.util.find_library("EGL"):
    os.environ.setdefault("MUJOCO_GL", "egl")
