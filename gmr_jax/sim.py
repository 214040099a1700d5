"""The simulated Jaco 2: load the MJCF, step it at 20 Hz, roll out controllers.

State x = [q, q̇] ([dX] = [12]: 6 Kinova actuator angles in rad, 6 velocities in rad/s), action
u = 6 joint torques (N·m) held for one control step of ``SimConfig.control_dt`` (0.05 s), which
is ``SimConfig.substeps`` physics steps. The plant adds gravity compensation (MuJoCo body
``gravcomp``, which MJX honours: ``mjx/_src/passive.py``) unless configured off, and saturates
the commanded torques at the actuator peak torques.

Two interchangeable backends run the same MJCF behind the same functions:

* ``"mjx"``: MuJoCo MJX with ``impl='jax'``, pure JAX (default where JAX has a GPU).
  Differentiable (``jax.jacfwd`` through :func:`step` works).
* ``"mujoco"``: C MuJoCo on the host, called once per control step through a host callback
  (``jax.pure_callback`` in a GPU program, ``jax.experimental.buffer_callback`` in a CPU one)
  with ``vmap_method="broadcast_all"``, so one callback receives the whole (possibly nested)
  batch and steps it with ``mujoco.rollout`` (a large batch on several host cores). It stays
  jittable and vmappable, and about 100× faster than MJX on a 2-core CPU (10 rollouts of 80
  steps, ``benchmarks/rollout.py``). Not differentiable (no JVP rule for the callback).

Everything here is a pure function of arrays; :func:`rollout` works under ``jax.jit`` and under
any number of nested ``jax.vmap``s over (policy, x0, eps). :func:`rollout_with_final` also
returns the state x_T after the last action (for final-state evaluation), at no extra cost.

Public API: :func:`make_sim` (cached ``Sim`` with dX, dU, torque_limit), :func:`step`,
:func:`rollout`, :func:`rollout_with_final`, :func:`end_effector`, :func:`clip_torques`,
:func:`linear_gaussian_action`, :func:`diverged`.

A rollout that diverges (non-finite state, or C MuJoCo's automatic reset after a bad
acceleration) yields NaN from that step on, with both backends; :func:`diverged` flags it.
"""

from __future__ import annotations

import dataclasses
import functools
import importlib.resources
import os
import pathlib
import threading
from typing import Callable, NamedTuple, Union

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from gmr_jax import sharding, types
from gmr_jax.config import SimConfig

Array = jax.Array

def _mjcf_dir() -> pathlib.Path:
    """``$GMR_JAX_MJCF_DIR``, else the package data ``gmr_jax/jaco_mjcf/`` (an installed wheel),
    else ``jaco_mjcf/`` next to the package (a checkout or an editable install)."""
    env = os.environ.get("GMR_JAX_MJCF_DIR")
    if env:
        return pathlib.Path(env).expanduser().resolve()
    # A wheel installs the repository's jaco_mjcf/ as gmr_jax/jaco_mjcf/ (pyproject.toml's
    # package-dir). MuJoCo reads files by path (and resolves the scene's <include> beside it), so
    # only a package on the file system counts.
    packaged = importlib.resources.files("gmr_jax") / "jaco_mjcf"
    if isinstance(packaged, pathlib.Path) and packaged.is_dir():
        return packaged.resolve()
    return pathlib.Path(__file__).resolve().parent.parent / "jaco_mjcf"


MJCF_DIR = _mjcf_dir()
ARM_JOINTS = tuple(f"joint_{i}" for i in range(1, 7))
EE_SITE = "end_effector"

# A policy callable maps (t [] int, x [dX], eps_t [dU]) to u [dU].
PolicyFn = Callable[[Array, Array, Array], Array]
Policy = Union[types.LinearGaussianPolicy, PolicyFn]


class MJCFError(ValueError):
    """The MJCF file is missing, malformed or lacks what the simulation needs."""


# ---------------------------------------------------------------------------------------------
# Loading


def scene_path(scene: str) -> pathlib.Path:
    """The MJCF file of a scene: ``"reach"`` → ``jaco_mjcf/reach.xml``; a path is taken as is."""
    if scene.endswith(".xml") or os.sep in scene or "/" in scene:
        return pathlib.Path(scene).expanduser().resolve()
    return MJCF_DIR / f"{scene}.xml"


