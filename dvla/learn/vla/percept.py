"""A pretrained, frozen perception for ``tiny-vla``: a small convolutional network that reads a few
scene quantities (e.g. an object's and a goal's table coordinates) from the image.

Why: RL from a behaviour-cloned tiny-vla does not improve on 64 px PushCube images while the same
network, given the cube's and goal's positions exactly, climbs within a few thousand env steps;
the patch encoder places the 4 cm cube to ~2 cm, and the task needs better (docs/benchmarks.md,
"Which part of perception?"). This network is trained once, supervised, on rendered scenes with
their recorded state (``python -m benchmarks.learn_vla pretrain``), then frozen inside the
policy: RL then only has control to learn.

Architecture: 3x3 convolutions over the image and two coordinate channels, ``keypoints`` feature
maps, a spatial soft-argmax (each map's expected x, y: a precise, differentiable position), and
an MLP to the ``outputs`` quantities, standardised (``mu``, ``sd`` buffers: the training labels').

File: safetensors of the state dict with ``outputs``, ``keypoints``, ``channels`` and ``labels``
(what the outputs are, comma-separated) in its metadata.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from .checkpoint import PERCEPT_SIZES, check_percept

__all__ = ["Percept", "load_percept", "save_percept"]


class Percept(nn.Module):
    """uint8 ``[B, H, W, 3]`` images -> ``[B, outputs]`` standardised estimates (:meth:`forward`)."""

    def __init__(self, outputs: int, keypoints: int = 16, channels: int = 32, labels: tuple[str, ...] = ()):
        super().__init__()
        if outputs < 1 or keypoints < 1 or channels < 1:
            raise ValueError(f"Percept: outputs {outputs}, keypoints {keypoints}, channels {channels} must be >= 1")
        self.outputs, self.keypoints, self.channels = int(outputs), int(keypoints), int(channels)
        self.labels = tuple(labels)
        c = self.channels
        self.conv = nn.Sequential(
            nn.Conv2d(5, c, 3, 2, 1), nn.GELU(), nn.Conv2d(c, c, 3, 1, 1), nn.GELU(),
            nn.Conv2d(c, c, 3, 1, 1), nn.GELU(), nn.Conv2d(c, self.keypoints, 1),
        )
        self.head = nn.Sequential(nn.Linear(2 * self.keypoints, 128), nn.GELU(), nn.Linear(128, self.outputs))
        # the labels' statistics: fixed parameters rather than buffers, so that inside a policy the
        # whole perception is frozen and nothing of it replicates
        self.mu = nn.Parameter(torch.zeros(self.outputs), requires_grad=False)
        self.sd = nn.Parameter(torch.ones(self.outputs), requires_grad=False)

    def forward(self, rgb: Tensor) -> Tensor:
        """Standardised estimates: ``(quantity - mu) / sd``."""
        x = rgb.to(self.mu.dtype).permute(0, 3, 1, 2) / 255.0 - 0.5
        b, _, h, w = x.shape
        ys = torch.linspace(-1, 1, h, device=x.device, dtype=x.dtype).view(1, 1, h, 1).expand(b, 1, h, w)
        xs = torch.linspace(-1, 1, w, device=x.device, dtype=x.dtype).view(1, 1, 1, w).expand(b, 1, h, w)
        f = self.conv(torch.cat([x, xs, ys], 1))
        _, k, fh, fw = f.shape
        att = f.flatten(2).softmax(-1).view(b, k, fh, fw)
        gy = torch.linspace(-1, 1, fh, device=x.device, dtype=x.dtype)
        gx = torch.linspace(-1, 1, fw, device=x.device, dtype=x.dtype)
        points = torch.cat([(att.sum(3) * gy).sum(2), (att.sum(2) * gx).sum(2)], 1)  # soft-argmax y, x
        return self.head(points)

    def estimate(self, rgb: Tensor) -> Tensor:
        """The quantities in their own units."""
        return self(rgb) * self.sd + self.mu


def save_percept(net: Percept, path: Path | str) -> None:
    from safetensors.torch import save_file

    meta = {**{k: str(getattr(net, k)) for k in PERCEPT_SIZES}, "labels": ",".join(net.labels)}
    save_file({k: v.detach().cpu().contiguous() for k, v in net.state_dict().items()}, str(path), metadata=meta)


def load_percept(path: Path | str, device: Any = None) -> Percept:
    """A :class:`Percept` from ``path`` (:func:`save_percept`'s file); a one-line error naming the
    file and what is wrong with it."""
    from safetensors import safe_open

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such perception file (policy_kwargs.percept)")
    sizes, meta = check_percept(path)
    try:
        with safe_open(str(path), "pt") as f:
            tensors = {k: f.get_tensor(k) for k in f.keys()}
    except Exception as e:  # a file its header does not describe
        raise ValueError(f"{path}: not a safetensors perception file ({type(e).__name__}: {e})") from None
    labels = tuple(x for x in meta.get("labels", "").split(",") if x)
    net = Percept(**sizes, labels=labels)
    try:
        net.load_state_dict(tensors)
    except RuntimeError as e:
        raise ValueError(f"{path}: tensors do not match a Percept of {sizes}: {str(e).splitlines()[0]}") from None
    bad = [k for k, v in tensors.items() if v.is_floating_point() and not torch.isfinite(v).all()]
    if bad:
        raise ValueError(f"{path}: non-finite values in {bad[0]}")
    if (net.sd <= 0).any():
        raise ValueError(f"{path}: sd must be > 0, got {net.sd.tolist()}")
    return net.to(device) if device is not None else net
