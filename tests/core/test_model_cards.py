"""The model set of a size is checked against its cards: renamed, damaged or mismatched files are typed errors."""

import json
import shutil

import numpy as np
import pytest

from addon.core.neural import (
    DEFAULT_SIZE,
    MODEL_DIR,
    ROLES,
    SIZES,
    ModelFileError,
    ModelSet,
    encode_stack,
    file_digest,
    load_models,
    read_card,
    resolve_size,
)
from addon.core.stack import PRESETS, Diffuse, Stack


def _copy(size: str, dest):
    for f in MODEL_DIR.glob(f"*_{size}*"):
        shutil.copy(f, dest / f.name)
    return dest


def _edit_card(path, **changes):
    card = json.loads(path.read_text())
    card.update(changes)
    path.write_text(json.dumps(card))


@pytest.mark.parametrize("size", SIZES)
def test_every_shipped_card_names_its_files_and_what_it_was_trained_with(size):
    for role in ROLES:
        card = read_card(role, size)  # raises on any mismatch
        assert f"{role}_{size}.onnx" in card["files"]
        for name, digest in card["files"].items():
            assert file_digest(MODEL_DIR / name) == digest
    assert set(read_card("encoder", size)["trained_with"]) == {f"decoder_{size}.onnx"}
    assert set(read_card("sampling", size)["trained_with"]) >= {f"layering_{size}.onnx"}


def test_a_paper_decoder_renamed_to_tiny_is_refused(tmp_path):
    d = _copy("tiny", tmp_path)
    shutil.copy(MODEL_DIR / "decoder_paper.onnx", d / "decoder_tiny.onnx")
    with pytest.raises(ModelFileError, match="decoder_tiny.onnx does not match its card"):
        ModelSet("tiny", model_dir=d)
    # renaming the card along with it is caught by the card's name
    shutil.copy(MODEL_DIR / "decoder_paper.json", d / "decoder_tiny.json")
    with pytest.raises(ModelFileError, match="card of 'decoder_paper'"):
        ModelSet("tiny", model_dir=d)


def test_a_changed_decoder_is_caught_by_the_encoder_card(tmp_path):
    d = _copy("tiny", tmp_path)
    _edit_card(d / "encoder_tiny.json", trained_with={"decoder_tiny.onnx": "0" * 64})
    with pytest.raises(ModelFileError, match="encoder_tiny.onnx was trained with another decoder_tiny.onnx"):
        ModelSet("tiny", model_dir=d)


def test_a_changed_encoder_is_caught_by_the_layering_card(tmp_path):
    d = _copy("tiny", tmp_path)
    card = json.loads((d / "layering_tiny.json").read_text())
    card["trained_with"]["encoder_tiny.onnx"] = "0" * 64
    (d / "layering_tiny.json").write_text(json.dumps(card))
    m = ModelSet("tiny", model_dir=d)  # single layers need no layering network
    encode_stack(Stack(Diffuse(0.5)), m)
    with pytest.raises(ModelFileError, match="layering_tiny.onnx was trained with another encoder_tiny.onnx"):
        encode_stack(PRESETS["coated_gold"], m)


def test_a_damaged_card_names_the_card(tmp_path):
    d = _copy("tiny", tmp_path)
    (d / "decoder_tiny.json").write_text('{"name": "decoder_tiny", "files": {')
    with pytest.raises(ModelFileError, match="decoder_tiny.json is not valid JSON"):
        ModelSet("tiny", model_dir=d)


@pytest.mark.parametrize("width", [0, -3, 2.5, True])
def test_a_card_with_a_bad_width_names_the_field(tmp_path, width):
    d = _copy("tiny", tmp_path)
    card = json.loads((d / "decoder_tiny.json").read_text())
    card["architecture"]["width"] = width
    (d / "decoder_tiny.json").write_text(json.dumps(card))
    with pytest.raises(ModelFileError, match="architecture.width must be a positive integer"):
        ModelSet("tiny", model_dir=d)


def test_a_git_lfs_pointer_is_named(tmp_path):
    d = _copy("tiny", tmp_path)
    (d / "encoder_tiny.onnx").write_text("version https://git-lfs.github.com/spec/v1\noid sha256:00\nsize 1\n")
    with pytest.raises(ModelFileError, match="encoder_tiny.onnx is a Git LFS pointer"):
        ModelSet("tiny", model_dir=d)


def test_a_corrupt_onnx_file_matching_its_card_is_a_typed_error(tmp_path):
    """Bytes that are no ONNX model (ONNX Runtime's InvalidProtobuf) give ModelFileError naming the file."""
    d = _copy("tiny", tmp_path)
    bad = d / "sampling_tiny.onnx"
    bad.write_bytes(np.random.default_rng(0).bytes(4096))
    card = json.loads((d / "sampling_tiny.json").read_text())
    card["files"] = {bad.name: file_digest(bad)}
    (d / "sampling_tiny.json").write_text(json.dumps(card))
    m = ModelSet("tiny", model_dir=d)
    with pytest.raises(ModelFileError, match="sampling_tiny.onnx is not a loadable ONNX model"):
        m.proxy_params(np.zeros((3, 32), np.float32))


def test_a_missing_card_or_file_is_file_not_found(tmp_path):
    d = _copy("tiny", tmp_path)
    (d / "decoder_tiny.json").unlink()
    with pytest.raises(FileNotFoundError, match="decoder_tiny.json is missing"):
        ModelSet("tiny", model_dir=d)
    (d / "layering_tiny.onnx").unlink()
    (d / "layering_tiny.json").unlink()
    with pytest.raises(FileNotFoundError, match="layering_tiny.onnx"):
        read_card("layering", "tiny", d)


def test_auto_resolves_to_the_default_size_in_one_place(tmp_path):
    assert resolve_size("auto") == DEFAULT_SIZE == "tiny"
    assert resolve_size("Small") == "small"
    assert load_models("auto") is load_models(DEFAULT_SIZE)
    with pytest.raises(ValueError, match="unknown decoder size 'huge'"):
        resolve_size("huge")
    with pytest.raises(FileNotFoundError, match="no decoder size is shipped"):
        resolve_size("auto", tmp_path)
    _copy("small", tmp_path)
    assert resolve_size("auto", tmp_path) == "small"  # the default is not shipped there: the first that is


def test_the_default_size_runs_at_least_a_million_rgb_evals_per_second_on_its_card():
    card = read_card("decoder", DEFAULT_SIZE)
    assert card["speed_cpu"]["rgb_evals_per_s"] >= 1e6, card["speed_cpu"]


def test_a_files_digest_is_read_once_and_again_when_the_file_changes(tmp_path):
    """Every export checks the models against their cards: the viewport read and hashed 27 MB at each edit. A digest
    is kept for each version of a file (its inode, size and modification time), and a changed file is read again."""
    import hashlib
    import os

    path = tmp_path / "m.onnx"
    path.write_bytes(b"one")
    assert file_digest(path) == hashlib.sha256(b"one").hexdigest()
    path.write_bytes(b"two")
    os.utime(path, ns=(1, 1))  # a changed file, whatever its clock says
    assert file_digest(path) == hashlib.sha256(b"two").hexdigest()
    path.write_bytes(b"three, longer")
    os.utime(path, ns=(1, 1))  # the same time as before: its size tells it
    assert file_digest(path) == hashlib.sha256(b"three, longer").hexdigest()
