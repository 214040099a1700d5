"""benchmarks.soak: the per-chunk rows add up to the final row, and the JSON is written per chunk."""

import json

from benchmarks import soak
from gmr_jax import config, sharding


def test_chunk_rows_accumulate_to_the_final_row(tmp_path):
    cfg = config.reach("A", "mdgps", sim__backend="mujoco", iterations=1, task__T=8, sstep__epochs=2)
    rows = []
    final = soak.soak_run(cfg, 3, 2, sharding.seed_mesh(None), first_seed=5, on_chunk=rows.append)
    assert [r["seeds"] for r in rows] == [2, 3]  # a padded last chunk counts only its real seeds
    assert rows[-1] == final
    assert final["first_seed"] == 5 and final["failed"] == 0 and final["nonfinite"] == 0
    assert final["failed"] + final["nonfinite"] <= final["seeds"]


def test_main_writes_the_json(tmp_path):
    out = tmp_path / "soak.json"
    soak.main(["--seeds", "2", "--chunk", "2", "--runs", "A/mdgps", "--backend", "mujoco",
               "--set", "iterations=1", "--set", "task__T=8", "--set", "sstep__epochs=2", "--out", str(out)])
    data = json.loads(out.read_text())
    assert data["runs"]["A/mdgps"]["seeds"] == 2
    assert data["environment"]["precision"] == "float64" and data["args"]["first_seed"] == 0
