"""Directories of the published OpenVLA and OpenVLA-OFT checkpoints (the Prismatic Hugging Face
layout of ``openvla/openvla-7b`` and ``moojink/openvla-7b-oft-finetuned-libero-*``): check one,
read what the policy needs (sizes from the safetensors headers, the image processor's settings,
the dataset statistics of one dataset key, the executed chunk), load the weights and OFT's
component pickles safely, convert those pickles to safetensors once, fingerprint the files, and
write a trained copy back in the same layout (:func:`export_openvla`).

Every problem is a :class:`CheckpointError`, one line naming the file (or key) and what is wrong.
No torch at module level (the CLI imports this): the weights-only check of a ``.pt`` here is a
restricted unpickler that only knows tensors in a dict and reads no tensor data;
:func:`read_oft_components` then loads with ``torch.load(weights_only=True)`` and nothing else.

Families:

- ``openvla``: the model emits 7 action tokens one at a time (the last ``n_action_bins`` ids of
  the tokenizer's vocabulary), de-tokenised to bin centres and un-normalised with the q01/q99 of
  one dataset key (config.json ``norm_stats``, or dataset_statistics.json for a key only it has).
  An OFT directory is refused as ``openvla``: its language model was fine-tuned to feed the L1
  action head in one bidirectional pass, and its lm_head does not emit the actions.
- ``openvla-oft``: the same files plus ``action_head--<step>_checkpoint.pt`` (and optionally
  ``proprio_projector--<step>_checkpoint.pt``), torch pickles of DDP state dicts (keys prefixed
  ``module.``). dataset_statistics.json replaces config.json's ``norm_stats`` as upstream
  inference does (config.json keeps the base model's). Upstream fixes the chunk, the number of
  images and the normalisation per robot platform in code (prismatic/vla/constants.py); the
  platform is told here by the head's action dim and the projector's proprio dim (LIBERO: 8 steps
  of 7 dims, 2 images, q01/q99). The diffusion and FiLM variants are refused.
"""

from __future__ import annotations

import collections
import json
import os
import pickle
import re
import shutil
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, NamedTuple

import xxhash

from .checkpoint import CheckpointError, _check_safetensors, _fail, hash_files
from .lerobot_format import _read_json, _weight_files, resolve_checkpoint

__all__ = ["OPENVLA_FAMILIES", "COMPONENTS", "STATISTICS_FILE", "NORM_BOUNDS", "OpenVLACheckpoint", "check_openvla",
           "read_state_dict", "read_oft_components", "convert_components", "content_hash", "export_openvla"]

OPENVLA_FAMILIES = ("openvla", "openvla-oft")
#: the OFT component files read, in the order of OFTHeads.from_state_dicts' arguments
COMPONENTS = ("action_head", "proprio_projector")
STATISTICS_FILE = "dataset_statistics.json"
DDP_PREFIX = "module."
#: OFT components dvla does not run: their presence means another action head / vision path
_UNSUPPORTED = {"noisy_action_projector": "the diffusion action head", "vision_backbone": "FiLM"}
#: the fused featurizer the model implements (config timm_model_ids)
_TOWERS = ("vit_large_patch14_reg4_dinov2.lvd142m", "vit_so400m_patch14_siglip_224")
#: files the policy reads besides the weights (hashed), when present
_READ_FILES = ("config.json", "generation_config.json", "preprocessor_config.json", "processor_config.json",
               STATISTICS_FILE, "tokenizer.json", "tokenizer.model", "tokenizer_config.json",
               "special_tokens_map.json", "added_tokens.json")
#: files copied byte for byte by an export (the above, the upstream .py files, READMEs)
_SIDE_FILE = re.compile(r".*\.(json|model|txt|py|md)")


class _Platform(NamedTuple):
    name: str
    action_dim: int
    proprio_dim: int
    chunk_size: int
    num_images: int
    normalization: str


#: prismatic/vla/constants.py's platforms, plus the cameras of each platform's published evaluation
_PLATFORMS = (_Platform("LIBERO", 7, 8, 8, 2, "bounds_q99"), _Platform("ALOHA", 14, 14, 25, 3, "bounds"),
              _Platform("BRIDGE", 7, 7, 5, 1, "bounds_q99"))
#: normalisation -> the statistics it reads (low, high)
NORM_BOUNDS = {"bounds_q99": ("q01", "q99"), "bounds": ("min", "max")}


