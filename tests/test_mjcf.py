"""The Jaco 2 MJCF against Kinova's published kinematics and the issue's plant requirements.

Loads the files with C MuJoCo only (no JAX compilation), so this module runs in about a second.
"""

import math
import pathlib
import xml.etree.ElementTree as ET

import mujoco
import numpy as np
import pytest

MJCF_DIR = pathlib.Path(__file__).resolve().parent.parent / "jaco_mjcf"
DEG = math.pi / 180


@pytest.fixture(scope="module")
def reach():
    return mujoco.MjModel.from_xml_path(str(MJCF_DIR / "reach.xml"))


@pytest.fixture(scope="module")
def arm():
    return mujoco.MjModel.from_xml_path(str(MJCF_DIR / "jaco2.xml"))


def dh_end_effector(q):
    """Kinova's classic DH table for the j2n6 curved wrist (jaco2-mjx.md §1.2), written out
    independently of the MJCF: frame i = Rz(θ_i) Tz(d_i) Tx(a_i) Rx(α_i), θ_i = sign·q_i + offset."""
    aa = 30 * DEG
    ratio = math.sin(aa) / math.sin(2 * aa)
    D1, D2, D3, D4, D5, D6, e2 = 0.2755, 0.41, 0.2073, 0.0741, 0.0741, 0.160, 0.0098
    a = [0, D2, 0, 0, 0, 0]
    alpha = [math.pi / 2, math.pi, math.pi / 2, 2 * aa, 2 * aa, math.pi]
    d = [D1, 0, -e2, -(D3 + ratio * D4), -ratio * (D4 + D5), -(ratio * D5 + D6)]
    theta = [-q[0], q[1] - math.pi / 2, q[2] + math.pi / 2, q[3], q[4] - math.pi, q[5] + math.pi / 2]
    T = np.eye(4)
    for i in range(6):
        ct, st, ca, sa = math.cos(theta[i]), math.sin(theta[i]), math.cos(alpha[i]), math.sin(alpha[i])
        T = T @ np.array([[ct, -st * ca, st * sa, a[i] * ct],
                          [st, ct * ca, -ct * sa, a[i] * st],
                          [0, sa, ca, d[i]],
                          [0, 0, 0, 1]])
    return T[:3, 3]


def site_position(m, q):
    d = mujoco.MjData(m)
    d.qpos[:] = q
    mujoco.mj_kinematics(m, d)
    return d.site(mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, "end_effector")).xpos.copy()


def random_angles(rng, n):
    q = rng.uniform(-2 * math.pi, 2 * math.pi, size=(n, 6))
    q[:, 1] = rng.uniform(47 * DEG, 313 * DEG, n)
    q[:, 2] = rng.uniform(19 * DEG, 341 * DEG, n)
    return q


def test_end_effector_matches_dh_table(reach):
    rng = np.random.default_rng(0)
    qs = random_angles(rng, 500)
    err = max(np.linalg.norm(site_position(reach, q) - dh_end_effector(q)) for q in qs)
    # The URDF offsets are rounded to 0.1 mm and the DH table's wrist lengths to 0.01 mm, so the
    # two descriptions differ by < 0.1 mm (jaco2-mjx.md §1.2 reports 7.5e-5 m); 1 mm is the spec.
    assert err < 1e-3
    assert err < 1.5e-4  # and it is the rounding, not a convention error


def test_dh_check_is_sensitive():
    """The DH comparison would catch a sign or offset error (guards the test above)."""
    q = np.array([0.3, 3.0, 1.2, 4.4, 2.0, 2.2])
    assert np.linalg.norm(dh_end_effector(q) - dh_end_effector(q * np.array([-1, 1, 1, 1, 1, 1]))) > 0.05
    assert np.linalg.norm(dh_end_effector(q) - dh_end_effector(q + np.array([0, 0.1, 0, 0, 0, 0]))) > 0.02


def test_straight_up_pose(reach):
    # q = (0, π, π, 0, 0, 0) is the arm pointing straight up: 1.181 m above the base (§1.2).
    p = site_position(reach, [0, math.pi, math.pi, 0, 0, 0])
    assert abs(p[2] - 1.181) < 1e-3
    assert np.hypot(p[0], p[1]) < 0.07


