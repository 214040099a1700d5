"""The simulation layer: kinematics, plant behaviour, batching, clipping, backend agreement.

Budget: most tests use the C MuJoCo backend (compiles in seconds); MJX is compiled once, for the
backend-agreement test (about a minute on a 2-core CPU, cached by the persistent compilation
cache afterwards). Runs in float64 (tests/conftest.py).
"""

import dataclasses
import math

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from gmr_jax import config, noise, sim, types
from gmr_jax.tasks import block_in_hole as bih
from gmr_jax.tasks import reach as reach_task
from test_mjcf import dh_end_effector, random_angles
from tolerances import SAFETY, affine_tol, assert_tolerances_small, assert_trees_within, linear_tol, measured_tol

# Forward kinematics in JAX against MuJoCo's C code: a chain of 6 rigid transforms (each a 3×3
# rotation product and a translation, ~6 roundings per coordinate) over an arm of about 1 m,
# so c·36·ε·(1 m) for positions and their derivatives (tests/tolerances.py).
FK_TOL = linear_tol(1.0, 36) * 1.0

T = 8
X_A = np.array(reach_task.INITIAL["A"] + (0.0,) * 6)


@pytest.fixture(scope="module")
def s():
    return sim.make_sim(config.SimConfig(backend="mujoco"))


def random_policy(rng, lead, T, dU=6, dX=12, gain=0.5, offset=3.0):
    shape = tuple(lead)
    K = jnp.asarray(rng.normal(size=shape + (T, dU, dX)) * gain)
    k = jnp.asarray(rng.normal(size=shape + (T, dU)) * offset)
    A = rng.normal(size=shape + (T, dU, dU)) * 0.3
    chol = jnp.asarray(np.triu(A) + np.eye(dU) * 1.5)  # upper Cholesky factor, positive diagonal
    cov = jnp.einsum("...ji,...jk->...ik", chol, chol)
    return types.LinearGaussianPolicy(K, k, cov, chol, jnp.linalg.inv(cov))


def random_states(rng, n):
    q = random_angles(rng, n)
    qd = rng.normal(size=(n, 6)) * 0.3
    return np.concatenate([q, qd], axis=1)


@pytest.fixture(scope="module")
def batched(s):
    """Nested vmap (conditions × samples) of rollout_with_final, compiled once for the module."""
    return jax.jit(jax.vmap(jax.vmap(lambda p, x, e: sim.rollout_with_final(s, p, x, e))))


@pytest.fixture(scope="module")
def single(s):
    return jax.jit(lambda p, x, e: sim.rollout_with_final(s, p, x, e))


@pytest.fixture(scope="module")
def step(s):
    return jax.jit(lambda x, u: sim.step(s, x, u))


@pytest.fixture(scope="module")
def zero_run(s):
    """Batched zero-torque rollouts of 80 steps (4 s)."""
    return jax.jit(jax.vmap(lambda x: sim.rollout_with_final(s, zero_policy, x, jnp.zeros((80, 6)))))


def constant_policy(u, T=T):
    """A LinearGaussianPolicy that commands u at every step (K = 0, no noise)."""
    u = jnp.asarray(u)
    z = jnp.zeros((T, 6, 6))
    return types.LinearGaussianPolicy(jnp.zeros((T, 6, 12)), jnp.broadcast_to(u, (T, 6)), z, z, z)


# ---------------------------------------------------------------------------------------------
# Loading and kinematics


def test_make_sim_api(s):
    assert (s.dX, s.dU) == (12, 6)
    np.testing.assert_allclose(s.torque_limit, [30.5] * 3 + [6.8] * 3)
    assert s.backend == "mujoco"
    assert sim.make_sim(config.SimConfig(backend="mujoco")) is s  # cached per config
    assert math.isclose(s.model.opt.timestep, 0.005)
    # "auto" is mjx only where JAX has a GPU
    auto = sim.make_sim(config.SimConfig(backend="auto"))
    assert auto.backend == ("mjx" if jax.default_backend() == "gpu" else "mujoco")
    s2 = sim.make_sim(config.SimConfig(backend="mujoco", substeps=4, control_dt=0.04))
    assert math.isclose(s2.model.opt.timestep, 0.01)


