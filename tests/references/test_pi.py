"""``dvla.learn.vla.pi`` against LeRobot 0.6.1's recorded pi0 / pi05 action chunks (the tiny
reference checkpoints), plus its loading rules: the openpi layout without ``embed_tokens``,
one-line errors for bad keys, a full-size build on the meta device, bf16 and gradients."""

from __future__ import annotations

import functools
import json
import math

import pytest
import torch
from safetensors.torch import load_file

from dvla.learn.vla.pi import PiModel
from tests.references.conftest import load_reference, reference_dir

EMBED = "paligemma_with_expert.paligemma.model.language_model.embed_tokens.weight"
LM_HEAD = "paligemma_with_expert.paligemma.lm_head.weight"
ACTION_DIM = 7
POLICIES = ["pi0", "pi05"]


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    """The tiny models gain nothing from intra-op threads, and on a busy machine waiting for
    them costs several times the work itself."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@functools.lru_cache(maxsize=None)
def _checkpoint(name: str) -> tuple[dict, dict, dict]:
    """(state dict without ``model.``, config.json, vlm_config with SigLIP's head count, which
    the tensor shapes cannot give: architecture.json records it for the tiny checkpoints)."""
    path = reference_dir(name)
    state = {k.removeprefix("model."): v for k, v in load_file(str(path / "model.safetensors")).items()}
    config = json.loads((path / "config.json").read_text())
    arch = json.loads((path / "architecture.json").read_text())
    vision_heads = arch["vision_tower (siglip)"]["num_attention_heads"]
    return state, config, {"vision_config": {"num_attention_heads": vision_heads}}


def _model(name: str, state: dict | None = None, dtype: torch.dtype = torch.float32) -> PiModel:
    base, config, vlm_config = _checkpoint(name)
    return PiModel.from_state_dict(base if state is None else state, config, vlm_config=vlm_config, dtype=dtype)


@functools.lru_cache(maxsize=None)
def _inputs(name: str) -> dict:
    """The model inputs of the recorded call: images uint8 -> [-1, 1], every camera present."""
    ref = load_reference(name)
    cameras = json.loads((reference_dir(name) / "reference" / "reference.json").read_text())["camera_keys"]
    images = [ref[f"input.{c}"].float() / 255.0 * 2.0 - 1.0 for c in cameras]
    return dict(images=images, image_masks=[torch.ones(images[0].shape[0], dtype=torch.bool) for _ in cameras],
                tokens=ref["processed.observation.language.tokens"],
                token_mask=ref["processed.observation.language.attention_mask"],
                state=ref["processed.observation.state"])


def _actions(model: PiModel, name: str, **changes) -> torch.Tensor:
    ref = load_reference(name)
    return model.sample_actions(**{**_inputs(name), **changes}, noise=ref["noise"])


@pytest.mark.parametrize("name", POLICIES)
def test_reproduces_lerobot_action_chunk(name):
    model = _model(name)
    actions = _actions(model, name)
    assert actions.shape == (2, model.chunk_size, model.max_action_dim) and actions.dtype == torch.float32
    expected = load_reference(name)["output.actions_normalized"]
    assert (actions[:, :, :ACTION_DIM] - expected).abs().max().item() < 1e-4
    # the module tree is the checkpoint's: exporting is {"model." + k: v}
    state, _, _ = _checkpoint(name)
    assert {k: tuple(v.shape) for k, v in model.state_dict().items()} == {k: tuple(v.shape) for k, v in state.items()}
    assert (model.variant, model.chunk_size, model.max_action_dim, model.max_state_dim) == (name, 50, 32, 32)
    assert (model.prefix_width, model.expert_width, model.image_size) == (64, 32, 224)


def test_openpi_layout_ties_embeddings_to_lm_head():
    name = "pi0"
    state, _, _ = _checkpoint(name)
    hub = {k: v for k, v in state.items() if k != EMBED}
    hub[LM_HEAD] = state[EMBED]  # openpi stores the one tied matrix as lm_head
    model = _model(name, hub)
    expected = load_reference(name)["output.actions_normalized"]
    assert (_actions(model, name)[:, :, :ACTION_DIM] - expected).abs().max().item() < 1e-4
    assert sum(p.numel() for p in model.parameters()) == sum(v.numel() for v in hub.values())
    assert torch.equal(model.state_dict()[EMBED], state[EMBED])  # exported in LeRobot's layout again


def _error(name: str, state: dict) -> str:
    with pytest.raises(ValueError) as info:
        _model(name, state)
    message = str(info.value)
    assert "\n" not in message
    return message


def test_bad_state_dict_names_the_key():
    state, _, _ = _checkpoint("pi05")
    misshapen = {**state, "action_out_proj.weight": torch.zeros(32, 31)}
    assert _error("pi05", misshapen) == "key 'action_out_proj.weight': expected shape (32, 32), found (32, 31)"
    norm = "paligemma_with_expert.gemma_expert.model.layers.1.post_attention_layernorm.dense.bias"
    message = _error("pi05", {k: v for k, v in state.items() if k != norm})
    assert message == f"missing key '{norm}' (expected shape (96,))"
    assert "unexpected key 'state_proj.weight'" in _error("pi05", {**state, "state_proj.weight": torch.zeros(32, 32)})
    assert LM_HEAD in _error("pi05", {k: v for k, v in state.items() if k != LM_HEAD})
    prefixed = {"model." + k: v for k, v in state.items()}
    assert "model." in _error("pi05", prefixed)


@pytest.mark.parametrize("name", POLICIES)
def test_full_size_tree_on_meta(name):
    listing = json.loads((reference_dir(name) / "state_dict_keys_full_size.json").read_text())
    shapes = {k.removeprefix("model."): tuple(v["shape"]) for k, v in listing["tensors"].items()}
    _, config, _ = _checkpoint(name)
    model = PiModel.from_shapes(shapes, config, torch.bfloat16)
    count = sum(p.numel() for p in model.parameters())
    assert count == sum(math.prod(s) for s in shapes.values()) == listing["num_parameters"]
    assert all(p.is_meta for p in model.parameters())
    s = model.sizes
    assert (s.width, s.expert_width, s.depth, s.heads, s.kv_heads, s.head_dim) == (2048, 1024, 18, 8, 1, 256)
    assert (s.vision_width, s.vision_depth, s.vision_heads, s.image_size, s.vocab) == (1152, 27, 16, 224, 257152)
    q = model.state_dict()["paligemma_with_expert.paligemma.model.language_model.layers.0.self_attn.q_proj.weight"]
    assert q.dtype == torch.bfloat16
    hub = {k: v for k, v in shapes.items() if k != EMBED}
    tied = PiModel.from_shapes(hub, config)
    assert sum(p.numel() for p in tied.parameters()) == listing["num_parameters_without_embed_tokens"]


@pytest.mark.parametrize("name", POLICIES)
def test_bfloat16_weights(name):
    model = _model(name, dtype=torch.bfloat16)
    actions = _actions(model, name)
    assert actions.dtype == torch.float32 and torch.isfinite(actions).all()
    expected = load_reference(name)["output.actions_normalized"]
    assert (actions[:, :, :ACTION_DIM] - expected).abs().max().item() < 0.05


def _small_inputs(name: str) -> dict:
    """One camera and the first 48 words of the recorded inputs: a shorter prefix for the
    tests that need no reference (the model takes any number of cameras and words)."""
    inputs = _inputs(name)
    return dict(images=inputs["images"][:1], image_masks=inputs["image_masks"][:1], tokens=inputs["tokens"][:, :48],
                token_mask=inputs["token_mask"][:, :48], state=inputs["state"])


def test_masked_camera_is_invisible():
    model = _model("pi0")
    inputs = _inputs("pi0")
    noise, t = load_reference("pi0")["noise"], torch.tensor([0.5, 0.5])
    masks = [inputs["image_masks"][0], torch.tensor([False, True])]
    other = torch.rand(inputs["images"][1].shape, generator=torch.Generator().manual_seed(0)) * 2 - 1
    with torch.no_grad():
        velocities = [model.velocity(model.prefix(**{**_small_inputs("pi0"), "images": [inputs["images"][0], image],
                                                     "image_masks": masks}), noise, t)[0]
                      for image in (inputs["images"][1], other)]
    assert torch.allclose(velocities[0][0], velocities[1][0], atol=1e-6)  # row 0 does not see the camera
    assert not torch.allclose(velocities[0][1], velocities[1][1], atol=1e-3)  # row 1 does


@pytest.mark.parametrize("name", POLICIES)
def test_velocity_is_differentiable_and_prefix_rows_select(name):
    model = _model(name)
    noise = load_reference(name)["noise"]
    prefix = model.prefix(**_small_inputs(name))
    assert prefix.hidden.shape == (2, 256 + 48, model.prefix_width) and prefix.mask.shape == (2, 256 + 48)
    t = torch.tensor([0.3, 0.9])
    v, hidden = model.velocity(prefix, noise, t)
    assert v.shape == noise.shape and hidden.shape == (2, model.chunk_size, model.expert_width)
    (v.square().mean() + hidden.mean()).backward()
    for tower in (model.language_model, model.expert):
        grad = tower.layers[0].self_attn.q_proj.weight.grad
        assert grad is not None and grad.abs().sum() > 0
    # K chains per observation: select repeats the rows, each row's velocity is unchanged
    with torch.no_grad():
        twice = prefix.select(torch.arange(2).repeat_interleave(2))
        v2, _ = model.velocity(twice, noise.repeat_interleave(2, 0), t.repeat_interleave(2))
    assert torch.allclose(v2[::2], v.detach(), atol=1e-5) and torch.allclose(v2[1::2], v.detach(), atol=1e-5)
