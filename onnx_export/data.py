"""Training data: BRDF parameters, direction pairs and target values, sharded and cached on disk.

Two sets:

- ``single``: single-layer analytic BRDFs (Diffuse, Conductor, Dielectric reflection over black),
  exact targets from ``addon.core.bsdf`` (cheap: numpy, a few seconds per thousand BRDFs);
- ``layered``: 1 to 3 coatings over any base, targets (and their standard errors) from the
  position-free Monte Carlo reference ``addon.core.reference.eval_brdf``.

Each set is a list of chunks of ``--chunk`` materials. Chunk ``j`` is generated from the seed
``(seed, j)`` alone, so the data do not depend on how the work is sharded: ``--shard i/n`` makes
chunks ``j = i, i + n, ...``; finished chunks on disk are skipped, so an interrupted run resumes.
``OUT/manifest.json`` records the options that decide the chunks' contents (set, seed, pairs, walks,
chunk size) and the number of materials: a rerun with other options is refused (naming the option),
a larger ``--materials`` adds chunks and makes a short last chunk again (``write_chunks``), and
``data_command`` renders the command of the data as they are.

    python -m onnx_export.data --set single --materials 4096 --pairs 1024 --out cache/data/single
    python -m onnx_export.data --set layered --materials 512 --pairs 512 --walks 64 --shard 0/4 ...

Direction pairs cover the whole hemisphere and the specular lobes: a quarter with both
directions uniform in solid angle (grazing included), a quarter cosine-distributed (the lobe
images' measure), and half with ``wo`` the mirror of ``wi`` about a GGX visible normal of a
slightly widened roughness (the lobe). Targets are f without the cosine, RGB, float32.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from addon.core.bsdf import ggx
from addon.core.bsdf.lambert import Lambertian, sample_cosine_hemisphere
from addon.core.stack import BASE_KINDS, StackArrays
from onnx_export.cli import command_line, positive_int

KIND_PROBS = (0.2, 0.4, 0.4)  # Diffuse, Conductor, Dielectric: the glossy kinds are the hard ones
GROUPS = 8  # layered set: outgoing directions per stack that share their reference walks
DEFAULT_SEED = 1
MANIFEST = "manifest.json"  # beside the chunks: the options they were made with (``prepare_out``)


class OptionError(ValueError):
    """Options that do not fit each other or the chunks already in the output folder (the scripts' usage error)."""


# ----------------------------------------------------------------------------- parameters


def log_uniform(rng, lo, hi, size):
    return np.exp(rng.uniform(np.log(lo), np.log(hi), size))


def sample_single_params(rng: np.random.Generator, n: int, kind_probs=KIND_PROBS) -> StackArrays:
    """``n`` random single-layer materials over the trained ranges (docs/architecture.md, Conventions)."""
    kind = rng.choice(3, size=n, p=np.asarray(kind_probs) / np.sum(kind_probs))
    # a third of conductors are "artist" metals eta ~ 1 with colour in k; the rest span eta/k widely
    eta = log_uniform(rng, 0.05, 4.0, (n, 3))
    k = np.where(rng.random((n, 1)) < 0.7, log_uniform(rng, 0.5, 12.0, (n, 3)), rng.uniform(0.0, 20.0, (n, 3)))
    return StackArrays(
        base_kind=kind.astype(np.int64),
        base_albedo=rng.random((n, 3)),
        base_roughness=log_uniform(rng, 0.01, 1.0, n),
        base_eta=eta,
        base_k=k,
        base_ior=rng.uniform(1.05, 2.0, n),
        coat_roughness=np.zeros((n, 0)),
        coat_ior=np.zeros((n, 0)),
        coat_albedo=np.zeros((n, 0, 3)),
        coat_thickness=np.zeros((n, 0)),
        coat_g=np.zeros((n, 0)),
    )


def sample_layered_params(rng: np.random.Generator, n: int, n_coatings: int) -> StackArrays:
    """``n`` random stacks with ``n_coatings`` coatings over random bases."""
    base = sample_single_params(rng, n)
    c = n_coatings
    thick = np.where(rng.random((n, c)) < 0.3, 0.0, rng.uniform(0.0, 5.0, (n, c)))
    clear = rng.random((n, c, 1)) < 0.3
    albedo = np.where(clear, 1.0, rng.random((n, c, 3)))
    return StackArrays(
        base_kind=base.base_kind,
        base_albedo=base.base_albedo,
        base_roughness=base.base_roughness,
        base_eta=base.base_eta,
        base_k=base.base_k,
        base_ior=base.base_ior,
        coat_roughness=log_uniform(rng, 0.01, 1.0, (n, c)),
        coat_ior=rng.uniform(1.05, 2.0, (n, c)),
        coat_albedo=albedo,
        coat_thickness=thick,
        coat_g=np.zeros((n, c)),
    )


# ----------------------------------------------------------------------------- directions


def uniform_hemisphere(u: np.ndarray) -> np.ndarray:
    z = u[..., 0]
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = 2.0 * np.pi * u[..., 1]
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)


