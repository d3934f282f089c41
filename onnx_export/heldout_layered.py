"""The held-out layered set: seeded stacks with 1 to 4 coatings, never trained on, with reference lobes.

    python -m onnx_export.heldout_layered --walks 256 --res 24 --out tests/data/heldout_layered.npz

For each configuration it stores ``lobe`` (C, 4, R, R, 3), the lobe image f cos(theta_o) of
:mod:`addon.core.lobe` at the incident elevations ``lobe.INCIDENT_ANGLES_DEG``, its standard error
``lobe_stderr``, the number of coatings ``n_coatings`` (C,), the stacks as JSON, the command(s) and
``walks`` (C,), the walks per incident direction of each stack (-1: as in the first command). The
stacks with one, two and three coatings were recomputed with more walks (``--only-coatings 1 --walks 4096``,
the same for 2 and 3): at 512 walks their reference noise was a large part of the error, and for the
smoothest coats the noisy reference had hidden part of the networks' error at grazing angles.

The reference values come from :func:`addon.core.reference.eval_brdf_many` by reciprocity: the
walks start from the incident direction and connect to every pixel of the lobe grid, so a lobe
image costs ``4 * walks`` walks. Training data are seeded ``(11, coatings, chunk, 77)``; this set
uses ``HELDOUT_SEED`` and hand-picked configurations, so no stack here is a training stack.

    python -m onnx_export.heldout_layered --validation 64 32 --walks 512 --out cache/data/validation_layered.npz

makes a validation set instead: random stacks of the training distribution (64 with one coating, 32
with two) seeded with ``VALIDATION_SEED``, for choosing between training recipes without looking at
the held-out set. It has the same format. ``--seed`` draws another one (stacks and reference walks),
for two rounds the first cannot tell apart (docs/layering_training.md, round 8).

    python -m onnx_export.heldout_layered --training cache/data/layering_c1_w64 32 cache/data/layering_c2_w64 16 \
        --walks 512 --out cache/data/fit_layered.npz

makes a set of *training* stacks (the first N of each ``onnx_export.layered_data`` directory, in its
order) with references as the validation set's: a network's error on it against its error on the
validation set says whether it under-fits (both alike) or over-fits (training much lower). Any of the
three files goes to ``benchmarks/bench_layering.py --heldout``.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path

import numpy as np

from addon.core import lobe
from addon.core.stack import PRESETS, Coating, Conductor, Dielectric, Diffuse, Stack, StackArrays
from onnx_export.data import sample_layered_params

HELDOUT_SEED = 424_242
VALIDATION_SEED = 515_151
GOLD = dict(eta=(0.143, 0.374, 1.442), k=(3.983, 2.385, 1.603))
ALUMINIUM = dict(eta=(1.657, 0.880, 0.521), k=(9.224, 6.270, 4.837))

# configurations the variance benchmark calls "specular" and "diffuse" (indices into configs())
SPECULAR_INDEX = 1
DIFFUSE_INDEX = 3


def configs() -> list[Stack]:
    """16 stacks with one coating, 8 with two, 4 with three, 4 with four."""
    out = [
        Stack(Conductor(roughness=0.05, **GOLD), (Coating(roughness=0.3, ior=1.5),)),
        Stack(Conductor(roughness=0.3, **ALUMINIUM), (Coating(roughness=0.03, ior=1.5),)),  # specular
        Stack(
            Dielectric(roughness=0.2, ior=1.6),
            (Coating(roughness=0.1, ior=1.3, albedo=(0.9, 0.5, 0.2), thickness=0.5),),
        ),
        Stack(Diffuse((0.7, 0.4, 0.1)), (Coating(roughness=0.05, ior=1.5),)),  # diffuse (coated)
        Stack(Diffuse((0.2, 0.5, 0.8)), (Coating(roughness=0.6, ior=1.4, albedo=(0.8, 0.8, 0.8), thickness=1.0),)),
        Stack(
            Conductor(roughness=0.02, **GOLD),
            (Coating(roughness=0.15, ior=1.7, albedo=(0.2, 0.6, 0.95), thickness=3.0),),
        ),
        Stack(Diffuse((0.9, 0.9, 0.9)), (Coating(roughness=0.02, ior=1.9, albedo=(0.95, 0.3, 0.3), thickness=4.5),)),
        Stack(Dielectric(roughness=0.5, ior=1.2), (Coating(roughness=0.01, ior=1.1),)),
    ]
    rng = np.random.default_rng(HELDOUT_SEED)
    for c, n in ((1, 8), (2, 7), (3, 3), (4, 4)):
        a = sample_layered_params(rng, n, c)
        out += [a.stack(i) for i in range(n)]
        if c == 2:
            out.append(PRESETS["red_car_paint"])
        if c == 3:
            out.append(PRESETS["three_layer"])
    return out


def validation_configs(counts: list[int], seed: int = VALIDATION_SEED) -> list[Stack]:
    """``counts[c - 1]`` random stacks with c coatings, drawn as the training stacks are."""
    rng = np.random.default_rng(seed)
    out = []
    for c, n in enumerate(counts, start=1):
        a = sample_layered_params(rng, n, c)
        out += [a.stack(i) for i in range(n)]
    return out


def training_configs(sources: list[tuple[Path, int]]) -> list[Stack]:
    """The first ``n`` stacks of each training data directory ``(dir, n)`` of ``onnx_export.layered_data``."""
    from onnx_export.layered_data import chunk_paths

    out = []
    for d, n in sources:
        got = []
        for p in chunk_paths(d):
            if len(got) >= n:
                break
            with np.load(p) as c:
                a = StackArrays(**{f: c[f"p_{f}"] for f in StackArrays.FIELDS})
            got += [a.stack(i) for i in range(min(n - len(got), len(a)))]
        if len(got) < n:
            raise ValueError(f"{d} holds {len(got)} finished stacks, fewer than the {n} asked for")
        out += got
    return out


def reference_lobes(stacks: list[Stack], walks: int, res: int, seed: int, log=print):
    """(C, A, res, res, 3) reference lobe images and standard errors, one batched call per coating count."""
    from addon.core import reference

    wo_grid, mask = lobe.lobe_grid(res)
    angles = lobe.INCIDENT_ANGLES_DEG
    na = len(angles)
    inc = np.stack([lobe.incident_direction(t) for t in angles])
    img = np.zeros((len(stacks), na, res * res, 3))
    err = np.zeros_like(img)
    t0 = time.perf_counter()
    counts = sorted({len(s.coatings) for s in stacks})
    for c in counts:
        idx = [i for i, s in enumerate(stacks) if len(s.coatings) == c]
        rows = StackArrays.from_stacks([stacks[i] for i in idx for _ in range(na)])
        wo = np.tile(inc, (len(idx), 1))  # walks start at the incident direction (reciprocity)
        wi = np.broadcast_to(wo_grid[mask], (wo.shape[0], int(mask.sum()), 3))
        f, se = reference.eval_brdf_many(rows, wi, wo, walks=walks, seed=seed + c)
        cos_o = wo_grid[mask, 2][None, :, None]
        img_c = np.zeros((len(idx), na, res * res, 3))
        err_c = np.zeros_like(img_c)
        img_c[:, :, mask] = (f * cos_o).reshape(len(idx), na, -1, 3)
        err_c[:, :, mask] = (se * cos_o).reshape(len(idx), na, -1, 3)
        img[idx] = img_c
        err[idx] = err_c
        log(f"[heldout layered] {len(idx)} stacks with {c} coating(s) done, {time.perf_counter() - t0:.0f} s")
    return img.reshape(len(stacks), na, res, res, 3), err.reshape(len(stacks), na, res, res, 3)


def load(path) -> dict:
    d = dict(np.load(path, allow_pickle=False))
    d["stacks"] = [Stack.from_json(str(s)) for s in d["stacks"]]
    return d


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--walks", type=int, default=256, help="reference walks per incident direction")
    ap.add_argument("--res", type=int, default=24)
    ap.add_argument(
        "--only-coatings",
        type=int,
        default=0,
        help="recompute only the stacks with this many coatings in an existing --out file (more walks "
        "where the reference is noisiest); the other rows are kept",
    )
    ap.add_argument(
        "--validation",
        type=int,
        nargs="+",
        default=None,
        metavar="N",
        help="a validation set: N random stacks with one coating, N2 with two, ... (not the held-out set)",
    )
    ap.add_argument(
        "--seed",
        type=int,
        default=VALIDATION_SEED,
        help="with --validation: the seed of the stacks and of the reference walks (another seed, "
        "another validation set); with --training: of the reference walks",
    )
    ap.add_argument(
        "--training",
        nargs="+",
        default=None,
        metavar="DIR N",
        help="a set of training stacks: the first N stacks of each layered_data directory DIR",
    )
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args(argv)
    if a.seed != VALIDATION_SEED and not (a.validation or a.training):
        ap.error("--seed draws another validation set (or the walks of a --training set): give --validation")
    if a.seed in (HELDOUT_SEED, HELDOUT_SEED + 1000):
        ap.error("--seed must differ from the held-out set's")
    if a.validation and (a.only_coatings or min(a.validation) < 0):
        ap.error("--validation takes counts >= 0 and makes a new file (no --only-coatings)")
    if a.training is not None:
        pairs = a.training
        if (
            a.validation
            or a.only_coatings
            or len(pairs) % 2
            or not all(n.isdigit() and int(n) > 0 for n in pairs[1::2])
        ):
            ap.error("--training takes pairs DIR N (N > 0) and makes a new file (no --validation, --only-coatings)")
        try:
            stacks = training_configs([(Path(d), int(n)) for d, n in zip(pairs[::2], pairs[1::2], strict=False)])
        except (FileNotFoundError, ValueError) as e:
            ap.error(str(e))
    else:
        stacks = validation_configs(a.validation, a.seed) if a.validation else configs()
    cmd = "python -m onnx_export.heldout_layered " + " ".join(shlex.quote(x) for x in (argv or sys.argv[1:]))
    lg = lambda s: print(s, file=sys.stderr, flush=True)  # noqa: E731
    if a.only_coatings:
        old = dict(np.load(a.out))
        idx = [i for i, s in enumerate(stacks) if len(s.coatings) == a.only_coatings]
        img, err = old["lobe"].copy(), old["lobe_stderr"].copy()
        img[idx], err[idx] = reference_lobes([stacks[i] for i in idx], a.walks, a.res, HELDOUT_SEED + 1000, log=lg)
        walks = old.get("walks", np.full(len(stacks), -1))
        walks[idx] = a.walks
        command = np.array(str(old["command"]) + " && " + cmd)
    else:
        seed = a.seed if a.validation or a.training else HELDOUT_SEED
        img, err = reference_lobes(stacks, a.walks, a.res, seed, log=lg)
        walks = np.full(len(stacks), a.walks)
        command = np.array(cmd)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        a.out,
        lobe=img.astype(np.float32),
        lobe_stderr=err.astype(np.float32),
        angles=np.asarray(lobe.INCIDENT_ANGLES_DEG),
        n_coatings=np.array([len(s.coatings) for s in stacks]),
        stacks=np.array([s.to_json() for s in stacks]),
        walks=walks,
        command=command,
    )
    print(
        json.dumps(
            {
                "configs": len(stacks),
                "by_coatings": np.bincount([len(s.coatings) for s in stacks]).tolist(),
                "out": str(a.out),
            }
        )
    )


if __name__ == "__main__":
    main()


def _calibrations(models, stacks: list, z: np.ndarray) -> list:
    """The albedo calibration the renderer gives each stack's latent (``neural_material.make``): against the
    reference, with the size's sampling proxy."""
    from addon.core.neural import calibrate
    from addon.core.render.neural_material import proxy_guess

    proxies = models.proxy_params(z) if models.has("sampling") else [proxy_guess(s) for s in stacks]
    return [calibrate.calibrate(s, models, z[k], proxies[k]) for k, s in enumerate(stacks)]


