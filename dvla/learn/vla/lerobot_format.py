"""Policy directories of the published pi0, pi05 and smolvla checkpoints: find one (a path, or a
Hugging Face repo id looked up in the local cache only), check it, read what the policy needs
(sizes, cameras, normalisation stats, tokenizer and backbone locations), load its weights, and
write a trained copy back in the same format (:func:`export_lerobot`).

Every problem is a :class:`CheckpointError`, one line naming the path and what is wrong. Sizes come
from the tensor shapes in the safetensors headers, never from variant names (LeRobot's config says
``gemma_2b`` whatever the size). No torch or transformers at module level: the CLI imports this;
:func:`read_state_dict` and :func:`export_lerobot` import torch when called.

Two layouts:

- ``lerobot``, what LeRobot's ``save_pretrained`` writes: config.json with ``"type"``,
  model.safetensors (or shards and model.safetensors.index.json) with keys prefixed ``model.``,
  policy_preprocessor.json / policy_postprocessor.json and the normaliser state files they name.
  The state's stats are the preprocessor normaliser's, the action's the postprocessor
  unnormaliser's (the preprocessor's when the postprocessor has none); base checkpoints
  (``"features": {}``, no state file) have none, and the policy then runs unnormalised.
- ``openpi``, what openpi's convert_jax_model_to_pytorch.py writes: model.safetensors with keys
  without ``model.``, a config.json without ``"type"`` (action_dim, action_horizon, variants) and
  norm_stats.json (beside it, or the one under assets/<robot>/). That config does not say pi0 or
  pi05, so the weights do (``state_proj`` is pi0's, ``time_mlp_in`` pi05's); what openpi fixes in
  code is set as openpi sets it: cameras base_0_rgb, left_wrist_0_rgb, right_wrist_0_rgb at
  224x224, 10 denoising steps, the whole chunk executed, mean/std normalisation for pi0 and
  quantiles for pi05 with openpi's eps (1e-6, added on both ways), prompts of 48 / 200 tokens,
  PaliGemma's tokenizer (pass it: openpi does not ship it); state_dim / action_dim are the
  lengths of the stats. Prompts are built as LeRobot builds them for pi0 / pi05.
"""

from __future__ import annotations

import json
import os
import re
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

from .checkpoint import CheckpointError, _check_safetensors, _fail, hash_files

#: files that make a directory a Hugging Face tokenizer (any one of them)
TOKENIZER_FILES = ("tokenizer.json", "tokenizer_config.json", "tokenizer.model")

__all__ = ["TOKENIZER_FILES", "LEROBOT_FAMILIES", "NORM_MODES", "STATE_KEY", "ACTION_KEY", "LeRobotCheckpoint", "resolve_checkpoint",
           "check_lerobot", "read_state_dict", "content_hash", "export_lerobot"]

LEROBOT_FAMILIES = ("pi0", "pi05", "smolvla")
"""config.json ``type`` of the policies this module reads."""
NORM_MODES = ("IDENTITY", "MEAN_STD", "MIN_MAX", "QUANTILES", "QUANTILE10")
"""LeRobot's normalisation modes; :mod:`.lerobot_processing` applies them."""
STATE_KEY, ACTION_KEY = "observation.state", "action"
PREPROCESSOR, POSTPROCESSOR = "policy_preprocessor.json", "policy_postprocessor.json"
OPENPI_STATS = "norm_stats.json"
_WEIGHTS, _INDEX = "model.safetensors", "model.safetensors.index.json"
#: the stats each mode reads
STATS_NEEDED = {"IDENTITY": (), "MEAN_STD": ("mean", "std"), "MIN_MAX": ("min", "max"), "QUANTILES": ("q01", "q99"),
                "QUANTILE10": ("q10", "q90")}
_PALIGEMMA_TOKENIZER = "google/paligemma-3b-pt-224"
_OPENPI_CAMERAS = tuple(f"observation.images.{c}" for c in ("base_0_rgb", "left_wrist_0_rgb", "right_wrist_0_rgb"))
_PROMPT_LENGTH = {"pi0": 48, "pi05": 200, "smolvla": 48}
#: the files of a tokenizer or backbone-config directory that are read, hashed and exported (never
#: the weights a Hugging Face cache snapshot of the same repo may hold)
_SIDE_FILE = re.compile(r".*\.(json|txt|model|jinja)")
_REPO_ID = re.compile(r"[A-Za-z0-9][\w.-]*/[\w.-]+")