@dataclass(frozen=True)
class OpenVLACheckpoint:
    """What :func:`check_openvla` read from a checkpoint directory."""

    #: the directory (absolute; a Hugging Face cache snapshot when a repo id was given)
    path: Path
    #: "openvla" or "openvla-oft"
    family: str
    #: config.json as read
    config: Mapping[str, Any]
    #: the safetensors shards in name order (or the single model.safetensors)
    weights: tuple[Path, ...]
    #: model.safetensors.index.json when sharded, else None
    weight_index: Path | None
    #: tensor name -> shape, shard by shard in each file's order
    shapes: Mapping[str, tuple[int, ...]]
    #: the language model's hidden size (embed_tokens' width)
    llm_dim: int
    #: action bins (config n_action_bins); the bin centres are one fewer
    n_action_bins: int
    #: the tokenizer's vocabulary size as upstream de-tokenises with it: text_config.vocab_size minus
    #: pad_to_multiple_of; the action tokens are its last n_action_bins ids
    tokenizer_vocab_size: int
    #: (H, W) each image is resized to; "resize-naive" (the only strategy read), bicubic
    image_size: tuple[int, int]
    #: per vision tower (DINOv2, SigLIP): the normalisation mean and std of each RGB channel
    image_means: tuple[tuple[float, float, float], ...]
    image_stds: tuple[tuple[float, float, float], ...]
    #: the tokenizer's files present (tokenizer.json is always among them)
    tokenizer_files: tuple[Path, ...]
    #: the dataset key whose statistics are used, every key the checkpoint has, and the file read
    dataset: str
    datasets: tuple[str, ...]
    stats_file: Path
    #: statistics of the dataset key: "q01", "q99", "min", "max", ... (floats) and "mask" (bools:
    #: False dims, the gripper, are not (un)normalised)
    action_stats: Mapping[str, tuple]
    #: OFT with a proprio projector: the proprio statistics (same form), else None
    proprio_stats: Mapping[str, tuple] | None
    #: "bounds_q99" (q01/q99) or "bounds" (min/max), and the epsilon added to the span (OFT 1e-8)
    normalization: str
    norm_eps: float
    #: dims of one action, actions per model call (all executed; 1 for openvla), images per call
    action_dim: int
    chunk_size: int
    num_images: int
    #: OFT: proprio dims the projector takes, else None
    proprio_dim: int | None
    #: OFT: component name (COMPONENTS) -> the file read: <stem>.safetensors when converted, else the .pt
    components: Mapping[str, Path]
    #: OFT: component name -> tensor name (no "module.") -> shape
    component_shapes: Mapping[str, Mapping[str, tuple[int, ...]]]

    @property
    def action_token_ids(self) -> range:
        """The ids of the action tokens (31744..31999 for Llama-2's vocabulary)."""
        return range(self.tokenizer_vocab_size - self.n_action_bins, self.tokenizer_vocab_size)


# --- torch pickles, weights only, without torch ---------------------------------------------------


class _TensorInfo(NamedTuple):
    dtype: str  # safetensors' name ("BF16", "F32", ...)
    shape: tuple[int, ...]
    storage: str  # the zip member under data/
    offset: int
    contiguous: bool


class _StorageType(NamedTuple):
    dtype: str


class _Storage(NamedTuple):
    dtype: str
    key: str


_STORAGE_DTYPES = {"FloatStorage": "F32", "BFloat16Storage": "BF16", "HalfStorage": "F16", "DoubleStorage": "F64",
                   "LongStorage": "I64", "IntStorage": "I32", "ShortStorage": "I16", "CharStorage": "I8",
                   "ByteStorage": "U8", "BoolStorage": "BOOL"}
_ITEMSIZE = {"F32": 4, "BF16": 2, "F16": 2, "F64": 8, "I64": 8, "I32": 4, "I16": 2, "I8": 1, "U8": 1, "BOOL": 1}


def _rebuild_tensor(storage, offset, shape, stride, *_):
    if not isinstance(storage, _Storage) or not all(isinstance(n, int) and n >= 0 for n in (offset, *shape, *stride)):
        raise pickle.UnpicklingError("a tensor without a storage of its own or with a malformed shape")
    shape, stride = tuple(shape), tuple(stride)
    dense, step = [], 1
    for n in reversed(shape):
        dense.insert(0, step)
        step *= n
    contiguous = all(s == d for s, d, n in zip(stride, dense, shape) if n > 1)  # size-1 dims: any stride
    return _TensorInfo(storage.dtype, shape, storage.key, offset, contiguous)


