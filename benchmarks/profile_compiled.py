"""Where a render's time goes, symbol by symbol, inside the compiled loops too.

    python benchmarks/profile_compiled.py --size 480x270 --samples 16 --bounces 4 --threads 1 --renders 3

perf, Linux's sampling profiler, records which instruction each thread of this process runs while it renders the
demo scene. Samples in the code numba compiles at run time have no symbol: perf sees anonymous memory. So before
recording, the script writes perf's map of such code (``/tmp/perf-<pid>.map``, the file perf reads for a process
with JIT code) naming every function compiled for ``addon.core``: each kernel, and each helper that the compiler
did not inline, as ``kernel:helper`` (the helper's machine code is a copy inside the kernel's). The loops are
compiled afresh for this (a temporary ``NUMBA_CACHE_DIR``): code loaded from numba's cache keeps no symbol table.

Writes ``docs/render_profile.md``: the share of the samples by part (rays, networks, each compiled function,
numpy, the interpreter, the C maths library, the system) and the heaviest symbols, beside the renders' own split
(``RenderStats``). Needs ``perf`` and permission to profile one's own processes
(``kernel.perf_event_paranoid`` at most 2); run on request, not in the test suite.
"""

from __future__ import annotations

import argparse
import os
import platform
import re
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

# --- perf's map of the compiled loops ------------------------------------------------------------------------

_SHT_SYMTAB, _STT_FUNC = 2, 2


