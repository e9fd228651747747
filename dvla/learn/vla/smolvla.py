"""SmolVLA, LeRobot 0.6.1's ``smolvla`` policy model, built natively from LeRobot's state dict.

:class:`SmolVLAModel` holds the same module tree as LeRobot's ``VLAFlowMatching`` (keys without
LeRobot's ``model.`` prefix), so ``{"model." + k: v for k, v in model.state_dict().items()}`` is a
LeRobot checkpoint again. Sizes come from tensor shapes; head counts (which shapes cannot tell)
from the SmolVLM backbone config (``vlm_model_name``'s ``config.json``). The action expert keeps
the backbone's head counts and head size at its own width, as LeRobot derives it.

**Prefix** (images, language, state; one pass, cached as :class:`Prefix`). Each camera is one
image at the model resolution through SmolVLM's vision transformer and pixel-shuffle connector
(transformers' classes): no tiling, no global image and no image-boundary tokens, as SmolVLA
feeds it (``add_image_special_tokens`` true is refused: the boundary token ids live in the
tokenizer, not in the weights). Image and language embeddings are both scaled by
sqrt(text width); the state is one token (``state_proj``). Images and language attend to each
other bidirectionally; the state token sees them all, they do not see it. Positions count real
tokens only. The text layers kept are those in the state dict (LeRobot keeps
``num_vlm_layers`` of the backbone's).

**Velocity** (the action expert, once per Euler step). Action tokens are
``action_time_mlp_out(silu(action_time_mlp_in([action_in_proj(x_t), sinusoid(t)])))`` and attend
causally among themselves. Self-attention expert layers (even ones with LeRobot's defaults) attend
over [real prefix; actions] with the VLM layer's cached keys/values; cross-attention layers
project the VLM layer's cached keys/values (after RoPE) through their own ``k_proj``/``v_proj``
and number the action positions from 0. RoPE uses wavelength 10000 whatever the backbone's
``rope_theta``; attention scores and softmax are float32, as LeRobot computes them.

Time runs as in pi0: t = 1 is noise, t = 0 the action; :meth:`SmolVLAModel.sample_actions` is
LeRobot's Euler loop (dt = -1/num_steps, x <- x + dt v).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = ["Prefix", "SmolVLAModel", "ROPE_MAX_WAVELENGTH"]

ROPE_MAX_WAVELENGTH = 10_000.0
"""SmolVLA's RoPE wavelength (LeRobot's own rotation, not the backbone's ``rope_theta``)."""
_VLM = "vlm_with_expert.vlm."
_TEXT = _VLM + "model.text_model."
_VISION = _VLM + "model.vision_model."
_EXPERT = "vlm_with_expert.lm_expert."
# SmolVLAConfig defaults for the fields read here (a config.json without them means these).
_DEFAULTS = {"chunk_size": 50, "min_period": 4e-3, "max_period": 4.0, "attention_mode": "cross_attn",
             "self_attn_every_n_layers": 2, "prefix_length": -1, "add_image_special_tokens": False}


@dataclass
class Prefix:
    """What :meth:`SmolVLAModel.velocity` reads of the observation: computed once per chunk."""

    hidden: Tensor
    """[B, L, prefix_width] float32: the VLM's final normed hidden states (images, language, state)."""
    mask: Tensor
    """[B, L] bool: real prefix tokens (masked cameras and language padding are False)."""
    keys: tuple[Tensor, ...]
    """Per kept text layer, [B, L, kv_heads, head_dim]: the VLM's keys after RoPE."""
    values: tuple[Tensor, ...]
    """Per kept text layer, [B, L, kv_heads, head_dim]: the VLM's values."""


def _shape(shapes: Mapping[str, Sequence[int]], key: str) -> tuple[int, ...]:
    if key not in shapes:
        raise ValueError(f"missing key {key}")
    return tuple(int(n) for n in shapes[key])


