"""``vla-tokens``: discrete action tokens from a transformers VLM (OpenVLA / OpenVLA-OFT style).

The language model reads one sequence and decodes every action dimension in ONE parallel forward
(OpenVLA-OFT's parallel decoding)::

    image patches (per camera) | instruction words (pads masked) | [proprio] | act_dim x [ACT]

``[ACT]`` is one learned embedding repeated ``act_dim`` times; the LM's rotary positions tell the
copies apart. The LM keeps its causal attention (Llava / Llama): each ``[ACT]`` sees the whole
prefix and the earlier ``[ACT]`` copies, which are constants, so the dimensions are independent
categoricals given the observation and no sampled value feeds back. ``[proprio]`` is
``proprio`` through a linear layer (one token).

**Bins.** The last ``n_bins`` ids of the vocabulary are the action bins (dvla_policy.json
``n_bins``; ``bin_order: descending`` reads them in OpenVLA's order). The logits at the ``[ACT]``
positions, restricted to those ids and divided by ``temperature``, go through a float32
log-softmax; a bin is sampled per dimension (argmax when deterministic). Bin i of n is the
interval centred on ``-1 + (2 i + 1) / n`` of [-1, 1], mapped linearly onto the checkpoint's
[action_low, action_high] per robot dimension (every action of the chunk alike). The log-prob is
the sum of the chosen bins' log-probs, the entropy the sum of the categorical entropies.

**Per step shipped.** ``extras["action_tokens"]``: the bins, int32 ``[act_dim]`` (4 * act_dim
bytes per env step). ``evaluate`` gathers them; without extras it recovers the bins from the
action itself (bin centres map back exactly).

**Value.** A small float32 MLP on the float32 mean of the prefix's last hidden states (images,
words, proprio: never the ``[ACT]`` positions, so the value depends on the observation only).

**Training.** ``lora=None``: everything trains, ``base_hash == ""``. ``lora={...}``: peft LoRA on
the LM (:func:`~.hf_backbone.apply_lora`), the VLM frozen; the ``[ACT]`` embedding, the proprio
projection and the value head train. New tensors start from a fixed seed on every host and are
float32 whatever ``dtype`` (which sets the checkpoint's weights: ``"bfloat16"`` runs the forward
under autocast; log-probs, entropies and values are float32 either way).
"""

from __future__ import annotations

from typing import Any, Mapping

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..policies import register_policy
from ..spec import ArraySpec
from .checkpoint import check_checkpoint, content_hash, executed_chunk
from .hf_backbone import HFBackbone, SampleAndAct, apply_lora, float32_head, freeze_all_but_lora, pooled, seeded

__all__ = ["TokenActionVLA"]


