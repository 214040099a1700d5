"""Why float32 needs the Cholesky floor: the first dynamics fit of the reach study per seed.

For each seed, the first iteration's samples (float64 rollouts of the initial controllers) are
fitted twice (``mdgps.dynamics_stage``): in float64 and, cast, in float32. Printed per seed:
whether each fit is finite, the relative difference of the fitted dynamics Fm, and the smallest
eigenvalue of the active GMM clusters' covariances scaled to unit diagonal (float64 fit) against
Cholesky's completion bound n(n+1)ε in float32 (Demmel; ``gmr_jax.linalg.cholesky_floor``)::

    python -m benchmarks.float32_fit --scenario A --seeds 4

Run at a commit before ``linalg.ridge`` (899e6c0) it shows the float32 NaN the ridge removes.
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import numpy as np

from gmr_jax import config, linalg, mdgps, tasks


def fit_both(cfg: config.Config, seed: int):
    """(Dynamics float64, Dynamics float32, DynamicsPrior float64) of seed's first iteration."""
    key = jax.random.PRNGKey(seed)
    state = mdgps.init(cfg, key)
    x0 = tasks.initial_states(cfg.task)
    samples = mdgps.sample_stage(cfg, state, x0, jax.random.fold_in(key, 1), jnp.asarray(True))
    out = []
    for dtype in (jnp.float64, jnp.float32):
        cast = lambda t: jax.tree_util.tree_map(  # noqa: E731
            lambda a: a.astype(dtype) if jnp.issubdtype(a.dtype, jnp.floating) else a, t)
        with jax.default_matmul_precision(mdgps.MATMUL_PRECISION):
            prior, dyn = jax.jit(lambda p, s, k: mdgps.dynamics_stage(cfg, p, s, k))(
                cast(state.dyn_prior), cast(samples), key)
        out.append((prior, dyn))
    return out[0][1], out[1][1], out[0][0]


def scaled_min_eigenvalue(prior) -> float:
    """Smallest eigenvalue of D⁻¹ΣD⁻¹ over the active clusters of every condition's GMM."""
    sig = np.asarray(prior.gmm.sigma)[np.asarray(prior.gmm.active)]  # [K', D, D]
    d = np.sqrt(np.diagonal(sig, axis1=-2, axis2=-1))
    return float(np.linalg.eigvalsh(sig / (d[:, :, None] * d[:, None, :])).min())


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.float32_fit", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenario", default="A")
    p.add_argument("--seeds", type=int, default=4)
    args = p.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    cfg = config.reach(args.scenario, "lqr", sim__backend="mujoco")
    for seed in range(args.seeds):
        d64, d32, prior = fit_both(cfg, seed)
        D = prior.gmm.sigma.shape[-1]
        ok32 = bool(linalg.all_finite(d32))
        rel = f"{float(jnp.max(jnp.abs(d32.Fm - d64.Fm)) / jnp.max(jnp.abs(d64.Fm))):.2e}" if ok32 else "–"
        print(f"seed {seed}: finite float64 {bool(linalg.all_finite(d64))}, float32 "
              f"{ok32}; Fm relative difference {rel}; smallest scaled "
              f"cluster eigenvalue {scaled_min_eigenvalue(prior):.2e} (float32 bound "
              f"n(n+1)ε = {D * (D + 1) * np.finfo(np.float32).eps:.2e}, n = {D})", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
