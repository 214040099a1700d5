"""benchmarks.compile's selection of programs."""

import pytest

from benchmarks import compile as compile_benchmark


def test_only_splits_at_commas_but_keeps_the_names_that_hold_one():
    assert compile_benchmark.selection("") == set()
    assert compile_benchmark.selection("train") == {"train"}
    assert compile_benchmark.selection("sample,C-step (η search)") == {"sample", "C-step (η search)"}
    assert compile_benchmark.selection("train, 256 seeds,S-step") == {"train, 256 seeds", "S-step"}


def test_only_that_names_no_program_is_an_error_naming_them():
    programs = [("train", None, ()), ("train, 256 seeds", None, ()), ("S-step", None, ())]
    assert compile_benchmark.chosen(programs, "") == programs
    assert [n for n, *_ in compile_benchmark.chosen(programs, "train, 256 seeds")] == ["train, 256 seeds"]
    assert [n for n, *_ in compile_benchmark.chosen(programs, "train")] == ["train", "train, 256 seeds"]
    with pytest.raises(ValueError, match=r"names no program; the programs: train; train, 256 seeds; S-step"):
        compile_benchmark.chosen(programs, "sample, train")
