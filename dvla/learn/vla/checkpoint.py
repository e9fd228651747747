"""Checkpoint directories of the Hugging Face VLA policies (``vla-tokens``, ``vla-flow``).

A checkpoint is one local directory, read with ``local_files_only=True`` (nothing is downloaded
at run time; every host running a role needs the same files at the same path)::

    config.json                     a transformers vision-language model (AutoModelForImageTextToText):
    model.safetensors               Llava (Llama + SigLIP, OpenVLA's layout) or PaliGemma (pi0's backbone);
                                    sharded weights need their model.safetensors.index.json
    tokenizer.json, tokenizer_config.json   (or tokenizer.model / vocab.json): AutoTokenizer
    preprocessor_config.json        optional: image_mean / image_std (else 0.5 / 0.5)
    dvla_policy.json                the action head, written by hand when converting a checkpoint
    action_expert.safetensors       flow family only: the action expert (dvla/learn/vla/flow.py)

``dvla_policy.json`` holds, for both families, ``family`` (``"tokens"`` or ``"flow"``),
``action_dim`` (the robot's action size), ``max_chunk`` (most actions predicted per decision) and
``action_low`` / ``action_high`` (``action_dim`` numbers each: the model's normalised action
[-1, 1] maps linearly onto [low, high]; take them from the dataset statistics a downloaded
OpenVLA-OFT / pi0 / SmolVLA checkpoint ships, e.g. OpenVLA's q01 / q99). The token family adds
``n_bins`` (the last ``n_bins`` ids of the LM vocabulary are the action bins, as OpenVLA
overwrites its last 256 ids) and optionally ``bin_order`` (``"ascending"``: bin i is id
V - n_bins + i, the default; ``"descending"``: bin i is id V - 1 - i, OpenVLA's order). The flow
family adds ``denoise_steps`` and ``expert`` (``width``, ``layers``, ``heads``, ``mlp``: the sizes
of the action expert saved in ``action_expert.safetensors``). A downloaded pi0 / SmolVLA expert
has another layout: only the VLM loads from such a checkpoint, the expert file must be ours.

:func:`check_checkpoint` checks all of this before anything loads and raises
:class:`CheckpointError` with one line naming the path and what is wrong. :func:`content_hash`
fingerprints the files the policy reads (the frozen base of a LoRA run is never shipped, so hosts
compare hashes instead). :func:`save_random_checkpoint` writes a random-initialised checkpoint of
real transformers classes with an offline word-level tokenizer: ``size="test"`` for unit tests
(~0.15 M parameters), ``"0.5b"`` for GPU benchmarks.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Mapping

import xxhash

__all__ = ["CheckpointError", "CheckpointInfo", "check_checkpoint", "executed_chunk", "content_hash",
           "save_random_checkpoint", "vlm_config", "FAMILIES", "POLICY_FILE", "EXPERT_FILE"]

FAMILIES = {"tokens": "vla-tokens", "flow": "vla-flow"}
"""dvla_policy.json family -> the policy name that loads it."""
POLICY_FILE = "dvla_policy.json"
EXPERT_FILE = "action_expert.safetensors"
_TOKENIZER_FILES = ("tokenizer.json", "tokenizer.model", "vocab.json")
_REQUIRED = {"tokens": ("n_bins",), "flow": ("denoise_steps", "expert")}
_COMMON = ("family", "action_dim", "max_chunk", "action_low", "action_high")
_BLOCK = 8 << 20


class CheckpointError(ValueError):
    """A checkpoint directory cannot be used; the message is one line naming the path."""


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
    #: the VLM's weight files (not the flow expert's)
    weight_files: tuple[Path, ...] = field(default=())


def _fail(path: Path, what: str) -> CheckpointError:
    return CheckpointError(f"{path}: {' '.join(str(what).split())}")


def _check_safetensors(file: Path) -> None:
    """Header and size of one safetensors file: a truncated copy fails here, in one line."""
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
    got = settings.get("family")
    if got not in _REQUIRED:
        raise _fail(policy_file, f"family {got!r} is not one of {', '.join(map(repr, _REQUIRED))}")
    if got != family:
        raise _fail(path, f"is a {got!r} checkpoint ({POLICY_FILE} family), policy {FAMILIES[family]} needs {family!r}")
    missing = [k for k in _COMMON + _REQUIRED[family] if k not in settings]
    if missing:
        raise _fail(policy_file, f"missing key {', '.join(missing)}")
    action_dim, max_chunk = int(settings["action_dim"]), int(settings["max_chunk"])
    if action_dim < 1 or max_chunk < 1:
        raise _fail(policy_file, f"action_dim {action_dim} and max_chunk {max_chunk} must be >= 1")
    bounds = [tuple(float(x) for x in settings[k]) for k in ("action_low", "action_high")]
    if any(len(b) != action_dim for b in bounds):
        raise _fail(policy_file, f"action_low / action_high need action_dim={action_dim} numbers each, "
                                 f"got {len(bounds[0])} and {len(bounds[1])}")
    if family == "flow" and not (path / EXPERT_FILE).is_file():
        raise _fail(path, f"{EXPERT_FILE} missing (the flow family's action expert)")
    for file in weights + ((path / EXPERT_FILE,) if family == "flow" else ()):
        _check_safetensors(file)
    return CheckpointInfo(path, family, settings, action_dim, max_chunk, bounds[0], bounds[1], weights)


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
    """xxh3-128 hex over the names and bytes of the files a policy reads from ``path``.

    Config, tokenizer, dvla_policy.json and every safetensors file, in name order, streamed in
    8 MiB blocks: two hosts with the same files agree, a host with other base weights does not.
    Cached per process on (name, size, mtime), since every copy of a policy asks (a rollout builds
    two)."""
    path = Path(path).expanduser().resolve()
    files = sorted(p for p in path.iterdir() if p.is_file() and _HASHED.fullmatch(p.name))
    key = (str(path),) + tuple((p.name, p.stat().st_size, p.stat().st_mtime_ns) for p in files)
    if key not in _HASH_CACHE:
        h = xxhash.xxh3_128()
        for p in files:
            h.update(p.name.encode() + b"\0" + p.stat().st_size.to_bytes(8, "little"))
            with open(p, "rb") as f:
                while block := f.read(_BLOCK):
                    h.update(block)
        _HASH_CACHE[key] = h.hexdigest()
    return _HASH_CACHE[key]


# --- random checkpoints -------------------------------------------------------------------------

_SIZES: dict[str, dict[str, Any]] = {
    # unit tests: 16 patches of a 32 px image; 64-wide 2-layer LMs with their families' MLP ratios
    # (Llama ~2.7x, Gemma 8x); a 32-wide 2-layer expert (pi0's expert is narrower than its VLM)
    "test": dict(vision=dict(image_size=32, patch_size=8, hidden_size=32, intermediate_size=64,
                             num_hidden_layers=2, num_attention_heads=2),
                 llama=dict(hidden_size=64, num_hidden_layers=2, num_attention_heads=4, intermediate_size=128),
                 gemma=dict(hidden_size=64, num_hidden_layers=2, num_attention_heads=4, intermediate_size=512),
                 vocab=0, expert=dict(width=32, layers=2, heads=4, mlp=128)),
    # GPU benchmarks, ~0.5e9 parameters: SigLIP-B/16 at 224 px (86 M) + a 1024-wide LM (Llama:
    # 24 layers, 0.37 B; Gemma: 18 layers, 0.3 B) + for flow a 512-wide 18-layer expert (76 M)
    "0.5b": dict(vision=dict(image_size=224, patch_size=16, hidden_size=768, intermediate_size=3072,
                             num_hidden_layers=12, num_attention_heads=12),
                 llama=dict(hidden_size=1024, num_hidden_layers=24, num_attention_heads=16, intermediate_size=2816),
                 gemma=dict(hidden_size=1024, num_hidden_layers=18, num_attention_heads=8, intermediate_size=4096),
                 vocab=32000, expert=dict(width=512, layers=18, heads=8, mlp=2048)),
}
_LIBERO_WORDS = ("put open close turn on off the a in into of top bowl plate drawer cabinet stove "
                 "basket mug black white wine bottle rack cream cheese ketchup alphabet soup tomato "
                 "sauce butter milk orange juice book caddy back front left right middle both it")


def vlm_config(family: str, size: str, tokenizer_size: int, n_bins: int = 256, image_token_id: int = 3) -> Any:
    """The transformers config of a random checkpoint: Llava (Llama + SigLIP) for the token
    family, PaliGemma (Gemma + SigLIP) for the flow family. No dropout anywhere."""
    from transformers import GemmaConfig, LlamaConfig, LlavaConfig, PaliGemmaConfig, SiglipVisionConfig

    if size not in _SIZES:
        raise ValueError(f"size {size!r}: expected one of {', '.join(_SIZES)}")
    s = _SIZES[size]
    # no attention-pooling head: neither family reads SigLIP's pooled output
    vision = SiglipVisionConfig(**s["vision"], attention_dropout=0.0, vision_use_head=False)
    if family == "tokens":
        vocab = max(s["vocab"], tokenizer_size + n_bins)
        text = LlamaConfig(**s["llama"], vocab_size=vocab, num_key_value_heads=s["llama"]["num_attention_heads"],
                           max_position_embeddings=4096, attention_dropout=0.0, pad_token_id=0, bos_token_id=2,
                           eos_token_id=None)
        # SigLIP has no CLS token: keep every patch ("full"), read the last layer (-1)
        return LlavaConfig(vision_config=vision, text_config=text, image_token_index=image_token_id,
                           vision_feature_select_strategy="full", vision_feature_layer=-1,
                           image_seq_length=(vision.image_size // vision.patch_size) ** 2)
    if family == "flow":
        vocab = max(s["vocab"], tokenizer_size)
        hidden = s["gemma"]["hidden_size"]
        # multi-query attention (one key/value head) as Gemma-2B, pi0's LM
        text = GemmaConfig(**s["gemma"], vocab_size=vocab, num_key_value_heads=1,
                           head_dim=hidden // s["gemma"]["num_attention_heads"],
                           max_position_embeddings=4096, attention_dropout=0.0, pad_token_id=0, bos_token_id=2,
                           eos_token_id=None)
        return PaliGemmaConfig(vision_config=vision, text_config=text, image_token_index=image_token_id,
                               projection_dim=hidden, hidden_size=hidden, vocab_size=vocab)
    raise ValueError(f"family {family!r}: expected one of {', '.join(FAMILIES)}")


def _save_tokenizer(path: Path, words: Iterable[str]) -> int:
    """A word-level tokenizer (dvla's word rule: lower-cased runs of [a-z0-9]), [BOS] first."""
    from tokenizers import Regex, Tokenizer, models, normalizers, pre_tokenizers, processors
    from transformers import PreTrainedTokenizerFast

    from .instructions import INSTRUCTIONS
    from .tokenizer import words as split_words

    vocab = {"[PAD]": 0, "[UNK]": 1, "[BOS]": 2, "<image>": 3}
    text = " ".join([*INSTRUCTIONS.values(), _LIBERO_WORDS, *words])
    for word in sorted(set(split_words(text))):
        vocab.setdefault(word, len(vocab))
    tok = Tokenizer(models.WordLevel(vocab, unk_token="[UNK]"))
    tok.normalizer = normalizers.Lowercase()
    tok.pre_tokenizer = pre_tokenizers.Split(Regex("[^a-z0-9]+"), behavior="removed")
    tok.post_processor = processors.TemplateProcessing(single="[BOS] $A", special_tokens=[("[BOS]", 2)])
    fast = PreTrainedTokenizerFast(tokenizer_object=tok, pad_token="[PAD]", unk_token="[UNK]", bos_token="[BOS]",
                                   additional_special_tokens=["<image>"])
    fast.save_pretrained(path)
    return len(vocab)


def save_random_checkpoint(path: str | Path, family: str, *, action_dim: int, max_chunk: int = 8,
                           size: str = "test", seed: int = 0, dtype: str = "float32", n_bins: int = 256,
                           denoise_steps: int = 4, instruction_words: Iterable[str] = ()) -> Path:
    """Write a random-initialised checkpoint for ``family`` to ``path`` (created or overwritten).

    Real transformers classes with the sizes of ``size`` (:data:`_SIZES`); action bounds [-1, 1].
    ``instruction_words``: text whose words join the tokenizer's vocabulary (the INSTRUCTIONS
    table and common LIBERO words are always in). ``"0.5b"`` allocates ~2 GB: GPU machines only."""
    import torch
    from safetensors.torch import save_file
    from transformers import AutoModelForImageTextToText
    from transformers.utils import logging as hf_logging

    hf_logging.disable_progress_bar()

    if family not in FAMILIES:
        raise ValueError(f"family {family!r}: expected one of {', '.join(FAMILIES)}")
    torch_dtype = {"float32": torch.float32, "bfloat16": torch.bfloat16}[dtype]
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    n_words = _save_tokenizer(path, instruction_words)
    config = vlm_config(family, size, n_words, n_bins)
    settings: dict[str, Any] = dict(family=family, action_dim=int(action_dim), max_chunk=int(max_chunk),
                                    action_low=[-1.0] * action_dim, action_high=[1.0] * action_dim)
    if family == "tokens":
        settings.update(n_bins=int(n_bins), bin_order="ascending")
    else:
        settings.update(denoise_steps=int(denoise_steps), expert=dict(_SIZES[size]["expert"]))
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = AutoModelForImageTextToText.from_config(config).to(torch_dtype)
        model.save_pretrained(path)
        if family == "flow":
            from .flow import ActionExpert

            expert = ActionExpert(config.text_config.hidden_size, action_dim, max_chunk, **settings["expert"])
            save_file({k: v.to(torch_dtype).contiguous() for k, v in expert.state_dict().items()}, path / EXPERT_FILE)
    (path / "preprocessor_config.json").write_text(json.dumps(
        {"image_mean": [0.5] * 3, "image_std": [0.5] * 3, "size": {"height": config.vision_config.image_size,
                                                                  "width": config.vision_config.image_size}}, indent=1))
    (path / POLICY_FILE).write_text(json.dumps(settings, indent=1) + "\n")
    return path