def test_joints_limits_and_actuators(reach):
    names = [reach.joint(i).name for i in range(reach.njnt)]
    assert names == [f"joint_{i}" for i in range(1, 7)]
    assert all(reach.jnt_type[i] == mujoco.mjtJoint.mjJNT_HINGE for i in range(6))
    assert list(reach.jnt_limited) == [0, 1, 1, 0, 0, 0]
    np.testing.assert_allclose(reach.jnt_range[1], [47 * DEG, 313 * DEG], atol=1e-12)
    np.testing.assert_allclose(reach.jnt_range[2], [19 * DEG, 341 * DEG], atol=1e-12)
    assert reach.nu == 6
    for i in range(6):
        assert reach.actuator_trntype[i] == mujoco.mjtTrn.mjTRN_JOINT
        assert reach.actuator_trnid[i, 0] == i
        assert reach.actuator_gear[i, 0] == 1.0
        assert reach.actuator_biastype[i] == mujoco.mjtBias.mjBIAS_NONE  # a pure torque motor
    np.testing.assert_allclose(reach.actuator_ctrlrange[:, 1], [30.5] * 3 + [6.8] * 3)
    np.testing.assert_allclose(reach.actuator_ctrlrange[:, 0], [-30.5] * 3 + [-6.8] * 3)
    assert all(reach.actuator_ctrllimited)


def test_base_at_origin_z_up(reach):
    base = mujoco.mj_name2id(reach, mujoco.mjtObj.mjOBJ_BODY, "base")
    assert reach.body_parentid[base] == 0
    np.testing.assert_allclose(reach.body_pos[base], 0)
    np.testing.assert_allclose(reach.body_quat[base], [1, 0, 0, 0])
    np.testing.assert_allclose(reach.opt.gravity, [0, 0, -9.81])


def test_plant_parameters(reach):
    assert np.all(reach.dof_armature > 0)
    assert np.all(reach.dof_damping > 0)
    # The damping time constant armature/damping is 10 s: a little loss, far slower than a reach.
    np.testing.assert_allclose(reach.dof_armature / reach.dof_damping, 10.0)
    assert np.all(reach.dof_frictionloss == 0)
    # Gravity compensation is on every moving link.
    assert np.all(reach.body_gravcomp[2:] == 1.0)
    # Paper author's (PE) mass set, fingers lumped into the hand.
    np.testing.assert_allclose(reach.body_mass[2:], [0.7477, 0.99, 0.6763, 0.1785, 0.1785, 0.787])
    # Capsule or box collision geoms only (plus the scene's floor plane), colliding by default
    # with nothing.
    for g in range(reach.ngeom):
        if reach.geom_bodyid[g] == 0:
            continue
        assert int(reach.geom_type[g]) in (int(mujoco.mjtGeom.mjGEOM_CAPSULE), int(mujoco.mjtGeom.mjGEOM_BOX))
        assert reach.geom_contype[g] == 0 and reach.geom_conaffinity[g] == 0


def test_reach_scene_is_lean(reach):
    flags = reach.opt.disableflags
    assert flags & mujoco.mjtDisableBit.mjDSBL_CONTACT
    assert flags & mujoco.mjtDisableBit.mjDSBL_EULERDAMP
    assert reach.opt.integrator == mujoco.mjtIntegrator.mjINT_EULER
    assert reach.opt.iterations <= 4


def test_arm_file_standalone_and_includable(arm, tmp_path):
    """jaco2.xml loads on its own and can be included by another scene (e.g. block-in-hole)."""
    assert arm.njnt == 6 and arm.nu == 6
    root = ET.parse(MJCF_DIR / "jaco2.xml").getroot()
    assert root.find("option") is None  # scene settings belong to the including file
    scene = tmp_path / "scene.xml"
    scene.write_text(f"""<mujoco><include file="{MJCF_DIR / 'jaco2.xml'}"/>
      <worldbody><body name="table" pos="0.5 0 0"><geom type="box" size="0.2 0.2 0.01"/></body></worldbody>
    </mujoco>""")
    m = mujoco.MjModel.from_xml_path(str(scene))
    assert m.njnt == 6 and m.nbody == arm.nbody + 1
    q = np.array([0.1, 3.0, 1.0, 4.0, 2.0, 2.0])
    np.testing.assert_allclose(site_position(m, q), site_position(arm, q), atol=1e-12)
