"""The transformers vision-language model under ``vla-tokens`` and ``vla-flow``.

:class:`HFBackbone` loads the checkpoint's VLM (``local_files_only``, after
:func:`~.checkpoint.check_checkpoint`) and turns dvla observations into its prefix: one image per
camera resized to the vision tower's ``image_size`` and normalised with
``preprocessor_config.json``'s mean/std (0.5/0.5 without one), through ``get_image_features``;
the instruction ids (the checkpoint's own tokenizer, pads masked) through
``get_input_embeddings()``; then the language model on ``inputs_embeds`` with ``position_ids``
counting real tokens only (padding never shifts a later token). A prefix-LM model (PaliGemma)
attends bidirectionally, as pi0's prefix does; Llava stays causal.

Dropout is zeroed before loading (``evaluate`` must be a pure function); vision parameters no
forward reads are frozen. With ``dtype="bfloat16"`` forwards run under autocast and callers cast
outputs to float32 before a log-prob or value; the image statistics are non-persistent buffers.
:func:`apply_lora` adds peft adapters from a fixed seed (every host builds the same ones), kept
float32 whatever the base's dtype.
"""

from __future__ import annotations

import contextlib
import inspect
import json
import re
from typing import Any, Iterator, Mapping, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.nn.attention import SDPBackend, sdpa_kernel

from .checkpoint import CheckpointError, CheckpointInfo
from .tokenizer import pad_id_of, tokenize_instruction

__all__ = ["HFBackbone", "SampleAndAct", "apply_lora", "load_tokenizer", "tokenize_instruction", "torch_dtype", "float32_head",
           "seeded", "pooled", "freeze_all_but_lora", "DTYPES", "LORA_TARGETS", "SDPA_BACKENDS"]

DTYPES = {"float32": torch.float32, "bfloat16": torch.bfloat16}
SDPA_BACKENDS = [SDPBackend.FLASH_ATTENTION, SDPBackend.EFFICIENT_ATTENTION, SDPBackend.MATH]
"""Attention kernels the policies' forwards may use on CUDA: PyTorch's own, not cuDNN's. On an H200
(torch 2.11 + CUDA 13.0) cuDNN's attention failed its internal check on PaliGemma's bf16 prefix
(``mha_graph.execute(...).is_good()``, a known defect of that backend: pytorch/pytorch#134001)
while these ran the same batch (docs/benchmarks.md, "VLA")."""
LORA_TARGETS = ("q_proj", "k_proj", "v_proj", "o_proj")
"""Default LoRA targets: the attention projections (the language model's, and the flow expert's)."""
_INIT_SEED = 0x5EED


def torch_dtype(dtype: str, checkpoint: Any) -> torch.dtype:
    if dtype not in DTYPES:
        raise ValueError(f"policy_kwargs.dtype: {dtype!r} for {checkpoint} is not one of {', '.join(DTYPES)}")
    return DTYPES[dtype]


