"""What OpenVLA's processor and ``predict_action`` do around the model, on a checked
:class:`~.openvla_format.OpenVLACheckpoint`: the prompt and its token ids (:func:`encode_prompts`),
the images as the fused DINOv2 + SigLIP featurizer takes them (:func:`pixel_values`), action tokens
to bin centres (:func:`tokens_to_normalized`), un-normalisation of the actions
(:func:`unnormalize_actions`) and OFT's proprio normalisation (:func:`normalize_proprio`). The
numbers are upstream's (openvla @ c8f03f4, openvla-oft @ 213c5ff): tests/references/
test_openvla_processing.py checks them against the recorded processor outputs and actions.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np
import torch

from .checkpoint import CheckpointError
from .openvla_format import NORM_BOUNDS, OpenVLACheckpoint

__all__ = ["PROMPT", "EMPTY_TOKEN_ID", "prompt", "load_tokenizer", "encode_prompts", "pixel_values", "bin_centers",
           "tokens_to_normalized", "unnormalize_actions", "normalize_proprio"]

PROMPT = "In: What action should the robot take to {task}?\nOut:"
"""OpenVLA's inference prompt (Prismatic's "pure" Llama-2 prompt without the trailing space)."""
EMPTY_TOKEN_ID = 29871
"""Llama-2's bare "▁" piece: training saw it after "Out:", so predict_action appends it."""


def prompt(task: str) -> str:
    """The prompt of one task, lower-cased as OpenVLA's training data and evaluation scripts have it."""
    return PROMPT.format(task=task.lower())


def load_tokenizer(ck: OpenVLACheckpoint) -> Any:
    """The checkpoint's fast tokenizer from its tokenizer.json (no remote code; the auto classes
    would read config.json's auto_map). Its BOS is added, its pad token is <PAD> (32000)."""
    from transformers import PreTrainedTokenizerFast

    try:
        return PreTrainedTokenizerFast.from_pretrained(str(ck.path), local_files_only=True)
    except (OSError, ValueError) as err:
        raise CheckpointError(f"{ck.path / 'tokenizer.json'}: cannot load the tokenizer "
                              f"({str(err).splitlines()[0] if str(err) else type(err).__name__})") from None