@dataclass(frozen=True)
class LeRobotCheckpoint:
    """What :func:`check_lerobot` read from a policy directory."""

    #: the directory (absolute; a Hugging Face cache snapshot when a repo id was given)
    path: Path
    #: "pi0", "pi05" or "smolvla"
    family: str
    #: "lerobot" or "openpi" (see the module docstring)
    layout: str
    #: config.json as read
    config: Mapping[str, Any]
    #: the safetensors weight files (one, or the shards in name order)
    weights: tuple[Path, ...]
    #: model.safetensors.index.json when the weights are sharded, else None
    weight_index: Path | None
    #: what every weight key starts with in the files: "model." (LeRobot) or "" (openpi)
    key_prefix: str
    #: tensor name (prefix stripped) -> shape, in the files' order
    shapes: Mapping[str, tuple[int, ...]]
    #: the model's cameras: the VISUAL input features in config order (+ LeRobot's empty_camera_<i>)
    cameras: tuple[str, ...]
    #: (H, W) the model sees images at
    image_size: tuple[int, int]
    #: dims of the real state and action (config features, or the stats for openpi)
    state_dim: int
    action_dim: int
    #: actions generated per call, and how many of them LeRobot executes before calling again
    chunk_size: int
    n_action_steps: int
    #: denoising steps (pi: num_inference_steps, smolvla: num_steps)
    num_steps: int
    #: the model's padded state / action widths (from state_proj / action_in_proj shapes; pi05's
    #: state lives in the prompt, so config max_state_dim)
    max_state_dim: int
    max_action_dim: int
    #: the tokenizer call: max_length, padding ("max_length" | "longest"), padding_side, truncation
    tokenizer_settings: Mapping[str, Any]
    #: feature type ("VISUAL", "STATE", "ACTION") -> one of NORM_MODES
    norm_modes: Mapping[str, str]
    #: the normaliser's eps (LeRobot 1e-8, openpi 1e-6)
    norm_eps: float
    #: {"observation.state": {"mean": (...), ...}, "action": {...}}; a feature without stats is absent
    stats: Mapping[str, Mapping[str, tuple[float, ...]]]
    #: the tokenizer directory, or None (only when check_lerobot was told not to need one)
    tokenizer_dir: Path | None
    #: smolvla: the backbone directory named by config vlm_model_name (config.json, processor); else None
    vlm_dir: Path | None
    #: policy_preprocessor.json / policy_postprocessor.json (None for openpi)
    preprocessor: Path | None
    postprocessor: Path | None
    #: every processor and stats file (the JSONs, the state files they name, openpi's norm_stats.json)
    processor_files: tuple[Path, ...]

    @property
    def tokenizer_max_length(self) -> int:
        """Prompt length in tokens (the exact length with padding "max_length", at most with "longest")."""
        return int(self.tokenizer_settings["max_length"])


# --- locating directories -----------------------------------------------------------------------


def _hf_cache() -> Path:
    """The Hugging Face hub cache, read from the environment at call time as huggingface_hub reads it."""
    env = os.environ
    cache = env.get("HF_HUB_CACHE") or env.get("HUGGINGFACE_HUB_CACHE")
    if cache:
        return Path(cache).expanduser()
    home = env.get("HF_HOME") or os.path.join(env.get("XDG_CACHE_HOME") or "~/.cache", "huggingface")
    return Path(home).expanduser() / "hub"


def _cached_repo(repo_id: str) -> Path | None:
    """The local snapshot of a Hugging Face repo, never a download; None when not cached."""
    if not _REPO_ID.fullmatch(repo_id):
        return None
    from huggingface_hub import snapshot_download

    try:
        return Path(snapshot_download(repo_id, cache_dir=_hf_cache(), local_files_only=True))
    except (OSError, ValueError):  # not cached / not a valid repo id
        return None


def _download_hint(name: str) -> str:
    return f"; download it first: hf download {name}" if _REPO_ID.fullmatch(name) else ""


