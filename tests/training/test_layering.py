"""Layering and sampling networks (torch): ONNX parity of the shipped models, the losses, the KL table."""

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from addon.core.neural import MODEL_DIR, SIZES
from onnx_export import layering as lay
from onnx_export import sampling_net as smp

LAYERING = [s for s in SIZES if (MODEL_DIR / f"layering_{s}.onnx").exists()]
SAMPLING = [s for s in SIZES if (MODEL_DIR / f"sampling_{s}.onnx").exists()]


@pytest.mark.parametrize("size", LAYERING)
def test_layering_onnx_matches_torch(size):
    path = MODEL_DIR / f"layering_{size}.onnx"
    card = json.loads(path.with_suffix(".json").read_text())
    net = lay.net_from_onnx(path, card)
    # relative, floor 1e-3 on latents near 0: float32 round-off of the paper size's 256 x 4 network reaches
    # about 2e-4 there (torch float32 against float64 differs as much: 1.9e-4 on these inputs); an export
    # error (an op, a weight, an input order) is orders larger
    assert lay.parity(net, path, n=2048, seed=7) <= 5e-4
    assert card["parameters"] == sum(p.numel() for p in net.parameters())


@pytest.mark.parametrize("size", SAMPLING)
def test_sampling_onnx_matches_torch(size):
    path = MODEL_DIR / f"sampling_{size}.onnx"
    card = json.loads(path.with_suffix(".json").read_text())
    net = smp.net_from_onnx(path, card)
    z = np.random.default_rng(3).normal(size=(512, 3, 32)).astype(np.float32)
    assert smp.parity(net, path, z) < 1e-4


def test_compose_applies_the_network_once_per_coating_bottom_up():
    torch.manual_seed(0)
    net = lay.LayeringNet(16, 2)
    s = 5
    zb = torch.randn(s, 3, 32)
    zt = torch.randn(s, 2, 3, 32)
    alb = torch.rand(s, 2, 3)
    th = torch.rand(s, 2) * 5
    z = lay.compose(net, zb, zt, alb, th)
    one = net(zt[:, 0].reshape(-1, 32), zb.reshape(-1, 32), alb[:, 0].reshape(-1), th[:, 0].repeat_interleave(3))
    two = net(zt[:, 1].reshape(-1, 32), one, alb[:, 1].reshape(-1), th[:, 1].repeat_interleave(3))
    torch.testing.assert_close(z, two.reshape(s, 3, 32))


def _fit_constant(kind: str, targets: torch.Tensor) -> float:
    """Fit one constant prediction to noisy targets with the given loss."""
    p = torch.tensor([0.5], requires_grad=True)
    opt = torch.optim.Adam([p], lr=0.02)
    n = targets.shape[0]
    up = torch.tensor([[0.0, 0.0, 1.0]]).expand(n, 3)
    for _ in range(1500):
        pred = torch.nn.functional.softplus(p).expand(n)
        loss = lay.layering_loss(pred, targets, up, up, None, kind)
        opt.zero_grad()
        loss.backward()
        opt.step()
    return float(torch.nn.functional.softplus(p.detach()))


def test_l2rel_fits_the_mean_of_noisy_targets_and_l1log_the_median():
    """Monte Carlo targets are skewed: the default loss must converge to their mean (unbiased)."""
    torch.manual_seed(0)
    targets = torch.distributions.Exponential(torch.tensor(1.0)).sample((20000,)) * 2.0  # mean 2, median 2 ln 2
    mean, median = float(targets.mean()), float(targets.median())
    assert abs(_fit_constant("l2rel", targets) - mean) < 0.05 * mean
    assert abs(_fit_constant("l1log", targets) - median) < 0.05 * median
    with pytest.raises(ValueError, match="unknown layering loss"):
        lay.layering_loss(targets, targets, None, None, None, "huber")


def test_kl_table_interpolation_is_exact_at_grid_nodes_and_the_minimum_is_found():
    rng = np.random.default_rng(0)
    table = torch.from_numpy(rng.random((4, len(smp.SIGMA_GRID), len(smp.W_GRID))).astype(np.float32))
    si = torch.tensor([0, 5, 10, 20])
    wi = torch.tensor([0, 3, 20, 7])
    got = smp.interp_table(
        table, torch.from_numpy(smp.SIGMA_GRID[si.numpy()]).float(), torch.from_numpy(smp.W_GRID[wi.numpy()]).float()
    )
    torch.testing.assert_close(got, table[torch.arange(4), si, wi], rtol=1e-4, atol=1e-5)
    t = np.ones((2, len(smp.SIGMA_GRID), len(smp.W_GRID)))
    t[0, 3, 4] = 0.1
    t[1, 7, 0] = 0.2
    kl, arg = smp.table_minimum(t)
    np.testing.assert_allclose(kl, [0.1, 0.2])
    np.testing.assert_allclose(arg, [[smp.SIGMA_GRID[3], smp.W_GRID[4]], [smp.SIGMA_GRID[7], smp.W_GRID[0]]])


