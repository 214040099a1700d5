"""The block-in-hole scene (jaco_mjcf/block_in_hole.xml) against its documented behaviour.

C MuJoCo everywhere except the one MJX comparison (about half of this module's run time).
Pushes that measure forces run the controller at the physics rate (2 ms) in C MuJoCo, so the
force at the block is known exactly; the 20 Hz checks go through the same plant as training.
"""

import pathlib

import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from experiments import block_in_hole_poses as bp
from gmr_jax import config, sim, types

MJCF_DIR = pathlib.Path(__file__).resolve().parent.parent / "jaco_mjcf"
SCENE = MJCF_DIR / "block_in_hole.xml"
ARM_BODIES = ("base", "link_1", "link_2", "link_3", "link_4", "link_5", "link_6")
BLOCK_SITES = ("block_tip", "block_tip_corner", "block_top")
LEAD_IN = 0.008  # m, width and height of the 45° chamfer (MJCF comment)
NUB_DEPTH = 0.012  # m, the nubs' centres below the rim
INTERFERENCE = 5e-5  # m, how far each nub reaches into the block's outline


@pytest.fixture(scope="module")
def m():
    return mujoco.MjModel.from_xml_path(str(SCENE))


@pytest.fixture(scope="module")
def poses(m):
    q_star = bp.inserted_pose(m)
    q_c, _ = bp.condition_pose(m, bp.C_HEIGHT, q_star)
    q_d, _ = bp.condition_pose(m, bp.D_HEIGHT, q_star)
    return {"q*": q_star, "C": q_c, "D": q_d}


def geom_box(m, name):
    """(centre in the fixture frame [3], half sizes [3]) of an axis-aligned fixture geom."""
    g = m.geom(name)
    np.testing.assert_allclose(g.quat, [1, 0, 0, 0])
    return g.pos.copy(), g.size.copy()


def k_ref(solref, solimp):
    """MuJoCo's reference stiffness of a (timeconst, dampratio) solref: 1/(dmax·tc·ζ)²."""
    return 1.0 / (solimp[1] * solref[0] * solref[1]) ** 2


# ---------------------------------------------------------------------------------------------
# Loading, the arm copy, the held block


def test_scene_loads_through_make_sim():
    s = sim.make_sim(config.SimConfig(scene="block_in_hole", substeps=25, backend="mujoco"))
    assert s.path.name == "block_in_hole.xml"
    m = s.model
    assert (s.nq, s.dX, s.dU) == (6, 12, 6)
    assert [m.joint(i).name for i in range(m.njnt)] == [f"joint_{i}" for i in range(1, 7)]
    for name in ("end_effector", "hole_rim", "hole_bottom", *BLOCK_SITES):
        assert mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, name) >= 0, name
    assert m.opt.timestep == pytest.approx(0.002)  # 50 ms / 25 substeps
    flags = m.opt.disableflags
    assert not flags & mujoco.mjtDisableBit.mjDSBL_CONTACT
    assert flags & mujoco.mjtDisableBit.mjDSBL_WARMSTART  # a control step depends on (q, q̇, u) only
    assert flags & mujoco.mjtDisableBit.mjDSBL_EULERDAMP
    assert m.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC
    # Contacts come only from the explicit pairs: no geom collides through contype/conaffinity.
    assert np.all(m.geom_contype == 0) and np.all(m.geom_conaffinity == 0)
    pairs = {(m.geom(m.pair_geom1[i]).name, m.geom(m.pair_geom2[i]).name) for i in range(m.npair)}
    nubs = {f"nub_{s}{k}" for s in ("px", "nx", "py", "ny") for k in (0, 1)}
    walls = {f"{kind}_{s}" for kind in ("wall", "chamfer") for s in ("px", "nx", "py", "ny")}
    expected = {tuple(sorted(("block_geom", g))) for g in nubs | walls | {"bottom", "table"}}
    expected.add(tuple(sorted(("hand_geom", "table"))))
    assert {tuple(sorted(p)) for p in pairs} == expected