def resolve_checkpoint(spec: str | Path) -> Path:
    """An existing directory, else a Hugging Face repo id ("org/name") found in the local cache
    (``HF_HUB_CACHE`` / ``HF_HOME``; nothing is downloaded)."""
    path = Path(spec).expanduser()
    if path.is_dir():
        return Path(os.path.abspath(path))
    if path.exists():
        raise _fail(path, "is not a directory (a policy directory or a Hugging Face repo id is expected)")
    snapshot = _cached_repo(str(spec))
    if snapshot is not None:
        return snapshot
    if _REPO_ID.fullmatch(str(spec)):
        raise CheckpointError(f"{spec}: not a directory and not in the Hugging Face cache ({_hf_cache()})"
                              f"{_download_hint(str(spec))}")
    raise _fail(path, "checkpoint directory does not exist")


def _named_dir(root: Path, name: str) -> Path | None:
    """A directory named in a config: relative to the checkpoint (as LeRobot resolves it relative to
    its working directory), absolute, or a cached Hugging Face repo."""
    local = Path(name).expanduser()
    local = local if local.is_absolute() else root / local
    if local.is_dir():
        return Path(os.path.normpath(local))
    return _cached_repo(name)


def _has_tokenizer(directory: Path | None) -> bool:
    return directory is not None and any((directory / f).is_file() for f in TOKENIZER_FILES)


def _find_tokenizer(root: Path, given: str | Path | None, name: str | None, source: str, need: bool) -> Path | None:
    """``given`` (a directory or a cached repo id), else <root>/tokenizer/, else ``name`` (from ``source``)."""
    if given is not None:
        found = Path(given).expanduser() if Path(given).expanduser().is_dir() else _cached_repo(str(given))
        if not _has_tokenizer(found):
            raise CheckpointError(f"{given}: the tokenizer given (policy_kwargs.tokenizer) is neither a directory with "
                                  f"{' / '.join(TOKENIZER_FILES)} nor a repo in the Hugging Face cache "
                                  f"({_hf_cache()})")
        return Path(os.path.abspath(found))
    if _has_tokenizer(root / "tokenizer"):
        return root / "tokenizer"
    found = _named_dir(root, name) if name else None
    if _has_tokenizer(found):
        return found
    if not need:
        return None
    named = f"{name!r} ({source}) is neither beside it nor in the Hugging Face cache ({_hf_cache()})" if name else \
        f"{source} names none"
    raise _fail(root, f"no tokenizer: no tokenizer/ directory in it and {named}; pass policy_kwargs.tokenizer "
                      f"(a tokenizer directory or a cached repo id){_download_hint(name or '')}")


# --- reading files --------------------------------------------------------------------------------


def _read_json(file: Path, missing: str) -> Any:
    if not file.is_file():
        raise _fail(file.parent, missing)
    try:
        return json.loads(file.read_text())
    except (ValueError, UnicodeDecodeError) as err:
        raise _fail(file, f"not JSON ({err})") from None


def _weight_files(root: Path) -> tuple[tuple[Path, ...], Path | None]:
    index = root / _INDEX
    if index.is_file():
        try:
            shards = sorted(set(json.loads(index.read_text())["weight_map"].values()))
        except (ValueError, KeyError, AttributeError, TypeError) as err:
            raise _fail(index, f"not a safetensors index ({type(err).__name__}: {err})") from None
        missing = [s for s in shards if not (root / s).is_file()]
        if missing or not shards:
            raise _fail(root, f"{_INDEX} names shard {missing[0] if missing else '(none)'}, which is not in the "
                              "directory")
        return tuple(root / s for s in shards), index
    if not (root / _WEIGHTS).is_file():
        raise _fail(root, f"{_WEIGHTS} missing (nor {_INDEX} with shards)")
    return (root / _WEIGHTS,), None


def _read_shapes(root: Path, weights: tuple[Path, ...]) -> tuple[str, dict[str, tuple[int, ...]]]:
    """The key prefix and every tensor's shape (prefix stripped), checking each file is complete."""
    header: dict[str, Any] = {}
    for file in weights:
        header.update({k: v for k, v in _check_safetensors(file).items() if k != "__metadata__"})
    prefixed = sum(k.startswith("model.") for k in header)
    if prefixed not in (0, len(header)):
        raise _fail(root, f"weights mix {prefixed} keys prefixed 'model.' with {len(header) - prefixed} without")
    prefix = "model." if header and prefixed else ""
    return prefix, {k[len(prefix):]: tuple(int(n) for n in v["shape"]) for k, v in header.items()}


