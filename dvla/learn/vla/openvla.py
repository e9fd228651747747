"""OpenVLA and OpenVLA-OFT (openvla @ c8f03f4, openvla-oft @ 213c5ff): the Prismatic model built
from the published checkpoints' tensors (``state_dict()`` has the checkpoint's keys, so export
writes them back), plus OFT's L1-regression action head and proprio projector.

**Vision.** Each camera is 6 channels of ``pixel_values``: DINOv2 ViT-L/14 with 4 registers
(``featurizer``) reads channels 0-2, SigLIP So400m/14 (``fused_featurizer``) channels 3-5. A tower's
features are its patch tokens after block ``depth - 2``, not normed (Prismatic's
``get_intermediate_layers(n={depth - 2})``); the last block, the final norm and SigLIP's MAP head
are held because the checkpoint stores them, never run. DINOv2: patch conv plus ``pos_embed`` on
the patches, then ``[cls; registers; patches]``, LayerScale ``scale_factor`` on both residual
branches. SigLIP: patches plus ``pos_embed``, no prefix token. Pre-norm blocks, LayerNorm eps 1e-6,
exact GELU, biased qkv. Head counts: width / 64 (DINOv2), width / 72 (SigLIP).

**Projector.** Per patch ``[DINOv2; SigLIP]`` features -> fc1, GELU, fc2, GELU, fc3. Several
cameras (OFT: primary, wrist) give their patches one after the other.

**Sequence.** ``[embedding of input_ids[0] (BOS); patches; extra tokens (OFT's proprio); embeddings
of input_ids[1:]]`` (Prismatic inserts after BOS). Llama-2: RMSNorm in float32 (``x rsqrt(mean x^2 +
eps)`` cast back, times the weight; eps from ``text_config``, LlamaConfig's 1e-6 when absent), RoPE
theta 10000 at the count of real tokens before each one (for right padding the same as upstream's
arange), SiLU MLP, untied ``lm_head``. OpenVLA attends causally, OFT bidirectionally (moojink's
transformers fork); pad keys are masked in both. Prompts must be right padded (their first column
real), as ``openvla_processing.encode_prompts`` gives them by default.

**OFT.** ``prompt (ending in 29871) + 56 placeholders (id 1, embeddings zeroed) + stop (id 2)``,
one bidirectional pass; the L1 head reads the final hidden states one position left of each
placeholder (the 29871 token and placeholders 1..55: next-token alignment as in training),
reshaped to ``[B, chunk, action_dim * width]``.

**Sizes** come from tensor shapes, except Llama's head count (``text_config``, LlamaConfig's 32
when absent; KV heads from ``k_proj``'s rows) and OFT's chunk length (a platform constant: LIBERO 8).

**dtype.** ``dtype`` holds every weight (the checkpoints are bf16); norms run in float32 and the
attention is PyTorch's ``scaled_dot_product_attention`` (its fused kernels accumulate and take
the softmax in float32). Outputs (hidden states, logits, action states, actions) are float32.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Mapping, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .pi import _cast, _check_keys, _divide, _layer_count, _namespace, _rope, _shape

__all__ = ["OpenVLAModel", "OpenVLASizes", "OFTHeads", "TowerSizes"]

_LM = "language_model.model"
_LM_HEAD = "language_model.lm_head.weight"
_TOWERS = {"featurizer": 64, "fused_featurizer": 72}
"""Vision towers (DINOv2, SigLIP) by key prefix under ``vision_backbone``, with their head_dim."""
_VISION_EPS = 1e-6
_HEAD_EPS = 1e-5  # OFT's action head: nn.LayerNorm's default
_LLAMA_DEFAULTS = {"num_attention_heads": 32, "rms_norm_eps": 1e-6, "rope_theta": 10000.0, "hidden_act": "silu"}
"""LlamaConfig's defaults for what the real-size ``text_config`` leaves out (it holds only the vocab)."""
PLACEHOLDER_ID, STOP_ID = 1, 2  # OFT's action placeholders (embeddings zeroed) and the stop token after them


@dataclass(frozen=True)
class TowerSizes:
    """One ViT tower, read from its tensor shapes."""

    width: int
    depth: int  #: blocks held (features come from block depth - 2)
    heads: int
    mlp: int
    patch: int
    grid: int  #: patches per side
    registers: int
    cls_token: bool
    layer_scale: bool
    pool_latents: int  #: SigLIP's MAP head latents (0: no head)


