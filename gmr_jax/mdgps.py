"""The GPS iteration: one pure, jittable function of named stages, and a whole run as a scan.

``iteration`` reads as the data flow of DESIGN.md:

    sample → cost expansion → dynamics fit → KL anchor (policy linearisation) → step size
           → C-step → S-step

Three algorithms share it (``cfg.algorithm``, registry ``gmr_jax.policies.ALGORITHMS``):

* ``"lqr"`` — trajectory optimisation only (the toolbox's AlgorithmTrajOpt, the paper's "LQR
  base layer"): the KL anchor of the C-step is the previous local controller; no S-step.
* ``"mdgps"`` / ``"gmr"`` — mirror-descent GPS (mdgps-toolbox.md §0) with the MLP or the GMR
  policy: the anchor is the global policy linearised around the samples, and an S-step fits the
  policy to the new controllers.

The first iteration differs in one way: MDGPS first fits the policy to the initial controllers
(the toolbox's catch-up S-step, §0.4) and the step size is not adapted. ``first`` is a boolean
scalar and both differences are ``lax.cond``/``where`` on it, so one compiled program serves
every iteration.

The iteration is a chain of parts (``ITERATION_PARTS``, each a function of a carry dict) that
``iteration`` traces as one program and that the runner may compile as programs of their own,
in parallel (``part_program``, ``runner.ITERATION_PARTS``).

``train`` runs the same iterations with the rollouts rearranged (``rollout_stage``): each scan
step rolls out this iteration's samples together with the learning curve of the previous
iteration's results, so the whole run holds one instance of the simulator's rollout, which is
what most of its compilation costs with MJX.

Axis conventions: condition M, sample N, time T. Every array in the state has a leading M axis
except the iteration counter and the policy parameters (shared by the conditions).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from gmr_jax import cost as cost_lib
from gmr_jax import dynamics as dyn_lib
from gmr_jax import evaluate, linearize, lqr, policies, sharding, step_size, tasks
from gmr_jax import noise as noise_lib
from gmr_jax import sim as sim_lib
from gmr_jax import sstep as sstep_lib
from gmr_jax.config import Config
from gmr_jax.dynamics import DynamicsPrior
from gmr_jax.linearize import PolicyPrior
from gmr_jax.step_size import LocalModel
from gmr_jax.types import Dynamics, LinearGaussianPolicy, Marginals, QuadraticCost, Trajectories

Array = jax.Array


class PolicyState(NamedTuple):
    """The global policy of MDGPS / GMR and the prior of its linearisation.

    Attributes:
      params: PolicyParams (shared by the conditions).
      prior: PolicyPrior [M], each condition's store of states and GMM over [x, π(x)].
    """

    params: policies.PolicyParams
    prior: PolicyPrior


class TrainState(NamedTuple):
    """Everything an iteration carries to the next (a pytree).

    Attributes:
      iteration: [] int32, iterations completed.
      traj: LinearGaussianPolicy [M, T, ...], the current local controllers (sampled next).
      eta: [M] dual variable of each condition's KL constraint (warm start of the η search).
      step_mult: [M] KL step multiplier.
      dyn_prior: DynamicsPrior [M], each condition's ring buffer of trajectories and GMM.
      prev: LocalModel [M], the previous iteration's anchor, dynamics, cost and sample cost (the
        step-size rule compares against it).
      policy: PolicyState of MDGPS / GMR; None for trajectory optimisation.
    """

    iteration: Array
    traj: LinearGaussianPolicy
    eta: Array
    step_mult: Array
    dyn_prior: DynamicsPrior
    prev: LocalModel
    policy: PolicyState | None = None


MATMUL_PRECISION = "highest"
"""``jax.default_matmul_precision`` of every stage (``init``, ``iteration``): full float32 matrix
products. The GPU's float32 default (TF32 inputs, ~1e-3 relative error) breaks the Cholesky
factorisations of the dynamics fit and the LQR; code that times a stage on its own traces it
under the same setting."""


def _zeros_like_tree(tree):
    return jax.tree_util.tree_map(jnp.zeros_like, tree)


def _broadcast_conditions(tree, M: int):
    return jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (M,) + jnp.shape(a)), tree)


def init(cfg: Config, key: Array) -> TrainState:
    """The initial training state: ``init_lqr`` controllers around each condition's x0 and, for
    MDGPS/GMR, freshly initialised policy parameters.

    Args:
      cfg: the run's configuration (static).
      key: PRNG key (initialises the policy network).
    Returns:
      TrainState with M = number of conditions.
    """
    s = sim_lib.make_sim(cfg.sim)
    T, dX, dU = cfg.task.T, s.dX, s.dU
    x0 = tasks.initial_states(cfg.task)
    M = x0.shape[0]
    dtype = x0.dtype
    with jax.default_matmul_precision(MATMUL_PRECISION):
        traj = jax.vmap(lambda x: lqr.init_lqr(x, T, dU, cfg.sim.control_dt, cfg.init))(x0)
    prior = _broadcast_conditions(dyn_lib.dynamics_prior_empty(T, dX, dU, cfg.dynamics, dtype), M)
    dyn0 = Dynamics(
        Fm=jnp.zeros((M, T, dX, dX + dU), dtype), fv=jnp.zeros((M, T, dX), dtype),
        dyn_covar=jnp.zeros((M, T, dX, dX), dtype), x0mu=jnp.zeros((M, dX), dtype),
        x0sigma=jnp.zeros((M, dX, dX), dtype))
    cost0 = QuadraticCost(Cm=jnp.zeros((M, T, dX + dU, dX + dU), dtype),
                          cv=jnp.zeros((M, T, dX + dU), dtype), cc=jnp.zeros((M, T), dtype))
    prev = LocalModel(anchor=_zeros_like_tree(traj), dyn=dyn0, cost=cost0,
                      sample_cost=jnp.zeros((M,), dtype))
    policy = policies.for_config(cfg)
    policy_state = None
    if policy is not None:
        pol_prior = linearize.policy_prior_empty(T, dX, dU, cfg.policy_prior, dtype)
        policy_state = PolicyState(params=policy.init(key, dX, dU, dtype),
                                   prior=_broadcast_conditions(pol_prior, M))
    return TrainState(iteration=jnp.zeros((), jnp.int32), traj=traj, eta=jnp.ones((M,), dtype),
                      step_mult=jnp.ones((M,), dtype), dyn_prior=prior, prev=prev,
                      policy=policy_state)


# ---------------------------------------------------------------------------------------------
# Stages


def in_float32(name: str, fn):
    """``fn`` computing in float32 inside a float64 run (``Config.float32_stages``).

    Its floating array arguments are rounded to float32 and its floating outputs widened back to
    float64, so the stage runs its own arithmetic in float32 and everything around it stays in
    float64. Raises ValueError when an argument is not float64 (the diagnostic needs a float64
    run) and TypeError when an output is not float32 (the stage would have mixed in float64
    arithmetic, so the diagnostic would not measure what it claims).
    """
    def floating(a):
        return isinstance(a, jax.Array) and jnp.issubdtype(a.dtype, jnp.floating)

    def wrapped(*args):
        leaves = [a for a in jax.tree_util.tree_leaves(args) if floating(a)]
        if any(a.dtype != jnp.float64 for a in leaves):
            raise ValueError(f"float32_stages ({name!r}) needs a float64 run: use --precision float64")
        narrow = jax.tree_util.tree_map(lambda a: a.astype(jnp.float32) if floating(a) else a, args)
        out = fn(*narrow)
        wide = [a.dtype for a in jax.tree_util.tree_leaves(out) if floating(a) and a.dtype != jnp.float32]
        if wide:
            raise TypeError(f"stage {name!r} returned {wide[0]} from float32 inputs: it mixes in "
                            "float64 arithmetic, so float32_stages cannot run it in float32")
        return jax.tree_util.tree_map(lambda a: a.astype(jnp.float64) if floating(a) else a, out)

    return wrapped


def _stage(cfg: Config, name: str, fn):
    """``fn``, or ``in_float32(name, fn)`` when ``cfg.float32_stages`` names it."""
    return in_float32(name, fn) if name in cfg.float32_stages else fn


def sample_noise(cfg: Config, key: Array, M: int, num_samples: int, dtype) -> Array:
    """The toolbox's smoothed exploration noise of N = num_samples rollouts per condition,
    [M, N, T, dU] in ``dtype``."""
    dU = sim_lib.make_sim(cfg.sim).dU
    keys = jax.random.split(key, (M, num_samples))
    eps = jax.vmap(jax.vmap(lambda k: noise_lib.smooth_noise(k, cfg.task.T, dU, cfg.noise)))(keys)
    return eps.astype(dtype)


def sample(cfg: Config, controller, x0: Array, key: Array, num_samples: int) -> Trajectories:
    """Noisy rollouts with the toolbox's smoothed exploration noise.

    Args:
      controller: a LinearGaussianPolicy with a leading condition axis M, or a callable
        ``(t, x, eps_t) -> u`` shared by all conditions.
      x0: [M, dX] initial states.
      key: PRNG key.
      num_samples: N rollouts per condition.
    Returns:
      Trajectories with leading axes [M, N].
    """
    s = sim_lib.make_sim(cfg.sim)
    eps = sample_noise(cfg, key, x0.shape[0], num_samples, x0.dtype)
    axis = 0 if isinstance(controller, LinearGaussianPolicy) else None
    per_sample = jax.vmap(lambda p, x, e: sim_lib.rollout(s, p, x, e), in_axes=(None, None, 0))
    return jax.vmap(per_sample, in_axes=(axis, 0, 0))(controller, x0, eps)


def sample_stage(cfg: Config, state: TrainState, x0: Array, key: Array, first: Array) -> Trajectories:
    """This iteration's rollouts [M, N]: the local controllers, or, with ``sample_on_policy``
    after the first iteration, the global policy with its exploration noise."""
    local = lambda: sample(cfg, state.traj, x0, key, cfg.num_samples)  # noqa: E731
    if state.policy is None or not cfg.sample_on_policy:
        return local()
    explore = policies.sampling_fn(policies.for_config(cfg), state.policy.params)
    return jax.lax.cond(first, local, lambda: sample(cfg, explore, x0, key, cfg.num_samples))


def rollout_stage(cfg: Config, state: TrainState, x0: Array, key: Array,
                  first: Array) -> tuple[Trajectories, dict]:
    """``sample_stage``'s rollouts [M, N] and ``learning_curve`` of the state's controllers and
    policy (the previous iteration's results), together.

    With MJX all of them (M·N samples, M noiseless runs of the controllers, M of the policy) are
    one batched rollout (``sim.rollout_per_row``), so a program built on this stage holds one
    instance of MJX's step: ``train`` is. With C MuJoCo they are the two stages as they are (the
    local controllers' rollouts are one host callback there). Same key, same samples.

    Returns: (Trajectories [M, N, ...], learning-curve metrics as ``learning_curve``'s).
    """
    s = sim_lib.make_sim(cfg.sim)
    if s.backend != "mjx":
        return sample_stage(cfg, state, x0, key, first), learning_curve(cfg, state.traj, state.policy, x0)
    M, N = x0.shape[0], cfg.num_samples
    conds = [jnp.repeat(jnp.arange(M), N), jnp.arange(M)]
    which = [jnp.zeros((M * N,), jnp.int32), jnp.zeros((M,), jnp.int32)]
    fns = ()
    if state.policy is not None:
        pol = policies.for_config(cfg)
        fns = (policies.mean_fn(pol, state.policy.params),)
        conds.append(jnp.arange(M))
        which.append(jnp.ones((M,), jnp.int32))
        if cfg.sample_on_policy:  # after the first iteration the samples explore with the policy
            fns += (policies.sampling_fn(pol, state.policy.params),)
            which[0] = jnp.where(first, which[0], 2)
    cond = jnp.concatenate(conds)
    R = cond.shape[0]
    eps = sample_noise(cfg, key, M, N, x0.dtype).reshape((M * N, cfg.task.T, s.dU))
    eps = jnp.concatenate([eps, jnp.zeros((R - M * N,) + eps.shape[1:], eps.dtype)])
    out = sim_lib.rollout_per_row(s, jax.tree_util.tree_map(lambda a: a[cond], state.traj), fns,
                                  jnp.concatenate(which), x0[cond], eps)
    rows = lambda lo, hi: jax.tree_util.tree_map(lambda a: a[lo:hi], out)  # noqa: E731
    samples = jax.tree_util.tree_map(lambda a: a.reshape((M, N) + a.shape[1:]), rows(0, M * N))
    pol_out = rows(M * N + M, R) if state.policy is not None else None
    return samples, _curve_metrics(cfg, rows(M * N, M * N + M), pol_out)


def cost_stage(cfg: Config, samples: Trajectories) -> tuple[QuadraticCost, Array]:
    """Sample-averaged quadratic cost expansion [M, T, ...] and per-sample total costs [M, N]."""
    cost_fn = tasks.of(cfg).make_cost(cfg)
    expansion, cs = jax.vmap(lambda X, U: cost_lib.quadratic_expansion(cost_fn, X, U))(samples.X, samples.U)
    return expansion, jnp.sum(cs, axis=-1)


def dynamics_stage(cfg: Config, prior: DynamicsPrior, samples: Trajectories,
                   key: Array) -> tuple[DynamicsPrior, Dynamics]:
    """Refresh each condition's prior with its samples, then fit the dynamics per time step."""
    keys = jax.random.split(key, samples.X.shape[0])
    prior = jax.vmap(lambda p, k, X, U: dyn_lib.update_dynamics_prior(p, k, X, U, cfg.dynamics))(
        prior, keys, samples.X, samples.U)
    dyn = jax.vmap(lambda p, X, U: dyn_lib.fit_dynamics(p, X, U, cfg.dynamics))(prior, samples.X, samples.U)
    return prior, dyn


def linearize_global_policy(cfg: Config, params, pol_prior: PolicyPrior, X: Array,
                            key: Array) -> tuple[LinearGaussianPolicy, PolicyPrior]:
    """Fit the linear-Gaussian model π̄ of the global policy around the samples (§1.2, §4.2).

    Args:
      params: PolicyParams.
      pol_prior: PolicyPrior [M].
      X: [M, N, T, dX] sample states.
    Returns:
      (LinearGaussianPolicy [M, T, ...], updated PolicyPrior [M]).
    """
    pol = policies.for_config(cfg)
    mean = lambda x: pol.mean(params, x)  # noqa: E731
    pol_mu = jax.vmap(jax.vmap(jax.vmap(mean)))(X)
    pol_sig = jax.vmap(jax.vmap(jax.vmap(lambda x: pol.covariance(params, x))))(X)
    keys = jax.random.split(key, X.shape[0])
    if cfg.policy_linearization == "autodiff":
        # Exact expansion around the per-step sample mean states; the prior is not needed.
        pol_K, pol_k, pol_S = jax.vmap(lambda x, sg: linearize.linearize_policy_autodiff(
            mean, jnp.mean(x, axis=0), jnp.mean(sg, axis=0)))(X, pol_sig)
        return jax.vmap(lqr.policy_from_covariance)(pol_K, pol_k, pol_S), pol_prior
    pol_prior = jax.vmap(lambda p, k, x: linearize.update_policy_prior(p, k, x, mean, cfg.policy_prior))(
        pol_prior, keys, X)
    pol_K, pol_k, pol_S = jax.vmap(lambda p, x, mu, sg: linearize.linearize_policy(p, x, mu, sg, cfg.policy_prior))(
        pol_prior, X, pol_mu, pol_sig)
    return jax.vmap(lqr.policy_from_covariance)(pol_K, pol_k, pol_S), pol_prior


def catch_up_stage(cfg: Config, state: TrainState, samples: Trajectories, first: Array,
                   key: Array) -> tuple[policies.PolicyParams | None, Array]:
    """MDGPS's first iteration fits the policy to the initial controllers before it is
    linearised (the toolbox's catch-up S-step, §0.4); later iterations keep it.

    Returns: (PolicyParams, or None for trajectory optimisation; [] bool: they are finite).
    """
    if state.policy is None:
        return None, jnp.asarray(True)

    def catch_up(params):
        new, _, ok = fit_policy(cfg, params, sstep_data(state.traj, samples.X), key)
        return new, ok

    return jax.lax.cond(first, catch_up, lambda p: (p, jnp.asarray(True)), state.policy.params)


def linearization_stage(cfg: Config, state: TrainState, params, samples: Trajectories,
                        key: Array) -> tuple[PolicyState | None, LinearGaussianPolicy]:
    """The KL anchor of the C-step: the previous local controllers (trajectory optimisation), or
    the global policy with ``params`` linearised around the samples (MDGPS).

    Returns: (PolicyState with ``params`` or None, anchor LinearGaussianPolicy [M, T, ...]).
    """
    if state.policy is None:
        return None, state.traj
    linearize_fn = _stage(cfg, "policy_linearization", linearize_global_policy)
    anchor, prior = linearize_fn(cfg, params, state.policy.prior, samples.X, key)
    return PolicyState(params=params, prior=prior), anchor


def anchor_stage(cfg: Config, state: TrainState, samples: Trajectories, first: Array,
                 key_catch_up: Array, key_lin: Array) -> tuple[PolicyState | None, LinearGaussianPolicy, Array]:
    """``catch_up_stage`` then ``linearization_stage``.

    Returns: (PolicyState or None, anchor LinearGaussianPolicy [M, T, ...], [] bool: the
    catch-up S-step's parameters are finite).
    """
    params, ok = catch_up_stage(cfg, state, samples, first, key_catch_up)
    policy, anchor = linearization_stage(cfg, state, params, samples, key_lin)
    return policy, anchor, ok


def c_step(cfg: Config, dyn: Dynamics, cost: QuadraticCost, anchor: LinearGaussianPolicy,
           eta: Array, step_mult: Array):
    """η search under KL(p_new ‖ anchor) ≤ ε = kl_step·step_mult·T, per condition.

    Returns: (new controllers [M, T, ...], their Marginals [M, T, ...], η [M], KL [M], ε [M],
    lqr.EtaSearchInfo [M]).
    """
    epsilon = step_size.kl_epsilon(step_mult, cfg.task.T, cfg.step)
    traj, marginals, eta, kl, info = jax.vmap(
        lambda d, c, a, e0, eps: lqr.eta_search(d, c, a, e0, eps, cfg.lqr))(dyn, cost, anchor, eta, epsilon)
    return traj, marginals, eta, kl, epsilon, info


def sstep_data(traj: LinearGaussianPolicy, X: Array, marginals: Marginals | None = None) -> policies.SStepData:
    """S-step data set from the (new) local controllers (mdgps-toolbox.md §1.4, gmr-method §3.6).

    Rows are the sampled states (and, when ``marginals`` is given, also the forward-pass mean
    states), each with its time step's controller: target action K_t x + k_t, precision Q_uu,t,
    gains K_t, offsets k_t and the forward-pass state covariance Σ_t.

    Args:
      traj: LinearGaussianPolicy [M, T, ...].
      X: [M, N, T, dX] sample states.
      marginals: Marginals [M, T, ...] of the new controllers, or None.
    Returns:
      SStepData with B = M·N·T (+ M·T) rows.
    """
    M, N, T, dX = X.shape
    states = X
    if marginals is not None:
        states = jnp.concatenate([X, marginals.mu[:, None, :, :dX]], axis=1)
    n = states.shape[1]
    rep = lambda a: jnp.broadcast_to(a[:, None], (M, n) + a.shape[1:]).reshape((M * n * T,) + a.shape[2:])  # noqa: E731
    K, k, prc = rep(traj.K), rep(traj.k), rep(traj.inv_pol_covar)
    if marginals is not None:
        state_cov = rep(marginals.sigma[:, :, :dX, :dX])
    else:
        state_cov = jnp.zeros((M * n * T, dX, dX), X.dtype)
    x = states.reshape(M * n * T, dX)
    tgt_mu = jnp.einsum("bux,bx->bu", K, x) + k
    return policies.SStepData(x=x, tgt_mu=tgt_mu, tgt_prc=prc, wt=jnp.ones((M * n * T,), X.dtype),
                              K=K, k=k, state_cov=state_cov)


def fit_policy(cfg: Config, params, data: policies.SStepData, key: Array):
    """One S-step of the configured policy: (new params, last epoch's loss [], [] bool finite)."""
    impl = None if cfg.sstep.impl == "auto" else cfg.sstep.impl

    def fit(params, data, key):
        new_params, info = sstep_lib.sstep(policies.for_config(cfg), params, data, key, cfg.sstep, impl=impl)
        return new_params, info["loss"][-1], info["finite"]

    return _stage(cfg, "sstep", fit)(params, data, key)


def s_step(cfg: Config, policy: PolicyState | None, traj: LinearGaussianPolicy, samples: Trajectories,
           marginals: Marginals, key: Array) -> tuple[PolicyState | None, Array, Array]:
    """Fit the global policy to the new controllers at the sampled states (GMR: also at the
    forward-pass means, with their state covariances). Returns (PolicyState, loss, ok)."""
    if policy is None:
        return None, jnp.zeros(()), jnp.asarray(True)
    with_marginals = policies.spec_for(cfg).sstep_marginals
    data = sstep_data(traj, samples.X, marginals if with_marginals else None)
    params, loss, ok = fit_policy(cfg, policy.params, data, key)
    return policy._replace(params=params), loss, ok


def learning_curve(cfg: Config, traj: LinearGaussianPolicy, policy: PolicyState | None,
                   x0: Array) -> dict:
    """Noiseless execution from the training states of the new local controllers (the "LQR base
    layer") and of the global policy: their final-state MSE [M], end-effector paths and final
    states."""
    if policy is None:
        return _curve_metrics(cfg, evaluate.execute(cfg, traj, x0))
    mean = policies.mean_fn(policies.for_config(cfg), policy.params)
    return _curve_metrics(cfg, *evaluate.execute_pair(cfg, traj, mean, x0))  # one MJX rollout program for both


def _curve_metrics(cfg: Config, out: Trajectories, pol_out: Trajectories | None = None) -> dict:
    """The learning curve's metrics from the noiseless rollouts [M, T, ...] of the controllers
    and (MDGPS / GMR) of the policy."""
    metrics = {"final_state_mse_lqr": evaluate.task_mse(cfg, out.X[:, -1]), "eval_ee": out.ee,
               "eval_final_x": out.X[:, -1]}
    if pol_out is not None:
        metrics.update(final_state_mse_policy=evaluate.task_mse(cfg, pol_out.X[:, -1]),
                       policy_eval_ee=pol_out.ee, policy_eval_final_x=pol_out.X[:, -1])
    return metrics


# ---------------------------------------------------------------------------------------------
# The iteration and the whole run


def stage_keys(key: Array) -> tuple[Array, ...]:
    """An iteration's keys: (sample, dynamics, linearisation, catch-up S-step, S-step)."""
    return tuple(jax.random.split(key, 5))


# ---------------------------------------------------------------------------------------------
# The iteration in parts
#
# An iteration is a chain of parts. A part maps (cfg, carry, first) to new entries of the carry, a
# dict that starts as {"state": TrainState, "key": the iteration's key} (``update``: also
# "samples") and ends with the new state's entries (``new_state``), "metrics" and "curve".
# ``iteration`` traces the chain as one program; the runner may compile groups of consecutive
# parts as programs of their own (``part_program``), which XLA compiles in parallel.


def _rollouts_part(cfg: Config, c: dict, first: Array) -> dict:
    """This iteration's samples (``sample_stage``)."""
    x0 = tasks.initial_states(cfg.task, c["state"].eta.dtype)
    return {"samples": sample_stage(cfg, c["state"], x0, stage_keys(c["key"])[0], first)}


def _model_part(cfg: Config, c: dict, first: Array) -> dict:
    """Cost expansion and dynamics fit of the samples."""
    cost, sample_costs = _stage(cfg, "cost", cost_stage)(cfg, c["samples"])
    dyn_prior, dyn = _stage(cfg, "dynamics", dynamics_stage)(cfg, c["state"].dyn_prior, c["samples"],
                                                             stage_keys(c["key"])[1])
    return {"cost": cost, "sample_costs": sample_costs, "dyn_prior": dyn_prior, "dyn": dyn}


def _catch_up_part(cfg: Config, c: dict, first: Array) -> dict:
    """The first iteration's catch-up S-step (``catch_up_stage``)."""
    params, ok = catch_up_stage(cfg, c["state"], c["samples"], first, stage_keys(c["key"])[3])
    return {"params": params, "catch_up_ok": ok}


def _anchor_part(cfg: Config, c: dict, first: Array) -> dict:
    """The KL anchor: the policy linearised at the samples (``linearization_stage``)."""
    policy, anchor = linearization_stage(cfg, c["state"], c["params"], c["samples"], stage_keys(c["key"])[2])
    return {"policy": policy, "anchor": anchor}


def _cstep_part(cfg: Config, c: dict, first: Array) -> dict:
    """The step size and the C-step."""
    state, anchor = c["state"], c["anchor"]
    model = LocalModel(anchor=anchor, dyn=c["dyn"], cost=c["cost"], sample_cost=jnp.mean(c["sample_costs"], axis=-1))
    step_mult, predicted, actual = _stage(cfg, "step_size", step_size.update)(
        cfg.step, state.step_mult, first, state.prev, state.traj, model)
    traj, marginals, eta, kl, epsilon, info = _stage(cfg, "cstep", c_step)(
        cfg, c["dyn"], c["cost"], anchor, state.eta, step_mult)
    return {"model": model, "step_mult": step_mult, "predicted": predicted, "actual": actual,
            "traj": traj, "marginals": marginals, "eta": eta, "kl": kl, "epsilon": epsilon, "info": info}


def _sstep_part(cfg: Config, c: dict, first: Array) -> dict:
    """The S-step (the new policy), the iteration count and the iteration's metrics (without the
    learning curve's)."""
    state, samples, traj, info = c["state"], c["samples"], c["traj"], c["info"]
    policy, sstep_loss, sstep_ok = s_step(cfg, c["policy"], traj, samples, c["marginals"], stage_keys(c["key"])[4])
    ok = info.ok & jnp.all(jnp.isfinite(traj.K), axis=(1, 2, 3)) & c["catch_up_ok"] & sstep_ok
    model = c["model"]
    metrics = {
        "sample_cost": model.sample_cost, "sample_costs": c["sample_costs"], "kl": c["kl"],
        "epsilon": c["epsilon"], "eta": c["eta"], "step_mult": c["step_mult"],
        "predicted_improvement": c["predicted"], "actual_improvement": c["actual"],
        "eta_iterations": info.iterations, "eta_converged": info.converged,
        "sample_final_x": samples.X[:, :, -1], "ok": ok}
    if policy is not None:
        metrics["sstep_loss"] = jnp.broadcast_to(sstep_loss, ok.shape)
    return {"iteration": state.iteration + 1, "new_policy": policy, "metrics": metrics}


STATE_ENTRIES = {"iteration": "iteration", "traj": "traj", "eta": "eta", "step_mult": "step_mult",
                 "dyn_prior": "dyn_prior", "prev": "model", "policy": "new_policy"}
"""The carry entry of each field of the new state (``new_state``)."""


def new_state(carry: dict, before: TrainState | None = None) -> TrainState:
    """The state after the iteration, assembled from the carry's entries as the parts computed
    them (not copied into one part's results): a program of later parts, or of the next
    iteration, then waits only for the parts whose results it reads (the next iteration's
    rollouts for the C-step, not for the S-step). With ``before``, the fields whose parts have
    not run yet keep ``before``'s values (for a program that reads only the others)."""
    if before is None:
        return TrainState(**{field: carry[entry] for field, entry in STATE_ENTRIES.items()})
    return before._replace(**{field: carry[entry] for field, entry in STATE_ENTRIES.items() if entry in carry})


def _curve_part(cfg: Config, c: dict, first: Array) -> dict:
    """The learning curve of the new controllers and policy."""
    x0 = tasks.initial_states(cfg.task, c["eta"].dtype)
    return {"curve": learning_curve(cfg, c["traj"], c["new_policy"], x0)}


ITERATION_PARTS = {"rollouts": _rollouts_part, "model": _model_part, "catch_up": _catch_up_part,
                   "anchor": _anchor_part, "cstep": _cstep_part, "sstep": _sstep_part, "curve": _curve_part}
"""The parts of an iteration in their order (``update``: all but the first and the last)."""

_UPDATE_PARTS = tuple(ITERATION_PARTS)[1:-1]

ROLLOUT_PARTS = ("rollouts", "curve")
"""The parts that roll the plant out (with C MuJoCo: host callbacks)."""


def run_parts(cfg: Config, names, carry: dict, first: Array) -> dict:
    """The carry after the parts ``names`` (in their order), traced under ``MATMUL_PRECISION``."""
    carry = dict(carry)
    with jax.default_matmul_precision(MATMUL_PRECISION):
        for name in names:
            new = ITERATION_PARTS[name](cfg, carry, first)
            if set(new) & set(carry):
                raise ValueError(f"iteration part {name!r} would replace {sorted(set(new) & set(carry))}")
            carry.update(new)
    return carry


@functools.cache
def part_program(names: tuple[str, ...]):
    """``fn(cfg, carry, first) -> dict``: the entries that the parts ``names`` add to ``carry``
    (not the ones it already holds, which a program would otherwise copy). One function per
    group, so that jitted programs of it share their caches."""
    def fn(cfg: Config, carry: dict, first: Array) -> dict:
        out = run_parts(cfg, names, carry, first)
        return {k: v for k, v in out.items() if k not in carry}
    fn.__name__ = fn.__qualname__ = "iteration_part_" + "_".join(names)
    return fn


def iteration_result(carry: dict) -> tuple[TrainState, dict]:
    """(new state, metrics) of a carry after every part of ``ITERATION_PARTS``."""
    return new_state(carry), {**carry["metrics"], **carry["curve"]}


def update(cfg: Config, state: TrainState, samples: Trajectories, key: Array,
           first: Array) -> tuple[TrainState, dict]:
    """Everything of an iteration after its rollouts and before its learning curve: cost
    expansion, dynamics fit, KL anchor, step size, C-step, S-step. Returns (new state, metrics
    without the learning curve's)."""
    carry = run_parts(cfg, _UPDATE_PARTS, {"state": state, "samples": samples, "key": key}, first)
    return new_state(carry), carry["metrics"]


def iteration(cfg: Config, state: TrainState, key: Array, first: Array | None = None):
    """One GPS iteration (pure; jit with ``cfg`` static): every part of ``ITERATION_PARTS``.

    Args:
      cfg: configuration (static).
      state: TrainState.
      key: PRNG key of this iteration.
      first: [] bool, True for the first iteration; default ``state.iteration == 0``. Under
        ``vmap`` over seeds pass it unbatched (``in_axes=None``): a batched predicate makes
        ``lax.cond`` compute both branches (the catch-up S-step in every iteration).
    Returns:
      (new state, metrics: dict of arrays, [M] where per condition).

    All matrix products run at full float32 precision: the GPU's default (TF32 inputs, ~1e-3
    relative error) breaks the Cholesky factorisations of the dynamics fit and the LQR.
    """
    first = state.iteration == 0 if first is None else jnp.asarray(first)
    return iteration_result(run_parts(cfg, tuple(ITERATION_PARTS), {"state": state, "key": key}, first))


def iteration_keys(key: Array, iterations: int) -> tuple[Array, Array]:
    """The (init key, per-iteration keys [iterations]) that ``train`` derives from ``key``.

    ``jax.random.split`` is prefix-stable, so the keys of the first n iterations do not depend
    on ``iterations``: a resumable loop that uses them equals ``train``, and a run extended to
    more iterations continues with the keys a longer run would have used.
    """
    k_init, k_iter = jax.random.split(key)
    return k_init, jax.random.split(k_iter, iterations)


def train(cfg: Config, key: Array):
    """A whole run: ``init`` then ``cfg.iterations`` iterations in a ``lax.scan``.

    Pure in ``key``: jit with ``cfg`` static and ``jax.vmap`` over keys to train many seeds (the
    first-iteration flag is a scan input, unbatched, so each iteration runs one branch).

    The same iterations as ``iteration`` with the same keys, arranged so that the program holds
    one instance of the rollouts: each scan step runs ``rollout_stage`` (this iteration's
    samples and the learning curve of the previous iteration's results) and then ``update``;
    one step more evaluates the last iteration's results, its ``update`` skipped by a
    ``lax.cond`` on an unbatched flag and its samples (and the first step's learning curve, of
    the initial controllers) discarded.

    Returns:
      (final TrainState, metrics history: each entry with a leading iteration axis, as
      ``iteration``'s metrics).
    """
    K = cfg.iterations
    k_init, keys = iteration_keys(key, K)
    keys = jnp.concatenate([keys, keys[-1:]])  # the evaluation step's samples are not used
    steps = jnp.arange(K + 1)

    def body(state, inp):
        k, first, last = inp
        with jax.default_matmul_precision(MATMUL_PRECISION):
            x0 = tasks.initial_states(cfg.task, state.eta.dtype)
            samples, curve = rollout_stage(cfg, state, x0, stage_keys(k)[0], first)
            metric_shapes = []

            def trained():
                new_state, metrics = update(cfg, state, samples, k, first)
                metric_shapes.append(jax.tree_util.tree_map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype), metrics))
                return new_state, metrics

            def skipped():
                # The metrics' shapes from tracing ``trained`` (``lax.cond`` traces its first
                # branch first); tracing ``update`` a second time only to learn them would cost
                # as much Python tracing as the update itself.
                shapes = metric_shapes[0] if metric_shapes else jax.eval_shape(trained)[1]
                return state, _zeros_like_tree(shapes)

            new_state, metrics = jax.lax.cond(jnp.logical_not(last), trained, skipped)
        return new_state, (metrics, curve)

    final, (metrics, curve) = sharding.seed_scan(body, init(cfg, k_init), (keys, steps == 0, steps == K),
                                                 (True, False, False))
    history = jax.tree_util.tree_map(lambda a: a[:K], metrics)
    history.update(jax.tree_util.tree_map(lambda a: a[1:], curve))
    return final, history
