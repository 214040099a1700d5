"""A command's timeline (gmr_jax.timeline, benchmarks.timeline): marks of several processes in
one file, nothing without the variable, and the per-run steps computed from the marks."""

import os
import subprocess
import sys

import pytest

from benchmarks import timeline as timeline_benchmark
from gmr_jax import timeline


def test_marks_of_several_processes_share_one_file(tmp_path, monkeypatch):
    path = tmp_path / "timeline"
    monkeypatch.delenv(timeline.VARIABLE, raising=False)
    timeline.mark("nothing")
    assert not path.exists() and timeline.environment() == {}
    monkeypatch.setenv(timeline.VARIABLE, str(path))
    assert timeline.environment() == {timeline.VARIABLE: str(path)}
    timeline.mark("command start", at=100.25)
    code = "from gmr_jax import timeline; timeline.mark('child mark with spaces')"
    subprocess.run([sys.executable, "-c", code], check=True,
                   env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    timeline.mark("command end")
    marks = timeline.read(path)
    assert [label for _, _, label in marks] == ["command start", "child mark with spaces", "command end"]
    assert marks[0][0] == 100.25 and marks[0][1] == marks[2][1] == os.getpid() != marks[1][1]
    assert marks[1][0] <= marks[2][0]


def test_the_benchmark_times_each_run_from_its_marks(tmp_path, capsys):
    lines = ["10.0 1 command start", "11.5 1 process asked A/gmr", "12.0 1 process started A/gmr",
             "12.1 7 process entry A/gmr", "13.1 7 run clock A/gmr", "20.1 7 run end A/gmr",
             "20.2 1 result received A/gmr", "11.6 1 process asked B/gmr", "21.0 1 command end"]
    path = tmp_path / "timeline"
    path.write_text("\n".join(lines) + "\n")
    result = timeline_benchmark.summary(timeline.read(path))
    assert result["marks"][0] == [0.0, 1, "command start"] and result["marks"][-1] == [11.0, 1, "command end"]
    steps = result["runs"]["A/gmr"]
    assert list(steps) == ["process asked → process started", "process started → process entry",
                           "process entry → run clock", "run clock → run end", "run end → result received"]
    assert [round(s, 6) for s in steps.values()] == [0.5, 0.1, 1.0, 7.0, 0.1]
    assert "B/gmr" not in result["runs"]  # asked, never started: no step
    assert timeline_benchmark.main([str(path), "--out", str(tmp_path / "t.json")]) == 0
    assert "A/gmr: process asked → process started 0.50 s" in capsys.readouterr().out
    (tmp_path / "empty").write_text("")
    assert timeline_benchmark.main([str(tmp_path / "empty")]) == 2
    assert capsys.readouterr().err.strip().endswith("the timeline holds no marks")
    with pytest.raises(ValueError):
        timeline_benchmark.summary([])