def test_arm_is_a_verbatim_copy_of_jaco2(m):
    """The scene carries its own copy of the arm (MJCF cannot add a child to an included body):
    every arm quantity must equal jaco2.xml's, so an edit there that is not copied fails here."""
    arm = mujoco.MjModel.from_xml_path(str(MJCF_DIR / "jaco2.xml"))
    for name in ARM_BODIES:
        a, b = arm.body(name), m.body(name)
        for field in ("pos", "quat", "ipos", "iquat", "mass", "inertia", "gravcomp", "jntnum"):
            np.testing.assert_array_equal(getattr(m, "body_" + field)[b.id], getattr(arm, "body_" + field)[a.id],
                                          err_msg=f"{name}.{field}")
        assert m.body(b.parentid[0]).name == arm.body(a.parentid[0]).name
    for i in range(arm.njnt):
        a, b = arm.joint(i), m.joint(arm.joint(i).name)
        for field in ("type", "pos", "axis", "range", "limited", "armature", "damping", "frictionloss", "stiffness"):
            np.testing.assert_array_equal(getattr(b, field), getattr(a, field), err_msg=f"{a.name}.{field}")
    for i in range(arm.nu):
        a, b = arm.actuator(i), m.actuator(arm.actuator(i).name)
        for field in ("trntype", "trnid", "gear", "ctrlrange", "ctrllimited", "biastype", "gaintype", "gainprm"):
            np.testing.assert_array_equal(getattr(b, field), getattr(a, field), err_msg=f"{a.name}.{field}")
    for i in range(arm.ngeom):
        a, b = arm.geom(i), m.geom(arm.geom(i).name)
        for field in ("type", "size", "pos", "quat"):
            np.testing.assert_array_equal(getattr(b, field), getattr(a, field), err_msg=f"{a.name}.{field}")
    np.testing.assert_array_equal(m.site("end_effector").pos, arm.site("end_effector").pos)
    np.testing.assert_array_equal(m.site("end_effector").quat, arm.site("end_effector").quat)
    assert m.nexclude == arm.nexclude == 1


def test_block_is_welded_to_the_hand(m):
    """The block is a jointless child of link_6 (so its mass is the arm's and the state stays
    12-D), gravity-compensated like the links, and its pose relative to link_6 does not change
    while contact forces act on it."""
    b = m.body("block")
    assert m.body(b.parentid[0]).name == "link_6" and b.jntnum[0] == 0
    assert m.nq == m.nv == 6
    assert b.mass[0] == pytest.approx(0.04 * 0.04 * 0.08 * 600)  # 40x40x80 mm of 600 kg/m³ wood
    assert m.body_gravcomp[b.id] == 1.0
    # The block's top face is the end-effector frame, its axis link_6's z axis.
    np.testing.assert_allclose(m.site("block_top").pos + b.pos, m.site("end_effector").pos, atol=1e-15)
    # A contact rollout: pressed down onto the fixture top beside the hole with 30 N for 1 s.
    d = mujoco.MjData(m)
    q0 = bp.tip_pose(m, (0.0403, 0.040, 0.002))
    d.qpos[:] = q0
    mujoco.mj_forward(m, d)
    rel0 = _relative_pose(m, d)
    pressed = 0
    for _ in range(500):
        d.ctrl[:] = _cartesian_push(m, d, np.array([0.0, 0.0, -30.0]), hold_xy=d.site("block_tip").xpos[:2])
        mujoco.mj_step(m, d)
        pressed += d.ncon > 0
        p, R = _relative_pose(m, d)
        # a welded child's frame is its parent's composed with a fixed offset, recomputed every
        # step: the only change allowed is float64 rounding of 0.5 m coordinates (~1e-16 m)
        np.testing.assert_allclose(p, rel0[0], atol=1e-14)
        np.testing.assert_allclose(R, rel0[1], atol=1e-14)
    assert pressed > 400  # the block really was in contact


def _relative_pose(m, d):
    b6, bb = m.body("link_6").id, m.body("block").id
    R6 = d.xmat[b6].reshape(3, 3)
    return R6.T @ (d.xpos[bb] - d.xpos[b6]), R6.T @ d.xmat[bb].reshape(3, 3)


# ---------------------------------------------------------------------------------------------
# Geometry as documented


