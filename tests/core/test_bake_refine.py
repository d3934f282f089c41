"""The bake's refine option (textures.bake.neural_encoder(refine_s=...)): distinct texels are refined in
order while the budget lasts, with the latents refine_latent returns, and the budget is validated."""

import numpy as np
import pytest

from addon.core.neural import encode_arrays, load_models
from addon.core.neural.refine import RefineSettings, refine_latent
from addon.core.stack import Coating, Conductor, Stack, StackArrays
from addon.core.textures.bake import bake_texels, neural_encoder

QUICK = RefineSettings(fit_groups=8, validation_groups=4, per_group=16, walks=8, steps=60)
STACKS = [
    Stack(
        Conductor(eta=(0.2, 0.4, 1.4), k=(3.9, 2.4, 1.6), roughness=r),
        (Coating(roughness=0.05, ior=1.5, thickness=0.5, albedo=(0.8, 0.5, 0.3)),),
    )
    for r in (0.3, 0.5)
]


def test_refine_budget_refines_distinct_texels_in_order_until_it_is_spent(tmp_path):
    arrays = StackArrays.from_stacks([STACKS[0], STACKS[1], STACKS[0], STACKS[1]])
    # a budget far below one refinement: the first distinct texel is refined (started while time was left),
    # the second is not
    encode = neural_encoder("tiny", threads=1, refine_s=0.05, refine_cache=tmp_path, refine_settings=QUICK)
    texels, stats = bake_texels(arrays, encode)
    assert stats.unique == 2 and encode.metadata["refined"] == 1 and encode.metadata["refine_s"] == 0.05
    plain = encode_arrays(arrays, load_models("tiny", 1)).reshape(4, 96)
    # which distinct texel was refined (the bake's order is its deduplication's): the one whose refinement
    # is in the cache folder the bake was given; its texels hold the latent that refinement returned. A refinement
    # its budget cut short answers only a smaller budget from the cache (the same budget refines again): 0.01 s
    got = [
        refine_latent(
            arrays.take(slice(i, i + 1)).stack(0), "tiny", budget_s=0.01, settings=QUICK, threads=1, cache_dir=tmp_path
        )
        for i in (0, 1)
    ]
    refined = [i for i in (0, 1) if got[i][1].cached]
    assert len(refined) == 1, [g[1].cached for g in got]
    i = refined[0]
    other = 1 - i
    assert np.allclose(texels[i, :96], got[i][0].reshape(-1)) and np.array_equal(texels[i + 2], texels[i])
    assert np.allclose(texels[other, :96], plain[other]) and np.array_equal(texels[other + 2], texels[other])
    # the proxy channels are the sampling network's for the latent stored
    assert np.allclose(texels[i, 96:98], load_models("tiny", 1).proxy_params(got[i][0][None])[0], atol=1e-6)


@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf"), True])
def test_bad_refine_budget_is_refused(bad):
    with pytest.raises(ValueError, match="refine_s"):
        neural_encoder("tiny", refine_s=bad)


def test_no_budget_means_no_refinement():
    encode = neural_encoder("tiny", threads=1)
    assert "refine_s" not in encode.metadata
    arrays = StackArrays.from_stacks(STACKS)
    z, _ = encode(arrays)
    assert np.array_equal(z, encode_arrays(arrays, load_models("tiny", 1)))


def test_a_refining_bake_hears_a_cancel_and_moves_its_progress_after_each_texel(monkeypatch):
    """Each refinement takes seconds (up to REFINE_PER_MATERIAL_S): the bake checks its cancel and moves its
    progress after each one, where it heard neither until the whole budget was spent (a Refine of 600 s ignored
    Esc for ten minutes)."""
    import time

    from addon.core.neural import refine
    from addon.core.textures.bake import BakeCancelled

    def slow_refinement(stack, size, budget_s, **kwargs):  # the refinement's seconds, without its work
        time.sleep(0.02)
        return encode_arrays(StackArrays.from_stacks([stack]), load_models("tiny", 1))[0], None

    monkeypatch.setattr(refine, "refine_latent", slow_refinement)
    stacks = [
        Stack(Conductor(eta=(0.2, 0.4, 1.4), k=(3.9, 2.4, 1.6), roughness=0.2 + 0.01 * i), STACKS[0].coatings)
        for i in range(20)
    ]
    arrays = StackArrays.from_stacks(stacks)
    encode = neural_encoder("tiny", threads=1, refine_s=60.0)
    seen = []
    with pytest.raises(BakeCancelled, match="while refining, after 4 of 20"):  # heard after the fourth
        bake_texels(arrays, encode, progress=seen.append, cancel=lambda: len(seen) >= 3)
    assert seen == [1 / 20, 2 / 20, 3 / 20] and encode.metadata["refined"] == 4
    assert encode.step is None  # the bake's callbacks went with it


def test_a_refined_bakes_key_follows_the_refinements_and_the_references_versions(monkeypatch):
    """Refined texels are fitted to the reference's lobes by one version of the refinement: a bake refined by an
    earlier one (other targets, another top lobe) was taken for current."""
    from addon.core import reference
    from addon.core.neural import refine
    from addon.core.textures.bake import model_key

    plain, refined = model_key("tiny", "d"), model_key("tiny", "d", 2.0)
    monkeypatch.setattr(refine, "REFINE_VERSION", refine.REFINE_VERSION + 1)
    assert model_key("tiny", "d", 2.0) != refined and model_key("tiny", "d") == plain
    monkeypatch.setattr(reference, "ESTIMATOR_VERSION", reference.ESTIMATOR_VERSION + 1)
    assert model_key("tiny", "d", 2.0) != refined and model_key("tiny", "d") == plain
