"""``dvla.learn.vla.openvla`` against the recorded upstream passes of the tiny OpenVLA and
OpenVLA-OFT checkpoints (towers, projector, hidden states, logits, greedy action tokens, OFT action
chunks; float32 from the bf16 weights), plus its loading rules: the checkpoint's keys exactly,
one-line errors, the real-size tree on the meta device, padded batches, gradients and bf16.
The model's inputs are the recorded processor outputs, the weights are read from the shards."""

from __future__ import annotations

import functools
import json
import math

import pytest
import torch
from safetensors.torch import load_file

from dvla.learn.vla.openvla import OFTHeads, OpenVLAModel
from tests.references.conftest import oft_reference_root

EMPTY_TOKEN = 29871  # predict_action appends it to the prompt


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    """The tiny models gain nothing from intra-op threads; on a busy machine waiting for them
    costs several times the work itself."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _error(a: torch.Tensor, b: torch.Tensor) -> float:
    return (a.float() - b.float()).abs().max().item()


@functools.lru_cache(maxsize=None)
def _checkpoint(name: str) -> tuple[dict, dict]:
    """(every shard's tensors as stored, config.json) of ``openvla-tiny`` / ``openvla-oft-tiny``."""
    path = oft_reference_root() / name
    index = json.loads((path / "model.safetensors.index.json").read_text())
    state = {}
    for shard in sorted(set(index["weight_map"].values())):
        state.update(load_file(str(path / shard)))
    return state, json.loads((path / "config.json").read_text())


@functools.lru_cache(maxsize=None)
def _model(name: str, dtype: torch.dtype = torch.float32) -> OpenVLAModel:
    state, config = _checkpoint(name)
    return OpenVLAModel.from_state_dict(state, config, dtype=dtype)


@functools.lru_cache(maxsize=None)
def _head_files() -> tuple[dict, dict]:
    path = oft_reference_root() / "openvla-oft-tiny"
    strip = lambda f: {k.removeprefix("module."): v for k, v in  # noqa: E731
                       torch.load(path / f"{f}--150000_checkpoint.pt", weights_only=True).items()}
    return strip("action_head"), strip("proprio_projector")


def _heads(dtype: torch.dtype = torch.float32) -> OFTHeads:
    return OFTHeads.from_state_dicts(*_head_files(), dtype=dtype)


@functools.lru_cache(maxsize=None)
def _reference(name: str) -> dict:
    return load_file(str(oft_reference_root() / "reference" / f"{name}_reference.safetensors"))


def _openvla_inputs() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(pixel_values, predict_action's input ids (29871 appended), their all-ones mask), batch 1."""
    ref = _reference("openvla")
    ids = ref["predict_action_input_ids"][None]
    return ref["pixel_values"][None], ids, torch.ones_like(ids, dtype=torch.bool)


def _oft_inputs() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    ref = _reference("oft")
    ids = torch.cat([ref["input_ids"], torch.tensor([EMPTY_TOKEN])])[None]
    return ref["pixel_values"][None], ids, torch.ones_like(ids, dtype=torch.bool), ref["proprio_normalized"][None]


def test_openvla_reproduces_the_recorded_pass():
    model, ref = _model("openvla-tiny"), _reference("openvla")
    pixels, ids, mask = _openvla_inputs()
    actions = ref["generated_action_token_ids"][None]
    with torch.no_grad():
        towers = model.vision_backbone
        assert _error(towers.featurizer(pixels[:, :3])[0], ref["dinov2_patches"]) < 1e-5
        assert _error(towers.fused_featurizer(pixels[:, 3:])[0], ref["siglip_patches"]) < 1e-5
        assert _error(model.patch_embeddings(pixels)[0], ref["projector_out"]) < 1e-5
        full = torch.cat([ids, actions], dim=1)
        hidden = model.hidden(pixels, full, torch.ones_like(full))
        assert hidden.shape == (1, 300, 32) and _error(hidden[0], ref["teacher_forced_last_hidden_state"]) < 1e-5
        logits = model.logits(pixels, full, torch.ones_like(full))
        assert _error(logits[0, 292:299], ref["teacher_forced_logits"]) < 1e-5  # position q predicts token q + 1
        action_logits = model.action_logits(pixels, ids, mask, actions)
        assert _error(action_logits[0], ref["teacher_forced_logits"]) < 1e-5
        assert _error(action_logits[0], ref["generate_logits"]) < 1e-5
    assert torch.equal(model.generate_action_tokens(pixels, ids, mask), actions)
    state, _ = _checkpoint("openvla-tiny")  # export writes state_dict() back as it came
    assert {k: tuple(v.shape) for k, v in model.state_dict().items()} == {k: tuple(v.shape) for k, v in state.items()}
    assert torch.equal(model.state_dict()["vision_backbone.fused_featurizer.attn_pool.latent"],
                       state["vision_backbone.fused_featurizer.attn_pool.latent"].float())
    assert (model.vocab_size, model.width, model.n_action_bins) == (32064, 32, 256)
    assert model.action_token_ids == range(31744, 32000)


def test_oft_reproduces_the_recorded_chunk():
    model, heads, ref = _model("openvla-oft-tiny"), _heads(), _reference("oft")
    pixels, ids, mask, proprio = _oft_inputs()
    with torch.no_grad():
        towers = model.vision_backbone
        for camera in range(2):
            image = pixels[:, 6 * camera: 6 * camera + 6]
            assert _error(towers.featurizer(image[:, :3])[0], ref["dinov2_patches"][camera]) < 1e-5
            assert _error(towers.fused_featurizer(image[:, 3:])[0], ref["siglip_patches"][camera]) < 1e-5
        assert _error(model.patch_embeddings(pixels)[0], ref["projector_out"]) < 1e-5
        assert _error(heads.proprio_token(proprio)[0, 0], ref["proprio_projector_out"]) < 1e-5
        states = heads.action_states(model, pixels, ids, mask, proprio)
        assert states.shape == (1, 56, 32) and _error(states[0], ref["actions_hidden_states"]) < 1e-5
        assert _error(states[0].reshape(8, 224), ref["action_head_input"]) < 1e-5
        actions = heads.predict_chunk(model, pixels, ids, mask, proprio)
        logits = model.lm_logits(states)[0]
    assert actions.shape == (1, 8, 7) and actions.dtype == torch.float32
    assert _error(actions[0], ref["normalized_actions"]) < 1e-4
    assert _error(logits[:, 31744:], ref["action_positions_logits_vocab_31744_32064"]) < 1e-5
    assert torch.equal(logits.argmax(-1), ref["action_positions_argmax_full_vocab"])
    assert (heads.chunk_size, heads.action_dim, heads.proprio_dim, heads.llm_width) == (8, 7, 8, 32)
    for module, file in zip((heads.action_head, heads.proprio_projector), _head_files()):
        assert {k: tuple(v.shape) for k, v in module.state_dict().items()} == {k: tuple(v.shape)
                                                                              for k, v in file.items()}


def _padded_pair(ids: torch.Tensor, pixels: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """A batch of the recorded prompt and a shorter one (8 words dropped) right padded with <PAD>,
    the second image mirrored; and the shorter prompt alone."""
    short = torch.cat([ids[:, :10], ids[:, 18:]], dim=1)
    batch = torch.full((2, ids.shape[1]), 32000)
    batch[0], batch[1, :short.shape[1]] = ids[0], short[0]
    return batch, batch != 32000, torch.cat([pixels, pixels.flip(-1)]), short


def test_padded_rows_match_the_same_rows_alone():
    model = _model("openvla-tiny")
    pixels, ids, _ = _openvla_inputs()
    batch, mask, pixels2, short = _padded_pair(ids, pixels)
    tokens = model.generate_action_tokens(pixels2, batch, mask)
    alone = model.generate_action_tokens(pixels2[1:], short, torch.ones_like(short))
    assert torch.equal(tokens[0], _reference("openvla")["generated_action_token_ids"])
    assert torch.equal(tokens[1], alone[0])
    with torch.no_grad():
        logits = model.action_logits(pixels2, batch, mask, tokens)
        single = model.action_logits(pixels2[1:], short, torch.ones_like(short), alone)
    assert torch.equal(logits.argmax(-1), tokens) and _error(logits[1], single[0]) < 1e-5
    model, heads = _model("openvla-oft-tiny"), _heads()
    pixels, ids, _, proprio = _oft_inputs()
    batch, mask, _, short = _padded_pair(ids, pixels)
    with torch.no_grad():
        states = heads.action_states(model, pixels.expand(2, -1, -1, -1), batch, mask, proprio.expand(2, -1))
        single = heads.action_states(model, pixels, short, torch.ones_like(short), proprio)
    assert _error(states[0], _reference("oft")["actions_hidden_states"]) < 1e-5
    assert _error(states[1], single[0]) < 1e-5
    with pytest.raises(ValueError, match="right padded"):
        model.hidden(pixels, ids, torch.cat([torch.zeros_like(ids[:, :1]), torch.ones_like(ids[:, 1:])], 1))


def _load_error(state: dict, config: dict | None = None) -> str:
    with pytest.raises(ValueError) as info:
        OpenVLAModel.from_state_dict(state, config or _checkpoint("openvla-tiny")[1])
    assert "\n" not in str(info.value)
    return str(info.value)


def test_bad_checkpoint_names_the_key():
    state, config = _checkpoint("openvla-tiny")
    norm = "vision_backbone.featurizer.norm.weight"  # stored, never run: still required for export
    assert _load_error({k: v for k, v in state.items() if k != norm}) == f"missing key '{norm}' (expected shape (128,))"
    extra = "language_model.model.layers.0.self_attn.q_proj.bias"
    assert _load_error({**state, extra: torch.zeros(32)}) == f"unexpected key '{extra}' (shape (32,))"
    fc3 = "projector.fc3.weight"
    assert _load_error({**state, fc3: torch.zeros(32, 31)}) == f"key '{fc3}': expected shape (32, 32), found (32, 31)"
    wrong = {**config, "text_config": {**config["text_config"], "num_hidden_layers": 3}}
    assert _load_error(state, wrong) == "text_config.num_hidden_layers is 3 but the checkpoint's tensors give 2"
    assert "language_model.lm_head.weight" in _load_error({"model." + k: v for k, v in state.items()})
    action_head, proprio = _head_files()
    with pytest.raises(ValueError, match=r"^action head: missing key 'model.layer_norm1.weight'.*'module.' prefix"):
        OFTHeads.from_state_dicts({"module." + k: v for k, v in action_head.items()}, proprio)
    with pytest.raises(ValueError, match=r"^proprio projector: key 'fc2.bias': expected shape \(32,\), found \(8,\)$"):
        OFTHeads.from_state_dicts(action_head, {**proprio, "fc2.bias": torch.zeros(8)})


def test_real_size_tree_on_meta():
    listing = json.loads((oft_reference_root() / "reference" / "openvla-7b.meta_keys.json").read_text())
    shapes = {entry["key"]: tuple(entry["shape"]) for entry in listing["keys"]}
    model = OpenVLAModel.from_shapes(shapes, listing["config"])  # text_config holds only the vocab here
    count = sum(p.numel() for p in model.parameters())
    assert count == sum(math.prod(s) for s in shapes.values()) == listing["num_parameters"] == 7_541_237_184
    assert all(p.is_meta and p.dtype == torch.bfloat16 for p in model.parameters())
    s = model.sizes
    assert (s.width, s.mlp, s.depth, s.heads, s.kv_heads, s.rms_eps, s.vocab) == (4096, 11008, 32, 32, 32, 1e-6, 32064)
    assert (s.dinov2.width, s.dinov2.depth, s.dinov2.heads, s.dinov2.registers) == (1024, 24, 16, 4)
    assert (s.siglip.width, s.siglip.depth, s.siglip.heads, s.siglip.mlp, s.projector_hidden) == (1152, 27, 16, 4304, 8704)


def test_logits_and_chunks_are_differentiable():
    model = _model("openvla-tiny")
    pixels, ids, mask = _openvla_inputs()
    actions = _reference("openvla")["generated_action_token_ids"][None]
    log_probs = model.action_logits(pixels, ids, mask, actions).log_softmax(-1).gather(-1, actions[..., None])
    log_probs.sum().backward()
    for p in (model.decoder.layers[0].self_attn.q_proj.weight, model.projector.fc1.weight,
              model.vision_backbone.featurizer.blocks[0].attn.qkv.weight):
        assert p.grad is not None and p.grad.abs().sum() > 0
    model.zero_grad(set_to_none=True)
    model, heads = _model("openvla-oft-tiny"), _heads()
    pixels, ids, mask, proprio = _oft_inputs()
    heads.predict_chunk(model, pixels, ids, mask, proprio).square().sum().backward()
    for p in (model.decoder.layers[0].self_attn.v_proj.weight, heads.proprio_projector.fc1.weight,
              heads.action_head.model.fc1.weight):
        assert p.grad is not None and p.grad.abs().sum() > 0
    model.zero_grad(set_to_none=True)
    heads.zero_grad(set_to_none=True)


def test_bfloat16_weights_run():
    model = _model("openvla-tiny", torch.bfloat16)
    assert model.decoder.layers[0].self_attn.q_proj.weight.dtype == torch.bfloat16
    pixels, ids, mask = _openvla_inputs()
    ref = _reference("openvla")
    with torch.no_grad():
        logits = model.action_logits(pixels, ids, mask, ref["generated_action_token_ids"][None])
    assert logits.dtype == torch.float32 and torch.isfinite(logits).all()
    assert _error(logits[0], ref["teacher_forced_logits"]) < 0.5
    assert model.generate_action_tokens(pixels, ids, mask).shape == (1, 7)
    model, heads = _model("openvla-oft-tiny", torch.bfloat16), _heads(torch.bfloat16)
    pixels, ids, mask, proprio = _oft_inputs()
    with torch.no_grad():
        actions = heads.predict_chunk(model, pixels, ids, mask, proprio)
    assert actions.dtype == torch.float32 and torch.isfinite(actions).all()
    assert _error(actions[0], _reference("oft")["normalized_actions"]) < 0.1
