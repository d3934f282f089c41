"""Decoder zoo: held-out error against evaluation speed, one point per size, one run.

    python benchmarks/bench_decoders.py                  # every shipped size
    python benchmarks/bench_decoders.py --sizes tiny small --update-cards

For each shipped decoder size (``addon/models``) it measures

- the held-out lobe error (`addon.core.lobe`) of the held-out BRDFs projected into the latent
  space by latent optimisation (``onnx_export.evaluate``), on ``tests/data/heldout_single.npz``
  and, when present, ``tests/data/heldout_layered_lobes.npz``; and of the single-layer set encoded in
  one pass by the size's encoder (runtime ``encode`` + ``eval_brdf``);
- RGB evaluations per second of the runtime's ``eval_brdf`` (ONNX Runtime, ``--threads``
  threads, batch 65,536, one material), and of the bare decoder session on the 3 x 65,536 rows;
- the arithmetic limit: ONNX Runtime's own MatMul rate on this machine (multiply-adds per
  second, 65,536 x 256 x 256) divided by the multiply-adds per RGB evaluation.

It writes ``docs/decoders.md`` (table) and ``docs/decoders_error_speed.png`` (chart), and with
``--update-cards`` stores the figures in the model cards.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from addon.core import lobe  # noqa: E402
from addon.core.neural import MODEL_DIR, SIZES, encode_stack, load_models  # noqa: E402
from addon.core.stack import Stack  # noqa: E402

DOCS = ROOT / "docs"
BATCH = 65536


def matmul_rate(threads: int, n: int = BATCH, k: int = 256, layers: int = 8, repeats: int = 5) -> float:
    """Multiply-adds per second that ONNX Runtime reaches here on ``threads`` cores: a chain of
    ``layers`` (n x k) @ (k x k) Gemms with ReLU, reduced to one column at the end (so writing
    the output does not dominate, as in a decoder). The better of one call with ``threads``
    intra-op threads and the runtime's way (chunks on single-threaded sessions, ``ChunkedSession``,
    chunk sizes 512 and 2,048)."""
    import tempfile

    import onnx
    import onnxruntime as ort
    from onnx import TensorProto, helper, numpy_helper

    from addon.core.neural.session import ChunkedSession

    rng = np.random.default_rng(0)
    inits, nodes, prev = [], [], "x"
    for i in range(layers):
        w = (rng.standard_normal((k, k)) * np.sqrt(2.0 / k)).astype(np.float32)
        inits.append(numpy_helper.from_array(w, f"w{i}"))
        inits.append(numpy_helper.from_array(np.zeros(k, np.float32), f"b{i}"))
        # Gemm + Relu, as the exported decoders are (ONNX Runtime fuses the pair)
        nodes += [
            helper.make_node("Gemm", [prev, f"w{i}", f"b{i}"], [f"m{i}"]),
            helper.make_node("Relu", [f"m{i}"], [f"h{i}"]),
        ]
        prev = f"h{i}"
    inits.append(numpy_helper.from_array(rng.standard_normal((k, 1)).astype(np.float32), "w_out"))
    nodes.append(helper.make_node("MatMul", [prev, "w_out"], ["y"]))
    g = helper.make_graph(
        nodes,
        "mm",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [None, k])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [None, 1])],
        inits,
    )
    model = helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)])
    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    one = ort.InferenceSession(model.SerializeToString(), so, providers=["CPUExecutionProvider"])
    x = rng.standard_normal((n, k)).astype(np.float32)
    runs = [lambda: one.run(None, {"x": x})]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "matmul.onnx"
        onnx.save(model, str(path))
        for chunk in (512, 2048):
            s = ChunkedSession(path, threads, chunk)
            runs.append(lambda s=s: s.run(["y"], {"x": x}))
    best = np.inf
    for fn in runs:
        fn()
        for _ in range(repeats):
            t = time.perf_counter()
            fn()
            best = min(best, time.perf_counter() - t)
    return n * k * (layers * k + 1) / best


def speed(size: str, threads: int, repeats: int = 5) -> dict:
    m = load_models(size, threads=threads)
    rng = np.random.default_rng(0)
    wi = rng.normal(size=(BATCH, 3))
    wo = rng.normal(size=(BATCH, 3))
    wi[:, 2] = np.abs(wi[:, 2])
    wo[:, 2] = np.abs(wo[:, 2])
    wi /= np.linalg.norm(wi, axis=1, keepdims=True)
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    z = encode_stack(Stack.from_json(json.dumps({"base": {"type": "Conductor", "roughness": 0.2}})), m)
    m.eval_brdf(z, wi, wo)
    best = np.inf
    for _ in range(repeats):
        t = time.perf_counter()
        m.eval_brdf(z, wi, wo)
        best = min(best, time.perf_counter() - t)
    # the previous way, for comparison: one ONNX Runtime call on the whole batch, ``threads``
    # intra-op threads, the same fused RGB graph
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    sess = ort.InferenceSession(str(m._rgb.path), so, providers=["CPUExecutionProvider"])
    feeds = {"zc": m.project_latents(z), "wi": wi.astype(np.float32), "wo": wo.astype(np.float32)}
    sess.run(["f"], feeds)
    one = np.inf
    for _ in range(repeats):
        t = time.perf_counter()
        sess.run(["f"], feeds)
        one = min(one, time.perf_counter() - t)
    return {
        "rgb_evals_per_s": BATCH / best,
        "rgb_evals_per_s_one_call": BATCH / one,
        "batch": BATCH,
        "threads": threads,
        "chunk": m._rgb.chunk,
    }


def operator_breakdown(size: str, chunk: int, runs: int = 100) -> dict:
    """Where one chunk's time goes in the RGB decoder graph, from ONNX Runtime's own profiler
    (one single-threaded session, as the runtime runs them): the share of kernel time per
    operator type (matrix products against everything else), and the time per call outside the
    kernels (session overhead)."""
    import onnxruntime as ort

    from addon.core.neural.session import session_options

    rng = np.random.default_rng(0)
    wi = rng.normal(size=(chunk, 3))
    wi[:, 2] = np.abs(wi[:, 2])
    wi = (wi / np.linalg.norm(wi, axis=1, keepdims=True)).astype(np.float32)
    zc = load_models(size).project_latents(rng.normal(size=(1, 3, 32)) * 0.3)
    with tempfile.TemporaryDirectory() as tmp:
        so = session_options()
        so.enable_profiling = True
        so.profile_file_prefix = str(Path(tmp) / "ort")
        sess = ort.InferenceSession(str(MODEL_DIR / f"decoder_{size}_rgb.onnx"), so, providers=["CPUExecutionProvider"])
        for _ in range(runs):
            sess.run(["f"], {"zc": zc, "wi": wi, "wo": wi})
        events = json.loads(Path(sess.end_profiling()).read_text())
    by_op: dict[str, float] = {}
    for e in events:
        if e.get("cat") == "Node" and e["name"].endswith("_kernel_time"):
            op = e["args"]["op_name"]
            by_op[op] = by_op.get(op, 0.0) + e["dur"]
    run_us = sum(e["dur"] for e in events if e.get("name") == "model_run") / runs
    kernel_us = sum(by_op.values()) / runs
    matmul = sum(v for k, v in by_op.items() if k in ("Gemm", "FusedGemm", "MatMul", "FusedMatMul")) / runs
    top = sorted(by_op.items(), key=lambda kv: -kv[1])[:6]
    return {
        "chunk": chunk,
        "run_us": run_us,
        "kernel_us": kernel_us,
        "matmul_share": matmul / kernel_us,
        "overhead_share": max(0.0, run_us - kernel_us) / run_us,
        "nodes": sum(1 for e in events if e.get("cat") == "Node" and e["name"].endswith("_kernel_time")) // runs,
        "top": [(k, v / runs / kernel_us) for k, v in top],
    }


def encoder_heldout(size: str, heldout: dict) -> dict:
    from onnx_export.evaluate import lobe_metrics

    m = load_models(size)
    res = heldout["lobe"].shape[2]
    pred = np.zeros_like(heldout["lobe"], dtype=np.float64)
    for i, s in enumerate(heldout["stacks"]):
        z = encode_stack(Stack(s.base), m)
        for a, t in enumerate(heldout["angles"]):
            pred[i, a] = lobe.lobe_image(lambda wi, wo, z=z: m.eval_brdf(z, wi, wo), float(t), res)
    out = lobe_metrics(pred, heldout["lobe"])
    out.pop("errors")
    return out


def projection_heldout(size: str, heldout: dict, steps: int, threads: int) -> dict:
    import torch

    from onnx_export.evaluate import evaluate_projection
    from onnx_export.export import torch_from_onnx

    torch.set_num_threads(threads)
    path = MODEL_DIR / f"decoder_{size}.onnx"
    card = json.loads(path.with_suffix(".json").read_text())
    dec = torch_from_onnx(path, card)
    large = card["parameters"] > 200_000  # fewer pairs per step: CPU time of the projection
    pairs = 128 if large else (256 if card["parameters"] > 20_000 else None)
    init = np.asarray(card["latent_mean"], np.float32)
    m = evaluate_projection(dec, heldout, init=init, steps=steps, chunk_pairs=pairs)
    errs = m.pop("errors")
    m.pop("z")
    m.update(projection_steps=steps, projection_pairs=pairs, projection_init=card["latent_mean"])
    m["per_config_median"] = [round(float(v), 4) for v in np.median(errs, axis=1)]
    return m


def chart(rows: list[dict], path: Path, command: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 4.8))
    for r in rows:
        x = r["speed"]["rgb_evals_per_s"]
        ax.scatter([x], [100 * r["single"]["lobe_error_median"]], color="C0", zorder=3)
        ax.annotate(
            f"{r['size']} ({r['params'] / 1e3:.1f} k params)",
            (x, 100 * r["single"]["lobe_error_median"]),
            textcoords="offset points",
            xytext=(6, 4),
            fontsize=8,
        )
        ax.scatter([r["limit"]], [100 * r["single"]["lobe_error_median"]], color="C3", marker="|", s=200, zorder=3)
        ax.plot([x, r["limit"]], [100 * r["single"]["lobe_error_median"]] * 2, color="C3", lw=0.8, ls=":")
        if "layered" in r:
            ax.scatter([x], [100 * r["layered"]["lobe_error_median"]], color="C1", marker="s", zorder=3)
    ax.scatter([], [], color="C0", label="single-layer held-out (projected), median")
    ax.scatter([], [], color="C1", marker="s", label="layered held-out (projected), median")
    ax.scatter([], [], color="C3", marker="|", s=200, label="arithmetic limit (MACs / MatMul rate)")
    ax.set_xscale("log")
    ax.set_xlabel("RGB evaluations per second (ONNX Runtime, 2 threads, batch 65,536)")
    ax.set_ylabel("held-out lobe error, median relative RMSE (%)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="center left")
    ax.set_title("Decoder zoo: error against speed", fontsize=10)
    fig.text(0.01, 0.01, command, fontsize=6, color="0.4")
    fig.tight_layout(rect=(0, 0.03, 1, 1))
    fig.savefig(path, dpi=120)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", nargs="+", default=[s for s in SIZES if (MODEL_DIR / f"decoder_{s}.onnx").exists()])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--steps", type=int, default=300, help="projection steps")
    ap.add_argument("--repeats", type=int, default=5, help="timed runs per speed figure (the best is kept)")
    ap.add_argument("--update-cards", action="store_true")
    ap.add_argument(
        "--errors-from-cache",
        action="store_true",
        help="reuse held-out errors measured earlier for unchanged model files (speed is always measured)",
    )
    ap.add_argument(
        "--errors-from-cards",
        action="store_true",
        help="reuse the held-out errors stored in the model cards by an earlier --update-cards run "
        "(speed is always measured)",
    )
    ap.add_argument("--out", type=Path, default=DOCS)
    a = ap.parse_args(argv)
    command = "python benchmarks/bench_decoders.py " + " ".join(shlex.quote(x) for x in (argv or sys.argv[1:]))
    from onnx_export.heldout import load as load_heldout

    sets = {"single": load_heldout(ROOT / "tests/data/heldout_single.npz")}
    lay = ROOT / "tests/data/heldout_layered_lobes.npz"
    if lay.exists():
        sets["layered"] = load_heldout(lay)
    mm = matmul_rate(a.threads, repeats=a.repeats)
    print(f"MatMul rate {mm / 1e9:.1f} GMAC/s", file=sys.stderr, flush=True)
    rows = []
    for size in a.sizes:
        card_path = MODEL_DIR / f"decoder_{size}.json"
        card = json.loads(card_path.read_text())
        r = {"size": size, "params": card["parameters"], "macs": card["macs_per_rgb_eval"]}
        r["remainder"] = card.get("remainder", False) is True
        r["speed"] = speed(size, a.threads, a.repeats)
        r["breakdown"] = operator_breakdown(size, r["speed"]["chunk"])
        r["limit"] = mm / r["macs"]
        cached = ROOT / "cache" / "bench" / f"errors_{size}.json"
        onnx_mtime = (MODEL_DIR / f"decoder_{size}.onnx").stat().st_mtime
        ecard = json.loads((MODEL_DIR / f"encoder_{size}.json").read_text())
        if a.errors_from_cards and "heldout_single" in card and "encoder_heldout_single" in ecard:
            # errors of the same files, measured by an earlier run and committed with them
            r.update(single=card["heldout_single"], encoder=ecard["encoder_heldout_single"])
            if "heldout_layered" in card:
                r["layered"] = card["heldout_layered"]
        elif a.errors_from_cache and cached.exists() and cached.stat().st_mtime > onnx_mtime:
            r.update(json.loads(cached.read_text()))  # errors of the same files, measured earlier
        else:
            # a remainder decoder holds no whole layered lobe: projecting one into it measures nothing
            # (its layered bound is `layering bound --remainder`, docs/layering_training.md)
            errs = {
                name: projection_heldout(size, h, a.steps, a.threads)
                for name, h in sets.items()
                if not (name == "layered" and card.get("remainder"))
            }
            errs["encoder"] = encoder_heldout(size, sets["single"])
            cached.parent.mkdir(parents=True, exist_ok=True)
            cached.write_text(json.dumps(errs, default=float))
            r.update(errs)
        rows.append(r)
        print(
            json.dumps({k: v for k, v in r.items() if k != "params"}, default=float)[:600], file=sys.stderr, flush=True
        )
        if a.update_cards:
            card["heldout_single"] = r["single"]
            if "layered" in r:
                card["heldout_layered"] = r["layered"]
            else:
                card.pop("heldout_layered", None)
            card["speed_cpu"] = r["speed"] | {
                "matmul_macs_per_s": mm,
                "arithmetic_limit_rgb_evals_per_s": r["limit"],
                "note": f"best of {a.repeats} runs on the 2-core development machine",
                "command": command,
            }
            card_path.write_text(json.dumps(card, indent=1) + "\n")
            ecard_path = MODEL_DIR / f"encoder_{size}.json"
            ecard = json.loads(ecard_path.read_text())
            ecard["encoder_heldout_single"] = r["encoder"]
            ecard_path.write_text(json.dumps(ecard, indent=1) + "\n")
    a.out.mkdir(parents=True, exist_ok=True)
    chart(rows, a.out / "decoders_error_speed.png", command)
    lines = [
        "# Decoder zoo: measured error and speed",
        "",
        f"Produced by `{command}` (ONNX Runtime, {a.threads} threads, batch {BATCH:,} RGB evaluations, "
        f"one material, best of {a.repeats}). The runtime cuts the batch into chunks of "
        f"{rows[0]['speed']['chunk'] if rows else '?'} queries run by single-threaded sessions on {a.threads} "
        "threads (`addon/core/neural/session.py`); the column beside it is one call on the whole batch with "
        f"{a.threads} intra-op threads, the same graph.",
        "",
        f"Load average of the machine when the run ended: {os.getloadavg()[1]:.1f} over 5 minutes on "
        f"{os.cpu_count()} CPU threads (shared with other jobs: compare rows of one run, not runs).",
        "",
        f"ONNX Runtime MatMul rate here: {mm / 1e9:.1f} G multiply-adds/s (65,536 rows through eight 256 x 256 "
        "Gemm + ReLU layers, the best of one 2-thread call and chunks on single-threaded sessions); the "
        "arithmetic limit of a size is that rate over its multiply-adds per RGB evaluation (three scalar "
        "decoder passes).",
        "",
        "Lobe error = relative RMSE of f cos(theta_o) lobe images at incident elevations 0/30/60/75 degrees "
        '(`addon.core.lobe`); median / 90th percentile over configurations x elevations. "projected": the '
        'held-out BRDF is fitted by latent optimisation on separate direction samples; "encoded": the '
        "single-layer encoder maps its parameters to the latent in one pass. Albedo error: mean absolute "
        "error of the directional albedo. Projection: 300 Adam steps on all 1024 pairs per configuration "
        "(for CPU time: models above 20 k parameters use 256 random pairs per step, above 200 k 128).",
        "",
        "| size | params | MACs / RGB eval | RGB evals/s (runtime eval_brdf: chunks on a thread pool) | "
        "RGB evals/s (one ONNX Runtime call on the whole batch) | arithmetic limit | "
        "single-layer projected (median / p90) | albedo err | layered projected (median / p90) | "
        "single-layer encoded (median / p90) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lay_txt = (
            f"{100 * r['layered']['lobe_error_median']:.1f}% / {100 * r['layered']['lobe_error_p90']:.1f}%"
            if "layered" in r
            else ("n/a (remainder design: docs/layering_training.md)" if r.get("remainder") else "n/a")
        )
        lines.append(
            f"| {r['size']} | {r['params']:,} | {r['macs']:,} | {r['speed']['rgb_evals_per_s']:,.0f} | "
            f"{r['speed']['rgb_evals_per_s_one_call']:,.0f} | {r['limit']:,.0f} | "
            f"{100 * r['single']['lobe_error_median']:.1f}% / {100 * r['single']['lobe_error_p90']:.1f}% | "
            f"{r['single']['albedo_abs_error_mean']:.4f} | {lay_txt} | "
            f"{100 * r['encoder']['lobe_error_median']:.1f}% / {100 * r['encoder']['lobe_error_p90']:.1f}% |"
        )
    lines += [
        "",
        "## Where a decoder call's time goes",
        "",
        "ONNX Runtime's profiler on one single-threaded session running one chunk of the runtime's size "
        "(100 calls): the share of kernel time in matrix products (Gemm, FusedGemm, MatMul), the share of "
        "each call spent outside kernels, and the costliest operator types. The rest of the kernel time is "
        "the graph's element-wise work: the direction features, the latent projection broadcast to the "
        "batch, the output exponential and the horizon mask.",
        "",
        "| size | chunk (queries) | operators per call | us per call | matrix products | outside kernels | "
        "costliest operators (share of kernel time) |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        b = r["breakdown"]
        top = ", ".join(f"{k} {100 * v:.0f}%" for k, v in b["top"])
        lines.append(
            f"| {r['size']} | {b['chunk']:,} | {b['nodes']} | {b['run_us']:,.0f} | "
            f"{100 * b['matmul_share']:.0f}% | {100 * b['overhead_share']:.0f}% | {top} |"
        )
    lines += ["", "![error against speed](decoders_error_speed.png)", ""]
    (a.out / "decoders_bench.md").write_text("\n".join(lines))
    print(json.dumps({"out": str(a.out / "decoders_bench.md")}))


if __name__ == "__main__":
    main()