@dataclass(frozen=True)
class OpenVLASizes:
    """Every size of the module tree (see the module docstring for where each comes from)."""

    dinov2: TowerSizes
    siglip: TowerSizes
    projector_hidden: int
    vocab: int  #: LM vocabulary (padded to a multiple of 64: 32064)
    width: int
    mlp: int
    depth: int
    heads: int
    kv_heads: int
    rms_eps: float
    n_action_bins: int
    tokenizer_vocab: int  #: the tokenizer's 32000: the action bins are its last n_action_bins ids
    pad_token_id: int


class LayerNorm(nn.LayerNorm):
    """LayerNorm computed in float32 whatever the weights' dtype."""

    def forward(self, x: Tensor) -> Tensor:
        return F.layer_norm(x.float(), self.normalized_shape, self.weight.float(), self.bias.float(),
                            self.eps).to(x.dtype)


class LayerScale(nn.Module):
    def __init__(self, width: int) -> None:
        super().__init__()
        self.scale_factor = nn.Parameter(torch.ones(width))

    def forward(self, x: Tensor) -> Tensor:
        return x * self.scale_factor


class VitAttention(nn.Module):
    def __init__(self, width: int, heads: int) -> None:
        super().__init__()
        self.heads = heads
        self.qkv = nn.Linear(width, 3 * width)
        self.proj = nn.Linear(width, width)

    def forward(self, x: Tensor) -> Tensor:
        q, k, v = self.qkv(x).view(*x.shape[:2], 3, self.heads, -1).permute(2, 0, 3, 1, 4)
        return self.proj(F.scaled_dot_product_attention(q, k, v).transpose(1, 2).reshape(x.shape))


class Mlp(nn.Module):
    """fc1, activation, fc2 (exact GELU: the ViTs, the projectors)."""

    def __init__(self, width: int, hidden: int, out: int | None = None) -> None:
        super().__init__()
        self.fc1, self.fc2 = nn.Linear(width, hidden), nn.Linear(hidden, out or width)

    def forward(self, x: Tensor) -> Tensor:
        return self.fc2(F.gelu(self.fc1(_cast(x, self.fc1))))


class VitBlock(nn.Module):
    def __init__(self, s: TowerSizes) -> None:
        super().__init__()
        self.norm1, self.norm2 = LayerNorm(s.width, eps=_VISION_EPS), LayerNorm(s.width, eps=_VISION_EPS)
        self.attn = VitAttention(s.width, s.heads)
        self.mlp = Mlp(s.width, s.mlp)
        self.ls1 = LayerScale(s.width) if s.layer_scale else nn.Identity()
        self.ls2 = LayerScale(s.width) if s.layer_scale else nn.Identity()

    def forward(self, x: Tensor) -> Tensor:
        x = x + self.ls1(self.attn(self.norm1(x)))
        return x + self.ls2(self.mlp(self.norm2(x)))


class AttentionPool(nn.Module):
    """SigLIP's MAP head (timm's ``attn_pool``): stored in the checkpoint, not run by OpenVLA."""

    def __init__(self, s: TowerSizes) -> None:
        super().__init__()
        self.latent = nn.Parameter(torch.zeros(1, s.pool_latents, s.width))
        self.q, self.proj = nn.Linear(s.width, s.width), nn.Linear(s.width, s.width)
        self.kv = nn.Linear(s.width, 2 * s.width)
        self.norm = LayerNorm(s.width, eps=_VISION_EPS)
        self.mlp = Mlp(s.width, s.mlp)


