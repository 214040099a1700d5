"""Poses of the block-in-hole task (scenarios C and D): ``python -m experiments.block_in_hole_poses``.

Derives, with C MuJoCo only, from ``jaco_mjcf/block_in_hole.xml``:

* the inserted pose q*: the block's tip on the hole bottom (50 mm below the rim), its axis
  vertical and its faces parallel to the hole's walls (a square block must be yaw-aligned);
* conditions C and D: the arm at rest with the block above the hole, C 60 mm and D 120 mm above
  the rim. Their lateral offsets are not picked by hand: each is solved so that the straight
  line in joint space from the condition to q* (what a controller that moves towards q* in
  joint space roughly follows) passes 5 mm above the rim within 0.1 mm of the hole axis, so
  moving towards q* moves the block down into the hole. A joint-space line is not a
  Cartesian one: it bows sideways by several millimetres over these distances, which is what
  the offsets compensate;
* a check that a 20 Hz time-varying linear controller (the class GPS learns) inserts the block
  from C and from D within T = 80 steps of 50 ms under the torque limits (``scripted_insertion``).

Importable: :func:`collision_free` (rejection sampling of robustness states), :func:`solve_ik`,
:func:`inserted_pose`, :func:`condition_pose`, :func:`scripted_insertion`, :func:`block_depth`.

Joint angles are Kinova actuator angles (the convention of jaco2.xml and of the reach
conditions), in radians.
"""

from __future__ import annotations

import copy
import pathlib

import mujoco
import numpy as np
import scipy.linalg

from gmr_jax.tasks import block_in_hole as task

SCENE = pathlib.Path(__file__).resolve().parent.parent / "jaco_mjcf" / "block_in_hole.xml"
BLOCK_SITES = task.BLOCK_POINTS
HOLE_DEPTH = task.HOLE_DEPTH  # m, rim (the top edge of the lead-in) to the hole bottom
# m above the rim: where the joint-space line from C or D to q* is solved to cross the hole axis
# (the lead-in chamfer starts at the rim)
ENTRY_HEIGHT = 0.005
INSERTED_DEPTH = task.INSERTED_FRACTION * task.HOLE_DEPTH  # m, the tip this far below the rim: inserted
# Block yaw (rotation about the vertical) at q*: the block's faces are parallel to the walls for
# any multiple of pi/2; -pi/2 is the one that leaves joint 6 nearest to zero (-0.34 rad).
YAW = -np.pi / 2
SEED = np.array([-1.71, 3.89, 1.40, -0.20, 0.76, -0.34])  # near q*, elbow up, wrist not flipped
C_HEIGHT, D_HEIGHT = 0.06, 0.12  # m, tip above the rim at conditions C and D
CONTROL_DT, SUBSTEPS, HORIZON = 0.05, 25, 80


def _model(model_or_path=None) -> mujoco.MjModel:
    if isinstance(model_or_path, mujoco.MjModel):
        return model_or_path
    return mujoco.MjModel.from_xml_path(str(model_or_path or SCENE))


