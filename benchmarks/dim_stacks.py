"""How a model set's networks fit the dim stacks of layered training data.

    python benchmarks/dim_stacks.py --size tiny --data cache/data/layering_c1 [--model-dir DIR]

Per stack of an ``onnx_export.layered_data`` set: the ratio of the decoded remainder's cosine-weighted sum
over the stack's pairs to the data's (its Monte Carlo values less the exact top-interface reflection,
``onnx_export.remainder.top_reflection``), the stack encoded as the renderer encodes it (encoder and
layering network) and decoded without calibration. The stacks are grouped by kind and by level (the RMS
of the data's f cos cos over the set's median, as ``onnx_export.nets.stack_levels`` without the pair
weights): a group whose median ratio is far from 1 is one the training does not fit, whatever its
validation error says. The dim stacks are nearly all dielectric bases under a coat of close index,
whose remainder (the light the inner interface reflects) is all but black (docs/layering_training.md).
"""

from __future__ import annotations

import argparse

import numpy as np

from addon.core.neural import load_models
from addon.core.neural.encode import encode_arrays
from addon.core.neural.top_lobe import top_coats
from onnx_export.layered_data import load
from onnx_export.remainder import top_reflection


def stack_ratios(models, data: dict) -> tuple[np.ndarray, np.ndarray]:
    """(S,) decoded / data sums of the remainder's f cos cos, and (S,) the stacks' levels over the median."""
    arrays = data["arrays"]
    s, n_wo, n_wi = data["f"].shape[:3]
    wi = data["wi"].astype(np.float64).reshape(s, -1, 3)
    wo = np.repeat(data["wo"][:, :, None, :], n_wi, axis=2).astype(np.float64).reshape(s, -1, 3)
    target = data["f"].reshape(s, -1, 3) - top_reflection(arrays, wi, wo)
    z = encode_arrays(arrays, models)
    pred = models.eval_brdf(
        np.repeat(z, n_wo * n_wi, axis=0),
        wi.reshape(-1, 3),
        wo.reshape(-1, 3),
        np.repeat(top_coats(arrays), n_wo * n_wi, axis=0),
        with_top_lobe=False,
    ).reshape(s, -1, 3)
    cc = (np.clip(wi[..., 2], 0.0, None) * np.clip(wo[..., 2], 0.0, None))[..., None]
    ratio = (pred * cc).sum((1, 2)) / np.maximum((target * cc).sum((1, 2)), 1e-12)
    level = np.sqrt(((target * cc) ** 2).mean((1, 2)))
    return ratio, level / np.median(level)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="tiny")
    ap.add_argument("--data", required=True, help="an onnx_export.layered_data directory")
    ap.add_argument("--model-dir", default=None, help="a model set other than the shipped one")
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args(argv)
    data = load(a.data)
    ratio, level = stack_ratios(load_models(a.size, threads=a.threads, model_dir=a.model_dir), data)
    arrays = data["arrays"]
    dielectric = arrays.base_kind == 2
    near = dielectric & (np.abs(arrays.base_ior / arrays.coat_ior[:, -1] - 1.0) < 0.12)
    print(f"{a.size} ({a.model_dir or 'shipped'}), {a.data}: {len(ratio)} stacks")
    print("| stacks | count | decoded / data, median | p10 | p90 | share over 2 |")
    print("|---|---|---|---|---|---|")
    groups = [
        ("all", np.ones(len(ratio), dtype=bool)),
        ("dielectric base", dielectric),
        ("dielectric base, coat index within 12%", near),
        ("level under 0.1 x median", level < 0.1),
        ("level under 0.03 x median", level < 0.03),
    ]
    for name, sel in groups:
        r = ratio[sel]
        if not len(r):
            continue
        p10, p50, p90 = np.percentile(r, [10, 50, 90])
        print(f"| {name} | {len(r)} | {p50:.2f} | {p10:.2f} | {p90:.2f} | {np.mean(r > 2):.2f} |")


if __name__ == "__main__":
    main()
