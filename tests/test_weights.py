import hashlib

import pytest

from vqtouch.core import MissingWeightsError, WeightsSpec, resolve_weights

SPEC = WeightsSpec(description="metric 'fid'", filenames=("inception.pth",), env_var="VQTOUCH_TEST_WEIGHTS",
                   config_hint="--set evaluate.fid_weights=PATH", source_url="https://example.org/inception.pth")


@pytest.fixture(autouse=True)
def clean_env(monkeypatch):
    monkeypatch.delenv("VQTOUCH_TEST_WEIGHTS", raising=False)
    monkeypatch.delenv("VQTOUCH_WEIGHTS_DIR", raising=False)


def test_missing_everywhere_explains_all_three_ways():
    with pytest.raises(MissingWeightsError) as info:
        resolve_weights(SPEC)
    message = str(info.value)
    for needle in ("inception.pth", "https://example.org/inception.pth", "--set evaluate.fid_weights=PATH",
                   "VQTOUCH_TEST_WEIGHTS=PATH", "VQTOUCH_WEIGHTS_DIR", "never downloads"):
        assert needle in message


def test_resolution_order_explicit_then_env_then_dir(tmp_path, monkeypatch):
    explicit, from_env, folder = tmp_path / "a.pth", tmp_path / "b.pth", tmp_path / "dir"
    folder.mkdir()
    for path in (explicit, from_env, folder / "inception.pth"):
        path.write_bytes(b"w")
    monkeypatch.setenv("VQTOUCH_WEIGHTS_DIR", str(folder))
    assert resolve_weights(SPEC) == folder / "inception.pth"
    monkeypatch.setenv("VQTOUCH_TEST_WEIGHTS", str(from_env))
    assert resolve_weights(SPEC) == from_env
    assert resolve_weights(SPEC, explicit) == explicit


def test_explicit_path_that_does_not_exist(tmp_path):
    with pytest.raises(MissingWeightsError, match="does not exist"):
        resolve_weights(SPEC, tmp_path / "nope.pth")


def test_sha256_prefix_is_checked(tmp_path):
    path = tmp_path / "inception.pth"
    path.write_bytes(b"real weights")
    good = hashlib.sha256(b"real weights").hexdigest()[:8]
    checked = WeightsSpec(**{**SPEC.__dict__, "sha256_prefix": good})
    assert resolve_weights(checked, path) == path
    wrong = WeightsSpec(**{**SPEC.__dict__, "sha256_prefix": "00000000"})
    with pytest.raises(MissingWeightsError, match="corrupt or a different model"):
        resolve_weights(wrong, path)
