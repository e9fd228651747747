"""``openvla``, ``openvla-oft``: OpenVLA and OpenVLA-OFT checkpoints (the Prismatic Hugging Face
layout) as RL policies, on dvla's own model (:mod:`.openvla`) and processor
(:mod:`.openvla_processing`); directories are checked and read by :mod:`.openvla_format`.

**Observations.** ``rgb`` [B, H, W, 3 * cameras]: ``policy_kwargs.cameras`` lists the env camera
indices the checkpoint's images come from (OpenVLA: one; OFT on LIBERO: primary, then wrist;
default the first ones in order), resized and normalised as PrismaticImageProcessor does.
``tokens``: the instruction in ids of the checkpoint's tokenizer (the env tokenises with it); the
policy decodes them into OpenVLA's prompt. OFT: ``proprio[:, policy_kwargs.state]`` (default the
first ``proprio_dim``), normalised with the chosen dataset's statistics (``policy_kwargs.dataset``).

**openvla: the token head, as trained.** One decision is one action of ``action_dim`` (7) tokens,
decoded one after the other with a KV cache; each is sampled from the softmax (at
``temperature``) over the 256 action-bin ids only, and the log-prob is the sum of the 7 tokens'
log-softmax over those bins. ``extras["action_tokens"]`` int32 [7] ships them; ``evaluate`` runs one
teacher-forced causal pass over prompt + tokens. ``deterministic``: the argmax over the bins
(upstream's greedy decoding whenever the argmax is an action id, which the references check).

**openvla-oft: a Gaussian around the L1 head.** OFT's head regresses a whole chunk in one
bidirectional pass and has no density, so RL needs a stochastic head: the executed E = ``act_dim /
action_dim`` actions are drawn from N(L1 regression, exp(log_std)^2) per dimension in the
normalised space, with a learned state-independent ``log_std`` (``init_log_std``): the mean stays
exactly what the fine-tune regresses (deterministic acting equals upstream's ``predict_action``), the
log-prob is exact and cheap, and the chunk stays one pass (a discrete-token variant would need a
token head OFT does not have). ``extras["normalized"]`` float32 [E, action_dim] ships the sample.

Actions are un-normalised with the dataset's q01/q99 (the gripper dimension as the mask says).
LoRA (peft) goes on the language model's attention projections; the value head (small float32 MLP
on the hidden state that reads the first action) and OFT's ``log_std`` always train; OFT's action
head and proprio projector stay frozen unless ``train_heads: true``.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar, Mapping, Sequence

import torch
from torch import Tensor, nn

from ..policies import register_policy
from ..spec import ArraySpec
from .checkpoint import CheckpointError
from .hf_backbone import SampleAndAct, apply_lora, float32_head, freeze_all_but_lora, seeded, torch_dtype
from .openvla_format import check_openvla, content_hash, read_oft_components, read_state_dict
from .tokenizer import decode_instructions
from .openvla_processing import encode_prompts, load_tokenizer, normalize_proprio, pixel_values, unnormalize_actions

__all__ = ["OpenVLAPolicy", "OpenVLAOFTPolicy", "LORA_TARGETS"]

LORA_TARGETS = r".*language_model.*\.(q_proj|k_proj|v_proj|o_proj)"
"""Default LoRA targets: the Llama decoder's attention projections (never the vision towers)."""
_HALF_LOG_2PI = 0.5 * math.log(2 * math.pi)


