"""The GPS iteration: one pure, jittable function, and a whole run as a ``lax.scan`` over it.

Two algorithms share the code (``cfg.algorithm``):

* ``"lqr"`` — trajectory optimisation only (the toolbox's AlgorithmTrajOpt, the paper's "LQR base
  layer"): sample the local controllers → cost expansion → dynamics fit → step-size rule →
  C-step with the KL bound to the previous local controller.
* ``"mdgps"`` / ``"gmr"`` — mirror-descent GPS (mdgps-toolbox.md §0): the KL anchor of the C-step
  is the linearised global policy, and an S-step fits the policy to the new controllers.

Axis conventions: condition M, sample N, time T. Every array in the state has a leading M axis
except the iteration counter and the policy parameters (shared by the conditions).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from gmr_jax import cost as cost_lib
from gmr_jax import dynamics as dyn_lib
from gmr_jax import linearize, lqr, policies, tasks
from gmr_jax import noise as noise_lib
from gmr_jax import sim as sim_lib
from gmr_jax import sstep as sstep_lib
from gmr_jax.config import Config
from gmr_jax.types import Dynamics, LinearGaussianPolicy, QuadraticCost


class TrainState(NamedTuple):
    """Everything an iteration carries to the next (a pytree).

    Attributes:
      iteration: [] int32, iterations completed.
      traj: LinearGaussianPolicy [M, T, ...], the current local controllers (sampled next).
      prev_traj: LinearGaussianPolicy [M, T, ...], the controllers of the previous iteration.
      eta: [M] dual variable of each condition's KL constraint (warm start of the η search).
      step_mult: [M] KL step multiplier.
      dyn_prior: DynamicsPrior [M], each condition's ring buffer of trajectories and GMM.
      prev_dyn: Dynamics [M], the previous iteration's fitted dynamics.
      prev_cost: QuadraticCost [M], the previous iteration's cost expansion.
      prev_cs: [M] the previous iteration's mean sample cost (for the 'mc' step rule).
      policy: PolicyParams of the global policy (MDGPS/GMR; None for "lqr").
      pol_prior: PolicyPrior [M] of the policy linearisation (None for "lqr").
      prev_pol_lin: LinearGaussianPolicy [M], the previous linearisation of the policy (None
        for "lqr").
    """

    iteration: jax.Array
    traj: LinearGaussianPolicy
    prev_traj: LinearGaussianPolicy
    eta: jax.Array
    step_mult: jax.Array
    dyn_prior: Any
    prev_dyn: Dynamics
    prev_cost: QuadraticCost
    prev_cs: jax.Array
    policy: Any = None
    pol_prior: Any = None
    prev_pol_lin: Any = None


def _zeros_like_tree(tree):
    return jax.tree_util.tree_map(jnp.zeros_like, tree)


def _broadcast_conditions(tree, M: int):
    return jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (M,) + jnp.shape(a)), tree)


def uses_policy(cfg: Config) -> bool:
    """Whether the algorithm trains a global policy (MDGPS, GMR) or only local controllers."""
    return cfg.algorithm != "lqr"


def make_global_policy(cfg: Config) -> policies.Policy:
    """The global policy of the configured algorithm ("mdgps": MLP, "gmr": GMR)."""
    if cfg.algorithm == "mdgps":
        return policies.make_policy("mlp", cfg.mlp)
    if cfg.algorithm == "gmr":
        return policies.make_policy("gmr", cfg.gmr)
    raise ValueError(f"algorithm={cfg.algorithm!r} has no global policy")


def init(cfg: Config, key: jax.Array) -> TrainState:
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
    with jax.default_matmul_precision("highest"):
        traj = jax.vmap(lambda x: lqr.init_lqr(x, T, dU, cfg.sim.control_dt, cfg.init))(x0)
    prior = _broadcast_conditions(dyn_lib.dynamics_prior_empty(T, dX, dU, cfg.dynamics, dtype), M)
    dyn0 = Dynamics(
        Fm=jnp.zeros((M, T, dX, dX + dU), dtype), fv=jnp.zeros((M, T, dX), dtype),
        dyn_covar=jnp.zeros((M, T, dX, dX), dtype), x0mu=jnp.zeros((M, dX), dtype),
        x0sigma=jnp.zeros((M, dX, dX), dtype))
    cost0 = QuadraticCost(Cm=jnp.zeros((M, T, dX + dU, dX + dU), dtype),
                          cv=jnp.zeros((M, T, dX + dU), dtype), cc=jnp.zeros((M, T), dtype))
    state = TrainState(
        iteration=jnp.zeros((), jnp.int32), traj=traj, prev_traj=_zeros_like_tree(traj),
        eta=jnp.ones((M,), dtype), step_mult=jnp.ones((M,), dtype), dyn_prior=prior,
        prev_dyn=dyn0, prev_cost=cost0, prev_cs=jnp.zeros((M,), dtype))
    if not uses_policy(cfg):
        return state
    pol = make_global_policy(cfg)
    params = pol.init(key, dX, dU, dtype)
    pol_prior = _broadcast_conditions(linearize.policy_prior_empty(T, dX, dU, cfg.policy_prior, dtype), M)
    return state._replace(policy=params, pol_prior=pol_prior, prev_pol_lin=_zeros_like_tree(traj))


def sample(cfg: Config, policy, x0: jax.Array, key: jax.Array, num_samples: int):
    """Noisy rollouts of per-condition controllers.

    Args:
      policy: a LinearGaussianPolicy with a leading condition axis M, or a callable
        ``policy(t, x, eps_t) -> u`` shared by all conditions.
      x0: [M, dX] initial states.
      key: PRNG key.
      num_samples: N rollouts per condition.
    Returns:
      Trajectories with leading axes [M, N].
    """
    s = sim_lib.make_sim(cfg.sim)
    M = x0.shape[0]
    keys = jax.random.split(key, (M, num_samples))
    eps = jax.vmap(jax.vmap(lambda k: noise_lib.smooth_noise(k, cfg.task.T, s.dU, cfg.noise)))(keys)
    eps = eps.astype(x0.dtype)
    pol_axis = 0 if isinstance(policy, LinearGaussianPolicy) else None
    per_sample = jax.vmap(lambda p, x, e: sim_lib.rollout(s, p, x, e), in_axes=(None, None, 0))
    return jax.vmap(per_sample, in_axes=(pol_axis, 0, 0))(policy, x0, eps)


def evaluate_controllers(cfg: Config, policy, x0: jax.Array):
    """Noiseless execution from each condition's initial state.

    Args:
      policy: LinearGaussianPolicy [M, ...] (each condition's own) or a callable shared by all.
      x0: [M, dX].
    Returns:
      (Trajectories [M, T, ...], final-state MSE [M] against the task target).
    """
    s = sim_lib.make_sim(cfg.sim)
    eps = jnp.zeros((cfg.task.T, s.dU), x0.dtype)
    pol_axis = 0 if isinstance(policy, LinearGaussianPolicy) else None
    out = jax.vmap(lambda p, x: sim_lib.rollout(s, p, x, eps), in_axes=(pol_axis, 0))(policy, x0)
    mse = tasks.final_state_mse(out.X[:, -1], tasks.target_state(cfg.task, x0.dtype))
    return out, mse


def policy_mean_fn(cfg: Config, params):
    """The global policy's deterministic action as a rollout callable ``(t, x, eps_t) -> u``."""
    pol = make_global_policy(cfg)
    return lambda t, x, e: pol.mean(params, x)


def policy_sampling_fn(cfg: Config, params):
    """The global policy with exploration noise, ``u = mean(x) + chol(cov(x)) eps_t``."""
    pol = make_global_policy(cfg)
    return lambda t, x, e: policies.noisy_action(pol, params, x, e)


def _laplace_total(traj, dyn, cst):
    """Σ_t of the Laplace cost estimate, per condition ([M])."""
    return jnp.sum(jax.vmap(lqr.estimate_cost)(traj, dyn, cst), axis=-1)


def linearize_global_policy(cfg: Config, params, pol_prior, X: jax.Array, key: jax.Array):
    """Fit the linear-Gaussian model π̄ of the global policy around the samples (§1.2, §4.2).

    Args:
      params: PolicyParams.
      pol_prior: PolicyPrior [M].
      X: [M, N, T, dX] sample states.
    Returns:
      (LinearGaussianPolicy [M, T, ...], updated PolicyPrior [M]).
    """
    pol = make_global_policy(cfg)
    mean = lambda x: pol.mean(params, x)  # noqa: E731
    M = X.shape[0]
    pol_mu = jax.vmap(jax.vmap(jax.vmap(mean)))(X)
    pol_sig = jax.vmap(jax.vmap(jax.vmap(lambda x: pol.covariance(params, x))))(X)
    keys = jax.random.split(key, M)
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


def sstep_data(traj: LinearGaussianPolicy, X: jax.Array, marginals=None) -> policies.SStepData:
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


def _run_sstep(cfg: Config, params, data: policies.SStepData, key):
    new_params, info = sstep_lib.sstep(make_global_policy(cfg), params, data, key, cfg.sstep)
    return new_params, info["loss"][-1], info["finite"]


def _iteration(cfg: Config, state: TrainState, key: jax.Array, first: bool | None):
    """One iteration; ``first`` static True/False for the first/later iterations, None to decide
    from ``state.iteration`` at run time, or a boolean scalar array decided at run time.

    All matrix products run at full float32 precision: the GPU's default (TF32 inputs, ~1e-3
    relative error) breaks the Cholesky factorisations of the dynamics fit and the LQR.
    """
    with jax.default_matmul_precision("highest"):
        return _iteration_body(cfg, state, key, first)


def _iteration_body(cfg: Config, state: TrainState, key: jax.Array, first: bool | None):
    T = cfg.task.T
    x0 = tasks.initial_states(cfg.task, state.eta.dtype)
    M = x0.shape[0]
    k_sample, k_dyn, k_lin, k_s0, k_s1 = jax.random.split(key, 5)
    with_policy = uses_policy(cfg)
    # `first`: a Python bool (static branch), None (decided per seed from state.iteration), or a
    # boolean scalar array (decided at run time, shared by all seeds: a real lax.cond under vmap).
    static = first if isinstance(first, bool) else None
    is_first = state.iteration == 0 if first is None else jnp.asarray(first)

    # 1. Sample the local controllers (or, with sample_on_policy after the first iteration, π).
    if with_policy and cfg.sample_on_policy and static is not True:
        on_pol = lambda: sample(cfg, policy_sampling_fn(cfg, state.policy), x0, k_sample, cfg.num_samples)  # noqa: E731
        off_pol = lambda: sample(cfg, state.traj, x0, k_sample, cfg.num_samples)  # noqa: E731
        trajs = on_pol() if static is False else jax.lax.cond(is_first, off_pol, on_pol)
    else:
        trajs = sample(cfg, state.traj, x0, k_sample, cfg.num_samples)

    # 2. Cost: per-sample costs and the sample-averaged quadratic expansion.
    cost_fn = tasks.make_cost(cfg)
    cst, cs = jax.vmap(lambda X, U: cost_lib.quadratic_expansion(cost_fn, X, U))(trajs.X, trajs.U)
    cs_total = jnp.mean(jnp.sum(cs, axis=-1), axis=-1)  # [M]

    # 3. Dynamics: refresh each condition's prior with its samples, then fit per time step.
    dyn_keys = jax.random.split(k_dyn, M)
    prior = jax.vmap(lambda p, k, X, U: dyn_lib.update_dynamics_prior(p, k, X, U, cfg.dynamics))(
        state.dyn_prior, dyn_keys, trajs.X, trajs.U)
    dyn = jax.vmap(lambda p, X, U: dyn_lib.fit_dynamics(p, X, U, cfg.dynamics))(prior, trajs.X, trajs.U)

    params, pol_prior, sstep_ok = state.policy, state.pol_prior, jnp.asarray(True)
    if with_policy:
        # 4. First iteration only: catch the policy up with the initial controllers (toolbox §0.4).
        def catch_up(p):
            new_p, _, ok = _run_sstep(cfg, p, sstep_data(state.traj, trajs.X), k_s0)
            return new_p, ok
        if static is True:
            params, sstep_ok = catch_up(params)
        elif static is None:
            params, sstep_ok = jax.lax.cond(is_first, catch_up, lambda p: (p, jnp.asarray(True)), params)
        # 5. Linearise the global policy around the samples: the KL anchor of the C-step.
        anchor, pol_prior = linearize_global_policy(cfg, params, state.pol_prior, trajs.X, k_lin)
        # 6. Step size: previous linearisation vs the executed controllers (§1.3).
        prev_laplace = _laplace_total(state.prev_pol_lin, state.prev_dyn, state.prev_cost)
        cur_laplace = _laplace_total(anchor, dyn, cst)
    else:
        # Trajectory optimisation: the anchor is the previous controller.
        anchor = state.traj
        prev_laplace = _laplace_total(state.prev_traj, state.prev_dyn, state.prev_cost)
        cur_laplace = _laplace_total(state.traj, dyn, cst)
    prev_predicted = _laplace_total(state.traj, state.prev_dyn, state.prev_cost)
    if cfg.step.step_rule == "laplace":
        predicted, actual = prev_laplace - prev_predicted, prev_laplace - cur_laplace
    else:
        predicted, actual = state.prev_cs - prev_predicted, state.prev_cs - cs_total
    adjusted = lqr.step_multiplier(predicted, actual, state.step_mult, cfg.step)
    step_mult = state.step_mult if static is True else jnp.where(is_first, state.step_mult, adjusted)

    # 7. C-step: η search under KL(p_new ‖ anchor) ≤ ε, per condition.
    epsilon = lqr.kl_epsilon(step_mult, T, cfg.step)
    new_traj, marginals, eta, kl, info = jax.vmap(
        lambda d, c, a, e0, eps: lqr.eta_search(d, c, a, e0, eps, cfg.lqr))(
            dyn, cst, anchor, state.eta, epsilon)

    # Learning curve: noiseless execution of the new local controllers ("LQR base layer").
    eval_traj, mse = evaluate_controllers(cfg, new_traj, x0)
    metrics = {
        "sample_cost": cs_total,
        "sample_costs": jnp.sum(cs, axis=-1),  # [M, N]
        "final_state_mse_lqr": mse,
        "kl": kl,
        "epsilon": epsilon,
        "eta": eta,
        "step_mult": step_mult,
        "predicted_improvement": predicted,
        "actual_improvement": actual,
        "eta_iterations": info.iterations,
        "eta_converged": info.converged,
        "eval_ee": eval_traj.ee,
        "eval_final_x": eval_traj.X[:, -1],
        "sample_final_x": trajs.X[:, :, -1],
    }
    ok = info.ok & jnp.all(jnp.isfinite(new_traj.K), axis=(1, 2, 3))

    if with_policy:
        # 8. S-step: fit the policy to the new controllers at the sampled states (GMR: also at
        #    the forward-pass means, with their state covariances).
        data = sstep_data(new_traj, trajs.X, marginals if cfg.algorithm == "gmr" else None)
        params, sstep_loss, finite = _run_sstep(cfg, params, data, k_s1)
        sstep_ok = sstep_ok & finite
        pol_eval, pol_mse = evaluate_controllers(cfg, policy_mean_fn(cfg, params), x0)
        metrics.update({
            "final_state_mse_policy": pol_mse,
            "sstep_loss": jnp.broadcast_to(sstep_loss, (M,)),
            "policy_eval_ee": pol_eval.ee,
            "policy_eval_final_x": pol_eval.X[:, -1],
        })
        ok = ok & sstep_ok
    metrics["ok"] = ok

    new_state = TrainState(
        iteration=state.iteration + 1, traj=new_traj, prev_traj=state.traj, eta=eta,
        step_mult=step_mult, dyn_prior=prior, prev_dyn=dyn, prev_cost=cst, prev_cs=cs_total,
        policy=params, pol_prior=pol_prior, prev_pol_lin=anchor if with_policy else None)
    return new_state, metrics


def iteration(cfg: Config, state: TrainState, key: jax.Array, first: jax.Array | None = None):
    """One GPS iteration (pure; jit with ``cfg`` static).

    The first iteration of MDGPS/GMR also runs the catch-up S-step on the initial controllers,
    decided at run time by a ``lax.cond``: from ``state.iteration`` when ``first`` is None (under
    ``vmap`` over seeds that predicate is batched, so both branches are computed), or from
    ``first``, a boolean scalar that ``vmap`` leaves unbatched (``in_axes=None``), so that only
    the taken branch runs and one compiled program serves every iteration (the CLI's choice).
    ``train`` decides it statically instead (``iteration_static``).

    Args:
      cfg: configuration (static).
      state: TrainState.
      key: PRNG key of this iteration.
      first: optional boolean scalar, True for the first iteration.
    Returns:
      (new state, metrics dict of arrays, [M] where per condition).
    """
    if isinstance(first, bool):
        raise TypeError("iteration: pass first as an array (jnp.asarray(True)); for a static "
                        "Python bool use iteration_static")
    return _iteration(cfg, state, key, first)


def iteration_static(cfg: Config, state: TrainState, key: jax.Array, first: bool):
    """``iteration`` with the first-iteration branch chosen statically (``first`` is static)."""
    return _iteration(cfg, state, key, first)


def train(cfg: Config, key: jax.Array):
    """A whole run: ``init`` then ``cfg.iterations`` iterations in a ``lax.scan``.

    Pure in ``key``: jit with ``cfg`` static and ``jax.vmap`` over keys to train many seeds.

    Returns:
      (final TrainState, metrics history: each entry with a leading iteration axis).
    """
    k_init, keys = iteration_keys(key, cfg.iterations)
    state = init(cfg, k_init)
    # The first iteration is peeled off so that its catch-up S-step is a static branch.
    state, first_metrics = _iteration(cfg, state, keys[0], True)
    state, rest = jax.lax.scan(lambda s, k: _iteration(cfg, s, k, False), state, keys[1:])
    history = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a[None], b]), first_metrics, rest)
    return state, history


def iteration_keys(key: jax.Array, iterations: int) -> tuple[jax.Array, jax.Array]:
    """The (init key, per-iteration keys) that ``train`` derives from ``key``.

    The CLI's resumable loop uses the same keys so that an interrupted and resumed run equals an
    uninterrupted ``train``.
    """
    k_init, k_iter = jax.random.split(key)
    return k_init, jax.random.split(k_iter, iterations)
