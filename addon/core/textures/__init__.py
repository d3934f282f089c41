"""Latent textures: per-texel latents, mip chains, trilinear lookup, OpenEXR I/O."""

from .latent_texture import CHANNEL_NAMES, LATENT_CHANNELS, PROXY_CHANNELS, LatentTexture, LatentTextureError
from .mip import box_weights, build_mip_chain, downsample, trilinear_lookup

__all__ = [
    "CHANNEL_NAMES",
    "LATENT_CHANNELS",
    "PROXY_CHANNELS",
    "LatentTexture",
    "LatentTextureError",
    "box_weights",
    "build_mip_chain",
    "downsample",
    "trilinear_lookup",
]