def rotz(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def hole_rim(m: mujoco.MjModel) -> np.ndarray:
    """World position of the rim centre (site ``hole_rim``) [3]."""
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    return d.site("hole_rim").xpos.copy()


def _pose(m, d, q):
    """(tip position [3], link_6 rotation [3, 3]) at joint angles q."""
    d.qpos[:] = q
    mujoco.mj_kinematics(m, d)
    mujoco.mj_comPos(m, d)
    return d.site("block_tip").xpos.copy(), d.body("link_6").xmat.reshape(3, 3).copy()


def _rot_error(R: np.ndarray, R_target: np.ndarray) -> np.ndarray:
    """Small-angle rotation vector taking R to R_target (world frame) [3]."""
    return 0.5 * sum(np.cross(R[:, i], R_target[:, i]) for i in range(3))


def solve_ik(m: mujoco.MjModel, p_tip: np.ndarray, R_link6: np.ndarray, q_seed=SEED,
             iters: int = 200, damping: float = 1e-6) -> np.ndarray:
    """Joint angles that put the block tip at p_tip with link_6 at rotation R_link6.

    Damped least squares on the 6-D error (tip position, link_6 orientation) with the site
    Jacobian ``mj_jacSite``; from a seed near q* it converges in a few iterations.

    Raises:
      RuntimeError: no convergence to 1e-10 (position m, orientation rad).
    """
    d = mujoco.MjData(m)
    q = np.array(q_seed, dtype=np.float64)
    jp, jr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
    sid = m.site("block_tip").id
    for _ in range(iters):
        p, R = _pose(m, d, q)
        e = np.concatenate([p_tip - p, _rot_error(R, R_link6)])
        if np.linalg.norm(e) < 1e-10:
            return q
        mujoco.mj_jacSite(m, d, jp, jr, sid)
        J = np.vstack([jp, jr])
        q = q + np.clip(J.T @ np.linalg.solve(J @ J.T + damping * np.eye(6), e), -0.1, 0.1)
    raise RuntimeError(f"IK did not converge (error {np.linalg.norm(e):.2e})")


def tip_pose(m: mujoco.MjModel, offset) -> np.ndarray:
    """Joint angles with the block vertical, yaw-aligned, its tip at rim centre + offset [3]."""
    return solve_ik(m, hole_rim(m) + np.asarray(offset, dtype=np.float64), rotz(YAW))


def inserted_pose(m: mujoco.MjModel) -> np.ndarray:
    """q*: the block fully inserted, its tip on the hole bottom."""
    return tip_pose(m, (0.0, 0.0, -HOLE_DEPTH))


def block_depth(m: mujoco.MjModel, q, d: mujoco.MjData | None = None) -> float:
    """Depth of the block tip below the rim (m; negative above it) at joint angles q."""
    d = d or mujoco.MjData(m)
    return float(hole_rim(m)[2] - _pose(m, d, q)[0][2])


def _line_crossing(m, q0, q1, height=ENTRY_HEIGHT, n=4001):
    """Tip offset from the hole axis where the joint-space line q0 -> q1 descends through
    ``height`` above the rim: (s, lateral offset [2], tilt+yaw error of link_6 [rad])."""
    d = mujoco.MjData(m)
    rim = hole_rim(m)
    for s in np.linspace(0.0, 1.0, n):
        p, R = _pose(m, d, q0 + s * (q1 - q0))
        if p[2] - rim[2] <= height:
            return s, (p - rim)[:2], float(np.linalg.norm(_rot_error(R, rotz(YAW))))
    raise ValueError("the joint-space line does not descend to the hole")


def condition_pose(m: mujoco.MjModel, height: float, q_target=None, tol: float = 1e-4):
    """A condition at ``height`` above the rim, its lateral offset solved (secant/Newton on the
    2-D crossing offset, finite differences) so that the joint-space line to q* passes
    ENTRY_HEIGHT above the rim within ``tol`` of the hole axis. Returns (q, offset [2])."""
    q_target = inserted_pose(m) if q_target is None else q_target
    off = np.zeros(2)

    def crossing(o):
        return _line_crossing(m, tip_pose(m, (o[0], o[1], height)), q_target, n=20001)[1]

    for _ in range(20):
        c = crossing(off)
        if np.linalg.norm(c) < tol:
            return tip_pose(m, (off[0], off[1], height)), off
        h = 1e-3
        J = np.column_stack([(crossing(off + h * e) - c) / h for e in np.eye(2)])
        off = off - np.linalg.solve(J, c)
    raise RuntimeError("condition offset did not converge")


# ---------------------------------------------------------------------------------------------
# Collision check for sampled arm configurations


_CHECKERS: dict = {}


def _checker(model_or_path) -> mujoco.MjModel:
    """The all-colliding copy, cached per scene file or per model object."""
    if isinstance(model_or_path, mujoco.MjModel):
        key, m = id(model_or_path), model_or_path
    else:
        key = str(pathlib.Path(model_or_path or SCENE).resolve())
        m = None
    if key not in _CHECKERS:
        m = m if m is not None else mujoco.MjModel.from_xml_path(key)
        # the original stays referenced by the entry, so an id() key is not reused while cached
        _CHECKERS[key] = (task._colliding_copy(m), m)
    return _CHECKERS[key][0]


def collision_free(model_or_path, q) -> bool:
    """Whether the arm at joint angles q [6] is free of contact with the table, the fixture
    (walls, bottom, nubs) and itself, the block included.

    Uses a copy of the scene in which every geom collides (arm capsules, block, table, fixture)
    except parent-child bodies and base/link_1 (adjacent capsules meet at their joint). Any
    penetration counts (distance < 0): a block pressed into the nubs, as at q*, is in contact
    and so not collision-free. Within the joint limits no two arm bodies (block included) ever
    overlapped in 20 000 random configurations: rejections come from the table and the fixture.

    Args:
      model_or_path: the scene's MjModel, its MJCF path, or None for
        jaco_mjcf/block_in_hole.xml (the all-colliding copy is cached per model or file).
      q: joint angles [6] (Kinova actuator angles, rad).
    """
    return bool(task.collision_free(_checker(model_or_path), q))


# ---------------------------------------------------------------------------------------------
# A 20 Hz time-varying linear insertion controller (feasibility check)


def _smooth(s):
    s = np.clip(s, 0.0, 1.0)
    return s * s * s * (10.0 - 15.0 * s + 6.0 * s * s)


def _point_jacobian(m, d, q):
    d.qpos[:] = q
    mujoco.mj_kinematics(m, d)
    mujoco.mj_comPos(m, d)
    rows = []
    for s in BLOCK_SITES:
        jp = np.zeros((3, m.nv))
        mujoco.mj_jacSite(m, d, jp, None, m.site(s).id)
        rows.append(jp)
    return np.vstack(rows)


def lqr_gains(m: mujoco.MjModel, q: np.ndarray, w_points: float = 1e5, w_vel: float = 1.0,
              w_u: float = 1.0, dt: float = CONTROL_DT) -> np.ndarray:
    """Feedback K [6, 12] of a discrete infinite-horizon LQR at 20 Hz (zero-order hold) for the
    free arm linearised at q (q̈ = M(q)⁻¹ u, gravity compensated), with the cost
    w_points·|Δ(block points)|² + w_vel·|q̇|² + w_u·|u|² per step: a point cost of the toolbox's
    kind. Stable at 20 Hz by construction (spectral radius of the closed loop < 1)."""
    d = mujoco.MjData(m)
    d.qpos[:] = q
    mujoco.mj_forward(m, d)
    M = np.zeros((m.nv, m.nv))
    mujoco.mj_fullM(m, d, M)
    Mi = np.linalg.inv(M)
    n = m.nv
    A = np.block([[np.eye(n), dt * np.eye(n)], [np.zeros((n, n)), np.eye(n)]])
    B = np.vstack([0.5 * dt * dt * Mi, dt * Mi])
    Jp = _point_jacobian(m, d, q)
    Q = np.zeros((2 * n, 2 * n))
    Q[:n, :n] = w_points * Jp.T @ Jp
    Q[n:, n:] = w_vel * np.eye(n)
    R = w_u * np.eye(n)
    P = scipy.linalg.solve_discrete_are(A, B, Q, R)
    return np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)


