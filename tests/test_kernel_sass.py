"""benchmarks.kernel_sass's text processing (the compile itself needs the triton package, which
gmr-jax does not depend on): the file encoding of IR locations round-trips through the SASS
line records, instructions are attributed to the line record before them, and ptxas's
statistics are read."""

import pytest

from benchmarks import kernel_sass as ks

IR = '''#loc1 = loc("/x/gmr_jax/policies/gmr_kernel.py":331:17 to :69)
#loc2 = loc("/x/gmr_jax/adam.py":22:5)
#loc3 = loc("/x/gmr_jax/policies/gmr_kernel.py":12:3)
%0 = tt.dot %a, %b loc(#loc1)
'''


def test_encode_files_renumbers_lines_per_file():
    ir, files = ks.encode_files(IR)
    assert files == ["/x/gmr_jax/policies/gmr_kernel.py", "/x/gmr_jax/adam.py"]
    stride = ks.FILE_STRIDE
    assert f'"/x/gmr_jax/policies/gmr_kernel.py":{stride + 331}:17 to :69' in ir
    assert f'"/x/gmr_jax/adam.py":{2 * stride + 22}:5' in ir
    assert f'"/x/gmr_jax/policies/gmr_kernel.py":{stride + 12}:3' in ir
    assert ir.count("loc(") == IR.count("loc(")


def test_sass_by_line_attributes_instructions_to_the_preceding_line_record():
    _, files = ks.encode_files(IR)
    stride = ks.FILE_STRIDE
    sass = "\n".join([
        "        /*0000*/                   MOV R1, c[0x0][0x28] ;",
        f'	//## File "<unknown>", line {stride + 331}',
        "        /*0010*/                   HMMA.1688.F32.TF32 R4, R8, R12, R4 ;",
        "        /*0020*/                   STL [R1+0x10], R4 ;",
        "        /*0030*/              @!P0 LDL R5, [R1+0x10] ;",
        f'	//## File "<unknown>", line {2 * stride + 22}',
        "        /*0040*/                   FFMA R2, R3, R4, R2 ;",
        "        /*0050*/                   FFMA R2, R3, R4, R2 ;",
        "        /*0060*/                   BAR.SYNC.DEFER_BLOCKING 0x0 ;",
    ])
    counts = ks.sass_by_line(sass, files)
    assert counts["opcodes"] == {"FFMA": 2, "MOV": 1, "HMMA": 1, "STL": 1, "LDL": 1, "BAR": 1}
    assert counts["lines"] == {"?": {"instructions": 1},
                               "gmr_kernel.py:331": {"instructions": 3, "STL": 1, "LDL": 1},
                               "adam.py:22": {"instructions": 3}}


def test_ptxas_stats():
    text = ("ptxas info    : Function properties for gmr_sstep\n"
            "    3664 bytes stack frame, 5012 bytes spill stores, 5796 bytes spill loads\n"
            "ptxas info    : Used 255 registers, used 1 barriers, 3664 bytes cumulative stack size\n")
    assert ks.ptxas_stats(text) == {"registers": 255, "stack_bytes": 3664, "spill_store_bytes": 5012,
                                    "spill_load_bytes": 5796}
    with pytest.raises(ValueError, match="no register or stack line"):
        ks.ptxas_stats("ptxas fatal : Unsupported .version 9.4")