class _WeightsOnlyUnpickler(pickle.Unpickler):
    """Knows an (Ordered)dict of tensors and nothing else: any other global is refused before it
    is looked up, and tensors become :class:`_TensorInfo` (their data is not read)."""

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) == ("collections", "OrderedDict"):
            return collections.OrderedDict
        if module == "torch._utils" and name == "_rebuild_tensor_v2":
            return _rebuild_tensor
        if module == "torch._utils" and name == "_rebuild_parameter":
            return lambda data, *_: data
        if module == "torch" and name in _STORAGE_DTYPES:
            return _StorageType(_STORAGE_DTYPES[name])
        raise pickle.UnpicklingError(f"it needs {module}.{name}")

    def persistent_load(self, pid: Any) -> Any:
        if not (isinstance(pid, tuple) and len(pid) == 5 and pid[0] == "storage" and isinstance(pid[1], _StorageType)):
            raise pickle.UnpicklingError(f"unknown persistent id {str(pid)[:60]}")
        return _Storage(pid[1].dtype, str(pid[2]))


def _pickle_member(archive: zipfile.ZipFile, file: Path) -> str:
    names = [n for n in archive.namelist() if n.endswith("/data.pkl") or n == "data.pkl"]
    if len(names) != 1:
        raise _fail(file, "not a torch.save archive (no single data.pkl in it)")
    return names[0]


def _pt_tensors(file: Path) -> dict[str, _TensorInfo]:
    """The tensors of a torch.save file (keys as stored), refusing a pickle that is not a
    weights-only state dict; nothing outside the allowed globals is imported or called."""
    try:
        with zipfile.ZipFile(file) as archive:
            member = _pickle_member(archive, file)
            found = _WeightsOnlyUnpickler(archive.open(member)).load()
    except zipfile.BadZipFile:
        raise _fail(file, "not a torch.save zip archive (legacy or corrupt file), refused") from None
    except CheckpointError:
        raise
    except Exception as err:  # whatever a hostile or broken pickle raises: one line, nothing run
        raise _fail(file, f"not a weights-only state dict, refused unloaded ({err or type(err).__name__})") from None
    if not isinstance(found, dict) or not found or not all(
            isinstance(k, str) and isinstance(v, _TensorInfo) for k, v in found.items()):
        raise _fail(file, "holds no state dict (a dict of tensors is expected), refused")
    return dict(found)


def _component_tensors(file: Path) -> dict[str, tuple[str, tuple[int, ...]]]:
    """name (without "module.") -> (dtype, shape) of a component file, .pt or .safetensors."""
    if file.suffix == ".safetensors":
        header = _check_safetensors(file)
        info = {k: (header[k]["dtype"], tuple(header[k]["shape"])) for k in _stored_order(header)}
    else:
        info = {k: (v.dtype, v.shape) for k, v in _pt_tensors(file).items()}
    return {_strip(k): v for k, v in info.items()}


def _stored_order(header: Mapping[str, Any]) -> list[str]:
    """A converted file's tensor names in the .pt's order (kept in its metadata; safetensors sorts)."""
    names = [k for k in header if k != "__metadata__"]
    try:
        order = json.loads((header.get("__metadata__") or {}).get("key_order") or "[]")
    except ValueError:
        return names
    return order if isinstance(order, list) and sorted(map(str, order)) == sorted(names) else names


def _strip(key: str) -> str:
    return key[len(DDP_PREFIX):] if key.startswith(DDP_PREFIX) else key


# --- checking a directory ---------------------------------------------------------------------------


def _component_files(root: Path) -> dict[str, list[Path]]:
    """Component name -> its files (<stem>.pt and/or <stem>.safetensors), found as upstream finds
    them: the name and "checkpoint" in the file name."""
    found: dict[str, list[Path]] = {}
    for file in sorted(root.iterdir()):
        if file.is_file() and file.suffix in (".pt", ".safetensors") and "checkpoint" in file.name:
            for name in (*COMPONENTS, *_UNSUPPORTED):
                if name in file.name:
                    found.setdefault(name, []).append(file)
    return found


def _pick_component(root: Path, name: str, files: list[Path]) -> Path:
    stems = sorted({f.stem for f in files})
    if len(stems) > 1:
        raise _fail(root, f"{len(stems)} {name} checkpoints ({', '.join(stems)}): keep one, as upstream loads "
                          "exactly one")
    converted = root / f"{stems[0]}.safetensors"
    return converted if converted.is_file() else root / f"{stems[0]}.pt"


def _shape(root: Path, shapes: Mapping[str, tuple[int, ...]], key: str, ndim: int, what: str) -> tuple[int, ...]:
    shape = shapes.get(key)
    if shape is None or len(shape) != ndim:
        raise _fail(root, f"the weights have no {ndim}-D {key} (found {shape}): not {what}")
    return shape


