"""Exact top coat + neural remainder, measured against the whole-BRDF latent design.

The first reflection at a stack's top interface is an analytic rough-dielectric lobe (GGX,
Fresnel): the interface between air and the top coating's medium, ``RoughDielectric(alpha, ior,
reflection_only=True)`` with the top coating's roughness and index (the walk's top event,
``addon.core.reference.walk``). In the *remainder* design the decoder represents only the rest of
the stack's BRDF (the light that entered the coat), and the two are summed.

This module holds the lobe (``top_reflection``) and the lobe images of it that the comparison
scores against the whole reference (``top_lobes``); ``train_decoder --remainder`` trains a decoder
on remainders (reference minus the top lobe) and ``layering bound --remainder`` projects held-out
remainders into such a decoder's latent space and scores top lobe + decoded remainder against the
whole reference (docs/layering_training.md, "Exact top coat + neural remainder").
"""

from __future__ import annotations

import numpy as np

from addon.core import lobe
from addon.core.bsdf import RoughDielectric
from addon.core.stack import StackArrays


def top_reflection(arrays: StackArrays, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """f (S, P, 3) of the top interface's reflection for stacks ``arrays`` (S rows) at the pairs
    ``wi``, ``wo`` (S, P, 3) (unit, local frame). Stacks without coatings give 0 (the base is the
    whole BRDF); a smooth top interface gives 0 (its mirror is a delta lobe, not part of f)."""
    wi = np.asarray(wi, dtype=np.float64)
    wo = np.asarray(wo, dtype=np.float64)
    s, p = wi.shape[:2]
    if wi.shape != (s, p, 3) or wo.shape != (s, p, 3) or len(arrays) != s:
        raise ValueError(f"wi, wo must be (S, P, 3) for {len(arrays)} stacks, got {wi.shape} and {wo.shape}")
    out = np.zeros((s, p, 3))
    n_coats = np.asarray(arrays.coat_roughness).shape[1]
    if n_coats == 0:
        return out
    alpha = np.repeat(np.asarray(arrays.coat_roughness, dtype=np.float64)[:, -1], p)
    ior = np.repeat(np.asarray(arrays.coat_ior, dtype=np.float64)[:, -1], p)
    f = RoughDielectric(alpha, ior, reflection_only=True).eval(wi.reshape(-1, 3), wo.reshape(-1, 3), check=False)
    f = np.asarray(f, dtype=np.float64).reshape(s * p, -1)
    out[:] = np.broadcast_to(f, (s * p, 3)).reshape(s, p, 3)
    return out


def top_lobes(arrays: StackArrays, res: int, angles) -> np.ndarray:
    """(S, A, res, res, 3) lobe images (f cos(theta_o), as ``addon.core.lobe``) of the top
    interface's reflection, for the held-out set's incident angles."""
    wo_grid, mask = lobe.lobe_grid(res)
    wo_m = wo_grid[mask]
    s, npx = len(arrays), wo_m.shape[0]
    out = np.zeros((s, len(angles), res * res, 3))
    for a, t in enumerate(angles):
        wi = np.broadcast_to(lobe.incident_direction(t), (s, npx, 3))
        f = top_reflection(arrays, wi, np.broadcast_to(wo_m, (s, npx, 3)))
        out[:, a][:, mask] = f * wo_m[None, :, 2:3]
    return out.reshape(s, len(angles), res, res, 3)
