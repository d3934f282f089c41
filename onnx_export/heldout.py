"""The held-out benchmark set (docs/architecture.md, Measurement): fixed seeded configurations, never trained on.

    python -m onnx_export.heldout --set single --out tests/data/heldout_single.npz
    python -m onnx_export.heldout --set layered --walks 256 --fit-walks 32 --out tests/data/heldout_layered_lobes.npz

For each configuration it stores

- ``lobe`` (C, 4, R, R, 3): the lobe image f cos(theta_o) (``addon.core.lobe``) at the incident
  elevations ``addon.core.lobe.INCIDENT_ANGLES_DEG``, and ``lobe_stderr`` its standard error
  (0 for the exact single-layer values);
- ``fit_wi``, ``fit_wo``, ``fit_f``, ``fit_stderr`` (C, P, ...): separately drawn direction pairs
  with values, used to project the BRDF into a decoder's latent space (latent optimisation),
  so that the lobe error is measured on directions the projection did not see;
- ``stacks``: the configurations as JSON (``Stack.to_json``), and ``command``: how it was made.

Seeds differ from every training seed (training chunks are seeded (seed, chunk, set)).
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
from addon.core.stack import Coating, Conductor, Dielectric, Diffuse, Stack, StackArrays
from onnx_export.data import eval_single, lobe_alpha_of, sample_directions, sample_single_params

HELDOUT_SEED = 987_654_321
LOBE_RES = 32
FIT_PAIRS = 1024

GOLD = dict(eta=(0.143, 0.374, 1.442), k=(3.983, 2.385, 1.603))
COPPER = dict(eta=(0.200, 0.924, 1.102), k=(3.912, 2.452, 2.142))
ALUMINIUM = dict(eta=(1.657, 0.880, 0.521), k=(9.224, 6.270, 4.837))


def single_configs() -> list[Stack]:
    rng = np.random.default_rng(HELDOUT_SEED)
    out = [Stack(Diffuse(tuple(rng.random(3)))) for _ in range(4)]
    for a in (0.02, 0.08, 0.3, 0.7):
        for metal in (GOLD, COPPER, ALUMINIUM):
            out.append(Stack(Conductor(roughness=a, **metal)))
        for ior in (1.1, 1.5, 1.9):
            out.append(Stack(Dielectric(roughness=a, ior=ior)))
    rnd = sample_single_params(rng, 12)
    out += [rnd.stack(i) for i in range(len(rnd))]
    return out


def layered_configs() -> list[Stack]:
    """1, 2 and 3 coatings; low/high roughness; thin/thick, clear/tinted media; all base kinds."""
    rng = np.random.default_rng(HELDOUT_SEED + 1)
    bases = [
        Diffuse((0.7, 0.4, 0.1)),
        Conductor(roughness=0.05, **GOLD),
        Dielectric(roughness=0.2, ior=1.6),
        Conductor(roughness=0.4, **ALUMINIUM),
    ]
    out = []
    for i, base in enumerate(bases):
        for rough in (0.03, 0.3):
            clear = Coating(roughness=rough, ior=1.5)
            tinted_thin = Coating(roughness=rough, ior=1.4, albedo=(0.9, 0.5, 0.2), thickness=0.3)
            tinted_thick = Coating(roughness=rough, ior=1.7, albedo=(0.2, 0.6, 0.95), thickness=3.0)
            choice = (clear, tinted_thin, tinted_thick)[(i + int(rough > 0.1)) % 3]
            out.append(Stack(base, (choice,)))
        out.append(
            Stack(
                base,
                (
                    Coating(
                        roughness=float(rng.uniform(0.05, 0.5)),
                        ior=1.5,
                        albedo=tuple(rng.random(3)),
                        thickness=float(rng.uniform(0.2, 4.0)),
                    ),
                    Coating(roughness=0.05, ior=1.5),
                ),
            )
        )
    out.append(
        Stack(
            Diffuse((0.8, 0.8, 0.8)),
            (
                Coating(roughness=0.3, ior=1.4, albedo=(0.2, 0.6, 0.9), thickness=1.0),
                Coating(roughness=0.2, ior=1.6, albedo=(0.9, 0.9, 0.3), thickness=0.5),
                Coating(roughness=0.05, ior=1.5),
            ),
        )
    )
    out.append(
        Stack(
            Conductor(roughness=0.2, **COPPER),
            (
                Coating(roughness=0.1, ior=1.3, albedo=(0.9, 0.9, 0.9), thickness=4.0),
                Coating(roughness=0.5, ior=1.8),
                Coating(roughness=0.02, ior=1.5),
            ),
        )
    )
    return out


def stack_brdf(stack: Stack, walks: int, seed: int):
    """(brdf(wi, wo) -> (f, stderr)) of a stack: exact for single layers, reference otherwise."""
    if not stack.coatings:
        arrays = StackArrays.from_stacks([stack])

        def exact(wi, wo):
            f = eval_single(arrays, wi[None], wo[None])[0]
            return f, np.zeros_like(f)

        return exact
    from addon.core import reference

    return lambda wi, wo: reference.eval_brdf(stack, wi, wo, walks=walks, seed=seed)


def make(kind: str, walks: int, res: int, pairs: int, fit_walks: int = 64, log=print) -> dict:
    stacks = single_configs() if kind == "single" else layered_configs()
    c, na = len(stacks), len(lobe.INCIDENT_ANGLES_DEG)
    wo_grid, mask = lobe.lobe_grid(res)
    lobe_img = np.zeros((c, na, res * res, 3))
    lobe_err = np.zeros_like(lobe_img)
    t0 = time.perf_counter()
    for i, s in enumerate(stacks):  # one batched call per configuration (and elevation)
        if not s.coatings:
            brdf = stack_brdf(s, walks, HELDOUT_SEED + 17 * i)
            wi = np.concatenate(
                [np.broadcast_to(lobe.incident_direction(t), (int(mask.sum()), 3)) for t in lobe.INCIDENT_ANGLES_DEG]
            )
            wo = np.tile(wo_grid[mask], (na, 1))
            f, se = brdf(wi, wo)
            f, se = f.reshape(na, -1, 3), se.reshape(na, -1, 3)
        else:
            # amortised reference: by reciprocity f(wi, wo) = f(wo, wi), so one set of walks from
            # the incident direction serves every pixel of its lobe image
            from addon.core import reference

            f = np.zeros((na, int(mask.sum()), 3))
            se = np.zeros_like(f)
            for a, t in enumerate(lobe.INCIDENT_ANGLES_DEG):
                fa, sa = reference.eval_brdf_many(
                    s,
                    wo_grid[mask][None],
                    lobe.incident_direction(t)[None],
                    walks=walks,
                    seed=HELDOUT_SEED + 17 * i + a,
                )
                f[a], se[a] = fa[0], sa[0]
        cos_o = wo_grid[mask][None, :, 2:3]
        lobe_img[i][:, mask] = f * cos_o
        lobe_err[i][:, mask] = se * cos_o
        log(f"[heldout {kind}] lobes {i + 1}/{c} {time.perf_counter() - t0:.0f} s")
    rng = np.random.default_rng(HELDOUT_SEED + 2)
    alpha = np.array([_lobe_alpha(s) for s in stacks])
    fit_wi, fit_wo = sample_directions(rng, alpha, pairs)
    fit_f = np.zeros((c, pairs, 3))
    fit_se = np.zeros_like(fit_f)
    for i, s in enumerate(stacks):
        fit_f[i], fit_se[i] = stack_brdf(s, fit_walks, HELDOUT_SEED + 17 * i + 5)(fit_wi[i], fit_wo[i])
    return dict(
        lobe=lobe_img.reshape(c, na, res, res, 3).astype(np.float32),
        lobe_stderr=lobe_err.reshape(c, na, res, res, 3).astype(np.float32),
        angles=np.asarray(lobe.INCIDENT_ANGLES_DEG),
        fit_wi=fit_wi.astype(np.float32),
        fit_wo=fit_wo.astype(np.float32),
        fit_f=fit_f.astype(np.float32),
        fit_stderr=fit_se.astype(np.float32),
        stacks=np.array([s.to_json() for s in stacks]),
    )


def _lobe_alpha(s: Stack) -> float:
    return float(lobe_alpha_of(StackArrays.from_stacks([s]))[0])


def load(path) -> dict:
    d = dict(np.load(path, allow_pickle=False))
    d["stacks"] = [Stack.from_json(str(s)) for s in d["stacks"]]
    return d


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--set", choices=("single", "layered"), default="single")
    ap.add_argument("--walks", type=int, default=1024, help="reference walks per lobe pixel (layered)")
    ap.add_argument("--fit-walks", type=int, default=64, help="reference walks per projection pair (layered)")
    ap.add_argument("--res", type=int, default=LOBE_RES)
    ap.add_argument("--pairs", type=int, default=FIT_PAIRS)
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args(argv)
    d = make(a.set, a.walks, a.res, a.pairs, a.fit_walks, log=lambda s: print(s, file=sys.stderr, flush=True))
    d["command"] = np.array("python -m onnx_export.heldout " + " ".join(shlex.quote(x) for x in (argv or sys.argv[1:])))
    a.out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(a.out, **d)
    print(json.dumps({"configs": len(d["stacks"]), "out": str(a.out)}))


if __name__ == "__main__":
    main()
