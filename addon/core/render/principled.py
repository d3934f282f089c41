"""A layer stack approximated by Principled BSDF inputs: the baseline artists use today.

Used to set up the same scene for Cycles/EEVEE (benchmarks, the demo .blend). Not a physical
equivalence: Principled's coat scales albedo with a view-dependent tint and has no light trapped
under the coat (docs/architecture.md, Physics traps), which is exactly the gap the layered materials close.
"""

from __future__ import annotations

import numpy as np

from ..bsdf.fresnel import fresnel_conductor
from ..stack import Conductor, Dielectric, Diffuse, Stack, artist_roughness_from_alpha


def principled_inputs(stack: Stack) -> dict:
    """Principled BSDF socket values (Blender 4.x/5.x names) approximating ``stack``.

    Base: Diffuse -> base colour, with no specular layer (Specular IOR Level 0: the stack has no interface on the
    base; Principled's default 0.5 added 14% in red to lacquered plastic); Conductor -> metallic with base colour =
    its normal-incidence Fresnel reflectance; Dielectric -> black base with the dielectric's IOR. Coatings: the top
    coating's roughness and IOR drive Coat; each coating's medium contributes a coat tint
    exp(-2 thickness (1 - albedo)) (its absorption only, in and out: Cycles' Coat Tint is the transmittance of the
    whole trip at normal incidence), multiplied over the coatings.
    Roughness values are artist roughness (sqrt of GGX alpha).
    """
    b = stack.base
    inputs = {"Roughness": 1.0, "Metallic": 0.0, "Base Color": (0.8, 0.8, 0.8, 1.0)}
    if isinstance(b, Diffuse):
        inputs["Base Color"] = (*b.albedo, 1.0)
        inputs["Specular IOR Level"] = 0.0
    elif isinstance(b, Conductor):
        f0 = fresnel_conductor(np.ones(1), np.asarray(b.eta), np.asarray(b.k))[0]
        inputs.update(
            {
                "Metallic": 1.0,
                "Base Color": (*(float(v) for v in f0), 1.0),
                "Roughness": artist_roughness_from_alpha(b.roughness),
            }
        )
    elif isinstance(b, Dielectric):
        inputs.update(
            {"Base Color": (0.0, 0.0, 0.0, 1.0), "IOR": b.ior, "Roughness": artist_roughness_from_alpha(b.roughness)}
        )
    if stack.coatings:
        top = stack.coatings[-1]
        tint = np.ones(3)
        for c in stack.coatings:
            tint *= np.exp(-2.0 * c.thickness * (1.0 - np.asarray(c.albedo)))
        inputs.update(
            {
                "Coat Weight": 1.0,
                "Coat Roughness": artist_roughness_from_alpha(top.roughness),
                "Coat IOR": top.ior,
                "Coat Tint": (*(float(v) for v in tint), 1.0),
            }
        )
    return inputs
