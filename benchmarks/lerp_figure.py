"""Latent interpolation versus linear blending of two BRDFs (supplement figure 1).

    python benchmarks/lerp_figure.py --size tiny

writes ``docs/lerp.png`` and ``docs/lerp.md``. Two layered materials A and B are encoded
(``encode_stack``); for t in 0 .. 1 the top rows decode ``lerp(z_A, z_B, t)`` and the bottom
rows show the linear blend (1 - t) f_A + t f_B of the two decoded BRDFs, as lobe images at 30 degrees
incidence and as spheres under the preview environment, plus the in-plane lobe f cos(theta_o). A linear
blend superimposes the two highlights (a sharp peak on a wide lobe); the latent interpolation moves one
highlight from one material to the other, as the paper's supplement shows.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from addon.core import lobe, preview  # noqa: E402
from addon.core.neural import encode_stack, lerp, load_models, top_coat  # noqa: E402
from addon.core.stack import Coating, Conductor, Diffuse, Stack  # noqa: E402

GOLD = dict(eta=(0.143, 0.374, 1.442), k=(3.983, 2.385, 1.603))
MATERIAL_A = Stack(Conductor(roughness=0.05, **GOLD), (Coating(roughness=0.02, ior=1.5),))
MATERIAL_B = Stack(Diffuse((0.1, 0.3, 0.7)), (Coating(roughness=0.4, ior=1.5, albedo=(0.9, 0.9, 0.9), thickness=1.0),))
TS = (0.0, 0.25, 0.5, 0.75, 1.0)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="tiny")
    ap.add_argument("--res", type=int, default=96)
    ap.add_argument("--out", type=Path, default=ROOT / "docs")
    a = ap.parse_args(argv)
    cmd = "python benchmarks/lerp_figure.py " + " ".join(shlex.quote(x) for x in (argv or sys.argv[1:]))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    models = load_models(a.size, threads=2)
    za = encode_stack(MATERIAL_A, models)
    zb = encode_stack(MATERIAL_B, models)
    ta, tb = top_coat(MATERIAL_A), top_coat(MATERIAL_B)  # a remainder decoder's exact top lobes, lerped as a texture's

    def latent_brdf(t):
        z = lerp(za, zb, t)
        return lambda wi, wo: models.eval_brdf(z, wi, wo, (1 - t) * ta + t * tb)

    def blend_brdf(t):
        return lambda wi, wo: (1 - t) * models.eval_brdf(za, wi, wo, ta) + t * models.eval_brdf(zb, wi, wo, tb)

    rows = {"latent lerp": latent_brdf, "linear BRDF blend": blend_brdf}
    lobes = {k: [lobe.lobe_image(fn(t), 30.0, a.res) for t in TS] for k, fn in rows.items()}
    spheres = {
        k: [preview.sphere_preview(fn(t), res=a.res, env_samples=32, seed=1) for t in TS] for k, fn in rows.items()
    }
    scale = 1.0 / max(float(np.percentile(np.concatenate([x.ravel() for x in lobes["linear BRDF blend"]]), 99.5)), 1e-6)

    fig = plt.figure(figsize=(2.0 * len(TS), 9.6))
    gs = fig.add_gridspec(5, len(TS), height_ratios=[1, 1, 1, 1, 1.2])
    for r, (name, imgs) in enumerate(lobes.items()):
        for j, t in enumerate(TS):
            ax = fig.add_subplot(gs[2 * r, j])
            ax.imshow(lobe.to_display(imgs[j], scale))
            ax.set_xticks([]), ax.set_yticks([])
            ax.set_title(f"{name}\nt = {t:g}" if j == 0 else f"t = {t:g}", fontsize=7)
            ax = fig.add_subplot(gs[2 * r + 1, j])
            ax.imshow(lobe.to_display(spheres[name][j][..., :3]))
            ax.set_xticks([]), ax.set_yticks([])
    # in-plane slice of the lobe: the row through the plane of incidence
    ax = fig.add_subplot(gs[4, :])
    x = (np.arange(a.res) + 0.5) / a.res * 2 - 1
    mid = a.res // 2
    cmap = plt.get_cmap("viridis")
    for j, t in enumerate(TS):
        ax.plot(
            x,
            lobes["latent lerp"][j][mid, :, :].mean(axis=1),
            color=cmap(j / (len(TS) - 1)),
            lw=1.5,
            label=f"latent t={t:g}",
        )
        ax.plot(x, lobes["linear BRDF blend"][j][mid, :, :].mean(axis=1), color=cmap(j / (len(TS) - 1)), lw=1, ls="--")
    ax.set_yscale("symlog", linthresh=0.05)
    ax.set_xlabel("projected outgoing x (plane of incidence, incidence 30 deg at -x)")
    ax.set_ylabel("f cos (mean RGB)")
    ax.legend(fontsize=6, ncol=5)
    ax.set_title("solid: latent interpolation, dashed: linear blend of the BRDFs", fontsize=8)
    fig.suptitle(
        f"A = coated gold (smooth coat), B = rough tinted coat over blue diffuse; decoder {a.size}", fontsize=9
    )
    fig.tight_layout()
    a.out.mkdir(parents=True, exist_ok=True)
    fig.savefig(a.out / "lerp.png", dpi=110)
    (a.out / "lerp.md").write_text(
        "# Latent interpolation\n\n"
        f"Made by `{cmd}`.\n\n"
        "`lerp(z_a, z_b, t) = (1 - t) z_a + t z_b` (`addon/core/neural/encode.py`) against the linear blend "
        "`(1 - t) f_a + t f_b` of the two decoded BRDFs. Material A: gold under a smooth clear coat "
        f"(`{MATERIAL_A.to_json()}`); material B: blue diffuse under a rough, scattering coat "
        f"(`{MATERIAL_B.to_json()}`).\n\n"
        "Top: latent interpolation; below: linear blend (lobe images at 30 degrees incidence, and spheres under the "
        "preview environment). The bottom plot is the in-plane lobe.\n\n![lerp](lerp.png)\n"
    )
    print(f"wrote {a.out / 'lerp.png'}")


if __name__ == "__main__":
    main()
