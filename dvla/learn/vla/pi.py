"""pi0 and pi0.5 (LeRobot 0.6.1's ``pi0`` / ``pi05``): the flow-matching model, loaded from
LeRobot's state dict (keys without its ``model.`` prefix) and reproducing its action chunks.

**Towers.** SigLIP (:class:`SiglipVision`) and a linear projector turn each camera into tokens; a
Gemma language model (the "VLM") reads ``[camera tokens; instruction tokens]`` bidirectionally,
pads masked (images: the camera's mask; words: the token mask). A second, narrower
Gemma (the action expert) reads the suffix: pi0 ``[state token; chunk action tokens]``, each action
token ``action_time_mlp_out(silu(action_time_mlp_in([action_in_proj(x_t); sinusoid(t)])))``;
pi0.5 only the action tokens ``action_in_proj(x_t)``, with the time entering through adaRMS norms
conditioned on ``silu(time_mlp_out(silu(time_mlp_in(sinusoid(t)))))``. The two towers meet in
attention only: layer i of the expert attends to layer i's prefix keys/values (cached once by
:meth:`PiModel.prefix`) and to its own suffix. The suffix's block mask: pi0's state token sees
the prefix and itself, the action tokens see the prefix, the state and each other; the prefix
never sees the suffix. ``action_out_proj`` of the expert's final normed action states is the
velocity (pi convention: t = 1 noise, t = 0 action; Euler with dt = -1 / steps).

**Numerics kept from the original.** Word embeddings times sqrt(width) (cast to the embedding's
dtype); no scale on image tokens. Gemma RMSNorm ``x rsqrt(mean x^2 + 1e-6) (1 + w)`` in float32;
adaRMS ``(scale, shift, gate) = dense(cond).chunk(3)``, ``normed (1 + scale) + shift`` and the
residual ``x + y gate``. RoPE (theta 10000) at the cumulative count of real tokens (suffix
positions continue from the prefix's count). Attention: ``q k^T / sqrt(head_dim)`` plus an
additive mask of -2.3819763e38 (finite, so a fully padded row stays finite); LeRobot's eager
softmax is float32, here PyTorch's ``scaled_dot_product_attention`` takes the same additive mask
(its fused kernels accumulate in float32; float32 agrees with LeRobot to about 1e-6).
Time sinusoid with periods from 4e-3 to 4.0 (config ``min_period`` / ``max_period``) in float64.

**Sizes** all come from tensor shapes, except two head counts shapes cannot give: the Gemma towers
have 8 query heads (LeRobot's fused attention hard-codes ``8 * head_dim``; override with
``vlm_config={"text_config": {"num_attention_heads": n}}``), so head_dim = q_proj rows / 8 and the
KV heads = k_proj rows / head_dim; SigLIP's heads are ``vision_config.num_attention_heads`` of
``vlm_config``, else width / 72 (so400m: 1152 / 72 = 16) when that divides. ``chunk_size`` and the
time periods come from the LeRobot ``config``.

**dtype.** ``dtype=torch.bfloat16`` holds the Gemma projections, embeddings and LM heads in bf16;
the vision tower, projector, every norm (adaRMS ``dense`` included) and the action/state/time
heads stay float32, as LeRobot's ``precision="bfloat16"`` keeps them. Each tower and head casts its input
to its weights' dtype, so any mix (and autocast) runs. Outputs (``Prefix.hidden``, velocities,
actions) are float32.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = ["PiModel", "PiSizes", "Prefix"]

_PALI = "paligemma_with_expert.paligemma"
_VLM = f"{_PALI}.model.language_model"
_VISION = f"{_PALI}.model.vision_tower.vision_model"
_EMBED = f"{_VLM}.embed_tokens.weight"
_LM_HEAD = f"{_PALI}.lm_head.weight"
_EXPERT = "paligemma_with_expert.gemma_expert.model"
_EXPERT_HEAD = "paligemma_with_expert.gemma_expert.lm_head.weight"
_FLOAT32_PARTS = ("vision_tower", "multi_modal_projector", "input_layernorm", "post_attention_layernorm",
                  "model.norm")
"""Parameter-name parts LeRobot keeps in float32 whatever the precision (``model.norm`` also
matches the VLM's ``language_model.norm``); parameters outside ``paligemma_with_expert`` (the
action, state and time heads) stay float32 too."""
_MASKED = -2.3819763e38
"""The additive attention mask of openpi / LeRobot: finite, so a row with no visible key (a pad
query) yields finite garbage instead of NaN, which would leak through 0 * NaN into real rows."""
_GEMMA_HEADS = 8
_SIGLIP_HEAD_DIM = 72
_ROPE_THETA = 10000.0
_EPS = 1e-6


@dataclass(frozen=True)
class PiSizes:
    """Every size of the module tree, read from tensor shapes (see the module docstring)."""

    variant: str  #: "pi0" (state token, action-time MLP) or "pi05" (adaRMS expert, time MLP)
    vocab: int
    width: int  #: VLM width (= Prefix.hidden's last dim)
    mlp: int
    depth: int  #: layers of each tower (the towers pair up layer by layer)
    heads: int
    kv_heads: int
    head_dim: int
    expert_vocab: int
    expert_width: int
    expert_mlp: int
    vision_width: int
    vision_mlp: int
    vision_depth: int
    vision_heads: int
    channels: int
    patch: int
    image_size: int
    max_action_dim: int
    max_state_dim: int
    chunk_size: int  #: from the config
    min_period: float  #: from the config
    max_period: float  #: from the config


@dataclass
class Prefix:
    """What :meth:`PiModel.prefix` computes once per observation and every velocity reads.
    Every field has the batch first; :meth:`select` indexes them all together."""

    hidden: Tensor  #: [B, L, width] float32: the VLM's final normed states (pads hold finite garbage)
    mask: Tensor  #: [B, L] bool: real prefix tokens (camera tokens of a present camera, real words)
    keys: tuple[Tensor, ...]  #: per layer [B, kv_heads, L, head_dim], after RoPE, the VLM's dtype
    values: tuple[Tensor, ...]  #: per layer [B, kv_heads, L, head_dim]
    state: Tensor  #: [B, max_state_dim] float32, zero padded (pi0's state token; pi05 ignores it)

    def select(self, index: Tensor) -> "Prefix":
        """The rows ``index`` (a long tensor on the prefix's device, repeats allowed: ``arange(B).repeat_interleave(K)``
        gives K copies of each observation for K chains)."""
        pick = lambda t: t.index_select(0, index)  # noqa: E731
        return Prefix(pick(self.hidden), pick(self.mask), tuple(map(pick, self.keys)),
                      tuple(map(pick, self.values)), pick(self.state))


def _cast(x: Tensor, module: nn.Module) -> Tensor:
    return x.to(module.weight.dtype)


class GemmaNorm(nn.Module):
    """Gemma's RMSNorm in float32; with ``cond_width`` the adaRMS form, which also returns the gate
    of the residual it precedes (None otherwise)."""

    def __init__(self, width: int, cond_width: int | None = None) -> None:
        super().__init__()
        if cond_width is None:
            self.weight = nn.Parameter(torch.zeros(width))
        else:
            self.dense = nn.Linear(cond_width, 3 * width)

    def forward(self, x: Tensor, cond: Tensor | None = None) -> tuple[Tensor, Tensor | None]:
        xf = x.float()
        normed = xf * torch.rsqrt(xf.square().mean(-1, keepdim=True) + _EPS)
        if not hasattr(self, "dense"):
            return (normed * (1.0 + self.weight.float())).to(x.dtype), None
        if cond is None:
            raise ValueError("an adaRMS norm needs the time condition")
        scale, shift, gate = self.dense(_cast(cond, self.dense)).unsqueeze(1).chunk(3, dim=-1)
        return (normed * (1.0 + scale.float()) + shift.float()).to(x.dtype), gate.to(x.dtype)


class GemmaAttention(nn.Module):
    """The projections only: the attention itself runs across towers in :meth:`PiModel._tower`."""

    def __init__(self, width: int, heads: int, kv_heads: int, head_dim: int) -> None:
        super().__init__()
        self.heads, self.kv_heads, self.head_dim = heads, kv_heads, head_dim
        self.q_proj = nn.Linear(width, heads * head_dim, bias=False)
        self.k_proj = nn.Linear(width, kv_heads * head_dim, bias=False)
        self.v_proj = nn.Linear(width, kv_heads * head_dim, bias=False)
        self.o_proj = nn.Linear(heads * head_dim, width, bias=False)


class GemmaMLP(nn.Module):
    def __init__(self, width: int, hidden: int) -> None:
        super().__init__()
        self.gate_proj = nn.Linear(width, hidden, bias=False)
        self.up_proj = nn.Linear(width, hidden, bias=False)
        self.down_proj = nn.Linear(hidden, width, bias=False)

    def forward(self, x: Tensor) -> Tensor:
        return self.down_proj(F.gelu(self.gate_proj(x), approximate="tanh") * self.up_proj(x))


class GemmaLayer(nn.Module):
    def __init__(self, width: int, mlp: int, heads: int, kv_heads: int, head_dim: int,
                 cond_width: int | None) -> None:
        super().__init__()
        self.self_attn = GemmaAttention(width, heads, kv_heads, head_dim)
        self.mlp = GemmaMLP(width, mlp)
        self.input_layernorm = GemmaNorm(width, cond_width)
        self.post_attention_layernorm = GemmaNorm(width, cond_width)


class GemmaTower(nn.Module):
    """One Gemma stack (state-dict names as transformers' ``GemmaModel``); ``vocab`` adds
    ``embed_tokens`` (the VLM's; LeRobot drops the expert's)."""

    def __init__(self, depth: int, width: int, mlp: int, heads: int, kv_heads: int, head_dim: int,
                 cond_width: int | None = None, vocab: int | None = None) -> None:
        super().__init__()
        if vocab is not None:
            self.embed_tokens = nn.Embedding(vocab, width)
        self.layers = nn.ModuleList(GemmaLayer(width, mlp, heads, kv_heads, head_dim, cond_width)
                                    for _ in range(depth))
        self.norm = GemmaNorm(width, cond_width)

    @property
    def dtype(self) -> torch.dtype:
        """The dtype the stack computes in: its projections' (peft's LoRA layers forward ``weight``)."""
        return self.layers[0].self_attn.q_proj.weight.dtype


class SiglipAttention(nn.Module):
    def __init__(self, width: int, heads: int) -> None:
        super().__init__()
        self.heads = heads
        self.q_proj, self.k_proj, self.v_proj, self.out_proj = (nn.Linear(width, width) for _ in range(4))

    def forward(self, x: Tensor) -> Tensor:
        split = lambda t: t.view(*x.shape[:2], self.heads, -1).transpose(1, 2)  # noqa: E731
        out = F.scaled_dot_product_attention(split(self.q_proj(x)), split(self.k_proj(x)), split(self.v_proj(x)))
        return self.out_proj(out.transpose(1, 2).reshape(x.shape))


class SiglipMLP(nn.Module):
    def __init__(self, width: int, hidden: int) -> None:
        super().__init__()
        self.fc1, self.fc2 = nn.Linear(width, hidden), nn.Linear(hidden, width)

    def forward(self, x: Tensor) -> Tensor:
        return self.fc2(F.gelu(self.fc1(x), approximate="tanh"))


class SiglipLayer(nn.Module):
    def __init__(self, width: int, mlp: int, heads: int) -> None:
        super().__init__()
        self.layer_norm1 = nn.LayerNorm(width, eps=_EPS)
        self.self_attn = SiglipAttention(width, heads)
        self.layer_norm2 = nn.LayerNorm(width, eps=_EPS)
        self.mlp = SiglipMLP(width, mlp)

    def forward(self, h: Tensor) -> Tensor:
        h = h + self.self_attn(self.layer_norm1(h))
        return h + self.mlp(self.layer_norm2(h))


class SiglipVision(nn.Module):
    """PaliGemma's SigLIP tower without its pooling head (state-dict names as transformers'
    ``vision_model``): patches + learned positions, pre-norm encoder layers, a final LayerNorm.
    Written out rather than taken from transformers, whose module tree for it changed between
    versions (5.24 dropped the ``vision_model`` level the checkpoints carry)."""

    def __init__(self, s: "PiSizes") -> None:
        super().__init__()
        self.embeddings = _namespace(
            patch_embedding=nn.Conv2d(s.channels, s.vision_width, s.patch, stride=s.patch),
            position_embedding=nn.Embedding((s.image_size // s.patch) ** 2, s.vision_width))
        self.encoder = _namespace(layers=nn.ModuleList(SiglipLayer(s.vision_width, s.vision_mlp, s.vision_heads)
                                                       for _ in range(s.vision_depth)))
        self.post_layernorm = nn.LayerNorm(s.vision_width, eps=_EPS)

    def forward(self, image: Tensor) -> Tensor:
        patches = self.embeddings.patch_embedding(_cast(image, self.embeddings.patch_embedding))
        h = patches.flatten(2).transpose(1, 2) + self.embeddings.position_embedding.weight
        for layer in self.encoder.layers:
            h = layer(h)
        return self.post_layernorm(h)


def _namespace(**children: nn.Module) -> nn.Module:
    """A plain module holding ``children`` under their names (the checkpoint's key path)."""
    module = nn.Module()
    for name, child in children.items():
        setattr(module, name, child)
    return module


def _rope(x: Tensor, positions: Tensor) -> Tensor:
    """Rotary embedding of ``x`` [B, H, S, D] at ``positions`` [B, S] (rotate-half layout)."""
    dim = x.shape[-1]
    inv_freq = 1.0 / (_ROPE_THETA ** (torch.arange(0, dim, 2, device=x.device, dtype=torch.int64).float() / dim))
    angles = positions[..., None].float() * inv_freq
    angles = torch.cat([angles, angles], dim=-1)
    cos, sin = angles.cos().to(x.dtype)[:, None], angles.sin().to(x.dtype)[:, None]
    first, second = x.chunk(2, dim=-1)
    return x * cos + torch.cat([-second, first], dim=-1) * sin


def _attention_bias(allowed: Tensor) -> Tensor:
    """[B, S, L] bool (query may see key) -> the additive float32 mask [B, 1, S, L]."""
    zero = torch.zeros((), dtype=torch.float32, device=allowed.device)
    return torch.where(allowed, zero, torch.full_like(zero, _MASKED))[:, None]


def _sinusoid(t: Tensor, width: int, min_period: float, max_period: float) -> Tensor:
    """[B] -> [B, width] float32: sin then cos of t * 2 pi / period, periods geometric from
    ``min_period`` to ``max_period`` (computed in float64 where the device has it)."""
    wide = torch.float32 if t.device.type == "mps" else torch.float64
    fraction = torch.linspace(0.0, 1.0, width // 2, dtype=wide, device=t.device)
    period = min_period * (max_period / min_period) ** fraction
    angles = (1.0 / period * 2 * math.pi)[None] * t[:, None]
    return torch.cat([angles.sin(), angles.cos()], dim=1).float()


def _layer_count(shapes: Mapping[str, tuple], prefix: str) -> int:
    pattern = re.compile(re.escape(prefix) + r"\.(\d+)\.")
    found = {int(m.group(1)) for k in shapes if (m := pattern.match(k))}
    if not found:
        raise ValueError(f"missing key {prefix}.0.*: no layers")
    return max(found) + 1


def _shape(shapes: Mapping[str, tuple], key: str) -> tuple[int, ...]:
    if key not in shapes:
        raise ValueError(f"missing key {key!r}")
    return tuple(int(n) for n in shapes[key])


def _divide(total: int, by: int, key: str, what: str) -> int:
    if by <= 0 or total % by:
        raise ValueError(f"key {key!r}: {total} rows do not split into {what} of {by}")
    return total // by


def _heads_from(vlm_config: Mapping | None, part: str) -> int | None:
    value = ((vlm_config or {}).get(part) or {}).get("num_attention_heads")
    return None if value is None else int(value)


def read_sizes(shapes: Mapping[str, Sequence[int]], config: Mapping[str, Any],
               vlm_config: Mapping | None = None) -> PiSizes:
    """:class:`PiSizes` from the state dict's shapes (ValueError naming the key it misses)."""
    if "time_mlp_in.weight" in shapes or "action_time_mlp_in.weight" in shapes:
        variant = "pi05" if "time_mlp_in.weight" in shapes else "pi0"
    else:
        hint = ": strip LeRobot's 'model.' prefix" if any(k.startswith("model.") for k in shapes) else ""
        raise ValueError(f"missing key 'action_time_mlp_in.weight' (pi0) or 'time_mlp_in.weight' (pi05){hint}")
    declared = config.get("type")
    if declared in ("pi0", "pi05") and declared != variant:
        raise ValueError(f"config type {declared!r} but the state dict holds a {variant} model "
                         f"({'time_mlp_in' if variant == 'pi05' else 'action_time_mlp_in'} keys)")
    vocab, width = _shape(shapes, _LM_HEAD)
    q_key = f"{_VLM}.layers.0.self_attn.q_proj.weight"
    heads = _heads_from(vlm_config, "text_config") or _GEMMA_HEADS
    head_dim = _divide(_shape(shapes, q_key)[0], heads, q_key, "query heads")
    k_key = f"{_VLM}.layers.0.self_attn.k_proj.weight"
    kv_heads = _divide(_shape(shapes, k_key)[0], head_dim, k_key, "heads")
    expert_vocab, expert_width = _shape(shapes, _EXPERT_HEAD)
    depth = _layer_count(shapes, f"{_VLM}.layers")
    if _layer_count(shapes, f"{_EXPERT}.layers") != depth:
        raise ValueError(f"key {_EXPERT}.layers: the expert has {_layer_count(shapes, f'{_EXPERT}.layers')} layers, "
                         f"the VLM {depth} (they attend jointly layer by layer)")
    patch_key = f"{_VISION}.embeddings.patch_embedding.weight"
    vision_width, channels, patch, _ = _shape(shapes, patch_key)
    positions = _shape(shapes, f"{_VISION}.embeddings.position_embedding.weight")[0]
    side = math.isqrt(positions)
    if side * side != positions:
        raise ValueError(f"key {_VISION}.embeddings.position_embedding.weight: {positions} positions is no square grid")
    vision_heads = _heads_from(vlm_config, "vision_config")
    if vision_heads is None:
        if vision_width % _SIGLIP_HEAD_DIM:
            raise ValueError(f"key {patch_key!r}: cannot tell SigLIP's head count for width {vision_width}; pass "
                             "vlm_config={'vision_config': {'num_attention_heads': N}}")
        vision_heads = vision_width // _SIGLIP_HEAD_DIM
    action_dim = _shape(shapes, "action_in_proj.weight")[1]
    state_dim = (_shape(shapes, "state_proj.weight")[1] if variant == "pi0"
                 else int(config.get("max_state_dim", 32)))
    return PiSizes(
        variant=variant, vocab=vocab, width=width, mlp=_shape(shapes, f"{_VLM}.layers.0.mlp.gate_proj.weight")[0],
        depth=depth, heads=heads, kv_heads=kv_heads, head_dim=head_dim, expert_vocab=expert_vocab,
        expert_width=expert_width, expert_mlp=_shape(shapes, f"{_EXPERT}.layers.0.mlp.gate_proj.weight")[0],
        vision_width=vision_width, vision_mlp=_shape(shapes, f"{_VISION}.encoder.layers.0.mlp.fc1.weight")[0],
        vision_depth=_layer_count(shapes, f"{_VISION}.encoder.layers"), vision_heads=vision_heads,
        channels=channels, patch=patch, image_size=side * patch, max_action_dim=action_dim, max_state_dim=state_dim,
        chunk_size=int(config.get("chunk_size", 50)), min_period=float(config.get("min_period", 4e-3)),
        max_period=float(config.get("max_period", 4.0)))


def _check_keys(expected: Mapping[str, tuple], given: Mapping[str, Sequence[int]]) -> None:
    """One-line ValueError naming the first missing, unexpected or misshapen key."""
    for key in sorted(set(expected) | set(given)):
        if key not in given:
            raise ValueError(f"missing key {key!r} (expected shape {tuple(expected[key])})")
        if key not in expected:
            raise ValueError(f"unexpected key {key!r} (shape {tuple(given[key])})")
        if tuple(expected[key]) != tuple(int(n) for n in given[key]):
            raise ValueError(f"key {key!r}: expected shape {tuple(expected[key])}, found {tuple(given[key])}")


class PiModel(nn.Module):
    """pi0 / pi05 (see the module docstring). Build with :meth:`from_state_dict` or, on the meta
    device, :meth:`from_shapes`; ``state_dict()`` has the checkpoint's keys minus ``model.``."""

    def __init__(self, sizes: PiSizes) -> None:
        super().__init__()
        s = sizes
        self.sizes = s
        self.variant = s.variant
        self.chunk_size, self.max_action_dim, self.max_state_dim = s.chunk_size, s.max_action_dim, s.max_state_dim
        self.prefix_width, self.expert_width, self.image_size = s.width, s.expert_width, s.image_size
        gemma = dict(heads=s.heads, kv_heads=s.kv_heads, head_dim=s.head_dim)
        paligemma = _namespace(
            model=_namespace(language_model=GemmaTower(s.depth, s.width, s.mlp, vocab=s.vocab, **gemma),
                             multi_modal_projector=_namespace(linear=nn.Linear(s.vision_width, s.width)),
                             vision_tower=_namespace(vision_model=SiglipVision(s))),
            lm_head=nn.Linear(s.width, s.vocab, bias=False))
        cond = s.expert_width if s.variant == "pi05" else None
        expert = _namespace(model=GemmaTower(s.depth, s.expert_width, s.expert_mlp, cond_width=cond, **gemma),
                            lm_head=nn.Linear(s.expert_width, s.expert_vocab, bias=False))
        self.paligemma_with_expert = _namespace(paligemma=paligemma, gemma_expert=expert)
        self.action_in_proj = nn.Linear(s.max_action_dim, s.expert_width)
        self.action_out_proj = nn.Linear(s.expert_width, s.max_action_dim)
        if s.variant == "pi0":
            self.state_proj = nn.Linear(s.max_state_dim, s.expert_width)
            self.action_time_mlp_in = nn.Linear(2 * s.expert_width, s.expert_width)
            self.action_time_mlp_out = nn.Linear(s.expert_width, s.expert_width)
        else:
            self.time_mlp_in = nn.Linear(s.expert_width, s.expert_width)
            self.time_mlp_out = nn.Linear(s.expert_width, s.expert_width)

    # -- the towers (properties, so that no module is registered under two names) --
    @property
    def language_model(self) -> GemmaTower:
        return self.paligemma_with_expert.paligemma.model.language_model

    @property
    def expert(self) -> GemmaTower:
        return self.paligemma_with_expert.gemma_expert.model

    # -- building --
    @classmethod
    def from_shapes(cls, shapes: Mapping[str, Sequence[int]], config: Mapping[str, Any],
                    dtype: torch.dtype = torch.float32, *, vlm_config: Mapping | None = None) -> "PiModel":
        """The module tree for ``shapes`` (checkpoint keys minus ``model.``) on the meta device: no
        memory, no weights. ValueError (one line naming the key) when the keys or shapes do not
        form a pi0 / pi05 model. Without the VLM's ``embed_tokens`` (openpi-converted layout) it
        is tied to ``lm_head``."""
        sizes = read_sizes(shapes, config, vlm_config)
        with torch.device("meta"):
            model = cls(sizes)
        expected = {k: tuple(v.shape) for k, v in model.state_dict().items()}
        tie = _EMBED not in shapes and _LM_HEAD in shapes
        if tie:
            expected.pop(_EMBED)
        _check_keys(expected, shapes)
        for name, p in model.named_parameters():
            if name.startswith("paligemma_with_expert.") and not any(part in name for part in _FLOAT32_PARTS):
                p.data = p.data.to(dtype)
        if tie:
            model.language_model.embed_tokens.weight = model.paligemma_with_expert.paligemma.lm_head.weight
        return model

    @classmethod
    def from_state_dict(cls, state_dict: Mapping[str, Tensor], config: Mapping[str, Any], *,
                        vlm_config: Mapping | None = None, dtype: torch.dtype = torch.float32) -> "PiModel":
        """The model holding ``state_dict``'s tensors (keys without LeRobot's ``model.`` prefix;
        float32 tensors are used in place, not copied). ``config``: LeRobot's config.json as read
        (``chunk_size``, ``min_period``, ``max_period``); ``vlm_config``: optional head counts
        (module docstring)."""
        shapes = {k: tuple(v.shape) for k, v in state_dict.items()}
        model = cls.from_shapes(shapes, config, dtype, vlm_config=vlm_config)
        wanted = {name: p.dtype for name, p in model.named_parameters(remove_duplicate=False)}
        tensors = {k: v.to(wanted[k]) for k, v in state_dict.items()}
        model.load_state_dict(tensors, strict=False, assign=True)
        if _EMBED not in state_dict:
            model.language_model.embed_tokens.weight = model.paligemma_with_expert.paligemma.lm_head.weight
        return model.eval()

    # -- the forward pieces --
    def embed_image(self, image: Tensor) -> Tensor:
        """[B, C, H, W] in [-1, 1] -> image tokens [B, (H / patch)^2, width] (float32 tower)."""
        if tuple(image.shape[1:]) != (self.sizes.channels, self.image_size, self.image_size):
            raise ValueError(f"images must be [B, {self.sizes.channels}, {self.image_size}, {self.image_size}], "
                             f"got {tuple(image.shape)}")
        paligemma = self.paligemma_with_expert.paligemma.model
        feats = paligemma.vision_tower.vision_model(image)
        projector = paligemma.multi_modal_projector.linear
        return projector(_cast(feats, projector))

    def embed_tokens(self, tokens: Tensor) -> Tensor:
        embed = self.language_model.embed_tokens
        scale = torch.tensor(self.prefix_width ** 0.5, device=tokens.device).to(embed.weight.dtype)
        return embed(tokens) * scale

    def _tower(self, tower: GemmaTower, h: Tensor, positions: Tensor, allowed: Tensor, cond: Tensor | None = None,
               past: Prefix | None = None) -> tuple[Tensor, list[Tensor], list[Tensor]]:
        """Run ``h`` [B, S, W] through ``tower``; queries see keys where ``allowed`` [B, S, (L +) S],
        the keys being ``past``'s layer keys (when given) then this input's. Returns the final
        normed states and each layer's (keys, values) of this input."""
        bias = _attention_bias(allowed)
        h = h.to(tower.dtype)
        keys, values = [], []
        for i, layer in enumerate(tower.layers):
            attn = layer.self_attn
            x, gate = layer.input_layernorm(h, cond)
            split = lambda t: t.view(*x.shape[:2], -1, attn.head_dim).transpose(1, 2)  # noqa: E731
            q = _rope(split(attn.q_proj(x)), positions)
            k = _rope(split(attn.k_proj(x)), positions)
            v = split(attn.v_proj(x))
            keys.append(k)
            values.append(v)
            if past is not None:
                k = torch.cat([past.keys[i].to(k.dtype), k], dim=2)
                v = torch.cat([past.values[i].to(v.dtype), v], dim=2)
            groups = q.shape[1] // k.shape[1]
            k, v = k.repeat_interleave(groups, dim=1), v.repeat_interleave(groups, dim=1)
            out = F.scaled_dot_product_attention(q, k, v, attn_mask=bias.to(q.dtype), scale=attn.head_dim ** -0.5)
            out = out.transpose(1, 2).reshape(*x.shape[:2], -1)
            y = attn.o_proj(out)
            h = h + (y if gate is None else y * gate)
            x, gate = layer.post_attention_layernorm(h, cond)
            y = layer.mlp(x)
            h = h + (y if gate is None else y * gate)
        out, _ = tower.norm(h, cond)
        return out, keys, values

    def prefix(self, images: Sequence[Tensor], image_masks: Sequence[Tensor], tokens: Tensor, token_mask: Tensor,
               state: Tensor) -> Prefix:
        """The VLM pass over ``[camera tokens...; words]`` (differentiable). ``images``: per camera
        [B, 3, H, W] in [-1, 1] at ``image_size``; ``image_masks``: per camera [B] bool; ``tokens``,
        ``token_mask``: [B, L]; ``state``: [B, <= max_state_dim] normalised (zero padded here)."""
        if len(images) != len(image_masks) or not images:
            raise ValueError(f"need one mask per image and at least one camera, got {len(images)} images, "
                             f"{len(image_masks)} masks")
        if state.shape[-1] > self.max_state_dim:
            raise ValueError(f"state has {state.shape[-1]} dims, the model takes at most {self.max_state_dim}")
        parts, masks = [], []
        for image, mask in zip(images, image_masks):
            feats = self.embed_image(image)
            parts.append(feats.to(self.language_model.dtype))
            masks.append(mask.bool()[:, None].expand(-1, feats.shape[1]))
        parts.append(self.embed_tokens(tokens.long()))
        masks.append(token_mask.bool())
        h, mask = torch.cat(parts, 1), torch.cat(masks, 1)
        positions = mask.long().cumsum(1) - 1
        hidden, keys, values = self._tower(self.language_model, h, positions, mask[:, None, :] & mask[:, :, None])
        state = F.pad(state.float(), (0, self.max_state_dim - state.shape[-1]))
        return Prefix(hidden.float(), mask, tuple(keys), tuple(values), state)

    def velocity(self, prefix: Prefix, x_t: Tensor, t: Tensor) -> tuple[Tensor, Tensor]:
        """(v [B, C, max_action_dim] float32, the expert's final normed action states [B, C,
        expert_width] float32) at noisy actions ``x_t`` [B, C, max_action_dim] and times ``t`` [B]
        (t = 1 noise, t = 0 action). Differentiable."""
        batch, chunk = x_t.shape[:2]
        x_t = x_t.float()
        temb = _sinusoid(t.float().reshape(batch), self.expert_width, self.sizes.min_period, self.sizes.max_period)
        actions = self.action_in_proj(_cast(x_t, self.action_in_proj))
        cond = None
        if self.variant == "pi0":
            fused = torch.cat([actions, temb[:, None].expand(-1, chunk, -1).to(actions.dtype)], dim=-1)
            fused = self.action_time_mlp_out(F.silu(self.action_time_mlp_in(_cast(fused, self.action_time_mlp_in))))
            state = self.state_proj(_cast(prefix.state, self.state_proj))[:, None]
            suffix = torch.cat([state, fused.to(state.dtype)], dim=1)
            blocks = [1, 1] + [0] * (chunk - 1)  # the state token, then the action block
        else:
            cond = F.silu(self.time_mlp_out(F.silu(self.time_mlp_in(_cast(temb, self.time_mlp_in)))))
            suffix = actions
            blocks = [1] + [0] * (chunk - 1)
        block = torch.tensor(blocks, device=x_t.device).cumsum(0)
        own = (block[None, :] <= block[:, None])[None].expand(batch, -1, -1)
        allowed = torch.cat([prefix.mask[:, None, :].expand(-1, len(blocks), -1), own], dim=2)
        positions = prefix.mask.sum(1, keepdim=True) + torch.arange(len(blocks), device=x_t.device)
        out, _, _ = self._tower(self.expert, suffix, positions, allowed, cond, past=prefix)
        hidden = out[:, -chunk:].float()
        return self.action_out_proj(_cast(hidden, self.action_out_proj)).float(), hidden

    @torch.no_grad()
    def sample_actions(self, images: Sequence[Tensor], image_masks: Sequence[Tensor], tokens: Tensor,
                       token_mask: Tensor, state: Tensor, noise: Tensor, num_steps: int = 10) -> Tensor:
        """LeRobot's ``predict_action_chunk`` from ``noise`` [B, chunk, max_action_dim] (x at t = 1):
        Euler to t = 0 with dt = -1 / num_steps. Returns [B, chunk, max_action_dim] float32."""
        prefix = self.prefix(images, image_masks, tokens, token_mask, state)
        dt = -1.0 / num_steps
        x = noise.float()
        for step in range(num_steps):
            t = torch.tensor(1.0 + step * dt, dtype=torch.float32, device=x.device).expand(x.shape[0])
            x = x + dt * self.velocity(prefix, x, t)[0]
        return x