def test_sampling_net_outputs_stay_in_the_tabulated_range():
    net = smp.SamplingNet(16, 1)
    with torch.no_grad():
        for p in net.parameters():
            p.mul_(50.0)  # push the pre-activations to the extremes
        s, w = net(torch.randn(256, 3, 32) * 10)
    assert torch.all(s >= smp.SIGMA_GRID[0] * 0.999) and torch.all(s <= smp.SIGMA_GRID[-1] * 1.001)
    assert torch.all(w >= smp.W_MIN - 1e-6) and torch.all(w <= 1.0)


def test_validation_set_is_seeded_drawn_like_training_and_apart_from_the_heldout_set(tmp_path):
    from onnx_export import heldout_layered as hl

    a, b = hl.validation_configs([3, 2]), hl.validation_configs([3, 2])
    assert [s.to_json() for s in a] == [s.to_json() for s in b]
    assert [len(s.coatings) for s in a] == [1, 1, 1, 2, 2]
    assert not {s.to_json() for s in a} & {s.to_json() for s in hl.configs()}
    out = tmp_path / "validation.npz"
    hl.main(["--validation", "2", "1", "--walks", "4", "--res", "8", "--out", str(out)])
    d = hl.load(out)
    assert d["lobe"].shape == (3, 4, 8, 8, 3) and d["n_coatings"].tolist() == [1, 1, 2]
    assert [s.to_json() for s in d["stacks"]] == [s.to_json() for s in hl.validation_configs([2, 1])]
    assert np.isfinite(d["lobe"]).all() and d["lobe"].max() > 0
    with pytest.raises(SystemExit):
        hl.main(["--validation", "2", "--only-coatings", "1", "--out", str(out)])
    # another seed, another validation set (stacks and walks), apart from both
    other = hl.validation_configs([3, 2], seed=626_262)
    assert not {s.to_json() for s in other} & {s.to_json() for s in a + hl.configs()}
    hl.main(
        ["--validation", "2", "1", "--seed", "626262", "--walks", "4", "--res", "8", "--out", str(tmp_path / "v2.npz")]
    )
    assert [s.to_json() for s in hl.load(tmp_path / "v2.npz")["stacks"]] == [
        s.to_json() for s in hl.validation_configs([2, 1], seed=626_262)
    ]
    for bad in (["--seed", "626262"], ["--validation", "2", "--seed", str(hl.HELDOUT_SEED)]):
        with pytest.raises(SystemExit):
            hl.main(bad + ["--out", str(tmp_path / "bad.npz")])


def test_training_fit_set_holds_the_first_training_stacks_in_order(tmp_path):
    from onnx_export import heldout_layered as hl
    from onnx_export import layered_data

    for c in (1, 2):
        layered_data.generate(
            tmp_path / f"c{c}", coatings=c, stacks=6, n_wo=2, n_wi=8, walks=2, chunk=4, seed=3, log=lambda s: None
        )
    want = [layered_data.load(tmp_path / "c1")["arrays"].stack(i) for i in range(5)]  # across both chunks
    want += [layered_data.load(tmp_path / "c2")["arrays"].stack(i) for i in range(2)]
    out = tmp_path / "fit.npz"
    hl.main(
        [
            "--training",
            str(tmp_path / "c1"),
            "5",
            str(tmp_path / "c2"),
            "2",
            "--walks",
            "4",
            "--res",
            "8",
            "--out",
            str(out),
        ]
    )
    d = hl.load(out)
    assert [s.to_json() for s in d["stacks"]] == [s.to_json() for s in want]
    assert d["n_coatings"].tolist() == [1] * 5 + [2] * 2 and d["lobe"].shape == (7, 4, 8, 8, 3)
    assert np.isfinite(d["lobe"]).all() and d["lobe"].max() > 0
    for bad in (
        ["--training", str(tmp_path / "c1"), "7"],  # more stacks than the directory holds
        ["--training", str(tmp_path / "none"), "1"],
        ["--training", str(tmp_path / "c1")],
        ["--training", str(tmp_path / "c1"), "0"],
        ["--training", str(tmp_path / "c1"), "2", "--validation", "2"],
    ):
        with pytest.raises(SystemExit):
            hl.main(bad + ["--out", str(tmp_path / "bad.npz")])
    assert not (tmp_path / "bad.npz").exists()