class Vit(nn.Module):
    """A timm ViT as Prismatic runs it (module docstring); ``forward`` gives the patch features."""

    def __init__(self, s: TowerSizes) -> None:
        super().__init__()
        self.sizes = s
        self.patch_embed = _namespace(proj=nn.Conv2d(3, s.width, s.patch, stride=s.patch))
        if s.cls_token:
            self.cls_token = nn.Parameter(torch.zeros(1, 1, s.width))
        if s.registers:
            self.reg_token = nn.Parameter(torch.zeros(1, s.registers, s.width))
        self.pos_embed = nn.Parameter(torch.zeros(1, s.grid * s.grid, s.width))
        self.blocks = nn.ModuleList(VitBlock(s) for _ in range(s.depth))
        self.norm = LayerNorm(s.width, eps=_VISION_EPS)
        if s.pool_latents:
            self.attn_pool = AttentionPool(s)

    def forward(self, image: Tensor) -> Tensor:
        """[B, 3, H, W] normalised pixels -> [B, grid^2, width] (the tower's dtype)."""
        x = self.patch_embed.proj(_cast(image, self.patch_embed.proj)).flatten(2).transpose(1, 2) + self.pos_embed
        prefix = [t.expand(x.shape[0], -1, -1) for t in (getattr(self, "cls_token", None),
                                                         getattr(self, "reg_token", None)) if t is not None]
        x = torch.cat([*prefix, x], dim=1)
        for block in self.blocks[:-1]:
            x = block(x)
        return x[:, x.shape[1] - self.pos_embed.shape[1]:]


class RMSNorm(nn.Module):
    def __init__(self, width: int, eps: float) -> None:
        super().__init__()
        self.eps = eps
        self.weight = nn.Parameter(torch.ones(width))

    def forward(self, x: Tensor) -> Tensor:
        xf = x.float()
        return self.weight * (xf * torch.rsqrt(xf.square().mean(-1, keepdim=True) + self.eps)).to(x.dtype)


class LlamaAttention(nn.Module):
    """The projections (names as transformers', so LoRA targets them); the attention runs in
    :meth:`OpenVLAModel._decode`."""

    def __init__(self, width: int, heads: int, kv_heads: int) -> None:
        super().__init__()
        self.heads, self.kv_heads, self.head_dim = heads, kv_heads, width // heads
        self.q_proj = nn.Linear(width, width, bias=False)
        self.k_proj = nn.Linear(width, kv_heads * self.head_dim, bias=False)
        self.v_proj = nn.Linear(width, kv_heads * self.head_dim, bias=False)
        self.o_proj = nn.Linear(width, width, bias=False)


class LlamaMLP(nn.Module):
    def __init__(self, width: int, hidden: int) -> None:
        super().__init__()
        self.gate_proj = nn.Linear(width, hidden, bias=False)
        self.up_proj = nn.Linear(width, hidden, bias=False)
        self.down_proj = nn.Linear(hidden, width, bias=False)

    def forward(self, x: Tensor) -> Tensor:
        return self.down_proj(F.silu(self.gate_proj(x)) * self.up_proj(x))


class LlamaLayer(nn.Module):
    def __init__(self, s: OpenVLASizes) -> None:
        super().__init__()
        self.self_attn = LlamaAttention(s.width, s.heads, s.kv_heads)
        self.mlp = LlamaMLP(s.width, s.mlp)
        self.input_layernorm = RMSNorm(s.width, s.rms_eps)
        self.post_attention_layernorm = RMSNorm(s.width, s.rms_eps)


def _tower_sizes(shapes: Mapping[str, Sequence[int]], prefix: str, head_dim: int) -> TowerSizes:
    patch_key = f"{prefix}.patch_embed.proj.weight"
    width, _, patch, _ = _shape(shapes, patch_key)
    depth = _layer_count(shapes, f"{prefix}.blocks")
    if depth < 2:
        raise ValueError(f"key {prefix}.blocks: {depth} block(s); the features come from the second-to-last")
    positions = _shape(shapes, f"{prefix}.pos_embed")[1]
    grid = math.isqrt(positions)
    if grid * grid != positions:
        raise ValueError(f"key '{prefix}.pos_embed': {positions} positions is no square grid of patches")
    reg = f"{prefix}.reg_token"
    pool = f"{prefix}.attn_pool.latent"
    return TowerSizes(width=width, depth=depth, heads=_divide(width, head_dim, patch_key, "heads"),
                      mlp=_shape(shapes, f"{prefix}.blocks.0.mlp.fc1.weight")[0], patch=patch, grid=grid,
                      registers=_shape(shapes, reg)[1] if reg in shapes else 0,
                      cls_token=f"{prefix}.cls_token" in shapes,
                      layer_scale=f"{prefix}.blocks.0.ls1.scale_factor" in shapes,
                      pool_latents=_shape(shapes, pool)[1] if pool in shapes else 0)


