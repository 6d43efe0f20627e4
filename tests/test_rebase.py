"""A tokenizer re-based onto its family's no-contact image (``Tokenizer.rebase_3HW``): the family
tokenizer on the sensor's images moved onto the family's background and back, saved and loaded with its
folder, and covered by its digest (``vqtouch fewshot``'s default: tests/test_fewshot_generation.py)."""

import pytest
import torch

import generator_runs
from vqtouch.core import ConfigError, load_plugins
from vqtouch.plugins.tokenizer import REBASE_FILE, Tokenizer, load_tokenizer, save_rebase, tokenizer_digest

HOST = load_plugins(autoload=False)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    folder = generator_runs.tiny_tokenizer_folder(tmp_path_factory.mktemp("tok"))
    tokenizer, _ = load_tokenizer(folder, HOST)
    return folder, tokenizer


def _images(seed, count=3, side=32):
    return torch.rand(count, 3, side, side, generator=torch.Generator().manual_seed(seed))


def test_a_rebased_tokenizer_is_the_family_tokenizer_on_images_moved_onto_the_familys_background(tiny):
    _, plain = tiny
    family_background, sensor_background = _images(1, 1)[0], _images(2, 1)[0]
    rebased = Tokenizer(plain.autoencoder, plain.quantizer, family_background - sensor_background)
    images = (sensor_background + 0.1 * (_images(3) - 0.5)).clamp(0, 1)
    moved = images - sensor_background + family_background
    with torch.no_grad():
        codes = rebased.encode_codes(images)
        assert torch.equal(codes, plain.encode_codes(moved))
        # Decoding moves back: the family decoder's image, less the family's background, on the sensor's.
        unclamped = (plain.autoencoder.decode(plain.quantizer.lookup(codes)).float() + 1) / 2
        expected = (unclamped - family_background + sensor_background).clamp(0, 1)
        assert torch.allclose(rebased.decode_codes(codes), expected, atol=1e-6)
        assert torch.allclose(rebased.reconstruct(images)[0], expected, atol=1e-6)
        # The sensor's own background takes exactly the family background's codes.
        assert torch.equal(rebased.encode_codes(sensor_background[None]), plain.encode_codes(family_background[None]))


def test_the_rebase_image_is_saved_loaded_and_digested_with_its_folder(tiny, tmp_path):
    import shutil

    folder, _ = tiny
    copy = tmp_path / "adapted"
    shutil.copytree(folder, copy)
    plain_digest = tokenizer_digest(copy)
    assert load_tokenizer(copy, HOST)[0].rebase_3HW is None
    rebase = _images(4, 1)[0] - 0.5
    save_rebase(copy, rebase, {"adaptation.target": "far"})
    loaded, _ = load_tokenizer(copy, HOST)
    assert torch.equal(loaded.rebase_3HW, rebase)
    rebased_digest = tokenizer_digest(copy)
    assert rebased_digest != plain_digest  # a generator pinned to the folder sees the change
    save_rebase(copy, rebase + 0.01, {})
    assert tokenizer_digest(copy) not in {plain_digest, rebased_digest}
    from safetensors.torch import save_file

    save_file({"other": torch.zeros(2)}, str(copy / REBASE_FILE))
    with pytest.raises(ConfigError, match=f"{REBASE_FILE}: not a tokenizer's rebase image"):
        load_tokenizer(copy, HOST)
