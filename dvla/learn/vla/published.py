"""``pi0``, ``pi05``, ``smolvla``: LeRobot's published flow-matching VLAs as RL policies.

The checkpoint is a LeRobot policy directory (or, for pi0, an openpi-converted one; or a Hugging
Face repo id found in the local cache), checked and read by :mod:`.lerobot_format`; the model is
dvla's own implementation (:mod:`.pi`, :mod:`.smolvla`), the same numbers as LeRobot's for the same
processed inputs and noise; :mod:`.lerobot_processing` reproduces LeRobot's processors (image
resize-with-pad, normalisation with the checkpoint's statistics, each family's prompt).

**Observations.** ``rgb`` [B, H, W, 3 * cameras] uint8: the env's camera ``i`` feeds the
checkpoint camera that ``policy_kwargs.cameras`` maps to ``i`` (default: the checkpoint's cameras
in ``config.json`` order take the env's cameras in order); a checkpoint camera without an env camera
is an all -1 image with mask False, as LeRobot sends a missing camera. ``proprio`` [B, P]: the
checkpoint's state is ``proprio[:, policy_kwargs.state]`` (default the first ``state_dim`` entries),
normalised with its statistics. ``tokens``: the instruction in ids of the checkpoint's tokenizer
(the env tokenises with it, docs/policies.md); the policy decodes them and builds the family's
prompt (pi05's holds the discretised state, so it is built per step).

**Actions.** The model denoises a chunk of ``chunk_size`` x ``max_action_dim`` from noise at t = 1 to
actions at t = 0 (``num_steps`` Euler steps, x <- x - v / K). The env executes the first E =
``act_dim / action_dim`` positions (``task.action_chunk``) of the first ``action_dim`` dimensions,
un-normalised with the checkpoint's statistics: one decision, one policy version, so a weight swap
can never land inside an executed chunk (the rollout installs weights between decisions only).

**Log-probs (Flow-Noise over the executed part).** Only the executed components are stochastic:
x_{k+1}[e, a] = mu_k[e, a] + sigma_k[e, a] eps, every other component follows the plain Euler step;
sigma_k = sigma_min + (sigma_max - sigma_min) sigmoid(noise_head(h_k)) from the expert's hidden
state h_k. The log-prob is sum_k log N(x_{k+1}[e, a]; mu_k, sigma_k) given x_0. Each step ships
``x0`` float32 [chunk_size, max_action_dim] (the start noise) and ``chain`` float32 [K, E, action_dim]
(the executed components of x_1 .. x_K): ``evaluate`` replays the K steps from them under the
current weights (the unexecuted components follow the current weights too), one function for both,
so the learner's log-prob equals the rollout's for the same weights. ``deterministic=True``: x_0 = 0,
no noise; the log-prob is the mean path's density.

**Training.** ``lora=None`` trains every tensor of the model; ``lora={...}`` puts peft LoRA on the
language model's and the expert's attention projections (``target_modules`` overrides, as a
regex or name suffixes), freezes the rest; the noise head and the value head (a small float32 MLP
on the mean of the prefix's hidden states; ``algorithm: grpo`` ignores it) always train.
``dtype: bfloat16`` holds the model in bf16 and runs it under autocast; chain, sigmas and log-probs
stay float32.
"""

from __future__ import annotations

import json
import re
from typing import Any, ClassVar, Mapping, Sequence

import torch
from torch import Tensor, nn

from ..policies import register_policy
from ..spec import ArraySpec
from .checkpoint import CheckpointError
from .hf_backbone import SampleAndAct, apply_lora, float32_head, freeze_all_but_lora, pooled, seeded, torch_dtype
from .lerobot_format import LeRobotCheckpoint, check_lerobot, content_hash, read_state_dict
from .tokenizer import decode_instructions
from .lerobot_processing import Normalizer, Prompter, load_tokenizer, model_images, pad_to

__all__ = ["PublishedFlowPolicy", "Pi0Policy", "Pi05Policy", "SmolVLAPolicy", "LORA_DEFAULTS", "gaussian_logpdf",
           "lora_scaling", "merge_trained"]

_HALF_LOG_2PI = 0.5 * torch.log(torch.tensor(2 * torch.pi)).item()