def sample_directions(
    rng: np.random.Generator, lobe_alpha: np.ndarray, pairs: int, wi: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(M, P, 3) wi and wo for M materials whose specular lobe has GGX roughness ``lobe_alpha`` (M,).

    ``wi`` (M, P, 3) may be given (e.g. repeated, for the amortised reference); else it is drawn.
    """
    m = lobe_alpha.shape[0]
    shape = (m, pairs)
    which = rng.random(shape)  # < 0.25 uniform, < 0.5 cosine, else lobe
    if wi is None:
        wi_u = uniform_hemisphere(rng.random(shape + (2,)))
        wi_c = sample_cosine_hemisphere(rng.random((m * pairs, 2))).reshape(shape + (3,))
        wi = np.where((which < 0.25)[..., None] | (which >= 0.5)[..., None], wi_u, wi_c)
    else:
        wi = np.array(wi, dtype=np.float64)
    wo_u = uniform_hemisphere(rng.random(shape + (2,)))
    wo_c = sample_cosine_hemisphere(rng.random((m * pairs, 2))).reshape(shape + (3,))
    widen = rng.uniform(1.0, 2.0, shape)
    a = np.minimum(1.0, np.broadcast_to(lobe_alpha[:, None], shape) * widen)
    h = ggx.sample_visible_normal(wi.reshape(-1, 3), a.reshape(-1), rng.random((m * pairs, 2))).reshape(shape + (3,))
    wo_l = 2.0 * np.einsum("mpi,mpi->mp", wi, h)[..., None] * h - wi
    lobe_ok = wo_l[..., 2] > 1e-4
    wo = np.where((which < 0.25)[..., None], wo_u, wo_c)
    wo = np.where(((which >= 0.5) & lobe_ok)[..., None], wo_l, wo)
    # keep every direction strictly above the horizon and of unit length
    for w in (wi, wo):
        w[..., 2] = np.maximum(w[..., 2], 1e-4)
        w /= np.linalg.norm(w, axis=-1, keepdims=True)
    # targets are evaluated at the float32 directions that are stored and fed to the networks
    return wi.astype(np.float32).astype(np.float64), wo.astype(np.float32).astype(np.float64)


# ----------------------------------------------------------------------------- targets


def single_layer_bsdf(arrays: StackArrays, kind: int, rows: np.ndarray, pairs: int):
    """The ``addon.core.bsdf`` object for materials ``rows`` (all of base ``kind``), each repeated
    ``pairs`` times so that it evaluates (len(rows) * pairs) direction pairs."""
    rep = lambda a: np.repeat(a[rows], pairs, axis=0)  # noqa: E731
    if kind == 0:
        return Lambertian(rep(arrays.base_albedo))
    if kind == 1:
        from addon.core.bsdf.conductor import RoughConductor

        return RoughConductor(rep(arrays.base_roughness), rep(arrays.base_eta), rep(arrays.base_k))
    from addon.core.bsdf.dielectric import RoughDielectric

    return RoughDielectric(rep(arrays.base_roughness), rep(arrays.base_ior), reflection_only=True)


def eval_single(arrays: StackArrays, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """Exact f (M, P, 3) of single-layer materials at (M, P, 3) direction pairs."""
    m, p = wi.shape[:2]
    f = np.zeros((m, p, 3))
    for kind in range(len(BASE_KINDS)):
        rows = np.flatnonzero(arrays.base_kind == kind)
        if rows.size == 0:
            continue
        bsdf = single_layer_bsdf(arrays, kind, rows, p)
        f[rows] = bsdf.eval(wi[rows].reshape(-1, 3), wo[rows].reshape(-1, 3), check=False).reshape(-1, p, 3)
    return f


def lobe_alpha_of(arrays: StackArrays) -> np.ndarray:
    """The roughness that sets the specular lobe: the top coating's, else the base's (diffuse: 1)."""
    if arrays.n_coatings:
        return arrays.coat_roughness[:, -1].copy()
    return np.where(arrays.base_kind == 0, 1.0, arrays.base_roughness)


def make_chunk(kind: str, seed: int, chunk: int, materials: int, pairs: int, walks: int = 64) -> dict:
    """One chunk of data as a dict of arrays; deterministic in (kind, seed, chunk)."""
    rng = np.random.default_rng([seed, chunk, 0 if kind == "single" else 1])
    if kind == "single":
        arrays = sample_single_params(rng, materials)
    else:
        arrays = sample_layered_params(rng, materials, n_coatings=int(rng.integers(1, 4)))
    if kind == "single":
        wi, wo = sample_directions(rng, lobe_alpha_of(arrays), pairs)
        f = eval_single(arrays, wi, wo)
        stderr = np.zeros_like(f)
    else:
        # amortised reference (eval_brdf_many): GROUP outgoing directions per stack, each shared by
        # pairs / GROUP incident directions drawn around it, so one set of walks serves a group
        from addon.core import reference

        per = pairs // GROUPS
        if per * GROUPS != pairs:
            raise ValueError(f"--pairs must be a multiple of {GROUPS} for the layered set, got {pairs}")
        first, _ = sample_directions(rng, lobe_alpha_of(arrays), GROUPS)  # (M, GROUPS, 3) shared directions
        wo = np.repeat(first, per, axis=1)
        _, wi = sample_directions(rng, lobe_alpha_of(arrays), pairs, wi=wo)  # drawn around each shared one
        f = np.zeros((materials, pairs, 3))
        stderr = np.zeros_like(f)
        for i in range(materials):  # one reference call per stack, all its direction pairs at once
            fi, si = reference.eval_brdf_many(
                arrays.take([i]), wi[i].reshape(GROUPS, per, 3), first[i], walks=walks, seed=int(rng.integers(2**31))
            )
            f[i], stderr[i] = fi.reshape(pairs, 3), si.reshape(pairs, 3)
    out = {f"p_{name}": getattr(arrays, name) for name in StackArrays.FIELDS}
    out.update(wi=wi.astype(np.float32), wo=wo.astype(np.float32), f=f.astype(np.float32))
    if kind != "single":  # exact single-layer targets have no error to store
        out["stderr"] = stderr.astype(np.float32)
    return out


def parse_shard(text: str) -> tuple[int, int]:
    try:
        i, n = (int(x) for x in text.split("/"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--shard must look like i/n (e.g. 0/4), got {text!r}") from None
    if not (n >= 1 and 0 <= i < n):
        raise argparse.ArgumentTypeError(f"--shard {text!r}: need 0 <= i < n")
    return i, n


def check_counts(**counts: int) -> None:
    """``OptionError`` naming the first of ``counts`` (flag dest -> value) that is not a positive integer."""
    for k, v in counts.items():
        if not v >= 1:
            raise OptionError(f"--{k.replace('_', '-')} must be a positive integer, got {v}")


def read_manifest(out: Path) -> dict | None:
    """The manifest of the chunks under ``out`` (``prepare_out``), None where there is none (no data, or
    chunks from before manifests were written)."""
    path = Path(out) / MANIFEST
    return json.loads(path.read_text()) if path.exists() else None


def chunk_rows(path: Path) -> int:
    """Materials (stacks) in the finished chunk ``path``."""
    with np.load(path) as d:
        return int(d["p_base_kind"].shape[0])


def finished_chunks(out: Path) -> list[Path]:
    """The finished chunks under ``out``, in order (an interrupted chunk is still a ``.tmp.npz``)."""
    return sorted(p for p in Path(out).glob("chunk_*.npz") if not p.name.endswith(".tmp.npz"))


def prepare_out(out: Path, options: dict, count_flag: str, count: int, visible: Callable[[Path], dict], log) -> None:
    """Make ``out`` ready for chunks made with ``options`` (argparse dests -> values: the options that decide
    the chunks' contents) up to ``count`` rows (``count_flag``: ``materials`` or ``stacks``), and record them in
    ``out/manifest.json``.

    A folder whose manifest records other options, or more rows, raises ``OptionError`` naming the option: its
    chunks are not the ones this run would make. Chunks from before manifests are checked on what they show
    (``visible(chunk)``: the options readable from a chunk) and adopted with a log line."""
    out.mkdir(parents=True, exist_ok=True)
    held = read_manifest(out)
    chunks = finished_chunks(out)
    if held is None and chunks:
        held = visible(chunks[0]) | {count_flag: sum(chunk_rows(c) for c in chunks)}
        log(f"{out} holds chunks without a manifest: checked on {sorted(held)} only, the rest taken as asked")
    if held is not None:
        for k, v in options.items():
            if k in held and held[k] != v:
                raise OptionError(
                    f"{out} holds chunks made with --{k.replace('_', '-')} {held[k]}, this run asks for {v}: "
                    "remove the folder or write elsewhere"
                )
        if count < held.get(count_flag, 0):
            raise OptionError(
                f"{out} holds {held[count_flag]} {count_flag}, this run asks for --{count_flag} {count}: ask for "
                f"{held[count_flag]} or more (a training run can take fewer), or write elsewhere"
            )
    tmp = out / f"{MANIFEST}.{os.getpid()}.tmp"  # shards write the same manifest side by side
    tmp.write_text(json.dumps(options | {count_flag: count}, indent=1) + "\n")
    tmp.replace(out / MANIFEST)


def write_chunks(
    out: Path,
    count_flag: str,
    count: int,
    chunk: int,
    shard: tuple[int, int],
    make: Callable[[int, int], dict],
    what: Callable[[int, int], str],
    log,
) -> list[Path]:
    """Chunks ``j = shard[0], shard[0] + shard[1], ...`` of ``count`` rows (``count_flag``: materials or stacks),
    ``chunk`` a chunk, under ``out``: ``make(j, size)`` is chunk j's dict of arrays, ``what(j, size)`` its words
    in the progress log. A finished
    chunk of the right size is kept (an interrupted run resumes); one of another size (the short last chunk of
    a run with fewer rows) is made again. Returns the paths of this shard's chunks."""
    n_chunks = (count + chunk - 1) // chunk
    mine = list(range(shard[0], n_chunks, shard[1]))
    paths = [out / f"chunk_{j:05d}.npz" for j in mine]
    t0 = time.perf_counter()
    done = 0
    for j, path in zip(mine, paths, strict=True):
        size = min(chunk, count - j * chunk)
        if path.exists():
            held = chunk_rows(path)
            if held == size:
                continue
            log(f"{out}: chunk {j} holds {held} {count_flag}, --{count_flag} {count} needs {size}: making it again")
        data = make(j, size)
        tmp = path.with_suffix(".tmp.npz")
        np.savez(tmp, **data)
        tmp.replace(path)  # atomic: a killed run never leaves a half-written chunk
        done += 1
        el = time.perf_counter() - t0
        left = sum(1 for q in paths if not q.exists())
        log(f"{what(j, size)} {done} new, {left} left, {el:.1f} s, eta {el / done * left:.0f} s")
    return paths


def generate(
    kind: str,
    out: Path,
    materials: int,
    pairs: int,
    chunk: int,
    seed: int,
    shard: tuple[int, int] = (0, 1),
    walks: int = 64,
    log=print,
) -> list[Path]:
    """Write the chunks of this shard under ``out`` (skipping finished ones); return all paths. ``out`` must
    hold no chunks made with other options (``prepare_out``)."""
    check_counts(materials=materials, pairs=pairs, chunk=chunk, walks=walks)
    if kind != "single" and pairs % GROUPS:
        raise OptionError(f"--pairs must be a multiple of {GROUPS} for the layered set, got {pairs}")
    options = {"set": kind, "seed": seed, "pairs": pairs, "chunk": chunk} | (
        {} if kind == "single" else {"walks": walks}
    )

    def visible(path: Path) -> dict:
        with np.load(path) as d:
            return {"set": "layered" if "stderr" in d else "single", "pairs": int(d["wi"].shape[1])}

    prepare_out(out, options, "materials", materials, visible, log)
    return write_chunks(
        out,
        "materials",
        materials,
        chunk,
        shard,
        lambda j, size: make_chunk(kind, seed, j, size, pairs, walks),
        lambda j, size: f"[{kind} shard {shard[0]}/{shard[1]}] chunk {j} ({size} materials x {pairs} pairs)",
        log,
    )


def data_command(out: Path) -> str:
    """The command that makes the data under ``out`` as they are: the options of its manifest and the
    materials its chunks hold (chunks from before manifests: the set and pairs read from them, the other
    options their defaults)."""
    chunks = finished_chunks(out)
    if not chunks:
        raise FileNotFoundError(f"no data chunks under {out}; run python -m onnx_export.data first")
    held = read_manifest(out)
    if held is None:
        with np.load(chunks[0]) as d:
            held = {"set": "layered" if "stderr" in d else "single", "pairs": int(d["wi"].shape[1])}
    opts = {k: v for k, v in held.items() if k != "materials"}
    return command_line(
        "onnx_export.data",
        {"set": opts.pop("set"), "materials": sum(chunk_rows(c) for c in chunks), **opts, "out": str(out)},
    )


def load(out: Path) -> dict:
    """Concatenate all chunks under ``out`` (materials axis first)."""
    paths = finished_chunks(out)
    if not paths:
        raise FileNotFoundError(f"no data chunks under {out}; run python -m onnx_export.data first")
    parts = [dict(np.load(p)) for p in paths]
    keys = [k for k in parts[0] if all(k in q for q in parts)]
    # layered chunks differ in their number of coatings: keep what is common (directions, targets, base)
    return {
        k: np.concatenate([q[k] for q in parts], axis=0)
        for k in keys
        if all(q[k].shape[1:] == parts[0][k].shape[1:] for q in parts)
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--set", choices=("single", "layered"), default="single")
    ap.add_argument("--materials", type=positive_int, default=4096)
    ap.add_argument("--pairs", type=positive_int, default=1024)
    ap.add_argument("--chunk", type=positive_int, default=128)
    ap.add_argument("--walks", type=positive_int, default=64, help="reference walks per pair (layered only)")
    ap.add_argument("--seed", type=int, default=DEFAULT_SEED)
    ap.add_argument("--shard", type=parse_shard, default=(0, 1))
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args(argv)
    try:
        generate(
            a.set,
            a.out,
            a.materials,
            a.pairs,
            a.chunk,
            a.seed,
            a.shard,
            a.walks,
            log=lambda s: print(s, file=sys.stderr, flush=True),
        )
    except OptionError as e:  # options that do not fit the folder or each other
        ap.error(str(e))


if __name__ == "__main__":
    main()