def _weights_family(shapes: Mapping[str, tuple[int, ...]]) -> str | None:
    """Which family the tensor names are: smolvla's VLM + expert, pi0's state token, pi05's time MLP."""
    if any(k.startswith("vlm_with_expert.") for k in shapes):
        return "smolvla"
    if not any(k.startswith("paligemma_with_expert.") for k in shapes):
        return None
    if "state_proj.weight" in shapes:
        return "pi0"
    return "pi05" if "time_mlp_in.weight" in shapes else None


def _width_in(root: Path, shapes: Mapping[str, tuple[int, ...]], key: str) -> int:
    shape = shapes.get(key)
    if shape is None or len(shape) != 2:
        raise _fail(root, f"the weights have no 2-D {key} (found {shape}): not a pi0 / pi05 / smolvla policy")
    return shape[1]


def _int(root: Path, config: Mapping[str, Any], key: str, default: int) -> int:
    value = config.get(key, default)
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise _fail(root / "config.json", f"{key} must be an integer >= 1, got {value!r}")
    return value


def _load_stats_file(file: Path) -> dict[str, Any]:
    from safetensors.numpy import load_file

    return load_file(str(file))


def _step_stats(root: Path, step: Mapping[str, Any] | None, key: str) -> tuple[dict[str, tuple[float, ...]], Path]:
    """The stats a (un)normaliser step holds for ``key`` and their file; none when the step does
    not list the feature or has no state file (what LeRobot then passes through unchanged)."""
    if step is None or key not in (step.get("config", {}).get("features") or {}) or not step.get("state_file"):
        return {}, root
    file = root / step["state_file"]
    return {name[len(key) + 1:]: tuple(float(x) for x in v.reshape(-1))
            for name, v in _load_stats_file(file).items() if name.rsplit(".", 1)[0] == key}, file


def _processor(root: Path, name: str) -> tuple[Path, dict[str, dict[str, Any]], list[Path]]:
    """A processor JSON: its steps by registry name and the state files they name (checked)."""
    file = root / name
    doc = _read_json(file, f"{name} missing (LeRobot writes it beside the weights; directories saved before "
                           "LeRobot 0.4 keep their stats in the weights: convert them with LeRobot's "
                           "migrate_policy_normalization)")
    steps = doc.get("steps") if isinstance(doc, dict) else None
    if not isinstance(steps, list) or not all(isinstance(s, dict) and "registry_name" in s for s in steps):
        raise _fail(file, "has no list of steps with registry_name")
    by_name: dict[str, dict[str, Any]] = {}
    files = []
    for step in steps:
        by_name.setdefault(step["registry_name"], step)
        state = step.get("state_file")
        if state:
            if not (root / state).is_file():
                raise _fail(root, f"{state} missing (named by {name}, step {step['registry_name']})")
            _check_safetensors(root / state)
            files.append(root / state)
    return file, by_name, files


def _check_stats(file: Path, key: str, mode: str, stats: Mapping[str, tuple[float, ...]], dim: int) -> None:
    if not stats:
        return
    for name in STATS_NEEDED[mode]:
        if name not in stats:
            raise _fail(file, f"{mode} normalisation of {key} needs {key}.{name}, which the stats lack")
        if len(stats[name]) != dim:
            raise _fail(file, f"{key}.{name} has {len(stats[name])} values, the {key} feature has {dim} dims")


