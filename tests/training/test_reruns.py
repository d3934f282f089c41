"""Reruns of the training pipeline: data folders, resumed runs, cached tables and exports do what the command
asks for, or refuse with an error naming the option; nothing is kept silently from another run."""

import json
import shlex
import shutil
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from addon.core.neural import MODEL_DIR  # noqa: E402
from addon.core.neural.features import N_FEATURES  # noqa: E402
from onnx_export import data as datamod  # noqa: E402
from onnx_export import export, layered_data, layering, layering_project, sampling_net, train_decoder  # noqa: E402
from onnx_export.cli import command_line  # noqa: E402
from onnx_export.evaluate import load_decoder  # noqa: E402
from onnx_export.nets import Decoder, Encoder, pair_loss  # noqa: E402

QUIET = dict(log=lambda s: None)


class Killed(Exception):
    """Stands for a run killed between two steps."""


def kill_at_call(monkeypatch, module, n: int) -> None:
    """Make ``module.cosine_lr`` (called once a step, before the step) raise ``Killed`` at its ``n``-th call."""
    real, calls = module.cosine_lr, []

    def counted(*a, **k):
        calls.append(a)
        if len(calls) == n:
            raise Killed
        return real(*a, **k)

    monkeypatch.setattr(module, "cosine_lr", counted)


