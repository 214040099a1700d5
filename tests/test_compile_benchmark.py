"""benchmarks.compile's selection of programs."""

from benchmarks import compile as compile_benchmark


def test_only_splits_at_commas_but_keeps_the_names_that_hold_one():
    assert compile_benchmark.selection("") == set()
    assert compile_benchmark.selection("train") == {"train"}
    assert compile_benchmark.selection("sample,C-step (η search)") == {"sample", "C-step (η search)"}
    assert compile_benchmark.selection("train, 256 seeds,S-step") == {"train, 256 seeds", "S-step"}
