"""Results, figures and the summary of a study (host-side, numpy and matplotlib).

Task-independent: the task of the runs (``gmr_jax.tasks``) gives the title, the names of its
scenarios' conditions and the paper's reference numbers.
"""

from __future__ import annotations

import concurrent.futures
import gzip
import json
import multiprocessing
import os
import pathlib
import signal
import threading
import time

import numpy as np

from gmr_jax import process_server, sim, stats, tasks
from gmr_jax.runner import jsonable

# Per-iteration learning-curve entries, in the order they are reported.
CURVES = (("final_state_mse_lqr", "LQR base layer"), ("final_state_mse_policy", "policy"))


def read_results(path) -> dict:
    """A study's results: ``path`` is a ``results.json``, a gzipped ``results.json.gz`` (as the
    committed studies in docs/results keep them) or a study folder holding either."""
    path = pathlib.Path(path)
    if path.is_dir():
        path = path / "results.json" if (path / "results.json").is_file() else path / "results.json.gz"
    data = gzip.decompress(path.read_bytes()) if path.suffix == ".gz" else path.read_bytes()
    return json.loads(data)


def _label(algorithm: str, curve: str) -> str:
    if curve == "final_state_mse_lqr":
        return "LQR base layer" if algorithm == "lqr" else f"LQR base layer ({algorithm})"
    return algorithm.upper()


def write_results(out: pathlib.Path, configs, runs, seeds, device, total_s,
                  command_s: float | None = None, start_s: float | None = None) -> dict:
    """Write ``results.json``: per run (scenario, algorithm, seed) the per-iteration metrics, and
    the seconds of the runs side by side (``total_s``, "total_wall_s"), of the whole command
    (``command_s``, "command_wall_s") and from the command's start to the runs' (``start_s``,
    "startup_s": imports and set-up).

    Scalars per condition are averaged over conditions (the learning-curve convention), and the
    per-condition values are kept too.
    """
    records = []
    for (scenario, algorithm), run in runs.items():
        h = run["history"]
        extra = final_extra(configs[(scenario, algorithm)], h)  # {name_curve: [iterations, S, M]}
        for i, seed in enumerate(seeds):
            rec = {"scenario": scenario, "algorithm": algorithm, "seed": seed}
            for name in ("final_state_mse_lqr", "final_state_mse_policy", "sample_cost", "kl",
                         "eta", "step_mult", "epsilon"):
                if name in h:
                    per_cond = h[name][:, i]  # [iterations, M]
                    rec[name] = jsonable(per_cond.mean(axis=-1))
                    rec[name + "_per_condition"] = jsonable(per_cond)
            rec["sample_costs"] = jsonable(h["sample_costs"][:, i])  # [iterations, M, N]
            if "final_state_mse_lqr" in h:
                rec["final_state_mse"] = rec["final_state_mse_lqr"]
            if "final_state_mse_policy" in h:
                rec["final_state_mse"] = rec["final_state_mse_policy"]
            for name, ok in extra.items():
                rec[name + "_per_condition"] = jsonable(ok[:, i])
            if "robustness" in run:
                rob = run["robustness"]
                rec["robustness"] = {
                    "successes": int(rob["success"][i].sum()),
                    "successes_loose": int(rob["success_loose"][i].sum()),
                    "states": int(rob["success"][i].size),
                    "mse": jsonable(rob["mse"][i]),
                    "distance": jsonable(rob["distance"][i])}
                for name, ok in rob.get("extra", {}).items():
                    rec["robustness"][f"successes_{name}"] = int(ok[i].sum())
                if "stability" in run:
                    stab = run["stability"]
                    rec["stability"] = {"target_radius": float(stab["target_radius"][i]),
                                        "contracting": float(stab["contracting"][i]),
                                        "radius_median": float(np.nanmedian(stab["radius"][i]))}
                rec["disturbance_sweep"] = {
                    "radii": run["sweep"]["radii"],
                    "success_rate": jsonable(run["sweep"]["success_rate"][i]),
                    "success_rate_loose": jsonable(run["sweep"]["success_rate_loose"][i])}
            records.append(rec)
    results = {"device": device, "seeds": list(seeds), "total_wall_s": total_s,
               **({} if command_s is None else {"command_wall_s": command_s}),
               **({} if start_s is None else {"startup_s": start_s}),
               "timing": {f"{s}/{a}": {"wall_s": r["wall_s"], **r.get("timing", {}),
                                       "iteration_s": list(r.get("iteration_s", []))}
                          for (s, a), r in runs.items()},
               "robustness_stats": {k: {m: {f: None if isinstance(x, float) and np.isnan(x) else x
                                                for f, x in v._asdict().items()} for m, v in row.items()}
                                    for k, row in robustness_stats(runs).items()},
               "learning_speed": {f"{s}/{a}": {k: v.tolist() for k, v in success_iterations(
                   r, configs[(s, a)].task.success_threshold).items()} for (s, a), r in runs.items()},
               "runs": records}
    (out / "results.json").write_text(json.dumps(results, indent=1))
    return results


