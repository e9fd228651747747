"""What LeRobot's processors do around a pi0 / pi05 / smolvla model, on a checked
:class:`~.lerobot_format.LeRobotCheckpoint`: state and action (un)normalisation (:class:`Normalizer`),
images at the model's size in [-1, 1] (:func:`model_images`), the prompt as token ids
(:class:`Prompter`), and the whole preprocessor in one call (:func:`preprocess`). The numbers are
LeRobot 0.6.1's (tests/references/test_lerobot_processing.py checks them against its recordings).
"""

from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from .checkpoint import CheckpointError
from .lerobot_format import ACTION_KEY, STATE_KEY, LeRobotCheckpoint

__all__ = ["Normalizer", "resize_with_pad", "model_images", "pad_to", "Prompter", "load_tokenizer", "preprocess",
           "TOKENS_KEY", "TOKEN_MASK_KEY", "STATE_BINS"]

TOKENS_KEY = "observation.language.tokens"
TOKEN_MASK_KEY = "observation.language.attention_mask"
STATE_BINS = 256
"""pi05 writes each normalised state dim in its prompt as one of this many bins over [-1, 1]."""


class Normalizer:
    """The checkpoint's state and action normalisation (LeRobot's normaliser and unnormaliser; the
    openpi layout's formulas for openpi directories).

    A feature whose mode needs stats the checkpoint does not carry (base checkpoints) passes
    through unchanged, as in LeRobot; :attr:`missing_stats` names those features and
    :attr:`identity` says that nothing is changed at all. Stats follow the input's dtype and
    device, as LeRobot's do."""

    def __init__(self, ck: LeRobotCheckpoint) -> None:
        self.ck = ck
        self._modes = {STATE_KEY: ck.norm_modes["STATE"], ACTION_KEY: ck.norm_modes["ACTION"]}
        #: features ("observation.state", "action") whose mode needs stats that the checkpoint lacks
        self.missing_stats = tuple(k for k, mode in self._modes.items() if mode != "IDENTITY" and k not in ck.stats)
        for key in self.missing_stats:
            self._modes[key] = "IDENTITY"
        #: True when neither the state nor the actions are changed
        self.identity = all(mode == "IDENTITY" for mode in self._modes.values())
        self._cache: dict[tuple, dict[str, torch.Tensor]] = {}

    def _stats(self, key: str, like: torch.Tensor) -> dict[str, torch.Tensor]:
        cache_key = (key, like.dtype, like.device)
        if cache_key not in self._cache:
            self._cache[cache_key] = {name: torch.tensor(values, dtype=torch.float32).to(like.device, like.dtype)
                                      for name, values in self.ck.stats[key].items()}
        return self._cache[cache_key]

    def _apply(self, x: torch.Tensor, key: str, inverse: bool) -> torch.Tensor:
        mode = self._modes[key]
        if mode == "IDENTITY":
            return x
        s = self._stats(key, x)
        eps = self.ck.norm_eps
        if self.ck.layout == "openpi":  # openpi adds eps to the scale both ways
            if mode == "MEAN_STD":
                return x * (s["std"] + eps) + s["mean"] if inverse else (x - s["mean"]) / (s["std"] + eps)
            span = s["q99"] - s["q01"] + eps
            return (x + 1.0) / 2.0 * span + s["q01"] if inverse else (x - s["q01"]) / span * 2.0 - 1.0
        if mode == "MEAN_STD":
            return x * s["std"] + s["mean"] if inverse else (x - s["mean"]) / (s["std"] + eps)
        low, high = {"MIN_MAX": ("min", "max"), "QUANTILES": ("q01", "q99"), "QUANTILE10": ("q10", "q90")}[mode]
        span = s[high] - s[low]
        span = torch.where(span == 0, torch.tensor(eps, dtype=x.dtype, device=x.device), span)
        if mode == "MIN_MAX":  # LeRobot orders the operations differently per mode: kept for equal rounding
            return (x + 1) / 2 * span + s[low] if inverse else 2 * (x - s[low]) / span - 1
        return (x + 1.0) * span / 2.0 + s[low] if inverse else 2.0 * (x - s[low]) / span - 1.0

    def _check_dim(self, x: torch.Tensor, key: str, dim: int, width: int) -> None:
        """With stats the dims must be the checkpoint's; without, anything the model's width holds."""
        n = x.shape[-1]
        ok, want = (n == dim, str(dim)) if self._modes[key] != "IDENTITY" else (1 <= n <= width, f"1 to {width}")
        if not ok:
            raise ValueError(f"{self.ck.path}: {key} has {n} dims, the checkpoint takes {want}")

    def normalize_state(self, state: torch.Tensor) -> torch.Tensor:
        """[B, state_dim] raw state -> normalised (not padded: :func:`pad_to` gives the model's width)."""
        self._check_dim(state, STATE_KEY, self.ck.state_dim, self.ck.max_state_dim)
        return self._apply(state, STATE_KEY, inverse=False)

    def normalize_actions(self, actions: torch.Tensor) -> torch.Tensor:
        """[..., action_dim] actions in robot units -> the model's normalised space."""
        self._check_dim(actions, ACTION_KEY, self.ck.action_dim, self.ck.max_action_dim)
        return self._apply(actions, ACTION_KEY, inverse=False)

    def unnormalize_actions(self, actions: torch.Tensor) -> torch.Tensor:
        """[..., A] normalised model actions, A >= action_dim -> [..., action_dim] in robot units: the
        padding dims beyond action_dim are cut first, as LeRobot does before its unnormaliser."""
        if actions.shape[-1] < self.ck.action_dim:
            raise ValueError(f"{self.ck.path}: actions have {actions.shape[-1]} dims, fewer than the checkpoint's "
                             f"action_dim {self.ck.action_dim}")
        return self._apply(actions[..., : self.ck.action_dim], ACTION_KEY, inverse=True)


