"""The files of a learner checkpoint, read without a live policy (``dvla export`` reads them from
outside the run; :mod:`dvla.roles.checkpoint` writes and restores them). Layout and crash safety:
docs/learners.md ("Checkpoints"). Nothing is unpickled: a file that is not safetensors is refused
with a CheckpointError naming it, and each file's sha256 is checked against the manifest."""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError, safe_open

__all__ = ["MANIFEST", "FILES", "DIR_RE", "CheckpointError", "read_json", "sha256", "read_safetensors", "read_current"]

MANIFEST = "MANIFEST.json"
#: the files of one checkpoint, all safetensors (tensors plus JSON metadata: no pickle)
FILES = ("policy.safetensors", "optimizer.safetensors")
#: name of a checkpoint's directory
DIR_RE = re.compile(r"v[0-9]{8}")
#: how files that are not safetensors begin: pickle protocol 2+ and torch.save's zip archive
_PICKLE_MAGIC = (b"\x80", b"PK\x03\x04")


class CheckpointError(RuntimeError):
    """A checkpoint that cannot be used as it is (named file, what is wrong)."""


def read_json(path: Path) -> dict[str, Any] | None:
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except ValueError as err:
        raise CheckpointError(f"{path}: not JSON ({err})") from err
    if not isinstance(doc, dict):
        raise CheckpointError(f"{path}: not a JSON object")
    return doc



def sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(1 << 20):
            h.update(block)
    return h.hexdigest()


def read_safetensors(path: Path) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """Tensors and metadata of a safetensors file. Anything else is refused unread: never
    ``torch.load`` or pickle, whose loading runs code the file chooses."""
    with open(path, "rb") as f:
        head = f.read(9)
    # safetensors: an 8-byte little-endian header length, then the JSON header's "{". The length's
    # first byte may be 0x80 (a header of 128, 384, ... bytes), so that alone says nothing.
    if head[8:9] != b"{" and head.startswith(_PICKLE_MAGIC):
        raise CheckpointError(f"{path}: a pickle (torch.save) file, refused unread: checkpoints are safetensors only")
    try:
        with safe_open(str(path), framework="pt") as f:
            return {k: f.get_tensor(k) for k in f.keys()}, dict(f.metadata() or {})
    except (SafetensorError, OSError, ValueError) as err:
        reason = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise CheckpointError(f"{path}: not a safetensors file, refused ({reason})") from err


def read_current(directory: Path) -> tuple[int, dict[str, torch.Tensor]] | None:
    """The current checkpoint's version and policy tensors (the replicated ones: a LoRA run's
    adapters and heads), each file's sha256 checked against the manifest; None when there is none.
    For readers outside the run (``dvla export``): nothing is applied to a live policy."""
    manifest = read_json(directory / MANIFEST)
    if manifest is None:
        return None
    try:
        name, files, version = str(manifest["dir"]), manifest["files"], int(manifest["version"])
        digest = str(files["policy.safetensors"])
    except (KeyError, TypeError, ValueError) as err:
        raise CheckpointError(f"{directory / MANIFEST}: malformed ({type(err).__name__}: {err})") from err
    path = directory / name / "policy.safetensors"
    if not DIR_RE.fullmatch(name) or not path.is_file() or sha256(path) != digest:
        raise CheckpointError(f"{path}: missing or its sha256 differs from {directory / MANIFEST}")
    return version, read_safetensors(path)[0]

