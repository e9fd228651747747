"""Checkpoint directories of the Hugging Face VLA policies (``vla-tokens``, ``vla-flow``): one local
directory read with ``local_files_only=True``, same files at the same path on every host
(docs/policies.md, "The checkpoint directory", lists every file and ``dvla_policy.json`` key).

:func:`check_checkpoint` raises :class:`CheckpointError`, one line naming the path and what is
wrong; :func:`content_hash` fingerprints the files the policy reads (a LoRA run's frozen base is
never shipped, so hosts compare hashes). No torch or transformers here: the CLI imports it.
:mod:`.build` writes random-initialised checkpoints.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import xxhash

from ..spec import PolicySetupError

__all__ = ["CheckpointError", "CheckpointInfo", "check_checkpoint", "check_percept", "executed_chunk", "content_hash",
           "hash_files", "FAMILIES", "POLICY_FILE", "EXPERT_FILE", "PERCEPT_SIZES"]

FAMILIES = {"tokens": "vla-tokens", "flow": "vla-flow"}
"""dvla_policy.json family -> the policy name that loads it."""
POLICY_FILE = "dvla_policy.json"
EXPERT_FILE = "action_expert.safetensors"
_TOKENIZER_FILES = ("tokenizer.json", "tokenizer.model", "vocab.json")
_REQUIRED = {"tokens": ("n_bins",), "flow": ("denoise_steps", "expert")}
_COMMON = ("family", "action_dim", "max_chunk", "action_low", "action_high")
_BLOCK = 8 << 20
#: the sizes a perception file (tiny-vla's ``policy_kwargs.percept``, :mod:`.percept`) keeps in its metadata
PERCEPT_SIZES = ("outputs", "keypoints", "channels")


class CheckpointError(PolicySetupError):
    """A checkpoint directory cannot be used; the message is one line naming the path (a role
    reports it without a traceback, dvla plan/up before starting anything)."""


@dataclass(frozen=True)
class CheckpointInfo:
    """What :func:`check_checkpoint` read from a checkpoint directory."""

    path: Path
    family: str
    #: dvla_policy.json as read
    settings: Mapping[str, Any]
    action_dim: int
    max_chunk: int
    action_low: tuple[float, ...]
    action_high: tuple[float, ...]


def _fail(path: Path, what: str) -> CheckpointError:
    return CheckpointError(f"{path}: {' '.join(str(what).split())}")


def _check_safetensors(file: Path) -> dict[str, Any]:
    """Header and size of one safetensors file: a truncated copy fails here, in one line. Returns
    the header (tensor name -> dtype, shape, data_offsets, in the file's order)."""
    size = file.stat().st_size
    try:
        with open(file, "rb") as f:
            n = int.from_bytes(f.read(8), "little")
            if size < 8 or n > size - 8:
                raise ValueError(f"header of {n} bytes in a file of {size}")
            header = json.loads(f.read(n))
        end = max((int(v["data_offsets"][1]) for k, v in header.items() if k != "__metadata__"), default=0)
    except (ValueError, KeyError, TypeError, IndexError) as err:
        raise _fail(file, f"corrupt safetensors file ({err})") from None
    if 8 + n + end > size:
        raise _fail(file, f"truncated safetensors file: its header needs {8 + n + end} bytes, the file has {size}")
    return header


def check_percept(path: str | Path) -> tuple[dict[str, int], dict[str, str]]:
    """The sizes and the metadata of a perception file (:mod:`.percept`), from its header alone:
    a file that is missing, not safetensors, truncated or without integer sizes is one line
    naming the file (:class:`CheckpointError`)."""
    path = Path(path)
    if not path.is_file():
        raise _fail(path, "No such file (a perception file: python -m benchmarks.learn_vla pretrain)")
    try:
        header = _check_safetensors(path)
    except CheckpointError as err:
        raise _fail(path, f"not a safetensors file, so not a perception file ({str(err).removeprefix(f'{path}: ')})") from None
    meta = header.get("__metadata__") or {}
    try:
        return {k: int(meta[k]) for k in PERCEPT_SIZES}, meta
    except (KeyError, ValueError, TypeError):
        raise _fail(path, f"metadata needs integer {', '.join(PERCEPT_SIZES)} (not a perception file); has {meta}") from None


def _weight_files(path: Path) -> tuple[Path, ...]:
    files = sorted(p for p in path.glob("*.safetensors") if p.name != EXPERT_FILE)
    for index in sorted(path.glob("*.safetensors.index.json")):
        try:
            shards = set(json.loads(index.read_text())["weight_map"].values())
        except (ValueError, KeyError, AttributeError) as err:
            raise _fail(index, f"not a safetensors index ({type(err).__name__}: {err})") from None
        missing = sorted(s for s in shards if not (path / s).is_file())
        if missing:
            raise _fail(path, f"{index.name} names shard {missing[0]} which is not in the directory")
    if not files:
        raise _fail(path, "no *.safetensors weights in the checkpoint directory")
    return tuple(files)


def check_checkpoint(path: str | Path, family: str) -> CheckpointInfo:
    """Check a checkpoint directory for policy family ``family`` (``"tokens"`` / ``"flow"``)."""
    path = Path(path).expanduser()
    if not path.exists():
        raise _fail(path, "checkpoint directory does not exist")
    if not path.is_dir():
        raise _fail(path, "checkpoint is not a directory")
    if not (path / "config.json").is_file():
        raise _fail(path, "config.json missing (a transformers model directory is expected)")
    weights = _weight_files(path)
    if not any((path / name).is_file() for name in _TOKENIZER_FILES):
        raise _fail(path, f"tokenizer files missing (none of {', '.join(_TOKENIZER_FILES)})")
    policy_file = path / POLICY_FILE
    if not policy_file.is_file():
        raise _fail(path, f"{POLICY_FILE} missing (it names the family and the action head, see "
                          "dvla/learn/vla/checkpoint.py)")
    try:
        settings = json.loads(policy_file.read_text())
    except ValueError as err:
        raise _fail(policy_file, f"not JSON ({err})") from None
    if not isinstance(settings, dict):
        raise _fail(policy_file, "must hold a JSON object")
    if "family" not in settings:
        raise _fail(policy_file, "missing key family")
    got = settings["family"]
    if got not in _REQUIRED:
        raise _fail(policy_file, f"family {got!r} is not one of {', '.join(map(repr, _REQUIRED))}")
    if got != family:
        raise _fail(path, f"is a {got!r} checkpoint ({POLICY_FILE} family), policy {FAMILIES[family]} needs {family!r}")
    missing = [k for k in _COMMON + _REQUIRED[family] if k not in settings]
    if missing:
        raise _fail(policy_file, f"missing key {', '.join(missing)}")
    try:
        action_dim, max_chunk = int(settings["action_dim"]), int(settings["max_chunk"])
        bounds = [tuple(float(x) for x in settings[k]) for k in ("action_low", "action_high")]
        if family == "tokens":
            int(settings["n_bins"])
        else:
            int(settings["denoise_steps"])
            [int(settings["expert"][k]) for k in ("width", "layers", "heads", "mlp")]
    except (TypeError, ValueError, KeyError) as err:
        raise _fail(policy_file, f"bad value ({type(err).__name__}: {err}): action_dim, max_chunk, n_bins, "
                                 "denoise_steps are integers, action_low / action_high lists of numbers, expert "
                                 "holds integer width, layers, heads, mlp") from None
    if action_dim < 1 or max_chunk < 1:
        raise _fail(policy_file, f"action_dim {action_dim} and max_chunk {max_chunk} must be >= 1")
    if any(len(b) != action_dim for b in bounds):
        raise _fail(policy_file, f"action_low / action_high need action_dim={action_dim} numbers each, "
                                 f"got {len(bounds[0])} and {len(bounds[1])}")
    if family == "flow" and not (path / EXPERT_FILE).is_file():
        raise _fail(path, f"{EXPERT_FILE} missing (the flow family's action expert)")
    for file in weights + ((path / EXPERT_FILE,) if family == "flow" else ()):
        _check_safetensors(file)
    return CheckpointInfo(path, family, settings, action_dim, max_chunk, bounds[0], bounds[1])


def executed_chunk(info: CheckpointInfo, act_dim: int) -> int:
    """Actions executed per decision: ``act_dim / action_dim``, at most ``max_chunk``."""
    act_dim = int(act_dim)
    if act_dim < 1 or act_dim % info.action_dim:
        raise ValueError(f"{info.path}: act_dim {act_dim} is not a multiple of the checkpoint's action_dim "
                         f"{info.action_dim} ({POLICY_FILE})")
    chunk = act_dim // info.action_dim
    if chunk > info.max_chunk:
        raise ValueError(f"{info.path}: act_dim {act_dim} is a chunk of {chunk} actions of {info.action_dim}, more "
                         f"than the checkpoint's max_chunk {info.max_chunk} ({POLICY_FILE})")
    return chunk


# --- content hash -------------------------------------------------------------------------------

_HASHED = re.compile(r"(config\.json|preprocessor_config\.json|dvla_policy\.json|special_tokens_map\.json"
                     r"|tokenizer.*|vocab\.json|merges\.txt|.*\.safetensors(\.index\.json)?)")
_HASH_CACHE: dict[tuple, str] = {}


def content_hash(path: str | Path) -> str:
    """xxh3-128 hex over the names and bytes of the files a policy reads from ``path`` (config,
    tokenizer, dvla_policy.json, every safetensors file)."""
    path = Path(path).expanduser().resolve()
    return hash_files([(p.name, p) for p in sorted(path.iterdir()) if p.is_file() and _HASHED.fullmatch(p.name)])


def hash_files(files: Sequence[tuple[str, Path]]) -> str:
    """xxh3-128 hex over ``(label, file)`` pairs: each label, size and content in order (labels, not
    paths, so copies at other paths agree), cached per process on (path, size, mtime) since every
    copy of a policy asks."""
    stats = [(label, p, p.stat()) for label, p in files]
    key = tuple((label, str(p), st.st_size, st.st_mtime_ns) for label, p, st in stats)
    if key not in _HASH_CACHE:
        h = xxhash.xxh3_128()
        for label, p, st in stats:
            h.update(label.encode() + b"\0" + st.st_size.to_bytes(8, "little"))
            with open(p, "rb") as f:
                while block := f.read(_BLOCK):
                    h.update(block)
        _HASH_CACHE[key] = h.hexdigest()
    return _HASH_CACHE[key]