def _count(shapes: Mapping[str, Any], prefix: str) -> int:
    """Layers under ``prefix`` (highest index + 1: a gap shows up as missing keys later)."""
    pattern = re.compile(re.escape(prefix) + r"(\d+)\.")
    found = [int(m.group(1)) for key in shapes if (m := pattern.match(key))]
    if not found:
        raise ValueError(f"missing key {prefix}0.*: no layers")
    return max(found) + 1


def _check_shapes(expected: Mapping[str, tuple[int, ...]], found: Mapping[str, Sequence[int]]) -> None:
    for key, shape in expected.items():
        if key not in found:
            raise ValueError(f"missing key {key} (expected shape {list(shape)})")
        if tuple(found[key]) != shape:
            raise ValueError(f"{key}: expected shape {list(shape)}, found {list(found[key])}")
    for key in found:
        if key not in expected:
            raise ValueError(f"unexpected key {key} (shape {list(found[key])})")


def _rotation(positions: Tensor, head_dim: int) -> tuple[Tensor, Tensor]:
    """RoPE's (cos, sin) [B, S, 1, head_dim / 2] in float32 for integer positions [B, S]."""
    exponents = (2.0 / head_dim) * torch.arange(head_dim // 2, dtype=torch.float32, device=positions.device)
    angles = (positions[..., None].float() / ROPE_MAX_WAVELENGTH ** exponents)[..., None, :]
    return angles.cos(), angles.sin()


def _rope(x: Tensor, rotation: tuple[Tensor, Tensor]) -> Tensor:
    """Rotate x [B, S, H, D] (first half paired with second half) in float32."""
    cos, sin = rotation
    x1, x2 = x.float().split(x.shape[-1] // 2, dim=-1)
    return torch.cat([x1 * cos - x2 * sin, x2 * cos + x1 * sin], dim=-1).to(x.dtype)


def _attend(q: Tensor, k: Tensor, v: Tensor, mask: Tensor) -> Tensor:
    """Grouped-query attention: q [B, S, H, D], k/v [B, T, KVH, D], mask [B, S, T] bool -> [B, S, H*D].
    A masked score is float32's lowest value rather than -inf, so a query with no visible key (a
    padding position) averages instead of producing NaN."""
    b, s, heads, dim = q.shape
    groups = heads // k.shape[2]
    k, v = k.repeat_interleave(groups, dim=2), v.repeat_interleave(groups, dim=2)
    scores = torch.matmul(q.float().transpose(1, 2), k.float().permute(0, 2, 3, 1)) * dim**-0.5
    scores = torch.where(mask[:, None], scores, torch.finfo(torch.float32).min)
    probs = scores.softmax(dim=-1).to(v.dtype)
    return torch.matmul(probs, v.transpose(1, 2)).transpose(1, 2).reshape(b, s, heads * dim)


def _residual_mlp(layer: nn.Module, x: Tensor, attended: Tensor) -> Tensor:
    """The rest of a pre-norm Llama layer after attention."""
    h = layer.self_attn.o_proj(attended.to(x.dtype)) + x
    return layer.mlp(layer.post_attention_layernorm(h)) + h


def _time_embedding(t: Tensor, width: int, min_period: float, max_period: float) -> Tensor:
    """Sine-cosine embedding [B, width] of t [B], float64 where the device has it (as LeRobot)."""
    dtype = torch.float32 if t.device.type == "mps" else torch.float64
    fraction = torch.linspace(0.0, 1.0, width // 2, dtype=dtype, device=t.device)
    period = min_period * (max_period / min_period) ** fraction
    angles = (1.0 / period * 2 * math.pi)[None, :] * t[:, None]
    return torch.cat([angles.sin(), angles.cos()], dim=1)


def _is_cross(config: Mapping[str, Any], layer: int) -> bool:
    """Whether an expert layer attends across to the VLM's keys/values (LeRobot's rule: in a
    ``cross`` attention mode, every layer but the multiples of ``self_attn_every_n_layers``)."""
    every = int(config["self_attn_every_n_layers"])
    return "cross" in str(config["attention_mode"]) and not (every > 0 and layer % every == 0)


def _vision(shapes: Mapping[str, Sequence[int]], backbone: Any, text: Any) -> tuple[nn.Module, nn.Module]:
    """SmolVLM's vision transformer and pixel-shuffle connector (transformers' classes), sized by
    the weights; the backbone config gives heads, norm epsilon and activation."""
    from transformers import SmolVLMConfig, SmolVLMVisionConfig
    from transformers.models.smolvlm.modeling_smolvlm import SmolVLMConnector, SmolVLMVisionTransformer

    patch = _shape(shapes, _VISION + "embeddings.patch_embedding.weight")  # [width, channels, size, size]
    positions = _shape(shapes, _VISION + "embeddings.position_embedding.weight")[0]
    projection = _VLM + "model.connector.modality_projection.proj.weight"
    width, merged = patch[0], _shape(shapes, projection)[1]
    scale = math.isqrt(merged // width)
    if scale * scale * width != merged:
        raise ValueError(f"{projection}: {merged} inputs are not {width} x a square pixel-shuffle factor")
    config = SmolVLMVisionConfig(**{
        **backbone.to_dict(), "hidden_size": width, "num_channels": patch[1], "patch_size": patch[2],
        "image_size": math.isqrt(positions) * patch[2],
        "intermediate_size": _shape(shapes, _VISION + "encoder.layers.0.mlp.fc1.weight")[0],
        "num_hidden_layers": _count(shapes, _VISION + "encoder.layers.")})
    config._attn_implementation = "sdpa"
    merged_config = SmolVLMConfig(text_config=text.to_dict(), vision_config=config.to_dict(), scale_factor=scale)
    return SmolVLMVisionTransformer(config), SmolVLMConnector(merged_config)


class SmolVLAModel(nn.Module):
    """SmolVLA's VLM with its action expert; see the module docstring for the numerics."""

    variant = "smolvla"

    def __init__(self, shapes: Mapping[str, Sequence[int]], config: Mapping[str, Any],
                 vlm_config: Mapping[str, Any]) -> None:
        from transformers import LlamaConfig, SmolVLMConfig
        from transformers.models.llama.modeling_llama import LlamaDecoderLayer, LlamaRMSNorm

        super().__init__()
        cfg = {**_DEFAULTS, **config}
        if cfg["add_image_special_tokens"]:
            raise ValueError("config add_image_special_tokens=true is not supported (its token ids are not in the "
                             "weights); SmolVLA's default is false")
        backbone = SmolVLMConfig(**vlm_config)
        text_cfg = backbone.text_config
        self.chunk_size = int(cfg["chunk_size"])
        self.min_period, self.max_period = float(cfg["min_period"]), float(cfg["max_period"])
        self.prefix_length = int(cfg["prefix_length"])
        self.max_state_dim = _shape(shapes, "state_proj.weight")[1]
        self.expert_width, self.max_action_dim = _shape(shapes, "action_in_proj.weight")
        self.prefix_width = _shape(shapes, _TEXT + "embed_tokens.weight")[1]

        heads, kv_heads = text_cfg.num_attention_heads, text_cfg.num_key_value_heads
        q_out = _shape(shapes, _TEXT + "layers.0.self_attn.q_proj.weight")[0]
        if q_out % heads:
            raise ValueError(f"{_TEXT}layers.0.self_attn.q_proj.weight: {q_out} rows do not split into "
                             f"num_attention_heads={heads} heads of the backbone config")
        self.head_dim = q_out // heads
        self.vlm_layers = _count(shapes, _TEXT + "layers.")
        self.expert_layers = _count(shapes, _EXPERT + "layers.")
        if self.vlm_layers % self.expert_layers:
            raise ValueError(f"{self.expert_layers} expert layers do not divide {self.vlm_layers} text layers")

        def llama(width: int, mlp_key: str, layers: int) -> Any:
            return LlamaConfig(
                hidden_size=width, intermediate_size=_shape(shapes, mlp_key)[0], num_hidden_layers=layers,
                num_attention_heads=heads, num_key_value_heads=kv_heads, head_dim=self.head_dim,
                vocab_size=_shape(shapes, _TEXT + "embed_tokens.weight")[0], rms_norm_eps=text_cfg.rms_norm_eps,
                hidden_act=text_cfg.hidden_act, attention_bias=_TEXT + "layers.0.self_attn.q_proj.bias" in shapes,
                mlp_bias=_TEXT + "layers.0.mlp.gate_proj.bias" in shapes)

        text_llama = llama(self.prefix_width, _TEXT + "layers.0.mlp.gate_proj.weight", self.vlm_layers)
        expert_llama = llama(self.expert_width, _EXPERT + "layers.0.mlp.gate_proj.weight", self.expert_layers)

        text = nn.Module()
        text.embed_tokens = nn.Embedding(text_llama.vocab_size, self.prefix_width)
        text.layers = nn.ModuleList(LlamaDecoderLayer(text_llama, i) for i in range(self.vlm_layers))
        text.norm = LlamaRMSNorm(self.prefix_width, eps=text_llama.rms_norm_eps)
        vlm = nn.Module()
        vlm.model = nn.Module()
        vlm.model.vision_model, vlm.model.connector = _vision(shapes, backbone.vision_config, text_llama)
        vlm.model.text_model = text
        vlm.lm_head = nn.Linear(self.prefix_width, text_llama.vocab_size, bias=False)
        vlm.lm_head.weight.requires_grad_(False)  # in the checkpoint, read by no forward here

        # LeRobot pairs text layer i with expert layer i // n (n = text layers / expert layers) when
        # i % n == 0; the others leave the action tokens as they are.
        per = self.vlm_layers // self.expert_layers
        self.expert_of = [i // per if i % per == 0 else None for i in range(self.vlm_layers)]
        self.cross = [_is_cross(cfg, i) for i in range(self.vlm_layers)]
        for i, j in enumerate(self.expert_of):
            if j is not None and self.cross[i] != _is_cross(cfg, j):  # LeRobot would fail on a shape
                raise ValueError(f"text layer {i} and its expert layer {j} disagree on cross-attention: "
                                 f"{self.expert_layers} expert layers cannot run with self_attn_every_n_layers="
                                 f"{cfg['self_attn_every_n_layers']}")
        expert = nn.Module()
        expert.layers = nn.ModuleList(LlamaDecoderLayer(expert_llama, j) for j in range(self.expert_layers))
        kv_width = kv_heads * self.head_dim  # the VLM's and the expert's alike
        for j, layer in enumerate(expert.layers):
            if _is_cross(cfg, j):  # reads the VLM's keys/values, not the expert's hidden states
                layer.self_attn.k_proj = nn.Linear(kv_width, kv_width, bias=expert_llama.attention_bias)
                layer.self_attn.v_proj = nn.Linear(kv_width, kv_width, bias=expert_llama.attention_bias)
        expert.norm = LlamaRMSNorm(self.expert_width, eps=expert_llama.rms_norm_eps)

        self.vlm_with_expert = nn.Module()
        self.vlm_with_expert.vlm = vlm
        self.vlm_with_expert.lm_expert = expert
        self.state_proj = nn.Linear(self.max_state_dim, self.prefix_width)
        self.action_in_proj = nn.Linear(self.max_action_dim, self.expert_width)
        self.action_out_proj = nn.Linear(self.expert_width, self.max_action_dim)
        self.action_time_mlp_in = nn.Linear(2 * self.expert_width, self.expert_width)
        self.action_time_mlp_out = nn.Linear(self.expert_width, self.expert_width)
        _check_shapes({k: tuple(v.shape) for k, v in self.state_dict().items()}, shapes)

    @classmethod
    def from_shapes(cls, shapes: Mapping[str, Sequence[int]], config: Mapping[str, Any], *,
                    vlm_config: Mapping[str, Any] | None = None, dtype: torch.dtype = torch.float32) -> "SmolVLAModel":
        """The module tree on torch's meta device (no memory), sizes from ``shapes`` (key -> shape,
        keys without ``model.``); raises ValueError naming the first missing, misshapen or unexpected key."""
        if vlm_config is None:
            raise ValueError("smolvla needs vlm_config: the backbone config.json under config vlm_model_name")
        with torch.device("meta"):
            return cls(shapes, config, vlm_config).to(dtype)

    @classmethod
    def from_state_dict(cls, state_dict: Mapping[str, Tensor], config: Mapping[str, Any], *,
                        vlm_config: Mapping[str, Any] | None = None,
                        dtype: torch.dtype = torch.float32) -> "SmolVLAModel":
        """Build from LeRobot's weights (keys without ``model.``), held in ``dtype``. Tensors already
        in ``dtype`` are taken over, not copied."""
        model = cls.from_shapes({k: tuple(v.shape) for k, v in state_dict.items()}, config,
                                vlm_config=vlm_config, dtype=dtype)
        model.load_state_dict({k: v.to(dtype) for k, v in state_dict.items()}, strict=True, assign=True)
        return model.eval()

    @property
    def dtype(self) -> torch.dtype:
        return self.action_in_proj.weight.dtype

    def _embed_images(self, images: Sequence[Tensor]) -> list[Tensor]:
        """[B, N, prefix_width] per camera, already scaled by sqrt(width); one vision pass for all."""
        vlm = self.vlm_with_expert.vlm.model
        pixels = torch.cat([image.to(self.dtype) for image in images])
        tokens = vlm.connector(vlm.vision_model(pixel_values=pixels).last_hidden_state)
        tokens = tokens * torch.tensor(tokens.shape[-1] ** 0.5, dtype=tokens.dtype, device=tokens.device)
        return list(tokens.chunk(len(images)))

    def prefix(self, images: Sequence[Tensor], image_masks: Sequence[Tensor], tokens: Tensor, token_mask: Tensor,
               state: Tensor) -> Prefix:
        """Run the VLM over [camera tokens...; language; state]. ``images``: [B, 3, H, W] in [-1, 1]
        per camera; ``image_masks`` [B] bool per camera; ``tokens``/``token_mask`` [B, L];
        ``state`` [B, max_state_dim]."""
        if len(images) != len(image_masks) or not images:
            raise ValueError(f"{len(images)} images for {len(image_masks)} image masks (at least one camera)")
        text = self.vlm_with_expert.vlm.model.text_model
        embeds, real = [], []
        for image_tokens, image_mask in zip(self._embed_images(images), image_masks):
            embeds.append(image_tokens)
            real.append(image_mask.bool()[:, None].expand(-1, image_tokens.shape[1]))
        embeds.append(text.embed_tokens(tokens) * math.sqrt(self.prefix_width))
        real.append(token_mask.bool())
        embeds.append(self.state_proj(state.to(self.dtype))[:, None])
        real.append(torch.ones_like(real[-1][:, :1]))
        # Block 0 (images, language) never sees block 1 (the state token, then any padding up to prefix_length).
        blocks = [0] * (sum(e.shape[1] for e in embeds) - 1) + [1]
        x, mask = torch.cat(embeds, dim=1), torch.cat(real, dim=1)
        if self.prefix_length > x.shape[1]:
            extra = self.prefix_length - x.shape[1]
            x, mask = F.pad(x, (0, 0, 0, extra)), F.pad(mask, (0, extra), value=False)
            blocks += [1] * extra
        block = torch.tensor(blocks, device=x.device)
        visible = (block[None, :] <= block[:, None]) & mask[:, None, :] & mask[:, :, None]
        rotation = _rotation(mask.long().cumsum(dim=1) - 1, self.head_dim)
        keys, values = [], []
        for layer in text.layers:
            h = layer.input_layernorm(x)
            attn = layer.self_attn
            split = lambda t: t.view(*t.shape[:2], -1, self.head_dim)  # noqa: E731
            q = _rope(split(attn.q_proj(h)), rotation)
            k = _rope(split(attn.k_proj(h)), rotation)
            v = split(attn.v_proj(h))
            keys.append(k)
            values.append(v)
            x = _residual_mlp(layer, x, _attend(q, k, v, visible))
        return Prefix(hidden=text.norm(x).float(), mask=mask, keys=tuple(keys), values=tuple(values))

    def velocity(self, prefix: Prefix, x_t: Tensor, t: Tensor) -> tuple[Tensor, Tensor]:
        """The expert's velocity [B, C, max_action_dim] (float32) at noisy actions ``x_t``
        [B, C, max_action_dim] and times ``t`` [B] (1 = noise), and its final normed states of the
        action positions [B, C, expert_width] (float32)."""
        b, c, _ = x_t.shape
        actions = self.action_in_proj(x_t.to(self.dtype))
        time = _time_embedding(t, self.expert_width, self.min_period, self.max_period).to(actions.dtype)
        x = torch.cat([actions, time[:, None].expand_as(actions)], dim=2)
        x = self.action_time_mlp_out(F.silu(self.action_time_mlp_in(x)))

        steps = torch.arange(c, device=x.device)
        from_zero = _rotation(steps.expand(b, c), self.head_dim)
        after_prefix = _rotation(prefix.mask.long().sum(dim=1, keepdim=True) + steps, self.head_dim)
        sees_prefix = prefix.mask[:, None, :].expand(b, c, -1)
        sees_all = torch.cat([sees_prefix, (steps[None, :] <= steps[:, None]).expand(b, c, c)], dim=2)
        layers = self.vlm_with_expert.lm_expert.layers
        for i, j in enumerate(self.expert_of):
            if j is None:
                continue
            layer = layers[j]
            attn = layer.self_attn
            h = layer.input_layernorm(x)
            split = lambda t: t.view(*t.shape[:2], -1, self.head_dim)  # noqa: E731
            q = split(attn.q_proj(h))
            if self.cross[i]:
                k = split(attn.k_proj(prefix.keys[i].flatten(2).to(h.dtype)))
                v = split(attn.v_proj(prefix.values[i].flatten(2).to(h.dtype)))
                attended = _attend(_rope(q, from_zero), k, v, sees_prefix)
            else:
                k = torch.cat([prefix.keys[i], _rope(split(attn.k_proj(h)), after_prefix)], dim=1)
                v = torch.cat([prefix.values[i], split(attn.v_proj(h))], dim=1)
                attended = _attend(_rope(q, after_prefix), k, v, sees_all)
            x = _residual_mlp(layer, x, attended)
        hidden = self.vlm_with_expert.lm_expert.norm(x)
        return self.action_out_proj(hidden).float(), hidden.float()

    @torch.no_grad()
    def sample_actions(self, images: Sequence[Tensor], image_masks: Sequence[Tensor], tokens: Tensor,
                       token_mask: Tensor, state: Tensor, noise: Tensor, num_steps: int = 10) -> Tensor:
        """The action chunk [B, C, max_action_dim] (float32, normalised): Euler from ``noise`` at
        t = 1 to t = 0 in ``num_steps`` steps over one cached prefix."""
        prefix = self.prefix(images, image_masks, tokens, token_mask, state)
        dt = -1.0 / num_steps
        x = noise.float()
        for step in range(num_steps):
            t = torch.full((x.shape[0],), 1.0 + step * dt, dtype=torch.float32, device=x.device)
            x = x + dt * self.velocity(prefix, x, t)[0]
        return x
