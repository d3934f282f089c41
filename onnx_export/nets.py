"""Network definitions (torch): the decoder zoo and the single-layer encoder.

The decoder is one scalar network f(z_c, wi, wo) -> f_c >= 0 shared by the three colour
channels (the paper's layout, 32 latent floats per channel). The direction encoding is part of
the network, so the exported ONNX graph takes the raw directions ``wi``, ``wo`` (B, 3).
"""

from __future__ import annotations

import math

import torch
from torch import nn

from addon.core.stack import LATENT  # floats per colour channel of a latent (the runtime's)

# name -> (hidden width, hidden layers); "paper" is the topology of Fan et al. 2022
SIZES = {
    "tiny": (32, 3),
    "small": (64, 3),
    "medium": (128, 4),
    "paper": (256, 16),
}

# sharpness of the fixed half-vector bumps exp(-s (1 - cos theta_h)): a GGX lobe of roughness
# alpha has width 1 - cos theta_h ~ alpha^2 / 2, so these cover alpha from about 0.01 to 1
BUMP_SHARPNESS = (2.0, 20.0, 200.0, 2000.0, 20000.0)
MAX_LOG_F = 16.0  # exp output clamp: f <= e^16 ~ 9e6 1/sr (a GGX peak at alpha 0.01 is ~3e3)


def direction_features(wi: torch.Tensor, wo: torch.Tensor, kind: str) -> torch.Tensor:
    """(B, F) features of the direction pairs. ``raw``: the paper's xyz of both directions.
    ``iso``: rotation-invariant terms (cos theta_i, cos theta_o, wi.wo, cos theta_h, wi.h,
    sin theta_h) and fixed bumps in theta_h that let a small network build sharp lobes.

    The terms are computed on the components as rows (``wi.t()``: contiguous (B,) vectors) and
    stacked at the end: the same values as on (B, 1) columns, but ONNX Runtime runs the exported
    element-wise graph about four times faster on rows (docs/decoders_bench.md)."""
    if kind == "raw":
        return torch.cat([wi, wo], dim=-1)
    a, b = wi.t(), wo.t()
    ci, co = a[2], b[2]
    dio = a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
    sx, sy, sz = a[0] + b[0], a[1] + b[1], a[2] + b[2]
    # 1 - cos(theta_h) and sin(theta_h) without cancellation: with sxy = s_x^2 + s_y^2 and
    # |s| = sqrt(sxy + s_z^2), 1 - s_z / |s| = sxy / (|s| (|s| + s_z)). The sharpest bump
    # multiplies 1 - cos(theta_h) by 2e4, so ``1 - hz`` in float32 (an error of 6e-8 near the
    # peak) would change it by 1e-3 relative, and two correct float32 implementations (torch,
    # ONNX Runtime) would disagree by that much.
    sxy = sx * sx + sy * sy
    sn = torch.sqrt(torch.clamp(sxy + sz * sz, min=1e-12))
    hz = sz / sn
    dh = torch.sqrt(torch.clamp(0.5 * (1.0 + dio), min=0.0))  # wi.h = cos(theta_d)
    one_minus = sxy / torch.clamp(sn * (sn + sz), min=1e-12)
    sin_h = torch.sqrt(sxy) / sn
    feats = [ci, co, dio, hz, dh, sin_h]
    if kind == "iso_bumps":
        feats += [torch.exp(-s_ * one_minus) for s_ in BUMP_SHARPNESS]
    elif kind != "iso":
        raise ValueError(f"unknown direction features {kind!r}; expected raw, iso or iso_bumps")
    return torch.stack(feats, dim=1)


def n_direction_features(kind: str) -> int:
    return {"raw": 6, "iso": 6, "iso_bumps": 6 + len(BUMP_SHARPNESS)}[kind]


def mlp(n_in: int, width: int, depth: int, n_out: int) -> nn.Sequential:
    layers: list[nn.Module] = []
    d = n_in
    for _ in range(depth):
        layers += [nn.Linear(d, width), nn.ReLU()]
        d = width
    layers.append(nn.Linear(d, n_out))
    return nn.Sequential(*layers)


class Decoder(nn.Module):
    """f(z (B, 32), wi (B, 3), wo (B, 3)) -> f (B,) in 1/sr, without the cosine.

    Output activation ``exp`` (clamped at MAX_LOG_F) or ``softplus``. Directions below the
    horizon give 0 (the runtime also checks this; here it keeps the graph safe on its own).
    """

    def __init__(self, width: int, depth: int, features: str = "iso_bumps", activation: str = "exp"):
        super().__init__()
        self.width, self.depth, self.features, self.activation = width, depth, features, activation
        self.net = mlp(LATENT + n_direction_features(features), width, depth, 1)

    def forward(self, z: torch.Tensor, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        x = torch.cat([z, direction_features(wi, wo, self.features)], dim=-1)
        y = self.net(x)[:, 0]
        if self.activation == "exp":
            f = torch.exp(torch.clamp(y, max=MAX_LOG_F))
        else:
            f = nn.functional.softplus(y)
        above = (wi[:, 2] > 0.0) & (wo[:, 2] > 0.0)
        return torch.where(above, f, torch.zeros_like(f))

    def config(self) -> dict:
        return {"width": self.width, "depth": self.depth, "features": self.features, "activation": self.activation}


class Encoder(nn.Module):
    """Per-channel single-layer features (B, N_FEATURES) -> latent z_c (B, 32)."""

    def __init__(self, n_features: int, width: int = 128, depth: int = 3):
        super().__init__()
        self.n_features, self.width, self.depth = n_features, width, depth
        self.net = mlp(n_features, width, depth, LATENT)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)

    def config(self) -> dict:
        return {"n_features": self.n_features, "width": self.width, "depth": self.depth}