def same_weights(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


# ----------------------------------------------------------------------------- data folders


def test_a_data_rerun_with_other_options_is_refused_naming_the_option(tmp_path):
    kw = dict(materials=8, pairs=16, chunk=8, seed=1, **QUIET)
    datamod.generate("single", tmp_path / "s", **kw)
    for change, flag in (({"seed": 2}, "--seed"), ({"pairs": 32}, "--pairs"), ({"chunk": 4}, "--chunk")):
        with pytest.raises(ValueError, match=f"made with {flag} "):
            datamod.generate("single", tmp_path / "s", **(kw | change))
    with pytest.raises(ValueError, match="--materials 4"):  # fewer than it holds
        datamod.generate("single", tmp_path / "s", **(kw | {"materials": 4}))
    assert json.loads((tmp_path / "s" / "manifest.json").read_text()) == {
        "set": "single",
        "seed": 1,
        "pairs": 16,
        "chunk": 8,
        "materials": 8,
    }
    layered_data.generate(tmp_path / "c1", 1, 2, 1, 8, 1, 2, seed=11, **QUIET)
    with pytest.raises(ValueError, match="made with --wi 8, this run asks for 4"):
        layered_data.generate(tmp_path / "c1", 1, 2, 1, 4, 1, 2, seed=11, **QUIET)
    with pytest.raises(ValueError, match="made with --coatings 1"):
        layered_data.generate(tmp_path / "c1", 2, 2, 1, 8, 1, 2, seed=11, **QUIET)


def test_chunks_from_before_manifests_are_checked_on_what_they_show(tmp_path):
    datamod.generate("single", tmp_path / "s", materials=8, pairs=16, chunk=8, seed=1, **QUIET)
    (tmp_path / "s" / "manifest.json").unlink()
    with pytest.raises(ValueError, match="made with --pairs 16, this run asks for 32"):
        datamod.generate("single", tmp_path / "s", materials=8, pairs=32, chunk=8, seed=1, **QUIET)
    logs = []
    datamod.generate("single", tmp_path / "s", materials=8, pairs=16, chunk=8, seed=1, log=logs.append)
    assert any("without a manifest" in s for s in logs) and (tmp_path / "s" / "manifest.json").exists()


def test_growing_a_data_folder_makes_its_short_last_chunk_again(tmp_path):
    kw = dict(pairs=16, chunk=8, seed=3, **QUIET)
    datamod.generate("single", tmp_path / "grown", materials=12, **kw)
    datamod.generate("single", tmp_path / "grown", materials=24, **kw)
    datamod.generate("single", tmp_path / "fresh", materials=24, **kw)
    grown, fresh = datamod.load(tmp_path / "grown"), datamod.load(tmp_path / "fresh")
    assert grown["f"].shape == (24, 16, 3)
    for k in fresh:
        np.testing.assert_array_equal(grown[k], fresh[k], err_msg=k)
    layered_data.generate(tmp_path / "c1", 1, 3, 1, 4, 1, 2, seed=11, **QUIET)
    layered_data.generate(tmp_path / "c1", 1, 4, 1, 4, 1, 2, seed=11, **QUIET)
    assert len(layered_data.load(tmp_path / "c1")["f"]) == 4
    assert layered_data.data_command(tmp_path / "c1") == (
        f"python -m onnx_export.layered_data --coatings 1 --stacks 4 --seed 11 --wo 1 --wi 4 --walks 1 --chunk 2 "
        f"--out {tmp_path / 'c1'}"
    )


# ----------------------------------------------------------------------------- command line


@pytest.mark.parametrize(
    "module, argv, flag",
    [
        (datamod, ["--chunk", "0", "--materials", "8"], "--chunk"),
        (datamod, ["--materials", "-5"], "--materials"),
        (layered_data, ["--wi", "0"], "--wi"),
        (train_decoder, ["--data", "x", "--every", "0"], "--every"),
        (train_decoder, ["--data", "x", "--log-every", "0"], "--log-every"),
        (train_decoder, ["--data", "x", "--width", "16", "--steps", "1"], "--width and --depth go together"),
    ],
)
def test_bad_counts_are_usage_errors_naming_the_flag(module, argv, flag, tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        module.main([*argv, "--out", str(tmp_path / "out")])
    assert e.value.code == 2 and flag in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_a_layering_card_command_parses_back_to_its_arguments():
    """``layering train`` stores its arguments as ``str(v)``: a list of numbers renders as its items."""
    argv = ["train", "--decoded-coatings", "1", "2", "--decoded-data", "a", "b", "--out", "x"]
    a = layering.parser().parse_args(argv)
    stored = {k: str(v) for k, v in vars(a).items()}
    cmd = command_line("onnx_export.layering train", stored, skip=("cmd",))
    assert "--decoded-coatings 1 2 --" in cmd and "--decoded-data a b --" in cmd
    assert vars(layering.parser().parse_args(shlex.split(cmd)[3:])) == vars(a)
    assert command_line("m", {"scales": "[0.5, 4.0]", "none": "[]"}) == "python -m m --scales 0.5 4.0 --none"


# ----------------------------------------------------------------------------- resumed runs


def decoder_args(data: Path, out: Path, *extra: str):
    argv = ["--data", str(data), "--steps", "6", "--every", "3", "--batch", "8", "--pairs", "16", "--out", str(out)]
    return train_decoder.parser().parse_args([*argv, *extra])


def test_a_resumed_decoder_run_equals_the_uninterrupted_one(tmp_path, monkeypatch):
    datamod.generate("single", tmp_path / "d", materials=16, pairs=32, chunk=8, seed=1, **QUIET)
    whole = train_decoder.train(decoder_args(tmp_path / "d", tmp_path / "A"), **QUIET)
    with monkeypatch.context() as m:
        kill_at_call(m, train_decoder, 4)  # before step 4: the checkpoint of step 3 is on disk
        with pytest.raises(Killed):
            train_decoder.train(decoder_args(tmp_path / "d", tmp_path / "C"), **QUIET)
    assert torch.load(tmp_path / "C" / "ckpt.pt", weights_only=False)["step"] == 3
    resumed = train_decoder.train(decoder_args(tmp_path / "d", tmp_path / "C"), **QUIET)
    a, c = (torch.load(tmp_path / w / "ckpt.pt", weights_only=False) for w in ("A", "C"))
    assert same_weights(a["decoder"], c["decoder"]) and torch.equal(a["latents"], c["latents"])
    assert resumed["loss"] == whole["loss"]
    # another argument on resume: refused, naming it (more steps are fine)
    with pytest.raises(ValueError, match="trained with --size tiny, this run asks for --size small"):
        train_decoder.train(decoder_args(tmp_path / "d", tmp_path / "C", "--size", "small"), **QUIET)
    with pytest.raises(ValueError, match="--materials 8"):
        train_decoder.train(decoder_args(tmp_path / "d", tmp_path / "C", "--materials", "8"), **QUIET)
    assert train_decoder.train(decoder_args(tmp_path / "d", tmp_path / "C", "--steps", "7"), **QUIET)["step"] == 7


@pytest.fixture(scope="module")
def layering_data(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("layering_data")
    for c in (1, 2):
        layered_data.generate(tmp / f"c{c}", c, 8, 2, 8, 2, 8, seed=11, **QUIET)
    return tmp


def layering_args(data: Path, out: Path, *extra: str):
    argv = ["train", "--size", "tiny", "--c1", str(data / "c1"), "--c2", str(data / "c2"), "--heldout", "none"]
    argv += ["--width", "16", "--depth", "2", "--batch", "4", "--pairs", "8", "--every", "1", "--out", str(out)]
    return layering.parser().parse_args([*argv, *extra])


@pytest.mark.parametrize("kill_at", [3, 6])  # in stage 1 (before step 2 of 4), in stage 2 (before its step 1)
def test_a_resumed_layering_run_equals_the_uninterrupted_one(layering_data, tmp_path, monkeypatch, kill_at):
    stages = ("--steps", "4", "--finetune", "3", "--remainder", "--top-transmission")
    layering.train(layering_args(layering_data, tmp_path / "A", *stages), **QUIET)
    with monkeypatch.context() as m:
        kill_at_call(m, layering, kill_at)
        with pytest.raises(Killed):
            layering.train(layering_args(layering_data, tmp_path / "C", *stages), **QUIET)
    assert torch.load(tmp_path / "C" / "ckpt.pt", weights_only=False)["step"] == kill_at - 1
    layering.train(layering_args(layering_data, tmp_path / "C", *stages), **QUIET)
    a, c = (torch.load(tmp_path / w / "ckpt.pt", weights_only=False) for w in ("A", "C"))
    assert a["step"] == c["step"] == 7 and same_weights(a["net"], c["net"])
    with pytest.raises(ValueError, match="trained with --pairs 8, this run asks for --pairs 16"):
        layering.train(layering_args(layering_data, tmp_path / "C", *stages, "--pairs", "16"), **QUIET)


def test_a_resumed_projected_run_regresses_once_and_equals_the_uninterrupted_one(layering_data, tmp_path, monkeypatch):
    """Stage 0 is done once its checkpoint is written, held-out evaluation or not."""
    z = np.random.default_rng(0).normal(scale=0.3, size=(8, 3, 32)).astype(np.float32)
    np.savez(tmp_path / "projected.npz", z=z)
    stages = ["--projected", str(tmp_path / "projected.npz"), "--regress-steps", "3", "--decoded-steps", "4"]
    stages += ["--steps", "0", "--finetune", "0"]
    regressions = []
    real = layering.regress_projected
    monkeypatch.setattr(layering, "regress_projected", lambda *a, **k: regressions.append(1) or real(*a, **k))
    layering.train(layering_args(layering_data, tmp_path / "A", *stages), **QUIET)
    assert len(regressions) == 1
    with monkeypatch.context() as m:
        kill_at_call(m, layering, 3 + 3)  # three regression steps, then the function-space stage's third
        with pytest.raises(Killed):
            layering.train(layering_args(layering_data, tmp_path / "C", *stages), **QUIET)
    assert torch.load(tmp_path / "C" / "ckpt.pt", weights_only=False)["history"]["decoded"]["step"] == 2
    layering.train(layering_args(layering_data, tmp_path / "C", *stages), **QUIET)
    assert len(regressions) == 2  # one for A, one for C: the resumed run did not regress again
    a, c = (torch.load(tmp_path / w / "ckpt.pt", weights_only=False) for w in ("A", "C"))
    assert same_weights(a["net"], c["net"])


def test_a_missing_heldout_file_fails_at_the_start(layering_data, tmp_path):
    with pytest.raises(FileNotFoundError, match="--heldout .*validaton.npz: no such file"):
        layering.train(layering_args(layering_data, tmp_path / "run", "--heldout", str(tmp_path / "validaton.npz")))
    assert not (tmp_path / "run").exists()
    with pytest.raises(ValueError, match="--keep-best .*give --heldout"):
        layering.train(layering_args(layering_data, tmp_path / "run", "--keep-best"))


# ----------------------------------------------------------------------------- re-fit, tables, export


def test_a_refit_of_a_remainder_decoder_fits_what_the_decoder_holds(layering_data, tmp_path, monkeypatch):
    """``layering_project --decoder`` on a ``--remainder --top-transmission`` checkpoint: the targets are the
    remainders and the decoder's output is scaled by the transmission, as in training (the loss it reports
    is that loss, and the re-fit lowers it); ``--size`` of a shipped remainder decoder likewise."""
    c1 = layering_data / "c1"
    train_decoder.main(
        ["--data", str(c1), "--steps", "40", "--batch", "8", "--pairs", "32", "--loss", "l2rel", "--remainder"]
        + ["--top-transmission", "--log-every", "1000", "--out", str(tmp_path / "run")]
    )
    layering_project.main(
        ["--decoder", str(tmp_path / "run" / "ckpt.pt"), "--data", str(c1), "--steps", "30", "--pairs", "32"]
        + ["--out", str(tmp_path / "refit.pt")]
    )
    t = train_decoder.load_training_tensors([c1], remainder=True, transmission=True)

    def trained_loss(ckpt):  # the l2rel of the latents as training compares them, at every pair
        dec, lat = load_decoder(ckpt)
        n, p = t["wi"].shape[:2]
        wi, wo = (t[k].unsqueeze(1).expand(n, 3, p, 3).reshape(-1, 3) for k in ("wi", "wo"))
        with torch.no_grad():
            pred = dec(lat.repeat_interleave(p, dim=0), wi, wo) * t["scale"].repeat_interleave(3, 0).reshape(-1)
        return float(pair_loss(pred, t["f"].permute(0, 2, 1).reshape(-1), wi, wo, "l2rel").mean())

    before, after = trained_loss(tmp_path / "run" / "ckpt.pt"), trained_loss(tmp_path / "refit.pt")
    rec = torch.load(tmp_path / "refit.pt", weights_only=False)["refit"]["sets"][str(c1)]
    assert after < before and rec["loss_before"][0] == pytest.approx(before, rel=0.5)
    seen = {}

    def fake_project(dec, wi, wo, f, **kw):
        seen.update(f=f, scale=kw.get("scale"))
        return torch.zeros(len(wi), 3, 32)

    monkeypatch.setattr(layering_project, "project", fake_project)
    layering_project.project_set("tiny", c1, steps=1, chunk=8, pairs=8, loss="l1", **QUIET)
    card = json.loads((MODEL_DIR / "decoder_tiny.json").read_text())
    expected = train_decoder.load_training_tensors(
        [c1], remainder=card["remainder"], transmission=card["top_transmission"]
    )
    torch.testing.assert_close(torch.as_tensor(seen["f"]), expected["f"])
    assert (seen["scale"] is not None) == bool(card.get("top_transmission"))


def test_sampling_tables_are_computed_again_for_other_settings(tmp_path, capsys):
    models = tmp_path / "models"
    models.mkdir()
    for role in ("decoder", "encoder", "layering"):
        for f in MODEL_DIR.glob(f"{role}_tiny*"):
            shutil.copy(f, models / f.name)
    base = ["--size", "tiny", "--heldout", "3", "--samples", "10", "--steps", "2", "--batch", "4"]
    base += ["--models", str(models), "--out", str(tmp_path / "run")]
    sampling_net.main([*base, "--materials", "4"])
    first = dict(np.load(tmp_path / "run" / "tables.npz"))
    capsys.readouterr()
    sampling_net.main([*base, "--materials", "4"])  # the same settings: the same tables, no word
    assert "computing them again" not in capsys.readouterr().err
    sampling_net.main([*base, "--materials", "6", "--samples", "15"])
    assert "(materials 4 -> 6, samples 10 -> 15): computing them again" in capsys.readouterr().err
    d = np.load(tmp_path / "run" / "tables.npz")
    assert d["z"].shape[0] == 6 and first["z"].shape[0] == 4
    assert (
        json.loads(str(d["key"]))["models"]["decoder_tiny.onnx"]
        == json.loads(str(first["key"]))["models"]["decoder_tiny.onnx"]
    )
    assert json.loads((models / "sampling_tiny.json").read_text())["training"]["materials"] == 6


def hand_made_encoder(path: Path) -> Path:
    enc = Encoder(N_FEATURES, 8, 1)
    torch.save({"encoder": enc.state_dict(), "config": enc.config(), "args": {}}, path)
    return path


def test_export_refuses_a_graph_that_does_not_match_torch_and_writes_nothing(tmp_path):
    """A depth-0 decoder (what ``--width`` without ``--depth`` trained): its fused RGB graph cannot hold it."""
    dec = Decoder(16, 0)
    torch.save(
        {"decoder": dec.state_dict(), "config": dec.config(), "latents": torch.zeros(3, 32), "step": 1,
         "args": {"data": ["x"], "seed": 0, "loss": ["l1"]}},
        tmp_path / "ckpt.pt",
    )  # fmt: skip
    out = tmp_path / "models"
    out.mkdir()
    (out / "decoder_tiny.json").write_text("old card")
    with pytest.raises(SystemExit) as e:
        export.main(
            ["--size", "tiny", "--decoder", str(tmp_path / "ckpt.pt"), "--encoder"]
            + [str(hand_made_encoder(tmp_path / "enc.pt")), "--out", str(out)]
        )
    assert e.value.code not in (0, None) and "decoder_tiny_rgb.onnx" in str(e.value.code)
    assert [p.name for p in out.iterdir()] == ["decoder_tiny.json"] and (
        out / "decoder_tiny.json"
    ).read_text() == "old card"


def test_the_decoder_card_names_the_data_the_checkpoint_was_trained_on(tmp_path):
    datamod.generate("single", tmp_path / "single", materials=8, pairs=32, chunk=8, seed=4, **QUIET)
    layered_data.generate(tmp_path / "c1", 1, 2, 2, 8, 2, 2, seed=11, **QUIET)
    train_decoder.main(
        ["--data", str(tmp_path / "single"), str(tmp_path / "c1"), "--steps", "2", "--batch", "8", "--pairs", "16"]
        + ["--loss", "l1", "l2rel", "--remainder", "--out", str(tmp_path / "run")]
    )
    layered_data.generate(tmp_path / "c1", 1, 6, 2, 8, 2, 2, seed=11, **QUIET)  # the data grow after the training
    export.main(
        ["--size", "tiny", "--decoder", str(tmp_path / "run" / "ckpt.pt"), "--encoder"]
        + [str(hand_made_encoder(tmp_path / "enc.pt")), "--out", str(tmp_path / "models")]
    )
    card = json.loads((tmp_path / "models" / "decoder_tiny.json").read_text())["training"]
    assert card["data"] == [
        "python -m onnx_export.data --set single --materials 8 --seed 4 --pairs 32 --chunk 8 "
        f"--out {tmp_path / 'single'}",
        f"python -m onnx_export.layered_data --coatings 1 --stacks 2 --seed 11 --wo 2 --wi 8 --walks 2 --chunk 2 "
        f"--out {tmp_path / 'c1'}",
    ]
    assert card["seeds"] == {"data": [4, 11], "training": 0}