def _numbers(file: Path, where: str, value: Any, n: int | None, kind: type = float) -> tuple:
    ok = isinstance(value, list) and all(isinstance(x, bool) if kind is bool else
                                         isinstance(x, (int, float)) and not isinstance(x, bool) for x in value)
    if not ok or (n is not None and len(value) != n) or not value:
        want = f"{n} " if n is not None else ""
        got = f"{len(value)} values" if isinstance(value, list) else repr(value)[:40]
        raise _fail(file, f"{where} must be a list of {want}{'booleans' if kind is bool else 'numbers'}, got {got}")
    return tuple(kind(x) for x in value)


def _stats(file: Path, entry: Any, where: str, normalization: str, dim: int | None, what: str) -> dict[str, tuple]:
    """One statistics entry ({q01, q99, min, max, mask, ...}) checked for what the normalisation reads."""
    if not isinstance(entry, dict):
        raise _fail(file, f"{where} is missing (the {what} statistics)")
    low, high = NORM_BOUNDS[normalization]
    out: dict[str, tuple] = {}
    for name in (low, high):
        if name not in entry:
            raise _fail(file, f"{where}.{name} is missing ({normalization} normalisation reads {low} and {high})")
        out[name] = _numbers(file, f"{where}.{name}", entry[name], dim)
        dim = len(out[name])
    for name, value in entry.items():  # the others (mean, std, ...) for whoever wants them, when well-formed
        if name not in out and name != "mask" and isinstance(value, list) and value and all(
                isinstance(x, (int, float)) and not isinstance(x, bool) for x in value):
            out[name] = tuple(float(x) for x in value)
    out["mask"] = _numbers(file, f"{where}.mask", entry["mask"], dim, bool) if "mask" in entry else (True,) * dim
    return out


def _dataset_stats(root: Path, config: Mapping[str, Any], family: str, dataset: str | None
                   ) -> tuple[str, tuple[str, ...], Path, dict[str, Any]]:
    """(key, every key, file, the key's entry). OFT: dataset_statistics.json replaces config.json's
    norm_stats; openvla: config.json's norm_stats, then the file's keys."""
    sources = []
    statistics = root / STATISTICS_FILE
    if statistics.is_file():
        doc = _read_json(statistics, f"{STATISTICS_FILE} missing")
        if not isinstance(doc, dict):
            raise _fail(statistics, "must hold a JSON object of dataset keys")
        sources.append((statistics, doc))
    norm_stats = config.get("norm_stats")
    if norm_stats is not None and not isinstance(norm_stats, dict):
        raise _fail(root / "config.json", "norm_stats must be a JSON object of dataset keys")
    if norm_stats and family == "openvla":
        sources.insert(0, (root / "config.json", norm_stats))
    elif norm_stats and not sources:  # upstream OFT warns and keeps config.json's
        sources.append((root / "config.json", norm_stats))
    known = tuple(dict.fromkeys(k for _, doc in sources for k in doc))
    if not known:
        raise _fail(root, f"no dataset statistics: config.json has no norm_stats and there is no {STATISTICS_FILE}")
    if dataset is None:
        if len(known) > 1:
            raise _fail(root, f"has statistics for {len(known)} datasets ({', '.join(known)}): name one "
                              "(policy_kwargs.dataset)")
        dataset = known[0]
    for file, doc in sources:
        if dataset in doc:
            return dataset, known, file, doc[dataset]
    names = " or ".join(str(f.name) for f, _ in sources)
    raise _fail(root, f"no statistics for dataset {dataset!r} in {names} (known: {', '.join(known)})")


def _image_settings(root: Path, config: Mapping[str, Any]) -> dict[str, Any]:
    file = root / "preprocessor_config.json"
    pre = _read_json(file, "preprocessor_config.json missing (the image processor's settings)")
    if not isinstance(pre, dict):
        raise _fail(file, "must hold a JSON object")
    if tuple(config.get("timm_model_ids") or ()) != _TOWERS or not config.get("use_fused_vision_backbone"):
        raise _fail(root / "config.json", f"vision backbone {config.get('vision_backbone_id')!r} (timm_model_ids "
                                          f"{config.get('timm_model_ids')}): only the fused DINOv2 + SigLIP "
                                          "featurizer (dinosiglip-vit-so-224px) is supported")
    strategy = pre.get("image_resize_strategy", config.get("image_resize_strategy"))
    if strategy != "resize-naive":
        raise _fail(file, f"image_resize_strategy {strategy!r} is not supported (resize-naive is)")
    sizes, interps = pre.get("input_sizes"), pre.get("interpolations")
    params = pre.get("tvf_normalize_params") or [{"mean": m, "std": s} for m, s in
                                                 zip(pre.get("means") or (), pre.get("stds") or ())]
    if not (isinstance(sizes, list) and isinstance(interps, list) and isinstance(params, list)
            and len(sizes) == len(interps) == len(params) == 2 and all(isinstance(p, dict) for p in params)):
        raise _fail(file, "input_sizes, interpolations and means/stds must each name the 2 vision towers")
    if not all(s == sizes[0] for s in sizes) or not isinstance(sizes[0], list) or len(sizes[0]) != 3 \
            or sizes[0][0] != 3 or not all(isinstance(n, int) and n > 0 for n in sizes[0]):
        raise _fail(file, f"input_sizes {sizes}: both towers must take the same [3, H, W]")
    if any(i != "bicubic" for i in interps):
        raise _fail(file, f"interpolations {interps} are not supported (bicubic is)")
    means = tuple(_numbers(file, f"tower {i} mean", p.get("mean"), 3) for i, p in enumerate(params))
    stds = tuple(_numbers(file, f"tower {i} std", p.get("std"), 3) for i, p in enumerate(params))
    return dict(image_size=(int(sizes[0][1]), int(sizes[0][2])), image_means=means, image_stds=stds)


