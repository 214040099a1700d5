"""Configuration: frozen, hashable dataclasses holding the paper's and the toolbox's defaults.

This is the one place where a default value lives. Every stage function takes the dataclass it
needs (static under ``jit``). Sources: ``shared/reference/mdgps-toolbox.md`` (toolbox numerics),
``shared/reference/gmr-method.md`` (paper, authors' Jaco setup, project decisions).
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from typing import Any

# ---------------------------------------------------------------------------------------------
# Simulation


@dataclass(frozen=True)
class SimConfig:
    """The simulated Jaco 2 plant.

    Attributes:
      scene: MJCF scene name in ``jaco_mjcf/`` (``"reach"`` → ``jaco_mjcf/reach.xml``) or a path
        to an MJCF file.
      control_dt: duration of one control step (s); the paper runs at 20 Hz.
      substeps: physics steps per control step; the physics timestep is control_dt / substeps.
      gravity_compensation: the plant adds the gravity torques (as the Jaco's torque mode does).
      clip_torques: saturate commanded torques at the actuator peak torques (ctrlrange).
      backend: ``"mjx"`` (MJX, impl='jax'), ``"mujoco"`` (C MuJoCo on the host through
        ``jax.pure_callback``) or ``"auto"`` (mjx where JAX has a GPU, else mujoco).
    """

    scene: str = "reach"
    control_dt: float = 0.05
    substeps: int = 10
    gravity_compensation: bool = True
    clip_torques: bool = True
    backend: str = "auto"

    @property
    def timestep(self) -> float:
        return self.control_dt / self.substeps


@dataclass(frozen=True)
class NoiseConfig:
    """Exploration noise, toolbox rule (mdgps-toolbox.md §6)."""

    smooth: bool = True
    sigma: float = 2.0  # Gaussian filter std in time steps (the toolbox's "smooth_noise_var")
    renormalize: bool = True
    truncate: float = 4.0


# ---------------------------------------------------------------------------------------------
# Task and cost

# Kinova actuator angles (rad) of the paper-era Jaco experiment (gmr-method.md §2).
REACH_INITIAL_A = (-0.2046, 3.4193, 1.2257, 4.449, 2.0378, 2.1919)
REACH_INITIAL_B = (-0.2046, 2.419, 1.2255, 4.449, 2.038, 2.1919)
REACH_TARGET = (-0.7046, 4.1905, 1.4259, 4.4488, 2.0376, 2.1919)
JACO_GAINS = (7.09, 2.3, 1.5, 1.2, 1.8, 0.1)


@dataclass(frozen=True)
class CostConfig:
    """Reach cost (mdgps-toolbox.md §5, weights after gmr-method.md §2).

    ℓ_t = ½ Σ wu u² + state term + final-state term.

    Attributes:
      action_weight: wu per joint (the authors': 5e-3 / JACO_GAINS).
      state_wp: per-entry weights of the joint-state term over x = [q, q̇] (angles 1, velocities 0).
      state_l1, state_l2, state_alpha: l1/l2/α of the joint-state term.
      state_ramp: ramp of the joint-state term: "constant", "linear", "quadratic", "final_only".
      final_wp: weights of an extra final-only term on [q, q̇] (velocities count, so the arm stops).
      final_l1, final_l2, final_alpha: its l1/l2/α.
      final_multiplier: wp_final_multiplier of the final term.
      ee_weight: weight of an end-effector position (l2) term towards the target's end-effector
        position; 0 disables it.
    """

    action_weight: tuple[float, ...] = tuple(5e-3 / g for g in JACO_GAINS)
    state_wp: tuple[float, ...] = (1.0,) * 6 + (0.0,) * 6
    state_l1: float = 0.0
    state_l2: float = 1.0
    state_alpha: float = 1e-2
    state_ramp: str = "constant"
    final_wp: tuple[float, ...] = (1.0,) * 6 + (0.1,) * 6
    final_l1: float = 0.0
    final_l2: float = 1.0
    final_alpha: float = 1e-5
    final_multiplier: float = 10.0
    ee_weight: float = 0.0


SCENARIOS = {"A": (REACH_INITIAL_A,), "B": (REACH_INITIAL_B,), "AB": (REACH_INITIAL_A, REACH_INITIAL_B)}


@dataclass(frozen=True)
class TaskConfig:
    """Reach task: conditions (initial joint angles, at rest), target, horizon.

    Attributes:
      scenario: "A", "B" or "AB" (A and B as two conditions).
      T: horizon in control steps (80 = 4 s at 20 Hz).
      target: target joint angles (target velocity 0).
      success_threshold: headline final-state MSE threshold (paper's table).
      success_threshold_loose: the paper's text threshold.
    """

    scenario: str = "A"
    T: int = 80
    target: tuple[float, ...] = REACH_TARGET
    success_threshold: float = 0.01
    success_threshold_loose: float = 0.1

    @property
    def initial_angles(self) -> tuple[tuple[float, ...], ...]:
        return SCENARIOS[self.scenario]

    @property
    def num_conditions(self) -> int:
        return len(self.initial_angles)


# ---------------------------------------------------------------------------------------------
# Trajectory optimisation


@dataclass(frozen=True)
class InitLQRConfig:
    """``init_lqr`` settings (mdgps-toolbox.md §4.1; Jaco values from gmr-method.md §2)."""

    init_var: float = 1.0
    stiffness: float = 1.0
    stiffness_vel: float = 0.25
    final_weight: float = 50.0
    init_acc: tuple[float, ...] = (0.0,) * 6
    init_gains: tuple[float, ...] = tuple(1.0 / g for g in JACO_GAINS)


@dataclass(frozen=True)
class LQRConfig:
    """KL-constrained LQR and η dual search (mdgps-toolbox.md §2).

    Attributes:
      del0: first η increment of the non-PD rule.
      min_eta, max_eta: bracket limits of the η search (max_eta is also the non-PD failure limit).
      max_iterations: DGD_MAX_ITER of the η search.
      tolerance: convergence when |KL − ε| < tolerance · ε.
    """

    del0: float = 1e-4
    min_eta: float = 1e-8
    max_eta: float = 1e16
    max_iterations: int = 50
    tolerance: float = 0.1


@dataclass(frozen=True)
class StepConfig:
    """KL step and its adaptation (mdgps-toolbox.md §1.1, §1.3). ε = kl_step · step_mult · T."""

    kl_step: float = 0.2
    min_step_mult: float = 0.01
    max_step_mult: float = 10.0
    step_rule: str = "laplace"


# How a regularisation value enters a block of a joint covariance (dynamics.regularizer_matrix):
# "ridge" adds value·I (what the toolbox meant, the default), "toolbox" adds value to every entry
# of the block (value·11ᵀ, the toolbox's numpy broadcast, rank one), for exact toolbox numerics.
REGULARIZERS = ("ridge", "toolbox")


@dataclass(frozen=True)
class DynamicsConfig:
    """Dynamics fit with the GMM prior (mdgps-toolbox.md §3; Jaco values from gmr-method.md §2).

    Attributes:
      regularization: added to the (x, u) block of the joint covariance, as set by ``regularizer``.
      regularizer: "ridge" (default): regularization·I; "toolbox": regularization added to every
        entry of the block (the toolbox's rank-one 1e-6·11ᵀ, which does not make a rank-deficient
        block invertible; see dynamics.py).
      max_clusters, min_samples_per_cluster: GMM size rule K = max(2, min(max, ⌊n/min⌋)).
      max_samples: trajectories kept in the prior's ring buffer.
      strength: prior strength.
      em_iterations: EM budget per update (toolbox: 100, stopping early when ll decreases).
      initial_state_var: floor of the initial-state variance.
    """

    regularization: float = 1e-6
    max_clusters: int = 40
    min_samples_per_cluster: int = 40
    max_samples: int = 30
    strength: float = 1.0
    em_iterations: int = 100
    initial_state_var: float = 1e-6
    regularizer: str = "ridge"

    def __post_init__(self):
        if self.regularizer not in REGULARIZERS:
            raise ValueError(f"dynamics.regularizer={self.regularizer!r}: allowed values are {REGULARIZERS}")


POLICY_PRIOR_MODES = ("add", "replace")


@dataclass(frozen=True)
class PolicyPriorConfig:
    """GMM prior of the policy linearisation (mdgps-toolbox.md §4.2, see linearize.py).

    Attributes:
      min_samples_per_cluster, max_clusters: GMM size rule K = max(2, min(max, ⌊n/min⌋)) over the
        n = n_stored·T stored states (toolbox POLICY_PRIOR_GMM: 20 and 50; we cap at 20 clusters;
        the toolbox's MDGPS MuJoCo example uses 40/20/20).
      max_samples: trajectories kept in the prior's ring buffer ('add' mode).
      strength: prior strength.
      em_iterations: EM budget per update (toolbox: 100).
      mode: "add" (append to the store, toolbox default) or "replace" (only the current samples,
        the MuJoCo MDGPS example).
      t0_regularization: added to the state block of the joint covariance at t = 0 (toolbox 1e-8),
        as set by ``t0_regularizer``.
      t0_regularizer: "ridge" (default): t0_regularization·I; "toolbox": t0_regularization added
        to every entry of the block (the toolbox's broadcast, rank one; see linearize.py).
    """

    min_samples_per_cluster: int = 20
    max_clusters: int = 20
    max_samples: int = 20
    strength: float = 1.0
    em_iterations: int = 100
    mode: str = "add"
    t0_regularization: float = 1e-8
    t0_regularizer: str = "ridge"

    def __post_init__(self):
        if self.mode not in POLICY_PRIOR_MODES:
            raise ValueError(f"policy_prior.mode={self.mode!r}: allowed values are {POLICY_PRIOR_MODES}")
        if self.t0_regularizer not in REGULARIZERS:
            raise ValueError(f"policy_prior.t0_regularizer={self.t0_regularizer!r}: allowed values are "
                             f"{REGULARIZERS}")


# ---------------------------------------------------------------------------------------------
# Top level


ALGORITHMS = ("lqr", "mdgps", "gmr")


@dataclass(frozen=True)
class Config:
    """A whole training run. Hashable, so it can be a static argument of ``jax.jit``.

    Attributes:
      algorithm: "lqr" (trajectory optimisation only, the paper's LQR base layer), "mdgps" (MLP
        policy) or "gmr" (generative motor reflex policy).
      iterations: GPS iterations.
      num_samples: rollouts per condition per iteration.
    """

    algorithm: str = "lqr"
    iterations: int = 10
    num_samples: int = 5
    sim: SimConfig = field(default_factory=SimConfig)
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    task: TaskConfig = field(default_factory=TaskConfig)
    cost: CostConfig = field(default_factory=CostConfig)
    init: InitLQRConfig = field(default_factory=InitLQRConfig)
    lqr: LQRConfig = field(default_factory=LQRConfig)
    step: StepConfig = field(default_factory=StepConfig)
    dynamics: DynamicsConfig = field(default_factory=DynamicsConfig)
    # Global policy (MDGPS / GMR only). The classes are defined below; lambdas defer the lookup.
    policy_prior: "PolicyPriorConfig" = field(default_factory=lambda: PolicyPriorConfig())
    sstep: "SStepConfig" = field(default_factory=lambda: SStepConfig())
    mlp: "MLPConfig" = field(default_factory=lambda: MLPConfig())
    gmr: "GMRConfig" = field(default_factory=lambda: GMRConfig())
    sample_on_policy: bool = False  # sample the global policy instead of the local controllers (itr > 0)
    # How the C-step's KL anchor π̄ is obtained from the global policy: "gmm" (the toolbox's
    # GMM-prior fit around the samples, default) or "autodiff" (exact first-order expansion of the
    # policy mean around the per-step sample mean states; gmr-method.md §3.8).
    policy_linearization: str = "gmm"

    def __post_init__(self):
        validate(self)


def validate(cfg: Config) -> None:
    """Raise ``ValueError`` naming the field and the allowed values for bad settings."""
    if cfg.algorithm not in ALGORITHMS:
        raise ValueError(f"algorithm={cfg.algorithm!r}: allowed values are {ALGORITHMS}")
    if cfg.task.scenario not in SCENARIOS:
        raise ValueError(f"task.scenario={cfg.task.scenario!r}: allowed values are {tuple(SCENARIOS)}")
    for name, value in (("iterations", cfg.iterations), ("num_samples", cfg.num_samples),
                        ("task.T", cfg.task.T), ("sim.substeps", cfg.sim.substeps)):
        if not isinstance(value, int) or value < 1:
            raise ValueError(f"{name}={value!r}: must be a positive integer")
    if cfg.num_samples < 2:
        raise ValueError(f"num_samples={cfg.num_samples}: the dynamics fit needs at least 2 samples")
    if cfg.sim.backend not in ("auto", "mjx", "mujoco"):
        raise ValueError(f"sim.backend={cfg.sim.backend!r}: allowed values are ('auto', 'mjx', 'mujoco')")
    if not (cfg.sim.control_dt > 0 and math.isfinite(cfg.sim.control_dt)):
        raise ValueError(f"sim.control_dt={cfg.sim.control_dt!r}: must be a positive number")
    if cfg.cost.state_ramp not in ("constant", "linear", "quadratic", "final_only"):
        raise ValueError(f"cost.state_ramp={cfg.cost.state_ramp!r}: allowed values are "
                         "('constant', 'linear', 'quadratic', 'final_only')")
    if cfg.policy_linearization not in ("gmm", "autodiff"):
        raise ValueError(f"policy_linearization={cfg.policy_linearization!r}: allowed values are "
                         "('gmm', 'autodiff')")
    if cfg.step.step_rule not in ("laplace", "mc"):
        raise ValueError(f"step.step_rule={cfg.step.step_rule!r}: allowed values are ('laplace', 'mc')")


def reach(scenario: str = "A", algorithm: str = "lqr", **overrides: Any) -> Config:
    """The paper's reach configuration for a scenario ("A", "B", "AB") and algorithm.

    ``overrides`` replace top-level fields (e.g. ``iterations=5``) or, with a double underscore,
    nested ones (e.g. ``task__T=20``, ``sim__backend="mjx"``).
    """
    nested: dict[str, dict[str, Any]] = {}
    top: dict[str, Any] = {}
    for key, value in overrides.items():
        if "__" in key:
            group, name = key.split("__", 1)
            nested.setdefault(group, {})[name] = value
        else:
            top[key] = value
    base = Config()
    unknown_top = sorted(set(top) - {f.name for f in dataclasses.fields(Config)})
    if unknown_top:
        raise ValueError(f"unknown configuration field(s) {unknown_top}")
    groups = {}
    for group, values in nested.items():
        if not hasattr(base, group):
            raise ValueError(f"unknown configuration group {group!r}")
        current = getattr(base, group)
        unknown = set(values) - {f.name for f in dataclasses.fields(current)}
        if unknown:
            raise ValueError(f"unknown field(s) {sorted(unknown)} in configuration group {group!r}")
        groups[group] = dataclasses.replace(current, **values)
    task = groups.pop("task", base.task)
    task = dataclasses.replace(task, scenario=scenario)
    return dataclasses.replace(base, algorithm=algorithm, task=task, **groups, **top)


def to_dict(cfg: Config) -> dict[str, Any]:
    """A JSON-serialisable dictionary of the whole configuration."""
    return dataclasses.asdict(cfg)


def from_dict(d: dict[str, Any]) -> Config:
    """The inverse of :func:`to_dict` (e.g. a run's ``config.json``); lists become tuples.

    Goes through :func:`reach`, so unknown groups or fields raise its ValueError naming them.
    """
    def tup(v):
        return tuple(tup(x) for x in v) if isinstance(v, list) else v

    d = dict(d)
    task = dict(d.pop("task", {}))
    scenario = task.pop("scenario", TaskConfig.scenario)
    algorithm = d.pop("algorithm", Config.algorithm)
    overrides = {f"task__{k}": tup(v) for k, v in task.items()}
    for name, value in d.items():
        if isinstance(value, dict):
            overrides.update({f"{name}__{k}": tup(v) for k, v in value.items()})
        else:
            overrides[name] = tup(value)
    return reach(scenario, algorithm, **overrides)


def to_json(cfg: Config) -> str:
    return json.dumps(to_dict(cfg), indent=2)


# ---------------------------------------------------------------------------------------------
# Policy and S-step (mdgps-toolbox.md §4.3, gmr-method.md §1–§3)

MLP_INITS = ("lecun_normal", "normal")
ACTIVATIONS = ("relu", "leaky_relu", "tanh", "elu", "swish")


@dataclass(frozen=True)
class SStepConfig:
    """The supervised S-step (paper: Adam, lr 1e-3, 400 epochs, batch 20, β = 2e-4).

    Attributes:
      lr: Adam learning rate (fixed).
      b1, b2, eps: Adam constants (library defaults, as the toolbox).
      epochs: passes over the data set per S-step; each epoch reshuffles.
      batch_size: rows per minibatch; the remainder of B mod batch_size is dropped per epoch.
      weight_decay: β of the L2 term β·Σθ² over all trainable weights and biases (the paper's
        form; the toolbox's weight_decay·½‖θ‖² is the same with β = weight_decay/2).
      obs_std_floor: floor of the input standard deviation in the normalisation (toolbox 1e-3).
      weight_median_floor: weights above this take part in the median of the weight rule (1e-2).
      weight_clip: weights are clipped at weight_clip × median before dividing by it (2).
      unroll: minibatch steps per iteration of the compiled loop (speed only: the same steps in
        the same order). 1 by default: on an H100, 4 saves about 8 % per step but adds about
        10 s to the compilation of a GMR iteration, more than the default run gains
        (benchmarks/RESULTS.md).
    """

    lr: float = 1e-3
    b1: float = 0.9
    b2: float = 0.999
    eps: float = 1e-8
    epochs: int = 400
    batch_size: int = 20
    weight_decay: float = 2e-4
    obs_std_floor: float = 1e-3
    weight_median_floor: float = 1e-2
    weight_clip: float = 2.0
    unroll: int = 1

    def __post_init__(self):
        for name in ("epochs", "batch_size", "unroll"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise ValueError(f"sstep.{name}={value!r}: must be a positive integer")
        for name in ("lr", "eps", "obs_std_floor", "weight_clip"):
            value = getattr(self, name)
            if not (value > 0 and math.isfinite(value)):
                raise ValueError(f"sstep.{name}={value!r}: must be a positive number")
        if not (self.weight_decay >= 0 and math.isfinite(self.weight_decay)):
            raise ValueError(f"sstep.weight_decay={self.weight_decay!r}: must be a number ≥ 0")


@dataclass(frozen=True)
class MLPConfig:
    """The MDGPS baseline policy: a fully connected network 12 → 64 → 64 → 6 (paper).

    Attributes:
      hidden: widths of the hidden layers.
      activation: hidden nonlinearity, one of ACTIVATIONS (paper: "relu").
      init: weight initialiser, "lecun_normal" (Flax default, variance 1/fan_in: keeps the
        activations of standardised inputs at unit scale) or "normal" (the toolbox's
        N(0, init_std²)); biases start at 0 in both cases.
      init_std: standard deviation of the "normal" initialiser (toolbox 0.01).
      init_var: exploration variance per action dimension before the first S-step (toolbox 0.1).
      ent_reg: entropy regulariser of the closed-form variance, var = 1/diag(A + 2·ent_reg)
        (toolbox 0).
    """

    hidden: tuple[int, ...] = (64, 64)
    activation: str = "relu"
    init: str = "lecun_normal"
    init_std: float = 0.01
    init_var: float = 0.1
    ent_reg: float = 0.0

    def __post_init__(self):
        if not (isinstance(self.hidden, tuple) and all(isinstance(h, int) and h >= 1 for h in self.hidden)):
            raise ValueError(f"mlp.hidden={self.hidden!r}: must be a tuple of positive integers")
        if self.activation not in ACTIVATIONS:
            raise ValueError(f"mlp.activation={self.activation!r}: allowed values are {ACTIVATIONS}")
        if self.init not in MLP_INITS:
            raise ValueError(f"mlp.init={self.init!r}: allowed values are {MLP_INITS}")
        if not (self.init_var > 0 and math.isfinite(self.init_var)):
            raise ValueError(f"mlp.init_var={self.init_var!r}: must be a positive number")
        if not (self.ent_reg >= 0 and math.isfinite(self.ent_reg)):
            raise ValueError(f"mlp.ent_reg={self.ent_reg!r}: must be a number ≥ 0")


GMR_HEAD_COORDINATES = ("normalized", "raw")
GMR_EXPLORATION = ("reflex", "fixed")


@dataclass(frozen=True)
class GMRConfig:
    """The Generative Motor Reflex policy (gmr-method.md §1 and §3.4–§3.8; see policies/gmr.py).

    The paper's layer sizes are lost (its Figure 3 is blank in the text); the sizes here are the
    project's decision §3.4.

    Attributes:
      latent: size of the latent state z.
      encoder_squash: c > 0 feeds the encoder c·tanh(x̃/c) instead of the standardised state x̃
        (and makes that the reconstruction target); 0 feeds x̃ itself. The reflex still acts on
        the whole state, u = Ψ_K(z)·x + Ψ_k(z); only the choice of reflex saturates, so a state
        far outside the training data gets a reflex generated from a latent the networks were
        trained on, instead of one extrapolated from z far outside it.
      encoder_hidden: hidden widths of h_enc: x̃ [dX] → … → (μ_z, log σ²_z) [2·latent].
      decoder_hidden: hidden widths of h_dec: z → … → x̂ [dX] (the normalised state).
      translation_hidden: hidden widths of h_trans: z → … → (Ψ_K [dU·dX], Ψ_k [dU], the
        dU(dU+1)/2 entries of the Cholesky factor of Ψ_Σ).
      negative_slope: slope of the leaky ReLU for negative inputs (all hidden layers).
      alpha: α, the weight of the latent term KL(q(z|x) ‖ N(0, I)). The paper hand-tunes it; 1.0
        is the plain VAE objective (with the paper's unhalved squared reconstruction error it is
        the ELBO of a Gaussian decoder of variance ½). To be chosen by a documented sweep.
      head_coordinates: the state coordinates in which h_trans emits the gain and offset.
        "normalized" (default): the head emits (G̃, g̃) for u = G̃ x̃ + g̃ with the standardised
        state x̃ = x·scale + bias, and the reflex in raw coordinates is Ψ_K = G̃·diag(scale),
        Ψ_k = g̃ + G̃·bias — the same function class, but every gain column is in action units
        per standard deviation of its state entry and the offset is of the size of an action
        (the raw offset k_p = u_p − K_p x cancels a large K_p x). "raw": the head emits Ψ_K, Ψ_k
        directly (the authors' code).
      exploration: the covariance used for on-policy sampling. "reflex" (default): the generated
        Ψ_Σ(x) (the paper's motor reflex); "fixed": diag(var), the closed-form variance of the
        S-step (what the authors' code used).
      init_var: exploration variance per action entry before the first S-step (``params.var``,
        toolbox 0.1), and the centre of the Ψ_Σ parameterisation: a zero head output gives
        Ψ_Σ = init_var·I.
      cov_std_range: R, the factor by which each standard deviation σ_i of Ψ_Σ may leave
        sqrt(init_var): σ_i ∈ sqrt(init_var)·[1/R, R] through a tanh-bounded log (a floor and a
        ceiling; the default allows variances in [1e-5, 1e3] around init_var 0.1). Bounded
        entries keep Ψ_Σ positive definite *in floating point* for any input.
      cov_offdiag_bound: c, the bound of the strictly lower entries of the unit-triangular V
        whose row-normalised form is the correlation factor (V_ij = c·tanh(r_ij/c)); a single
        entry allows a correlation of up to c/√(1+c²) (0.95 for c = 3). A larger c allows
        stronger correlations at the price of a worse worst-case conditioning.
      ent_reg: entropy regulariser of the closed-form variance, var = 1/diag(A + 2·ent_reg)
        (toolbox 0; shared with the MLP).
    """

    latent: int = 4
    encoder_squash: float = 1.0
    encoder_hidden: tuple[int, ...] = (64, 64)
    decoder_hidden: tuple[int, ...] = (64, 64)
    translation_hidden: tuple[int, ...] = (64, 64)
    negative_slope: float = 0.2
    alpha: float = 1.0
    head_coordinates: str = "normalized"
    exploration: str = "reflex"
    init_var: float = 0.1
    cov_std_range: float = 1e2
    cov_offdiag_bound: float = 3.0
    ent_reg: float = 0.0

    def __post_init__(self):
        if not (isinstance(self.latent, int) and self.latent >= 1):
            raise ValueError(f"gmr.latent={self.latent!r}: must be a positive integer")
        for name in ("encoder_hidden", "decoder_hidden", "translation_hidden"):
            value = getattr(self, name)
            if not (isinstance(value, tuple) and all(isinstance(h, int) and h >= 1 for h in value)):
                raise ValueError(f"gmr.{name}={value!r}: must be a tuple of positive integers")
        if not (self.encoder_squash >= 0 and math.isfinite(self.encoder_squash)):
            raise ValueError(f"gmr.encoder_squash={self.encoder_squash!r}: must be a number ≥ 0")
        if not (0 <= self.negative_slope < 1):
            raise ValueError(f"gmr.negative_slope={self.negative_slope!r}: must be in [0, 1)")
        if not (self.alpha >= 0 and math.isfinite(self.alpha)):
            raise ValueError(f"gmr.alpha={self.alpha!r}: must be a number ≥ 0")
        if self.head_coordinates not in GMR_HEAD_COORDINATES:
            raise ValueError(f"gmr.head_coordinates={self.head_coordinates!r}: allowed values are "
                             f"{GMR_HEAD_COORDINATES}")
        if self.exploration not in GMR_EXPLORATION:
            raise ValueError(f"gmr.exploration={self.exploration!r}: allowed values are {GMR_EXPLORATION}")
        if not (self.init_var > 0 and math.isfinite(self.init_var)):
            raise ValueError(f"gmr.init_var={self.init_var!r}: must be a positive number")
        if not (self.cov_std_range > 1 and math.isfinite(self.cov_std_range)):
            raise ValueError(f"gmr.cov_std_range={self.cov_std_range!r}: must be a number > 1")
        if not (self.cov_offdiag_bound > 0 and math.isfinite(self.cov_offdiag_bound)):
            raise ValueError(f"gmr.cov_offdiag_bound={self.cov_offdiag_bound!r}: must be a positive number")
        if not (self.ent_reg >= 0 and math.isfinite(self.ent_reg)):
            raise ValueError(f"gmr.ent_reg={self.ent_reg!r}: must be a number ≥ 0")