def test_end_effector_against_dh_and_mujoco(s):
    rng = np.random.default_rng(1)
    qs = random_angles(rng, 200)
    ee = np.asarray(jax.jit(jax.vmap(lambda q: sim.end_effector(s, q)))(jnp.asarray(qs)))
    dh = np.array([dh_end_effector(q) for q in qs])
    assert np.max(np.linalg.norm(ee - dh, axis=1)) < 1e-3  # the acceptance bound (1 mm)
    d = mujoco.MjData(s.model)
    sid = mujoco.mj_name2id(s.model, mujoco.mjtObj.mjOBJ_SITE, "end_effector")
    for q, e in zip(qs[:50], ee[:50]):
        d.qpos[:] = q
        mujoco.mj_kinematics(s.model, d)
        np.testing.assert_allclose(e, d.site_xpos[sid], atol=FK_TOL)  # same frames, same numbers


def test_end_effector_jacobian(s):
    """jax.jacfwd of end_effector equals MuJoCo's site Jacobian, so ee costs differentiate right."""
    rng = np.random.default_rng(2)
    jac = jax.jit(jax.jacfwd(lambda q: sim.end_effector(s, q)))
    d = mujoco.MjData(s.model)
    sid = mujoco.mj_name2id(s.model, mujoco.mjtObj.mjOBJ_SITE, "end_effector")
    for q in random_angles(rng, 10):
        d.qpos[:] = q
        mujoco.mj_kinematics(s.model, d)
        mujoco.mj_comPos(s.model, d)
        jacp = np.zeros((3, 6))
        mujoco.mj_jacSite(s.model, d, jacp, None, sid)
        np.testing.assert_allclose(np.asarray(jac(jnp.asarray(q))), jacp, atol=FK_TOL)
    assert sim.end_effector(s, jnp.zeros(6, jnp.float32)).dtype == jnp.float32


def test_missing_and_malformed_mjcf(tmp_path):
    with pytest.raises(FileNotFoundError, match="no_such_scene"):
        sim.make_sim(config.SimConfig(scene="no_such_scene", backend="mujoco"))
    bad = tmp_path / "broken.xml"
    bad.write_text("<mujoco><worldbody><body><geom size='0.1'/></body></worldbody")  # unclosed
    with pytest.raises(sim.MJCFError, match="broken.xml"):
        sim.make_sim(config.SimConfig(scene=str(bad), backend="mujoco"))
    wrong = tmp_path / "not_a_jaco.xml"
    wrong.write_text("<mujoco><worldbody><body><joint name='joint_1'/><geom size='0.1'/></body>"
                     "</worldbody></mujoco>")
    with pytest.raises(sim.MJCFError, match="not_a_jaco.xml.*joint_2"):
        sim.make_sim(config.SimConfig(scene=str(wrong), backend="mujoco"))


# ---------------------------------------------------------------------------------------------
# Plant behaviour


def zero_policy(t, x, e):
    return jnp.zeros(6, x.dtype)


def test_gravity_compensation_holds_pose(s, zero_run):
    """Zero torque with compensation: the arm stays put for 4 s at the paper's poses and at
    random ones. The compensation cancels gravity exactly and the state starts at rest, so only
    float64 rounding (≈1e-16 per step) can move it: 1e-9 rad over 80 control steps is a bound
    with 5 orders of margin that any missing or partial compensation breaks by orders of
    magnitude (without it the arm moves ~0.1–1 rad, test below)."""
    rng = np.random.default_rng(3)
    q = np.concatenate([np.array([reach_task.INITIAL["A"], reach_task.INITIAL["B"], reach_task.TARGET]),
                        random_angles(rng, 5)])
    x0 = np.concatenate([q, np.zeros_like(q)], axis=1)
    traj, xT = zero_run(jnp.asarray(x0))
    assert np.max(np.abs(np.asarray(traj.X) - x0[:, None])) < 1e-9
    assert np.max(np.abs(np.asarray(xT) - x0)) < 1e-9


def potential_energy(m, q):
    d = mujoco.MjData(m)
    d.qpos[:] = q
    mujoco.mj_kinematics(m, d)
    return -float(np.sum(m.body_mass * (d.xipos @ m.opt.gravity)))


