"""SmolVLAModel on LeRobot 0.6.1's tiny smolvla checkpoint: the recorded action chunk, the state
dict's key set, one-line errors for bad weights, bf16, gradients, camera masking."""

from __future__ import annotations

import json

import pytest
import torch
import torch.nn.functional as F
from safetensors.torch import load_file

from dvla.learn.vla.smolvla import SmolVLAModel
from tests.references.conftest import load_reference, reference_dir

CAMERAS = ("observation.images.camera1", "observation.images.camera2")
ACTION_DIM = 7


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    """The tiny model's ops are microseconds long: a second intra-op thread only adds a wake-up
    per op, which costs a scheduler slice on a busy machine."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def checkpoint() -> tuple[dict, dict, dict]:
    """(weights without LeRobot's ``model.`` prefix, config.json, the backbone's config.json)."""
    path = reference_dir("smolvla")
    weights = {k.removeprefix("model."): v for k, v in load_file(str(path / "model.safetensors")).items()}
    config = json.loads((path / "config.json").read_text())
    vlm_config = json.loads((path / config["vlm_model_name"] / "config.json").read_text())
    return weights, config, vlm_config


@pytest.fixture(scope="module")
def model(checkpoint) -> SmolVLAModel:
    weights, config, vlm_config = checkpoint
    return SmolVLAModel.from_state_dict(weights, config, vlm_config=vlm_config)


@pytest.fixture(scope="module")
def batch() -> dict:
    """The recorded inputs as the model takes them, plus the noise and the expected chunk."""
    ref = load_reference("smolvla")
    state = ref["processed.observation.state"]
    return {
        "images": [ref[f"input.{cam}"].float() / 255.0 * 2.0 - 1.0 for cam in CAMERAS],
        "image_masks": [torch.ones(state.shape[0], dtype=torch.bool) for _ in CAMERAS],
        "tokens": ref["processed.observation.language.tokens"],
        "token_mask": ref["processed.observation.language.attention_mask"],
        "state": F.pad(state, (0, 32 - state.shape[1])),
        "noise": ref["noise"],
        "expected": ref["output.actions_normalized"],
    }


def _inputs(batch: dict) -> dict:
    return {k: batch[k] for k in ("images", "image_masks", "tokens", "token_mask", "state")}


@pytest.fixture(scope="module")
def chunk(model, batch) -> torch.Tensor:
    return model.sample_actions(**_inputs(batch), noise=batch["noise"])


def test_sizes_come_from_the_weights(model):
    assert (model.variant, model.chunk_size, model.max_action_dim, model.max_state_dim) == ("smolvla", 50, 32, 32)
    assert (model.prefix_width, model.expert_width) == (64, 48)


def test_action_chunk_matches_lerobot(chunk, batch):
    assert chunk.shape == (2, 50, 32) and chunk.dtype == torch.float32
    error = (chunk[:, :, :ACTION_DIM] - batch["expected"]).abs().max().item()
    assert error < 1e-4, f"max abs error {error} against output.actions_normalized"


def test_state_dict_is_the_checkpoints(model, checkpoint):
    weights = checkpoint[0]
    own = model.state_dict()
    assert sorted(own) == sorted(weights)
    assert all(torch.equal(own[k], weights[k]) for k in weights)


@pytest.mark.parametrize("edit, message", [
    (lambda w: w.__setitem__("vlm_with_expert.lm_expert.layers.3.mlp.up_proj.weight", torch.zeros(256, 47)),
     "vlm_with_expert.lm_expert.layers.3.mlp.up_proj.weight: expected shape [256, 48], found [256, 47]"),
    (lambda w: w.__setitem__("vlm_with_expert.lm_expert.layers.1.self_attn.k_proj.weight", torch.zeros(32, 48)),
     "vlm_with_expert.lm_expert.layers.1.self_attn.k_proj.weight: expected shape [32, 32], found [32, 48]"),
    (lambda w: w.pop("vlm_with_expert.vlm.model.text_model.layers.5.self_attn.v_proj.weight"),
     "missing key vlm_with_expert.vlm.model.text_model.layers.5.self_attn.v_proj.weight (expected shape [32, 64])"),
    (lambda w: w.pop("state_proj.weight"), "missing key state_proj.weight"),
    (lambda w: w.__setitem__("vlm_with_expert.lm_expert.lm_head.weight", torch.zeros(4, 48)),
     "unexpected key vlm_with_expert.lm_expert.lm_head.weight (shape [4, 48])"),
])
def test_bad_weights_raise_one_line_naming_the_key(checkpoint, edit, message):
    weights, config, vlm_config = checkpoint
    weights = dict(weights)
    edit(weights)
    with pytest.raises(ValueError) as err:
        SmolVLAModel.from_state_dict(weights, config, vlm_config=vlm_config)
    assert str(err.value) == message


def test_backbone_config_is_required(checkpoint):
    weights, config, _ = checkpoint
    with pytest.raises(ValueError, match="vlm_config"):
        SmolVLAModel.from_state_dict(weights, config)


def test_bfloat16_runs_close_to_float32(checkpoint, batch, chunk):
    weights, config, vlm_config = checkpoint
    model = SmolVLAModel.from_state_dict(weights, config, vlm_config=vlm_config, dtype=torch.bfloat16)
    assert all(p.dtype == torch.bfloat16 for p in model.parameters())
    low = model.sample_actions(**_inputs(batch), noise=batch["noise"])
    assert low.dtype == torch.float32 and torch.isfinite(low).all()
    # bf16 keeps ~3 significant digits through 16 layers and 10 Euler steps: a loose bound.
    assert (low - chunk).norm() / chunk.norm() < 0.03
    assert (low - chunk).abs().max() < 0.25


def test_velocity_is_differentiable_through_the_prefix(model, batch):
    params = dict(model.named_parameters())
    expert_q = params["vlm_with_expert.lm_expert.layers.0.self_attn.q_proj.weight"]
    vlm_q = params["vlm_with_expert.vlm.model.text_model.layers.0.self_attn.q_proj.weight"]
    prefix = model.prefix(**_inputs(batch))
    assert prefix.hidden.shape == (2, 2 * 64 + 12 + 1, model.prefix_width) and prefix.mask.shape == (2, 141)
    v, hidden = model.velocity(prefix, batch["noise"], torch.full((2,), 0.7))
    assert v.shape == (2, 50, 32) and hidden.shape == (2, 50, model.expert_width)
    grads = torch.autograd.grad(v.square().mean() + hidden.mean(), [expert_q, vlm_q])
    assert all(torch.isfinite(g).all() and g.abs().sum() > 0 for g in grads)


def test_masked_camera_is_invisible(model, batch):
    inputs = _inputs(batch)
    inputs["image_masks"] = [inputs["image_masks"][0], torch.zeros(2, dtype=torch.bool)]
    blank = model.sample_actions(**{**inputs, "images": [inputs["images"][0], -torch.ones_like(inputs["images"][1])]},
                                 noise=batch["noise"])
    other = model.sample_actions(**inputs, noise=batch["noise"])
    assert torch.allclose(blank, other, atol=1e-6)