def _lobes(models, z, top, calibration, angles, res: int, swap: bool = False) -> np.ndarray:
    """(angles, R, R, 3) lobe images of one latent (``swap``: the decoder's two directions exchanged)."""

    def f(wi, wo):
        return models.eval_brdf(z, wo if swap else wi, wi if swap else wo, top, calibration)

    return np.array([lobe.lobe_image(f, t, res) for t in angles])


def runtime_errors(models, data: dict, res: int | None = None, calibrated: bool = False) -> dict:
    """Held-out lobe errors of the RUNTIME path (ONNX encoders + layering + decoder) per coating count.

    ``calibrated``: each stack's latent decoded with its albedo calibration, as the renderer decodes a
    material's own latent by default (``neural_material.make(..., calibrate=True)``: about a second of
    reference walks per stack, ``addon.core.neural.calibrate``); latent textures are not calibrated.

    Returns {n_coatings: {"errors": (configs, angles) relative RMSE, "albedo_error": (configs, angles, 3)
    |albedo - reference albedo|, "albedo_bias": (configs, angles) (albedo - reference) / reference of the
    RGB mean (signed: > 0 the network reflects too much), "lobes": (configs, angles, R, R, 3), "index":
    config indices, "reference_noise": (configs, angles) the reference's own relative standard error
    ||stderr|| / ||ref||, "reciprocity": (configs, angles) the relative RMSE of the lobe decoded with the
    two directions swapped, f(wo, wi) cos(theta_o), against the lobe as measured (the reference BRDF is
    reciprocal; the decoder is not by construction), "errors_swapped": (configs, angles) the relative RMSE
    of that swapped lobe against the reference}}.
    """
    from addon.core.neural import encode_arrays, top_coats

    stacks = data["stacks"]
    stacks = [s if isinstance(s, Stack) else Stack.from_json(str(s)) for s in stacks]
    res = res or data["lobe"].shape[2]
    angles = [float(t) for t in data["angles"]]
    out = {}
    for c in sorted({len(s.coatings) for s in stacks}):
        idx = [i for i, s in enumerate(stacks) if len(s.coatings) == c]
        arrays = StackArrays.from_stacks([stacks[i] for i in idx])
        z, top = encode_arrays(arrays, models), top_coats(arrays)  # top: a remainder decoder's exact top lobe
        cal = _calibrations(models, [stacks[i] for i in idx], z) if calibrated else [None] * len(idx)

        lobes = np.array([_lobes(models, z[k], top[k], cal[k], angles, res) for k in range(len(idx))])
        swapped = np.array([_lobes(models, z[k], top[k], cal[k], angles, res, swap=True) for k in range(len(idx))])
        ref = data["lobe"][idx]
        err = lobe.relative_rmse(lobes, ref, image_axes=3)  # (stacks, angles)
        alb_net, alb_ref = lobe.albedo_from_lobe(lobes), lobe.albedo_from_lobe(ref)
        alb = np.abs(alb_net - alb_ref)
        bias = (alb_net.mean(-1) - alb_ref.mean(-1)) / np.maximum(alb_ref.mean(-1), 1e-12)
        noise = lobe.relative_rmse(ref + data["lobe_stderr"][idx], ref, image_axes=3)
        recip = lobe.relative_rmse(swapped, lobes, image_axes=3)
        err_sw = lobe.relative_rmse(swapped, ref, image_axes=3)
        out[c] = {
            "errors": err,
            "albedo_error": alb,
            "albedo_bias": bias,
            "lobes": lobes,
            "index": idx,
            "reference_noise": noise,
            "reciprocity": recip,
            "errors_swapped": err_sw,
        }
    return out
