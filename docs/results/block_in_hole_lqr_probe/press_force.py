"""Depth of the block after a constant downward push of F newtons for 4 s, for variants of the
press-fit nubs (interference, friction): the probe behind benchmarks/RESULTS.md ("Block-in-hole:
the LQR base layer"). Run from the repository root: python docs/results/block_in_hole_lqr_probe/press_force.py"""
import sys

import mujoco
import numpy as np

sys.path[:0] = ["tests", "."]
import test_block_in_hole_scene as t  # noqa: E402
from experiments import block_in_hole_poses as bp  # noqa: E402


def variant(interference: float, friction: float) -> mujoco.MjModel:
    spec = mujoco.MjSpec.from_file(str(bp.SCENE))
    for g in spec.geoms:
        if g.name.startswith("nub_"):
            p = np.array(g.pos, dtype=float)
            ax = 0 if abs(p[0]) > abs(p[1]) else 1
            p[ax] = np.sign(p[ax]) * (0.020 - interference + 0.005)  # block half-width + nub radius
            g.pos = p
    for pr in spec.pairs:
        if pr.geomname2.startswith("nub_"):
            pr.friction = [friction, friction, 0.005, 0.0001, 0.0001]
    return spec.compile()


for interference, friction in ((2e-4, 0.3), (1e-4, 0.3), (5e-5, 0.3), (5e-5, 0.15), (1e-4, 0.1), (5e-5, 0.1),
                               (2e-5, 0.1), (5e-5, 0.05)):
    m = variant(interference, friction)
    print(f"interference {interference * 1e3:.2f} mm, friction {friction}: depth (mm) after 4 s at F N:",
          [(F, round(1e3 * t._push_down(m, F), 1)) for F in (0.5, 1.0, 2.0, 3.0, 5.0, 8.0)], flush=True)