def test_bench_layering_errors_only_tables_the_given_set_and_touches_no_card(tmp_path):
    from benchmarks import bench_layering  # the repository root is on sys.path (conftest)

    size = LAYERING[0]
    card = (MODEL_DIR / f"layering_{size}.json").read_text()
    out = tmp_path / "docs"
    bench_layering.main(["--errors-only", "--sizes", size, "--threads", "1", "--out", str(out)])
    text = (out / "layering.md").read_text()
    assert f"## Decoder `{size}`" in text and len([s for s in LAYERING if f"## Decoder `{s}`" in text]) == 1
    assert "Held-out set: `tests/data/heldout_layered.npz` (32 stacks: 16 with 1 coating" in text
    assert "| 1 | 2 | 16 |" in text and "| 4 | 5 | 4 |" in text  # coatings, layers, stacks
    assert "Encoding speed" not in text and "Sampling efficiency" not in text
    assert (out / f"layering_lobes_{size}.png").stat().st_size > 0
    assert (MODEL_DIR / f"layering_{size}.json").read_text() == card
    for bad in (["--errors-only", "--update-cards"], ["--sizes", "huge"]):
        with pytest.raises(SystemExit):
            bench_layering.main(bad + ["--out", str(tmp_path / "bad")])
    assert not (tmp_path / "bad").exists()


def _toy_stack_set(s=6, groups=4, m=8, seed=0):
    """A StackSet without files: random latents, media and directions; values f = cos(theta_i) of the
    data's incident direction in every channel (not reciprocal, so that the order shows)."""
    g = torch.Generator().manual_seed(seed)
    ss = lay.StackSet.__new__(lay.StackSet)
    ss.n, ss.groups, ss.use_weight = s, groups, True
    ss.z_base, ss.z_tops = torch.randn(s, 3, 32, generator=g), torch.randn(s, 1, 3, 32, generator=g)
    ss.albedo, ss.thickness = torch.rand(s, 1, 3, generator=g), torch.rand(s, 1, generator=g)

    def unit(shape):
        v = torch.randn(*shape, 3, generator=g)
        v[..., 2] = v[..., 2].abs() + 0.1
        return v / v.norm(dim=-1, keepdim=True)

    ss.wi = unit((s, groups * m))
    ss.wo = unit((s, groups)).repeat_interleave(m, dim=1)
    ss.f = ss.wi[..., 2:3].expand(s, groups * m, 3).contiguous()
    ss.weight = torch.rand(s, groups * m, generator=g) + 0.5
    ss.scale = None  # no top-coat transmission factor (StackSet(..., transmission=True) sets one)
    ss.stack_weight = None  # no per-stack level weights (StackSet(..., level_floor=F) sets them)
    return ss


def test_reciprocal_function_space_loss_swaps_the_decoders_directions_and_nothing_else():
    torch.manual_seed(0)
    net = lay.LayeringNet(16, 2)
    ss = _toy_stack_set()

    def loss(dec, reciprocal, seed=3):
        return ss.decoded_batch(
            net, dec, None, 16, 2, torch.Generator().manual_seed(seed), "squared", reciprocal
        ).item()

    def incident_cos(z, wi, wo):  # reproduces the values in the data's order only
        return wi[:, 2]

    def symmetric(z, wi, wo):  # the same in both orders
        return 0.5 * (wi[:, 2] + wo[:, 2]) + z[:, 0].abs()

    assert loss(incident_cos, False) == 0.0
    swapped = [loss(incident_cos, True, seed) for seed in range(8)]
    assert all(v > 0.0 for v in swapped)  # some group of 32 was swapped in every batch
    # targets, weights and cosines stay with their pairs: a reciprocal decoder does not see the swap
    assert loss(symmetric, True) == pytest.approx(loss(symmetric, False), rel=1e-6)


