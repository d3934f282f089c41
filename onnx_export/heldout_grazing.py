"""Grazing references of the held-out stacks: directional albedo and f cos(theta_i) near the horizon.

    python -m onnx_export.heldout_grazing --walks 4096 --res 16 --view-walks 32768 --full-walks 32768 \
        --out tests/data/heldout_grazing.npz

The stacks are those of ``tests/data/heldout_layered.npz`` (``heldout_layered.configs()``); the incident
elevations ``GRAZING_ANGLES_DEG`` run from 75 to 89.5 degrees. For each stack and elevation it stores

- ``albedo`` (C, A, 3): the directional albedo, the sum of a lobe image of resolution ``--res``
  (``addon.core.lobe``; the walks start at the incident direction and connect to every pixel, by
  reciprocity), with ``albedo_stderr`` from the walks' own spread (the pixels of one walk are correlated,
  so the standard error of the sum is bounded by the sum of the pixels' standard errors, which is stored);
- ``fcos`` (C, A, 3): f(wi, wo) cos(theta_i) with the viewer on the normal (wo = +z), the brightness a
  light at that elevation gives a surface seen head-on; the walks start at the viewer and connect to all
  incident directions at once, with ``fcos_stderr``.

- ``albedo_full`` (C, A, 3): the directional albedo integrated in full (analog walks from the incident
  direction, ``--full-walks`` each), with ``albedo_full_stderr``. The lobe grid holds anything from a few
  percent to all of a lobe's energy at grazing (its specular peaks fall between the grid's points,
  docs/calibration.md): the grid's sum compares two lobes at those points, this one what the issue's albedo
  targets are about.

A network's values on the same lobe grid and directions, and its directional albedo integrated by importance
sampling, give the grazing ratios (network / reference) that ``tests/training/test_grazing.py`` bounds.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from addon.core import lobe
from addon.core.stack import Stack, StackArrays
from onnx_export.heldout_layered import HELDOUT_SEED, configs

GRAZING_ANGLES_DEG = (75.0, 80.0, 82.0, 85.0, 86.0, 88.0, 89.5)
GRAZING_SEED = HELDOUT_SEED + 2000


def grazing_albedo_reference(stacks: list[Stack], angles, walks: int, res: int, seed: int, log=print):
    """(C, A, 3) albedo and the sum of the pixels' standard errors, from lobe images at ``angles``."""
    from addon.core import reference

    wo_grid, mask = lobe.lobe_grid(res)
    na = len(angles)
    inc = np.stack([lobe.incident_direction(t) for t in angles])
    alb = np.zeros((len(stacks), na, 3))
    err = np.zeros_like(alb)
    t0 = time.perf_counter()
    for c in sorted({len(s.coatings) for s in stacks}):
        idx = [i for i, s in enumerate(stacks) if len(s.coatings) == c]
        rows = StackArrays.from_stacks([stacks[i] for i in idx for _ in range(na)])
        wo = np.tile(inc, (len(idx), 1))
        wi = np.broadcast_to(wo_grid[mask], (wo.shape[0], int(mask.sum()), 3))
        f, se = reference.eval_brdf_many(rows, wi, wo, walks=walks, seed=seed + c)
        area = (2.0 / res) ** 2  # the grid is uniform on the projected disk: albedo = sum of f times the area
        alb[idx] = (f.sum(axis=1) * area).reshape(len(idx), na, 3)
        err[idx] = (se.sum(axis=1) * area).reshape(len(idx), na, 3)
        log(f"[heldout grazing] albedo, {len(idx)} stacks with {c} coating(s), {time.perf_counter() - t0:.0f} s")
    return alb, err


def grazing_fcos_reference(stacks: list[Stack], angles, walks: int, seed: int):
    """(C, A, 3) f(wi, +z) cos(theta_i) and its standard error, one walk set per stack from the viewer."""
    from addon.core import reference

    inc = np.stack([lobe.incident_direction(t) for t in angles])
    wo = np.tile([0.0, 0.0, 1.0], (len(stacks), 1))
    wi = np.broadcast_to(inc, (len(stacks), len(angles), 3))
    out_f = np.zeros((len(stacks), len(angles), 3))
    out_e = np.zeros_like(out_f)
    for c in sorted({len(s.coatings) for s in stacks}):  # one batched call per coating count (same layout)
        idx = [i for i, s in enumerate(stacks) if len(s.coatings) == c]
        rows = StackArrays.from_stacks([stacks[i] for i in idx])
        f, se = reference.eval_brdf_many(rows, wi[idx], wo[idx], walks=walks, seed=seed + 10 + c)
        out_f[idx], out_e[idx] = f, se
    cos_i = inc[:, 2][None, :, None]
    return out_f * cos_i, out_e * cos_i