def _oft_fields(root: Path, components: dict[str, Path], llm_dim: int, chunk_size: int | None) -> dict[str, Any]:
    shapes = {name: _component_tensors(file) for name, file in components.items()}
    head = {k: s for k, (_, s) in shapes["action_head"].items()}
    head_file = components["action_head"]
    out_shape = head.get("model.fc2.weight")
    in_shape = head.get("model.layer_norm1.weight")
    if out_shape is None or in_shape is None or len(out_shape) != 2 or len(in_shape) != 1:
        raise _fail(head_file, "has no model.fc2.weight / model.layer_norm1.weight: not an L1-regression action head")
    action_dim = out_shape[0]
    if in_shape[0] != action_dim * llm_dim:
        raise _fail(head_file, f"reads {in_shape[0]} features per step, the language model gives {action_dim} x "
                               f"{llm_dim}")
    proprio_dim = None
    if "proprio_projector" in shapes:
        fc1 = shapes["proprio_projector"].get("fc1.weight", (None, ()))[1]
        if len(fc1) != 2 or fc1[0] != llm_dim:
            raise _fail(components["proprio_projector"], f"fc1.weight has shape {fc1}, [{llm_dim}, proprio dims] "
                                                         "is expected")
        proprio_dim = fc1[1]
    platform = next((p for p in _PLATFORMS if p.action_dim == action_dim and proprio_dim in (None, p.proprio_dim)),
                    None)
    if platform is None and chunk_size is None:
        raise _fail(head_file, f"{action_dim} action dims and {proprio_dim} proprio dims match no OFT platform "
                               f"({', '.join(f'{p.name} {p.action_dim}/{p.proprio_dim}' for p in _PLATFORMS)}): "
                               "give the chunk size (policy_kwargs.chunk_size)")
    return dict(action_dim=action_dim, proprio_dim=proprio_dim, chunk_size=chunk_size or platform.chunk_size,
                num_images=platform.num_images if platform else 1,
                normalization=platform.normalization if platform else "bounds_q99", norm_eps=1e-8,
                components=components,
                component_shapes={n: {k: s for k, (_, s) in v.items()} for n, v in shapes.items()})


