"""The study report (experiments.report) from small synthetic run results: results.json, the
summary's robustness table against the paper, the learning speed, and the figures."""

import json
import os

import numpy as np
import pytest

from experiments import report
from gmr_jax import config

ITERS, SEEDS, T, N, STATES = 3, 2, 5, 2, 50


def fake_run(M: int, successes, policy=True, seed=0):
    rng = np.random.default_rng(seed)
    shape = (ITERS, SEEDS, M)
    lqr_mse = np.array([1.0, 0.1, 0.01])[:, None, None] * np.ones(shape)
    h = {"final_state_mse_lqr": lqr_mse, "sample_cost": rng.uniform(1, 2, shape),
         "kl": rng.uniform(size=shape), "eta": rng.uniform(size=shape), "step_mult": np.ones(shape),
         "epsilon": np.ones(shape), "sample_costs": rng.uniform(size=shape + (N,)),
         "eval_ee": rng.normal(size=shape + (T, 3))}
    run = {"history": h, "wall_s": 1.5, "timing": {"compile_s": 1.0}, "iteration_s": [0.1] * ITERS}
    if policy:
        # the policy reaches 3× the base layer's MSE at iteration 1, then 1.5×: imitation from 2
        h["final_state_mse_policy"] = lqr_mse * np.array([3.0, 1.5, 1.5])[:, None, None]
        h["policy_eval_ee"] = rng.normal(size=shape + (T, 3))
        success = np.zeros((SEEDS, STATES), bool)
        for i, k in enumerate(successes):
            success[i, :k] = True
        run["robustness"] = {"success": success, "success_loose": success | True,
                             "mse": rng.uniform(size=(SEEDS, STATES)), "distance": rng.uniform(size=(SEEDS, STATES)),
                             "ee": rng.normal(size=(SEEDS, STATES, T, 3)), "extra": {}}
        run["stability"] = {"target_radius": np.array([0.9, 1.1]), "contracting": np.array([0.5, 0.7]),
                            "radius": rng.uniform(0.5, 1.5, size=(SEEDS, STATES, 4))}
        run["sweep"] = {"radii": [0.0, 1.0], "success_rate": np.array([[1.0, 0.5], [1.0, 0.3]]),
                        "success_rate_loose": np.ones((SEEDS, 2))}
    return run