def _lerobot_fields(root: Path, config: Mapping[str, Any], family: str,
                    shapes: Mapping[str, tuple[int, ...]]) -> dict[str, Any]:
    pre, pre_steps, pre_files = _processor(root, PREPROCESSOR)
    post, post_steps, post_files = _processor(root, POSTPROCESSOR)
    for steps, file in ((pre_steps, pre), (post_steps, post)):
        for name in ("relative_actions_processor", "absolute_actions_processor"):
            if (steps.get(name, {}).get("config") or {}).get("enabled"):
                raise _fail(file, f"step {name} is enabled: relative actions are not supported")
    norm, unnorm = pre_steps.get("normalizer_processor"), post_steps.get("unnormalizer_processor")

    modes = {"VISUAL": "IDENTITY", "STATE": "IDENTITY", "ACTION": "IDENTITY"}
    modes.update(config.get("normalization_mapping") or {})
    modes.update((norm or {}).get("config", {}).get("norm_map") or {})
    modes["ACTION"] = ((unnorm or {}).get("config", {}).get("norm_map") or {}).get("ACTION", modes["ACTION"])
    for kind, mode in modes.items():
        if mode not in NORM_MODES:
            raise _fail(pre, f"normalisation mode {mode!r} for {kind} is not one of {', '.join(NORM_MODES)}")
    eps = float((norm or unnorm or {}).get("config", {}).get("eps", 1e-8))

    max_action_dim = _width_in(root, shapes, "action_in_proj.weight")
    max_state_dim = (_int(root, config, "max_state_dim", 32) if family == "pi05"
                     else _width_in(root, shapes, "state_proj.weight"))
    for key, width, tensor in (("max_action_dim", max_action_dim, "action_in_proj.weight"),
                               ("max_state_dim", max_state_dim, "state_proj.weight")):
        if key in config and config[key] != width:
            raise _fail(root, f"config.json says {key} {config[key]}, the weights' {tensor} takes {width}")

    inputs = config.get("input_features") or {}
    cameras = [k for k, v in inputs.items() if isinstance(v, dict) and v.get("type") == "VISUAL"]
    cameras += [f"observation.images.empty_camera_{i}" for i in range(int(config.get("empty_cameras") or 0))
                if f"observation.images.empty_camera_{i}" not in cameras]
    try:
        state_dim = int(inputs[STATE_KEY]["shape"][0]) if STATE_KEY in inputs else max_state_dim
        outputs = config.get("output_features") or {}
        action_dim = int(outputs[ACTION_KEY]["shape"][0]) if ACTION_KEY in outputs else max_action_dim
        if family == "smolvla":
            size = config.get("resize_imgs_with_padding")  # LeRobot stores (width, height) here
            image_size = ((int(size[1]), int(size[0])) if size
                          else tuple(int(n) for n in inputs[cameras[0]]["shape"][1:]))
        else:
            image_size = tuple(int(n) for n in config.get("image_resolution") or (224, 224))
    except (KeyError, IndexError, TypeError, ValueError) as err:
        raise _fail(root / "config.json", f"bad input_features / output_features / image size ({type(err).__name__}: "
                                          f"{err})") from None

    found = {STATE_KEY: _step_stats(root, norm, STATE_KEY),
             ACTION_KEY: _step_stats(root, unnorm, ACTION_KEY)}
    if not found[ACTION_KEY][0]:
        found[ACTION_KEY] = _step_stats(root, norm, ACTION_KEY)
    if modes["VISUAL"] != "IDENTITY" and norm and norm.get("state_file") and any(
            name.rsplit(".", 1)[0] in cameras for name in _load_stats_file(root / norm["state_file"])):
        raise _fail(pre, f"VISUAL normalisation {modes['VISUAL']} with image stats is not supported (IDENTITY is)")

    tok_step = (pre_steps.get("tokenizer_processor") or {}).get("config") or {}
    settings = {"max_length": int(tok_step.get("max_length") or config.get("tokenizer_max_length")
                                  or _PROMPT_LENGTH[family]),
                "padding": tok_step.get("padding") or config.get("pad_language_to") or "max_length",
                "padding_side": tok_step.get("padding_side") or "right",
                "truncation": bool(tok_step.get("truncation", True))}
    return dict(
        layout="lerobot", cameras=tuple(cameras), image_size=image_size, state_dim=state_dim, action_dim=action_dim,
        chunk_size=_int(root, config, "chunk_size", 50), n_action_steps=_int(root, config, "n_action_steps", 50),
        num_steps=_int(root, config, "num_steps" if family == "smolvla" else "num_inference_steps", 10),
        max_state_dim=max_state_dim, max_action_dim=max_action_dim, tokenizer_settings=settings,
        norm_modes=modes, norm_eps=eps, stats={k: v for k, (v, _) in found.items() if v},
        preprocessor=pre, postprocessor=post, processor_files=(pre, *pre_files, post, *post_files),
        tokenizer_name=tok_step.get("tokenizer_name"), tokenizer_source=f"{PREPROCESSOR} tokenizer_name",
        stats_files={k: f for k, (_, f) in found.items()})