def scripted_insertion(m: mujoco.MjModel, q0: np.ndarray, q_target: np.ndarray, push: float = 15.0,
                       t_move: int = 50, T: int = HORIZON, dt: float = CONTROL_DT):
    """A time-varying linear controller u_t = K_t x_t + k_t (the class GPS learns) that moves
    from q0 to q_target along the straight joint-space line and presses the block in.

    * reference: q_ref(t) = q0 + σ(t/t_move)(q_target − q0), σ a quintic smoothstep, q̇_ref its
      finite-difference derivative (continued past t_move at q_target);
    * feedback: K from :func:`lqr_gains` at q_target (block-point cost), u = −K (x − x_ref);
    * feedforward: M(q_ref) q̈_ref (the reference's own acceleration) plus J_tip(q_ref)ᵀ·(0, 0,
      −F(t)), a downward push at the tip that ramps from 0 to ``push`` N over 5 steps once the
      reference tip is 7 mm above the rim, and stays on.

    Returns (K [T, 6, 12], k [T, 6]); torques are clipped by the plant.
    """
    d = mujoco.MjData(m)
    K = lqr_gains(m, q_target)
    s = _smooth(np.arange(T + 1) / t_move)
    q_ref = q0[None] + s[:, None] * (q_target - q0)[None]
    qd_ref = np.gradient(q_ref, dt, axis=0)
    rim_z = hole_rim(m)[2]
    tip_z = np.array([_pose(m, d, q)[0][2] - rim_z for q in q_ref])
    near = tip_z <= ENTRY_HEIGHT + 0.002
    t_touch = int(np.argmax(near)) if np.any(near) else T  # no push if the reference stays high
    force = push * _smooth((np.arange(T) - t_touch) / 5.0)
    Ks, ks = np.empty((T, m.nu, 2 * m.nv)), np.empty((T, m.nu))
    jp = np.zeros((3, m.nv))
    for t in range(T):
        d.qpos[:] = q_ref[t]
        mujoco.mj_forward(m, d)
        M = np.zeros((m.nv, m.nv))
        mujoco.mj_fullM(m, d, M)
        mujoco.mj_jacSite(m, d, jp, None, m.site("block_tip").id)
        u_ff = M @ (qd_ref[t + 1] - qd_ref[t]) / dt + jp.T @ np.array([0.0, 0.0, -force[t]])
        Ks[t] = -K
        ks[t] = K @ np.concatenate([q_ref[t], qd_ref[t]]) + u_ff
    return Ks, ks