def read_sizes(shapes: Mapping[str, Sequence[int]], config: Mapping[str, Any]) -> OpenVLASizes:
    """:class:`OpenVLASizes` from the checkpoint's shapes and config.json (ValueError naming the
    key it misses or the ``text_config`` field the shapes contradict)."""
    text = {**_LLAMA_DEFAULTS, **(config.get("text_config") or {})}
    if text.get("rope_scaling") or float(text["rope_theta"]) != 10000.0 or text["hidden_act"] != "silu":
        raise ValueError(f"text_config: rope_theta {text['rope_theta']}, rope_scaling {text.get('rope_scaling')}, "
                         f"hidden_act {text['hidden_act']!r} (Llama-2 has 10000, none, 'silu')")
    vocab, width = _shape(shapes, _LM_HEAD)
    heads = int(text["num_attention_heads"])
    q_key, k_key = f"{_LM}.layers.0.self_attn.q_proj.weight", f"{_LM}.layers.0.self_attn.k_proj.weight"
    head_dim = _divide(_shape(shapes, q_key)[0], heads, q_key, "query heads")
    kv_heads = _divide(_shape(shapes, k_key)[0], head_dim, k_key, "heads")
    found = {"vocab_size": vocab, "hidden_size": width, "num_key_value_heads": kv_heads,
             "intermediate_size": _shape(shapes, f"{_LM}.layers.0.mlp.gate_proj.weight")[0],
             "num_hidden_layers": _layer_count(shapes, f"{_LM}.layers")}
    for field, value in found.items():
        if field in text and int(text[field]) != value:
            raise ValueError(f"text_config.{field} is {text[field]} but the checkpoint's tensors give {value}")
    dinov2, siglip = (_tower_sizes(shapes, f"vision_backbone.{name}", hd) for name, hd in _TOWERS.items())
    n_bins = int(config.get("n_action_bins", 256))
    return OpenVLASizes(
        dinov2=dinov2, siglip=siglip, projector_hidden=_shape(shapes, "projector.fc1.weight")[0], vocab=vocab,
        width=width, mlp=found["intermediate_size"], depth=found["num_hidden_layers"], heads=heads,
        kv_heads=kv_heads, rms_eps=float(text["rms_norm_eps"]), n_action_bins=n_bins,
        tokenizer_vocab=vocab - int(config.get("pad_to_multiple_of", 64)),
        pad_token_id=int(config.get("pad_token_id", 32000)))


def _insert(t: Tensor, n: int, value: float | bool) -> Tensor:
    """``t`` [B, L, ...] with ``n`` entries of ``value`` after the first column (where the patches go)."""
    fill = torch.full((t.shape[0], n, *t.shape[2:]), value, dtype=t.dtype, device=t.device)
    return torch.cat([t[:, :1], fill, t[:, 1:]], dim=1)


def _right_padded(mask: Tensor) -> Tensor:
    mask = mask.bool()
    if not bool(mask[:, 0].all()) or bool((mask[:, 1:] & ~mask[:, :-1]).any()):
        raise ValueError("attention_mask must be right padded (each row's real tokens first, BOS in column 0)")
    return mask


def _positions(mask: Tensor) -> Tensor:
    """RoPE positions: the count of real tokens before each one (pads: 0, never seen)."""
    return (mask.long().cumsum(1) - 1).clamp(min=0)


def _allowed(mask: Tensor, bidirectional: bool) -> Tensor:
    """[B, S, S] bool: query i may see key j (a real key; at or before i unless bidirectional)."""
    allowed = _right_padded(mask)[:, None, :].expand(-1, mask.shape[1], -1)
    if bidirectional:
        return allowed
    return allowed & torch.ones(mask.shape[1], mask.shape[1], dtype=torch.bool, device=mask.device).tril()


def _append(ids: Tensor, mask: Tensor, tail: Tensor, pad_id: int) -> tuple[Tensor, Tensor, Tensor]:
    """Right-padded ``ids`` / ``mask`` [B, L] with ``tail`` [B, T] placed right after each row's real
    tokens: (ids [B, L + T], mask [B, L + T], the tail's columns [B, T])."""
    lengths = _right_padded(mask).sum(1, keepdim=True)
    columns = lengths + torch.arange(tail.shape[1], device=ids.device)
    out = F.pad(ids.long(), (0, tail.shape[1]), value=pad_id).scatter(1, columns, tail.long())
    width = torch.arange(out.shape[1], device=ids.device)
    return out, width[None] < lengths + tail.shape[1], columns


