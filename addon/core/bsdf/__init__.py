"""Analytic BSDFs in the local shading frame (normal +z): one implementation of each formula.

See ``base.py`` for the interface (eval / pdf / sample, modes, BSDFSample) and
docs/architecture.md for the conventions.
"""

from . import frame, fresnel, ggx
from .base import BSDF, IMPORTANCE, RADIANCE, SMOOTH_ALPHA, BSDFSample
from .conductor import RoughConductor
from .dielectric import RoughDielectric
from .frame import (
    coordinate_system,
    cos_theta,
    normalize,
    reflect,
    refract,
    same_hemisphere,
    to_local,
    to_world,
)
from .fresnel import fresnel_conductor, fresnel_dielectric
from .ggx import ndf, pdf_visible_normal, sample_visible_normal, smith_g1, smith_g2, smith_lambda
from .lambert import Lambertian
from .phase import HenyeyGreenstein
from .specular_diffuse import SpecularDiffuse, specular_ior

__all__ = [
    "BSDF",
    "BSDFSample",
    "HenyeyGreenstein",
    "IMPORTANCE",
    "Lambertian",
    "RADIANCE",
    "RoughConductor",
    "RoughDielectric",
    "SMOOTH_ALPHA",
    "SpecularDiffuse",
    "coordinate_system",
    "cos_theta",
    "frame",
    "fresnel",
    "fresnel_conductor",
    "fresnel_dielectric",
    "ggx",
    "ndf",
    "normalize",
    "pdf_visible_normal",
    "reflect",
    "refract",
    "same_hemisphere",
    "sample_visible_normal",
    "smith_g1",
    "smith_g2",
    "smith_lambda",
    "specular_ior",
    "to_local",
    "to_world",
]
