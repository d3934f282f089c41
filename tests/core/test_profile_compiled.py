"""The profiler's harness (``benchmarks/profile_compiled.py``): the map it gives perf of numba's machine code,
and its reading of perf's report. perf itself is not run here (it may be missing or not permitted)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))

import profile_compiled as P  # noqa: E402

SURFACE_HITS = (
    "_ZN5addon4core7kernels12surface_hitsB4v106B56c8tJTIeFIjxB2IKSgI4CrvQCk0Z4yRYcWsBAK4JJIqUWsIgmAA_3d_3dE5Tuple"
)
WHERE = "_ZN5addon4core7formula13_where_scalar12_3clocals_3e12_3clambda_3eB3v75B68c8tJTC_2fWwGaMLSgd6CjA4xE"


def test_readable_names_a_kernel_and_a_formulas_scalar_operation():
    assert P.readable(SURFACE_HITS) == "surface_hits"
    assert P.readable(WHERE) == "where<lambda>"
    assert P.readable("__sincos_fma") == "__sincos_fma"  # not numba's: as it is


REPORT = """\
# Samples: 25K of event 'cpu-clock:ppp'
#
# Overhead;Shared Object;Symbol
#
     4.72%;[JIT] tid 19782;[.] surface_hits
     2.00%;[JIT] tid 19782;[.] decoded_brdf:rough_dielectric_eval_pdf
     1.50%;[JIT] tid 19782;[.] 0x00007f46275ca069
    23.50%;libembree4-4aef3270.so.4;[.] 0x0000000001e52798
    14.98%;onnxruntime_pybind11_state.cpython-311-x86_64-linux-gnu.so;[.] 0x0000000000990d4a
     2.61%;_pcg64.cpython-311-x86_64-linux-gnu.so;[.] __pyx_f_5numpy_6random_6_pcg64_pcg64_double
     1.91%;_multiarray_umath.cpython-311-x86_64-linux-gnu.so;[.] DOUBLE_multiply_FMA3__AVX2
     1.53%;libm.so.6;[.] __sincos_fma
     1.00%;[kernel.kallsyms];[k] clear_page_erms
"""


def test_the_report_is_read_and_grouped_by_part():
    rows = P.read_report(REPORT)
    assert len(rows) == 9 and rows[0] == (4.72, "[JIT] tid 19782", "surface_hits")
    parts = {part: (share, symbols) for part, share, symbols in P.by_part(rows)}
    assert parts["rays (embree)"][0] == 23.5
    assert parts["networks (ONNX Runtime)"][0] == 14.98
    assert parts["compiled `surface_hits`"][0] == 4.72
    assert parts["compiled `decoded_brdf`"] == (2.0, [(2.0, "decoded_brdf:rough_dielectric_eval_pdf")])
    assert parts["compiled code without a symbol"][0] == 1.5
    assert parts["random numbers (numpy)"][0] == 2.61 and parts["numpy"][0] == 1.91
    assert parts["C maths library (called by the loops)"][0] == 1.53
    assert parts["the system (page faults, scheduling)"][0] == 1.0
    assert [share for _, share, _ in P.by_part(rows)] == sorted((s for _, s, _ in P.by_part(rows)), reverse=True)
    table = P.markdown(P.by_part(rows), rows, top=3)
    assert table[2].startswith("| rays (embree) | 23.5% |")
    assert "`rough_dielectric_eval_pdf` 2.0%" in "\n".join(table)


def test_the_map_places_each_compiled_loop_at_its_machine_code(tmp_path):
    """Compiled afresh (an empty cache folder: code loaded from a cache keeps no symbol table), a kernel and a
    formula it calls are named at the addresses numba gives their entry points, with their sizes."""
    script = """
import json, math, sys
import numpy as np
sys.path.insert(0, sys.argv[1])
import profile_compiled as P
from addon.core import kernels

out = (np.empty(4), np.empty(4, np.int64), np.empty(4), np.empty(4))
z = np.zeros(4, np.float32)
kernels.closest_hits(out, np.zeros(4, np.int32), z, z, z)
result = next(iter(kernels.closest_hits.overloads.values()))
entry = result.library.get_pointer_to_function(result.fndesc.llvm_func_name)
functions = P.compiled_functions(P.compiled_libraries())
print(json.dumps({"entry": entry, "functions": functions}))
"""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba"), PYTHONPATH=str(ROOT))
    done = subprocess.run(
        [sys.executable, "-c", script, str(ROOT / "benchmarks")], capture_output=True, text=True, env=env, check=True
    )
    found = json.loads(done.stdout.strip().splitlines()[-1])
    named = {address: (size, name) for address, size, name in found["functions"]}
    size, name = named[found["entry"]]
    assert name == "closest_hits" and 16 < size < 100_000
    starts = sorted(named)
    assert all(a + named[a][0] <= b for a, b in zip(starts, starts[1:], strict=False))  # no two overlap
    path = P.write_perf_map(found["functions"], 12345)
    try:
        line = next(line for line in path.read_text().splitlines() if line.endswith(" closest_hits"))
        assert line == f"{found['entry']:x} {size:x} closest_hits"
    finally:
        path.unlink()


def test_elf_functions_is_empty_for_what_is_not_an_elf_object():
    assert P.elf_functions(b"") == {} and P.elf_functions(b"MZ" + bytes(100)) == {}