def _openpi_stats_file(root: Path) -> Path | None:
    if (root / OPENPI_STATS).is_file():
        return root / OPENPI_STATS
    found = sorted(root.glob(f"assets/*/{OPENPI_STATS}"))
    if len(found) > 1:
        raise _fail(root, f"several {OPENPI_STATS} under assets/ ({', '.join(str(f.parent.name) for f in found)}): "
                          f"copy the robot's one to {root / OPENPI_STATS}")
    return found[0] if found else None


def _openpi_fields(root: Path, config: Mapping[str, Any], family: str,
                   shapes: Mapping[str, tuple[int, ...]]) -> dict[str, Any]:
    stats_file = _openpi_stats_file(root)
    if stats_file is None:
        raise _fail(root / "config.json", f"has no \"type\" (not a LeRobot policy config) and there is no "
                                          f"{OPENPI_STATS} (not an openpi-converted directory either)")
    doc = _read_json(stats_file, f"{OPENPI_STATS} missing")
    norm_stats = doc.get("norm_stats", doc) if isinstance(doc, dict) else None
    if not isinstance(norm_stats, dict):
        raise _fail(stats_file, "holds no norm_stats object")
    got = _weights_family(shapes)
    if got != family:
        raise _fail(root, f"is a {got or 'unknown'!r} checkpoint (openpi layout, told by its weights), policy "
                          f"{family} needs {family!r}")
    max_action_dim = _width_in(root, shapes, "action_in_proj.weight")
    max_state_dim = _width_in(root, shapes, "state_proj.weight") if family == "pi0" else max_action_dim
    if config.get("action_dim", max_action_dim) != max_action_dim:
        raise _fail(root, f"config.json says action_dim {config['action_dim']}, the weights' action_in_proj.weight "
                          f"takes {max_action_dim}")
    stats, dims = {}, {}
    for key, name, width in ((STATE_KEY, "state", max_state_dim), (ACTION_KEY, "actions", max_action_dim)):
        entry = norm_stats.get(name) or {}
        try:
            stats[key] = {s: tuple(float(x) for x in entry[s]) for s in ("mean", "std", "q01", "q99")
                          if entry.get(s) is not None}
        except (TypeError, ValueError) as err:
            raise _fail(stats_file, f"norm_stats.{name} is not lists of numbers ({err})") from None
        dims[key] = len(stats[key]["mean"]) if "mean" in stats[key] else width
    horizon = _int(root, config, "action_horizon", 50)
    mode = "MEAN_STD" if family == "pi0" else "QUANTILES"
    return dict(
        layout="openpi", cameras=_OPENPI_CAMERAS, image_size=(224, 224), state_dim=dims[STATE_KEY],
        action_dim=dims[ACTION_KEY], chunk_size=horizon, n_action_steps=horizon, num_steps=10,
        max_state_dim=max_state_dim, max_action_dim=max_action_dim,
        tokenizer_settings={"max_length": _int(root, config, "max_token_len", _PROMPT_LENGTH[family]),
                            "padding": "max_length", "padding_side": "right", "truncation": True},
        norm_modes={"VISUAL": "IDENTITY", "STATE": mode, "ACTION": mode}, norm_eps=1e-6,
        stats={k: v for k, v in stats.items() if v}, preprocessor=None, postprocessor=None,
        processor_files=(stats_file,), tokenizer_name=_PALIGEMMA_TOKENIZER, tokenizer_source="openpi's tokenizer",
        stats_files={STATE_KEY: stats_file, ACTION_KEY: stats_file})