def test_documented_geometry(m):
    """Clearance, lead-in, interference, depth and placement as the MJCF comment and the README
    state."""
    half = m.geom("block_geom").size
    np.testing.assert_allclose(half, [0.02, 0.02, 0.04])
    pos, size = geom_box(m, "wall_px")
    clearance = pos[0] - size[0] - half[0]
    assert clearance == pytest.approx(3e-4, abs=1e-12)
    for name in ("wall_nx", "wall_py", "wall_ny"):
        p, s = geom_box(m, name)
        axis = 0 if name.endswith("x") else 1
        assert abs(p[axis]) - s[axis] - half[0] == pytest.approx(clearance, abs=1e-12)
        assert p[2] + s[2] == pytest.approx(-LEAD_IN, abs=1e-12)  # wall tops at the lead-in's foot
    p, s = geom_box(m, "bottom")
    assert p[2] + s[2] == pytest.approx(-bp.HOLE_DEPTH, abs=1e-12)
    # The fixture stands on the table, whose top is the base plane z = 0.
    rim = bp.hole_rim(m)
    np.testing.assert_allclose(rim, [0.0, -0.45, 0.10], atol=1e-12)
    assert rim[2] + p[2] - s[2] == pytest.approx(0.0, abs=1e-12)
    assert m.geom("table").pos[2] + m.geom("table").size[2] == pytest.approx(0.0, abs=1e-12)
    # Lead-in: each chamfer bar has a 45° face from the rim, LEAD_IN out from the wall's inner
    # face, down to that face at the wall's top; its other faces lie in the wall or slope
    # outwards from the rim (the lip).
    wall_face = half[0] + clearance
    for side in ("px", "nx", "py", "ny"):
        g = m.geom(f"chamfer_{side}")
        axis = 0 if side[1] == "x" else 1
        sign = 1.0 if side[0] == "p" else -1.0
        R = np.zeros(9)
        mujoco.mju_quat2Mat(R, g.quat)
        R = R.reshape(3, 3)
        # the corners of the bar's cross-section in the plane (axis, z)
        corners = [g.pos + R @ (np.array([a, b, c]) * g.size) for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)]
        radial = sorted({round(sign * c[axis], 9) for c in corners})
        heights = sorted({round(c[2], 9) for c in corners})
        np.testing.assert_allclose(radial, [wall_face, wall_face + LEAD_IN, wall_face + 2 * LEAD_IN], atol=1e-8)
        np.testing.assert_allclose(heights, [-2 * LEAD_IN, -LEAD_IN, 0.0], atol=1e-8)
        innermost = min(corners, key=lambda c: sign * c[axis])
        top = max(corners, key=lambda c: c[2])
        assert innermost[2] == pytest.approx(-LEAD_IN, abs=1e-8) and sign * top[axis] == pytest.approx(wall_face + LEAD_IN, abs=1e-8)
    # Nubs: radius 5 mm, 0.05 mm into the block's outline, NUB_DEPTH below the rim (below the
    # lead-in's foot, so the walls align the block before it meets them).
    for side in ("px", "nx", "py", "ny"):
        for k in (0, 1):
            g = m.geom(f"nub_{side}{k}")
            assert g.type[0] == mujoco.mjtGeom.mjGEOM_SPHERE and g.size[0] == pytest.approx(0.005)
            axis = 0 if side[1] == "x" else 1
            assert g.pos[2] == pytest.approx(-NUB_DEPTH, abs=1e-12)
            # the cap that stands out of the wall face lies wholly below the lead-in's foot
            cap = np.sqrt(g.size[0] ** 2 - (abs(g.pos[axis]) - wall_face) ** 2)
            assert g.pos[2] + cap < -LEAD_IN
            assert half[0] - (abs(g.pos[axis]) - g.size[0]) == pytest.approx(INTERFERENCE, abs=1e-12)
            assert abs(g.pos[1 - axis]) == pytest.approx(0.012)


# ---------------------------------------------------------------------------------------------
# The press fit and the walls