def test_without_compensation_the_arm_falls(s):
    """No compensation, zero torque: the arm falls the way gravity pulls it.

    The direction is checked against an independent computation: the initial acceleration must
    be M⁻¹(−∇V), with ∇V the gradient of the potential energy Σ m g z_com by central differences
    of MuJoCo's kinematics (not its dynamics). After one 50 ms step from rest q̇ ≈ 0.05·M⁻¹(−∇V)
    (cosine > 0.99), and over 1 s the potential energy and the end effector go down.
    """
    s_off = sim.make_sim(config.SimConfig(backend="mujoco", gravity_compensation=False))
    m = s_off.model
    run = jax.jit(lambda x: sim.rollout_with_final(s_off, zero_policy, x, jnp.zeros((20, 6))))
    for q0 in (np.array(reach_task.INITIAL["A"]), np.array(reach_task.TARGET)):
        traj, xT = run(jnp.asarray(np.concatenate([q0, np.zeros(6)])))
        X = np.asarray(traj.X)
        grad = np.array([(potential_energy(m, q0 + h) - potential_energy(m, q0 - h)) / 2e-6
                         for h in np.eye(6) * 1e-6])
        d = mujoco.MjData(m)
        d.qpos[:] = q0
        mujoco.mj_forward(m, d)
        M = np.zeros((6, 6))
        mujoco.mj_fullM(m, d, M)
        acc = np.linalg.solve(M, -grad)
        v1 = X[1, 6:]
        cos = v1 @ acc / np.linalg.norm(v1) / np.linalg.norm(acc)
        assert cos > 0.99
        np.testing.assert_allclose(v1, 0.05 * acc, rtol=0.05, atol=1e-3)
        assert potential_energy(m, np.asarray(xT)[:6]) < potential_energy(m, q0) - 0.1  # J
        assert np.asarray(traj.ee)[-1, 2] < np.asarray(traj.ee)[0, 2] - 0.01  # m


def test_torque_clipping(s, single, step):
    big = np.array([100.0, -100.0, 50.0, 20.0, -20.0, 7.0])
    x0 = jnp.asarray(X_A)
    eps = jnp.zeros((T, 6))
    traj, xT = single(constant_policy(big), x0, eps)
    expected = np.clip(big, -s.torque_limit, s.torque_limit)
    np.testing.assert_allclose(np.asarray(traj.U), np.broadcast_to(expected, (T, 6)))
    # identical to commanding the saturated torques directly
    traj2, xT2 = single(constant_policy(expected), x0, eps)
    np.testing.assert_array_equal(np.asarray(traj.X), np.asarray(traj2.X))
    np.testing.assert_array_equal(np.asarray(xT), np.asarray(xT2))
    # sim.step clips too
    np.testing.assert_array_equal(np.asarray(step(x0, jnp.asarray(big))), np.asarray(traj.X[1]))
    # and with clipping off the torques pass through and move the arm further
    s_free = sim.make_sim(config.SimConfig(backend="mujoco", clip_torques=False))
    traj3, _ = jax.jit(lambda p, x, e: sim.rollout_with_final(s_free, p, x, e))(constant_policy(big), x0, eps)
    np.testing.assert_array_equal(np.asarray(traj3.U), np.broadcast_to(big, (T, 6)))
    assert abs(float(traj3.X[-1, 6]) - float(traj.X[-1, 6])) > 0.1  # joint 1 saw 100 vs 30.5 N·m


# ---------------------------------------------------------------------------------------------
# Rollouts


def test_rollout_semantics(s, single, step):
    """X[t+1] = step(X[t], U[t]); x_T = step(X[T-1], U[T-1]); U is the LG action (clipped)."""
    rng = np.random.default_rng(4)
    pol = random_policy(rng, (), T)
    x0 = jnp.asarray(random_states(rng, 1)[0])
    eps = jnp.asarray(rng.normal(size=(T, 6)))
    traj, xT = single(pol, x0, eps)
    X, U = np.asarray(traj.X), np.asarray(traj.U)
    assert X.shape == (T, 12) and U.shape == (T, 6) and traj.ee.shape == (T, 3)
    np.testing.assert_array_equal(X[0], np.asarray(x0))
    for t in range(T):
        A = np.c_[np.asarray(pol.K[t]), np.asarray(pol.chol_pol_covar[t]).T]
        xe = np.r_[X[t], np.asarray(eps[t])]
        u = A @ xe + np.asarray(pol.k[t])
        # K x + k + Lᵀε summed in another order: affine_tol (tests/tolerances.py)
        np.testing.assert_allclose(U[t], np.clip(u, -s.torque_limit, s.torque_limit), rtol=0,
                                   atol=affine_tol(A, xe, np.asarray(pol.k[t])))
        nxt = X[t + 1] if t + 1 < T else np.asarray(xT)
        np.testing.assert_allclose(np.asarray(step(jnp.asarray(X[t]), jnp.asarray(U[t]))), nxt, atol=1e-12)
    d = mujoco.MjData(s.model)
    for t in range(T):  # ee[t] is the site position at x_t
        d.qpos[:] = X[t, :6]
        mujoco.mj_kinematics(s.model, d)
        np.testing.assert_allclose(np.asarray(traj.ee[t]), d.site("end_effector").xpos, atol=FK_TOL)
    assert np.max(np.abs(np.diff(X[:, :6], axis=0))) > 1e-3  # it actually moved
    assert not bool(sim.diverged(traj, xT))
    assert jax.eval_shape(lambda: sim.rollout(s, pol, x0, eps, with_ee=False)).ee is None