def elf_functions(elf: bytes) -> dict[str, tuple[int, int, int]]:
    """The defined functions of a 64-bit little-endian ELF object (numba's compiled code on x86-64 and arm64
    Linux), from its symbol table: name -> (section, offset in it, size in bytes). Empty for anything else."""
    if len(elf) < 64 or elf[:4] != b"\x7fELF" or elf[4] != 2 or elf[5] != 1:
        return {}
    shoff = struct.unpack_from("<Q", elf, 0x28)[0]
    shentsize, shnum = struct.unpack_from("<HH", elf, 0x3A)
    # (name, type, flags, addr, offset, size, link, info, addralign, entsize)
    sections = [struct.unpack_from("<IIQQQQIIQQ", elf, shoff + k * shentsize) for k in range(shnum)]
    found = {}
    for sec in sections:
        if sec[1] != _SHT_SYMTAB:
            continue
        strings = sections[sec[6]][4]
        for j in range(sec[5] // 24):
            st_name, st_info, _, st_shndx, st_value, st_size = struct.unpack_from("<IBBHQQ", elf, sec[4] + 24 * j)
            if st_info & 0xF == _STT_FUNC and st_shndx and st_size:
                end = elf.index(b"\0", strings + st_name)
                found[elf[strings + st_name : end].decode()] = (st_shndx, st_value, st_size)
    return found


def readable(mangled: str) -> str:
    """The last name of a numba function's mangled symbol (``_ZN5addon4core7kernels12surface_hitsB4v106...``
    -> ``surface_hits``; a formula's scalar operation -> ``where<lambda>``); other symbols as they are."""
    if not mangled.startswith("_ZN"):
        return mangled
    names, k = [], 3
    while k < len(mangled) and mangled[k].isdigit():
        m = re.match(r"\d+", mangled[k:])
        n = int(m.group())
        k += len(m.group())
        names.append(mangled[k : k + n])
        k += n
    if not names:
        return mangled
    names = [s.replace("_3clocals_3e", "<locals>").replace("_3clambda_3e", "<lambda>") for s in names]
    last = names[-1]
    if last.startswith("<") and len(names) > 2:  # a formula's scalar overload: its Python function's name
        return names[-3].lstrip("_").removesuffix("_scalar") + last
    return last


def compiled_libraries() -> list:
    """Every library of machine code numba has compiled in this process (a kernel's, and each helper's that is
    compiled on its own: a formula called but not inlined)."""
    import gc
    import weakref

    from numba.core.codegen import CPUCodeLibrary

    found = {}
    for obj in gc.get_objects():
        if not isinstance(obj, weakref.ProxyTypes) and isinstance(obj, CPUCodeLibrary):
            found[id(obj)] = obj
    return list(found.values())


def compiled_functions(libraries) -> list[tuple[int, int, str]]:
    """(address, size, name) of the functions in ``libraries``' machine code, named after their library
    (``library`` for its own function, ``library:helper`` for a helper copied into it). A helper is copied
    into each library that calls it, under one name, so a function is placed by its offset from a symbol that
    only its library defines, never by looking its own name up."""
    tables = []
    for library in libraries:
        try:
            tables.append((library, elf_functions(library._get_compiled_object())))
        except Exception:  # loaded from numba's cache: no symbol table to read
            continue
    defined = defaultdict(int)
    for _, symbols in tables:
        for symbol in symbols:
            defined[symbol] += 1
    rows = {}
    for library, symbols in tables:
        unique = [(symbol, where) for symbol, where in symbols.items() if defined[symbol] == 1]
        if not unique:
            continue
        anchor, (section, offset, _) = unique[0]
        base = library.get_pointer_to_function(anchor) - offset
        for symbol, (sec, off, size) in symbols.items():
            if sec != section or base + off in rows:
                continue
            name = "python wrapper" if symbol.startswith("_ZN7cpython") else readable(symbol)
            rows[base + off] = (size, library.name if name == library.name else f"{library.name}:{name}")
    return sorted((address, size, name) for address, (size, name) in rows.items())


def write_perf_map(functions, pid: int) -> Path:
    """perf's map of JIT code for process ``pid`` (``/tmp/perf-<pid>.map``: start, size, name in hex)."""
    path = Path("/tmp") / f"perf-{pid}.map"  # perf's own convention, whatever TMPDIR says
    path.write_text("".join(f"{address:x} {size:x} {name}\n" for address, size, name in functions))
    return path


# --- perf's report, by part -------------------------------------------------------------------------------

PARTS = (  # (part, pattern of the shared object): the first that matches
    ("rays (embree)", r"libembree|rtcore_"),
    ("networks (ONNX Runtime)", r"onnxruntime"),
    ("random numbers (numpy)", r"_pcg64|_generator|bit_generator|_bounded_integers"),
    ("numpy", r"_multiarray|_umath|numpy"),
    ("Python interpreter", r"libpython|python3"),
    ("C maths library (called by the loops)", r"libm[.-]"),
    ("C library (copies, allocation)", r"libc[.-]|ld-linux"),
    ("the system (page faults, scheduling)", r"kernel"),
    ("numba's runtime", r"_helperlib|_nrt_python|_dispatcher"),
)


def part_of(dso: str, symbol: str) -> str:
    """The part a sample belongs to, from its shared object and symbol (``[JIT]``: the compiled function
    named before the symbol's colon)."""
    if dso.startswith("[JIT]") or dso.startswith("perf-"):
        owner = symbol.split(":", 1)[0]
        return f"compiled `{owner}`" if not owner.startswith("0x") else "compiled code without a symbol"
    for part, pattern in PARTS:
        if re.search(pattern, dso):
            return part
    return "other"


def read_report(text: str) -> list[tuple[float, str, str]]:
    """(percent, shared object, symbol) of each line of ``perf report --sort dso,sym -t ';'``."""
    rows = []
    for line in text.splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        fields = [f.strip() for f in line.split(";")]
        if len(fields) < 3 or not fields[0].endswith("%"):
            continue
        symbol = re.sub(r"^\[[.k]\]\s*", "", fields[2])
        rows.append((float(fields[0].rstrip("%")), fields[1], symbol))
    return rows


def by_part(rows) -> list[tuple[str, float, list[tuple[float, str]]]]:
    """The parts by share, each with its symbols by share."""
    parts: dict[str, list[tuple[float, str]]] = defaultdict(list)
    for percent, dso, symbol in rows:
        parts[part_of(dso, symbol)].append((percent, symbol))
    return sorted(
        ((part, sum(p for p, _ in symbols), sorted(symbols, reverse=True)) for part, symbols in parts.items()),
        key=lambda row: -row[1],
    )


def markdown(parts, rows, top: int) -> list[str]:
    out = ["| part | share of the samples | its heaviest symbols |", "|---|---|---|"]
    for part, share, symbols in parts:
        named = ", ".join(f"`{s.split(':', 1)[-1][:60]}` {p:.1f}%" for p, s in symbols[:4] if not s.startswith("0x"))
        out.append(f"| {part} | {share:.1f}% | {named} |")
    out += ["", f"The {top} heaviest symbols:", "", "| symbol | part | share |", "|---|---|---|"]
    for percent, dso, symbol in sorted(rows, reverse=True)[:top]:
        out.append(f"| `{symbol[:90]}` | {part_of(dso, symbol)} | {percent:.2f}% |")
    return out


# --- the run ----------------------------------------------------------------------------------------------


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", default="480x270")
    ap.add_argument("--samples", type=int, default=16)
    ap.add_argument("--bounces", type=int, default=4)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--renders", type=int, default=3)
    ap.add_argument("--frequency", type=int, default=4000, help="samples a second per thread")
    ap.add_argument("--floor", choices=("lambertian", "baked"), default="lambertian")
    ap.add_argument("--top", type=int, default=30)
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "render_profile.md")
    args = ap.parse_args(argv)
    perf = shutil.which("perf")
    if perf is None:
        raise SystemExit("perf is not installed (Debian: apt install linux-perf)")
    width, height = (int(v) for v in args.size.lower().split("x"))
    work = Path(tempfile.mkdtemp(prefix="profile_compiled_"))
    os.environ["NUMBA_CACHE_DIR"] = str(work / "numba")  # before numba is imported: compile afresh

    import numpy as np

    from addon.core.render import RenderSettings, render
    from addon.core.render.demo_scene import bake_floor, demo_scene

    texture = bake_floor()[0] if args.floor == "baked" else None
    scene = demo_scene(width, height, floor_texture=texture)

    def settings(seed, samples):
        return RenderSettings(samples=samples, max_bounces=args.bounces, seed=seed, threads=args.threads)

    render(scene, settings(0, 1))  # compiles the loops
    functions = compiled_functions(compiled_libraries())
    map_path = write_perf_map(functions, os.getpid())
    data = work / "perf.data"
    recorder = subprocess.Popen(
        [perf, "record", "-F", str(args.frequency), "-p", str(os.getpid()), "-o", str(data)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    time.sleep(1.0)  # perf attaches
    if recorder.poll() is not None:
        raise SystemExit(f"perf record failed: {recorder.stderr.read().decode().strip()}")
    stats = []
    start = time.perf_counter()
    for seed in range(1, args.renders + 1):
        stats.append(render(scene, settings(seed, args.samples))[1])
    seconds = time.perf_counter() - start
    recorder.send_signal(signal.SIGINT)
    recorder.wait()
    report = subprocess.run(
        [perf, "report", "-i", str(data), "--no-children", "--sort", "dso,sym", "-t", ";", "--stdio", "-g", "none"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    map_path.unlink(missing_ok=True)
    rows = read_report(report)
    shutil.rmtree(work, ignore_errors=True)

    total = sum(s.seconds["total"] for s in stats)
    share = {k: sum(s.seconds[k] for s in stats) / total for k in ("rays", "network", "shading")}
    command = "python benchmarks/profile_compiled.py " + " ".join(
        argv if argv is not None else sys.argv[1:]
    )  # as it was run
    lines = [
        f"# Where a render's time goes, inside the compiled loops too ({args.size}, {args.samples} spp, "
        f"{args.bounces} bounces, {args.threads} {'thread' if args.threads == 1 else 'threads'}, {args.floor} floor)",
        "",
        f"Command: `{command.strip()}`",
        "",
        f"Machine: {platform.machine()}, {os.cpu_count()} CPU threads. perf sampled this process at "
        f"{args.frequency} Hz a thread during {args.renders} renders ({seconds:.2f} s); {len(functions)} compiled "
        "functions named in its map. Shares are of all samples of all threads (ONNX Runtime's and embree's own "
        "threads included). A compiled function's row holds the helpers copied into its code (`kernel:helper`); a "
        "helper compiled on its own (a formula called but not inlined, as `top_reflection` is from "
        "`decoded_brdf`) has a row of its own. The C maths library's functions (exp, expm1, log) are called from "
        "the loops.",
        "",
        f"The renders' own split (`RenderStats`): rays {share['rays']:.0%}, networks {share['network']:.0%}, "
        f"shading {share['shading']:.0%}, the rest of the rest {1 - sum(share.values()):.0%}; "
        f"median render {np.median([s.seconds['total'] for s in stats]):.2f} s.",
        "",
        *markdown(by_part(rows), rows, args.top),
        "",
    ]
    args.out.write_text("\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