class OpenVLAModel(nn.Module):
    """OpenVLA's Prismatic model (module docstring). Build with :meth:`from_state_dict` or, on the
    meta device, :meth:`from_shapes`; ``state_dict()`` has the checkpoint's keys."""

    def __init__(self, sizes: OpenVLASizes) -> None:
        super().__init__()
        s = self.sizes = sizes
        self.vocab_size, self.width, self.n_action_bins = s.vocab, s.width, s.n_action_bins
        self.action_token_ids = range(s.tokenizer_vocab - s.n_action_bins, s.tokenizer_vocab)
        self.vision_backbone = _namespace(featurizer=Vit(s.dinov2), fused_featurizer=Vit(s.siglip))
        self.projector = _namespace(fc1=nn.Linear(s.dinov2.width + s.siglip.width, s.projector_hidden),
                                    fc2=nn.Linear(s.projector_hidden, s.width), fc3=nn.Linear(s.width, s.width))
        decoder = _namespace(embed_tokens=nn.Embedding(s.vocab, s.width),
                             layers=nn.ModuleList(LlamaLayer(s) for _ in range(s.depth)),
                             norm=RMSNorm(s.width, s.rms_eps))
        self.language_model = _namespace(model=decoder, lm_head=nn.Linear(s.width, s.vocab, bias=False))

    @property
    def decoder(self) -> nn.Module:
        """The Llama stack (``language_model.model``: embed_tokens, layers, norm)."""
        return self.language_model.model

    @property
    def dtype(self) -> torch.dtype:
        """The dtype the LM computes in (peft's LoRA layers forward ``weight``)."""
        return self.decoder.layers[0].self_attn.q_proj.weight.dtype

    @property
    def patches_per_image(self) -> int:
        return self.sizes.dinov2.grid ** 2

    # -- building --
    @classmethod
    def from_shapes(cls, shapes: Mapping[str, Sequence[int]], config: Mapping[str, Any], *,
                    dtype: torch.dtype = torch.bfloat16) -> "OpenVLAModel":
        """The module tree for the checkpoint's ``shapes`` on the meta device (no memory, no weights).
        ValueError, one line naming the first missing, unexpected or misshapen key."""
        sizes = read_sizes(shapes, config)
        if sizes.dinov2.grid != sizes.siglip.grid:
            raise ValueError(f"the towers' patch grids differ ({sizes.dinov2.grid} and {sizes.siglip.grid} per side)")
        with torch.device("meta"):
            model = cls(sizes)
        _check_keys({k: tuple(v.shape) for k, v in model.state_dict().items()}, shapes)
        return model.to(dtype)

    @classmethod
    def from_state_dict(cls, state_dict: Mapping[str, Tensor], config: Mapping[str, Any], *,
                        dtype: torch.dtype = torch.float32) -> "OpenVLAModel":
        """The model holding ``state_dict``'s tensors (the safetensors shards' keys as stored) cast
        to ``dtype``; ``config``: config.json as read."""
        model = cls.from_shapes({k: tuple(v.shape) for k, v in state_dict.items()}, config, dtype=dtype)
        model.load_state_dict({k: v.to(dtype) for k, v in state_dict.items()}, assign=True)
        return model.eval()

    # -- the forward pieces --
    def patch_embeddings(self, pixel_values: Tensor) -> Tensor:
        """[B, 6 * cameras, H, W] -> the projected patches [B, cameras * grid^2, width] (the LM's dtype)."""
        if pixel_values.shape[1] % 6 or not pixel_values.shape[1]:
            raise ValueError(f"pixel_values must have 6 channels per camera (DINOv2 3, SigLIP 3), got "
                             f"{tuple(pixel_values.shape)}")
        towers = self.vision_backbone
        features = torch.cat([torch.cat([towers.featurizer(image[:, :3]), towers.fused_featurizer(image[:, 3:])], 2)
                              for image in pixel_values.split(6, dim=1)], dim=1)
        p = self.projector
        return p.fc3(F.gelu(p.fc2(F.gelu(p.fc1(_cast(features, p.fc1)))))).to(self.dtype)

    def embed(self, pixel_values: Tensor, input_ids: Tensor, extra: Tensor | None = None) -> Tensor:
        """The LM's input ``[BOS; patches; extra; input_ids[1:]]`` [B, 1 + P + K + L - 1, width];
        ``extra`` [B, K, width]: tokens after the patches (OFT's proprio token)."""
        words = self.decoder.embed_tokens(input_ids.long())
        inserted = [self.patch_embeddings(pixel_values)] + ([] if extra is None else [extra.to(words.dtype)])
        return torch.cat([words[:, :1], *inserted, words[:, 1:]], dim=1)

    def _decode(self, h: Tensor, positions: Tensor, allowed: Tensor,
                past: Sequence[tuple[Tensor, Tensor]] | None = None) -> tuple[Tensor, list[tuple[Tensor, Tensor]]]:
        """``h`` [B, S, width] through the Llama stack; queries see keys where ``allowed`` [B, S,
        (cached +) S]. Returns the final normed states (LM dtype) and each layer's keys/values
        (``past``'s then this input's)."""
        h = h.to(self.dtype)
        bias = allowed[:, None]
        cache = []
        for i, layer in enumerate(self.decoder.layers):
            attn = layer.self_attn
            x = layer.input_layernorm(h)
            split = lambda t: t.view(*x.shape[:2], -1, attn.head_dim).transpose(1, 2)  # noqa: E731
            q, k = _rope(split(attn.q_proj(x)), positions), _rope(split(attn.k_proj(x)), positions)
            v = split(attn.v_proj(x))
            if past is not None:
                k, v = torch.cat([past[i][0], k], dim=2), torch.cat([past[i][1], v], dim=2)
            cache.append((k, v))
            groups = attn.heads // attn.kv_heads
            out = F.scaled_dot_product_attention(q, k.repeat_interleave(groups, 1), v.repeat_interleave(groups, 1),
                                                 attn_mask=bias)
            h = h + attn.o_proj(out.transpose(1, 2).reshape(*x.shape[:2], -1))
            h = h + layer.mlp(layer.post_attention_layernorm(h))
        return self.decoder.norm(h), cache

    def decode(self, embeds: Tensor, mask: Tensor, *, bidirectional: bool = False) -> Tensor:
        """The final normed hidden states [B, S, width] (LM dtype) of the LM over ``embeds`` with the
        multimodal ``mask`` [B, S] (right padded): causal, or every real token seeing every other."""
        return self._decode(embeds, _positions(mask), _allowed(mask, bidirectional))[0]

    def hidden(self, pixel_values: Tensor, input_ids: Tensor, attention_mask: Tensor, *,
               bidirectional: bool = False) -> Tensor:
        """The LM's final normed hidden states [B, 1 + P + L - 1, width] float32 over the
        multimodal sequence of right-padded ``input_ids`` [B, L]; differentiable."""
        return self._hidden(pixel_values, input_ids, attention_mask, bidirectional).float()

    def _sequence(self, pixel_values: Tensor, input_ids: Tensor, attention_mask: Tensor) -> tuple[Tensor, Tensor]:
        """(embeds, mask) of the multimodal sequence."""
        embeds = self.embed(pixel_values, input_ids)
        return embeds, _insert(_right_padded(attention_mask), embeds.shape[1] - input_ids.shape[1], True)

    def _hidden(self, pixel_values: Tensor, input_ids: Tensor, attention_mask: Tensor, bidirectional: bool) -> Tensor:
        return self.decode(*self._sequence(pixel_values, input_ids, attention_mask), bidirectional=bidirectional)

    def lm_logits(self, hidden: Tensor) -> Tensor:
        """``lm_head`` of hidden states -> float32 logits over the LM vocabulary."""
        return self.language_model.lm_head(hidden.to(self.dtype)).float()

    def logits(self, pixel_values: Tensor, input_ids: Tensor, attention_mask: Tensor, *,
               bidirectional: bool = False) -> Tensor:
        """[B, 1 + P + L - 1, vocab] float32 over the whole multimodal sequence; differentiable.
        Position q's logits predict the token at q + 1."""
        return self.lm_logits(self._hidden(pixel_values, input_ids, attention_mask, bidirectional))

    def action_logits(self, pixel_values: Tensor, input_ids: Tensor, attention_mask: Tensor,
                      action_ids: Tensor) -> Tensor:
        """Teacher-forced logits [B, n, vocab] float32 that predict each of ``action_ids`` [B, n]
        after the right-padded prompt (``log_softmax(...).gather(-1, action_ids[..., None])`` are
        their log-probabilities); one differentiable causal pass over prompt + actions."""
        ids, mask, columns = _append(input_ids, attention_mask, action_ids, self.sizes.pad_token_id)
        hidden = self._hidden(pixel_values, ids, mask, False)
        rows = columns + (hidden.shape[1] - ids.shape[1]) - 1  # a token column c sits at c + P in the sequence
        return self.lm_logits(hidden.gather(1, rows[..., None].expand(-1, -1, hidden.shape[-1])))

    @torch.no_grad()
    def generate_action_tokens(self, pixel_values: Tensor, input_ids: Tensor, attention_mask: Tensor, n: int = 7,
                               choose: Callable[[Tensor], Tensor] | None = None) -> Tensor:
        """``n`` tokens [B, n] after each right-padded prompt, with a KV cache: upstream
        ``predict_action``'s ``generate`` (greedy over the whole vocabulary) unless ``choose``
        (float32 logits [B, vocab] -> ids [B]) picks them, e.g. by sampling."""
        choose = choose or (lambda logits: logits.argmax(-1))
        embeds, mask = self._sequence(pixel_values, input_ids, attention_mask)
        length = mask.sum(1)
        h, cache = self._decode(embeds, _positions(mask), _allowed(mask, False))
        last = h[torch.arange(h.shape[0], device=h.device), length - 1][:, None]
        tokens = []
        for step in range(n):
            tokens.append(choose(self.lm_logits(last[:, 0])).long())
            if step + 1 == n:
                break
            mask = torch.cat([mask, torch.ones_like(mask[:, :1])], dim=1)
            last, cache = self._decode(self.decoder.embed_tokens(tokens[-1])[:, None], (length + step)[:, None],
                                       mask[:, None, :], past=cache)
        return torch.stack(tokens, dim=1)