def _cartesian_push(m, d, force, hold_xy, k_xy=3000.0):
    """Joint torques for a Cartesian controller at the physics rate: the given force at the
    block tip plus springs that hold the tip's horizontal position at hold_xy (``k_xy`` N/m,
    3000 stiff, a few hundred compliant like an arm under a learned controller) and link_6's
    orientation vertical and yaw-aligned (60 N·m/rad), with damping. The vertical component of
    ``force`` is applied as is (no vertical spring or damper)."""
    jp, jr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
    mujoco.mj_jacSite(m, d, jp, jr, m.site("block_tip").id)
    p = d.site("block_tip").xpos
    R = d.body("link_6").xmat.reshape(3, 3)
    v, w = jp @ d.qvel, jr @ d.qvel
    f = np.array(force, dtype=np.float64)
    f[:2] += k_xy * (hold_xy - p[:2]) - (0.4 / 3.0) * k_xy * v[:2]
    moment = 60.0 * bp._rot_error(R, bp.rotz(bp.YAW)) - 20.0 * w
    u = jp.T @ f + jr.T @ moment
    lim = m.actuator_ctrlrange[:, 1]
    assert np.all(np.abs(u) <= lim), "the push must stay within the torque limits to be exact"
    return u


def _push_down(m, force, seconds=4.0, offset=(0.0, 0.0), k_xy=3000.0):
    """Depth (m below the rim) of the block tip after pushing straight down with ``force`` N,
    starting at rest, aligned, with the tip 2 mm above the rim and ``offset`` [2] (m) beside
    the hole axis, where the horizontal spring of stiffness ``k_xy`` holds it."""
    d = mujoco.MjData(m)
    rim = bp.hole_rim(m)
    d.qpos[:] = bp.tip_pose(m, (offset[0], offset[1], 0.002))
    mujoco.mj_forward(m, d)
    hold = rim[:2] + np.asarray(offset)
    for _ in range(int(round(seconds / m.opt.timestep))):
        d.ctrl[:] = _cartesian_push(m, d, (0.0, 0.0, -force), hold, k_xy)
        mujoco.mj_step(m, d)
    return rim[2] - d.site("block_tip").xpos[2]


def _without_nubs(m):
    """The scene with the nubs' contact pairs removed (the press fit off, walls as they are)."""
    spec = mujoco.MjSpec.from_file(str(SCENE))
    for p in list(spec.pairs):
        if p.geomname2.startswith("nub_"):
            spec.delete(p)
    return spec.compile()


def test_press_fit_needs_the_documented_force(m):
    """README: a light press fit. Pushed straight down for 4 s (the task's horizon), the block
    rests on the nubs at 0.15 N (tip about 12 mm deep, at the nubs), passes them part of the way
    at 0.3 N and reaches the bottom at 1 N; without the nubs 0.3 N already takes it most of the
    way down: the resistance is the nubs'."""
    assert _push_down(m, 0.15) < NUB_DEPTH + 0.001  # held at the nubs (measured 11.8 mm)
    partial = _push_down(m, 0.3)
    assert NUB_DEPTH + 0.002 < partial < bp.INSERTED_DEPTH - 0.01  # measured 17.4 mm
    full = _push_down(m, 1.0)
    assert full >= bp.INSERTED_DEPTH  # on the bottom
    # The bottom stops it: the tip is no deeper than the hole plus the rigid contact's
    # penetration bound of the next test (well under a millimetre).
    assert full < bp.HOLE_DEPTH + 1e-3
    assert _push_down(_without_nubs(m), 0.3) > partial + 0.015  # measured 49.9 mm


@pytest.mark.parametrize("offset, force", [((0.006, 0.0), 2.0), ((0.004, 0.004), 5.0)])
def test_lead_in_guides_an_offset_block_into_the_hole(m, offset, force):
    """The chamfer turns a downward push into a sideways one: a block 6 mm beside the axis, held
    there by a compliant 300 N/m horizontal spring (which pulls it back with up to 1.8 N), is
    pushed into the hole by 2 N; 4 mm off in x and in y, its corner in the crease where two
    chamfers meet, it needs 5 N (2 N leaves it there, 7 mm deep). 12 mm off (the block's far
    edge beyond the ridge of the lip, 8 mm out) it rests on the ridge, its tip in the rim plane
    up to the contact's penetration."""
    assert _push_down(m, force, offset=offset, k_xy=300.0) >= bp.INSERTED_DEPTH
    assert _push_down(m, 2.0, offset=(0.012, 0.0), k_xy=300.0) < 1e-4