def test_host_rollout_equals_stepwise_rollout(s):
    """On the C MuJoCo backend a linear-Gaussian controller runs as one host callback for the
    whole horizon; the same controller given as a callable runs one step callback per control
    step. Both give the same trajectory (batched, with saturated torques)."""
    rng = np.random.default_rng(12)
    pol = random_policy(rng, (3,), T, offset=20.0)  # large offsets: some torques saturate
    x0 = jnp.asarray(random_states(rng, 3))
    eps = jnp.asarray(rng.normal(size=(3, T, 6)))

    def stepwise(p, x, e):
        return sim.rollout_with_final(s, lambda t, xt, et: sim.linear_gaussian_action(p, t, xt, et), x, e)
    whole_fn = jax.jit(jax.vmap(lambda p, x, e: sim.rollout_with_final(s, p, x, e)))
    # The controller's products round differently in the two programs: tolerance from the
    # computation (tests/tolerances.py), the whole-horizon program rerun on inputs perturbed by ε
    # relative, SAFETY times the spread of each output.
    whole, tol = measured_tol(whole_fn, (pol, x0, eps), SAFETY)
    assert_tolerances_small(whole, tol, 1e-8)
    steps = jax.jit(jax.vmap(stepwise))(pol, x0, eps)
    assert np.any(np.abs(np.asarray(whole[0].U)) >= s.torque_limit - 1e-12)
    assert_trees_within(steps, whole, tol)