class _OpenVLABase(SampleAndAct, nn.Module):
    family: ClassVar[str] = ""

    def __init__(self, obs: Mapping[str, Any], act_dim: int, *, checkpoint: str, dataset: str | None = None,
                 chunk_size: int | None = None, cameras: Sequence[int] | None = None, lora: Mapping[str, Any] | None = None,
                 dtype: str = "float32", device: str | torch.device | None = None, value_hidden: int = 16) -> None:
        super().__init__()
        if not isinstance(obs, Mapping) or "rgb" not in obs:
            raise TypeError(f"{self.family} needs structured observations with an 'rgb' image (obs_mode: rgb), got {obs!r}")
        ck = check_openvla(checkpoint, self.family, dataset=dataset, chunk_size=chunk_size)
        self.ck, self.checkpoint = ck, str(ck.path)
        self.dtype = torch_dtype(dtype, ck.path)
        from .openvla import OpenVLAModel

        try:
            self.model = OpenVLAModel.from_state_dict(read_state_dict(ck), ck.config, dtype=self.dtype).eval()
        except (ValueError, KeyError, RuntimeError) as err:
            raise CheckpointError(f"{ck.path}: does not hold the model its config.json says: "
                                  f"{' '.join(str(err).split())[:300]}") from None
        self.tokenizer = load_tokenizer(ck)
        self._texts: dict[bytes, str] = {}
        n_env = int(obs["rgb"].shape[-1]) // 3
        self.cameras = list(range(ck.num_images)) if cameras is None else [int(c) for c in cameras]
        if len(self.cameras) != ck.num_images or not all(0 <= c < n_env for c in self.cameras):
            raise ValueError(f"policy_kwargs.cameras: {cameras!r} must list {ck.num_images} env camera index(es) in "
                             f"0..{n_env - 1} ({ck.path} takes {ck.num_images} image(s))")
        with seeded():
            self.value_head = nn.Sequential(nn.Linear(self.model.width, value_hidden), nn.Tanh(),
                                            nn.Linear(value_hidden, 1))
        self._lora_scaling = 0.0
        if lora is not None:
            from .published import lora_scaling

            lora = {"target_modules": LORA_TARGETS, **dict(lora)}
            self._lora_scaling = lora_scaling(lora)
            apply_lora(self.model, lora, str(ck.path))
            freeze_all_but_lora(self.model)

    def _finish(self, device: str | torch.device | None) -> None:
        self.base_hash = content_hash(self.ck) if any(not p.requires_grad for p in self.parameters()) else ""
        if device is not None:
            self.to(device)

    def _autocast(self, device: torch.device) -> Any:
        return torch.autocast(device_type=device.type, dtype=self.dtype, enabled=self.dtype != torch.float32)

    def _prompt(self, obs: Mapping[str, Tensor]) -> tuple[Tensor, Tensor, Tensor]:
        """(pixel values, input ids, attention mask) on the observations' device."""
        rgb = obs["rgb"]
        device = rgb.device
        images = [rgb[..., 3 * c: 3 * c + 3].cpu() for c in self.cameras]
        pv = pixel_values(images if len(images) > 1 else images[0], self.ck).to(device)
        texts = decode_instructions(self.tokenizer, obs["tokens"], self._texts)
        ids, mask = encode_prompts(self.tokenizer, texts)
        return pv, ids.to(device), mask.to(device)

    def base_state_dict(self) -> dict[str, Tensor]:
        """The model's tensors under the checkpoint's names, LoRA merged (what ``dvla export`` writes)."""
        from .published import merge_trained

        state = self.model.state_dict()
        base = {k.replace(".base_layer.", "."): v for k, v in state.items() if ".lora_" not in k}
        return merge_trained(base, {f"model.{k}": v for k, v in state.items() if ".lora_" in k}, self._lora_scaling)