def test_stage_two_trains_each_coating_count_with_an_equal_share_of_the_batch(tmp_path, monkeypatch):
    """With --c3 and --c4 the recursion is trained three and four deep too: every stage-2 step draws stacks
    with four, three, two and one coating in equal shares, and the run records the data sets it read."""
    from onnx_export import layered_data

    for c in (1, 2, 3, 4):
        layered_data.generate(tmp_path / f"c{c}", c, 4, 2, 8, 2, 4, seed=11, log=lambda s: None)
    drawn = []
    batch = lay.StackSet.batch

    def recorded(self, net, dec, b, *rest, **kw):
        drawn.append((self.z_tops.shape[1], b))
        return batch(self, net, dec, b, *rest, **kw)

    monkeypatch.setattr(lay.StackSet, "batch", recorded)
    args = ["train", "--size", "tiny", "--init-from", "tiny", "--heldout", "none"]
    args += ["--c1", str(tmp_path / "c1"), "--c2", str(tmp_path / "c2"), "--c3", str(tmp_path / "c3")]
    args += ["--c4", str(tmp_path / "c4")]
    args += ["--steps", "1", "--finetune", "2", "--batch", "9", "--pairs", "4", "--out", str(tmp_path / "run")]
    res = lay.train(lay.parser().parse_args(args), log=lambda s: None)
    assert res["step"] == 3 and np.isfinite(res["loss"])
    assert drawn == [(1, 9)] + [(2, 2), (3, 2), (4, 2), (1, 3)] * 2
    data = torch.load(tmp_path / "run" / "ckpt.pt", weights_only=False)["history"]["data"]
    assert [f"--coatings {c}" in d for d, c in zip(data, (1, 2, 3, 4), strict=True)] == [True] * 4
    with pytest.raises(ValueError, match="--c3"):
        lay.coating_data(lay.parser().parse_args(["train", "--out", str(tmp_path / "x")]), 3)
    with pytest.raises(ValueError, match="--c4"):
        lay.coating_data(lay.parser().parse_args(["train", "--out", str(tmp_path / "x")]), 4)


def test_layering_loss_weights_grazing_pairs_as_the_pair_loss_does():
    from onnx_export.nets import pair_loss

    grazing, steep = np.radians(86.0), np.radians(20.0)
    wi = torch.tensor([[np.sin(grazing), 0.0, np.cos(grazing)], [np.sin(steep), 0.0, np.cos(steep)]]).float()
    wo = torch.tensor([[0.0, 0.6, 0.8], [0.0, 0.6, 0.8]])
    pred, target = torch.tensor([0.5, 0.5]), torch.tensor([0.25, 0.25])
    plain = lay.layering_loss(pred, target, wi, wo, None, "l2rel")
    floored = lay.layering_loss(pred, target, wi, wo, None, "l2rel", grazing_floor=0.1)
    assert floored.item() == pytest.approx(pair_loss(pred, target, wi, wo, "l2rel", 0.1).mean().item())
    assert plain.item() == pytest.approx(pair_loss(pred, target, wi, wo, "l2rel").mean().item())
    assert floored > plain  # the grazing pair's term is divided by its floored cosine, squared
    args = lay.parser().parse_args(["train", "--grazing-floor", "0.1", "--out", "x"])
    card = {"args": {k: str(v) for k, v in vars(args).items()}, "history": {}, "step": 10}
    assert "--grazing-floor 0.1" in lay.training_loss(card)


def test_a_three_coating_share_sets_its_stacks_and_loss_weight_and_the_rest_is_split_evenly():
    def shares(*extra):
        return lay.stage2_shares(lay.parser().parse_args(["train", "--batch", "8", *extra, "--out", "x"]))

    assert shares() == {2: (4, 0.5), 1: (4, 0.5)}
    assert shares("--c3", "c3") == {
        2: (2, pytest.approx(1 / 3)),
        3: (2, pytest.approx(1 / 3)),
        1: (4, pytest.approx(1 / 3)),
    }
    assert shares("--c3", "c3", "--c3-share", "0.25") == {2: (3, 0.375), 3: (2, 0.25), 1: (3, 0.375)}
    for c, (b, w) in shares("--c3", "c3", "--c3-share", "0.1").items():
        assert b >= 1 and w > 0, (c, b, w)  # a small share still draws one stack
    assert shares("--c3", "c3", "--c4", "c4") == {c: (2, 0.25) for c in (2, 3, 4, 1)}
    four = shares("--c3", "c3", "--c4", "c4", "--c3-share", "0.25")
    assert four == {2: (2, 0.25), 4: (2, 0.25), 3: (2, 0.25), 1: (2, 0.25)}
    assert sum(b for b, _ in shares("--c3", "c3", "--c4", "c4", "--c3-share", "0.5").values()) == 8
    with pytest.raises(ValueError, match="needs --c3"):
        shares("--c3-share", "0.2")
    with pytest.raises(ValueError, match="needs --c3"):
        shares("--c4", "c4", "--c3-share", "0.2")
    with pytest.raises(ValueError, match=r"must be in \(0, 1\)"):
        shares("--c3", "c3", "--c3-share", "1.0")