def encode_prompts(tokenizer: Any, tasks: Sequence[str] | str, *, padding_side: str = "right"
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """(input_ids int64 [B, L], attention_mask bool [B, L]) of :func:`prompt` of each task: the
    tokenizer's ids with its BOS, then :data:`EMPTY_TOKEN_ID` as predict_action appends it (upstream
    leaves the mask one shorter; with no padding that is the same all-ones mask); rows of different
    lengths padded with the pad id on ``padding_side``, False in the mask."""
    if isinstance(tasks, str):
        tasks = [tasks]
    rows = [ids if ids[-1:] == [EMPTY_TOKEN_ID] else ids + [EMPTY_TOKEN_ID]
            for ids in tokenizer([prompt(t) for t in tasks])["input_ids"]]
    width = max(len(r) for r in rows)
    ids = torch.full((len(rows), width), int(tokenizer.pad_token_id), dtype=torch.int64)
    mask = torch.zeros((len(rows), width), dtype=torch.bool)
    for i, row in enumerate(rows):
        cols = slice(0, len(row)) if padding_side == "right" else slice(width - len(row), width)
        ids[i, cols] = torch.tensor(row, dtype=torch.int64)
        mask[i, cols] = True
    return ids, mask


def _resize(images: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """uint8 [B, h, w, 3] -> [B, height, width, 3] by PIL's bicubic resize, as the processor resizes
    (PIL rounds to uint8 between its two passes; torch's bicubic differs by up to 20 levels)."""
    from PIL import Image

    out = [np.asarray(Image.fromarray(img).resize((width, height), Image.BICUBIC))
           for img in images.cpu().numpy()]
    return torch.from_numpy(np.stack(out)).to(images.device)


def _camera(images: Any, ck: OpenVLACheckpoint) -> torch.Tensor:
    x = torch.as_tensor(images)
    if x.ndim == 3:
        x = x[None]
    if x.ndim == 4 and x.shape[-1] != 3 and x.shape[1] == 3:  # channels first
        x = x.permute(0, 2, 3, 1)
    if x.dtype != torch.uint8 or x.ndim != 4 or x.shape[-1] != 3:
        raise ValueError(f"{ck.path}: images must be uint8 [B, H, W, 3] (or [H, W, 3], [B, 3, H, W]), got {x.dtype} "
                         f"{tuple(x.shape)}")
    if tuple(x.shape[1:3]) != ck.image_size:  # "resize-naive": straight to the size, aspect not kept
        x = _resize(x, *ck.image_size)
    return x.permute(0, 3, 1, 2).to(torch.float32).div(255)


def pixel_values(images: Any, ck: OpenVLACheckpoint, *, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """The model's pixel values [B, 6 * ck.num_images, H, W] from one camera (uint8 [B, H, W, 3],
    [H, W, 3] or [B, 3, H, W], numpy or torch) or a list of ``ck.num_images`` cameras (OFT on
    LIBERO: primary, then wrist). Per camera, as PrismaticImageProcessor: bicubic resize to ``ck.image_size`` (none
    when already there), /255, then the DINOv2 tower's normalisation (3 channels) and the SigLIP
    tower's (3 channels); cameras concatenated on channels as OFT does."""
    cameras = list(images) if isinstance(images, (list, tuple)) else [images]
    if len(cameras) != ck.num_images:
        raise ValueError(f"{ck.path}: {len(cameras)} camera image(s) given, the checkpoint takes {ck.num_images}")
    out = []
    for cam in cameras:
        x = _camera(cam, ck)
        for mean, std in zip(ck.image_means, ck.image_stds):
            m = torch.tensor(mean, dtype=torch.float32, device=x.device).view(-1, 1, 1)
            s = torch.tensor(std, dtype=torch.float32, device=x.device).view(-1, 1, 1)
            out.append((x - m) / s)
    if len({t.shape[0] for t in out}) != 1:
        raise ValueError(f"{ck.path}: the cameras' batch sizes differ ({[t.shape[0] for t in out[::2]]})")
    return torch.cat(out, dim=1).to(dtype)


def bin_centers(n_bins: int) -> torch.Tensor:
    """float64 [n_bins - 1]: the midpoints of ``n_bins`` edges evenly over [-1, 1] (upstream's bins)."""
    bins = np.linspace(-1.0, 1.0, n_bins)
    return torch.from_numpy((bins[:-1] + bins[1:]) / 2.0)


def tokens_to_normalized(token_ids: torch.Tensor, ck: OpenVLACheckpoint) -> torch.Tensor:
    """Action token ids -> normalised actions (float64, same shape): the last id of the vocabulary
    is bin 0 (about -1), counting down; the two lowest action ids share the last bin centre."""
    ids = torch.as_tensor(token_ids).to(torch.int64)
    index = (ck.tokenizer_vocab_size - ids - 1).clamp(0, ck.n_action_bins - 2)
    return bin_centers(ck.n_action_bins).to(ids.device)[index]


def _bounds(ck: OpenVLACheckpoint, stats: Any, x: torch.Tensor, dim: int, what: str
            ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    if x.shape[-1] != dim:
        raise ValueError(f"{ck.path}: {what} have {x.shape[-1]} dims, the checkpoint's have {dim}")
    low, high = NORM_BOUNDS[ck.normalization]
    as64 = lambda v: torch.tensor(v, dtype=torch.float64, device=x.device)  # noqa: E731
    return as64(stats[low]), as64(stats[high]), torch.tensor(stats["mask"], dtype=torch.bool, device=x.device)


def unnormalize_actions(normalized: torch.Tensor, ck: OpenVLACheckpoint) -> torch.Tensor:
    """Normalised actions [..., action_dim] -> robot units (float64, as upstream's numpy):
    ``0.5 (n + 1) (high - low + eps) + low`` where the mask is set, ``n`` elsewhere (the gripper).
    Like numpy on the head's float32 output, ``0.5 (n + 1)`` is taken in float32 (float64 stays)."""
    n = torch.as_tensor(normalized)
    n = n.to(torch.float64 if n.dtype == torch.float64 else torch.float32)
    low, high, mask = _bounds(ck, ck.action_stats, n, ck.action_dim, "actions")
    return torch.where(mask, (0.5 * (n + 1)).to(torch.float64) * (high - low + ck.norm_eps) + low, n.to(torch.float64))


def normalize_proprio(raw: torch.Tensor, ck: OpenVLACheckpoint) -> torch.Tensor:
    """OFT: raw proprio [..., proprio_dim] -> the projector's input (float64), as upstream's
    evaluation: ``2 (x - low) / (high - low + 1e-8) - 1`` where the mask is set, clipped to [-1, 1]."""
    if ck.proprio_stats is None or ck.proprio_dim is None:
        raise ValueError(f"{ck.path}: the checkpoint has no proprio projector, it takes no proprio")
    x = torch.as_tensor(raw).to(torch.float64)
    low, high, mask = _bounds(ck, ck.proprio_stats, x, ck.proprio_dim, "proprio")
    return torch.where(mask, 2 * (x - low) / (high - low + ck.norm_eps) - 1, x).clamp(-1.0, 1.0)