LORA_DEFAULTS = {
    # the language model's and the action expert's attention projections (never the vision tower's)
    "pi": r".*(language_model|gemma_expert).*\.(q_proj|k_proj|v_proj|o_proj)",
    "smolvla": r".*(text_model|lm_expert).*\.(q_proj|k_proj|v_proj|o_proj)",
}


def gaussian_logpdf(x: Tensor, mu: Tensor, sigma: Tensor) -> Tensor:
    return -0.5 * ((x - mu) / sigma).square() - sigma.log() - _HALF_LOG_2PI


def _camera_map(ck: LeRobotCheckpoint, cameras: Mapping[str, int] | None, n_env: int) -> dict[str, int]:
    """Checkpoint camera name -> env camera index (names with or without ``observation.images.``)."""
    short = {name.removeprefix("observation.images."): name for name in ck.cameras}
    if cameras is None:
        return {name: i for i, name in enumerate(ck.cameras[:n_env])}
    if not isinstance(cameras, Mapping):
        raise ValueError(f"policy_kwargs.cameras: expected a mapping checkpoint camera -> env camera index, got {cameras!r}")
    out: dict[str, int] = {}
    for key, index in cameras.items():
        name = short.get(str(key), str(key))
        if name not in ck.cameras:
            raise ValueError(f"policy_kwargs.cameras: {key!r} is not a camera of {ck.path} "
                             f"(it has {', '.join(short) or 'none'})")
        if not isinstance(index, int) or isinstance(index, bool) or not 0 <= index < n_env:
            raise ValueError(f"policy_kwargs.cameras.{key}: {index!r} is not an env camera index 0..{n_env - 1}")
        out[name] = index
    return out