def directional_albedo_reference(stacks: list[Stack], angles, walks: int, seed: int):
    """(C, A, 3) directional albedo integrated in full and its standard error: ``walks`` analog walks from
    each incident direction (``reference.albedo``), one call per stack."""
    from addon.core import reference

    inc = np.stack([lobe.incident_direction(t) for t in angles])
    out = [reference.albedo(s, inc, samples=walks, seed=seed + 20 + k) for k, s in enumerate(stacks)]
    return np.array([f for f, _ in out]), np.array([e for _, e in out])


@dataclass(frozen=True)
class Materials:
    """The runtime path's materials of held-out stacks: latents ``z`` (C, 3, 32), top coats ``top`` (C, 2),
    the sampling proxy's (sigma, w) per stack, and each stack's albedo calibration (None: decoder alone)."""

    z: np.ndarray
    top: np.ndarray
    proxies: list
    calibrations: list

    def brdf(self, models, k: int):
        """f(wi, wo) -> (N, 3) of stack ``k`` as the renderer evaluates it."""
        return lambda wi, wo: models.eval_brdf(self.z[k], wi, wo, self.top[k], self.calibrations[k])


def materials(models, stacks: list[Stack], calibrate: bool = False) -> Materials:
    """Each stack encoded as the renderer encodes it (one batch per coating count); with ``calibrate``, with
    its albedo calibration (``addon.core.neural.calibrate``)."""
    from addon.core.neural import calibrate as cal
    from addon.core.neural import encode_arrays, top_coats

    z = np.zeros((len(stacks), 3, 32), np.float32)
    top = np.zeros((len(stacks), 2))
    for c in sorted({len(s.coatings) for s in stacks}):
        idx = [i for i, s in enumerate(stacks) if len(s.coatings) == c]
        arrays = StackArrays.from_stacks([stacks[i] for i in idx])
        z[idx], top[idx] = encode_arrays(arrays, models), top_coats(arrays)
    if models.has("sampling"):
        proxies = [tuple(p) for p in models.proxy_params(z)]
    else:  # a candidate set without its sampling network: the renderer's guess from the stack
        from addon.core.render.neural_material import proxy_guess

        proxies = [proxy_guess(s) for s in stacks]
    calibrations = [cal.calibrate(s, models, z[k], proxies[k]) if calibrate else None for k, s in enumerate(stacks)]
    return Materials(z, top, proxies, calibrations)


def network_grazing(
    models, stacks: list[Stack], angles, res: int, calibrate: bool = False, mats: Materials | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The runtime path's (C, A, 3) albedo on the same lobe grid and f cos(theta_i) for the viewer on the
    normal; with ``calibrate``, of each stack's calibrated material (``addon.core.neural.calibrate``, as the
    renderer evaluates it). ``mats``: the materials, when already made."""
    mats = mats or materials(models, stacks, calibrate)
    return brdf_grazing([mats.brdf(models, k) for k in range(len(stacks))], angles, res)


def network_directional_albedo(
    models, stacks: list[Stack], angles, calibrate: bool = False, mats: Materials | None = None, seed: int = 77
) -> np.ndarray:
    """The runtime path's (C, A, 3) directional albedo at ``angles``, integrated in full: the decoded part by
    importance sampling (``calibrate.decoded_albedo``, its default sample count), plus the exact top lobe's."""
    from addon.core.neural import calibrate as cal

    mats = mats or materials(models, stacks, calibrate)
    cosines = np.cos(np.radians(np.asarray(angles, dtype=np.float64)))
    return np.array(
        [
            cal.decoded_albedo(
                models,
                mats.z[k],
                *mats.proxies[k],
                cosines,
                calibration=mats.calibrations[k],
                seed=seed,
                top=mats.top[k],
            )
            for k in range(len(stacks))
        ]
    )


def brdf_grazing(brdfs, angles, res: int) -> tuple[np.ndarray, np.ndarray]:
    """(C, A, 3) albedo on the lobe grid and f cos(theta_i) for the viewer on the normal of BRDFs
    ``brdfs`` (one ``f(wi, wo) -> (N, 3)`` per stack), at the incident angles ``angles``."""
    inc = np.stack([lobe.incident_direction(t) for t in angles])
    view = np.tile([0.0, 0.0, 1.0], (len(angles), 1))
    alb, fcos = [], []
    for f in brdfs:
        alb.append([lobe.albedo_from_lobe(lobe.lobe_image(f, t, res)) for t in angles])
        fcos.append(f(inc, view) * inc[:, 2:3])
    return np.array(alb), np.array(fcos)


