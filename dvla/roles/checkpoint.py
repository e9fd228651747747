"""Durable checkpoints of the learner group (written by rank 0), and the version high-water mark.

Layout of ``RUN_DIR/checkpoints/``::

    MANIFEST.json          the current checkpoint: version, env steps, checksum, files + sha256
    v00000040/             one checkpoint: policy.safetensors (the weights *as published* with
                           that version), optimizer.safetensors (tensors; the rest as JSON metadata)
    high_water.json        versions up to here may have been published: a restart numbers above it

Every file is written to a temporary name, fsynced and renamed, and the directory fsynced, so
a crash at any point leaves the previous checkpoint whole; MANIFEST.json is replaced last and
names one consistent set. Nothing is unpickled on load; the weights' checksum and each file's
sha256 are verified before anything is applied.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import load_file, save_file

from ..learn.optstate import optimizer_from_tensors, optimizer_to_tensors

MANIFEST = "MANIFEST.json"
HIGH_WATER = "high_water.json"
#: version numbers reserved per write of the high-water mark (one fsync per this many versions)
RESERVE = 16


class CheckpointError(RuntimeError):
    """A checkpoint that cannot be used as it is (named file, what is wrong)."""


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
        files[f] = _sha256(tmp / f)
    final = directory / name
    shutil.rmtree(final, ignore_errors=True)
    os.replace(tmp, final)
    _fsync(directory)
    previous = _read_json(directory / MANIFEST)
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


def load_checkpoint(directory: Path, policy: torch.nn.Module, optimizer: torch.optim.Optimizer,
                    flat_checksum: Any) -> Checkpoint | None:
    """Restore the current checkpoint into ``policy`` and ``optimizer`` (None when there is none).
    ``flat_checksum(policy)`` gives the checksum of the policy's flat weights, checked against
    the manifest's after loading. Raises CheckpointError before applying anything that fails."""
    manifest = _read_json(directory / MANIFEST)
    high = (_read_json(directory / HIGH_WATER) or {}).get("version", 0)
    if manifest is None:
        return None
    where = directory / str(manifest.get("dir"))
    for f, digest in manifest.get("files", {}).items():
        if not (where / f).is_file() or _sha256(where / f) != digest:
            raise CheckpointError(f"{where / f}: missing or its sha256 differs from {directory / MANIFEST}")
    weights = load_file(str(where / "policy.safetensors"))
    tensors = load_file(str(where / "optimizer.safetensors"))
    with open(where / "optimizer.safetensors", "rb") as fh:  # safetensors' header: 8-byte length, JSON
        header = json.loads(fh.read(int.from_bytes(fh.read(8), "little")))
    try:
        opt_state = optimizer_from_tensors(tensors, header["__metadata__"]["dvla.optimizer"], optimizer.state_dict())
    except (KeyError, ValueError) as err:
        raise CheckpointError(f"{where / 'optimizer.safetensors'}: {err}") from err
    backup = {k: v.clone() for k, v in policy.state_dict().items()}
    policy.load_state_dict(weights)
    got = flat_checksum(policy)
    if got != manifest["checksum"]:
        policy.load_state_dict(backup)
        raise CheckpointError(f"{where / 'policy.safetensors'}: weights checksum {got} != {manifest['checksum']} in the manifest")
    optimizer.load_state_dict(opt_state)
    version = int(manifest["version"])
    return Checkpoint(version, int(manifest["env_steps"]), manifest["checksum"], max(version, int(high)))


def optimizer_tensors(optimizer: torch.optim.Optimizer) -> tuple[dict[str, torch.Tensor], str]:
    """A copy of the optimizer's state to checkpoint (taken between two updates)."""
    return optimizer_to_tensors(optimizer.state_dict())


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(1 << 20):
            h.update(block)
    return h.hexdigest()


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


def _read_json(path: Path) -> dict[str, Any] | None:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except ValueError as err:
        raise CheckpointError(f"{path}: not JSON ({err})") from err