def test_a_bad_three_coating_share_fails_before_any_training_step(tmp_path):
    args = lay.parser().parse_args(
        ["train", "--c3", "c3", "--c3-share", "0.9", "--batch", "3", "--finetune", "5", "--out", str(tmp_path / "r")]
    )
    with pytest.raises(ValueError, match="leaves no stacks with the other coating counts"):
        lay.train(args, log=lambda s: None)
    assert not (tmp_path / "r").exists()  # nothing was loaded, trained or written


def test_the_paired_bootstrap_of_the_shipping_rule_sees_ties_and_clear_differences():
    """benchmarks/compare_layering.py: a network against itself differs by exactly 0 in every resample;
    one worse on every stack is worse in every resample; unpaired arrays are an error."""
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
    import compare_layering as cmp

    errors = np.random.default_rng(0).random((40, 4)) * 0.2
    assert cmp.paired_bootstrap(errors, errors, 200, 0) == (0.0, 0.0, 0.0)
    d, sd, worse = cmp.paired_bootstrap(errors, errors + 0.01, 200, 0)
    assert d == pytest.approx(0.02) and worse == 1.0 and sd < 1e-9  # +0.01 on each of median and p90
    with pytest.raises(ValueError, match="one shape"):
        cmp.paired_bootstrap(errors, errors[:30], 10, 0)


def test_stack_levels_scale_with_the_values_and_level_weights_make_a_dim_stack_count_like_the_median_one():
    ss = _toy_stack_set(s=3)
    for name in ("wi", "wo", "f", "weight"):  # three copies of stack 0's lobe
        setattr(ss, name, getattr(ss, name)[:1].expand(3, *getattr(ss, name).shape[1:]).clone())
    ss.f = ss.f * torch.tensor([1.0, 0.01, 1e-6])[:, None, None]  # the same lobe, a hundredth, all but black
    level = lay.stack_levels(ss.f, ss.wi, ss.wo, ss.weight)
    cc = ss.wi[..., 2] * ss.wo[..., 2]
    rms0 = ((ss.weight[0] * (cc[0] * ss.f[0, :, 0]) ** 2).sum() / ss.weight[0].sum()).sqrt()
    assert level[0].item() == pytest.approx(rms0.item(), rel=1e-5)
    assert level[1].item() == pytest.approx(0.01 * level[0].item(), rel=1e-5)
    assert lay.level_weights(level, 0.0) is None
    w = lay.level_weights(level, 0.05)  # median level: stack 1's; the floor: 0.05 of it
    assert w[1].item() == pytest.approx(1.0 / level[1].item() ** 2, rel=1e-5)  # a relative error weighs alike
    assert w[0].item() == pytest.approx(w[1].item(), rel=1e-5)  # the brighter stack keeps the median's weight
    assert w[2].item() == pytest.approx(w[1].item() / 0.05**2, rel=1e-5)  # floored, not 1e8 times

    # the batch carries each row's stack weight times its cosine weight, into layering_loss
    ss.use_weight, ss.weight = True, torch.ones_like(ss.weight)
    ss.stack_weight = w
    net = lay.LayeringNet(16, 2)
    dec = lambda z, wi, wo: wi[:, 2] * 0.0 + 1.0  # noqa: E731
    gen = torch.Generator().manual_seed(5)
    pred, f, wi, wo, wt = ss.batch(net, dec, 7, 4, gen)
    s = torch.randint(0, ss.n, (7,), generator=torch.Generator().manual_seed(5))
    assert torch.equal(wt, w[s].repeat_interleave(3 * 4))
    args = lay.parser().parse_args(["train", "--level-floor", "0.1", "--out", "x"])
    card = {"args": {k: str(v) for k, v in vars(args).items()}, "history": {}, "step": 10}
    assert "--level-floor 0.1" in lay.training_loss(card)