def rollout_c(m: mujoco.MjModel, q0: np.ndarray, Ks: np.ndarray, ks: np.ndarray,
              substeps: int = SUBSTEPS) -> tuple[np.ndarray, np.ndarray]:
    """C MuJoCo rollout of u_t = clip(K_t x_t + k_t) held for ``substeps`` physics steps of
    control_dt/substeps; the same plant as gmr_jax.sim's "mujoco" backend. Returns X [T+1, 12],
    U [T, 6]."""
    m = _with_timestep(m, CONTROL_DT / substeps)
    d = mujoco.MjData(m)
    d.qpos[:] = q0
    mujoco.mj_forward(m, d)
    lim = m.actuator_ctrlrange[:, 1]
    X, U = [np.concatenate([d.qpos, d.qvel])], []
    for t in range(len(ks)):
        u = np.clip(Ks[t] @ X[-1] + ks[t], -lim, lim)
        d.ctrl[:] = u
        mujoco.mj_step(m, d, nstep=substeps)
        U.append(u)
        X.append(np.concatenate([d.qpos, d.qvel]))
    return np.array(X), np.array(U)


def _with_timestep(m, h):
    if abs(m.opt.timestep - h) < 1e-15:
        return m
    m2 = copy.copy(m)
    m2.opt.timestep = h
    return m2


# ---------------------------------------------------------------------------------------------


def _describe(m, name, q):
    d = mujoco.MjData(m)
    d.qpos[:] = q
    mujoco.mj_kinematics(m, d)
    rim = hole_rim(m)
    print(f"{name}: q = [{', '.join(f'{v:.6f}' for v in q)}]")
    for s in BLOCK_SITES:
        p = d.site(s).xpos
        print(f"    {s:17s} world [{p[0]: .4f}, {p[1]: .4f}, {p[2]: .4f}] m,"
              f" rel. rim centre [{1e3 * (p[0] - rim[0]): 7.2f}, {1e3 * (p[1] - rim[1]): 7.2f},"
              f" {1e3 * (p[2] - rim[2]): 7.2f}] mm")