class _Chain(NamedTuple):
    """Static data of the kinematic chain from the world to a site (numpy)."""

    body_pos: tuple  # per body on the chain, root first: [3]
    body_quat: tuple  # [4] (w, x, y, z)
    joints: tuple  # per body: tuple of (qpos address, axis [3], anchor [3]) of its hinges
    site_pos: np.ndarray  # [3] site position in its body frame


@dataclasses.dataclass(frozen=True, eq=False)
class Sim:
    """A loaded plant. Hashes by identity, so it can be a static argument of ``jax.jit``.

    Attributes:
      config: the SimConfig it was made from.
      path: the scene's MJCF file.
      backend: the resolved backend, "mjx" or "mujoco".
      model: the compiled C ``MjModel`` (timestep, gravity compensation and control limits set
        from the config).
      dX, dU: state and action sizes (12, 6 for the Jaco 2).
      nq: number of joint angles (6).
      torque_limit: [dU] numpy array of actuator peak torques (N·m), the saturation bounds.
    """

    config: SimConfig
    path: pathlib.Path
    backend: str
    model: mujoco.MjModel
    dX: int
    dU: int
    nq: int
    torque_limit: np.ndarray
    chain: _Chain
    _cache: dict = dataclasses.field(default_factory=dict, repr=False)
    _lock: threading.Lock = dataclasses.field(default_factory=threading.Lock, repr=False)

    # -- MJX model and data template (built lazily, per precision) --------------------------
    def mjx_model_and_data(self):
        """(mjx.Model, mjx.Data template) in the current default float precision.

        Built eagerly (never as tracers, even when first asked for inside a ``jit`` trace) and
        cached per precision, because ``put_model`` follows ``jax_enable_x64``.
        """
        key = ("mjx", bool(jax.config.jax_enable_x64))
        if key not in self._cache:
            from mujoco import mjx  # imported lazily: it is slow to import and the C path skips it

            with self._lock, jax.ensure_compile_time_eval():
                if key not in self._cache:
                    mx = mjx.put_model(self.model, impl="jax")
                    self._cache[key] = (mx, mjx.make_data(mx, impl="jax"))
        return self._cache[key]

    # -- host stepper for the mujoco backend ----------------------------------------------
    def _host(self):
        """The C MuJoCo stepper of this plant: a large batch on up to all host cores (``host_cores``)."""
        if "host" not in self._cache:
            with self._lock:
                if "host" not in self._cache:
                    self._cache["host"] = _HostStepper(self.model, self.config.substeps, host_cores())
        return self._cache["host"]


def _validate(m: mujoco.MjModel, path: pathlib.Path) -> None:
    def fail(msg):
        raise MJCFError(f"MJCF {path}: {msg}")

    for name in ARM_JOINTS:
        jid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, name)
        if jid < 0:
            fail(f"no joint named {name!r} (the arm needs joint_1 … joint_6)")
        if m.jnt_type[jid] != mujoco.mjtJoint.mjJNT_HINGE:
            fail(f"joint {name!r} must be a hinge")
    if m.nq != m.nv:
        fail(f"nq={m.nq} != nv={m.nv}: the state [q, q̇] assumes hinge/slide joints only")
    if m.nu < 1:
        fail("no actuators")
    if mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, EE_SITE) < 0:
        fail(f"no site named {EE_SITE!r}")
    for i in range(m.nu):
        if m.actuator_trntype[i] != mujoco.mjtTrn.mjTRN_JOINT:
            fail(f"actuator {i} does not drive a joint")
        lo, hi = m.actuator_ctrlrange[i]
        if not (m.actuator_ctrllimited[i] and np.isclose(lo, -hi) and hi > 0):
            fail(f"actuator {i} needs a symmetric ctrlrange (the torque limit), got [{lo}, {hi}]")


