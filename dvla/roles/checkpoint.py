"""Durable checkpoints of the learner group (written by rank 0), and the version high-water mark.

Layout and crash safety: docs/learners.md ("Checkpoints"). Nothing is unpickled: a checkpoint is
exactly the two safetensors files its manifest names; anything else (a ``torch.save`` pickle, an
``optimizer.pt``, a ``dir`` pointing elsewhere) is refused with a CheckpointError naming the file,
and the weights' checksum and each file's sha256 are verified before anything is applied.
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import save_file

from ..learn.checkpoint_files import (DIR_RE, FILES, MANIFEST, CheckpointError, read_current, read_json,
                                     read_safetensors, sha256)
from ..learn.optstate import optimizer_from_tensors, optimizer_to_tensors
from ..replication import replicated_tensors

HIGH_WATER = "high_water.json"
#: version numbers reserved per write of the high-water mark (one fsync per this many versions)
RESERVE = 16





@dataclass(frozen=True)
class Checkpoint:
    """A verified checkpoint: its version and env steps, and the published weights' checksum."""

    version: int
    env_steps: int
    checksum: str
    #: highest version that may have been published (restarts number above it)
    high_water: int


def save_checkpoint(directory: Path, state_dict: dict[str, torch.Tensor], optimizer: tuple[dict[str, torch.Tensor], str],
                    version: int, env_steps: int, checksum: str) -> Path:
    """Write one checkpoint and make it current; returns its directory."""
    directory.mkdir(parents=True, exist_ok=True)
    name = f"v{version:08d}"
    tmp = directory / f".{name}.tmp-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    files = {}
    save_file({k: v.detach().cpu().contiguous() for k, v in state_dict.items()}, str(tmp / "policy.safetensors"))
    tensors, meta = optimizer
    save_file(tensors, str(tmp / "optimizer.safetensors"), metadata={"dvla.optimizer": meta})
    for f in ("policy.safetensors", "optimizer.safetensors"):
        _fsync(tmp / f)
        files[f] = sha256(tmp / f)
    final = directory / name
    shutil.rmtree(final, ignore_errors=True)
    os.replace(tmp, final)
    _fsync(directory)
    previous = read_json(directory / MANIFEST)
    _write_json(directory / MANIFEST, {"format": 1, "version": version, "env_steps": env_steps, "checksum": checksum,
                                       "dir": name, "files": files})
    for old in directory.glob("v*"):  # keep this checkpoint and the one before it
        if old.name not in (name, (previous or {}).get("dir")) and old.is_dir():
            shutil.rmtree(old, ignore_errors=True)
    return final


def reserve_versions(directory: Path, version: int, reserved: int) -> int:
    """Before ``version`` is published: make sure the high-water mark on disk is at least it.
    Returns the new reservation (``reserved`` when it already covers ``version``)."""
    if version <= reserved:
        return reserved
    directory.mkdir(parents=True, exist_ok=True)
    _write_json(directory / HIGH_WATER, {"version": version + RESERVE})
    return version + RESERVE


def _check_names(source: str, weights: dict[str, torch.Tensor], expected: dict[str, torch.Tensor]) -> None:
    """CheckpointError unless ``weights`` names exactly the tensors the policy replicates."""
    if weights.keys() != expected.keys():
        missing, extra = sorted(expected.keys() - weights.keys()), sorted(weights.keys() - expected.keys())
        raise CheckpointError(f"{source}: not this policy's tensors (missing {missing[:3]}{'...' if len(missing) > 3 else ''}"
                              f", unexpected {extra[:3]}{'...' if len(extra) > 3 else ''})")