def check_openvla(spec: str | Path, family: str, *, dataset: str | None = None,
                  chunk_size: int | None = None) -> OpenVLACheckpoint:
    """Check an OpenVLA / OpenVLA-OFT directory (or cached repo id) for policy ``family`` and read it.

    ``dataset`` names the statistics key (needed when the checkpoint has several); ``chunk_size``
    overrides the OFT platform's chunk (needed only for an action/proprio size no platform has)."""
    if family not in OPENVLA_FAMILIES:
        raise ValueError(f"family {family!r} is not one of {', '.join(OPENVLA_FAMILIES)}")
    root = resolve_checkpoint(spec)
    if chunk_size is not None and (isinstance(chunk_size, bool) or not isinstance(chunk_size, int) or chunk_size < 1
                                   or family == "openvla" and chunk_size != 1):
        raise _fail(root, f"chunk_size {chunk_size!r}: an integer >= 1 is expected (and 1 for openvla, which "
                          "predicts one action per call)")
    config = _read_json(root / "config.json", "config.json missing (an OpenVLA checkpoint directory is expected)")
    if not isinstance(config, dict):
        raise _fail(root / "config.json", "must hold a JSON object")
    if config.get("model_type") != "openvla":
        raise _fail(root / "config.json", f"model_type is {config.get('model_type')!r}, an OpenVLA checkpoint has "
                                          "'openvla'")
    weights, index = _weight_files(root)
    shapes: dict[str, tuple[int, ...]] = {}
    for file in weights:
        shapes.update({k: tuple(int(n) for n in v["shape"]) for k, v in _check_safetensors(file).items()
                       if k != "__metadata__"})
    if index is not None:
        listed = json.loads(index.read_text())["weight_map"]
        absent = next((k for k in (*listed, *shapes) if k not in listed or k not in shapes), None)
        if absent is not None:
            raise _fail(index, f"and the shards disagree on {absent} (listed in one, not in the other)")
    what = "an OpenVLA (Prismatic) checkpoint"
    vocab, llm_dim = _shape(root, shapes, "language_model.model.embed_tokens.weight", 2, what)
    _shape(root, shapes, "language_model.lm_head.weight", 2, what)
    _shape(root, shapes, "projector.fc1.weight", 2, what)
    for tower in ("featurizer", "fused_featurizer"):
        if not any(k.startswith(f"vision_backbone.{tower}.") for k in shapes):
            raise _fail(root, f"the weights have no vision_backbone.{tower}.*: not {what}")
    text = config.get("text_config") or {}
    if text.get("vocab_size", vocab) != vocab:
        raise _fail(root / "config.json", f"text_config.vocab_size {text['vocab_size']} but embed_tokens has "
                                          f"{vocab} rows")
    n_bins, pad_to = config.get("n_action_bins", 256), config.get("pad_to_multiple_of", 64)
    if not all(isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in (n_bins, pad_to)) \
            or not 2 <= n_bins <= vocab - pad_to:
        raise _fail(root / "config.json", f"n_action_bins {n_bins!r} / pad_to_multiple_of {pad_to!r} do not fit a "
                                          f"vocabulary of {vocab}")
    tokenizer_files = tuple(root / n for n in _READ_FILES if n.startswith(("tokenizer", "special", "added"))
                            and (root / n).is_file())
    if root / "tokenizer.json" not in tokenizer_files:
        raise _fail(root, "tokenizer.json missing (OpenVLA checkpoints ship their fast tokenizer beside the weights)")

    found = _component_files(root)
    for name, what_else in _UNSUPPORTED.items():
        if name in found:
            raise _fail(found[name][0], f"is an OFT checkpoint with {what_else}, which is not supported (the "
                                        "L1-regression head is)")
    components = {name: _pick_component(root, name, found[name]) for name in COMPONENTS if name in found}
    if family == "openvla" and components:
        raise _fail(root, f"is an OpenVLA-OFT checkpoint ({next(iter(components.values())).name}): load it as "
                          "openvla-oft (its language model feeds the action head; its lm_head does "
                          "not emit actions)")
    if family == "openvla-oft" and "action_head" not in components:
        raise _fail(root, "no action_head--<step>_checkpoint.pt: not an OpenVLA-OFT L1-regression checkpoint (a "
                          "plain OpenVLA one loads as openvla)")
    fields: dict[str, Any] = dict(
        action_dim=0, proprio_dim=None, chunk_size=1, num_images=1, normalization="bounds_q99", norm_eps=0.0,
        components={}, component_shapes={})
    if family == "openvla-oft":
        fields = _oft_fields(root, components, llm_dim, chunk_size)
    key, known, stats_file, entry = _dataset_stats(root, config, family, dataset)
    where = f"{key}.action"
    action_stats = _stats(stats_file, entry.get("action") if isinstance(entry, dict) else None, where,
                          fields["normalization"], fields["action_dim"] or None, "action")
    if not fields["action_dim"]:
        fields["action_dim"] = len(action_stats["mask"])
    proprio_stats = None
    if fields["proprio_dim"] is not None:
        proprio_stats = _stats(stats_file, entry.get("proprio"), f"{key}.proprio", fields["normalization"],
                               fields["proprio_dim"], "proprio")
    return OpenVLACheckpoint(
        path=root, family=family, config=config, weights=weights, weight_index=index, shapes=shapes, llm_dim=llm_dim,
        n_action_bins=n_bins, tokenizer_vocab_size=vocab - pad_to, tokenizer_files=tokenizer_files, dataset=key,
        datasets=known, stats_file=stats_file, action_stats=action_stats, proprio_stats=proprio_stats,
        **_image_settings(root, config), **fields)


# --- weights, components, fingerprint, export --------------------------------------------------------


def read_state_dict(ck: OpenVLACheckpoint, dtype: Any = None) -> dict[str, Any]:
    """Every tensor of the shards, in ``ck.shapes`` order; floating tensors cast to ``dtype`` (a
    torch dtype) when given."""
    from safetensors.torch import load_file

    loaded: dict[str, Any] = {}
    for file in ck.weights:
        loaded.update(load_file(str(file)))
    return {k: loaded[k].to(dtype) if dtype is not None and loaded[k].is_floating_point() else loaded[k]
            for k in ck.shapes}


