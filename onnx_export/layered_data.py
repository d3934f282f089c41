"""Training data of the layering network: stacks with 1 to 4 coatings and reference BRDF values.

    python -m onnx_export.layered_data --coatings 1 --stacks 3072 --out cache/data/layering_c1
    python -m onnx_export.layered_data --coatings 2 --stacks 1024 --out cache/data/layering_c2

Each stack gets ``--wo`` outgoing directions and, for each of them, ``--wi`` incident directions;
the targets come from the reference's amortised estimator
(:func:`addon.core.reference.eval_brdf_many`): every walk from ``wo`` connects to all ``--wi``
incident directions, so one walk pays for many values. Few walks per value and many values is the
better trade for training: the loss of :mod:`onnx_export.layering` has the mean as its minimiser,
so the Monte Carlo noise averages out over the data instead of biasing the fit.

Directions: ``wo`` half cosine-distributed, half uniform in solid angle (grazing included); for
each ``wo``, half of the ``wi`` are the mirror of ``wo`` about a GGX visible normal of the top
coating's roughness widened by a factor in [1, 2] (the specular lobe), a quarter cosine, a quarter
uniform. Parameters span the trained ranges (``onnx_export.data.sample_layered_params``).

Chunk ``j`` depends only on ``(seed, coatings, j)``: ``--shard i/n`` makes chunks i, i+n, ...;
finished chunks are skipped, so a killed run resumes where it stopped. ``OUT/manifest.json`` records the
options the chunks were made with, as for ``onnx_export.data`` (``data.prepare_out``): a rerun with other
options is refused, a larger ``--stacks`` adds chunks and makes a short last chunk again.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from addon.core.bsdf import ggx
from addon.core.bsdf.lambert import sample_cosine_hemisphere
from addon.core.stack import StackArrays
from onnx_export.cli import command_line, positive_int
from onnx_export.data import (
    OptionError,
    check_counts,
    chunk_rows,
    finished_chunks,
    parse_shard,
    prepare_out,
    read_manifest,
    sample_layered_params,
    uniform_hemisphere,
    write_chunks,
)

DEFAULT_SEED = 11
DEFAULT_WALKS = 8


def _unit_above(w: np.ndarray) -> np.ndarray:
    w = w.copy()
    w[..., 2] = np.maximum(w[..., 2], 1e-4)
    w /= np.linalg.norm(w, axis=-1, keepdims=True)
    # values are computed at the float32 directions that are stored and fed to the networks
    return w.astype(np.float32).astype(np.float64)


def sample_query_directions(rng: np.random.Generator, lobe_alpha: np.ndarray, n_wo: int, n_wi: int):
    """``wo`` (S, n_wo, 3) and ``wi`` (S, n_wo, n_wi, 3) for S stacks whose top coating has roughness
    ``lobe_alpha`` (S,)."""
    s = lobe_alpha.shape[0]
    wo_u = uniform_hemisphere(rng.random((s, n_wo, 2)))
    wo_c = sample_cosine_hemisphere(rng.random((s * n_wo, 2))).reshape(s, n_wo, 3)
    wo = _unit_above(np.where((rng.random((s, n_wo)) < 0.5)[..., None], wo_u, wo_c))
    shape = (s, n_wo, n_wi)
    which = rng.random(shape)
    wi_u = uniform_hemisphere(rng.random(shape + (2,)))
    wi_c = sample_cosine_hemisphere(rng.random((int(np.prod(shape)), 2))).reshape(shape + (3,))
    a = np.minimum(1.0, lobe_alpha[:, None, None] * rng.uniform(1.0, 2.0, shape))
    wo_rep = np.broadcast_to(wo[:, :, None, :], shape + (3,)).reshape(-1, 3)
    h = ggx.sample_visible_normal(wo_rep, a.reshape(-1), rng.random((wo_rep.shape[0], 2))).reshape(shape + (3,))
    wi_l = 2.0 * np.einsum("spmi,spmi->spm", wo[:, :, None, :], h)[..., None] * h - wo[:, :, None, :]
    wi = np.where((which < 0.25)[..., None], wi_u, wi_c)
    wi = np.where(((which >= 0.5) & (wi_l[..., 2] > 1e-4))[..., None], wi_l, wi)
    return wo, _unit_above(wi)


def make_chunk(seed: int, coatings: int, chunk: int, stacks: int, n_wo: int, n_wi: int, walks: int) -> dict:
    """One chunk of ``stacks`` stacks as a dict of arrays; deterministic in (seed, coatings, chunk)."""
    from addon.core import reference

    rng = np.random.default_rng([seed, coatings, chunk, 77])
    arrays = sample_layered_params(rng, stacks, coatings)
    wo, wi = sample_query_directions(rng, arrays.coat_roughness[:, -1], n_wo, n_wi)
    rows = arrays.take(np.repeat(np.arange(stacks), n_wo))  # one stack per (stack, wo) row: one batched call
    f, se = reference.eval_brdf_many(
        rows, wi.reshape(-1, n_wi, 3), wo.reshape(-1, 3), walks=walks, seed=int(rng.integers(2**31))
    )
    out = {f"p_{name}": getattr(arrays, name) for name in StackArrays.FIELDS}
    out.update(
        wo=wo.astype(np.float32),
        wi=wi.astype(np.float32),
        f=f.reshape(stacks, n_wo, n_wi, 3).astype(np.float32),
        stderr=se.reshape(stacks, n_wo, n_wi, 3).astype(np.float32),
        walks=np.full(stacks, walks),
    )
    return out


def generate(
    out: Path,
    coatings: int,
    stacks: int,
    n_wo: int,
    n_wi: int,
    walks: int,
    chunk: int,
    seed: int,
    shard=(0, 1),
    log=print,
) -> list[Path]:
    """Write the chunks of this shard under ``out`` (skipping finished ones); return their paths. ``out`` must
    hold no chunks made with other options (``data.prepare_out``)."""
    check_counts(stacks=stacks, wo=n_wo, wi=n_wi, walks=walks, chunk=chunk)
    options = {"coatings": coatings, "seed": seed, "wo": n_wo, "wi": n_wi, "walks": walks, "chunk": chunk}

    def visible(path: Path) -> dict:
        with np.load(path) as d:
            shown = {"coatings": d["p_coat_roughness"].shape[1], "wo": d["wi"].shape[1], "wi": d["wi"].shape[2]}
            return {k: int(v) for k, v in shown.items()} | ({"walks": int(d["walks"][0])} if "walks" in d else {})

    prepare_out(out, options, "stacks", stacks, visible, log)
    return write_chunks(
        out,
        "stacks",
        stacks,
        chunk,
        shard,
        lambda j, size: make_chunk(seed, coatings, j, size, n_wo, n_wi, walks),
        lambda j, size: (
            f"[layering data c{coatings} shard {shard[0]}/{shard[1]}] chunk {j} ({size} stacks x {n_wo} x {n_wi} "
            f"values, {walks} walks)"
        ),
        log,
    )


def chunk_paths(out: Path) -> list[Path]:
    """The finished chunks under ``out``, in order (an interrupted chunk is still a ``.tmp.npz``)."""
    return finished_chunks(out)


def load(out: Path) -> dict:
    """All chunks under ``out`` concatenated along the stack axis, with ``arrays`` (StackArrays)."""
    paths = chunk_paths(out)
    if not paths:
        raise FileNotFoundError(f"no layering data under {out}; run python -m onnx_export.layered_data first")
    parts = [dict(np.load(p)) for p in paths]
    d = {k: np.concatenate([q[k] for q in parts]) for k in parts[0]}
    d["arrays"] = StackArrays(**{f: d.pop(f"p_{f}") for f in StackArrays.FIELDS})
    return d


def holds_layering_data(out: Path) -> bool:
    """True when ``out`` holds chunks of this module (incident directions per outgoing direction),
    False for other data (``onnx_export.data``) or none."""
    chunks = chunk_paths(out)
    return bool(chunks) and np.load(chunks[0])["wi"].ndim == 4


def data_command(out: Path, coatings: int | None = None, default_stacks: int = 0) -> str:
    """The command that makes the layering data under ``out``: the options of its manifest and the stacks its
    chunks hold; chunks from before manifests: their coatings, stacks and walks as found there, the other
    options their defaults; no data here: ``coatings`` and ``default_stacks`` (data not on this machine)."""
    chunks = chunk_paths(out)
    held = read_manifest(out) if chunks else None
    if held is not None:
        opts = {k: v for k, v in held.items() if k != "stacks"}
        stacks = sum(chunk_rows(c) for c in chunks)
        return command_line(
            "onnx_export.layered_data",
            {"coatings": opts.pop("coatings"), "stacks": stacks, **opts, "out": str(out)},
        )
    if chunks:
        first = np.load(chunks[0])
        coatings = first["p_coat_roughness"].shape[1]
        stacks = sum(chunk_rows(c) for c in chunks)
        walks = int(first["walks"][0]) if "walks" in first else DEFAULT_WALKS  # chunks from before it was recorded
        if walks != DEFAULT_WALKS:
            return (
                f"python -m onnx_export.layered_data --coatings {coatings} --stacks {stacks} --walks {walks} "
                f"--out {out}"
            )
    elif coatings is None:
        raise FileNotFoundError(f"no layering data under {out}, and no number of coatings given")
    else:
        stacks = default_stacks
    return f"python -m onnx_export.layered_data --coatings {coatings} --stacks {stacks} --out {out}"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--coatings", type=int, default=1, choices=(1, 2, 3, 4))
    ap.add_argument("--stacks", type=positive_int, default=3072)
    ap.add_argument("--wo", type=positive_int, default=16, help="outgoing directions per stack")
    ap.add_argument("--wi", type=positive_int, default=64, help="incident directions per outgoing direction")
    ap.add_argument("--walks", type=positive_int, default=DEFAULT_WALKS, help="reference walks per outgoing direction")
    ap.add_argument("--chunk", type=positive_int, default=128)
    ap.add_argument("--seed", type=int, default=DEFAULT_SEED)
    ap.add_argument("--shard", type=parse_shard, default=(0, 1))
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args(argv)
    try:
        generate(
            a.out,
            a.coatings,
            a.stacks,
            a.wo,
            a.wi,
            a.walks,
            a.chunk,
            a.seed,
            a.shard,
            log=lambda s: print(s, file=sys.stderr, flush=True),
        )
    except OptionError as e:  # options that do not fit the folder
        ap.error(str(e))


if __name__ == "__main__":
    main()