def _penetration_bound(m, d, force, pair_class_geom):
    """Largest steady-state penetration of the contacts of one rigid pair class under a total
    normal force ``force`` (N), from MuJoCo's soft-contact model.

    For an active contact row at rest (a1 = 0, v = 0) the solver's optimality condition
    (A + R) f = aref − a0 with A f = −a0 leaves R f = aref = −k·d(r)·r, where
    R = (1 − d)/d · Â (Â the row's diagonal approximation of J M⁻¹ Jᵀ, ``efc_diagA``) and
    k = 1/(dmax·timeconst·dampratio)². Hence |r| = (1 − d)/d² · Â · f / k. The impedance d(r)
    is at least solimp's dmin and f at most the total normal force, so
    |r| <= (1 − dmin)/dmin² · max Â · F / k."""
    pid = next(i for i in range(m.npair) if pair_class_geom in (m.geom(m.pair_geom1[i]).name, m.geom(m.pair_geom2[i]).name))
    solref, solimp = m.pair_solref[pid], m.pair_solimp[pid]
    diag = max(d.efc_diagA[d.contact[i].efc_address] for i in range(d.ncon))
    dmin = solimp[0]
    return (1 - dmin) / dmin**2 * diag * force / k_ref(solref, solimp)


@pytest.mark.parametrize("case", ["down_on_fixture_top", "sideways_into_wall"])
def test_walls_bound_the_penetration(m, case):
    """Pressed onto the fixture top beside the hole with 40 N (over half of what the arm can push
    down there within its torque limits), or sideways against a wall from inside the hole with
    20 N (the wrist's 6.8 N·m limit allows about 35 N there), the block penetrates the rigid
    fixture less than the bound derived from the contact parameters, a fraction of a
    millimetre: it cannot pass through."""
    d = mujoco.MjData(m)
    F = 40.0 if case == "down_on_fixture_top" else 20.0
    if case == "down_on_fixture_top":
        # the tip over the hole's +x+y corner, the block's face on the ridges of two lead-in bars
        q0, force, walls = bp.tip_pose(m, (0.0403, 0.040, 0.001)), np.array([0.0, 0.0, -F]), ("chamfer_px", "chamfer_py")
    else:
        q0, force, walls = bp.tip_pose(m, (0.0, 0.0, -0.045)), np.array([F, 0.0, 0.0]), ("wall_px",)
    d.qpos[:] = q0
    mujoco.mj_forward(m, d)
    hold = d.site("block_tip").xpos[:2].copy()
    z_hold = d.site("block_tip").xpos[2]
    jp = np.zeros((3, m.nv))
    for _ in range(1000):  # 2 s: the soft contacts (time constant 20 ms) settle
        f = force.copy()
        if case == "sideways_into_wall":
            # a spring holds the height; along the push (x) there is no spring, only the force
            mujoco.mj_jacSite(m, d, jp, None, m.site("block_tip").id)
            f[2] = 3000.0 * (z_hold - d.site("block_tip").xpos[2]) - 400.0 * (jp @ d.qvel)[2]
            hold[0] = d.site("block_tip").xpos[0]
        d.ctrl[:] = _cartesian_push(m, d, f, hold_xy=hold)
        mujoco.mj_step(m, d)
    # settled: the bound is a steady-state one (block tip slower than 1 mm/s)
    jp = np.zeros((3, m.nv))
    mujoco.mj_jacSite(m, d, jp, None, m.site("block_tip").id)
    assert np.linalg.norm(jp @ d.qvel) < 1e-3
    ids = {m.geom(w).id for w in walls}
    pen = [-d.contact[i].dist for i in range(d.ncon) if d.contact[i].geom2 in ids or d.contact[i].geom1 in ids]
    assert pen, "the block must be touching the wall"
    bound = _penetration_bound(m, d, F, walls[0])
    assert max(pen) <= bound
    assert bound < 3e-4  # and the bound is below the 0.3 mm clearance (the walls are 40 mm thick)