def _load_component(file: Path) -> dict[str, Any]:
    """A component's tensors, keys without "module.": a converted .safetensors, or the .pt through
    ``torch.load(weights_only=True)`` only."""
    import torch

    if file.suffix == ".safetensors":
        from safetensors.torch import load_file

        loaded = load_file(str(file))
        return {_strip(k): loaded[k] for k in _stored_order(_check_safetensors(file))}
    try:
        loaded = torch.load(file, weights_only=True, map_location="cpu")
    except Exception as err:  # torch.load raises pickle, runtime and OS errors alike
        lines = [ln.strip() for ln in str(err).splitlines() if ln.strip()]
        why = next((ln for ln in lines if "Unsupported global" in ln), lines[0] if lines else type(err).__name__)
        raise _fail(file, f"refused: torch.load(weights_only=True) cannot read it ({why[:200]})") from None
    if not isinstance(loaded, dict) or not all(isinstance(v, torch.Tensor) for v in loaded.values()):
        raise _fail(file, "holds no state dict (a dict of tensors is expected), refused")
    return {_strip(k): v for k, v in loaded.items()}


def read_oft_components(ck: OpenVLACheckpoint, dtype: Any = None) -> dict[str, dict[str, Any]]:
    """OFT: component name -> state dict (keys without "module.", in the file's order), e.g.
    ``{"action_head": {...}, "proprio_projector": {...}}``; floating tensors cast to ``dtype`` when
    given. Converted .safetensors files are read when present, else the .pt (weights only)."""
    out = {}
    for name, file in ck.components.items():
        state = _load_component(file)
        if {k: tuple(v.shape) for k, v in state.items()} != dict(ck.component_shapes[name]):
            raise _fail(file, "changed since the directory was checked (other tensors or shapes)")
        out[name] = {k: v.to(dtype) if dtype is not None and v.is_floating_point() else v for k, v in state.items()}
    return out


def convert_components(ck: OpenVLACheckpoint) -> list[Path]:
    """Write each OFT component .pt once as <stem>.safetensors beside it (keys without "module.",
    dtypes as stored), so that later loads never unpickle; returns the files written (none when
    every component is converted already). Check the directory again to read them."""
    from safetensors.torch import save_file

    written = []
    for file in ck.components.values():
        target = file.with_suffix(".safetensors")
        if file.suffix == ".safetensors" or target.exists():
            continue
        tensors = {k: v.contiguous() for k, v in _load_component(file).items()}
        partial = target.with_name(f".{target.name}.partial-{os.getpid()}")
        save_file(tensors, str(partial), metadata={"format": "pt", "converted_from": file.name,
                                                   "key_order": json.dumps(list(tensors))})
        partial.rename(target)
        written.append(target)
    return written


_DIGESTS: dict[tuple, str] = {}


def _tensor_digest(file: Path) -> str:
    """xxh3-128 over a component's tensors (sorted names without "module.", dtype, shape, bytes): the
    same for a .pt and its converted .safetensors, so converted and unconverted copies agree."""
    st = file.stat()
    cache_key = (str(file), st.st_size, st.st_mtime_ns)
    if cache_key in _DIGESTS:
        return _DIGESTS[cache_key]
    h = xxhash.xxh3_128()
    if file.suffix == ".safetensors":
        entries = {_strip(k): v for k, v in _check_safetensors(file).items() if k != "__metadata__"}
        with open(file, "rb") as f:
            start = 8 + int.from_bytes(f.read(8), "little")
            for name in sorted(entries):
                v = entries[name]
                f.seek(start + v["data_offsets"][0])
                data = f.read(v["data_offsets"][1] - v["data_offsets"][0])
                h.update(f"{name}\0{v['dtype']}\0{tuple(v['shape'])}\0".encode() + data)
    else:
        tensors = {_strip(k): v for k, v in _pt_tensors(file).items()}
        with zipfile.ZipFile(file) as archive:
            prefix = _pickle_member(archive, file)[: -len("data.pkl")]
            for name in sorted(tensors):
                t = tensors[name]
                if not t.contiguous:
                    raise _fail(file, f"{name} is not a dense tensor; convert the file with a trusted copy of torch")
                size = _ITEMSIZE[t.dtype]
                numel = 1
                for n in t.shape:
                    numel *= n
                data = archive.read(f"{prefix}data/{t.storage}")[t.offset * size: (t.offset + numel) * size]
                h.update(f"{name}\0{t.dtype}\0{t.shape}\0".encode() + data)
    _DIGESTS[cache_key] = h.hexdigest()
    return _DIGESTS[cache_key]


