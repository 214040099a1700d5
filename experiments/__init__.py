"""The studies and tools on top of ``gmr_jax`` (``python -m experiments.<name>``)."""

import ctypes.util
import os
import sys

# MuJoCo picks its OpenGL backend when first imported: offscreen EGL (a GPU's, or Mesa's on a CPU)
# for the rollout pictures (gmr_jax.render), unless the user chose one.
# Only where libEGL exists: without it PyOpenGL's EGL import raises inside ``import mujoco``.
if sys.platform.startswith("linux") and ctypes.util.find_library("EGL"):
    os.environ.setdefault("MUJOCO_GL", "egl")
