"""One source, several array libraries: the reference walk and the analytic BSDFs on torch
(CPU here; CUDA where one exists) and CuPy agree with numpy when fed identical random numbers."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from addon.core import reference
from addon.core import xp as X
from addon.core.bsdf import (
    IMPORTANCE,
    RADIANCE,
    HenyeyGreenstein,
    Lambertian,
    RoughConductor,
    RoughDielectric,
    coordinate_system,
    fresnel_conductor,
    fresnel_dielectric,
    ggx,
    normalize,
    refract,
)
from addon.core.stack import Coating, Conductor, Dielectric, Diffuse, Stack

GOLD = dict(eta=(0.143, 0.374, 1.442), k=(3.983, 2.385, 1.603))
RTOL = 1e-9

BASES = {
    "diffuse": Diffuse((0.8, 0.5, 0.2)),
    "conductor": Conductor(0.2, **GOLD),
    "smooth_conductor": Conductor(0.0, **GOLD),
    "dielectric": Dielectric(0.25, 1.9),
}
COATS = [
    Coating(0.3, 1.5, (0.2, 0.6, 0.9), 1.0, 0.7),
    Coating(0.0, 1.6, (0.9, 0.9, 0.3), 0.5, -0.3),
    Coating(0.1, 1.3),
]
STACKS = {f"{b}-{c}coat": Stack(base, tuple(COATS[:c])) for b, base in BASES.items() for c in (1, 2, 3)}


def directions(n, seed, upper=True):
    v = normalize(np.random.default_rng(seed).normal(size=(n, 3)))
    if upper:
        v[:, 2] = np.abs(v[:, 2]) + 1e-3
        v = normalize(v)
    return v


def close(a, b, rtol=RTOL):
    """Equal to ``rtol`` relative to the larger of the two (elementwise, or of the array's
    scale where values are tiny)."""
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape and a.dtype == b.dtype
    scale = np.maximum(np.maximum(np.abs(a), np.abs(b)), 1e-12 * max(np.abs(b).max(initial=0.0), 1e-300))
    assert np.all(np.abs(a - b) <= rtol * scale), float(np.max(np.abs(a - b) / scale))


TORCH = X.get("torch")


# ----------------------------------------------------------------------------- the walk


@pytest.mark.parametrize("name", sorted(STACKS))
def test_eval_brdf_torch_equals_numpy(name):
    stack = STACKS[name]
    wi, wo = directions(24, 1), directions(24, 2)
    f0, s0 = reference.eval_brdf(stack, wi, wo, walks=8, seed=X.HostRng(np, 5))
    f1, s1 = reference.eval_brdf(stack, wi, wo, walks=8, seed=X.HostRng(TORCH, 5), backend="torch")
    assert isinstance(f1, np.ndarray) and f1.dtype == np.float64
    assert np.any(f0 > 0.0)
    close(f1, f0)
    close(s1, s0)


def test_eval_brdf_many_and_batches_torch_equals_numpy():
    stacks = [STACKS["diffuse-2coat"], STACKS["conductor-2coat"], STACKS["dielectric-2coat"]] * 4
    batch = reference.pack_stacks(stacks)
    wi, wo = directions(12, 3), directions(12, 4)
    f0, s0 = reference.eval_brdf(batch, wi, wo, walks=8, seed=X.HostRng(np, 6))
    f1, s1 = reference.eval_brdf(batch, wi, wo, walks=8, seed=X.HostRng(TORCH, 6), backend="torch")
    close(f1, f0)
    close(s1, s0)
    wim = np.stack([directions(12, 7), directions(12, 8), directions(12, 9)], axis=1)
    f0, s0 = reference.eval_brdf_many(STACKS["conductor-3coat"], wim, wo, walks=8, seed=X.HostRng(np, 7))
    f1, s1 = reference.eval_brdf_many(
        STACKS["conductor-3coat"], wim, wo, walks=8, seed=X.HostRng(TORCH, 7), backend="torch"
    )
    close(f1, f0)
    close(s1, s0)


@pytest.mark.parametrize("name", ["diffuse-1coat", "smooth_conductor-2coat", "dielectric-3coat"])
def test_albedo_and_sample_torch_equal_numpy(name):
    stack = STACKS[name]
    wo = directions(16, 11)
    a0, e0 = reference.albedo(stack, wo, samples=32, seed=X.HostRng(np, 8))
    a1, e1 = reference.albedo(stack, wo, samples=32, seed=X.HostRng(TORCH, 8), backend="torch")
    close(a1, a0)
    close(e1, e0)
    wo = directions(512, 12)
    wi0, w0, sp0 = reference.sample(stack, wo, X.HostRng(np, 9), with_flags=True)
    wi1, w1, sp1 = reference.sample(stack, wo, X.HostRng(TORCH, 9), with_flags=True, backend="torch")
    close(wi1, wi0)
    close(w1, w0)
    np.testing.assert_array_equal(sp1, sp0)


def test_torch_inputs_stay_torch_and_native_generator_is_deterministic():
    stack = STACKS["conductor-2coat"]
    wi, wo = torch.as_tensor(directions(8, 13)), torch.as_tensor(directions(8, 14))
    f, se = reference.eval_brdf(stack, wi, wo, walks=16, seed=3)
    assert isinstance(f, torch.Tensor) and f.dtype == torch.float64
    f2, _ = reference.eval_brdf(stack, wi, wo, walks=16, seed=3)
    assert torch.equal(f, f2)
    assert torch.all(torch.isfinite(f)) and torch.all(f >= 0.0)
    # the native generator draws other numbers than numpy: same estimate, within noise
    a_t, e_t = reference.albedo(stack, wo.numpy(), samples=2000, seed=1, backend="torch")
    a_n, e_n = reference.albedo(stack, wo.numpy(), samples=2000, seed=1)
    assert np.all(np.abs(a_t - a_n) < 5.0 * np.hypot(e_t, e_n) + 1e-12)


def test_backend_arguments_are_checked():
    wo = directions(2, 15)
    with pytest.raises(ValueError, match="backend"):
        reference.albedo(STACKS["diffuse-1coat"], wo, samples=2, backend="jax")
    with pytest.raises(ValueError, match="device"):
        reference.albedo(STACKS["diffuse-1coat"], wo, samples=2, device="cuda")
    with pytest.raises(ValueError, match="wo must be unit"):
        reference.albedo(STACKS["diffuse-1coat"], torch.ones(2, 3, dtype=torch.float64), samples=2)


def test_core_imports_neither_torch_nor_cupy():
    code = (
        "import sys; import addon.core.reference, addon.core.bsdf, addon.core.xp; "
        "assert 'torch' not in sys.modules and 'cupy' not in sys.modules, 'imported'"
    )
    subprocess.run([sys.executable, "-c", code], check=True, cwd=Path(__file__).resolve().parents[2])


# ----------------------------------------------------------------------------- analytic BSDFs


def _bsdfs(xp, n):
    rng = np.random.default_rng(20)
    alpha = np.concatenate([[0.0, 1e-4], rng.uniform(0.01, 1.0, n - 2)])
    ior = rng.uniform(0.6, 2.2, n)
    rgb = rng.uniform(0.05, 1.0, (n, 3))
    eta, k = rng.uniform(0.1, 2.0, (n, 3)), rng.uniform(0.0, 4.0, (n, 3))
    a = xp.asarray
    return {
        "lambert": Lambertian(a(rgb)),
        "conductor": RoughConductor(a(alpha), a(eta), a(k)),
        "dielectric": RoughDielectric(a(alpha), a(ior)),
        "dielectric_over_black": RoughDielectric(a(alpha), a(ior), reflection_only=True),
    }


@pytest.mark.parametrize("kind", ["lambert", "conductor", "dielectric", "dielectric_over_black"])
@pytest.mark.parametrize("mode", [RADIANCE, IMPORTANCE])
def test_bsdf_eval_pdf_sample_torch_equal_numpy(kind, mode):
    n = 400
    b0, b1 = _bsdfs(np, n)[kind], _bsdfs(TORCH, n)[kind]
    wi, wo = directions(n, 21, upper=False), directions(n, 22, upper=False)
    u = np.random.default_rng(23).random((n, 3))
    t = torch.as_tensor
    close(b1.eval(t(wi), t(wo), mode).numpy(), b0.eval(wi, wo, mode))
    close(b1.pdf(t(wi), t(wo), mode).numpy(), b0.pdf(wi, wo, mode))
    s0 = b0.sample(wo, u[:, 0], u[:, 1:], mode)
    s1 = b1.sample(t(wo), t(u[:, 0]), t(u[:, 1:]), mode)
    for f in ("wi", "weight", "pdf"):
        close(getattr(s1, f).numpy(), getattr(s0, f))
    for f in ("delta", "transmission", "valid"):
        np.testing.assert_array_equal(getattr(s1, f).numpy(), getattr(s0, f))
    # numpy parameters with torch directions also run on torch
    mixed = _bsdfs(np, n)[kind].eval(t(wi), t(wo), mode)
    assert isinstance(mixed, torch.Tensor)
    close(mixed.numpy(), b0.eval(wi, wo, mode))


def test_phase_frame_fresnel_ggx_torch_equal_numpy():
    n = 300
    t = torch.as_tensor
    wi, wo = directions(n, 31, upper=False), directions(n, 32, upper=False)
    u = np.random.default_rng(33).random((n, 2))
    g = np.random.default_rng(34).uniform(-0.95, 0.95, n)
    g[:3] = 0.0
    p0, p1 = HenyeyGreenstein(g), HenyeyGreenstein(t(g))
    close(p1.eval(t(wi), t(wo)).numpy(), p0.eval(wi, wo))
    w0, q0 = p0.sample(wo, u)
    w1, q1 = p1.sample(t(wo), t(u))
    close(w1.numpy(), w0)
    close(q1.numpy(), q0)
    alpha = np.random.default_rng(35).uniform(0.01, 1.0, n)
    close(ggx.ndf(t(wi), t(alpha)).numpy(), ggx.ndf(wi, alpha))
    close(ggx.smith_g2(t(wi), t(wo), t(alpha)).numpy(), ggx.smith_g2(wi, wo, alpha))
    close(ggx.sample_visible_normal(t(wo), t(alpha), t(u)).numpy(), ggx.sample_visible_normal(wo, alpha, u))
    eta = np.random.default_rng(36).uniform(0.5, 2.0, n)
    close(fresnel_dielectric(t(wi[:, 2]), t(eta)).numpy(), fresnel_dielectric(wi[:, 2], eta))
    close(
        fresnel_conductor(t(wi[:, 2]), t(np.array(GOLD["eta"])), t(np.array(GOLD["k"]))).numpy(),
        fresnel_conductor(wi[:, 2], GOLD["eta"], GOLD["k"]),
    )
    r0, v0 = refract(wi, np.array([0.0, 0.0, 1.0]), eta)
    r1, v1 = refract(t(wi), t(np.array([0.0, 0.0, 1.0])), t(eta))
    close(r1.numpy(), r0)
    np.testing.assert_array_equal(v1.numpy(), v0)
    for a, b in zip(coordinate_system(t(wo)), coordinate_system(wo), strict=False):
        close(a.numpy(), b)


# ----------------------------------------------------------------------------- CuPy


def _cupy_or_skip():
    try:
        import cupy
    except ImportError:
        pytest.skip("CuPy is not installed (pip install cupy-cuda12x on a machine with a CUDA GPU)")
    try:
        if cupy.cuda.runtime.getDeviceCount() < 1:
            raise RuntimeError("no device")
    except Exception as e:  # noqa: BLE001 - any CUDA failure means: no usable device
        pytest.skip(f"CuPy is installed but no CUDA device is usable: {e}")
    return cupy


@pytest.mark.parametrize("name", ["diffuse-1coat", "conductor-2coat", "dielectric-3coat"])
def test_cupy_equals_numpy(name):
    _cupy_or_skip()
    cp = X.get("cupy")
    stack = STACKS[name]
    wi, wo = directions(24, 41), directions(24, 42)
    f0, s0 = reference.eval_brdf(stack, wi, wo, walks=8, seed=X.HostRng(np, 5))
    f1, s1 = reference.eval_brdf(stack, wi, wo, walks=8, seed=X.HostRng(cp, 5), backend="cupy")
    close(f1, f0)
    close(s1, s0)
    a0, _ = reference.albedo(stack, wo, samples=32, seed=X.HostRng(np, 8))
    a1, _ = reference.albedo(stack, wo, samples=32, seed=X.HostRng(cp, 8), backend="cupy")
    close(a1, a0)


def test_torch_cuda_equals_numpy():
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device for torch")
    dev = X.get("torch", "cuda")
    stack = STACKS["conductor-3coat"]
    wi, wo = directions(24, 51), directions(24, 52)
    f0, _ = reference.eval_brdf(stack, wi, wo, walks=8, seed=X.HostRng(np, 5))
    f1, _ = reference.eval_brdf(stack, wi, wo, walks=8, seed=X.HostRng(dev, 5), backend="torch", device="cuda")
    close(f1, f0, rtol=1e-7)  # GPU transcendental functions differ from the CPU's in the last bits