class MLPResNetBlock(nn.Module):
    def __init__(self, width: int) -> None:
        super().__init__()
        self.ffn = nn.Sequential(LayerNorm(width, eps=_HEAD_EPS), nn.Linear(width, width), nn.ReLU())

    def forward(self, x: Tensor) -> Tensor:
        return x + self.ffn(x)


class MLPResNet(nn.Module):
    def __init__(self, blocks: int, width_in: int, hidden: int, out: int) -> None:
        super().__init__()
        self.layer_norm1 = LayerNorm(width_in, eps=_HEAD_EPS)
        self.fc1 = nn.Linear(width_in, hidden)
        self.mlp_resnet_blocks = nn.ModuleList(MLPResNetBlock(hidden) for _ in range(blocks))
        self.layer_norm2 = LayerNorm(hidden, eps=_HEAD_EPS)
        self.fc2 = nn.Linear(hidden, out)

    def forward(self, x: Tensor) -> Tensor:
        x = F.relu(self.fc1(self.layer_norm1(_cast(x, self.fc1))))
        for block in self.mlp_resnet_blocks:
            x = block(x)
        return self.fc2(self.layer_norm2(x))


class OFTHeads(nn.Module):
    """OpenVLA-OFT's L1-regression action head (``action_head``, keys ``model.*``) and proprio
    projector (``proprio_projector``, keys ``fc1.*``, ``fc2.*``): each submodule's ``state_dict()``
    is its .pt file's without DDP's ``module.`` prefix."""

    def __init__(self, llm_width: int, action_dim: int, hidden: int, blocks: int, proprio_dim: int | None,
                 chunk_size: int) -> None:
        super().__init__()
        self.llm_width, self.action_dim, self.proprio_dim = llm_width, action_dim, proprio_dim
        self.chunk_size = chunk_size
        self.action_head = _namespace(model=MLPResNet(blocks, action_dim * llm_width, hidden, action_dim))
        if proprio_dim is not None:
            self.proprio_projector = Mlp(proprio_dim, llm_width, llm_width)

    @classmethod
    def from_state_dicts(cls, action_head: Mapping[str, Tensor], proprio_projector: Mapping[str, Tensor] | None = None,
                         *, chunk_size: int = 8, dtype: torch.dtype = torch.float32) -> "OFTHeads":
        """The heads holding the two files' tensors (keys without ``module.``) cast to ``dtype``;
        ``chunk_size``: the platform's NUM_ACTIONS_CHUNK (LIBERO 8), which no shape records."""
        ah = {k: tuple(v.shape) for k, v in action_head.items()}
        pp = None if proprio_projector is None else {k: tuple(v.shape) for k, v in proprio_projector.items()}
        try:
            width_in = _shape(ah, "model.layer_norm1.weight")[0]
            hidden, action_dim = _shape(ah, "model.fc1.weight")[0], _shape(ah, "model.fc2.weight")[0]
            blocks = _layer_count(ah, "model.mlp_resnet_blocks")
            llm_width = _divide(width_in, action_dim, "model.layer_norm1.weight", "action dims")
        except ValueError as err:
            hint = " (strip DDP's 'module.' prefix)" if any(k.startswith("module.") for k in ah) else ""
            raise ValueError(f"action head: {err}{hint}") from None
        try:
            proprio_dim = None if pp is None else _shape(pp, "fc1.weight")[1]
        except ValueError as err:
            raise ValueError(f"proprio projector: {err}") from None
        with torch.device("meta"):
            heads = cls(llm_width, action_dim, hidden, blocks, proprio_dim, chunk_size)
        for what, module, shapes, tensors in (("action head", heads.action_head, ah, action_head),
                                              ("proprio projector", getattr(heads, "proprio_projector", None), pp,
                                               proprio_projector)):
            if module is None:
                continue
            try:
                _check_keys({k: tuple(v.shape) for k, v in module.state_dict().items()}, shapes)
            except ValueError as err:
                raise ValueError(f"{what}: {err}") from None
            module.load_state_dict({k: v.to(dtype) for k, v in tensors.items()}, assign=True)
        return heads.eval()

    def proprio_token(self, proprio: Tensor) -> Tensor:
        """Normalised proprio [B, proprio_dim] -> [B, 1, llm_width] (fc1, GELU, fc2)."""
        return self.proprio_projector(proprio)[:, None]

    def action_states(self, model: OpenVLAModel, pixel_values: Tensor, input_ids: Tensor, attention_mask: Tensor,
                      proprio: Tensor | None = None) -> Tensor:
        """The final hidden states the L1 head reads, [B, chunk * action_dim, llm_width] float32
        (module docstring), from one bidirectional pass; differentiable. ``input_ids``: right-padded
        prompts ending in 29871; ``proprio``: [B, proprio_dim] normalised (needed when the heads hold
        a proprio projector)."""
        if (proprio is None) != (getattr(self, "proprio_projector", None) is None):
            raise ValueError("pass proprio exactly when the heads hold a proprio projector")
        batch, n = input_ids.shape[0], self.chunk_size * self.action_dim
        tail = torch.tensor([PLACEHOLDER_ID] * n + [STOP_ID], device=input_ids.device).expand(batch, -1)
        ids, mask, columns = _append(input_ids, attention_mask, tail, model.sizes.pad_token_id)
        extra = None if proprio is None else self.proprio_token(proprio)
        embeds = model.embed(pixel_values, ids, extra)
        inserted = embeds.shape[1] - ids.shape[1]
        placeholders = torch.zeros_like(mask).scatter(1, columns[:, :n], True)
        embeds = embeds * ~_insert(placeholders, inserted, False)[..., None]
        hidden = model.decode(embeds, _insert(mask, inserted, True), bidirectional=True)
        rows = columns[:, :n] + inserted - 1
        return hidden.gather(1, rows[..., None].expand(-1, -1, hidden.shape[-1])).float()

    def actions_from_states(self, states: Tensor) -> Tensor:
        """:meth:`action_states` -> normalised actions [B, chunk, action_dim] float32."""
        return self.action_head.model(states.reshape(states.shape[0], self.chunk_size, -1)).float()

    def predict_chunk(self, model: OpenVLAModel, pixel_values: Tensor, input_ids: Tensor, attention_mask: Tensor,
                      proprio: Tensor | None = None) -> Tensor:
        """Upstream ``predict_action``'s normalised action chunk [B, chunk, action_dim] float32 (before
        un-normalisation); differentiable."""
        return self.actions_from_states(self.action_states(model, pixel_values, input_ids, attention_mask, proprio))