def _chain(m: mujoco.MjModel, site: str = EE_SITE) -> _Chain:
    sid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, site)
    if sid < 0:
        raise MJCFError(f"no site named {site!r}")
    bodies = []
    b = int(m.site_bodyid[sid])
    while b != 0:
        bodies.append(b)
        b = int(m.body_parentid[b])
    bodies.reverse()
    pos, quat, joints = [], [], []
    for b in bodies:
        pos.append(np.array(m.body_pos[b]))
        quat.append(np.array(m.body_quat[b]))
        js = []
        for j in range(m.body_jntadr[b], m.body_jntadr[b] + m.body_jntnum[b]):
            if m.jnt_type[j] != mujoco.mjtJoint.mjJNT_HINGE:
                raise MJCFError(f"chain of site {site!r}: joint {j} is not a hinge")
            js.append((int(m.jnt_qposadr[j]), np.array(m.jnt_axis[j]), np.array(m.jnt_pos[j])))
        joints.append(tuple(js))
    return _Chain(tuple(pos), tuple(quat), tuple(joints), np.array(m.site_pos[sid]))


def _resolve_backend(backend: str) -> str:
    if backend == "auto":
        from gmr_jax import sharding  # noqa: PLC0415 (sharding needs nothing of this module)

        return "mjx" if sharding.target_platform() == "gpu" else "mujoco"
    if backend not in ("mjx", "mujoco"):
        raise ValueError(f"sim.backend={backend!r}: allowed values are ('auto', 'mjx', 'mujoco')")
    return backend


def make_sim(cfg: SimConfig) -> Sim:
    """Load and compile the scene of ``cfg`` (cached per config and resolved backend, so cheap at
    trace time; backend "auto" is MJX when tracing for a GPU, ``sharding.target_platform``).

    The config's physics timestep (control_dt / substeps) replaces the MJCF's; with
    ``gravity_compensation=False`` every body's ``gravcomp`` is set to 0; with
    ``clip_torques=False`` the actuators' control limits are lifted.

    Raises:
      FileNotFoundError: the MJCF file does not exist (the message names it).
      MJCFError: the file is malformed or lacks the joints/actuators/site the plant needs.
    """
    return _make_sim(cfg, _resolve_backend(cfg.backend))


@functools.lru_cache(maxsize=None)
def _make_sim(cfg: SimConfig, backend: str) -> Sim:
    if not isinstance(cfg.substeps, int) or cfg.substeps < 1:
        raise ValueError(f"sim.substeps={cfg.substeps!r}: must be a positive integer")
    if not cfg.control_dt > 0:
        raise ValueError(f"sim.control_dt={cfg.control_dt!r}: must be a positive number")
    if cfg.float32 and backend != "mjx":
        raise ValueError("sim.float32 steps MJX in float32; C MuJoCo computes in float64 only: "
                         "use --backend mjx or leave sim.float32 off")
    path = scene_path(cfg.scene)
    if not path.is_file():
        available = sorted(p.stem for p in MJCF_DIR.glob("*.xml"))
        raise FileNotFoundError(f"MJCF scene {cfg.scene!r}: file {path} does not exist "
                                f"(scenes in {MJCF_DIR}: {available})")
    try:
        spec = mujoco.MjSpec.from_file(str(path))
        m0 = spec.compile()
    except Exception as e:  # MuJoCo raises ValueError without naming the file
        raise MJCFError(f"MJCF {path} could not be loaded: {e}") from e
    _validate(m0, path)
    torque_limit = np.array(m0.actuator_ctrlrange[:, 1], dtype=np.float64)

    spec.option.timestep = cfg.timestep
    if not cfg.gravity_compensation:
        for body in spec.bodies:
            body.gravcomp = 0.0
    if not cfg.clip_torques:
        for act in spec.actuators:
            act.ctrllimited = mujoco.mjtLimited.mjLIMITED_FALSE
    model = spec.compile()
    return Sim(config=cfg, path=path, backend=backend, model=model, dX=2 * model.nq, dU=model.nu,
               nq=model.nq, torque_limit=torque_limit, chain=_chain(model))


# ---------------------------------------------------------------------------------------------
# Kinematics


def _quat_to_mat(qt: np.ndarray) -> np.ndarray:
    w, x, y, z = qt / np.linalg.norm(qt)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _axis_rotation(axis: np.ndarray, angle: Array) -> Array:
    """Rotation matrix [3, 3] about a fixed unit axis (Rodrigues), differentiable in angle."""
    a = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    dtype = angle.dtype
    return (jnp.eye(3, dtype=dtype) + jnp.sin(angle) * jnp.asarray(k, dtype)
            + (1 - jnp.cos(angle)) * jnp.asarray(k @ k, dtype))