@register_policy("vla-tokens")
class TokenActionVLA(SampleAndAct, nn.Module):
    """Parallel-decoded action bins from a Llava-style checkpoint (see the module docstring)."""

    def __init__(self, obs: Mapping[str, Any], act_dim: int, *, checkpoint: str, lora: Mapping[str, Any] | None = None,
                 dtype: str = "float32", device: str | torch.device | None = None, temperature: float = 1.0,
                 value_hidden: int = 16) -> None:
        super().__init__()
        if not isinstance(obs, Mapping) or "rgb" not in obs:
            raise TypeError(f"vla-tokens needs structured observations with an 'rgb' image (obs_mode: rgb), "
                            f"got {obs!r}")
        info = check_checkpoint(checkpoint, "tokens")
        self.chunk = executed_chunk(info, act_dim)
        self.act_dim = int(act_dim)
        self.temperature = float(temperature)
        if self.temperature <= 0:
            raise ValueError(f"policy_kwargs.temperature: {temperature} must be > 0")
        self.backbone = HFBackbone(info, obs, dtype=dtype)
        self.n_bins = int(info.settings["n_bins"])
        vocab = int(self.backbone.vlm.get_output_embeddings().weight.shape[0])
        if not 2 <= self.n_bins < vocab:
            raise ValueError(f"{info.path}: n_bins {self.n_bins} must be in [2, vocab size {vocab})")
        order = info.settings.get("bin_order", "ascending")
        if order not in ("ascending", "descending"):
            raise ValueError(f"{info.path}: bin_order {order!r} is not 'ascending' or 'descending'")
        ids = torch.arange(vocab - self.n_bins, vocab)
        if order == "descending":
            ids = ids.flip(0)
        self.register_buffer("bin_ids", ids, persistent=False)
        self.register_buffer("centres", -1.0 + (2 * torch.arange(self.n_bins) + 1.0) / self.n_bins, persistent=False)
        self.register_buffer("low", torch.tensor(info.action_low).repeat(self.chunk), persistent=False)
        self.register_buffer("high", torch.tensor(info.action_high).repeat(self.chunk), persistent=False)
        width = self.backbone.width
        self.n_proprio = int(obs["proprio"].shape[0]) if "proprio" in obs else 0
        with seeded():  # new tensors: float32 (trained), the same on every host
            self.action_query = nn.Parameter(torch.randn(width) * 0.02)
            if self.n_proprio:
                self.proprio_in = nn.Linear(self.n_proprio, width)
            self.value_head = nn.Sequential(nn.Linear(width, value_hidden), nn.Tanh(), nn.Linear(value_hidden, 1))
        if lora is not None:
            apply_lora(self.backbone.language_model, lora, str(info.path))
            freeze_all_but_lora(self.backbone)
        frozen = any(not p.requires_grad for p in self.parameters())
        self.base_hash = content_hash(info.path) if frozen else ""
        self.extras_spec = {"action_tokens": ArraySpec((self.act_dim,), "int32", vocab=self.n_bins)}
        self.checkpoint = str(info.path)
        if device is not None:
            self.to(device)

    # --- forward ------------------------------------------------------------------------------

    def _forward(self, obs: Mapping[str, Tensor]) -> tuple[Tensor, Tensor]:
        """(bin log-probs [B, act_dim, n_bins] float32, value [B] float32)."""
        device = obs["rgb"].device
        bb = self.backbone
        with bb.forward_context(device):
            x, mask = bb.prefix(obs)
            b = x.shape[0]
            parts = [x]
            if self.n_proprio:
                parts.append(self.proprio_in(obs["proprio"].float()).to(x.dtype).unsqueeze(1))
            n_obs = sum(p.shape[1] for p in parts)
            parts.append(self.action_query.to(x.dtype).expand(b, self.act_dim, -1))
            full = torch.cat([mask, mask.new_ones(b, n_obs - mask.shape[1] + self.act_dim)], 1)
            hidden = bb.run(torch.cat(parts, 1), full)
            logits = self._bin_logits(hidden[:, n_obs:])
        with float32_head(device):
            logp = F.log_softmax(logits.float() / self.temperature, dim=-1)
            value = self.value_head(pooled(hidden[:, :n_obs], full[:, :n_obs])).squeeze(-1)
        return logp, value

    def _bin_logits(self, hidden: Tensor) -> Tensor:
        head = self.backbone.vlm.get_output_embeddings()
        if type(head) is nn.Linear:  # only the bins' rows of a plain lm_head
            bias = None if head.bias is None else head.bias.index_select(0, self.bin_ids)
            return F.linear(hidden, head.weight.index_select(0, self.bin_ids), bias)
        return head(hidden).index_select(-1, self.bin_ids)

    def _to_action(self, bins: Tensor) -> Tensor:
        return self.low + (self.centres[bins] + 1.0) * 0.5 * (self.high - self.low)

    def _to_bins(self, action: Tensor) -> Tensor:
        u = (action.float() - self.low) / (self.high - self.low).clamp(min=1e-12)
        return (u * self.n_bins).floor().long().clamp(0, self.n_bins - 1)

    # --- the policy protocol ------------------------------------------------------------------

    def _sample(self, obs: Mapping[str, Tensor], deterministic: bool,
                generator: torch.Generator | None) -> tuple[Tensor, Tensor, dict[str, Tensor], Tensor]:
        logp, value = self._forward(obs)
        if deterministic:
            bins = logp.argmax(-1)
        else:
            probs = logp.exp().reshape(-1, self.n_bins)
            bins = torch.multinomial(probs, 1, generator=generator).view(logp.shape[:2])
        logprob = logp.gather(-1, bins.unsqueeze(-1)).squeeze(-1).sum(-1)
        return self._to_action(bins), logprob, {"action_tokens": bins.to(torch.int32)}, value

    def evaluate(self, obs: Mapping[str, Tensor], action: Tensor,
                 extras: Mapping[str, Tensor] | None = None) -> tuple[Tensor, Tensor, Tensor]:
        logp, value = self._forward(obs)
        bins = extras["action_tokens"].long() if extras and "action_tokens" in extras else self._to_bins(action)
        logprob = logp.gather(-1, bins.unsqueeze(-1)).squeeze(-1).sum(-1)
        entropy = -(logp.exp() * logp).sum(-1).sum(-1)
        return logprob, entropy, value

    def value(self, obs: Mapping[str, Tensor]) -> Tensor:
        return self._forward(obs)[1]