@contextlib.contextmanager
def seeded(seed: int = _INIT_SEED) -> Iterator[None]:
    """Initialise new modules from a fixed seed (every host builds the same initial heads and
    adapters) without touching the caller's global RNG."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        yield


def _one_line(err: BaseException) -> str:
    text = " ".join(str(err).split())
    return f"{type(err).__name__}: {text[:300]}"


def load_tokenizer(info: CheckpointInfo) -> Any:
    from transformers import AutoTokenizer

    try:
        return AutoTokenizer.from_pretrained(str(info.path), local_files_only=True)
    except Exception as err:  # any loader failure becomes one line naming the path
        raise CheckpointError(f"{info.path}: cannot load the tokenizer: {_one_line(err)}") from None


def _zero_dropout(config: Any) -> None:
    for sub in [config] + [getattr(config, k) for k in ("text_config", "vision_config") if hasattr(config, k)]:
        for key, value in list(vars(sub).items()):
            if "dropout" in key and isinstance(value, float):
                setattr(sub, key, 0.0)


def _load_vlm(info: CheckpointInfo, dtype: torch.dtype) -> nn.Module:
    from transformers import AutoConfig, AutoModelForImageTextToText
    from transformers.utils import logging as hf_logging

    hf_logging.disable_progress_bar()  # a "Loading weights" bar per policy copy is noise in role logs
    try:
        config = AutoConfig.from_pretrained(str(info.path), local_files_only=True)
        _zero_dropout(config)
        vlm = AutoModelForImageTextToText.from_pretrained(str(info.path), config=config, local_files_only=True,
                                                          dtype=dtype)
    except Exception as err:  # corrupt weights, unknown architecture, ...: one line naming the path
        raise CheckpointError(f"{info.path}: cannot load the model: {_one_line(err)}") from None
    for module in vlm.modules():
        if isinstance(module, nn.Dropout):
            module.p = 0.0
    return vlm.eval()


def _never_read(name: str, config: Any) -> bool:
    """Vision parameters no forward here reads: SigLIP's attention-pooling head, and the final
    norm when the model (Llava) takes a hidden state from before it. They are frozen (never
    trained, never shipped), so every trainable parameter gets a gradient (DDP needs that)."""
    if "vision_tower." not in name:
        return False
    return ".head." in name or (hasattr(config, "vision_feature_layer") and ".post_layernorm." in name)


def apply_lora(module: nn.Module, lora: Mapping[str, Any], where: str,
               default_targets: Sequence[str] = LORA_TARGETS, required: bool = True) -> bool:
    """Inject LoRA adapters into ``module`` in place: ``lora`` keys ``r`` (default 8),
    ``lora_alpha`` (default 2 r), ``target_modules`` (module name suffixes, or one regex string
    matched against whole names, as peft reads it; default :data:`LORA_TARGETS`).
    ``required=False``: a module none of whose names match is left alone (returns False)."""
    from peft import LoraConfig, inject_adapter_in_model

    unknown = sorted(set(lora) - {"r", "lora_alpha", "target_modules"})
    if unknown:
        raise ValueError(f"policy_kwargs.lora: unknown key {', '.join(unknown)} (expected r, lora_alpha, "
                         "target_modules)")
    r = int(lora.get("r", 8))
    targets = lora.get("target_modules", default_targets)
    targets = targets if isinstance(targets, str) else list(targets)  # a string is peft's regex
    names = [name for name, _ in module.named_modules()]
    hit = (any(re.fullmatch(targets, n) for n in names) if isinstance(targets, str)
           else any(n.rsplit(".", 1)[-1] in targets for n in names))
    if not required and not hit:
        return False
    config = LoraConfig(r=r, lora_alpha=float(lora.get("lora_alpha", 2 * r)), lora_dropout=0.0, bias="none",
                        target_modules=targets)
    try:
        with seeded():
            inject_adapter_in_model(config, module)
    except ValueError as err:  # e.g. no module matches the targets
        raise ValueError(f"policy_kwargs.lora on {where}: {_one_line(err)}") from None
    for name, p in module.named_parameters():
        if "lora_" in name and p.is_floating_point():
            # float32 adapters on a bf16 base: an Adam step of 1e-5 is below bf16's resolution
            # for most weights (autocast still runs their matmuls in bf16)
            p.data = p.data.float()
    return True


def freeze_all_but_lora(*modules: nn.Module) -> None:
    """The frozen base of a LoRA run: only the adapters of ``modules`` keep training."""
    for module in modules:
        for name, p in module.named_parameters():
            p.requires_grad_("lora_" in name)


@contextlib.contextmanager
def float32_head(device: torch.device) -> Iterator[None]:
    """Heads (value, noise) compute in float32 even inside a bf16 autocast region."""
    with torch.autocast(device_type=device.type, enabled=False):
        yield


class HFBackbone(nn.Module):
    """The checkpoint's VLM plus the observation -> prefix mapping (see the module docstring)."""

    def __init__(self, info: CheckpointInfo, obs: Mapping[str, Any], *, dtype: str = "float32") -> None:
        super().__init__()
        self.dtype = torch_dtype(dtype, info.path)
        self.vlm = _load_vlm(info, self.dtype)
        c = int(obs["rgb"].shape[-1])
        if c % 3:
            raise ValueError(f"{info.path}: the rgb observation has {c} channels, not 3 per camera")
        self.cams = c // 3
        vision = self.vlm.config.vision_config
        self.image_size = int(vision.image_size)
        mean, std = self._image_stats(info)
        self.register_buffer("pixel_mean", torch.tensor(mean).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("pixel_std", torch.tensor(std).view(1, 3, 1, 1), persistent=False)
        self.tokenizer = load_tokenizer(info)
        self.pad_id = pad_id_of(self.tokenizer)
        self.n_words = int(obs["tokens"].shape[0]) if "tokens" in obs else 0
        rows = self.vlm.get_input_embeddings().num_embeddings
        vocab = getattr(obs.get("tokens"), "vocab", None)
        if self.n_words and vocab and int(vocab) > rows:
            raise ValueError(f"{info.path}: the tokens observation has ids up to {int(vocab) - 1} but the model embeds "
                             f"{rows}; tokenise the instruction with the checkpoint's tokenizer")
        self.width = int(self.vlm.config.get_text_config().hidden_size)
        self._prefix_lm = "token_type_ids" in inspect.signature(self.vlm.model.forward).parameters
        for name, p in self.vlm.named_parameters():
            if _never_read(name, self.vlm.config):
                p.requires_grad_(False)

    @staticmethod
    def _image_stats(info: CheckpointInfo) -> tuple[list[float], list[float]]:
        file = info.path / "preprocessor_config.json"
        if not file.is_file():
            return [0.5] * 3, [0.5] * 3
        try:
            cfg = json.loads(file.read_text())
            mean, std = [float(x) for x in cfg["image_mean"]], [float(x) for x in cfg["image_std"]]
        except (ValueError, KeyError, TypeError) as err:
            raise CheckpointError(f"{file}: no usable image_mean / image_std ({_one_line(err)})") from None
        if len(mean) != 3 or len(std) != 3:
            raise CheckpointError(f"{file}: image_mean and image_std need 3 numbers each")
        return mean, std

    @property
    def language_model(self) -> nn.Module:
        """Where LoRA goes: the decoder stack (not the vision tower, whose attention shares names)."""
        return self.vlm.model.language_model

    def forward_context(self, device: torch.device) -> contextlib.AbstractContextManager:
        """The context every forward of the policy runs in: bf16 autocast for a bf16 model, and on
        CUDA attention without cuDNN's backend (:data:`SDPA_BACKENDS`)."""
        stack = contextlib.ExitStack()
        if device.type == "cuda":
            stack.enter_context(sdpa_kernel(SDPA_BACKENDS))
        if self.dtype != torch.float32:
            stack.enter_context(torch.autocast(device_type=device.type, dtype=self.dtype))
        return stack

    def prefix(self, obs: Mapping[str, Tensor]) -> tuple[Tensor, Tensor]:
        """(embeddings [B, S, width] in the model dtype, mask [B, S] bool): images then words."""
        rgb = obs["rgb"]
        if rgb.dim() != 4 or rgb.shape[-1] != 3 * self.cams:
            raise ValueError(f"obs['rgb'] must be [B, H, W, {3 * self.cams}] uint8, got {tuple(rgb.shape)}")
        b, hgt, wid, _ = rgb.shape
        img = rgb.permute(0, 3, 1, 2).reshape(b * self.cams, 3, hgt, wid).float() / 255.0
        if (hgt, wid) != (self.image_size, self.image_size):
            img = F.interpolate(img, size=(self.image_size, self.image_size), mode="bilinear",
                                align_corners=False, antialias=True)
        img = ((img - self.pixel_mean) / self.pixel_std).to(self.dtype)
        feats = self.vlm.get_image_features(pixel_values=img)
        feats = getattr(feats, "pooler_output", feats)
        if isinstance(feats, (list, tuple)):  # Llava returns one tensor per image
            feats = torch.stack(list(feats))
        parts = [feats.reshape(b, self.cams * feats.shape[1], feats.shape[-1]).to(self.dtype)]
        masks = [torch.ones(b, parts[0].shape[1], dtype=torch.bool, device=rgb.device)]
        if self.n_words:
            ids = obs["tokens"].long()
            parts.append(self.vlm.get_input_embeddings()(ids).to(self.dtype))
            masks.append(ids != self.pad_id)
        return torch.cat(parts, 1), torch.cat(masks, 1)

    def run(self, embeds: Tensor, mask: Tensor) -> Tensor:
        """The language model's last hidden states [B, S, width] for ``embeds`` (pads masked)."""
        positions = (mask.long().cumsum(1) - 1).clamp(min=0)
        extra = {"token_type_ids": torch.zeros_like(positions)} if self._prefix_lm else {}
        out = self.vlm.model(inputs_embeds=embeds, attention_mask=mask.long(), position_ids=positions,
                             use_cache=False, **extra)
        return out.last_hidden_state


def pooled(hidden: Tensor, mask: Tensor) -> Tensor:
    """Float32 mean of ``hidden`` [B, S, W] over the real positions of ``mask`` [B, S]."""
    m = mask.unsqueeze(-1).float()
    return (hidden.float() * m).sum(1) / m.sum(1).clamp(min=1.0)


class SampleAndAct:
    """``sample`` and ``act`` of the policy protocol from one ``_sample(obs, deterministic,
    generator) -> (action, logprob, extras, value)`` (both families compute the value with the
    same prefix pass, so ``act`` costs no second forward)."""

    @torch.no_grad()
    def sample(self, obs: Mapping[str, Tensor], deterministic: bool = False,
               generator: torch.Generator | None = None) -> tuple[Tensor, Tensor, dict[str, Tensor]]:
        action, logprob, extras, _ = self._sample(obs, deterministic, generator)  # type: ignore[attr-defined]
        return action, logprob, extras

    @torch.no_grad()
    def act(self, obs: Mapping[str, Tensor], deterministic: bool = False,
            generator: torch.Generator | None = None) -> tuple[Tensor, Tensor, Tensor]:
        action, logprob, _, value = self._sample(obs, deterministic, generator)  # type: ignore[attr-defined]
        return action, logprob, value