@pytest.mark.parametrize("scene", ["reach", "block_in_hole"])
@pytest.mark.parametrize("warm_start", [False, True])
def test_host_stepper_threads_and_concurrent_callers_give_the_same_bits(scene, warm_start):
    """The C MuJoCo stepper's result for a state does not depend on the batch order, the thread
    count, nor on other callers stepping at the same time (each with its own MjData): every
    member starts from its full physics state and a zero warm start, in both scenes (the
    block-in-hole's contacts too), also with MuJoCo's warm start switched on."""
    import concurrent.futures

    plant = sim.make_sim(config.SimConfig(scene=scene, substeps=25 if scene == "block_in_hole" else 10,
                                          backend="mujoco"))
    model = mujoco.MjModel.from_xml_path(str(plant.path))  # its own copy: the flag below stays here
    model.opt.timestep = plant.model.opt.timestep
    if warm_start:
        model.opt.disableflags &= ~int(mujoco.mjtDisableBit.mjDSBL_WARMSTART)
    rng = np.random.default_rng(3)
    B = 64
    x = random_states(rng, B)
    if scene == "block_in_hole":  # half of them near the hole, where the block touches its walls
        goal = np.asarray(bih.target_state(bih.default_config("C").task))
        x[: B // 2, :6] = goal[:6] + rng.normal(size=(B // 2, 6)) * 0.03
    u = rng.normal(size=(B, 6)) * 15.0  # applied as given (the stepper does not clip)
    serial = sim._HostStepper(model, plant.config.substeps)
    ref = serial(x, u)
    assert np.all(np.isfinite(ref)) and not np.allclose(ref, x)
    if scene == "block_in_hole":
        data = mujoco.MjData(model)
        contacts = []
        for xi in x:
            data.qpos[:], data.qvel[:] = xi[:6], xi[6:]
            mujoco.mj_forward(model, data)
            contacts.append(data.ncon)
        assert sum(c > 0 for c in contacts) >= 8  # the comparison covers states in contact
    perm = rng.permutation(B)
    np.testing.assert_array_equal(serial(x[perm], u[perm]), ref[perm])
    for n in (2, 3, 64):  # 2 threads, 2 (a power of two), 8 (= 64 // ROWS_PER_THREAD)
        np.testing.assert_array_equal(sim._HostStepper(model, plant.config.substeps, n)(x, u), ref)
    threaded = sim._HostStepper(model, plant.config.substeps, 2)
    batches = [(x[i::4], u[i::4]) for i in range(4)]  # 16 each: 2 threads each
    with concurrent.futures.ThreadPoolExecutor(4) as pool:  # one stepper, four callers at once
        outs = list(pool.map(lambda xu: threaded(*xu), batches * 4))
    for i, out in enumerate(outs):
        np.testing.assert_array_equal(out, ref[i % 4::4])


def test_batched_equals_one_by_one(s, batched, single):
    rng = np.random.default_rng(5)
    M, N = 2, 3
    pol = random_policy(rng, (M, N), T)
    x0 = jnp.asarray(random_states(rng, M * N).reshape(M, N, 12))
    eps = jnp.asarray(rng.normal(size=(M, N, T, 6)))
    traj, xT = batched(pol, x0, eps)
    assert traj.X.shape == (M, N, T, 12) and xT.shape == (M, N, 12)
    # Batched and single controller products may round differently: tolerances from the
    # computation (tests/tolerances.py), each single rollout rerun on inputs perturbed by ε
    # relative, SAFETY times the spread.
    for i in range(M):
        for j in range(N):
            p = jax.tree.map(lambda a: a[i, j], pol)
            ref, tol = measured_tol(single, (p, x0[i, j], eps[i, j]), SAFETY)
            assert_tolerances_small(ref, tol, 1e-8)
            assert_trees_within((jax.tree.map(lambda a: a[i, j], traj), xT[i, j]), ref, tol)
            if (i, j) == (0, 0):
                tol00 = tol[0]  # of traj.X, the first leaf
    # an unbatched policy broadcast over samples (in_axes None) gives the same as tiling it
    p0 = jax.tree.map(lambda a: a[0, 0], pol)
    shared = jax.jit(jax.vmap(lambda x, e: sim.rollout(s, p0, x, e)))(x0[0], eps[0])
    assert_trees_within(shared.X[0], traj.X[0, 0], 2 * tol00)  # both within tol00 of one rollout


def test_same_key_same_result(s, batched):
    M, N = 2, 3
    pol = random_policy(np.random.default_rng(6), (M, N), T)
    x0 = jnp.broadcast_to(jnp.asarray(X_A), (M, N, 12))
    one_noise = jax.jit(lambda k: noise.smooth_noise(k, T, 6, config.NoiseConfig()))

    def make_noise(key):  # the sampling pipeline: key → per-rollout keys → smoothed noise
        keys = jax.random.split(key, M * N)
        return jnp.stack([one_noise(k) for k in keys]).reshape(M, N, T, 6)

    def sample(key):
        return batched(pol, x0, make_noise(key))[0]

    a, b, c = sample(jax.random.key(7)), sample(jax.random.key(7)), sample(jax.random.key(8))
    np.testing.assert_array_equal(np.asarray(a.X), np.asarray(b.X))
    np.testing.assert_array_equal(np.asarray(a.U), np.asarray(b.U))
    assert np.max(np.abs(np.asarray(a.X) - np.asarray(c.X))) > 1e-3
    assert np.max(np.abs(np.asarray(a.U) - np.asarray(c.U))) > 1e-3


def test_dtype_follows_input(s):
    x0 = jnp.asarray(X_A, jnp.float32)
    traj, xT = jax.jit(lambda x: sim.rollout_with_final(s, zero_policy, x, jnp.zeros((3, 6), jnp.float32)))(x0)
    assert traj.X.dtype == traj.U.dtype == traj.ee.dtype == xT.dtype == jnp.float32
    assert sim.step(s, x0, jnp.ones(6, jnp.float32)).dtype == jnp.float32
    assert sim.step(s, jnp.asarray(X_A), jnp.ones(6)).dtype == jnp.float64


def test_float32_plant_inside_a_float64_run_is_the_float32_plant(s):
    """``sim.float32`` (a diagnostic) steps MJX exactly as a float32 run does, inside float64."""
    s32 = sim.make_sim(dataclasses.replace(s.config, backend="mjx", float32=True))
    x, u = jnp.asarray(X_A), jnp.linspace(-0.5, 0.5, 6)  # within the torque limits: no clipping
    y = sim.step(s32, x, u)
    assert y.dtype == jnp.float64
    with jax.enable_x64(False):  # a float32 run
        y_run = sim.step(s32, jnp.asarray(X_A, jnp.float32), jnp.asarray(u, jnp.float32))
    assert y_run.dtype == jnp.float32
    np.testing.assert_array_equal(np.asarray(y), np.asarray(y_run).astype(np.float64))
    with pytest.raises(ValueError, match="sim.float32"):
        sim.make_sim(dataclasses.replace(s.config, backend="mujoco", float32=True))


def test_divergence_is_flagged(s, zero_run):
    """A state C MuJoCo would silently reset (non-finite or beyond its 1e10 bound) comes back NaN."""
    x_bad = jnp.asarray(X_A).at[7].set(1e12)
    x_nan = jnp.asarray(X_A).at[0].set(jnp.nan)
    batch = jnp.stack([jnp.asarray(X_A), x_bad, x_nan] + [jnp.asarray(X_A)] * 5)  # the fixture's batch size
    traj, xT = zero_run(batch)
    assert np.asarray(sim.diverged(traj, xT)).tolist() == [False, True, True] + [False] * 5
    assert np.all(np.isnan(np.asarray(traj.X[1, 1:])))


# ---------------------------------------------------------------------------------------------
# Backends


def test_backends_agree(s, batched):
    """MJX (impl='jax') and C MuJoCo give the same trajectories, nested vmap, one rollout driven
    into the joint-2 lower limit. Same integrator (Euler, no implicit damping), same
    compensation, same solver without warmstart: they differ only by float64 rounding and the
    solver's convergence tests (measured 3e-15); 1e-9 leaves room for platform differences but
    catches any modelling mismatch (e.g. MJX ignoring gravcomp moves joint 2 by ~1e-2 rad in
    one step)."""
    s_mjx = sim.make_sim(dataclasses.replace(s.config, backend="mjx"))
    assert s_mjx.backend == "mjx"
    rng = np.random.default_rng(9)
    M, N = 2, 2
    pol = random_policy(rng, (M, N), T)
    pol = pol._replace(k=pol.k.at[1, 0, :, 1].set(-25.0))  # push joint 2 down hard
    x0 = random_states(rng, M * N).reshape(M, N, 12)
    x0[1, 0] = [0.3, 0.86, 1.0, 4.0, 2.0, 2.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0]
    x0[0, 0] = X_A
    x0 = jnp.asarray(x0)
    eps = jnp.asarray(rng.normal(size=(M, N, T, 6)))
    traj_c, xT_c = batched(pol, x0, eps)
    traj_m, xT_m = jax.jit(jax.vmap(jax.vmap(lambda p, x, e: sim.rollout_with_final(s_mjx, p, x, e))))(pol, x0, eps)
    # A fixed bound on purpose: this compares two implementations of the physics, whose solvers
    # may stop at different iterations, not two roundings of one computation; 1e-9 sits 5 orders
    # of magnitude above the measured difference and 7 below a modelling mismatch.
    np.testing.assert_allclose(np.asarray(traj_m.X), np.asarray(traj_c.X), rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.asarray(traj_m.U), np.asarray(traj_c.U), rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.asarray(xT_m), np.asarray(xT_c), rtol=0, atol=1e-9)
    # the limit case really hit the limit: MuJoCo's soft limit lets it overshoot by < 15 mrad
    # on impact at 1 rad/s, then it rests within 2 mrad of 47° while pushed at -25 N·m
    q2 = np.asarray(traj_c.X[1, 0, :, 1])
    lower = 47 * math.pi / 180
    assert lower - 0.015 < q2.min() < lower
    assert abs(q2[-1] - lower) < 2e-3


def test_host_callback_in_a_cpu_program_checks_results_and_reads_operands_only():
    """``sim._host_callback`` in a CPU program (``buffer_callback``): a result of another dtype or
    shape is an error, as ``jax.pure_callback`` makes it, and the operands, XLA's own memory,
    cannot be written; a right result comes back."""
    x = jnp.arange(3.0)
    spec = jax.ShapeDtypeStruct(x.shape, x.dtype)
    call = lambda fn: jax.block_until_ready(jax.jit(lambda y: sim._host_callback(fn, spec, y))(x))  # noqa: E731
    for bad in (lambda a: a.astype(np.float32), lambda a: a[:2]):
        with pytest.raises(jax.errors.JaxRuntimeError, match="host callback result 0"):
            call(bad)

    def scribble(a):
        a[0] = 1.0
        return a

    with pytest.raises(jax.errors.JaxRuntimeError, match="read-only"):
        call(scribble)
    np.testing.assert_array_equal(call(lambda a: 2 * a), [0.0, 2.0, 4.0])