def content_hash(ck: OpenVLACheckpoint) -> str:
    """xxh3-128 hex over what the policy reads: the shards and index, config, processor, tokenizer
    and statistics files (labelled by name, so a copy elsewhere or an untrained export hashes the
    same), and the OFT components' tensors (a .pt and its converted .safetensors hash the same)."""
    files = [(f.name, f) for f in ck.weights + ((ck.weight_index,) if ck.weight_index else ())]
    files += [(name, ck.path / name) for name in _READ_FILES if (ck.path / name).is_file()]
    h = xxhash.xxh3_128(hash_files(files).encode())
    for name in sorted(ck.components):
        h.update(f"\0{name}\0{_tensor_digest(ck.components[name])}".encode())
    return h.hexdigest()


def _check_tensors(out: Path, what: str, given: Mapping[str, Any], want: Mapping[str, tuple[int, ...]]) -> None:
    for key, shape in want.items():
        if key not in given:
            raise _fail(out, f"cannot export: the {what} lacks {key}")
        if tuple(given[key].shape) != shape:
            raise _fail(out, f"cannot export: {what} {key} has shape {tuple(given[key].shape)}, the checkpoint's "
                             f"is {shape}")
    extra = next((k for k in given if k not in want), None)
    if extra is not None:
        raise _fail(out, f"cannot export: {extra} is not a tensor of the checkpoint's {what}")


def export_openvla(ck: OpenVLACheckpoint, state_dict: Mapping[str, Any], out: str | Path, *,
                   heads: Mapping[str, Mapping[str, Any]] | None = None) -> Path:
    """Write ``state_dict`` (the checkpoint's tensor names, e.g. a merged trained model's) as a
    directory of ``ck``'s layout at ``out``: the same shards with the same tensors in the same order,
    each cast to the dtype stored (bf16), the same safetensors metadata and index; every other file
    of the directory (config, processor, tokenizer, statistics, upstream .py) copied byte for byte.

    OFT: ``heads`` maps component names (COMPONENTS) to state dicts (keys without "module."); each is
    written as upstream's fine-tuning saves it, ``<stem>.pt`` by ``torch.save`` of an OrderedDict
    with keys prefixed "module." and the stored dtypes, so upstream's loader reads the export; no
    converted .safetensors is written beside it. A component not in ``heads`` (all with
    ``heads=None``) is copied unchanged, with its converted .safetensors if there is one.

    ``state_dict`` and each head must hold exactly the checkpoint's tensors with their shapes;
    ``out`` must not exist or be empty."""
    import torch
    from safetensors.torch import save_file

    out = Path(out).expanduser()
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise _fail(out, "export target exists and is not an empty directory; choose a new one")
    _check_tensors(out, "state dict", state_dict, ck.shapes)
    for name, given in (heads or {}).items():
        if name not in ck.components:
            raise _fail(out, f"cannot export: {name} is not a component of {ck.path} "
                             f"({', '.join(ck.components) or 'it has none'})")
        _check_tensors(out, name, given, ck.component_shapes[name])

    partial = out.parent / f".{out.name}.partial-{os.getpid()}"
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)
    try:
        for file in ck.weights:
            header = _check_safetensors(file)
            tensors = {}
            for key, info in header.items():
                if key != "__metadata__":
                    tensors[key] = _stored(state_dict[key], info["dtype"])
            save_file(tensors, str(partial / file.name), metadata=header.get("__metadata__"))
        for file in sorted(ck.path.iterdir()):
            if file.is_file() and _SIDE_FILE.fullmatch(file.name):
                shutil.copyfile(file, partial / file.name)
        for name, file in ck.components.items():
            pt = file.with_suffix(".pt")
            if heads is None or name not in heads:
                for original in (pt, file):
                    if original.is_file():
                        shutil.copyfile(original, partial / original.name)
                continue
            dtypes = {k: d for k, (d, _) in _component_tensors(file).items()}
            torch.save(collections.OrderedDict((DDP_PREFIX + k, _stored(heads[name][k], dtypes[k]))  # stored order
                                               for k in ck.component_shapes[name]), partial / pt.name)
        if out.exists():
            out.rmdir()
        partial.rename(out)
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    return out


def _stored(tensor: Any, dtype: str) -> Any:
    """A CPU copy in the stored dtype with its own dense storage (safetensors refuses shared views)."""
    import torch

    return tensor.detach().to("cpu", getattr(torch, _TORCH_DTYPES[dtype])).clone(memory_format=torch.contiguous_format)


#: safetensors dtype name -> torch attribute
_TORCH_DTYPES = {"F32": "float32", "BF16": "bfloat16", "F16": "float16", "F64": "float64", "I64": "int64",
                 "I32": "int32", "I16": "int16", "I8": "int8", "U8": "uint8", "BOOL": "bool"}