def site_chain(s: Sim, site: str) -> _Chain:
    """The kinematic chain of a site of the scene (cached per plant)."""
    key = ("chain", site)
    if key not in s._cache:
        with s._lock:
            s._cache.setdefault(key, _chain(s.model, site))
    return s._cache[key]


def site_position(s: Sim, q: Array, site: str) -> Array:
    """World position of a site, [nq] → [3] (m).

    A plain JAX chain of the compiled model's body frames and hinge rotations (the same numbers
    MuJoCo uses, so it agrees with ``site_xpos`` to rounding), jittable, vmappable and
    differentiable (``jax.jacfwd``). Follows the dtype of ``q``.
    """
    q = jnp.asarray(q)
    if not jnp.issubdtype(q.dtype, jnp.floating):
        q = q.astype(jnp.result_type(float))
    dtype = q.dtype
    R = jnp.eye(3, dtype=dtype)
    p = jnp.zeros(3, dtype=dtype)
    c = s.chain if site == EE_SITE else site_chain(s, site)
    for pos, quat, joints in zip(c.body_pos, c.body_quat, c.joints):
        p = p + R @ jnp.asarray(pos, dtype)
        R = R @ jnp.asarray(_quat_to_mat(quat), dtype)
        for adr, axis, anchor in joints:
            Rj = _axis_rotation(axis, q[adr])
            # rotation about an axis through the anchor point (zero for this arm)
            p = p + R @ (jnp.asarray(anchor, dtype) - Rj @ jnp.asarray(anchor, dtype))
            R = R @ Rj
    return p + R @ jnp.asarray(c.site_pos, dtype)


def end_effector(s: Sim, q: Array) -> Array:
    """World position of the ``end_effector`` site, [nq] → [3] (m); see :func:`site_position`."""
    return site_position(s, q, EE_SITE)


# ---------------------------------------------------------------------------------------------
# One control step


def clip_torques(s: Sim, u: Array) -> Array:
    """Saturate u [..., dU] at ±torque_limit if the config clips (identity otherwise)."""
    if not s.config.clip_torques:
        return u
    lim = jnp.asarray(s.torque_limit, u.dtype)
    return jnp.clip(u, -lim, lim)


def _mjx_step(s: Sim, x: Array, u: Array) -> Array:
    from mujoco import mjx

    mx, d0 = s.mjx_model_and_data()
    fdt = d0.qpos.dtype
    # A fresh Data from the template each control step: the state is exactly (q, q̇), and the
    # model has warmstart disabled, so nothing else carries over between control steps.
    d = d0.replace(qpos=x[: s.nq].astype(fdt), qvel=x[s.nq:].astype(fdt), ctrl=u.astype(fdt))
    # The template's other fields come to depend on (q, q̇, u) in the first physics step: made to
    # vary with them from the start, so that a vmap batches the step once (sharding.scan_varying).
    # One anchor for x and u: in a rollout the action reads the state, so they vary together
    # (where only one varied, the vmap would keep the other's pass-through fields unbatched).
    varying = (jax.tree_util.tree_map(lambda _: False, d).replace(qpos=True, qvel=True, ctrl=True), None)
    anchor = jnp.stack([x[0], u[0].astype(x.dtype)])
    d, _ = sharding.scan_varying(lambda dd, _: (mjx.step(mx, dd), None), d, None, varying, anchor,
                                 length=s.config.substeps)
    return jnp.concatenate([d.qpos, d.qvel]).astype(x.dtype)


# Wrapped in ``jit`` so that its jaxpr is traced once per (plant, dtype) and the batched versions
# are cached: tracing and batching MJX's step is most of the trace time of a training iteration,
# which holds several rollouts (and CLI runs trace several iterations side by side).
_mjx_step_jit = jax.jit(_mjx_step, static_argnums=0)


# A threaded step gives its threads this many members each or more, on average: a member's control
# step is tens of microseconds of MuJoCo, a thread's hand-off a few.
ROWS_PER_THREAD = 8