# The final states of the noiseless executions after every iteration, per curve.
FINAL_STATES = (("eval_final_x", "lqr"), ("policy_eval_final_x", "policy"))


def final_extra(cfg, history) -> dict:
    """The task's further success measures (e.g. "inserted") of every iteration's noiseless
    executions: {"<name>_<lqr|policy>": bool [iterations, seeds, M]}; empty for reach."""
    task = tasks.of(cfg)
    out = {}
    for key, curve in FINAL_STATES:
        if key in history:
            for name, ok in task.success_extra(cfg, np.asarray(history[key])).items():
                out[f"{name}_{curve}"] = np.asarray(ok)
    return out


def _curves(run):
    h = run["history"]
    for curve, _ in CURVES:
        if curve in h:
            yield curve, h[curve].mean(axis=-1)  # [iterations, seeds]


def preload_plotting() -> None:
    """Import matplotlib with the file-only Agg backend (a second or so; the CLI does it in the
    background while it trains, so that the figures follow the training at once)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot  # noqa: F401


def plot_learning_curves(path: pathlib.Path, configs, runs) -> None:
    """Final-state MSE per iteration, mean ± std over seeds, one panel per scenario."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenarios = sorted({s for s, _ in runs}, key=lambda s: (len(s), s))
    fig, axes = plt.subplots(1, len(scenarios), figsize=(5.5 * len(scenarios), 4), squeeze=False)
    for ax, scenario in zip(axes[0], scenarios):
        for (s, algorithm), run in runs.items():
            if s != scenario:
                continue
            threshold = configs[(s, algorithm)].task.success_threshold
            for curve, values in _curves(run):
                it = np.arange(1, values.shape[0] + 1)
                mean, std = values.mean(axis=1), values.std(axis=1)
                line, = ax.semilogy(it, mean, marker="o", label=_label(algorithm, curve),
                                    linestyle="--" if curve.endswith("lqr") and algorithm != "lqr" else "-")
                # mean ± std over seeds; on the log axis the lower edge is floored at the best
                # seed so that a band reaching below zero does not stretch the axis.
                ax.fill_between(it, np.maximum(mean - std, values.min(axis=1)), mean + std,
                                alpha=0.2, color=line.get_color())
        ax.axhline(threshold, color="k", lw=0.8, ls=":", label=f"success threshold {threshold}")
        ax.set_title(f"scenario {scenario}")
        ax.set_xlabel("iteration")
        ax.set_ylabel("final-state MSE")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_paths(path: pathlib.Path, configs, runs) -> None:
    """End-effector paths (x–y and x–z projections) of the noiseless controllers, first seed,
    every iteration (light) and the last (dark)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = list(runs)
    fig, axes = plt.subplots(len(keys), 2, figsize=(10, 4.2 * len(keys)), squeeze=False)
    for row, key in enumerate(keys):
        ee = runs[key]["history"]["eval_ee"][:, 0]  # [iterations, M, T, 3]
        n_it = ee.shape[0]
        for col, (a, b, name) in enumerate(((0, 1, "y"), (0, 2, "z"))):
            ax = axes[row, col]
            for m in range(ee.shape[1]):
                for i in range(n_it):
                    alpha = 0.15 + 0.85 * (i + 1) / n_it
                    ax.plot(ee[i, m, :, a], ee[i, m, :, b], color=f"C{m}", alpha=alpha,
                            lw=2.0 if i == n_it - 1 else 0.8,
                            label=f"condition {m}" if i == n_it - 1 else None)
                ax.plot(ee[-1, m, 0, a], ee[-1, m, 0, b], "o", color=f"C{m}")
                ax.plot(ee[-1, m, -1, a], ee[-1, m, -1, b], "x", color="k")
            ax.set_xlabel("x (m)")
            ax.set_ylabel(f"{name} (m)")
            ax.set_aspect("equal", adjustable="datalim")
            ax.grid(True, alpha=0.3)
            ax.set_title(f"{key[0]} / {key[1]}: end-effector paths (o start, x end)")
            ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


TIMING_PHASES = (("init_s", "init"), ("trace_s", "trace"), ("lower_s", "lower"),
                 ("compile_s", "compile"), ("training_start_s", "first iteration from"),
                 ("iterations_s", "iterations"),
                 ("checkpoint_s", "checkpoints"), ("robustness_trace_s", "robustness trace"),
                 ("robustness_lower_s", "lower"), ("robustness_compile_s", "compile (beside training, in a slot)"),
                 ("robustness_wait_s", "waited for"), ("robustness_run_s", "run"),
                 ("stability_warm_up_s", "stability prepared (beside training)"), ("stability_s", "stability"))


def format_timing(run) -> str:
    """The run's seconds per phase, e.g. "init 1.2 s, trace 3.4 s, …" (phases it did not have
    are left out; side-by-side runs overlap, so the phases of all runs add up to more than the
    total wall time)."""
    timing = run.get("timing", {})
    parts = [f"{name} {timing[key]:.1f} s" for key, name in TIMING_PHASES if key in timing]
    its = run.get("iteration_s", [])
    if len(its) > 1:
        parts.append(f"iteration 1 {its[0]:.2f} s, later ones {np.median(its[1:]):.2f} s median")
    return ", ".join(parts)


def _total(runs_s: float, results: dict) -> str:
    if "command_wall_s" not in results:
        return f"{runs_s:.1f} s"
    return (f"{results['command_wall_s']:.1f} s for the whole command (imports, compilation, "
            f"training, evaluation, figures); the runs side by side {runs_s:.1f} s")


def _task(configs) -> tasks.Task:
    return tasks.of(next(iter(configs.values())))


FIGURE_WORKERS_MIN_CORES = 8
"""The host cores (this process's affinity) from which :func:`figure_workers` draws the figures
in processes of their own: their imports (matplotlib, while the runs train) would slow a small
host's training."""


def _figure_worker_start() -> None:
    """A figure worker's start: SIGTERM's default action (the server it forks from ignores it),
    its end as soon as the command that started it has ended (it waits on a queue that tells it
    nothing of that), matplotlib imported."""
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    parent = multiprocessing.parent_process()
    if parent is not None:
        def watch():
            while parent.is_alive():
                time.sleep(0.5)
            os._exit(0)
        threading.Thread(target=watch, daemon=True).start()
    preload_plotting()


def figure_workers() -> concurrent.futures.ProcessPoolExecutor | None:
    """Processes that draw the study's figures side by side (matplotlib draws under the GIL, so
    threads would not), one per figure, forked from ``gmr_jax.process_server``'s server in a
    background thread (so this one never waits for the server's imports) and importing
    matplotlib while the runs train; None on a host with fewer than
    :data:`FIGURE_WORKERS_MIN_CORES` cores (:func:`plot_all` then draws the figures here). A
    Ctrl-C reaches this process only; shut the workers down after :func:`plot_all`."""
    if sim.host_cores() < FIGURE_WORKERS_MIN_CORES:
        return None
    process_server.start()  # from this thread, as for the runs' processes (a no-op once it runs)
    workers = concurrent.futures.ProcessPoolExecutor(len(FIGURES), mp_context=process_server.context(),
                                                     initializer=_figure_worker_start)
    threading.Thread(target=_start_workers, args=(workers,), daemon=True).start()
    return workers


def _start_workers(workers: concurrent.futures.ProcessPoolExecutor) -> None:
    # each call while no worker is idle starts one (and waits until the server can fork it)
    try:
        for _ in FIGURES:
            workers.submit(int)
    except RuntimeError:  # shut down meanwhile (the study ended early)
        pass


def plot_all(out: pathlib.Path, configs, runs, workers: concurrent.futures.Executor | None = None) -> None:
    """The study's figures (:data:`FIGURES`): learning curves, paths, robustness, per-seed
    successes; drawn by ``workers`` (:func:`figure_workers`) side by side, else, or where a
    worker has died, one after the other here. The first figure that fails raises its error."""
    jobs = [(plot, out / file) for plot, file in FIGURES]
    if workers is not None:
        try:
            for future in [workers.submit(plot, path, configs, runs) for plot, path in jobs]:
                future.result()
            return
        except concurrent.futures.BrokenExecutor:
            pass
    for plot, path in jobs:
        plot(path, configs, runs)


def plot_seed_successes(path: pathlib.Path, configs, runs) -> None:
    """Successes from the random states per seed (dots), their mean with the 95 % bootstrap
    interval (bar), the IQM (diamond) and the paper's count (star), one column per run."""
    keys = [k for k in runs if "robustness" in runs[k]]
    if not keys:
        return
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    task = _task(configs)
    fig, ax = plt.subplots(figsize=(1.6 * len(keys) + 2.5, 4.2))
    jitter = np.random.default_rng(0)
    for i, key in enumerate(keys):
        counts = np.asarray(runs[key]["robustness"]["success"]).sum(axis=-1)
        st = stats.over_seeds(counts)
        color = "tab:blue" if key[1] == "gmr" else "tab:orange"
        ax.plot(i + jitter.uniform(-0.15, 0.15, counts.size), counts, "o", color=color, alpha=0.5, ms=4)
        if st.n > 1:
            ax.errorbar(i + 0.3, st.mean, yerr=[[st.mean - st.low], [st.high - st.mean]], fmt="o", color="k",
                        capsize=4)
        ax.plot(i + 0.3, st.iqm, "D", color="k", mfc="none", ms=6)
        paper = task.paper_robustness.get(key)
        if paper is not None:
            ax.plot(i + 0.45, paper, "*", color="tab:red", ms=11)
    ax.set_xticks(range(len(keys)), [f"{', '.join(task.scenarios[s])}\n{a.upper()}" for s, a in keys])
    n = np.asarray(runs[keys[0]]["robustness"]["success"]).shape[-1]
    ax.set_ylim(-1, n + 1)
    ax.set_ylabel(f"successes of {n} random states")
    ax.set_title("per seed (dots); mean, 95 % bootstrap CI (bar); IQM (◇); paper (★)", fontsize=9)
    ax.grid(True, axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_summary(path: pathlib.Path, configs, runs, seeds, device, total_s, results) -> None:
    """``summary.md``: robustness table against the paper, final-state MSE per iteration (mean
    over seeds), successes, timing."""
    task = _task(configs)
    lines = [f"# {task.title} study summary", "",
             f"Device: {device}. Seeds: {seeds}. Total wall time: {_total(total_s, results)}.", ""]
    lines += robustness_table(task, runs)
    lines += stability_table(task, runs)
    for (scenario, algorithm), run in runs.items():
        cfg = configs[(scenario, algorithm)]
        thr, thr2 = cfg.task.success_threshold, cfg.task.success_threshold_loose
        lines += [f"## Scenario {scenario}, algorithm {algorithm}", "",
                  f"{cfg.iterations} iterations, {cfg.num_samples} samples/condition, T = {cfg.task.T}; "
                  f"wall time {run['wall_s']:.1f} s ({format_timing(run)}).", ""]
        curves = dict(_curves(run))
        header = "| iteration | " + " | ".join(
            f"{_label(algorithm, c)} MSE mean (min–max)" for c in curves) + " | sample cost |"
        lines += [header, "|" + "---|" * (len(curves) + 2)]
        cost = run["history"]["sample_cost"].mean(axis=-1)
        for i in range(cost.shape[0]):
            cells = [f"{v[i].mean():.4g} ({v[i].min():.3g}–{v[i].max():.3g})" for v in curves.values()]
            lines.append(f"| {i + 1} | " + " | ".join(cells) + f" | {cost[i].mean():.2f} |")
        lines.append("")
        speed = learning_speed_line(algorithm, run, thr)
        if speed is not None:
            lines.append(speed)
        for curve, v in curves.items():
            final = v[-1]
            lines.append(f"- {_label(algorithm, curve)}: final-state MSE < {thr} at the last iteration "
                         f"for {int((final < thr).sum())}/{len(final)} seeds "
                         f"(< {thr2}: {int((final < thr2).sum())}/{len(final)}).")
        failed = run["history"].get("seed_failed")
        if failed is not None and failed[-1].any():
            first = failed.argmax(axis=0)  # [S]: the iteration index at which each seed failed
            lines.append("- Failed seeds, frozen at their last good iteration (its rows and policy count "
                         "for them from then on): " + ", ".join(
                             f"seed {seeds[i]} in iteration {first[i] + 1}" for i in np.flatnonzero(failed[-1])) + ".")
        for name, ok in final_extra(cfg, run["history"]).items():
            per_cond = ok[-1].sum(axis=0)  # [M]: seeds at the last iteration
            conds = task.scenarios[scenario]
            lines.append(f"- {name.replace('_', ' ')} at the last iteration: " + ", ".join(
                f"{c} {int(k)}/{ok.shape[1]} seeds" for c, k in zip(conds, per_cond)) + ".")
        lines.append("")
    path.write_text("\n".join(lines))


def success_iterations(run, threshold: float) -> dict:
    """Learning speed per seed: the first iteration (1-based) from which the noiseless execution's
    final-state MSE is below ``threshold`` from every training condition at that and every later
    iteration, for the LQR base layer ("lqr") and the global policy ("policy"); iterations + 1 for
    a seed that never gets there (counted so: a conservative value). Returns {"lqr", "policy",
    "lag" (policy − lqr, with a policy): [S] int}."""
    out = {}
    for curve, name in (("final_state_mse_lqr", "lqr"), ("final_state_mse_policy", "policy")):
        h = run["history"].get(curve)
        if h is None:
            continue
        ok = (np.asarray(h) < threshold).all(axis=-1)  # [iterations, S]: every condition succeeds
        stays = np.flip(np.logical_and.accumulate(np.flip(ok, 0), axis=0), 0)  # ok at i and later
        out[name] = np.where(stays.any(axis=0), stays.argmax(axis=0) + 1, ok.shape[0] + 1)
    if "policy" in out:
        out["lag"] = out["policy"] - out["lqr"]
    return out


def learning_speed_line(algorithm: str, run, threshold: float) -> str | None:
    """One summary line: the base layer's and the policy's success iterations and the policy's
    lag behind its base layer, each as mean [95 % CI] over seeds (``gmr_jax.stats``)."""
    it = success_iterations(run, threshold)
    if "policy" not in it:
        return None
    n = np.asarray(run["history"]["final_state_mse_lqr"]).shape[0]
    fmt = lambda v: stats.over_seeds(v).format()  # noqa: E731
    return (f"- Learning speed (first iteration from which the final-state MSE from every training "
            f"condition stays below {threshold}; mean [95 % CI], IQM (range) over seeds, 'never' "
            f"counted as {n + 1}): LQR base layer {fmt(it['lqr'])}; {_label(algorithm, 'final_state_mse_policy')} "
            f"{fmt(it['policy'])}; the policy's lag {fmt(it['lag'])} iterations"
            + (" (paper: GMR imitates the base layer after about 2 iterations, MDGPS 2–4× later)."
               if algorithm in ("gmr", "mdgps") else "."))


def robustness_stats(runs) -> dict:
    """{"scenario/algorithm": {"success": SeedStats, "success_loose": …, <extra>: …}} of the
    runs with a robustness evaluation: successes out of the random states, over seeds."""
    out = {}
    for (s, a), run in runs.items():
        rob = run.get("robustness")
        if rob is None:
            continue
        row = {k: stats.over_seeds(np.asarray(rob[k]).sum(axis=-1)) for k in ("success", "success_loose")}
        for name, ok in rob.get("extra", {}).items():
            row[name] = stats.over_seeds(np.asarray(ok).sum(axis=-1))
        out[f"{s}/{a}"] = row
    return out


def stability_table(task: tasks.Task, runs) -> list[str]:
    """Markdown rows: the trained policies' closed-loop stability (``gmr_jax.stability``) beside
    their successes, each as mean [95 % CI], IQM (range) over seeds."""
    keys = [k for k in sorted(runs, key=lambda k: (len(k[0]), k)) if "stability" in runs[k]]
    if not keys:
        return []
    lines = ["## Stability of the trained policies' closed loop", "",
             "ρ = spectral radius of the one-control-step Jacobian of x' = f(x, u(x)) (plant by central "
             "differences of C MuJoCo, policy by autodiff; ρ < 1: small perturbations shrink locally). "
             "Contracting: the fraction of the states along the noiseless rollouts from the random "
             "states (every 5th control step) with ρ < 1.", "",
             "| trained on | algorithm | ρ at the target | contracting states | successes (of 50) |",
             "|---|---|---|---|---|"]
    for s, a in keys:
        st, rob = runs[(s, a)]["stability"], runs[(s, a)]["robustness"]
        lines.append(f"| {', '.join(task.scenarios[s])} | {a.upper()} | "
                     f"{stats.over_seeds(st['target_radius']).format(3)} | "
                     f"{stats.over_seeds(st['contracting']).format(2)} | "
                     f"{stats.over_seeds(np.asarray(rob['success']).sum(axis=-1)).format()} |")
    lines.append("")
    return lines


def robustness_table(task: tasks.Task, runs) -> list[str]:
    """Markdown rows: our successes (mean with its 95 % bootstrap interval over seeds, IQM and
    range; gmr_jax.stats) next to the paper's."""
    scenarios = sorted({s for s, a in runs if "robustness" in runs[(s, a)]}, key=lambda s: (len(s), s))
    if not scenarios:
        return []
    algs = [a for a in ("mdgps", "gmr") if any((s, a) in runs for s in scenarios)]
    head = "| trained on | " + " | ".join(
        f"{a.upper()} ours (mean [95 % CI], IQM (range)) | {a.upper()} paper" for a in algs) + " |"
    lines = ["## Robustness: 50 random initial states, success = final-state MSE < 0.01", "",
             head, "|---|" + "---|---|" * len(algs)]
    for scen in scenarios:
        cells = []
        for a in algs:
            run = runs.get((scen, a))
            if run is None or "robustness" not in run:
                cells += ["–", "–"]
                continue
            n = run["robustness"]["success"].shape[-1]
            paper = task.paper_robustness.get((scen, a))
            cells += [f"{stats.over_seeds(run['robustness']['success'].sum(axis=-1)).format()} of {n}",
                      "–" if paper is None else f"{paper}/50"]
        lines.append(f"| {', '.join(task.scenarios[scen])} | " + " | ".join(cells) + " |")
    lines.append("")
    lines.append("Loose threshold 0.1 (the paper's text): " + "; ".join(
        f"{s}/{a}: {runs[(s, a)]['robustness']['success_loose'].sum(axis=-1).mean():.1f}"
        for s in scenarios for a in algs if (s, a) in runs and "robustness" in runs[(s, a)]) + ".")
    names = sorted({n for r in runs.values() for n in r.get("robustness", {}).get("extra", {})})
    for name in names:
        lines.append(f"Also {name} (mean over seeds): " + "; ".join(
            f"{s}/{a}: {np.asarray(runs[(s, a)]['robustness']['extra'][name]).sum(axis=-1).mean():.1f}"
            for s in scenarios for a in algs if (s, a) in runs and "robustness" in runs[(s, a)]) + ".")
    lines.append("")
    return lines


def plot_robustness(path: pathlib.Path, configs, runs) -> None:
    """End-effector paths of the policy from the 50 random states (first seed; green success,
    red failure, black the training conditions) and the disturbance sweep (mean over seeds)."""
    keys = [k for k in runs if "robustness" in runs[k]]
    if not keys:
        return
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(keys) + 1, figsize=(4.6 * (len(keys) + 1), 4.4), squeeze=False)
    for ax, key in zip(axes[0], keys):
        rob = runs[key]["robustness"]
        ee, ok = rob["ee"][0], rob["success"][0]
        for p, good in zip(ee, ok):
            ax.plot(p[:, 0], p[:, 1], color="tab:green" if good else "tab:red", lw=0.7, alpha=0.7)
            ax.plot(p[0, 0], p[0, 1], ".", color="grey", ms=3)
        train = runs[key]["history"]["policy_eval_ee"][-1, 0]  # [M, T, 3]
        for p in train:
            ax.plot(p[:, 0], p[:, 1], color="k", lw=2)
        ax.set_title(f"{key[0]} / {key[1].upper()}: {int(ok.sum())}/{ok.size} succeed (seed 0)")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(True, alpha=0.3)
    ax = axes[0, -1]
    for key in keys:
        sw = runs[key]["sweep"]
        rate = np.asarray(sw["success_rate"])  # [seeds, R]
        ax.errorbar(sw["radii"], rate.mean(axis=0), yerr=rate.std(axis=0), marker="o", capsize=3,
                    label=f"{key[0]} / {key[1].upper()}")
    ax.set_xlabel("disturbance of the training joint angles (rad)")
    ax.set_ylabel("success rate (MSE < 0.01)")
    ax.set_ylim(-0.05, 1.05)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("disturbance sweep (mean ± std over seeds)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# The study's figures as plot_all draws them: (function, file in the study's folder).
FIGURES = ((plot_learning_curves, "learning_curves.png"), (plot_paths, "paths.png"),
           (plot_robustness, "robustness.png"), (plot_seed_successes, "seeds.png"))