# ---------------------------------------------------------------------------------------------
# Conditions, target, collision check


def test_inserted_pose_and_conditions(m, poses):
    d = mujoco.MjData(m)
    rim = bp.hole_rim(m)
    q_star = poses["q*"]
    d.qpos[:] = q_star
    mujoco.mj_kinematics(m, d)
    np.testing.assert_allclose(d.site("block_tip").xpos, rim + [0, 0, -bp.HOLE_DEPTH], atol=1e-9)
    np.testing.assert_allclose(d.site("block_top").xpos, rim + [0, 0, 0.08 - bp.HOLE_DEPTH], atol=1e-9)
    # the tip corner sits on a corner of the hole's square: faces parallel to the walls
    np.testing.assert_allclose(np.abs(d.site("block_tip_corner").xpos - rim)[:2], [0.02, 0.02], atol=1e-9)
    for name, q in poses.items():
        assert m.jnt_range[1, 0] < q[1] < m.jnt_range[1, 1], name
        assert m.jnt_range[2, 0] < q[2] < m.jnt_range[2, 1], name
    for name, height in (("C", bp.C_HEIGHT), ("D", bp.D_HEIGHT)):
        q = poses[name]
        assert bp.block_depth(m, q) == pytest.approx(-height, abs=1e-9)
        assert bp.collision_free(SCENE, q), name
        s, lateral, _ = bp._line_crossing(m, q, q_star)
        # the joint line to q* enters between the nubs: the offset was solved to 0.1 mm, and the
        # crossing is sampled here at 1/4000 of the line (< 0.05 mm of tip travel)
        assert np.linalg.norm(lateral) < 1.5e-4


def test_collision_free_sees_block_hand_and_fixture(m, poses):
    assert bp.collision_free(SCENE, poses["C"]) and bp.collision_free(m, poses["C"])
    assert not bp.collision_free(SCENE, poses["q*"])  # pressed into the nubs (0.05 mm)
    assert not bp.collision_free(m, poses["q*"])
    # the block 10 mm into the fixture top beside the hole
    assert not bp.collision_free(SCENE, bp.tip_pose(m, (0.04, 0.04, -0.01)))
    assert bp.collision_free(SCENE, bp.tip_pose(m, (0.04, 0.04, 0.01)))
    # the hand alone in the table: block pointing along +x, its tip 30 mm above the table, so
    # the hand capsule (radius 40 mm) dips 10 mm into it while the block (half-width 20 mm)
    # stays 10 mm clear; 15 mm higher the hand clears the table too
    R = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    assert not bp.collision_free(SCENE, bp.solve_ik(m, np.array([0.35, -0.2, 0.03]), R))
    assert bp.collision_free(SCENE, bp.solve_ik(m, np.array([0.35, -0.2, 0.045]), R))


def test_scripted_20hz_controller_inserts_from_c_and_d(m, poses):
    """A time-varying linear controller at 20 Hz (LQR feedback on the block points, a joint-space
    reference to q*, a 15 N feedforward push) inserts from C and from D within the task's
    T = 80 steps, within the torque limits (the plant clips; the controller needs at most 54 %),
    and ends at q* at rest by the paper's criterion (final-state MSE < 0.01)."""
    target = np.concatenate([poses["q*"], np.zeros(6)])
    for name in ("C", "D"):
        Ks, ks = bp.scripted_insertion(m, poses[name], poses["q*"], push=15.0)
        X, U = bp.rollout_c(m, poses[name], Ks, ks)
        assert len(U) == bp.HORIZON
        assert np.all(np.abs(U) < m.actuator_ctrlrange[:, 1]), name  # never saturated
        assert bp.block_depth(m, X[-1, :6]) >= bp.INSERTED_DEPTH, name
        assert np.mean((X[-1] - target) ** 2) < 0.01, name


# ---------------------------------------------------------------------------------------------
# C MuJoCo and MJX in contact