class _HostStepper:
    """Steps a batch of C MuJoCo states for ``substeps`` physics steps with ``mujoco.rollout``
    (``nthread`` > 0: on up to that many threads, a power of two, with about
    ``ROWS_PER_THREAD`` members or more each).

    Callers at the same time step with their own ``MjData`` (and thread pool), so runs trained
    side by side step their plants at the same time. A member's result does not depend on the
    batch or thread it is stepped in: every member starts from its full physics state and a zero
    warm start (``initial_warmstart``), and MuJoCo computes everything else (contacts, the
    solver's state) anew in every step, so any thread count gives the same bits.
    """

    def __init__(self, model: mujoco.MjModel, substeps: int, nthread: int = 0):
        self.model = model
        self.substeps = substeps
        self.nthread = nthread
        self._free = {}  # thread count: (Rollout, data) pairs not in use
        self._lock = threading.Lock()
        self.nstate = mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_FULLPHYSICS)
        d = mujoco.MjData(model)
        self.template = np.empty(self.nstate)
        mujoco.mj_getState(model, d, self.template, mujoco.mjtState.mjSTATE_FULLPHYSICS)
        # FULLPHYSICS is laid out in mjtState bit order: time, qpos, qvel, act, ...
        self.i_qpos = mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_TIME)
        self.i_qvel = self.i_qpos + model.nq
        self.t_end = substeps * model.opt.timestep

    def _take(self, nthread: int):
        """A free (``mujoco.rollout.Rollout``, data) pair of ``nthread`` threads, made if every
        one is in use. (Not one per thread: XLA runs a host callback under a Python thread
        state made for that call.)"""
        with self._lock:
            free = self._free.setdefault(nthread, [])
            if free:
                return free.pop()
        from mujoco import rollout as mj_rollout

        return (mj_rollout.Rollout(nthread=nthread),
                [mujoco.MjData(self.model) for _ in range(nthread)] if nthread else mujoco.MjData(self.model))

    def _give_back(self, nthread: int, pair) -> None:
        with self._lock:
            self._free[nthread].append(pair)

    def __call__(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """x [..., dX], u [..., dU] (same leading shape) → x1 [..., dX] in x's dtype."""
        lead = x.shape[:-1]
        nq, nu = self.model.nq, self.model.nu
        xb = np.asarray(x, dtype=np.float64).reshape(-1, 2 * nq)
        ub = np.broadcast_to(np.asarray(u, dtype=np.float64), lead + (nu,)).reshape(-1, 1, nu)
        B = xb.shape[0]
        # Members with a non-finite state or torque are not stepped (MuJoCo would warn about
        # each one); they come out as NaN below.
        bad_in = ~np.all(np.isfinite(xb), axis=1) | ~np.all(np.isfinite(ub), axis=(1, 2))
        state0 = np.tile(self.template, (B, 1))
        state0[:, 0] = 0.0  # time
        state0[:, self.i_qpos:self.i_qvel] = np.where(bad_in[:, None], state0[:, self.i_qpos:self.i_qvel], xb[:, :nq])
        state0[:, self.i_qvel:self.i_qvel + nq] = np.where(bad_in[:, None], 0.0, xb[:, nq:])
        out = np.empty((B, self.substeps, self.nstate))
        ctrl = np.ascontiguousarray(np.broadcast_to(np.where(bad_in[:, None, None], 0.0, ub), (B, self.substeps, nu)))
        n = min(self.nthread, B // ROWS_PER_THREAD)
        nthread = 1 << (n.bit_length() - 1) if n > 1 else 0  # a power of two: few pool sizes
        pair = self._take(nthread)
        try:
            pair[0].rollout(self.model, pair[1], state0, ctrl, nstep=self.substeps, state=out,
                            initial_warmstart=np.zeros((B, self.model.nv)),
                            sensordata=np.empty((B, self.substeps, self.model.nsensordata)))
        finally:
            self._give_back(nthread, pair)
        last = out[:, -1]
        x1 = np.concatenate([last[:, self.i_qpos:self.i_qvel], last[:, self.i_qvel:self.i_qvel + nq]], axis=1)
        # C MuJoCo silently resets a state whose acceleration or position went bad (time then
        # restarts at 0): turn such members, and any non-finite input, into NaN so the
        # divergence is visible, as it is with MJX.
        bad = (np.abs(last[:, 0] - self.t_end) > 0.5 * self.model.opt.timestep) | bad_in
        x1[bad] = np.nan
        return x1.reshape(lead + (2 * nq,)).astype(x.dtype, copy=False)

    def rollout(self, x0, K, k, chol, eps, limit):
        """A whole linear-Gaussian rollout on the host (one callback instead of one per step).

        x0 [..., dX]; K [..., T, dU, dX]; k [..., T, dU]; chol [..., T, dU, dU]; eps [..., T, dU];
        limit [dU] or None. Returns (X [..., T, dX], U [..., T, dU], x_T [..., dX]) in x0's
        dtype, with the semantics of ``rollout_with_final``: u_t = clip(K_t x_t + k_t + chol_tᵀ
        ε_t), the state rounded to x0's dtype after every step as the step callback does.
        """
        dtype = x0.dtype
        lead, (T, dU) = x0.shape[:-1], eps.shape[-2:]
        dX = x0.shape[-1]
        flat = lambda a, tail: np.asarray(a, np.float64).reshape((-1,) + tail)  # noqa: E731
        x = flat(x0, (dX,))
        K, k, chol, eps = flat(K, (T, dU, dX)), flat(k, (T, dU)), flat(chol, (T, dU, dU)), flat(eps, (T, dU))
        X = np.empty((x.shape[0], T, dX))
        U = np.empty((x.shape[0], T, dU))
        for t in range(T):
            X[:, t] = x
            u = (np.einsum("bij,bj->bi", K[:, t], x) + k[:, t]
                 + np.einsum("bji,bj->bi", chol[:, t], eps[:, t])).astype(dtype).astype(np.float64)
            if limit is not None:
                u = np.clip(u, -limit, limit)
            U[:, t] = u
            x = self(x.astype(dtype), u.astype(dtype)).astype(np.float64)
        return (X.reshape(lead + (T, dX)).astype(dtype), U.reshape(lead + (T, dU)).astype(dtype),
                x.reshape(lead + (dX,)).astype(dtype))


def _host_rollout(s: Sim, policy: types.LinearGaussianPolicy, x0: Array, eps: Array):
    """``rollout_with_final``'s (X, U, x_T) of a linear-Gaussian controller on the C MuJoCo
    backend, as one host callback for the whole horizon (the per-step callbacks of a policy
    rollout each stop the device stream; here the controller is known in advance)."""
    T, dU = eps.shape
    dtype = x0.dtype
    limit = np.asarray(s.torque_limit, np.float64) if s.config.clip_torques else None
    out = (jax.ShapeDtypeStruct((T, x0.shape[-1]), dtype), jax.ShapeDtypeStruct((T, dU), dtype),
           jax.ShapeDtypeStruct(x0.shape, dtype))
    stepper = s._host()
    return _host_callback(lambda *a: stepper.rollout(*a, limit=limit), out, x0, policy.K.astype(dtype),
                          policy.k.astype(dtype), policy.chol_pol_covar.astype(dtype), eps.astype(dtype))


def host_cores() -> int:
    """The host cores this process may run on (its CPU affinity, else ``os.cpu_count()``)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def _host_step(s: Sim, x: Array, u: Array) -> Array:
    return _host_callback(s._host(), jax.ShapeDtypeStruct(x.shape, x.dtype), x, u.astype(x.dtype))


def _host_callback(fn: Callable, result_shape_dtypes, *args: Array):
    """``fn(*args)`` (NumPy arrays in, a pytree of NumPy arrays out, shaped like
    ``result_shape_dtypes``) called on the host from the program being traced, with
    ``vmap_method="broadcast_all"`` (one call receives the whole batch).

    Traced for a GPU (``sharding.target_platform``): ``jax.pure_callback``. Traced for the CPU:
    ``jax.experimental.buffer_callback``, which reads the operands in XLA's buffers and writes the
    results into them. ``pure_callback`` would first put every operand on the first CPU device;
    on several CPU devices (``--xla_force_host_platform_device_count``) each partition of a
    sharded program then waits in its callback for a copy that runs, above about 100 KiB, in
    the client's thread pool, whose threads are those partitions: the program never finished.
    """
    from gmr_jax import sharding  # noqa: PLC0415 (sharding needs nothing of this module)

    if sharding.target_platform() != "cpu":
        return jax.pure_callback(fn, result_shape_dtypes, *args, vmap_method="broadcast_all")
    from jax.experimental.buffer_callback import buffer_callback  # noqa: PLC0415

    def read_only(buffer) -> np.ndarray:  # XLA's operand memory, which other operations may share
        a = np.asarray(buffer)
        a.flags.writeable = False
        return a

    def write(ctx, out, *operands):
        del ctx
        results = fn(*(read_only(a) for a in operands))
        for i, (o, r) in enumerate(zip(jax.tree.leaves(out), jax.tree.leaves(results), strict=True)):
            o, r = np.asarray(o), np.asarray(r)
            if r.shape != o.shape or r.dtype != o.dtype:  # as pure_callback checks
                raise RuntimeError(f"host callback result {i}: {r.dtype}{list(r.shape)}, expected "
                                   f"{o.dtype}{list(o.shape)}")
            o[...] = r

    return buffer_callback(write, result_shape_dtypes, vmap_method="broadcast_all")(*args)


def step_unclipped(s: Sim, x: Array, u: Array) -> Array:
    """One control step without the torque saturation of :func:`step` (x [dX], u [dU] → [dX])."""
    x = jnp.asarray(x)
    u = jnp.asarray(u, x.dtype)
    if s.backend == "mjx" and s.config.float32 and x.dtype == jnp.float64:
        # traced with x64 off: the float32 MJX model, and float32 for MJX's own constants too
        with jax.enable_x64(False):
            x_next = _mjx_step_jit(s, x.astype(jnp.float32), u.astype(jnp.float32))
        return x_next.astype(x.dtype)
    if s.backend == "mjx":
        return _mjx_step_jit(s, x, u)
    return _host_step(s, x, u)


def step(s: Sim, x: Array, u: Array) -> Array:
    """One control step: torques u [dU] (clipped at the limits) held for ``substeps`` physics
    steps from x [dX] = [q, q̇]; returns x' [dX] in x's dtype."""
    x = jnp.asarray(x)
    return step_unclipped(s, x, clip_torques(s, jnp.asarray(u, x.dtype)))


# ---------------------------------------------------------------------------------------------
# Rollouts


def linear_gaussian_action(policy: types.LinearGaussianPolicy, t: Array | None, x: Array, eps_t: Array) -> Array:
    """u_t = K_t x + k_t + chol_pol_covar_tᵀ ε_t, [dU] (toolbox convention: chol is upper).

    ``policy`` holds all steps (K [T, dU, dX], …) and t picks one, or t is None and ``policy``
    holds one step's slices (K [dU, dX], k [dU], chol [dU, dU]).
    """
    K, k, chol = policy.K, policy.k, policy.chol_pol_covar
    if t is not None:
        K, k, chol = K[t], k[t], chol[t]
    return K @ x + k + chol.T @ eps_t


def rollout_with_final(s: Sim, policy: Policy, x0: Array, eps: Array, with_ee: bool = True):
    """Roll out a controller for T = eps.shape[0] control steps; also return the final state.

    Args:
      s: the plant (``make_sim(cfg.sim)``).
      policy: a ``types.LinearGaussianPolicy`` (K [T, dU, dX], k [T, dU], chol_pol_covar
        [T, dU, dU]; u_t = K_t x_t + k_t + chol_tᵀ ε_t) or a callable ``policy(t, x, eps_t) -> u``
        (t a traced int scalar, x [dX], eps_t [dU]), e.g. a closure around a Flax ``apply``.
      x0: [dX] initial state.
      eps: [T, dU] exploration noise (zeros for a noiseless rollout).
      with_ee: also compute end-effector positions (otherwise ``ee`` is None).

    Returns:
      (traj, x_T): ``types.Trajectories`` with X [T, dX] (x_0 … x_{T-1}), U [T, dU] (the
      torques applied, after clipping), ee [T, 3] (site position at x_t), and x_T [dX], the
      state after the last action. Batch axes come from ``jax.vmap`` over (policy, x0, eps).
    """
    x0 = jnp.asarray(x0)
    if not jnp.issubdtype(x0.dtype, jnp.floating):
        x0 = x0.astype(jnp.result_type(float))
    eps = jnp.asarray(eps)
    T = eps.shape[0]
    if s.backend == "mujoco" and isinstance(policy, types.LinearGaussianPolicy):
        X, U, xT = _host_rollout(s, policy, x0, eps)
        ee = jax.vmap(functools.partial(end_effector, s))(X[:, : s.nq]) if with_ee else None
        return types.Trajectories(X=X, U=U, ee=ee), xT
    if isinstance(policy, types.LinearGaussianPolicy):
        # scan over the per-step slices rather than indexing with a traced t
        pol_xs = types.LinearGaussianPolicy(policy.K, policy.k, None, policy.chol_pol_covar, None)

        def act(t, x, e, p):
            return linear_gaussian_action(p, None, x, e)

        # the action reads the noise, so the state varies wherever the noise does under vmap
        x0 = sharding.varying_like(x0, eps)
    elif callable(policy):
        pol_xs = None

        def act(t, x, e, p):
            return policy(t, x, e)
    else:
        raise TypeError(f"policy must be a LinearGaussianPolicy or a callable, got {type(policy)}")

    def body(x, inp):
        t, e, p = inp
        u = clip_torques(s, jnp.asarray(act(t, x, e, p)).astype(x.dtype))
        return step_unclipped(s, x, u), (x, u)

    xT, (X, U) = jax.lax.scan(body, x0, (jnp.arange(T), eps, pol_xs))
    ee = jax.vmap(functools.partial(end_effector, s))(X[:, : s.nq]) if with_ee else None
    return types.Trajectories(X=X, U=U, ee=ee), xT


def rollout(s: Sim, policy: Policy, x0: Array, eps: Array, with_ee: bool = True) -> types.Trajectories:
    """:func:`rollout_with_final` without the final state: X [T, dX], U [T, dU], ee [T, 3]."""
    return rollout_with_final(s, policy, x0, eps, with_ee)[0]


def rollout_per_row(s: Sim, traj: types.LinearGaussianPolicy, fns: tuple[PolicyFn, ...], which: Array,
                    x0: Array, eps: Array) -> types.Trajectories:
    """R rollouts, each with its own controller, as one batched rollout (MJX).

    Row r runs the local controller ``traj`` [r] when ``which[r] == 0`` and the callable
    ``fns[which[r] - 1]`` otherwise. Every controller is evaluated at every step of every row and
    the row's action picked by ``jnp.where``, so a program that needs rollouts of several
    controllers holds one instance of the simulator's step instead of one per controller: on MJX
    each instance costs seconds of compilation (benchmarks/RESULTS.md). The picked action is the
    same arithmetic as a rollout of that controller alone.

    Args:
      traj: LinearGaussianPolicy with leading axis R (K [R, T, dU, dX], k, chol_pol_covar).
      fns: rollout callables ``(t, x, eps_t) -> u``, shared by the rows.
      which: [R] int, 0 for the local controller, i ≥ 1 for ``fns[i - 1]``.
      x0: [R, dX] initial states; eps: [R, T, dU] noise (zeros for noiseless rows).
    Returns:
      Trajectories [R, T, ...].
    """

    def one(pol, x, e, w):
        def act(t, xx, et):
            u = linear_gaussian_action(pol, t, xx, et)
            for i, fn in enumerate(fns, start=1):
                u = jnp.where(w == i, fn(t, xx, et), u)
            return u

        # every row's action reads its noise (the local controller's), so the state varies
        # wherever the noise does under vmap
        return rollout(s, act, sharding.varying_like(x, e), e)

    return jax.vmap(one)(traj, x0, eps, which)


def diverged(traj: types.Trajectories, x_final: Array | None = None) -> Array:
    """True for each rollout (leading batch axes of X) whose states or actions are not finite."""
    bad = ~jnp.all(jnp.isfinite(traj.X), axis=(-2, -1)) | ~jnp.all(jnp.isfinite(traj.U), axis=(-2, -1))
    if x_final is not None:
        bad = bad | ~jnp.all(jnp.isfinite(x_final), axis=-1)
    return bad