class PublishedFlowPolicy(SampleAndAct, nn.Module):
    """A LeRobot flow-matching VLA with Flow-Noise log-probs over its executed actions (module docstring)."""

    family: ClassVar[str] = ""

    def __init__(self, obs: Mapping[str, Any], act_dim: int, *, checkpoint: str, tokenizer: str | None = None,
                 cameras: Mapping[str, int] | None = None, state: Sequence[int] | None = None,
                 lora: Mapping[str, Any] | None = None, dtype: str = "float32", device: str | torch.device | None = None,
                 denoise_steps: int | None = None, sigma_min: float = 0.02, sigma_max: float = 0.2,
                 value_hidden: int = 16, vision_heads: int | None = None) -> None:
        super().__init__()
        self.vision_heads = vision_heads
        if not isinstance(obs, Mapping) or "rgb" not in obs:
            raise TypeError(f"{self.family} needs structured observations with an 'rgb' image (obs_mode: rgb), got {obs!r}")
        if not 0 < sigma_min < sigma_max:
            raise ValueError(f"policy_kwargs: need 0 < sigma_min ({sigma_min}) < sigma_max ({sigma_max})")
        ck = check_lerobot(checkpoint, self.family, tokenizer=tokenizer)
        self.ck = ck
        self.checkpoint = str(ck.path)
        act_dim = int(act_dim)
        if act_dim < 1 or act_dim % ck.action_dim:
            raise ValueError(f"{ck.path}: act_dim {act_dim} is not a multiple of the checkpoint's action dimension "
                             f"{ck.action_dim} (config.json output_features.action): choose the env's control mode "
                             "with as many action dimensions")
        self.act_dim, self.action_dim = act_dim, ck.action_dim
        self.executed = act_dim // ck.action_dim
        if self.executed > ck.chunk_size:
            raise ValueError(f"{ck.path}: task.action_chunk {self.executed} is more than the checkpoint's chunk_size "
                             f"{ck.chunk_size}")
        self.steps = int(denoise_steps if denoise_steps is not None else ck.num_steps)
        if self.steps < 1:
            raise ValueError(f"policy_kwargs.denoise_steps: {self.steps} must be >= 1")
        self.sigma_min, self.sigma_max = float(sigma_min), float(sigma_max)
        self.dtype = torch_dtype(dtype, ck.path)
        self.model = self._load_model(ck)
        self.normalizer = Normalizer(ck)
        self.tokenizer = load_tokenizer(ck)
        self.prompter = Prompter(ck, self.tokenizer)
        self._texts: dict[bytes, str] = {}
        n_env_cams = int(obs["rgb"].shape[-1]) // 3
        self.cameras = _camera_map(ck, cameras, n_env_cams)
        n_proprio = int(obs["proprio"].shape[0]) if "proprio" in obs else 0
        self.state_index = self._state_index(ck, state, n_proprio)
        m = self.model
        with seeded():  # new tensors: float32 (trained), the same on every host
            self.noise_head = nn.Linear(m.expert_width, m.max_action_dim)
            nn.init.normal_(self.noise_head.weight, std=0.01)
            nn.init.zeros_(self.noise_head.bias)
            self.value_head = nn.Sequential(nn.Linear(m.prefix_width, value_hidden), nn.Tanh(), nn.Linear(value_hidden, 1))
        self._lora_scaling = lora_scaling(lora)
        if lora is not None:
            lora = dict(lora)
            lora.setdefault("target_modules", LORA_DEFAULTS["smolvla" if self.family == "smolvla" else "pi"])
            apply_lora(self.model, lora, str(ck.path))
            freeze_all_but_lora(self.model)
        self.base_hash = content_hash(ck) if any(not p.requires_grad for p in self.parameters()) else ""
        self.extras_spec = {"x0": ArraySpec((m.chunk_size, m.max_action_dim), "float32"),
                            "chain": ArraySpec((self.steps, self.executed, self.action_dim), "float32")}
        if device is not None:
            self.to(device)

    def _load_model(self, ck: LeRobotCheckpoint) -> nn.Module:
        raise NotImplementedError

    @staticmethod
    def _state_index(ck: LeRobotCheckpoint, state: Sequence[int] | None, n_proprio: int) -> list[int]:
        if state is None:
            if ck.state_dim > n_proprio:
                raise ValueError(f"{ck.path}: the checkpoint's state has {ck.state_dim} dimensions, the env's proprio "
                                 f"{n_proprio}: set policy_kwargs.state to the proprio indices to feed it")
            return list(range(ck.state_dim))
        index = list(state)
        if len(index) != ck.state_dim or not all(isinstance(i, int) and 0 <= i < n_proprio for i in index):
            raise ValueError(f"policy_kwargs.state: {state!r} must be {ck.state_dim} proprio indices in 0..{n_proprio - 1} "
                             f"({ck.path} has a state of {ck.state_dim})")
        return index

    # --- observations -> the model's inputs -----------------------------------------------------

    def _inputs(self, obs: Mapping[str, Tensor]) -> tuple[list[Tensor], list[Tensor], Tensor, Tensor, Tensor]:
        rgb = obs["rgb"]
        b, device = rgb.shape[0], rgb.device
        chw = rgb.permute(0, 3, 1, 2)
        images = {name: chw[:, 3 * i: 3 * i + 3] for name, i in self.cameras.items()}
        imgs, masks = model_images(images, self.ck)
        if self.state_index:
            raw = obs["proprio"].float()[:, self.state_index]
        else:
            raw = torch.zeros(b, 0, device=device)
        state = self.normalizer.normalize_state(raw) if self.state_index else raw
        texts = decode_instructions(self.tokenizer, obs["tokens"], self._texts) if "tokens" in obs else [""] * b
        tokens, token_mask = self.prompter.encode(texts, state)
        return imgs, masks, tokens.to(device), token_mask.to(device), pad_to(state, self.model.max_state_dim)

    def _prefix(self, obs: Mapping[str, Tensor]) -> tuple[Any, Tensor]:
        imgs, masks, tokens, token_mask, state = self._inputs(obs)
        device = tokens.device
        with self._autocast(device):
            prefix = self.model.prefix(imgs, masks, tokens, token_mask, state)
        with float32_head(device):
            value = self.value_head(pooled(prefix.hidden, prefix.mask)).squeeze(-1)
        return prefix, value

    def _autocast(self, device: torch.device) -> Any:
        return torch.autocast(device_type=device.type, dtype=self.dtype, enabled=self.dtype != torch.float32)

    # --- the chain ------------------------------------------------------------------------------

    def _chain(self, prefix: Any, x0: Tensor, chain: Tensor | None, deterministic: bool,
               generator: torch.Generator | None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Denoise from ``x0``: sampling (``chain`` None) or replaying a given executed chain.
        Returns (executed x_K [B, E, A], chain [B, K, E, A], logprob [B], entropy [B])."""
        e, a, k_steps = self.executed, self.action_dim, self.steps
        b, device = x0.shape[0], x0.device
        x = x0
        dt = -1.0 / k_steps
        links, logprob, entropy = [], torch.zeros(b, device=device), torch.zeros(b, device=device)
        for k in range(k_steps):
            t = torch.full((b,), 1.0 + k * dt, device=device)
            with self._autocast(device):
                v, h = self.model.velocity(prefix, x, t)
            with float32_head(device):
                mu = x + dt * v.float()
                sigma = self.sigma_min + (self.sigma_max - self.sigma_min) * torch.sigmoid(
                    self.noise_head(h[:, :e].float())[..., :a])
            mu_e = mu[:, :e, :a]
            if chain is not None:
                nxt = chain[:, k].float()
            elif deterministic:
                nxt = mu_e
            else:
                nxt = mu_e + sigma * torch.randn(mu_e.shape, generator=generator, device=device)
            logprob = logprob + gaussian_logpdf(nxt, mu_e, sigma).flatten(1).sum(-1)
            entropy = entropy + (0.5 + _HALF_LOG_2PI + sigma.log()).flatten(1).sum(-1)
            links.append(nxt)
            x = torch.cat([torch.cat([nxt, mu[:, :e, a:]], -1), mu[:, e:]], 1)
        return links[-1], torch.stack(links, 1), logprob, entropy

    def _to_action(self, x: Tensor) -> Tensor:
        return self.normalizer.unnormalize_actions(x).reshape(x.shape[0], -1).float()

    # --- the policy protocol ----------------------------------------------------------------------

    def _sample(self, obs: Mapping[str, Tensor], deterministic: bool,
                generator: torch.Generator | None) -> tuple[Tensor, Tensor, dict[str, Tensor], Tensor]:
        prefix, value = self._prefix(obs)
        b, device = value.shape[0], value.device
        shape = (b, self.model.chunk_size, self.model.max_action_dim)
        x0 = torch.zeros(shape, device=device) if deterministic else torch.randn(shape, generator=generator, device=device)
        x, chain, logprob, _ = self._chain(prefix, x0, None, deterministic, generator)
        return self._to_action(x), logprob, {"x0": x0, "chain": chain}, value

    def evaluate(self, obs: Mapping[str, Tensor], action: Tensor,
                 extras: Mapping[str, Tensor] | None = None) -> tuple[Tensor, Tensor, Tensor]:
        if not extras or "x0" not in extras or "chain" not in extras:
            raise ValueError(f"{self.family}: evaluate needs extras['x0'] and extras['chain'] (what sample() returned)")
        prefix, value = self._prefix(obs)
        _, _, logprob, entropy = self._chain(prefix, extras["x0"].float(), extras["chain"], False, None)
        return logprob, entropy, value

    def value(self, obs: Mapping[str, Tensor]) -> Tensor:
        return self._prefix(obs)[1]

    # --- LeRobot's own inference (the reference path) ---------------------------------------------

    @torch.no_grad()
    def predict_chunk(self, obs: Mapping[str, Tensor], noise: Tensor) -> Tensor:
        """LeRobot's ``predict_action_chunk`` from dvla observations and a given noise: the
        un-normalised chunk [B, chunk_size, action_dim] (plain Euler, no RL noise)."""
        imgs, masks, tokens, token_mask, state = self._inputs(obs)
        with self._autocast(tokens.device):
            x = self.model.sample_actions(imgs, masks, tokens, token_mask, state, noise, num_steps=self.steps)
        return self.normalizer.unnormalize_actions(x[..., : self.action_dim].float())

    def base_state_dict(self) -> dict[str, Tensor]:
        """The model's tensors under the checkpoint's names, each LoRA delta merged into a copy of
        its weight (the live adapters are untouched): what ``dvla export`` writes."""
        state = self.model.state_dict()
        base = {k.replace(".base_layer.", "."): v for k, v in state.items() if ".lora_" not in k}
        adapters = {f"model.{k}": v for k, v in state.items() if ".lora_" in k}
        return merge_trained(base, adapters, self._lora_scaling)


def lora_scaling(lora: Mapping[str, Any] | None) -> float:
    """peft's scaling of a LoRA delta (``lora_alpha / r``, :func:`.hf_backbone.apply_lora`'s defaults)."""
    if lora is None:
        return 0.0
    r = int(lora.get("r", 8))
    return float(lora.get("lora_alpha", 2 * r)) / r


def merge_trained(base: Mapping[str, Tensor], trained: Mapping[str, Tensor], scaling: float) -> dict[str, Tensor]:
    """A checkpoint's tensors (``base``, its own names) with a run's trained policy tensors applied
    (``trained``: the policy's names, ``model.`` + the checkpoint's; heads of the policy's own,
    e.g. ``noise_head``, are skipped): ``model.X`` replaces X; ``model.P.lora_A.<adapter>.weight``
    with its ``lora_B`` adds ``scaling * B @ A`` to ``P.weight`` (float32 sum, stored in the
    base's dtype). Tensors nothing touched are the base's own objects, unchanged."""
    out = dict(base)
    pairs: dict[str, dict[str, Tensor]] = {}
    for key, value in trained.items():
        if not key.startswith("model."):
            continue
        name = key[len("model."):]
        m = re.fullmatch(r"(.+)\.lora_([AB])\.[^.]+\.weight", name)
        if m:
            pairs.setdefault(m.group(1), {})[m.group(2)] = value
        elif ".lora_" in name:
            raise ValueError(f"{key}: a LoRA tensor of a kind dvla does not merge")
        else:
            name = name.replace(".base_layer.", ".")
            if name not in out:
                raise ValueError(f"{key}: not a tensor of the checkpoint")
            if tuple(value.shape) != tuple(out[name].shape):
                raise ValueError(f"{key}: shape {tuple(value.shape)} != the checkpoint's {tuple(out[name].shape)}")
            out[name] = value.detach().to(out[name].dtype).clone()
    for layer, ab in sorted(pairs.items()):
        weight = f"{layer}.weight"
        if set(ab) != {"A", "B"} or weight not in out:
            raise ValueError(f"model.{layer}: LoRA {'/'.join(sorted(ab))} without its pair or its base weight")
        w = out[weight]
        out[weight] = (w.float() + scaling * (ab["B"].float() @ ab["A"].float())).to(w.dtype)
    return out


@register_policy("pi0")
class Pi0Policy(PublishedFlowPolicy):
    family = "pi0"

    def _load_model(self, ck: LeRobotCheckpoint) -> nn.Module:
        from .pi import PiModel

        vlm = {"vision_config": {"num_attention_heads": self._vision_heads(ck)}} if self._vision_heads(ck) else None
        return _build(ck, lambda sd: PiModel.from_state_dict(sd, ck.config, vlm_config=vlm, dtype=self.dtype))

    def _vision_heads(self, ck: LeRobotCheckpoint) -> int | None:
        """SigLIP's head count, which the tensor shapes cannot tell: ``policy_kwargs.vision_heads``,
        else the ``architecture.json`` that tiny test checkpoints carry, else None (width / 72, the
        published so400m tower's 16)."""
        if self.vision_heads is not None:
            return int(self.vision_heads)
        try:
            arch = json.loads((ck.path / "architecture.json").read_text())
            return int(arch["vision_tower (siglip)"]["num_attention_heads"])
        except (OSError, ValueError, KeyError, TypeError):
            return None


@register_policy("pi05")
class Pi05Policy(Pi0Policy):
    family = "pi05"


@register_policy("smolvla")
class SmolVLAPolicy(PublishedFlowPolicy):
    family = "smolvla"

    def _load_model(self, ck: LeRobotCheckpoint) -> nn.Module:
        from .smolvla import SmolVLAModel

        try:
            vlm = json.loads((ck.vlm_dir / "config.json").read_text())
        except (OSError, ValueError, TypeError) as err:
            raise CheckpointError(f"{ck.path}: cannot read the backbone config (vlm_model_name "
                                  f"{ck.config.get('vlm_model_name')!r}): {type(err).__name__}: {err}") from None
        return _build(ck, lambda sd: SmolVLAModel.from_state_dict(sd, ck.config, vlm_config=vlm, dtype=self.dtype))


def _build(ck: LeRobotCheckpoint, make: Any) -> nn.Module:
    try:
        model = make(read_state_dict(ck))
    except (ValueError, KeyError, RuntimeError) as err:
        text = " ".join(str(err).split())[:300]
        raise CheckpointError(f"{ck.path}: does not hold a {ck.family} model as its config.json says: {text}") from None
    return model.eval()