def grazing_ratios(models, data: dict, calibrate: bool = False, full: bool = True) -> dict:
    """Network / reference of the albedo and of f cos(theta_i) (RGB mean), (C, A) each, with the angles;
    ``calibrate``: of the calibrated materials. With ``full``, where ``data`` holds ``albedo_full``, also
    ``albedo_full``: the directional albedo integrated in full, network / reference."""
    stacks = [s if isinstance(s, Stack) else Stack.from_json(str(s)) for s in data["stacks"]]
    mats = materials(models, stacks, calibrate)
    alb, fcos = network_grazing(models, stacks, data["angles"], int(data["res"]), mats=mats)
    integrated = None
    if full and "albedo_full" in data:
        integrated = network_directional_albedo(models, stacks, data["angles"], mats=mats)
    return ratios_to_reference(data, alb, fcos, integrated)


def ratios_to_reference(data: dict, alb: np.ndarray, fcos: np.ndarray, full: np.ndarray | None = None) -> dict:
    """The measured albedo and f cos (C, A, 3) over the reference's (RGB means), with the angles; with ``full``
    (C, A, 3), the directional albedo integrated in full over ``data["albedo_full"]`` too."""
    tiny = 1e-12
    out = {
        "angles": np.asarray(data["angles"]),
        "n_coatings": np.asarray(data["n_coatings"]),
        "albedo": alb.mean(-1) / np.maximum(data["albedo"].mean(-1), tiny),
        "fcos": fcos.mean(-1) / np.maximum(data["fcos"].mean(-1), tiny),
    }
    if full is not None:
        out["albedo_full"] = full.mean(-1) / np.maximum(data["albedo_full"].mean(-1), tiny)
    return out


BIAS_ANGLES_DEG = (75.0, 85.0)  # the incident elevations of the median albedo bias


def medians_by_coatings(ratios: dict, key: str = "albedo", angles=BIAS_ANGLES_DEG) -> dict:
    """The median of ``ratios[key]`` ((C, A) network / reference, from :func:`ratios_to_reference`) over the
    stacks of each coating count at each of ``angles``: {(angle, coatings): median}."""
    col = {t: list(ratios["angles"]).index(t) for t in angles}
    n_coat = np.asarray(ratios["n_coatings"])
    return {(t, int(c)): float(np.median(ratios[key][n_coat == c, col[t]])) for t in angles for c in np.unique(n_coat)}


def load(path) -> dict:
    d = dict(np.load(path, allow_pickle=False))
    d["stacks"] = [Stack.from_json(str(s)) for s in d["stacks"]]
    return d


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--walks", type=int, default=4096, help="reference walks per incident direction (lobe grid)")
    ap.add_argument("--res", type=int, default=16, help="lobe grid of the albedo")
    ap.add_argument("--view-walks", type=int, default=32768, help="walks from the viewer (f cos theta_i)")
    ap.add_argument(
        "--full-walks", type=int, default=32768, help="analog walks per incident direction (albedo integrated in full)"
    )
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args(argv)
    if min(a.walks, a.view_walks, a.full_walks) < 1 or a.res < 2:
        ap.error(
            f"--walks, --view-walks and --full-walks must be >= 1 and --res >= 2, got {a.walks}, {a.view_walks}, "
            f"{a.full_walks}, {a.res}"
        )
    lg = lambda s: print(s, file=sys.stderr, flush=True)  # noqa: E731
    stacks = configs()
    angles = GRAZING_ANGLES_DEG
    fcos, fcos_se = grazing_fcos_reference(stacks, angles, a.view_walks, GRAZING_SEED)
    lg("[heldout grazing] f cos done")
    alb, alb_se = grazing_albedo_reference(stacks, angles, a.walks, a.res, GRAZING_SEED, log=lg)
    full, full_se = directional_albedo_reference(stacks, angles, a.full_walks, GRAZING_SEED)
    lg("[heldout grazing] albedo integrated in full done")
    cmd = "python -m onnx_export.heldout_grazing " + " ".join(shlex.quote(x) for x in (argv or sys.argv[1:]))
    a.out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        a.out,
        albedo=alb.astype(np.float32),
        albedo_stderr=alb_se.astype(np.float32),
        fcos=fcos.astype(np.float32),
        fcos_stderr=fcos_se.astype(np.float32),
        albedo_full=full.astype(np.float32),
        albedo_full_stderr=full_se.astype(np.float32),
        angles=np.asarray(angles),
        res=np.array(a.res),
        n_coatings=np.array([len(s.coatings) for s in stacks]),
        stacks=np.array([s.to_json() for s in stacks]),
        command=np.array(cmd),
    )
    print(json.dumps({"stacks": len(stacks), "angles": list(angles), "out": str(a.out)}))


if __name__ == "__main__":
    main()