def test_results_summary_and_figures(tmp_path, monkeypatch):
    configs = {(s, a): config.reach(s, a, iterations=ITERS, task__T=T) for s in ("A", "AB") for a in ("gmr", "mdgps")}
    runs = {("A", "gmr"): fake_run(1, [50, 27]), ("A", "mdgps"): fake_run(1, [0, 2], seed=1),
            ("AB", "gmr"): fake_run(2, [50, 50], seed=2), ("AB", "mdgps"): fake_run(2, [3, 4], seed=3)}
    results = report.write_results(tmp_path, configs, runs, [0, 1], "cpu: test", 12.0, command_s=13.0, start_s=0.5)
    again = json.loads((tmp_path / "results.json").read_text())
    assert again == json.loads(json.dumps(results))
    assert (again["total_wall_s"], again["command_wall_s"], again["startup_s"]) == (12.0, 13.0, 0.5)
    recs = {(r["scenario"], r["algorithm"], r["seed"]): r for r in again["runs"]}
    assert recs[("A", "gmr", 1)]["robustness"]["successes"] == 27
    assert recs[("A", "gmr", 1)]["robustness"]["successes_loose"] == 50
    assert np.allclose(recs[("AB", "mdgps", 0)]["final_state_mse"], [3.0, 0.15, 0.015])  # the policy's
    report.write_summary(tmp_path / "summary.md", configs, runs, [0, 1], "cpu: test", 12.0, results)
    text = (tmp_path / "summary.md").read_text()
    assert text.startswith("# Reach study summary")
    # Two seeds: a quarter of the bootstrap resamples repeat the smaller value, a quarter the
    # larger, so the 95 % percentile interval is [min, max]; the IQM of two values is their mean.
    assert ("| A | 1.0 [0.0, 2.0], IQM 1.0 (0–2) of 50 | 12/50 | 38.5 [27.0, 50.0], IQM 38.5 (27–50) of 50 "
            "| 50/50 |") in text
    assert ("| A, B | 3.5 [3.0, 4.0], IQM 3.5 (3–4) of 50 | 50/50 | 50.0 [50.0, 50.0], IQM 50.0 (50–50) of 50 "
            "| 50/50 |") in text
    st = again["robustness_stats"]["A/gmr"]["success"]
    assert (st["n"], st["mean"], st["low"], st["high"], st["iqm"]) == (2, 38.5, 27.0, 50.0, 38.5)
    assert "13.0 s for the whole command" in text
    # ρ 0.9 and 1.1: mean 1.000, interval [0.900, 1.100]; contracting 0.5 and 0.7; successes 50, 27
    assert ("| A | GMR | 1.000 [0.900, 1.100], IQM 1.000 (0.900–1.100) | 0.60 [0.50, 0.70], IQM 0.60 (0.50–0.70) | "
            "38.5 [27.0, 50.0], IQM 38.5 (27–50) |") in text
    assert recs[("A", "gmr", 1)]["stability"]["target_radius"] == 1.1
    assert text.count("- Learning speed") == 4
    assert again["learning_speed"]["A/gmr"] == {"lqr": [4, 4], "policy": [4, 4], "lag": [0, 0]}  # never below 0.01
    report.plot_all(tmp_path, configs, runs)
    names = [name for _, name in report.FIGURES]
    assert names == ["learning_curves.png", "paths.png", "robustness.png", "seeds.png"]
    for name in names:
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", name
    # drawn by processes of their own, as on a host with FIGURE_WORKERS_MIN_CORES cores: the same files
    import concurrent.futures

    monkeypatch.setattr(report.sim, "host_cores", lambda: report.FIGURE_WORKERS_MIN_CORES - 1)
    assert report.figure_workers() is None
    monkeypatch.setattr(report.sim, "host_cores", lambda: report.FIGURE_WORKERS_MIN_CORES)
    workers = report.figure_workers()
    try:
        for where in ("apart", "broken"):
            (tmp_path / where).mkdir()
        report.plot_all(tmp_path / "apart", configs, runs, workers)
        with pytest.raises(FileNotFoundError):  # a figure's error is raised here
            report.plot_all(tmp_path / "missing", configs, runs, workers)
    finally:
        workers.shutdown()

    class Broken(concurrent.futures.Executor):  # a worker has died
        def submit(self, fn, /, *args, **kwargs):
            raise concurrent.futures.process.BrokenProcessPool("a worker died")
    report.plot_all(tmp_path / "broken", configs, runs, Broken())  # drawn here instead
    for name in names:
        for where in ("apart", "broken"):
            assert (tmp_path / where / name).read_bytes() == (tmp_path / name).read_bytes(), (where, name)


def test_figure_workers_end_with_the_command_that_started_them(tmp_path):
    """A command that dies without shutting its figure workers down (SIGKILL, a crash) takes
    them with it: they watch it, although the server they fork from ignores SIGTERM."""
    import subprocess
    import sys
    import time

    code = ("import os; from experiments import report; report.sim.host_cores = lambda: 8; "
            "w = report.figure_workers(); [w.submit(int).result() for _ in range(8)]; "
            "print(' '.join(str(p) for p in w._processes), flush=True); os._exit(0)")
    with open(tmp_path / "pids", "w") as out:  # a file: a pipe would wait for the workers too
        subprocess.run([sys.executable, "-c", code], stdout=out, check=True, timeout=300)
    pids = [int(p) for p in (tmp_path / "pids").read_text().split()]
    assert len(pids) == len(report.FIGURES)

    def alive(pid):
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return False
        try:
            with open(f"/proc/{pid}/stat") as f:  # a zombie has ended
                return f.read().rsplit(")", 1)[1].split()[0] != "Z"
        except FileNotFoundError:
            return False
    deadline = time.monotonic() + 30
    while any(alive(p) for p in pids) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not [p for p in pids if alive(p)]


def test_compare_names_the_differing_fields():
    from experiments import compare

    rec = {"scenario": "A", "algorithm": "gmr", "seed": 0, "kl": [1.0, 2.0], "robustness": {"successes": 50}}
    same = {("A", "gmr", 0): rec}
    assert compare.compare(same, {("A", "gmr", 0): dict(rec)}) == []
    other = {("A", "gmr", 0): dict(rec, kl=[1.0, 2.2]), ("A", "gmr", 1): rec}
    lines = compare.compare(same, other)
    assert lines[0] == "only in the second: ('A', 'gmr', 1)"
    assert lines[1] == "A/gmr/0 kl: largest relative difference 0.1"