def main():
    m = _model()
    rim = hole_rim(m)
    print(f"scene {SCENE}")
    print(f"hole rim centre (site hole_rim) [{rim[0]:.4f}, {rim[1]:.4f}, {rim[2]:.4f}] m; bottom {HOLE_DEPTH * 1e3:.0f} mm "
          f"below. Joint angles: Kinova actuator angles, rad.")
    q_star = inserted_pose(m)
    q_c, off_c = condition_pose(m, C_HEIGHT, q_star)
    q_d, off_d = condition_pose(m, D_HEIGHT, q_star)
    for name, q in (("q* (inserted)", q_star), ("C", q_c), ("D", q_d)):
        _describe(m, name, q)
    print(f"C: tip {C_HEIGHT * 1e3:.0f} mm above the rim, offset [{off_c[0] * 1e3:.2f}, {off_c[1] * 1e3:.2f}] mm; "
          f"D: {D_HEIGHT * 1e3:.0f} mm above, offset [{off_d[0] * 1e3:.2f}, {off_d[1] * 1e3:.2f}] mm")
    lo2, hi2 = m.jnt_range[1]
    lo3, hi3 = m.jnt_range[2]
    for name, q in (("q*", q_star), ("C", q_c), ("D", q_d)):
        jp, jr = np.zeros((3, 6)), np.zeros((3, 6))
        d = mujoco.MjData(m)
        _pose(m, d, q)
        mujoco.mj_jacSite(m, d, jp, jr, m.site("block_tip").id)
        sv = np.linalg.svd(jp, compute_uv=False)
        s, lat, rot = _line_crossing(m, q, q_star) if name != "q*" else (np.nan, np.zeros(2), 0.0)
        print(f"{name}: joint_2 {q[1]:.4f} in [{lo2:.4f}, {hi2:.4f}]: {lo2 < q[1] < hi2}; joint_3 {q[2]:.4f} in "
              f"[{lo3:.4f}, {hi3:.4f}]: {lo3 < q[2] < hi3}; collision-free: {collision_free(None, q)}; "
              f"tip Jacobian singular values {np.array2string(sv, precision=3)} m/rad"
              + ("" if name == "q*" else f"; joint line to q* passes {ENTRY_HEIGHT * 1e3:.0f} mm above the rim at s = {s:.3f}, "
                 f"{1e3 * np.linalg.norm(lat):.2f} mm off axis, orientation error {1e3 * rot:.1f} mrad"))
    print(f"|C - q*| = {np.linalg.norm(q_c - q_star):.3f} rad, |D - q*| = {np.linalg.norm(q_d - q_star):.3f} rad")
    print("\nScripted 20 Hz insertion (LQR point-cost feedback, joint-space reference to q*, "
          "feedforward push), C MuJoCo, 25 substeps:")
    for name, q0 in (("C", q_c), ("D", q_d)):
        for push in (10.0, 15.0, 20.0):
            Ks, ks = scripted_insertion(m, q0, q_star, push=push)
            X, U = rollout_c(m, q0, Ks, ks)
            depth = np.array([block_depth(m, x[:6]) for x in X])
            t_in = int(np.argmax(depth >= INSERTED_DEPTH)) if np.any(depth >= INSERTED_DEPTH) else None
            frac = np.max(np.abs(U) / m.actuator_ctrlrange[:, 1], axis=0)
            print(f"  {name}, push {push:4.1f} N: depth {1e3 * depth[-1]:5.1f} mm after {HORIZON} steps; "
                  f">= {INSERTED_DEPTH * 1e3:.0f} mm at step {t_in}; final |q - q*| {np.abs(X[-1, :6] - q_star).max():.4f} rad, "
                  f"|q̇| {np.abs(X[-1, 6:]).max():.4f} rad/s; peak |u|/limit {np.array2string(frac, precision=2)}")


if __name__ == "__main__":
    main()
