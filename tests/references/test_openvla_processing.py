"""OpenVLA's processor and predict_action's decoding reproduced on the reference checkpoints
($DVLA_REFERENCE_CHECKPOINTS_OFT): the prompt's token ids, the 6- and 12-channel pixel values, OFT's
normalised proprio, the actions from the recorded tokens / normalised actions, the OFT pickles read
weights-only, and an export of both directories that writes the shards upstream wrote."""

from __future__ import annotations

import json

import pytest
import torch
from safetensors.torch import load_file

from dvla.learn.vla.openvla_format import (check_openvla, content_hash, export_openvla, read_oft_components,
                                           read_state_dict)
from dvla.learn.vla.openvla_processing import (EMPTY_TOKEN_ID, encode_prompts, load_tokenizer, normalize_proprio,
                                               pixel_values, tokens_to_normalized, unnormalize_actions)
from tests.references.conftest import oft_reference_root

CHECKPOINTS = {"openvla": "openvla-tiny", "openvla-oft": "openvla-oft-tiny"}
RECORDINGS = {"openvla": "openvla_reference", "openvla-oft": "oft_reference"}


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    """Nothing here gains from intra-op threads on a busy machine."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _load(family: str):
    root = oft_reference_root()
    meta = json.loads((root / "reference" / f"{RECORDINGS[family]}.json").read_text())
    return check_openvla(root / CHECKPOINTS[family], family), load_file(
        str(root / "reference" / f"{RECORDINGS[family]}.safetensors")), meta


@pytest.mark.parametrize("family", list(CHECKPOINTS))
def test_prompt_token_ids(family: str) -> None:
    ck, ref, meta = _load(family)
    ids, mask = encode_prompts(load_tokenizer(ck), meta["instruction"])
    assert ids.dtype == torch.int64 and mask.all()
    assert torch.equal(ids[0, :-1], ref["input_ids"]) and ids[0, -1] == EMPTY_TOKEN_ID  # exact
    if family == "openvla":
        assert torch.equal(ids[0], ref["predict_action_input_ids"])
    else:  # OFT: the same ids, then the 56 placeholders and the stop token
        assert torch.equal(ids[0], ref["llm_input_ids"][: ids.shape[1]])


@pytest.mark.parametrize("family", list(CHECKPOINTS))
def test_pixel_values(family: str) -> None:
    ck, ref, _ = _load(family)
    images = [ref["image_primary_uint8"]] + ([ref["image_wrist_uint8"]] if family == "openvla-oft" else [])
    got = pixel_values(images if len(images) > 1 else images[0].numpy(), ck)
    assert got.shape == (1, 6 * len(images), 224, 224) and got.dtype == torch.float32
    error = (got[0] - ref["pixel_values"]).abs().max().item()
    assert error <= 1e-6, error  # measured: 0 (the same float32 operations as torchvision's)
    batch = pixel_values([img[None].expand(3, -1, -1, -1) for img in images] if len(images) > 1
                         else images[0][None].expand(3, -1, -1, -1), ck)
    assert torch.equal(batch, got.expand(3, -1, -1, -1))


def test_openvla_actions_from_tokens() -> None:
    ck, ref, meta = _load("openvla")
    assert ck.action_token_ids == range(31744, 32000) and ck.dataset == meta["unnorm_key"]
    tokens = ref["generated_action_token_ids"]
    assert all(t in ck.action_token_ids for t in tokens.tolist())
    normalized = tokens_to_normalized(tokens, ck)
    assert (normalized - ref["normalized_actions"]).abs().max().item() <= 1e-12  # measured: 0
    actions = unnormalize_actions(normalized, ck)
    assert actions.dtype == torch.float64
    assert (actions - ref["actions"]).abs().max().item() <= 1e-12  # measured: 0


def test_oft_proprio_and_actions() -> None:
    ck, ref, meta = _load("openvla-oft")
    assert (ck.chunk_size, ck.action_dim, ck.num_images, ck.proprio_dim) == (8, 7, 2, 8)
    assert ck.stats_file.name == "dataset_statistics.json" and ck.dataset == meta["unnorm_key"]
    proprio = normalize_proprio(ref["proprio_raw"], ck)
    assert (proprio - ref["proprio_normalized"]).abs().max().item() <= 1e-12  # measured: 0
    actions = unnormalize_actions(ref["normalized_actions"], ck)  # the head's float32 output
    assert actions.shape == (8, 7) and (actions - ref["actions"]).abs().max().item() <= 1e-12  # measured: 0
    # config.json's norm_stats (the base model's) would give other actions: the right file is read
    assert ck.action_stats["q99"] != tuple(ck.config["norm_stats"][ck.dataset]["action"]["q99"])


def test_oft_components_weights_only() -> None:
    ck, _, meta = _load("openvla-oft")
    heads = read_oft_components(ck)
    for name, file in ck.components.items():
        recorded = meta["component_files"][file.name]["keys"]
        assert [(k, tuple(v.shape), str(v.dtype)) for k, v in heads[name].items()] == [
            (r["key"][len("module."):], tuple(r["shape"]), f"torch.{r['dtype']}") for r in recorded]


@pytest.mark.parametrize("family", list(CHECKPOINTS))
def test_export_writes_what_upstream_wrote(family: str, tmp_path) -> None:
    ck, _, _ = _load(family)
    trained = {k: v.float() for k, v in read_state_dict(ck).items()}
    heads = {n: {k: v.float() for k, v in s.items()} for n, s in read_oft_components(ck).items()} or None
    out = export_openvla(ck, trained, tmp_path / "export", heads=heads)
    for file in sorted(ck.path.iterdir()):  # shards, index, config, processor, tokenizer, statistics
        if file.suffix != ".pt":
            assert (out / file.name).read_bytes() == file.read_bytes(), file.name
    again = check_openvla(out, family)
    assert content_hash(again) == content_hash(ck)
    for name, state in read_oft_components(again).items():
        original = torch.load(ck.components[name], weights_only=True)
        written = torch.load(again.components[name], weights_only=True)
        assert list(written) == list(original)
        assert all(torch.equal(written[k], original[k]) and written[k].dtype == original[k].dtype for k in original)