def pad_to(x: torch.Tensor, width: int) -> torch.Tensor:
    """Zero-pad the last dim to ``width`` (the model's max_state_dim / max_action_dim)."""
    if x.shape[-1] > width:
        raise ValueError(f"{x.shape[-1]} dims do not fit the model's {width}")
    return F.pad(x, (0, width - x.shape[-1])) if x.shape[-1] < width else x


def resize_with_pad(images: torch.Tensor, height: int, width: int, *, centered: bool = True) -> torch.Tensor:
    """[B, C, h, w] -> [B, C, height, width] without distortion: bilinear resize (align_corners
    False) to fit, then zero padding. ``centered`` (pi0 / pi05, openpi's convention): padding split
    on both sides, uint8 rounded back to uint8, float clamped to [0, 1]. Not centered (smolvla):
    padding on the top and left only, no clamp (uint8 is interpolated in float and rounded back in
    both). An image already at the size is returned as is."""
    h, w = images.shape[-2:]
    if (h, w) == (height, width):
        return images
    ratio = max(w / width, h / height)
    new_h, new_w = int(h / ratio), int(w / ratio)
    resized = F.interpolate(images.float() if images.dtype == torch.uint8 else images, size=(new_h, new_w),
                            mode="bilinear", align_corners=False)
    if images.dtype == torch.uint8:
        resized = resized.round().clamp(0, 255).to(torch.uint8)
    elif centered:
        resized = resized.clamp(0.0, 1.0)
    pad_h, pad_w = max(0, height - new_h), max(0, width - new_w)
    pads = (pad_w // 2, pad_w - pad_w // 2, pad_h // 2, pad_h - pad_h // 2) if centered else (pad_w, 0, pad_h, 0)
    return F.pad(resized, pads, value=0)


def model_images(images: Mapping[str, torch.Tensor], ck: LeRobotCheckpoint, *,
                 dtype: torch.dtype = torch.float32) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """Camera images as the model takes them, as LeRobot prepares them: ``images`` maps checkpoint
    camera names (``ck.cameras``) to uint8 [B, 3, h, w] (or [B, h, w, 3]; float in [0, 1] works too);
    each becomes [B, 3, H, W] at ``ck.image_size`` in [-1, 1] with an all-True [B] mask.

    Order and missing cameras follow LeRobot: the given cameras in ``ck.cameras`` order, then one
    all -1 image with an all-False mask per missing camera (pi0 / pi05), or per missing camera up
    to config ``empty_cameras`` (smolvla drops the rest). Masked images are ignored by the model,
    so the result does not depend on the order; at least one camera must be given."""
    unknown = sorted(set(images) - set(ck.cameras))
    if unknown or not images:
        raise ValueError(f"{ck.path}: cameras {unknown or '(none)'} given, the checkpoint's are "
                         f"{', '.join(ck.cameras)} (map the env's cameras to these names)")
    height, width = ck.image_size
    out, masks = [], []
    for name in (c for c in ck.cameras if c in images):
        img = images[name]
        if img.ndim != 4 or 3 not in (img.shape[1], img.shape[-1]):
            raise ValueError(f"{ck.path}: camera {name} has shape {tuple(img.shape)}, [B, 3, H, W] is expected")
        if img.shape[1] != 3:
            img = img.permute(0, 3, 1, 2)
        img = img.to(torch.float32) / 255.0 if img.dtype == torch.uint8 else img.to(torch.float32)
        img = resize_with_pad(img, height, width, centered=ck.family != "smolvla")
        out.append((img * 2.0 - 1.0).to(dtype))
        masks.append(torch.ones(img.shape[0], dtype=torch.bool, device=img.device))
    missing = len(ck.cameras) - len(out)
    if ck.family == "smolvla":
        missing = min(missing, int(ck.config.get("empty_cameras") or 0))
    for _ in range(missing):
        out.append(torch.full_like(out[0], -1.0))
        masks.append(torch.zeros_like(masks[0]))
    return out, masks


def load_tokenizer(ck: LeRobotCheckpoint) -> Any:
    """The checkpoint's Hugging Face tokenizer (``ck.tokenizer_dir``, local files only)."""
    from transformers import AutoTokenizer

    if ck.tokenizer_dir is None:
        raise CheckpointError(f"{ck.path}: no tokenizer (pass policy_kwargs.tokenizer: a tokenizer directory or a "
                              "cached repo id)")
    try:
        return AutoTokenizer.from_pretrained(str(ck.tokenizer_dir), local_files_only=True)
    except (OSError, ValueError) as err:
        raise CheckpointError(f"{ck.tokenizer_dir}: cannot load the tokenizer ({str(err).splitlines()[0]})") from None


class Prompter:
    """Task text (+ pi05's state) -> the token ids and mask each family's preprocessor produces.

    pi0 and smolvla: the task with a trailing newline. pi05: ``"Task: <task>, State: <bins>;\\nAction: "``
    with the task stripped, ``_`` and newlines made spaces, and each normalised state dim (the
    checkpoint's real dims only) as its bin among 256 over [-1, 1] (below -1 gives -1, 1 and above
    255); without the state when config ``use_proprioceptive_memory`` is set. The tokenizer adds
    its own special tokens (PaliGemma's BOS; none for SmolVLM) and pads as the checkpoint's
    tokenizer step says (pi: to tokenizer_max_length; smolvla: to the longest, at most that)."""

    def __init__(self, ck: LeRobotCheckpoint, tokenizer: Any) -> None:
        self.ck = ck
        self.tokenizer = tokenizer
        self._state_in_prompt = ck.family == "pi05" and not ck.config.get("use_proprioceptive_memory", False)
        self._edges = np.linspace(-1.0, 1.0, STATE_BINS + 1)[:-1]

    def prompts(self, tasks: Sequence[str], normalized_state: torch.Tensor | None = None) -> list[str]:
        """The strings the tokenizer gets."""
        if isinstance(tasks, str):
            tasks = [tasks]
        if self.ck.family != "pi05":
            return [t if t.endswith("\n") else t + "\n" for t in tasks]
        if not self._state_in_prompt:
            return [f"Task: {self._clean(t)};\nAction: " for t in tasks]
        if normalized_state is None or normalized_state.ndim != 2 or normalized_state.shape[0] != len(tasks):
            got = None if normalized_state is None else tuple(normalized_state.shape)
            raise ValueError(f"{self.ck.path}: pi05 prompts need the normalised state [B={len(tasks)}, "
                             f"{self.ck.state_dim}], got {got}")
        bins = np.digitize(normalized_state.detach().float().cpu().numpy(), bins=self._edges) - 1
        return [f"Task: {self._clean(t)}, State: {' '.join(str(int(b)) for b in row)};\nAction: "
                for t, row in zip(tasks, bins)]

    @staticmethod
    def _clean(task: str) -> str:
        return task.strip().replace("_", " ").replace("\n", " ")

    def encode(self, tasks: Sequence[str], normalized_state: torch.Tensor | None = None
               ) -> tuple[torch.Tensor, torch.Tensor]:
        """(tokens int64 [B, L], mask bool [B, L])."""
        settings = self.ck.tokenizer_settings
        enc = self.tokenizer(self.prompts(tasks, normalized_state), max_length=int(settings["max_length"]),
                             truncation=bool(settings["truncation"]), padding=settings["padding"],
                             padding_side=settings["padding_side"], return_tensors="pt")
        return enc["input_ids"].to(torch.int64), enc["attention_mask"].to(torch.bool)


def preprocess(ck: LeRobotCheckpoint, tokenizer: Any, batch: Mapping[str, Any]) -> dict[str, Any]:
    """LeRobot's preprocessor on a batch ``{camera: images, "observation.state": [B, S], "task":
    [str] * B}``: a copy with the state normalised and the prompt's ``observation.language.tokens``
    / ``observation.language.attention_mask`` added (images untouched: :func:`model_images`)."""
    out = dict(batch)
    state = Normalizer(ck).normalize_state(torch.as_tensor(batch[STATE_KEY]))
    out[STATE_KEY] = state
    out[TOKENS_KEY], out[TOKEN_MASK_KEY] = Prompter(ck, tokenizer).encode(batch["task"], state)
    return out
