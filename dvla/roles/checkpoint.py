"""Checkpoints of the actor: policy weights as safetensors, optimizer state and version beside it.

Written atomically (temp file + rename) so a crash mid-write never leaves a torn checkpoint;
`load_checkpoint` is what a restarted actor resumes from.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import load_file, save_file


def save_checkpoint(
    directory: Path, state_dict: dict[str, torch.Tensor], learner: Any, version: int, env_steps: int
) -> Path:
    directory.mkdir(parents=True, exist_ok=True)
    weights = directory / "policy.safetensors"
    tmp = weights.with_suffix(".tmp")
    save_file({k: v.detach().cpu().contiguous() for k, v in state_dict.items()}, str(tmp))
    os.replace(tmp, weights)
    opt = directory / "optimizer.pt"
    tmp = opt.with_suffix(".tmp")
    torch.save(learner.state_dict(), tmp)
    os.replace(tmp, opt)
    meta = directory / "meta.json"
    tmp = meta.with_suffix(".tmp")
    tmp.write_text(json.dumps({"version": version, "env_steps": env_steps}))
    os.replace(tmp, meta)
    return weights


def load_checkpoint(directory: Path, policy: torch.nn.Module, learner: Any) -> dict[str, int] | None:
    """Restore policy and optimizer; returns {"version", "env_steps"} or None when absent."""
    meta = directory / "meta.json"
    weights = directory / "policy.safetensors"
    if not meta.exists() or not weights.exists():
        return None
    policy.load_state_dict(load_file(str(weights)))
    opt = directory / "optimizer.pt"
    if opt.exists():
        learner.load_state_dict(torch.load(opt, weights_only=False))
    return json.loads(meta.read_text())
