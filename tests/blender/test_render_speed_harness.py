"""The speed benchmark's harness (``benchmarks/bench_render.py --speed-only``): Cycles' own kernel statistics
read from what it prints, and docs/render_speed.md rewritten without losing its hand-written notes. Shapes and
behaviour only, never absolute times."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))

import bench_render  # noqa: E402

# As Cycles 5.0 prints it after a profiled render of the demo scene (trimmed).
PRINTED = """\
Render statistics:
Kernel statistics:
  Total render time               : Total 100.00% (6.06s), Self 0.92% (0.06s)
    Shade Surface                   : Total 53.81% (3.26s), Self 0.00% (0.00s)
      Direct Light                    : Total 33.48% (2.03s), Self 33.48% (2.03s)
      Shader Evaluation               : Total 8.91% (0.54s), Self 8.91% (0.54s)
    Shade Light                     : Total 22.06% (1.34s), Self 0.00% (0.00s)
    Intersect Closest               : Total 13.58% (0.82s), Self 13.58% (0.82s)
    Intersect Shadow                : Total 4.47% (0.27s), Self 4.47% (0.27s)
Shader statistics:
  tiles                           : 1.73s (Relative cost: 1.75)
"""


def test_cycles_kernel_times_reads_every_kernel_with_its_depth():
    rows = bench_render.cycles_kernel_times("Fra:1 noise before\n" + PRINTED)
    assert rows[0] == (0, "Total render time", 6.06)
    assert (1, "Shade Surface", 3.26) in rows and (2, "Direct Light", 2.03) in rows
    assert [name for depth, name, _ in rows if depth == 1] == [
        "Shade Surface",
        "Shade Light",
        "Intersect Closest",
        "Intersect Shadow",
    ]
    assert "tiles" not in {name for _, name, _ in rows}  # the shader statistics that follow are not kernels


def test_cycles_kernel_times_is_empty_without_statistics():
    assert bench_render.cycles_kernel_times("Fra:1 Mem:12M | Sample 16/16\n") == []


def test_notes_below_the_marker_survive_a_rewrite(tmp_path):
    doc = tmp_path / "render_speed.md"
    bench_render.write_keeping_notes(doc, "# Tables\n\n| a |\n")
    assert doc.read_text().rstrip().endswith(bench_render.NOTES_MARKER)
    doc.write_text(doc.read_text() + "\n## Why it changed\n\nMeasured by hand.\n")
    bench_render.write_keeping_notes(doc, "# Tables\n\n| b |\n")
    text = doc.read_text()
    assert "| b |" in text and "| a |" not in text
    assert text.index("| b |") < text.index(bench_render.NOTES_MARKER) < text.index("## Why it changed")
    assert text.count(bench_render.NOTES_MARKER) == 1 and text.endswith("Measured by hand.\n")


def test_a_file_without_the_marker_is_refused_not_overwritten(tmp_path):
    doc = tmp_path / "render_speed.md"
    doc.write_text("# Old tables\n\n## Notes written by hand\n")
    with pytest.raises(SystemExit, match="no line"):
        bench_render.write_keeping_notes(doc, "# Tables\n")
    assert doc.read_text() == "# Old tables\n\n## Notes written by hand\n"


@pytest.mark.parametrize(
    "name, generated", [("render_speed.md", "## Where the rest goes"), ("render_benchmark.md", "## Equal-time error")]
)
def test_the_committed_docs_have_the_marker_once_below_their_tables(name, generated):
    text = (ROOT / "docs" / name).read_text()
    assert text.count(bench_render.NOTES_MARKER) == 1
    assert generated in text.partition(bench_render.NOTES_MARKER)[0]


def test_cycles_split_measures_both_renderers_on_a_small_scene():
    """In a process of its own: the profiler it turns on stays on for the rest of the process."""
    pytest.importorskip("bpy")
    code = "import bench_render; print('\\n'.join(bench_render.cycles_split(160, 90, 16, 4)))"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), str(ROOT / "benchmarks")]))
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    section = out.stdout[out.stdout.index("## Where Cycles' own time goes") :]
    shares = [float(v) for v in re.findall(r"^\| (?!all)[A-Z][^|]* \| [\d.]+ \| ([\d.]+)% \|$", section, re.M)]
    assert shares and 90.0 <= sum(shares) <= 105.0  # the kernels under the total (seconds printed to 0.01)
    assert re.search(r"^\| Intersect Closest \| [\d.]+ \| [\d.]+% \|$", section, re.M)
    share = float(re.search(r"Ray intersection is \*\*(\d+)%\*\*", section).group(1))
    assert 0 < share < 100
    assert re.search(r"Ours in the render before it: rays \d+%, networks \d+%, the rest \d+%", section)


def test_film_memory_reads_the_rendering_process_own_peak_not_its_parent_s():
    """``ru_maxrss`` keeps a parent's peak across the exec that starts a child: under a parent holding Blender it
    read 1.91 GB for a render whose own peak was 1.26 GB. The section reads the child's ``VmHWM``."""
    import numpy as np

    held = np.ones(1 << 30, np.uint8)  # this process: 1 GiB more, touched
    lines = bench_render.film_memory(size=(32, 18), samples=1, bounces=1)
    peak_gb, film_gb, per_pixel = (float(v) for v in lines[4].strip("| ").split(" | "))
    assert per_pixel == 84 and film_gb == 0.0
    assert 0.0 < peak_gb < held.nbytes / 1e9  # the child's own peak: a tiny render is far below the parent's GiB


def test_allocators_says_it_did_not_measure_without_a_jemalloc_library(monkeypatch):
    monkeypatch.setattr(bench_render, "_jemalloc_library", lambda: None)
    lines = bench_render.allocators(32, 18, 1, 1, 1)
    assert lines[0].startswith("## The allocator") and "Not measured: no jemalloc library" in lines[2]


def test_allocators_refuses_a_child_the_preload_did_not_reach(monkeypatch):
    """The loader skips a library it cannot preload and runs on: the child says which malloc it has, and a
    jemalloc row measured on glibc is an error, not a table."""
    pytest.importorskip("bpy")
    monkeypatch.setattr(bench_render, "_jemalloc_library", lambda: "libno-such-jemalloc.so.2")
    with pytest.raises(RuntimeError, match="lacks jemalloc"):
        bench_render.allocators(32, 18, 1, 1, 1)