def test_intervals_cli_reads_a_results_json(tmp_path, capsys):
    from experiments import intervals

    lqr = [[[0.5], [0.005], [0.002]], [[0.5], [0.02], [0.005]]]  # per seed [iterations, M]
    pol = [[[0.5], [0.02], [0.005]], [[0.5], [0.5], [0.005]]]
    recs = [{"scenario": "A", "algorithm": "gmr", "seed": s, "robustness": {"successes": k, "states": 50},
             "final_state_mse_lqr_per_condition": lqr[s], "final_state_mse_policy_per_condition": pol[s]}
            for s, k in enumerate([50, 27])]
    path = tmp_path / "results.json"
    path.write_text(json.dumps({"runs": recs}))
    assert intervals.main([str(path)]) == 0
    out = capsys.readouterr().out
    assert "| A/gmr | successes | 2 | 38.5 [27.0, 50.0], IQM 38.5 (27–50) |" in out
    assert "| A/gmr | learning speed: lqr | 2 | 2.5 [2.0, 3.0], IQM 2.5 (2–3) |" in out
    assert "| A/gmr | learning speed: lag | 2 | 0.5 [0.0, 1.0], IQM 0.5 (0–1) |" in out  # 3−2, 3−3
    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(SystemExit) as exc:
        intervals.main([str(tmp_path / "bad.json")])
    assert exc.value.code == 2 and "cannot read a results.json" in capsys.readouterr().err


def test_final_states_cli_names_a_folder_that_is_not_a_run(tmp_path, capsys):
    from experiments import final_states

    with pytest.raises(SystemExit) as exc:
        final_states.main([str(tmp_path), "C_gmr"])
    assert exc.value.code == 2 and "C_gmr: not a run folder of a study" in capsys.readouterr().err


def test_success_iterations_need_every_condition_at_every_later_iteration():
    lqr = np.array([[[0.5], [0.5]], [[0.005], [0.02]], [[0.002], [0.005]]])  # [iterations, seeds, M]
    # seed 0 succeeds from 3 (condition 2 only then); seed 1 at 1 but not at 2 and 3: never (4)
    policy = np.concatenate([np.array([[[0.5], [0.005]], [[0.02], [0.5]], [[0.005], [0.02]]]),
                             np.array([[[0.001], [0.001]], [[0.5], [0.001]], [[0.001], [0.001]]])], axis=-1)
    run = {"history": {"final_state_mse_lqr": lqr, "final_state_mse_policy": policy}}
    it = report.success_iterations(run, 0.01)
    np.testing.assert_array_equal(it["lqr"], [2, 3])
    np.testing.assert_array_equal(it["policy"], [3, 4])
    line = report.learning_speed_line("gmr", run, 0.01)
    # the lag per seed is 1 and 1: mean 1.0 with the interval [1, 1]
    assert "the policy's lag 1.0 [1.0, 1.0]" in line and "counted as 4" in line
    assert report.learning_speed_line("lqr", {"history": {"final_state_mse_lqr": lqr}}, 0.01) is None


def test_final_states_scene_without_contacts(tmp_path):
    import mujoco

    from experiments import final_states
    from gmr_jax import sim as sim_lib

    cfg = config.make("block_in_hole", "C", "gmr")
    free = final_states.without_contacts(cfg, tmp_path)
    m0, m1 = sim_lib.make_sim(cfg.sim).model, sim_lib.make_sim(free.sim).model
    assert m1.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT
    assert not m0.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT
    # the same plant otherwise: bodies, masses, joints and actuators
    assert (m1.nq, m1.nu, m1.nbody, m1.npair) == (m0.nq, m0.nu, m0.nbody, m0.npair)
    np.testing.assert_array_equal(m1.body_mass, m0.body_mass)
    np.testing.assert_array_equal(m1.actuator_ctrlrange, m0.actuator_ctrlrange)


def test_read_results_takes_json_gzip_and_folders(tmp_path):
    import gzip
    import json

    data = {"runs": [{"scenario": "A", "algorithm": "gmr", "seed": 0, "x": [1.5, 2.0]}]}
    (tmp_path / "plain").mkdir()
    (tmp_path / "plain" / "results.json").write_text(json.dumps(data))
    (tmp_path / "packed").mkdir()
    (tmp_path / "packed" / "results.json.gz").write_bytes(gzip.compress(json.dumps(data).encode()))
    for path in (tmp_path / "plain", tmp_path / "plain" / "results.json", tmp_path / "packed",
                 tmp_path / "packed" / "results.json.gz"):
        assert report.read_results(path) == data
    with pytest.raises(OSError):
        report.read_results(tmp_path / "missing")