def check_lerobot(spec: str | Path, family: str, *, tokenizer: str | Path | None = None,
                  need_tokenizer: bool = True) -> LeRobotCheckpoint:
    """Check a policy directory (or cached repo id) for policy ``family`` and read it.

    The tokenizer is ``tokenizer`` (a directory or a cached repo id), else <dir>/tokenizer/, else
    the preprocessor's tokenizer_name (beside the checkpoint, or from the cache); with
    ``need_tokenizer=False`` none found gives ``tokenizer_dir=None`` instead of an error."""
    if family not in LEROBOT_FAMILIES:
        raise ValueError(f"family {family!r} is not one of {', '.join(LEROBOT_FAMILIES)}")
    root = resolve_checkpoint(spec)
    config = _read_json(root / "config.json", "config.json missing (a LeRobot policy directory is expected)")
    if not isinstance(config, dict):
        raise _fail(root / "config.json", "must hold a JSON object")
    weights, index = _weight_files(root)
    prefix, shapes = _read_shapes(root, weights)
    if "type" in config:
        if config["type"] != family:
            raise _fail(root, f"is a {config['type']!r} checkpoint, policy {family} needs {family!r}")
        got = _weights_family(shapes)
        if got != family:
            raise _fail(root, f"config.json says {family!r} but the weights are {got or 'of no known family'!r} "
                              "(pi0: paligemma_with_expert + state_proj, pi05: paligemma_with_expert + time_mlp_in, "
                              "smolvla: vlm_with_expert)")
        fields = _lerobot_fields(root, config, family, shapes)
    else:
        fields = _openpi_fields(root, config, family, shapes)
    for key, dim, width in (("state", fields["state_dim"], fields["max_state_dim"]),
                            ("action", fields["action_dim"], fields["max_action_dim"])):
        if not 1 <= dim <= width:
            raise _fail(root, f"{key} has {dim} dims, the model takes 1 to {width}")
    if not fields["cameras"]:
        raise _fail(root / "config.json", "input_features has no VISUAL feature and empty_cameras is 0: the policy "
                                          "would see no image")
    if fields["n_action_steps"] > fields["chunk_size"]:
        raise _fail(root / "config.json", f"n_action_steps {fields['n_action_steps']} exceeds chunk_size "
                                          f"{fields['chunk_size']}")
    stats_files = fields.pop("stats_files")
    for key, kind, dim in ((STATE_KEY, "STATE", fields["state_dim"]), (ACTION_KEY, "ACTION", fields["action_dim"])):
        _check_stats(stats_files[key], key, fields["norm_modes"][kind], fields["stats"].get(key, {}), dim)
    tokenizer_dir = _find_tokenizer(root, tokenizer, fields.pop("tokenizer_name"), fields.pop("tokenizer_source"),
                                    need_tokenizer)
    vlm_dir = None
    if family == "smolvla":
        name = str(config.get("vlm_model_name") or "")
        vlm_dir = _named_dir(root, name) if name else None
        if vlm_dir is None or not (vlm_dir / "config.json").is_file():
            raise _fail(root, f"vlm_model_name {name!r} (config.json) is neither a directory with config.json beside "
                              f"the checkpoint nor in the Hugging Face cache ({_hf_cache()}){_download_hint(name)}")
    return LeRobotCheckpoint(path=root, family=family, config=config, weights=weights, weight_index=index,
                             key_prefix=prefix, shapes=shapes, tokenizer_dir=tokenizer_dir, vlm_dir=vlm_dir, **fields)


# --- weights, fingerprint, export -----------------------------------------------------------------


def read_state_dict(ck: LeRobotCheckpoint, dtype: Any = None) -> dict[str, Any]:
    """Every tensor, keys without ``ck.key_prefix``, in the files' order; floating tensors cast to
    ``dtype`` (a torch dtype) when given."""
    from safetensors.torch import load_file

    loaded: dict[str, Any] = {}
    for file in ck.weights:
        loaded.update(load_file(str(file)))
    out = {}
    for key in ck.shapes:
        tensor = loaded.pop(ck.key_prefix + key)
        out[key] = tensor.to(dtype) if dtype is not None and tensor.is_floating_point() else tensor
    return out


def _side_dirs(ck: LeRobotCheckpoint) -> list[tuple[str, Path, str | None]]:
    """(hash label, directory, place in an export) of the tokenizer and backbone-config directories:
    one inside the checkpoint keeps its relative place (the config names it so), a tokenizer from
    elsewhere goes to tokenizer/ (where :func:`check_lerobot` looks first), a backbone from the
    cache stays there (None: config.json names its repo)."""
    out = []
    for label, directory in (("tokenizer", ck.tokenizer_dir), ("vlm", ck.vlm_dir)):
        if directory is not None:
            inside = os.path.relpath(directory, ck.path)
            outside = inside == ".." or inside.startswith("../")
            out.append((label, directory, ("tokenizer" if label == "tokenizer" else None) if outside else inside))
    return out