def test_mujoco_and_mjx_agree_in_contact(m):
    """The scripted controller takes the block from 20 mm above the rim through the nubs and
    about 43 mm into the hole, touching the walls on the way (40 steps, 2 s), on both backends,
    float64.

    Tolerance. The engines resolve box-box contacts differently (MJX-JAX: 4 contacts from a
    separating-axis test; C MuJoCo: up to 8 from its own box-box routine), so once the block
    touches a wall their trajectories part; sphere-box (the nubs) is the same in both (before
    the first wall contact they agree to 0.4 µm). What the physics allows is set by the
    clearance: as long as every point of the block agrees to within the 0.3 mm clearance, both
    engines have the block in the same place in the hole, touching the same surfaces.
    Velocities: at most clearance / control_dt (6 mm/s), a difference that cannot carry the
    block across the clearance within one control step.
    Measured (2-core CPU): 77 µm and 1.7 mm/s here; faster pushes of the same kind 64-203 µm
    and 1.7-3.3 mm/s; the full 80-step scripted insertions from C and D 33 and 67 µm."""
    T = 40
    q_star = bp.inserted_pose(m)
    q0, _ = bp.condition_pose(m, 0.02, q_star)
    Ks, ks = bp.scripted_insertion(m, q0, q_star, push=15.0, t_move=40, T=T)
    pol = types.LinearGaussianPolicy(jnp.asarray(Ks), jnp.asarray(ks), None, jnp.zeros((T, 6, 6)), None)
    x0 = jnp.asarray(np.concatenate([q0, np.zeros(6)]))
    out = {}
    for backend in ("mujoco", "mjx"):
        s = sim.make_sim(config.SimConfig(scene="block_in_hole", substeps=25, backend=backend))
        traj, xT = sim.rollout_with_final(s, pol, x0, jnp.zeros((T, 6)), with_ee=False)
        assert traj.X.dtype == jnp.float64
        out[backend] = np.concatenate([np.asarray(traj.X), np.asarray(xT)[None]])
    clearance, dt = 3e-4, 0.05
    d = mujoco.MjData(m)
    worst_p, worst_v = 0.0, 0.0
    for xc, xm in zip(out["mujoco"], out["mjx"]):
        pc, vc = _block_points(m, d, xc)
        pm, vm = _block_points(m, d, xm)
        worst_p = max(worst_p, np.linalg.norm(pc - pm, axis=1).max())
        worst_v = max(worst_v, np.linalg.norm(vc - vm, axis=1).max())
    depth = [bp.block_depth(m, x[:6]) for x in out["mujoco"]]
    assert depth[-1] > 0.03  # the rollout did go through the nubs and deep into the hole
    assert _wall_contact_steps(m, q0, Ks, ks) >= 5  # and the block touched the walls (box-box)
    assert worst_p <= clearance, worst_p
    assert worst_v <= clearance / dt, worst_v


def _wall_contact_steps(m, q0, Ks, ks):
    """Number of control steps of the C MuJoCo rollout in which the block touches a wall or the
    lead-in (box-box contacts)."""
    walls = {m.geom(f"{kind}_{s}").id for kind in ("wall", "chamfer") for s in ("px", "nx", "py", "ny")}
    d = mujoco.MjData(m)
    d.qpos[:] = q0
    mujoco.mj_forward(m, d)
    lim = m.actuator_ctrlrange[:, 1]
    steps = 0
    for K, k in zip(Ks, ks):
        d.ctrl[:] = np.clip(K @ np.concatenate([d.qpos, d.qvel]) + k, -lim, lim)
        touched = False
        for _ in range(25):
            mujoco.mj_step(m, d)
            touched |= any(c.dist < 0 and (c.geom1 in walls or c.geom2 in walls) for c in d.contact[: d.ncon])
        steps += touched
    return steps


def _block_points(m, d, x):
    """World positions [3, 3] and velocities [3, 3] of the block's three cost points."""
    d.qpos[:], d.qvel[:] = x[:6], x[6:]
    mujoco.mj_kinematics(m, d)
    mujoco.mj_comPos(m, d)
    P, V = [], []
    jp = np.zeros((3, m.nv))
    for s in BLOCK_SITES:
        mujoco.mj_jacSite(m, d, jp, None, m.site(s).id)
        P.append(d.site(s).xpos.copy())
        V.append(jp @ x[6:])
    return np.array(P), np.array(V)