def test_compact_table_has_one_row_per_run_with_the_seed_statistics(tmp_path):
    from experiments import intervals
    from gmr_jax import stats

    rng = np.random.default_rng(3)
    runs = [{"scenario": sc, "algorithm": "gmr", "seed": s,
             "robustness": {"successes": int(rng.integers(0, 51)), "successes_loose": 50},
             "stability": {"contracting": float(rng.uniform())}}
            for sc in ("A", "AB") for s in range(5)]
    rows = intervals.compact_rows("cell", {"runs": runs})
    assert len(rows) == 2
    a = [r for r in runs if r["scenario"] == "A"]
    want = stats.over_seeds([r["robustness"]["successes"] for r in a]).format(1)
    assert rows[0].startswith("| cell | A/gmr | 5 | " + want + " | ")
    assert stats.over_seeds([r["stability"]["contracting"] for r in a]).format(2) in rows[0]
    (tmp_path / "x" / "one").mkdir(parents=True)
    (tmp_path / "x" / "two").mkdir()
    assert intervals.labels([tmp_path / "x" / "one", tmp_path / "x" / "two" / "results.json"]) == ["one", "two"]


def test_distance_table_bins_the_states_and_counts_both_thresholds():
    from experiments import intervals

    dist = [0.5, 3.5, 3.7, 9.0]
    runs = [{"scenario": "A", "algorithm": "mdgps", "seed": s,
             "robustness": {"distance": dist, "mse": [0.001, 0.05, 0.5, 0.001 if s == 0 else 0.2]}}
            for s in range(2)]
    (row,) = intervals.distance_rows("cell", {"runs": runs}, bins=(0.0, 3.0, 4.0, 8.0, np.inf))
    # [0, 3): one state, both seeds < 0.01; [3, 4): two states, none < 0.01, half < 0.1;
    # [4, 8): empty; [8, inf): one state, one seed of two < 0.01 and < 0.1.
    assert row == "| cell | A/mdgps | 2 | 1: 100 % / 100 % | 2: 0 % / 50 % | – | 1: 50 % / 50 % |"


def test_every_ablation_cell_is_a_valid_configuration_of_the_cli():
    """experiments/ablations.sh's cells ("NAME=ARGS") parse and validate as the reach CLI's runs,
    and each changes the configuration (a misspelt field would end the CLI with a usage error)."""
    import pathlib
    import re
    import shlex

    from experiments import cli

    script = (pathlib.Path(__file__).parents[1] / "experiments" / "ablations.sh").read_text()
    blocks = {alg: re.search(rf"{alg.upper()}_CELLS=\((.*?)\n\)", script, re.S).group(1)
              for alg in ("gmr", "mdgps")}
    seen = 0
    for alg, block in blocks.items():
        base = cli.parse_args("reach", ["--algorithm", alg, "--scenario", "A,AB"]).configs
        for name, args in re.findall(r'"([\w.]+)=(.*?)"', block):
            cfgs = cli.parse_args("reach", ["--algorithm", alg, "--scenario", "A,AB", *shlex.split(args)]).configs
            assert set(cfgs) == {("A", alg), ("AB", alg)}
            assert (cfgs == base) == (args == ""), (alg, name)
            seen += 1
    assert seen >= 10


def test_host_cpu_reads_the_first_processor_of_cpuinfo():
    """config.json's ``host_cpu``: the first processor block of /proc/cpuinfo, AVX-512 from its flags."""
    from experiments import cli

    text = ("processor\t: 0\nvendor_id\t: AuthenticAMD\ncpu family\t: 26\nmodel\t\t: 2\n"
            "model name\t: AMD EPYC 9B45\nflags\t\t: fpu sse2 avx2 avx512f avx512bw\n\n"
            "processor\t: 1\ncpu family\t: 25\nmodel name\t: other\nflags\t\t: fpu\n")
    assert cli.host_cpu(text) == {"model": "AMD EPYC 9B45", "family": "26", "model_number": "2",
                                  "avx512": True}
    intel = "processor\t: 0\ncpu family\t: 6\nmodel\t\t: 85\nmodel name\t: Intel Xeon\nflags\t\t: sse2 avx2\n"
    assert cli.host_cpu(intel)["avx512"] is False
    assert cli.host_cpu(intel)["model"] == "Intel Xeon"
    # this machine's, whatever it is: a model name is always there
    assert isinstance(cli.host_cpu()["model"], str)