@register_policy("openvla")
class OpenVLAPolicy(_OpenVLABase):
    """OpenVLA's 256-bin token head with sampled tokens (module docstring)."""

    family = "openvla"

    def __init__(self, obs: Mapping[str, Any], act_dim: int, *, temperature: float = 1.0, **kwargs: Any) -> None:
        device = kwargs.pop("device", None)
        super().__init__(obs, act_dim, **kwargs)
        if int(act_dim) != self.ck.action_dim:
            raise ValueError(f"{self.ck.path}: OpenVLA acts one action of {self.ck.action_dim} dims per decision, "
                             f"act_dim is {act_dim} (task.action_chunk 1 and a control mode of {self.ck.action_dim} dims)")
        if not temperature > 0:
            raise ValueError(f"policy_kwargs.temperature: {temperature} must be > 0")
        self.temperature, self.act_dim = float(temperature), int(act_dim)
        self.first_bin = self.ck.tokenizer_vocab_size - self.ck.n_action_bins
        self.extras_spec = {"action_tokens": ArraySpec((self.act_dim,), "int32", vocab=self.model.vocab_size)}
        self._finish(device)

    def _bins(self, logits: Tensor) -> Tensor:
        return (logits[..., self.first_bin: self.ck.tokenizer_vocab_size].float() / self.temperature).log_softmax(-1)

    def _to_action(self, tokens: Tensor) -> Tensor:
        from .openvla_processing import tokens_to_normalized

        return unnormalize_actions(tokens_to_normalized(tokens, self.ck), self.ck).float()

    @torch.no_grad()
    def sample(self, obs: Mapping[str, Tensor], deterministic: bool = False,
               generator: torch.Generator | None = None) -> tuple[Tensor, Tensor, dict[str, Tensor]]:
        pv, ids, mask = self._prompt(obs)
        logprob = torch.zeros(ids.shape[0], device=ids.device)

        def choose(logits: Tensor) -> Tensor:
            nonlocal logprob
            lp = self._bins(logits)
            pick = lp.argmax(-1) if deterministic else torch.multinomial(lp.exp(), 1, generator=generator)[:, 0]
            logprob = logprob + lp.gather(-1, pick[:, None])[:, 0]
            return pick + self.first_bin

        with self._autocast(ids.device):
            tokens = self.model.generate_action_tokens(pv, ids, mask, n=self.act_dim, choose=choose)
        return self._to_action(tokens), logprob, {"action_tokens": tokens.to(torch.int32)}

    def _sample(self, obs: Mapping[str, Tensor], deterministic: bool,
                generator: torch.Generator | None) -> tuple[Tensor, Tensor, dict[str, Tensor], Tensor]:
        action, logprob, extras = self.sample(obs, deterministic, generator)
        return action, logprob, extras, self.value(obs)

    def _evaluate(self, obs: Mapping[str, Tensor], tokens: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        from .openvla import _append

        pv, ids, mask = self._prompt(obs)
        seq, seq_mask, columns = _append(ids, mask, tokens.long(), self.model.sizes.pad_token_id)
        with self._autocast(ids.device):
            hidden = self.model.hidden(pv, seq, seq_mask)
            rows = columns + (hidden.shape[1] - seq.shape[1]) - 1
            states = hidden.gather(1, rows[..., None].expand(-1, -1, hidden.shape[-1]))
            lp = self._bins(self.model.lm_logits(states))
        with float32_head(ids.device):
            value = self.value_head(states[:, 0].float()).squeeze(-1)
        return lp, value, tokens.long() - self.first_bin

    def evaluate(self, obs: Mapping[str, Tensor], action: Tensor,
                 extras: Mapping[str, Tensor] | None = None) -> tuple[Tensor, Tensor, Tensor]:
        if not extras or "action_tokens" not in extras:
            raise ValueError("openvla: evaluate needs extras['action_tokens'] (the tokens sample() returned)")
        lp, value, index = self._evaluate(obs, extras["action_tokens"])
        logprob = lp.gather(-1, index[..., None].clamp(0, lp.shape[-1] - 1))[..., 0].sum(-1)
        entropy = -(lp.exp() * lp).sum(-1).sum(-1)
        return logprob, entropy, value

    @torch.no_grad()
    def value(self, obs: Mapping[str, Tensor]) -> Tensor:
        pv, ids, mask = self._prompt(obs)
        with self._autocast(ids.device):
            hidden = self.model.hidden(pv, ids, mask)
        last = hidden[torch.arange(ids.shape[0], device=ids.device), hidden.shape[1] - ids.shape[1] + mask.sum(1) - 1]
        with float32_head(ids.device):
            return self.value_head(last.float()).squeeze(-1)


@register_policy("openvla-oft")
class OpenVLAOFTPolicy(_OpenVLABase):
    """OpenVLA-OFT's L1 chunk with a learned Gaussian around it (module docstring)."""

    family = "openvla-oft"

    def __init__(self, obs: Mapping[str, Any], act_dim: int, *, state: Sequence[int] | None = None,
                 init_log_std: float = -2.0, train_heads: bool = False, **kwargs: Any) -> None:
        device = kwargs.pop("device", None)
        super().__init__(obs, act_dim, **kwargs)
        ck = self.ck
        from .openvla import OFTHeads

        comps = read_oft_components(ck)
        try:
            self.heads = OFTHeads.from_state_dicts(comps["action_head"], comps.get("proprio_projector"),
                                                   chunk_size=ck.chunk_size, dtype=self.dtype)
        except (ValueError, KeyError, RuntimeError) as err:
            raise CheckpointError(f"{ck.path}: OFT heads unusable: {' '.join(str(err).split())[:300]}") from None
        self.heads.requires_grad_(bool(train_heads))
        act_dim = int(act_dim)
        if act_dim % ck.action_dim or not 0 < act_dim // ck.action_dim <= ck.chunk_size:
            raise ValueError(f"{ck.path}: act_dim {act_dim} must be E x {ck.action_dim} with 1 <= E <= the chunk's "
                             f"{ck.chunk_size} actions (task.action_chunk E, a control mode of {ck.action_dim} dims)")
        self.act_dim, self.executed = act_dim, act_dim // ck.action_dim
        n_proprio = int(obs["proprio"].shape[0]) if "proprio" in obs else 0
        need = ck.proprio_dim or 0
        self.state_index = list(range(need)) if state is None else [int(i) for i in state]
        if len(self.state_index) != need or not all(0 <= i < n_proprio for i in self.state_index):
            raise ValueError(f"policy_kwargs.state: {state!r} must be {need} proprio indices in 0..{n_proprio - 1} "
                             f"({ck.path} takes a proprio of {need})")
        self.log_std = nn.Parameter(torch.full((ck.action_dim,), float(init_log_std)))
        self.extras_spec = {"normalized": ArraySpec((self.executed, ck.action_dim), "float32")}
        self._finish(device)

    def _mean(self, obs: Mapping[str, Tensor]) -> tuple[Tensor, Tensor]:
        pv, ids, mask = self._prompt(obs)
        proprio = None
        if self.state_index:
            proprio = normalize_proprio(obs["proprio"].float()[:, self.state_index], self.ck).float()
        with self._autocast(ids.device):
            states = self.heads.action_states(self.model, pv, ids, mask, proprio)
            mean = self.heads.actions_from_states(states)[:, : self.executed]
        with float32_head(ids.device):
            value = self.value_head(states[:, 0].float()).squeeze(-1)
        return mean.float(), value

    def _logprob(self, x: Tensor, mean: Tensor) -> tuple[Tensor, Tensor]:
        std = self.log_std.exp()
        lp = (-0.5 * ((x - mean) / std).square() - self.log_std - _HALF_LOG_2PI).flatten(1).sum(-1)
        entropy = (0.5 + _HALF_LOG_2PI + self.log_std).sum() * self.executed
        return lp, entropy.expand_as(lp)

    def _sample(self, obs: Mapping[str, Tensor], deterministic: bool,
                generator: torch.Generator | None) -> tuple[Tensor, Tensor, dict[str, Tensor], Tensor]:
        mean, value = self._mean(obs)
        x = mean if deterministic else mean + self.log_std.exp() * torch.randn(mean.shape, generator=generator,
                                                                                device=mean.device)
        logprob, _ = self._logprob(x, mean)
        action = unnormalize_actions(x, self.ck).float().reshape(x.shape[0], -1)
        return action, logprob, {"normalized": x}, value

    def evaluate(self, obs: Mapping[str, Tensor], action: Tensor,
                 extras: Mapping[str, Tensor] | None = None) -> tuple[Tensor, Tensor, Tensor]:
        if not extras or "normalized" not in extras:
            raise ValueError("openvla-oft: evaluate needs extras['normalized'] (the sample() returned)")
        mean, value = self._mean(obs)
        logprob, entropy = self._logprob(extras["normalized"].float(), mean)
        return logprob, entropy, value

    def value(self, obs: Mapping[str, Tensor]) -> Tensor:
        return self._mean(obs)[1]

    @torch.no_grad()
    def predict_chunk(self, obs: Mapping[str, Tensor]) -> Tensor:
        """Upstream ``predict_action``: the whole un-normalised chunk [B, chunk, action_dim]."""
        pv, ids, mask = self._prompt(obs)
        proprio = normalize_proprio(obs["proprio"].float()[:, self.state_index], self.ck).float() if self.state_index else None
        with self._autocast(ids.device):
            x = self.heads.predict_chunk(self.model, pv, ids, mask, proprio)
        return unnormalize_actions(x.float(), self.ck).float()
