"""Constants of the Kinova Jaco 2 shared by the tasks on it (gmr-method.md §2).

The authors' Jaco configuration models each joint as q̈ = u / gain: the gains are torque per unit
acceleration, used by the initial controller (``init_lqr`` guesses the acceleration per unit
torque as 1/gain) and by the action cost (wu = 5e-3 / gain).
"""

from __future__ import annotations

from gmr_jax.config import InitLQRConfig

# Joints 1, 4, 5 and 6 turn without limit (jaco_mjcf: no range); 0-based indices.
CONTINUOUS_JOINTS = (0, 3, 4, 5)
GAINS = (7.09, 2.3, 1.5, 1.2, 1.8, 0.1)
ACTION_WEIGHT = tuple(5e-3 / g for g in GAINS)
# init_lqr with the authors' Jaco values: init_var 1, stiffness 1, stiffness_vel 0.25,
# final_weight 50 (the toolbox defaults) and the guessed dynamics of the gains above.
INIT_LQR = InitLQRConfig(init_acc=(0.0,) * len(GAINS), init_gains=tuple(1.0 / g for g in GAINS))