def _side_files(directory: Path) -> list[Path]:
    return sorted(p for p in directory.iterdir() if p.is_file() and _SIDE_FILE.fullmatch(p.name))


def content_hash(ck: LeRobotCheckpoint) -> str:
    """xxh3-128 hex over every file the policy reads: weights (and index), config.json, the
    processor and stats files, the tokenizer's and the backbone config's files. Labelled by role,
    not path, so a copy elsewhere (or an untrained export) hashes the same."""
    files = [(f.name, f) for f in ck.weights + ((ck.weight_index,) if ck.weight_index else ())]
    files += [(f.relative_to(ck.path).as_posix(), f) for f in (ck.path / "config.json", *ck.processor_files)]
    for label, directory, _ in _side_dirs(ck):
        files += [(f"{label}/{p.name}", p) for p in _side_files(directory)]
    return hash_files(files)


def export_lerobot(ck: LeRobotCheckpoint, state_dict: Mapping[str, Any], out: str | Path, *,
                   metadata: Mapping[str, str] | None = None) -> Path:
    """Write ``state_dict`` (keys without the prefix, e.g. a trained model's) as a policy directory
    of ``ck``'s layout at ``out``: the weights split into the same files with the prefix re-added,
    each tensor in its own dtype, ``metadata`` added to each file's safetensors metadata;
    config.json, the processor and stats files copied byte for byte, the tokenizer and backbone
    config directories copied (see :func:`_side_dirs`) so that the directory stands alone.

    ``state_dict`` must hold exactly the checkpoint's tensors with their shapes; an extra key is
    accepted only as a tied alias of a written tensor. ``out`` must not exist or be empty."""
    from safetensors.torch import save_file

    out = Path(out).expanduser()
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise _fail(out, "export target exists and is not an empty directory; choose a new one")
    for key, shape in ck.shapes.items():
        if key not in state_dict:
            raise _fail(out, f"cannot export: the state dict lacks {key} (a tensor of {ck.path})")
        if tuple(state_dict[key].shape) != shape:
            raise _fail(out, f"cannot export: {key} has shape {tuple(state_dict[key].shape)}, {ck.path} has {shape}")
    written = {state_dict[k].data_ptr() for k in ck.shapes}
    extra = [k for k in state_dict if k not in ck.shapes and state_dict[k].data_ptr() not in written]
    if extra:
        raise _fail(out, f"cannot export: {extra[0]} is not a tensor of {ck.path}")

    partial = out.parent / f".{out.name}.partial-{os.getpid()}"
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)
    try:
        seen: set[int] = set()
        total = 0
        for file in ck.weights:
            header = _check_safetensors(file)
            tensors = {}
            for name in header:
                if name == "__metadata__":
                    continue
                tensor = state_dict[name[len(ck.key_prefix):]].detach().to("cpu").contiguous()
                if tensor.data_ptr() in seen:  # safetensors refuses shared storage: tied weights are written twice
                    tensor = tensor.clone()
                seen.add(tensor.data_ptr())
                total += tensor.numel() * tensor.element_size()
                tensors[name] = tensor
            meta = {**(header.get("__metadata__") or {}), **(metadata or {})}
            save_file(tensors, str(partial / file.name), metadata=meta or None)
        if ck.weight_index is not None:
            index = json.loads(ck.weight_index.read_text())
            if (index.get("metadata") or {}).get("total_size") == total:
                shutil.copyfile(ck.weight_index, partial / ck.weight_index.name)
            else:
                index.setdefault("metadata", {})["total_size"] = total
                (partial / ck.weight_index.name).write_text(json.dumps(index, indent=2))
        for file in (ck.path / "config.json", *ck.processor_files):
            target = partial / file.relative_to(ck.path)
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(file, target)
        for _, directory, place in _side_dirs(ck):
            if place:
                (partial / place).mkdir(parents=True, exist_ok=True)
                for p in _side_files(directory):
                    shutil.copyfile(p, partial / place / p.name)
        if out.exists():
            out.rmdir()
        partial.rename(out)
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    return out