def load_checkpoint(directory: Path, policy: torch.nn.Module, optimizer: torch.optim.Optimizer,
                    flat_checksum: Any) -> Checkpoint | None:
    """Restore the current checkpoint into ``policy`` and ``optimizer`` (None when there is none).
    ``flat_checksum(policy)`` gives the checksum of the policy's flat weights, checked against
    the manifest's after loading. Raises CheckpointError before applying anything that fails."""
    manifest = read_json(directory / MANIFEST)
    high_doc = read_json(directory / HIGH_WATER) or {}
    if manifest is None:
        return None
    try:
        name, files = str(manifest["dir"]), manifest["files"]
        version, env_steps, checksum = int(manifest["version"]), int(manifest["env_steps"]), str(manifest["checksum"])
        high = int(high_doc.get("version", 0))
    except (KeyError, TypeError, ValueError) as err:
        raise CheckpointError(f"{directory / MANIFEST}: malformed ({type(err).__name__}: {err})") from err
    if not DIR_RE.fullmatch(name) or not isinstance(files, dict) or sorted(files) != sorted(FILES):
        raise CheckpointError(f"{directory / MANIFEST}: does not name a checkpoint (expected 'dir' v######## and"
                              f" 'files' exactly {', '.join(FILES)})")
    where = directory / name
    for f, digest in files.items():
        if not (where / f).is_file() or sha256(where / f) != digest:
            raise CheckpointError(f"{where / f}: missing or its sha256 differs from {directory / MANIFEST}")
    weights, _ = read_safetensors(where / "policy.safetensors")
    tensors, meta = read_safetensors(where / "optimizer.safetensors")
    try:
        opt_state = optimizer_from_tensors(tensors, meta["dvla.optimizer"], optimizer.state_dict())
    except (KeyError, ValueError, TypeError, AttributeError) as err:
        why = f"{type(err).__name__}: {err}"
        raise CheckpointError(f"{where / 'optimizer.safetensors'}: unusable optimizer state ({why})") from err
    # A checkpoint holds what replicates: a frozen base comes from its own checkpoint directory.
    expected = replicated_tensors(policy)
    _check_names(f"{where / 'policy.safetensors'}", weights, expected)
    backup = {k: v.clone() for k, v in expected.items()}
    try:
        policy.load_state_dict(weights, strict=False)
    except RuntimeError as err:  # shapes of another policy
        policy.load_state_dict(backup, strict=False)
        raise CheckpointError(f"{where / 'policy.safetensors'}: {str(err).splitlines()[0]}") from err
    got = flat_checksum(policy)
    if got != checksum:
        policy.load_state_dict(backup, strict=False)
        raise CheckpointError(f"{where / 'policy.safetensors'}: weights checksum {got} != {checksum} in the manifest")
    optimizer.load_state_dict(opt_state)
    return Checkpoint(version, env_steps, checksum, max(version, high))





def load_init_weights(path: str | Path, policy: torch.nn.Module) -> str:
    """Apply a warm start (``task.init_weights``) to ``policy``: a safetensors file, or a
    ``checkpoints`` directory whose current checkpoint is read with its sha256 checked. The file
    must hold exactly the tensors the policy replicates, each of its shape, every floating one
    finite (cast to the policy's dtype); otherwise CheckpointError names the file and the first
    key at fault and nothing is applied. Returns what was loaded, for the log."""
    where = Path(path)
    if where.is_dir():
        current = read_current(where)
        if current is None:
            raise CheckpointError(f"{where}: init_weights names a directory without a checkpoint (no {MANIFEST})")
        version, weights = current
        source = f"{where} (checkpoint v{version})"
    elif where.is_file():
        weights, _ = read_safetensors(where)
        source = str(where)
    else:
        raise CheckpointError(f"{where}: init_weights not found (expected a safetensors file or a checkpoints directory)")
    expected = replicated_tensors(policy)
    _check_names(source, weights, expected)
    for k, want in expected.items():
        got = weights[k]
        if tuple(got.shape) != tuple(want.shape):
            raise CheckpointError(f"{source}: {k} has shape {tuple(got.shape)}, the policy's is {tuple(want.shape)}")
        if want.is_floating_point() != got.is_floating_point() or (not want.is_floating_point() and got.dtype != want.dtype):
            raise CheckpointError(f"{source}: {k} is {got.dtype}, the policy's is {want.dtype}")
        if got.is_floating_point() and not bool(torch.isfinite(got).all()):
            raise CheckpointError(f"{source}: {k} holds non-finite values")
    with torch.no_grad():
        for k, want in expected.items():  # state-dict tensors share the parameters' storage
            want.copy_(weights[k].to(want.dtype))
    return source


def optimizer_tensors(optimizer: torch.optim.Optimizer) -> tuple[dict[str, torch.Tensor], str]:
    """A copy of the optimizer's state to checkpoint (taken between two updates)."""
    return optimizer_to_tensors(optimizer.state_dict())





def _fsync(path: Path) -> None:
    """fsync a file, or a directory (its entries: a rename in it is durable after this)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _write_json(path: Path, doc: dict[str, Any]) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    with open(tmp, "w") as f:
        json.dump(doc, f)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    _fsync(path.parent)