def he_init(dec: Decoder) -> Decoder:
    """He-normal weights (std sqrt(2 / fan_in)) and zero biases for the hidden layers, and a
    small last layer, so activations keep their scale through a deep ReLU stack. With PyTorch's
    default (std sqrt(1 / (3 fan_in))) the input-dependent part of the activations shrinks about
    3x per layer: after the paper's 16 layers the output hardly depends on the input and training
    stalls (tests/training/test_neural_training.py measures both)."""
    lins = [m for m in dec.net if isinstance(m, nn.Linear)]
    with torch.no_grad():
        for m in lins[:-1]:
            nn.init.normal_(m.weight, 0.0, math.sqrt(2.0 / m.in_features))
            m.bias.zero_()
        nn.init.normal_(lins[-1].weight, 0.0, 0.1 / math.sqrt(lins[-1].in_features))
        lins[-1].bias.zero_()
    return dec


def n_params(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


def macs_per_eval(module: nn.Module) -> int:
    """Multiply-adds of the linear layers for one scalar evaluation (one row)."""
    return sum(m.in_features * m.out_features for m in module.modules() if isinstance(m, nn.Linear))


def make_decoder(size: str, **kw) -> Decoder:
    if size not in SIZES:
        raise ValueError(f"unknown decoder size {size!r}; sizes are {sorted(SIZES)}")
    w, d = SIZES[size]
    return Decoder(w, d, **kw)


def log_target(f: torch.Tensor, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
    """log1p(f cos_i cos_o): the compressed quantity the loss compares."""
    cc = torch.clamp(wi[:, 2], min=0.0) * torch.clamp(wo[:, 2], min=0.0)
    return torch.log1p(f * cc)


PAIR_LOSSES = ("l1", "l2", "l2rel")


def pair_loss(
    pred: torch.Tensor, target: torch.Tensor, wi: torch.Tensor, wo: torch.Tensor, kind: str, grazing_floor: float = 1.0
) -> torch.Tensor:
    """Loss of each (wi, wo) pair, compared as log1p(f cos_i cos_o):

    - ``l1``: |difference of logs|; its minimiser is the median of noisy targets (exact targets: fine);
    - ``l2``: squared difference of logs; the mean of the LOG, still biased low for skewed noise;
    - ``l2rel``: squared first-order change of the log, ``cc (pred - target) / (1 + cc pred)`` with the
      denominator held constant in the gradient: a squared error in f weighted by the prediction only,
      so its minimiser is the MEAN of Monte Carlo targets (unbiased), scaled like the log losses.

    ``grazing_floor`` < 1 divides each pair's difference by max(min(cos_i, cos_o), grazing_floor): the
    compared quantity then scales like f cos of the steeper direction, the lobe image's value at a grazing
    incident (or outgoing) direction, instead of carrying a second small cosine that hides the grazing
    pairs from the loss (a network trained without it over-reflects near the horizon, where the
    reference's f falls with the coat's Fresnel transmission). 1 (the default) leaves the loss unchanged.
    """
    if not 0.0 < grazing_floor <= 1.0:
        raise ValueError(f"grazing_floor must be in (0, 1], got {grazing_floor}")
    if kind == "l2rel":
        cc = torch.clamp(wi[:, 2], min=0.0) * torch.clamp(wo[:, 2], min=0.0)
        d = cc * (pred - target) / (1.0 + cc * pred.detach())
    elif kind in PAIR_LOSSES:
        d = log_target(pred, wi, wo) - log_target(target, wi, wo)
    else:
        raise ValueError(f"unknown loss {kind!r}; expected one of {', '.join(PAIR_LOSSES)}")
    if grazing_floor < 1.0:
        d = d / torch.clamp(torch.minimum(wi[:, 2], wo[:, 2]), min=grazing_floor)
    return d.abs() if kind == "l1" else d * d


def stack_levels(f: torch.Tensor, wi: torch.Tensor, wo: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """(S,) each stack's level: the RMS over its pairs (S, P) and colour channels of the compared value
    f cos_i cos_o (``pair_loss``), each pair weighted by ``weight`` (S, P) (``layering.cosine_weights``, or
    ones).

    The pair loss is an absolute error for values well under 1, so without a per-stack scale a stack whose
    BRDF is a hundredth of another's counts ten thousand times less, however wrong its lobe is; the lobe
    error the held-out tables report is relative per lobe. ``level_weights`` turns the levels into the
    per-stack weights that make them alike."""
    cc = wi[..., 2].clamp(min=0.0) * wo[..., 2].clamp(min=0.0)
    v = (cc.unsqueeze(-1) * f) ** 2
    return ((weight.unsqueeze(-1) * v).sum((1, 2)) / (3.0 * weight.sum(1).clamp(min=1e-12))).sqrt()


def level_weights(level: torch.Tensor, floor: float) -> torch.Tensor | None:
    """(S,) 1 / clip(level, ``floor`` x m, m)^2 with m the median level (``stack_levels``), or None for
    ``floor`` <= 0.

    A stack dimmer than the median weighs as if it were as bright, so its relative error counts like
    the median stack's; the floor keeps one whose values are all but zero (a clear coat on a black base)
    from taking the batch: it weighs at most 1 / floor^2 times the median stack. Stacks brighter than the
    median keep their weight: their large values are compared on a log scale already (``pair_loss``), and
    weighing them down as well cost the bright single layers their fit."""
    if floor <= 0.0:
        return None
    m = float(level.median())
    return 1.0 / torch.clamp(level, min=floor * m, max=m) ** 2


def cosine_lr(step: int, steps: int, base: float, floor: float = 0.05, warmup: int = 100) -> float:
    if step < warmup:
        return base * (step + 1) / warmup
    t = min(1.0, (step - warmup) / max(1, steps - warmup))
    return base * (floor + (1.0 - floor) * 0.5 * (1.0 + math.cos(math.pi * t)))


class RGBDecoder(nn.Module):
    """The same decoder evaluated for the three colour channels at once (the runtime's graph).

    zc (Bz, 3W) with Bz = 1 (one material) or B (per row), wi, wo (B, 3) -> f (B, 3). ``zc`` is the latents'
    product with the first layer, bias included (:meth:`project`: ``z (Bz, 3, 32) @ w_z.T + b``, the three
    channels side by side), which the runtime computes outside the graph (``LatentProjection``): once for a
    material's latent, once per texel for a latent texture (the product is affine, so it commutes with the
    texture's filtering), instead of once per query row. The direction features and their first-layer product
    are computed once per query instead of once per channel: same weights, same values as ``Decoder`` row by row.

    Unlike ``Decoder`` the directions need not be unit length: the graph normalises them (in
    float32; a zero direction counts as below the horizon), so the runtime hands its directions
    over as they are. The direction term of the first layer is produced for the three channels
    by one product with the direction weights repeated three times ((B, 3W), 2-D), since ONNX
    Runtime adds a 2-D bias far faster than it broadcasts (B, 1, W) against (1, 3, W).
    """

    def __init__(self, dec: Decoder):
        super().__init__()
        self.dec = dec
        first = dec.net[0]
        self.width = first.weight.shape[0]
        self.w_z = nn.Parameter(first.weight[:, :LATENT].detach().clone())
        self.register_buffer("w_d3", first.weight[:, LATENT:].detach().repeat(3, 1))  # (3W, F)
        self.b = nn.Parameter(first.bias.detach().clone())
        self.rest = dec.net[2:]  # after the first Linear + ReLU

    def project(self, z: torch.Tensor) -> torch.Tensor:
        """(Bz, 3W): the latents z (Bz, 3, 32) through the first layer's latent columns, bias included."""
        return (torch.matmul(z, self.w_z.t()) + self.b).reshape(z.shape[0], 3 * self.width)

    def forward(self, zc: torch.Tensor, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        above = ((wi[:, 2] > 0.0) & (wo[:, 2] > 0.0)).to(wi.dtype).unsqueeze(1)
        wi, wo = unit_rows(wi), unit_rows(wo)
        d = torch.matmul(direction_features(wi, wo, self.dec.features), self.w_d3.t())  # (B, 3W)
        h = torch.relu(d + zc).reshape(-1, self.width)  # (B * 3, W)
        y = self.rest(h).reshape(-1, 3)  # 2-D rows: the exporter emits Gemm, which fuses bias and ReLU
        if self.dec.activation == "exp":
            f = torch.exp(torch.clamp(y, max=MAX_LOG_F))
        else:
            f = nn.functional.softplus(y)
        return f * above  # f is finite (clamped), so this is 0 below the horizon


class LatentProjection(nn.Module):
    """The fused graph's first step as a graph of its own (the runtime's ``decoder_<size>_latents.onnx``): latents
    z (B, 3, 32) -> zc (B, 3W), ``RGBDecoder.project``. The runtime runs it once a material's latent, once a texel
    of a latent texture, or once a hit's looked-up latents, and feeds the products to the fused graph."""

    def __init__(self, rgb: RGBDecoder):
        super().__init__()
        self.rgb = rgb

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return self.rgb.project(z)


def unit_rows(w: torch.Tensor) -> torch.Tensor:
    """Rows of ``w`` (B, 3) scaled to unit length (computed on the components as rows, as
    ``direction_features`` is); zero rows stay zero."""
    a = w.t()
    return (a * torch.rsqrt(torch.clamp(a[0] * a[0] + a[1] * a[1] + a[2] * a[2], min=1e-30))).t()
