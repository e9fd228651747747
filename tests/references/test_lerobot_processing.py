"""LeRobot's processors reproduced on the reference checkpoints (DVLA_REFERENCE_CHECKPOINTS): from
the recorded raw inputs, the normalised state, the prompt token ids and their masks; the
unnormaliser on the recorded normalised actions; the images the model sees; an export round trip."""

from __future__ import annotations

import json

import pytest
import torch

from dvla.learn.vla.lerobot_format import (STATE_KEY, check_lerobot, content_hash, export_lerobot,
                                           read_state_dict)
from dvla.learn.vla.lerobot_processing import (TOKEN_MASK_KEY, TOKENS_KEY, Normalizer, Prompter, load_tokenizer,
                                               model_images, pad_to, preprocess)
from tests.references.conftest import load_reference, reference_dir

FAMILIES = ("pi0", "pi05", "smolvla")


@pytest.fixture(autouse=True)
def _offline(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")


def _recording(family: str) -> dict:
    return json.loads((reference_dir(family) / "reference" / "reference.json").read_text())


@pytest.mark.parametrize("family", FAMILIES)
def test_preprocessor(family: str) -> None:
    ref, meta = load_reference(family), _recording(family)
    ck = check_lerobot(reference_dir(family), family)
    assert ck.cameras == tuple(meta["camera_keys"]) and ck.image_size == tuple(meta["image_hw"])
    tokenizer = load_tokenizer(ck)
    batch = {cam: ref[f"input.{cam}"] for cam in ck.cameras}
    batch |= {STATE_KEY: ref["input.observation.state"], "task": meta["tasks"]}
    out = preprocess(ck, tokenizer, batch)
    torch.testing.assert_close(out[STATE_KEY], ref["processed.observation.state"], rtol=0, atol=1e-6)
    assert out[TOKENS_KEY].dtype == torch.int64 and out[TOKEN_MASK_KEY].dtype == torch.bool
    assert torch.equal(out[TOKENS_KEY], ref["processed.observation.language.tokens"])
    assert torch.equal(out[TOKEN_MASK_KEY], ref["processed.observation.language.attention_mask"])
    if "prompts" in meta:  # pi05: the state's bins are in the prompt
        assert Prompter(ck, tokenizer).prompts(meta["tasks"], out[STATE_KEY]) == meta["prompts"]


@pytest.mark.parametrize("family", FAMILIES)
def test_unnormaliser(family: str) -> None:
    ref = load_reference(family)
    ck = check_lerobot(reference_dir(family), family)
    norm = Normalizer(ck)
    assert not norm.identity and norm.missing_stats == ()
    normalized = ref["output.actions_normalized"]
    torch.testing.assert_close(norm.unnormalize_actions(normalized), ref["output.actions"], rtol=0, atol=1e-5)
    # the model's padded output: the padding is cut before unnormalising
    torch.testing.assert_close(norm.unnormalize_actions(pad_to(normalized, ck.max_action_dim)), ref["output.actions"],
                               rtol=0, atol=1e-5)
    torch.testing.assert_close(norm.normalize_actions(ref["output.actions"]), normalized, rtol=0, atol=1e-5)


@pytest.mark.parametrize("family", FAMILIES)
def test_model_images(family: str) -> None:
    ref = load_reference(family)
    ck = check_lerobot(reference_dir(family), family)
    images, masks = model_images({cam: ref[f"input.{cam}"] for cam in ck.cameras}, ck)
    assert len(images) == len(ck.cameras) and all(m.all() for m in masks)
    for cam, img in zip(ck.cameras, images):  # recorded at the model's size: no resize
        assert torch.equal(img, ref[f"input.{cam}"].float() / 255.0 * 2.0 - 1.0)


@pytest.mark.parametrize("family", FAMILIES)
def test_export_round_trip(family: str, tmp_path) -> None:
    ck = check_lerobot(reference_dir(family), family)
    state = read_state_dict(ck)
    out = export_lerobot(ck, state, tmp_path / "export")
    again = check_lerobot(out, family)
    back = read_state_dict(again)
    assert list(back) == list(state)
    for key, tensor in state.items():
        assert back[key].dtype == tensor.dtype and back[key].shape == tensor.shape
        assert back[key].numpy().tobytes() == tensor.numpy().tobytes(), key
    copied = [ck.path / "config.json", *ck.processor_files, *ck.tokenizer_dir.iterdir()]
    for file in copied:
        assert (out / file.relative_to(ck.path)).read_bytes() == file.read_bytes(), file
    assert again.tokenizer_dir == out / ck.tokenizer_dir.relative_to(ck.path)
    assert content_hash(again) == content_hash(ck)
