"""Configuration: frozen, hashable dataclasses, one per stage, validated where they are defined.

Every stage function takes the dataclass it needs (static under ``jit``). The defaults here are
the toolbox's and the paper's MDGPS settings (``shared/reference/mdgps-toolbox.md``,
``shared/reference/gmr-method.md``); what belongs to a task — its scene, cost, conditions and
the arm's constants — lives in the task's module under ``gmr_jax/tasks/``, which builds a whole
:class:`Config` with :func:`make`. Each dataclass checks its own fields in ``__post_init__`` with
the helpers below, so a bad value fails where it is made, with one line naming the field and
what it must be.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from typing import Any

# ---------------------------------------------------------------------------------------------
# Checks (one helper per kind; each raises ValueError naming the field and the allowed values)


def check_positive_int(name: str, value) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{name}={value!r}: must be a positive integer")


def check_positive(name: str, value) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (value > 0 and math.isfinite(value)):
        raise ValueError(f"{name}={value!r}: must be a positive number")


def check_nonnegative(name: str, value) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (value >= 0 and math.isfinite(value)):
        raise ValueError(f"{name}={value!r}: must be a number ≥ 0")


def check_bool(name: str, value) -> None:
    if not isinstance(value, bool):
        raise ValueError(f"{name}={value!r}: must be True or False")


def check_choice(name: str, value, allowed) -> None:
    if value not in allowed:
        raise ValueError(f"{name}={value!r}: allowed values are {tuple(allowed)}")


def check_int_tuple(name: str, value) -> None:
    if not (isinstance(value, tuple) and all(isinstance(h, int) and not isinstance(h, bool) and h >= 1
                                             for h in value)):
        raise ValueError(f"{name}={value!r}: must be a tuple of positive integers")


def check_number_tuple(name: str, value) -> None:
    if not (isinstance(value, tuple) and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                             and math.isfinite(v) for v in value)):
        raise ValueError(f"{name}={value!r}: must be a tuple of finite numbers")


# ---------------------------------------------------------------------------------------------
# Simulation

BACKENDS = ("auto", "mjx", "mujoco")


@dataclass(frozen=True)
class SimConfig:
    """The simulated Jaco 2 plant.

    Attributes:
      scene: MJCF scene name in ``jaco_mjcf/`` (``"reach"`` → ``jaco_mjcf/reach.xml``, the arm
        alone) or a path to an MJCF file.
      control_dt: duration of one control step (s); the paper runs at 20 Hz.
      substeps: physics steps per control step; the physics timestep is control_dt / substeps.
      gravity_compensation: the plant adds the gravity torques (as the Jaco's torque mode does).
      clip_torques: saturate commanded torques at the actuator peak torques (ctrlrange).
      backend: ``"mjx"`` (MJX, impl='jax'), ``"mujoco"`` (C MuJoCo on the host through a
        host callback, ``sim._host_callback``) or ``"auto"`` (mjx where JAX has a GPU, else mujoco).
      float32: a diagnostic beside ``Config.float32_stages``: in a float64 run, MJX steps the
        plant in float32 (states and torques rounded to float32 at each control step, the result
        widened back), everything else stays in float64. MJX only.
    """

    scene: str = "reach"
    control_dt: float = 0.05
    substeps: int = 10
    gravity_compensation: bool = True
    clip_torques: bool = True
    backend: str = "auto"
    float32: bool = False

    def __post_init__(self):
        if not (isinstance(self.scene, str) and self.scene):
            raise ValueError(f"sim.scene={self.scene!r}: must be a scene name or an MJCF path")
        check_positive("sim.control_dt", self.control_dt)
        check_positive_int("sim.substeps", self.substeps)
        check_bool("sim.gravity_compensation", self.gravity_compensation)
        check_bool("sim.clip_torques", self.clip_torques)
        check_choice("sim.backend", self.backend, BACKENDS)
        check_bool("sim.float32", self.float32)

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

    def __post_init__(self):
        check_nonnegative("noise.sigma", self.sigma)
        check_positive("noise.truncate", self.truncate)


# ---------------------------------------------------------------------------------------------
# Task


@dataclass(frozen=True)
class TaskConfig:
    """Which task and scenario, the horizon and the success thresholds.

    The task's conditions, target, cost and robustness states are defined by its module
    ``gmr_jax/tasks/<name>.py``; see :mod:`gmr_jax.tasks`.

    Attributes:
      name: the task ("reach", "block_in_hole").
      scenario: the task's scenario: which of its conditions are trained (e.g. reach "A", "AB").
      T: horizon in control steps (80 = 4 s at 20 Hz).
      success_threshold: headline final-state MSE threshold (the paper's table).
      success_threshold_loose: the paper's text threshold.
      wrap_angles: measure the continuous joints' angle errors (the task's ``continuous_joints``)
        the shortest way round, wrapped to [−π, π), in the success test and the state cost; False
        (the authors' toolbox): raw angle differences.
      random_angles_around_target: represent the robustness test's random states' continuous
        joints by the angles within [−π, π) of the target's (the same arm configurations, each
        angle moved by whole turns); False: as the task draws them (reach: the authors' reset
        distribution, [−π, π]).
    """

    name: str = "reach"
    scenario: str = "A"
    T: int = 80
    success_threshold: float = 0.01
    success_threshold_loose: float = 0.1
    wrap_angles: bool = False
    random_angles_around_target: bool = False

    def __post_init__(self):
        from gmr_jax import tasks  # the registry imports this module

        task = tasks.get(self.name)
        check_choice("task.scenario", self.scenario, task.scenarios)
        check_positive_int("task.T", self.T)
        check_positive("task.success_threshold", self.success_threshold)
        check_positive("task.success_threshold_loose", self.success_threshold_loose)
        check_bool("task.wrap_angles", self.wrap_angles)
        check_bool("task.random_angles_around_target", self.random_angles_around_target)

    @property
    def num_conditions(self) -> int:
        from gmr_jax import tasks

        return len(tasks.get(self.name).scenarios[self.scenario])


# ---------------------------------------------------------------------------------------------
# Trajectory optimisation


@dataclass(frozen=True)
class InitLQRConfig:
    """``init_lqr`` settings (mdgps-toolbox.md §4.1; toolbox defaults, a task sets its arm's).

    Attributes:
      init_var, stiffness, stiffness_vel, final_weight: the toolbox's init_lqr settings.
      init_acc: guessed constant acceleration per joint; empty: 0 for every joint.
      init_gains: guessed acceleration per unit torque per joint; empty: 1 for every joint (the
        tasks on the Jaco set 1/[7.09, 2.3, 1.5, 1.2, 1.8, 0.1], ``tasks/jaco.py``).
    """

    init_var: float = 1.0
    stiffness: float = 1.0
    stiffness_vel: float = 0.25
    final_weight: float = 50.0
    init_acc: tuple[float, ...] = ()
    init_gains: tuple[float, ...] = ()

    def __post_init__(self):
        check_positive("init.init_var", self.init_var)
        check_nonnegative("init.stiffness", self.stiffness)
        check_nonnegative("init.stiffness_vel", self.stiffness_vel)
        check_positive("init.final_weight", self.final_weight)
        check_number_tuple("init.init_acc", self.init_acc)
        check_number_tuple("init.init_gains", self.init_gains)


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

    def __post_init__(self):
        for name in ("del0", "min_eta", "max_eta", "tolerance"):
            check_positive(f"lqr.{name}", getattr(self, name))
        check_positive_int("lqr.max_iterations", self.max_iterations)
        if self.min_eta >= self.max_eta:
            raise ValueError(f"lqr.min_eta={self.min_eta!r} must be below lqr.max_eta={self.max_eta!r}")


STEP_RULES = ("laplace", "mc")


@dataclass(frozen=True)
class StepConfig:
    """KL step and its adaptation (mdgps-toolbox.md §1.1, §1.3). ε = kl_step · step_mult · T."""

    kl_step: float = 0.2
    min_step_mult: float = 0.01
    max_step_mult: float = 10.0
    step_rule: str = "laplace"

    def __post_init__(self):
        for name in ("kl_step", "min_step_mult", "max_step_mult"):
            check_positive(f"step.{name}", getattr(self, name))
        check_choice("step.step_rule", self.step_rule, STEP_RULES)
        if self.min_step_mult > self.max_step_mult:
            raise ValueError(f"step.min_step_mult={self.min_step_mult!r} must not exceed "
                             f"step.max_step_mult={self.max_step_mult!r}")


# How a regularisation value enters a block of a joint covariance (prior.regularizer_matrix):
# "ridge" adds value·I (what the toolbox meant, the default), "toolbox" adds value to every entry
# of the block (value·11ᵀ, the toolbox's numpy broadcast, rank one), for exact toolbox numerics.
REGULARIZERS = ("ridge", "toolbox")


@dataclass(frozen=True)
class DynamicsConfig:
    """Dynamics fit with the GMM prior (mdgps-toolbox.md §3; the authors' Jaco values, gmr-method.md §2).

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
        check_choice("dynamics.regularizer", self.regularizer, REGULARIZERS)
        for name in ("regularization", "strength", "initial_state_var"):
            check_nonnegative(f"dynamics.{name}", getattr(self, name))
        for name in ("max_clusters", "min_samples_per_cluster", "max_samples", "em_iterations"):
            check_positive_int(f"dynamics.{name}", getattr(self, name))


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
        check_choice("policy_prior.t0_regularizer", self.t0_regularizer, REGULARIZERS)
        for name in ("min_samples_per_cluster", "max_clusters", "max_samples", "em_iterations"):
            check_positive_int(f"policy_prior.{name}", getattr(self, name))
        check_nonnegative("policy_prior.strength", self.strength)
        check_nonnegative("policy_prior.t0_regularization", self.t0_regularization)
        check_choice("policy_prior.mode", self.mode, POLICY_PRIOR_MODES)


# ---------------------------------------------------------------------------------------------
# Policy and S-step (mdgps-toolbox.md §4.3, gmr-method.md §1–§3)


SSTEP_IMPLS = ("auto", "cuda", "kernel", "packed", "reference")
SSTEP_ADAM_ENTRIES = ("all", "trained")
SSTEP_STATISTICS = ("auto", "epoch", "step")
SSTEP_STATISTICS_EPOCHS = ("last", "all")


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
      impl: the S-step's form (``gmr_jax.sstep``, equal to round-off): "cuda" (GMR: all Adam
        steps in one hand-written CUDA kernel, one thread block per seed, or a thread-block
        cluster per seed where the seeds all fit on the GPU at once; float32 on an NVIDIA
        GPU, built with nvcc on first use; other policies: "packed"), "kernel" (GMR: all Adam
        steps in one Pallas kernel; other policies: "packed"), "packed" (one packed weight
        vector and data matrix, a few fused operations per minibatch step: fast on a GPU),
        "reference" (per-layer Flax networks and optax: fast on a CPU), or "auto" (packed on an
        accelerator, reference on a CPU).
      unroll: minibatch steps per iteration of the compiled loop (speed only: the same steps in
        the same order). 1 by default: on an H100, 4 saves about 8 % per step but adds about
        10 s to the compilation of a GMR iteration, more than the default run gains
        (benchmarks/RESULTS.md).
      adam_entries: which entries of the packed form's weight vector Adam carries (speed only:
        the same arithmetic on every weight): "all" (the layout's zero padding included, one
        fused update), or "trained" (the real weights only, the packed vector formed from them by
        a gather each step: about a third of the memory traffic of Adam's update). On an H100
        "trained" makes the S-step 21 % (GMR) and 10 % (MLP) faster with 256 seeds side by side
        and 2–13 % slower with one seed (benchmarks/RESULTS.md), so "all" is the default and
        runs of many seeds should set "trained" (the CLI does from 256 seeds per GPU).
      statistics: when the packed form computes its per-step statistics (the loss and its terms,
        which the gradient does not need; their epoch means are the S-step's metrics): "epoch"
        keeps an epoch's weights and evaluates all its steps at once after the epoch, "step"
        inside every minibatch step, "auto" per epoch in the runner's programs of up to
        ``sharding.EPOCH_STATISTICS_MAX_SEEDS`` seeds per GPU and per step elsewhere. The same
        values up to the order of their sums, and the same weights. Per epoch a GMR step of one
        seed per GPU launches fewer kernels; with many seeds per GPU the kept weights cost more
        than that saves (benchmarks/RESULTS.md, twenty-second session).
      statistics_epochs: the epochs whose statistics the S-step returns: "last" (the default:
        training reads only the last epoch's loss; the S-step's loss, data loss and aux entries
        are then [1]) or "all" (the loss curve, [epochs] entries, e.g. to watch a fit converge). Where
        the packed form evaluates the statistics per epoch (``statistics``), "last" computes
        none in the steps: each step keeps its weights in a buffer of one epoch, evaluated once
        after the loop (on an H100 one seed's GMR step 6–8 % faster; with many seeds per GPU,
        where the statistics stay in every step, that buffer would cost more than it saves).
        The same weights and last-epoch values either way up to round-off (the order of their
        sums; bit-identical on an H100, benchmarks/RESULTS.md, twenty-fourth session).
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
    impl: str = "auto"
    unroll: int = 1
    adam_entries: str = "all"
    statistics: str = "auto"
    statistics_epochs: str = "last"

    def __post_init__(self):
        check_choice("sstep.impl", self.impl, SSTEP_IMPLS)
        check_choice("sstep.adam_entries", self.adam_entries, SSTEP_ADAM_ENTRIES)
        check_choice("sstep.statistics", self.statistics, SSTEP_STATISTICS)
        check_choice("sstep.statistics_epochs", self.statistics_epochs, SSTEP_STATISTICS_EPOCHS)
        for name in ("epochs", "batch_size", "unroll"):
            check_positive_int(f"sstep.{name}", getattr(self, name))
        for name in ("lr", "eps", "obs_std_floor", "weight_clip"):
            check_positive(f"sstep.{name}", getattr(self, name))
        check_nonnegative("sstep.weight_decay", self.weight_decay)
        check_nonnegative("sstep.weight_median_floor", self.weight_median_floor)
        for name in ("b1", "b2"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and 0 <= value < 1):
                raise ValueError(f"sstep.{name}={value!r}: must be in [0, 1)")


MLP_INITS = ("lecun_normal", "normal")
ACTIVATIONS = ("relu", "leaky_relu", "tanh", "elu", "swish")


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
      input_squash: c > 0 feeds the network c·tanh(x̃/c) instead of the standardised state x̃
        (GMR's ``encoder_squash`` on the MLP, for the ablation "does the bound alone make the
        plain MLP robust?"); 0, the default, is the paper's network.
    """

    hidden: tuple[int, ...] = (64, 64)
    activation: str = "relu"
    init: str = "lecun_normal"
    init_std: float = 0.01
    init_var: float = 0.1
    ent_reg: float = 0.0
    input_squash: float = 0.0

    def __post_init__(self):
        check_int_tuple("mlp.hidden", self.hidden)
        check_nonnegative("mlp.input_squash", self.input_squash)
        check_choice("mlp.activation", self.activation, ACTIVATIONS)
        check_choice("mlp.init", self.init, MLP_INITS)
        check_positive("mlp.init_std", self.init_std)
        check_positive("mlp.init_var", self.init_var)
        check_nonnegative("mlp.ent_reg", self.ent_reg)


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
        check_positive_int("gmr.latent", self.latent)
        for name in ("encoder_hidden", "decoder_hidden", "translation_hidden"):
            check_int_tuple(f"gmr.{name}", getattr(self, name))
        check_nonnegative("gmr.encoder_squash", self.encoder_squash)
        if not (isinstance(self.negative_slope, (int, float)) and 0 <= self.negative_slope < 1):
            raise ValueError(f"gmr.negative_slope={self.negative_slope!r}: must be in [0, 1)")
        check_nonnegative("gmr.alpha", self.alpha)
        check_choice("gmr.head_coordinates", self.head_coordinates, GMR_HEAD_COORDINATES)
        check_choice("gmr.exploration", self.exploration, GMR_EXPLORATION)
        check_positive("gmr.init_var", self.init_var)
        if not (isinstance(self.cov_std_range, (int, float)) and self.cov_std_range > 1
                and math.isfinite(self.cov_std_range)):
            raise ValueError(f"gmr.cov_std_range={self.cov_std_range!r}: must be a number > 1")
        check_positive("gmr.cov_offdiag_bound", self.cov_offdiag_bound)
        check_nonnegative("gmr.ent_reg", self.ent_reg)


# ---------------------------------------------------------------------------------------------
# Top level

POLICY_LINEARIZATIONS = ("gmm", "autodiff")

FLOAT32_STAGES = ("cost", "dynamics", "policy_linearization", "step_size", "cstep", "sstep")
"""Stages of ``mdgps.update`` that ``Config.float32_stages`` can run in float32 inside a float64
run: the cost expansion, the dynamics fit (prior and per-step fit), the linearisation of the
global policy (its prior and fit), the step-size rule, the C-step (η search) and the S-steps
(the catch-up S-step too)."""


@dataclass(frozen=True)
class Config:
    """A whole training run. Hashable, so it can be a static argument of ``jax.jit``.

    Build one with :func:`make` (or :func:`reach`): it starts from the task's own stage settings
    (scene, cost, the arm's initial controller) and applies overrides.

    Attributes:
      task: which task and scenario (:class:`TaskConfig`).
      cost: the task's cost settings, a frozen dataclass defined by the task's module.
      algorithm: "lqr" (trajectory optimisation only, the paper's LQR base layer), "mdgps" (MLP
        policy) or "gmr" (generative motor reflex policy); ``gmr_jax.policies.ALGORITHMS``.
      iterations: GPS iterations.
      num_samples: rollouts per condition per iteration (≥ 2: the dynamics fit needs two).
      sample_on_policy: sample the global policy instead of the local controllers (after the
        first iteration).
      policy_linearization: how the C-step's KL anchor π̄ is obtained from the global policy:
        "gmm" (the toolbox's GMM-prior fit around the samples, default) or "autodiff" (exact
        first-order expansion of the policy mean around the per-step sample mean states;
        gmr-method.md §3.8).
      float32_stages: a diagnostic: these stages (names in ``FLOAT32_STAGES``) of a float64 run
        compute in float32 (their array inputs are rounded to float32, their outputs widened
        back), to find which stage's float32 arithmetic changes a result that differs between
        the precisions. Needs a float64 run (``jax_enable_x64``); empty (every stage in the
        run's precision) by default.
    """

    task: TaskConfig
    cost: Any
    algorithm: str = "lqr"
    iterations: int = 10
    num_samples: int = 5
    sim: SimConfig = field(default_factory=SimConfig)
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    init: InitLQRConfig = field(default_factory=InitLQRConfig)
    lqr: LQRConfig = field(default_factory=LQRConfig)
    step: StepConfig = field(default_factory=StepConfig)
    dynamics: DynamicsConfig = field(default_factory=DynamicsConfig)
    policy_prior: PolicyPriorConfig = field(default_factory=PolicyPriorConfig)
    sstep: SStepConfig = field(default_factory=SStepConfig)
    mlp: MLPConfig = field(default_factory=MLPConfig)
    gmr: GMRConfig = field(default_factory=GMRConfig)
    sample_on_policy: bool = False
    policy_linearization: str = "gmm"
    float32_stages: tuple[str, ...] = ()

    def __post_init__(self):
        from gmr_jax import policies, tasks  # both registries import this module

        check_choice("algorithm", self.algorithm, policies.ALGORITHMS)
        check_positive_int("iterations", self.iterations)
        check_positive_int("num_samples", self.num_samples)
        if self.num_samples < 2:
            raise ValueError(f"num_samples={self.num_samples}: the dynamics fit needs at least 2 samples")
        check_choice("policy_linearization", self.policy_linearization, POLICY_LINEARIZATIONS)
        if not isinstance(self.float32_stages, tuple):
            raise ValueError(f"float32_stages={self.float32_stages!r}: must be a tuple of stage names "
                             f"from {FLOAT32_STAGES}, e.g. --set \"float32_stages=('dynamics',)\"")
        for stage in self.float32_stages:
            check_choice("float32_stages entry", stage, FLOAT32_STAGES)
        if len(set(self.float32_stages)) != len(self.float32_stages):
            raise ValueError(f"float32_stages={self.float32_stages!r}: a stage is named twice")
        cost_type = tasks.get(self.task.name).cost_config
        if not isinstance(self.cost, cost_type):
            raise ValueError(f"cost={type(self.cost).__name__}: task {self.task.name!r} needs a "
                             f"{cost_type.__module__}.{cost_type.__name__}")


def override(cfg: Config, **overrides: Any) -> Config:
    """``cfg`` with fields replaced: top-level names (``iterations=5``) or, with a double
    underscore, nested ones (``task__T=20``, ``sim__backend="mjx"``, ``cost__state_l2=2.0``).

    Raises:
      ValueError: an unknown group or field (named), or a value its dataclass rejects.
    """
    nested: dict[str, dict[str, Any]] = {}
    top: dict[str, Any] = {}
    for key, value in overrides.items():
        if "__" in key:
            group, name = key.split("__", 1)
            nested.setdefault(group, {})[name] = value
        else:
            top[key] = value
    top_fields = {f.name for f in dataclasses.fields(Config)}
    unknown_top = sorted(set(top) - top_fields)
    if unknown_top:
        raise ValueError(f"unknown configuration field(s) {unknown_top}")
    groups = {}
    for group, values in nested.items():
        current = getattr(cfg, group, None)
        if group not in top_fields or not dataclasses.is_dataclass(current):
            raise ValueError(f"unknown configuration group {group!r}")
        unknown = set(values) - {f.name for f in dataclasses.fields(current)}
        if unknown:
            raise ValueError(f"unknown field(s) {sorted(unknown)} in configuration group {group!r}")
        groups[group] = dataclasses.replace(current, **values)
    return dataclasses.replace(cfg, **groups, **top)


def make(task: str = "reach", scenario: str | None = None, algorithm: str = "lqr",
         **overrides: Any) -> Config:
    """The configuration of ``task`` (its stage settings) for a scenario and an algorithm.

    Args:
      task: a registered task name (``gmr_jax.tasks.TASKS``).
      scenario: one of the task's scenarios (default: its first).
      algorithm: "lqr", "mdgps" or "gmr".
      overrides: see :func:`override`.
    """
    from gmr_jax import tasks

    t = tasks.get(task)
    base = t.default_config(t.default_scenarios[0] if scenario is None else scenario)
    return override(base, algorithm=algorithm, **overrides)


def reach(scenario: str = "A", algorithm: str = "lqr", **overrides: Any) -> Config:
    """The paper's reach configuration for a scenario ("A", "B", "AB") and algorithm."""
    return make("reach", scenario, algorithm, **overrides)


def to_dict(cfg: Config) -> dict[str, Any]:
    """A JSON-serialisable dictionary of the whole configuration."""
    return dataclasses.asdict(cfg)


def from_dict(d: dict[str, Any]) -> Config:
    """The inverse of :func:`to_dict` (e.g. a run's ``config.json``); lists become tuples.

    Goes through :func:`make`, so unknown groups or fields raise its ValueError naming them.
    """
    def tup(v):
        return tuple(tup(x) for x in v) if isinstance(v, list) else v

    d = dict(d)
    task = dict(d.pop("task", {}))
    name = task.pop("name", TaskConfig.name)
    scenario = task.pop("scenario", None)
    algorithm = d.pop("algorithm", Config.algorithm)
    overrides = {f"task__{k}": tup(v) for k, v in task.items()}
    for group, value in d.items():
        if isinstance(value, dict):
            overrides.update({f"{group}__{k}": tup(v) for k, v in value.items()})
        else:
            overrides[group] = tup(value)
    return make(name, scenario, algorithm, **overrides)


def to_json(cfg: Config) -> str:
    return json.dumps(to_dict(cfg), indent=2)
