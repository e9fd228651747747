"""Random-initialised checkpoints of the Hugging Face VLA families, in the directory format of
:mod:`.checkpoint`: real transformers classes (Llava = Llama + SigLIP for ``tokens``, PaliGemma =
Gemma + SigLIP for ``flow``, plus dvla's action expert) with an offline word-level tokenizer.
``size="test"`` is for unit and end-to-end tests, ``"0.5b"`` (about half a billion parameters)
for GPU benchmarks. Used by the tests and ``dvla bench vla``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Iterable

from .checkpoint import EXPERT_FILE, FAMILIES, POLICY_FILE

__all__ = ["save_random_checkpoint", "vlm_config", "SIZES"]


SIZES: dict[str, dict[str, Any]] = {
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

    if size not in SIZES:
        raise ValueError(f"size {size!r}: expected one of {', '.join(SIZES)}")
    s = SIZES[size]
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
    """Write a random-initialised checkpoint for ``family`` to ``path``: real transformers classes of
    :data:`SIZES` ``size``, action bounds [-1, 1]; the words of ``instruction_words``, the
    INSTRUCTIONS table and common LIBERO words join the tokenizer's vocabulary."""
    import torch
    from safetensors.torch import save_file
    from transformers import AutoModelForImageTextToText
    from transformers.utils import logging as hf_logging

    hf_logging.disable_progress_bar()
    dtypes = {"float32": torch.float32, "bfloat16": torch.bfloat16}
    if family not in FAMILIES or dtype not in dtypes:
        raise ValueError(f"family {family!r} / dtype {dtype!r}: expected one of {', '.join(FAMILIES)} / "
                         f"{', '.join(dtypes)}")
    torch_dtype = dtypes[dtype]
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    n_words = _save_tokenizer(path, instruction_words)
    config = vlm_config(family, size, n_words, n_bins)
    settings: dict[str, Any] = dict(family=family, action_dim=int(action_dim), max_chunk=int(max_chunk),
                                    action_low=[-1.0] * action_dim, action_high=[1.0] * action_dim)
    if family == "tokens":
        settings.update(n_bins=int(n_bins), bin_order="ascending")
    else:
        settings.update(denoise_steps=int(denoise_steps), expert=dict(SIZES[size]["expert"]))
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


def main(argv: list[str] | None = None) -> int:
    """``python -m dvla.learn.vla.build DIR --family tokens``: write a random checkpoint (to try
    the pipeline, e.g. topologies/local-hf-vla.yaml, before pointing it at real weights)."""
    import argparse

    ap = argparse.ArgumentParser(prog="python -m dvla.learn.vla.build", description=main.__doc__)
    ap.add_argument("path")
    ap.add_argument("--family", choices=sorted(FAMILIES), default="tokens")
    ap.add_argument("--action-dim", type=int, default=8, help="the robot's action size (PushCube pd_joint_delta_pos: 8)")
    ap.add_argument("--max-chunk", type=int, default=4)
    ap.add_argument("--size", choices=sorted(SIZES), default="test")
    ap.add_argument("--dtype", choices=("float32", "bfloat16"), default="float32")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    path = save_random_checkpoint(args.path, args.family, action_dim=args.action_dim, max_chunk=args.max_chunk,
                                  size=args.size, dtype=args.dtype, seed=args.seed)
    print(f"wrote a random {args.size} {args.family} checkpoint to {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
