"""The studies and tools on top of ``gmr_jax`` (``python -m experiments.<name>``)."""

import os
import sys

# MuJoCo picks its OpenGL backend when first imported: offscreen EGL (a GPU's, or Mesa's on a CPU)
# for the rollout pictures (gmr_jax.render), unless the user chose one.
if sys.platform.startswith("linux"):
    os.environ.setdefault("MUJOCO_GL", "egl")
