"""``vla-flow``: a flow-matching action expert on a transformers VLM (pi0 / SmolVLA style).

The VLM (PaliGemma in the test checkpoints, as pi0) reads images and instruction with a
bidirectional prefix; its last hidden states, projected to the expert's width, are the context.
:class:`ActionExpert` (plain torch, saved in ``action_expert.safetensors``) is a pre-norm
transformer over the chunk's action tokens (plus one ``proprio`` token when observed): self-attention,
cross-attention to the context (pads masked), MLP; each action token is
``action_in(x) + position + time_out(silu(time_in(sinusoid(t))))``; ``velocity_out`` reads the velocity.

**Time.** x_0 ~ N(0, I) is noise at t = 0, x_K the normalised action at t = 1 (rectified flow:
v ~ action - noise; pi0 runs the other way round). K = ``denoise_steps`` Euler steps,
t_k = k / K, mean mu_k = x_k + v(x_k, t_k) / K. The executed action is x_K mapped from [-1, 1]
onto [action_low, action_high] (not clipped: the env clips).

**Log-probs for RL.** A noise head (float32, on the expert's output tokens) gives
sigma_k = sigma_min + (sigma_max - sigma_min) * sigmoid(.) per action element.

* ``method="noise"`` (Flow-Noise, ReinFlow-style, the default): every step is stochastic,
  x_{k+1} = mu_k + sigma_k eps_k. The log-prob is the chain's joint density
  sum_k log N(x_{k+1}; mu_k, sigma_k) (the x_0 term, a constant of the weights, is left out);
  the entropy is the sum of those Gaussians' entropies.
* ``method="sde"`` (Flow-SDE): one step j, uniform per sample, is stochastic, the others are
  plain Euler steps; log-prob and entropy are that step's.

``deterministic=True``: x_0 = 0, no noise anywhere; the log-prob is the mean path's density.

**Per step shipped.** ``extras["chain"]``: x_0 .. x_K, float32 ``[K + 1, act_dim]``
(4 (K + 1) act_dim bytes per env step), plus for ``sde`` ``extras["denoise_index"]`` int32 [1].
``evaluate`` recomputes every step's (mu, sigma) from the chain in one batched expert pass
(B * K rows; ``sde``: B rows), so it needs the chain; its ``action`` argument (x_K mapped) is
not read.

**Value and training.** Value: small float32 MLP on the mean prefix hidden state.
``lora=None`` trains everything; ``lora={...}`` puts peft LoRA on the LM and on the expert's
attention (both name their projections q/k/v/o_proj), freezes both; the noise head, the
proprio projection and the value head train. As in ``vla-tokens``, new tensors are seeded and
float32; ``dtype="bfloat16"`` holds the VLM and the expert in bf16 and runs them under autocast,
while the chain, the means, the sigmas and every log-prob are float32.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..policies import register_policy
from ..spec import ArraySpec
from .checkpoint import EXPERT_FILE, CheckpointError, check_checkpoint, content_hash, executed_chunk
from .hf_backbone import HFBackbone, SampleAndAct, apply_lora, float32_head, freeze_all_but_lora, pooled, seeded

__all__ = ["ActionExpert", "ContextCache", "FlowVLA", "METHODS"]

METHODS = ("noise", "sde")
_HALF_LOG_2PI = 0.5 * math.log(2 * math.pi)


class _Attention(nn.Module):
    def __init__(self, width: int, heads: int) -> None:
        super().__init__()
        self.heads = heads
        self.q_proj, self.k_proj, self.v_proj, self.o_proj = (nn.Linear(width, width) for _ in range(4))

    def _split(self, t: Tensor) -> Tensor:
        return t.view(t.shape[0], -1, self.heads, t.shape[-1] // self.heads).transpose(1, 2)

    def keys_values(self, context: Tensor) -> tuple[Tensor, Tensor]:
        """Keys and values of ``context`` [N, S, width], split into heads [N, heads, S, width / heads]."""
        return self._split(self.k_proj(context)), self._split(self.v_proj(context))

    def attend(self, x: Tensor, kv: tuple[Tensor, Tensor], mask: Tensor | None = None) -> Tensor:
        n, s, w = x.shape
        out = F.scaled_dot_product_attention(self._split(self.q_proj(x)), kv[0], kv[1], attn_mask=mask)
        return self.o_proj(out.transpose(1, 2).reshape(n, s, w))

    def forward(self, x: Tensor, context: Tensor, mask: Tensor | None = None) -> Tensor:
        return self.attend(x, self.keys_values(context), mask)


class _Block(nn.Module):
    def __init__(self, width: int, heads: int, mlp: int) -> None:
        super().__init__()
        self.norm1, self.norm2, self.norm3 = (nn.LayerNorm(width) for _ in range(3))
        self.self_attn, self.cross_attn = _Attention(width, heads), _Attention(width, heads)
        self.fc1, self.fc2 = nn.Linear(width, mlp), nn.Linear(mlp, width)

    def forward(self, h: Tensor, cross_kv: tuple[Tensor, Tensor], mask: Tensor) -> Tensor:
        x = self.norm1(h)
        h = h + self.self_attn(x, x)
        h = h + self.cross_attn.attend(self.norm2(h), cross_kv, mask)
        return h + self.fc2(F.gelu(self.fc1(self.norm3(h))))


def _additive_mask(mask: Tensor, dtype: torch.dtype) -> Tensor:
    """[N, 1, 1, S] additive attention mask (0 real, -inf pad) in the attention's dtype, made once
    per call (SDPA would turn a bool mask into this at every attention). Its rows are stored padded
    to a multiple of 16 elements: CUDA's memory-efficient attention copies a mask whose strides are
    not (PyTorch's ``preprocess_mask``); the view is the first S columns."""
    n, s = mask.shape
    padded = torch.zeros(n, 1, 1, -(-s // 16) * 16, dtype=dtype, device=mask.device)
    view = padded[..., :s]
    view.masked_fill_(~mask[:, None, None, :], float("-inf"))
    return view


@dataclass(frozen=True)
class ContextCache:
    """What the expert reads of the context, the same at every denoising step of a call: each
    block's cross-attention keys and values and the additive pad mask."""

    #: per block: keys, values [N, heads, S, width / heads]
    kv: tuple[tuple[Tensor, Tensor], ...]
    #: the context's real positions [N, S] (bool)
    valid: Tensor
    #: the additive mask [N, 1, 1, S] in the attention's dtype
    mask: Tensor

    def repeat_rows(self, n: int) -> "ContextCache":
        """Every row ``n`` times in a row (``repeat_interleave``): one per denoising step."""
        kv = tuple((k.repeat_interleave(n, 0), v.repeat_interleave(n, 0)) for k, v in self.kv)
        valid = self.valid.repeat_interleave(n, 0)
        return ContextCache(kv, valid, _additive_mask(valid, self.mask.dtype))


class ActionExpert(nn.Module):
    """The velocity network: action tokens attend to themselves and to the VLM's prefix.

    A denoising call runs :meth:`cache` once on the context and :meth:`step_bias` once for its
    step times, then :meth:`tokens` per step; ``forward`` is the three in one (one step, nothing
    kept)."""

    def __init__(self, prefix_width: int, action_dim: int, max_chunk: int, *, width: int, layers: int, heads: int,
                 mlp: int) -> None:
        super().__init__()
        if width % heads or width % 2:
            raise ValueError(f"expert width {width} must be even and a multiple of heads={heads}")
        self.width = width
        self.prefix_proj = nn.Linear(prefix_width, width)
        self.context_norm = nn.LayerNorm(width)
        self.action_in = nn.Linear(action_dim, width)
        self.positions = nn.Parameter(torch.randn(max_chunk, width) * 0.02)
        self.time_in, self.time_out = nn.Linear(width, width), nn.Linear(width, width)
        self.blocks = nn.ModuleList(_Block(width, heads, mlp) for _ in range(layers))
        self.norm = nn.LayerNorm(width)
        self.velocity_out = nn.Linear(width, action_dim)

    def context(self, prefix_hidden: Tensor) -> Tensor:
        return self.context_norm(self.prefix_proj(prefix_hidden))

    def cache(self, context: Tensor, context_mask: Tensor) -> ContextCache:
        """Every block's cross-attention keys/values of ``context`` [N, S, width] and the pad mask."""
        kv = tuple(block.cross_attn.keys_values(context) for block in self.blocks)
        return ContextCache(kv, context_mask, _additive_mask(context_mask, kv[0][0].dtype) if kv else context_mask)

    def step_bias(self, t: Tensor, chunk: int, dtype: torch.dtype) -> Tensor:
        """What an action token adds to ``action_in(x)`` at times ``t`` [N]: its position plus the
        time embedding ``time_out(silu(time_in(sinusoid(t))))``, [N, chunk, width]."""
        half = self.width // 2
        freqs = torch.exp(-math.log(1000.0) * torch.arange(half, device=t.device) / half)
        angles = 100.0 * t.float().unsqueeze(-1) * freqs
        temb = self.time_out(F.silu(self.time_in(torch.cat([angles.sin(), angles.cos()], -1).to(dtype))))
        return self.positions[:chunk] + temb.unsqueeze(1)

    def tokens(self, x: Tensor, bias: Tensor, cache: ContextCache, extra: Tensor | None = None) -> Tensor:
        """Output tokens [N, C, width] for noisy actions ``x`` [N, C, action_dim]; ``bias``
        [N or 1, C, width] from :meth:`step_bias`, ``cache`` from :meth:`cache`."""
        c = x.shape[1]
        h = self.action_in(x) + bias
        if extra is not None:
            h = torch.cat([extra.to(h.dtype), h], 1)
        for block, kv in zip(self.blocks, cache.kv):
            h = block(h, kv, cache.mask)
        return self.norm(h)[:, -c:]

    def forward(self, x: Tensor, t: Tensor, context: Tensor, context_mask: Tensor,
                extra: Tensor | None = None) -> Tensor:
        """Output tokens [N, C, width] for noisy actions ``x`` [N, C, action_dim] at times ``t`` [N]."""
        return self.tokens(x, self.step_bias(t, x.shape[1], x.dtype), self.cache(context, context_mask), extra)


def _gaussian_logpdf(x: Tensor, mu: Tensor, sigma: Tensor) -> Tensor:
    return -0.5 * ((x - mu) / sigma).square() - sigma.log() - _HALF_LOG_2PI


@register_policy("vla-flow")
class FlowVLA(SampleAndAct, nn.Module):
    """Flow-matching action chunks with Flow-Noise or Flow-SDE log-probs (see the module docstring)."""

    def __init__(self, obs: Mapping[str, Any], act_dim: int, *, checkpoint: str, lora: Mapping[str, Any] | None = None,
                 dtype: str = "float32", device: str | torch.device | None = None, method: str = "noise",
                 denoise_steps: int | None = None, sigma_min: float = 0.05, sigma_max: float = 0.3,
                 value_hidden: int = 16) -> None:
        super().__init__()
        if not isinstance(obs, Mapping) or "rgb" not in obs:
            raise TypeError(f"vla-flow needs structured observations with an 'rgb' image (obs_mode: rgb), got {obs!r}")
        info = check_checkpoint(checkpoint, "flow")
        if method not in METHODS:
            raise ValueError(f"policy_kwargs.method: {method!r} is not one of {', '.join(METHODS)}")
        if not 0 < sigma_min < sigma_max:
            raise ValueError(f"policy_kwargs: need 0 < sigma_min ({sigma_min}) < sigma_max ({sigma_max})")
        self.method, self.sigma_min, self.sigma_max = method, float(sigma_min), float(sigma_max)
        self.chunk = executed_chunk(info, act_dim)
        self.act_dim, self.action_dim = int(act_dim), info.action_dim
        self.steps = int(denoise_steps if denoise_steps is not None else info.settings["denoise_steps"])
        if self.steps < 1:
            raise ValueError(f"{info.path}: denoise_steps {self.steps} must be >= 1")
        self.backbone = HFBackbone(info, obs, dtype=dtype)
        self.expert = self._load_expert(info)
        self.register_buffer("low", torch.tensor(info.action_low).repeat(self.chunk), persistent=False)
        self.register_buffer("high", torch.tensor(info.action_high).repeat(self.chunk), persistent=False)
        ew = self.expert.width
        self.n_proprio = int(obs["proprio"].shape[0]) if "proprio" in obs else 0
        with seeded():  # new tensors: float32 (trained), the same on every host
            if self.n_proprio:
                self.proprio_in = nn.Linear(self.n_proprio, ew)
            self.noise_head = nn.Linear(ew, self.action_dim)
            nn.init.normal_(self.noise_head.weight, std=0.01)
            nn.init.zeros_(self.noise_head.bias)
            self.value_head = nn.Sequential(nn.Linear(self.backbone.width, value_hidden), nn.Tanh(),
                                            nn.Linear(value_hidden, 1))
        if lora is not None:
            apply_lora(self.backbone.language_model, lora, str(info.path))
            # the expert is adapted where the targets name its layers too (the default q/k/v/o_proj)
            apply_lora(self.expert, lora, str(info.path / EXPERT_FILE), required=False)
            freeze_all_but_lora(self.backbone, self.expert)
        self.base_hash = content_hash(info.path) if any(not p.requires_grad for p in self.parameters()) else ""
        self.extras_spec = {"chain": ArraySpec((self.steps + 1, self.act_dim), "float32")}
        if method == "sde":
            self.extras_spec["denoise_index"] = ArraySpec((1,), "int32", vocab=self.steps)
        self.checkpoint = str(info.path)
        if device is not None:
            self.to(device)

    def _load_expert(self, info: Any) -> ActionExpert:
        from safetensors.torch import load_file

        sizes = info.settings["expert"]
        file = info.path / EXPERT_FILE
        try:
            with torch.device("meta"):  # no random init to overwrite (nor draws from the caller's RNG)
                expert = ActionExpert(self.backbone.width, info.action_dim, info.max_chunk,
                                      **{k: int(sizes[k]) for k in ("width", "layers", "heads", "mlp")})
            expert.load_state_dict(load_file(file), assign=True)
        except Exception as err:  # missing / extra / misshapen tensors, unreadable file: one line
            text = " ".join(str(err).split())[:300]
            raise CheckpointError(f"{file}: does not match dvla_policy.json's expert {sizes}: "
                                  f"{type(err).__name__}: {text}") from None
        return expert.to(self.backbone.dtype)

    # --- forward pieces -----------------------------------------------------------------------

    def _context(self, obs: Mapping[str, Tensor]) -> tuple[Tensor, Tensor, Tensor | None, Tensor]:
        """(expert context [B, S, ew], mask [B, S], proprio token [B, 1, ew] or None, value [B])."""
        device = obs["rgb"].device
        bb = self.backbone
        with bb.forward_context(device):
            x, mask = bb.prefix(obs)
            hidden = bb.run(x, mask)
            context = self.expert.context(hidden.to(bb.dtype))
            extra = self.proprio_in(obs["proprio"].float()).to(bb.dtype).unsqueeze(1) if self.n_proprio else None
        with float32_head(device):
            value = self.value_head(pooled(hidden, mask)).squeeze(-1)
        return context, mask, extra, value

    def _step(self, x: Tensor, bias: Tensor, cache: ContextCache, extra: Tensor | None) -> tuple[Tensor, Tensor]:
        """Float32 (mean, sigma) of x_{k+1} given x_k ``x`` [N, C, D]; ``bias`` the step's
        :meth:`ActionExpert.step_bias` rows. Runs inside the backbone's ``forward_context``: the
        one step function of ``sample`` and ``evaluate``."""
        h = self.expert.tokens(x.to(self.backbone.dtype), bias, cache, extra)
        velocity = self.expert.velocity_out(h)
        with float32_head(x.device):
            mu = x + velocity.float() / self.steps
            sigma = self.sigma_min + (self.sigma_max - self.sigma_min) * torch.sigmoid(self.noise_head(h.float()))
        return mu, sigma

    def _step_bias(self, device: torch.device) -> Tensor:
        """:meth:`ActionExpert.step_bias` of the K step times t_k = k / K, [K, C, width]."""
        t = torch.arange(self.steps, device=device) / self.steps
        return self.expert.step_bias(t, self.chunk, self.backbone.dtype)

    def _to_action(self, x: Tensor) -> Tensor:
        return self.low + (x.reshape(x.shape[0], -1) + 1.0) * 0.5 * (self.high - self.low)

    # --- the policy protocol ------------------------------------------------------------------

    def _sample(self, obs: Mapping[str, Tensor], deterministic: bool,
                generator: torch.Generator | None) -> tuple[Tensor, Tensor, dict[str, Tensor], Tensor]:
        context, mask, extra, value = self._context(obs)
        b, device, K = context.shape[0], context.device, self.steps
        shape = (b, self.chunk, self.action_dim)
        noise = lambda: torch.randn(shape, generator=generator, device=device)  # noqa: E731
        sde = self.method == "sde"
        # the draws in the order the chain uses them (x_0, sde's step, eps_0 .. eps_{K-1}): the
        # loop below then reads no generator and touches no host value
        x = torch.zeros(shape, device=device) if deterministic else noise()
        if sde and not deterministic:
            j = torch.randint(0, K, (b,), generator=generator, device=device)
        else:
            j = torch.zeros(b, dtype=torch.long, device=device)
        eps = [] if deterministic else [noise() for _ in range(K)]
        chosen = j.unsqueeze(0) == torch.arange(K, device=device).unsqueeze(1)  # [K, b]: sde's stochastic step
        stochastic = chosen.float().view(K, b, 1, 1)
        chain, logprob = [x], torch.zeros(b, device=device)
        with self.backbone.forward_context(device):
            cache, bias = self.expert.cache(context, mask), self._step_bias(device)
            for k in range(K):
                mu, sigma = self._step(x, bias[k], cache, extra)
                if deterministic:
                    x = mu
                elif sde:
                    x = mu + sigma * eps[k] * stochastic[k]
                else:
                    x = mu + sigma * eps[k]
                lp = _gaussian_logpdf(x, mu, sigma).sum((1, 2))
                logprob += torch.where(chosen[k], lp, 0.0) if sde else lp
                chain.append(x)
        extras = {"chain": torch.stack(chain, 1).reshape(b, K + 1, self.act_dim)}
        if sde:
            extras["denoise_index"] = j.to(torch.int32).view(b, 1)
        return self._to_action(x), logprob, extras, value

    def evaluate(self, obs: Mapping[str, Tensor], action: Tensor,
                 extras: Mapping[str, Tensor] | None = None) -> tuple[Tensor, Tensor, Tensor]:
        if not extras or "chain" not in extras:
            raise ValueError("vla-flow: evaluate needs extras['chain'] (the denoising chain sample() returned)")
        context, mask, extra, value = self._context(obs)
        b, k_steps, device = context.shape[0], self.steps, context.device
        chain = extras["chain"].float().view(b, k_steps + 1, self.chunk, self.action_dim)
        with self.backbone.forward_context(device):
            cache, bias = self.expert.cache(context, mask), self._step_bias(device)
            if self.method == "noise":  # every step at once: B * K rows, each with its sample's context
                k = torch.arange(k_steps, device=device).repeat(b)
                x, target = chain[:, :-1].flatten(0, 1), chain[:, 1:].flatten(0, 1)
                rep_extra = None if extra is None else extra.repeat_interleave(k_steps, 0)
                mu, sigma = self._step(x, bias[k], cache.repeat_rows(k_steps), rep_extra)
            else:
                k = extras["denoise_index"].long().view(b)
                rows = torch.arange(b, device=device)
                x, target = chain[rows, k], chain[rows, k + 1]
                mu, sigma = self._step(x, bias[k], cache, extra)
        logprob = _gaussian_logpdf(target, mu, sigma).view(b, -1).sum(-1)
        entropy = (0.5 + _HALF_LOG_2PI + sigma.log()).view(b, -1).sum(-1)
        return logprob, entropy, value

    def value(self, obs: Mapping[str, Tensor]) -> Tensor:
        return self._context(obs)[3]
