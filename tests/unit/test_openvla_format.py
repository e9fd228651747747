"""OpenVLA / OpenVLA-OFT directories (dvla.learn.vla.openvla_format) on small directories written
here: what is read, the one-line error for each kind of broken directory (a missing shard, a pickle
that is not weights-only, a wrong dataset key or family), the OFT pickles converted once to
safetensors, and the export round trip; plus the prompt padding and action decoding of
openvla_processing that the reference recordings do not cover."""

from __future__ import annotations

import argparse
import collections
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from dvla.learn.vla.checkpoint import CheckpointError
from dvla.learn.vla.openvla_format import (check_openvla, content_hash, convert_components, export_openvla,
                                           read_oft_components, read_state_dict)
from dvla.learn.vla.openvla_processing import (EMPTY_TOKEN_ID, encode_prompts, normalize_proprio, pixel_values,
                                               prompt, tokens_to_normalized, unnormalize_actions)

VOCAB, PAD_TO, BINS, HIDDEN = 128, 64, 16, 8  # tokenizer vocabulary 64: action ids 48..63
HEAD, PROPRIO = "action_head--100_checkpoint", "proprio_projector--100_checkpoint"
TOWERS = ["vit_large_patch14_reg4_dinov2.lvd142m", "vit_so400m_patch14_siglip_224"]
SHARDS = ("model-00001-of-00002.safetensors", "model-00002-of-00002.safetensors")


def _stats(scale: float, action_dim: int = 7, proprio_dim: int = 8) -> dict:
    def entry(dim: int) -> dict:
        return {"q01": [-scale] * dim, "q99": [scale] * dim, "min": [-2 * scale] * dim, "max": [2 * scale] * dim,
                "mean": [0.0] * dim, "std": [1.0] * dim}
    return {"action": entry(action_dim) | {"mask": [True] * (action_dim - 1) + [False]},
            "proprio": entry(proprio_dim), "num_transitions": 10, "num_trajectories": 2}


def _weights() -> list[dict[str, torch.Tensor]]:
    gen = torch.Generator().manual_seed(0)

    def t(*shape: int) -> torch.Tensor:
        return torch.randn(*shape, generator=gen).to(torch.bfloat16)
    return [{"vision_backbone.featurizer.blocks.0.ls1.scale_factor": t(4), "projector.fc1.weight": t(HIDDEN, 6),
             "vision_backbone.fused_featurizer.blocks.0.norm1.weight": t(4)},
            {"language_model.model.embed_tokens.weight": t(VOCAB, HIDDEN),
             "language_model.lm_head.weight": t(VOCAB, HIDDEN)}]


def _heads(proprio: bool = True) -> dict[str, collections.OrderedDict]:
    gen = torch.Generator().manual_seed(1)
    sizes = (("layer_norm1.weight", (7 * HIDDEN,)), ("fc1.weight", (HIDDEN, 7 * HIDDEN)), ("fc2.weight", (7, HIDDEN)),
             ("fc2.bias", (7,)))
    head = collections.OrderedDict((f"module.model.{k}", torch.randn(*s, generator=gen).to(torch.bfloat16))
                                   for k, s in sizes)
    out = {HEAD: head}
    if proprio:
        out[PROPRIO] = collections.OrderedDict((f"module.{k}", torch.randn(*s, generator=gen)) for k, s in (
            ("fc1.weight", (HIDDEN, 8)), ("fc1.bias", (HIDDEN,)), ("fc2.weight", (HIDDEN, HIDDEN))))
    return out


def make_dir(root: Path, family: str = "openvla", *, datasets: tuple[str, ...] = ("ds_a",)) -> Path:
    """The Prismatic layout in miniature: the files and key names upstream writes, tiny tensors."""
    root.mkdir(parents=True)
    weight_map = {}
    for name, tensors in zip(SHARDS, _weights()):
        save_file(tensors, str(root / name), metadata={"format": "pt"})
        weight_map |= {k: name for k in tensors}
    (root / "model.safetensors.index.json").write_text(json.dumps({"metadata": {"total_size": 0},
                                                                   "weight_map": dict(sorted(weight_map.items()))}))
    config = {"model_type": "openvla", "architectures": ["OpenVLAForActionPrediction"], "timm_model_ids": TOWERS,
              "use_fused_vision_backbone": True, "image_resize_strategy": "resize-naive", "n_action_bins": BINS,
              "pad_to_multiple_of": PAD_TO, "text_config": {"vocab_size": VOCAB, "hidden_size": HIDDEN},
              "norm_stats": {d: _stats(1.0) for d in datasets}}
    (root / "config.json").write_text(json.dumps(config, indent=2))
    (root / "preprocessor_config.json").write_text(json.dumps({
        "image_processor_type": "PrismaticImageProcessor", "image_resize_strategy": "resize-naive",
        "input_sizes": [[3, 224, 224]] * 2, "interpolations": ["bicubic"] * 2,
        "means": [[0.485, 0.456, 0.406], [0.5] * 3], "stds": [[0.229, 0.224, 0.225], [0.5] * 3]}))
    (root / "tokenizer.json").write_text('{"version": "1.0", "model": {"type": "WordLevel", "vocab": {}}}')
    (root / "modeling_prismatic.py").write_text("# upstream code travels with the checkpoint\n")
    if family == "openvla-oft":
        (root / "dataset_statistics.json").write_text(json.dumps({d: _stats(0.5) for d in datasets}, indent=2))
        for stem, state in _heads().items():
            torch.save(state, root / f"{stem}.pt")
    return root


def assert_one_line(call, path: Path | str, *fragments: str) -> None:
    """``call()`` raises a CheckpointError of one line that starts with ``path`` and holds ``fragments``."""
    with pytest.raises(CheckpointError) as info:
        call()
    message = str(info.value)
    assert "\n" not in message and message.startswith(str(path)), message
    for fragment in fragments:
        assert fragment in message, message


class _RunsCode:
    """Unpickling this runs a shell command: what a hostile .pt does."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


# --- what is read -------------------------------------------------------------------------------


def test_reads_an_openvla_directory(tmp_path: Path) -> None:
    ck = check_openvla(make_dir(tmp_path / "ckpt"), "openvla")
    assert (ck.family, ck.llm_dim, ck.n_action_bins, ck.tokenizer_vocab_size) == ("openvla", HIDDEN, BINS, 64)
    assert ck.action_token_ids == range(48, 64)
    assert ck.weights == tuple(ck.path / s for s in SHARDS)
    assert ck.weight_index == ck.path / "model.safetensors.index.json"
    assert list(ck.shapes) == [k for w in _weights() for k in sorted(w)]  # shard by shard, as each file lists them
    assert (ck.action_dim, ck.chunk_size, ck.num_images, ck.proprio_dim, ck.components) == (7, 1, 1, None, {})
    assert (ck.dataset, ck.datasets, ck.stats_file) == ("ds_a", ("ds_a",), ck.path / "config.json")
    assert ck.action_stats["q99"] == (1.0,) * 7 and ck.action_stats["mask"] == (True,) * 6 + (False,)
    assert (ck.normalization, ck.norm_eps, ck.proprio_stats) == ("bounds_q99", 0.0, None)
    assert ck.image_size == (224, 224) and ck.image_stds == ((0.229, 0.224, 0.225), (0.5, 0.5, 0.5))
    assert ck.tokenizer_files == (ck.path / "tokenizer.json",)
    state = read_state_dict(ck)
    assert list(state) == list(ck.shapes) and state["projector.fc1.weight"].dtype == torch.bfloat16
    assert read_state_dict(ck, torch.float32)["projector.fc1.weight"].dtype == torch.float32


def test_reads_an_oft_directory(tmp_path: Path) -> None:
    ck = check_openvla(make_dir(tmp_path / "ckpt", "openvla-oft"), "openvla-oft")
    # dataset_statistics.json replaces config.json's norm_stats, as upstream inference does
    assert ck.stats_file == ck.path / "dataset_statistics.json" and ck.action_stats["q99"] == (0.5,) * 7
    assert (ck.action_dim, ck.chunk_size, ck.num_images, ck.proprio_dim) == (7, 8, 2, 8)  # LIBERO
    assert (ck.normalization, ck.norm_eps, ck.proprio_stats["q01"]) == ("bounds_q99", 1e-8, (-0.5,) * 8)
    assert ck.components == {"action_head": ck.path / f"{HEAD}.pt", "proprio_projector": ck.path / f"{PROPRIO}.pt"}
    assert ck.component_shapes["action_head"] == {k[len("module."):]: tuple(v.shape) for k, v in _heads()[HEAD].items()}
    heads = read_oft_components(ck)
    for name, stem in (("action_head", HEAD), ("proprio_projector", PROPRIO)):
        assert list(heads[name]) == list(ck.component_shapes[name])
        for key, tensor in _heads()[stem].items():
            assert torch.equal(heads[name][key[len("module."):]], tensor) and heads[name][key[7:]].dtype == tensor.dtype


def test_no_proprio_projector_and_an_unknown_platform(tmp_path: Path) -> None:
    root = make_dir(tmp_path / "ckpt", "openvla-oft")
    (root / f"{PROPRIO}.pt").unlink()
    ck = check_openvla(root, "openvla-oft")
    assert (ck.proprio_dim, ck.proprio_stats, list(ck.components)) == (None, None, ["action_head"])
    with pytest.raises(ValueError, match="no proprio projector"):
        normalize_proprio(torch.zeros(8), ck)
    head = _heads()[HEAD] | {"module.model.fc2.weight": torch.zeros(5, HIDDEN), "module.model.layer_norm1.weight":
                             torch.zeros(5 * HIDDEN)}
    torch.save(head, root / f"{HEAD}.pt")
    assert_one_line(lambda: check_openvla(root, "openvla-oft"), root / f"{HEAD}.pt", "5 action dims",
                    "policy_kwargs.chunk_size")
    (root / "dataset_statistics.json").write_text(json.dumps({"ds_a": _stats(0.5, action_dim=5)}))
    assert check_openvla(root, "openvla-oft", chunk_size=4).chunk_size == 4


def test_the_format_module_imports_no_torch(tmp_path: Path) -> None:
    """The CLI checks directories, OFT pickles included, without importing torch."""
    root = make_dir(tmp_path / "ckpt", "openvla-oft")
    code = ("import sys; from dvla.learn.vla.openvla_format import check_openvla, content_hash; "
            f"content_hash(check_openvla({str(root)!r}, 'openvla-oft')); "
            "sys.exit('torch' in sys.modules or 'transformers' in sys.modules)")
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0


# --- one line per broken directory ---------------------------------------------------------------


def test_missing_shard(tmp_path: Path) -> None:
    root = make_dir(tmp_path / "ckpt")
    (root / SHARDS[1]).unlink()
    assert_one_line(lambda: check_openvla(root, "openvla"), root, f"names shard {SHARDS[1]}", "not in the directory")


def test_index_and_shards_disagree(tmp_path: Path) -> None:
    root = make_dir(tmp_path / "ckpt")
    index = json.loads((root / "model.safetensors.index.json").read_text())
    index["weight_map"]["language_model.model.norm.weight"] = SHARDS[1]
    (root / "model.safetensors.index.json").write_text(json.dumps(index))
    assert_one_line(lambda: check_openvla(root, "openvla"), root / "model.safetensors.index.json",
                    "language_model.model.norm.weight")


def test_pickle_that_is_not_weights_only(tmp_path: Path) -> None:
    root = make_dir(tmp_path / "ckpt", "openvla-oft")
    checked = check_openvla(root, "openvla-oft")
    head = root / f"{HEAD}.pt"
    torch.save(_heads()[HEAD] | {"module.args": argparse.Namespace(lr=1e-4)}, head)
    assert_one_line(lambda: check_openvla(root, "openvla-oft"), head, "not a weights-only state dict",
                    "argparse.Namespace")
    assert_one_line(lambda: read_oft_components(checked), head, "torch.load(weights_only=True)", "argparse.Namespace")
    marker = tmp_path / "ran"
    torch.save({"module.model.fc2.weight": _RunsCode(marker)}, head)
    assert_one_line(lambda: check_openvla(root, "openvla-oft"), head, "refused", "system")
    assert_one_line(lambda: read_oft_components(checked), head, "refused")
    assert_one_line(lambda: convert_components(checked), head, "refused")
    assert not marker.exists()
    head.write_bytes(b"\x80\x02}q\x00.")  # a bare pickle, not torch.save's zip
    assert_one_line(lambda: check_openvla(root, "openvla-oft"), head, "not a torch.save zip archive")


def test_dataset_keys(tmp_path: Path) -> None:
    root = make_dir(tmp_path / "ckpt", datasets=("ds_a", "ds_b"))
    assert_one_line(lambda: check_openvla(root, "openvla"), root, "statistics for 2 datasets (ds_a, ds_b)",
                    "policy_kwargs.dataset")
    assert_one_line(lambda: check_openvla(root, "openvla", dataset="bridge"), root, "no statistics for dataset "
                    "'bridge' in config.json", "known: ds_a, ds_b")
    assert check_openvla(root, "openvla", dataset="ds_b").dataset == "ds_b"
    # the plain model also takes a key that only dataset_statistics.json has
    (root / "dataset_statistics.json").write_text(json.dumps({"ds_c": _stats(2.0)}))
    ck = check_openvla(root, "openvla", dataset="ds_c")
    assert (ck.stats_file.name, ck.datasets, ck.action_stats["q01"]) == ("dataset_statistics.json",
                                                                         ("ds_a", "ds_b", "ds_c"), (-2.0,) * 7)
    stats = _stats(2.0, action_dim=6)
    stats["action"]["mask"].append(True)
    (root / "dataset_statistics.json").write_text(json.dumps({"ds_c": stats}))
    assert_one_line(lambda: check_openvla(root, "openvla", dataset="ds_c"), root / "dataset_statistics.json",
                    "ds_c.action.mask must be a list of 6 booleans, got 7 values")


def test_oft_statistics_must_fit_the_heads(tmp_path: Path) -> None:
    root = make_dir(tmp_path / "ckpt", "openvla-oft")
    stats = _stats(0.5)
    stats["action"]["q99"] = [0.5] * 6
    (root / "dataset_statistics.json").write_text(json.dumps({"ds_a": stats}))
    assert_one_line(lambda: check_openvla(root, "openvla-oft"), root / "dataset_statistics.json",
                    "ds_a.action.q99 must be a list of 7 numbers, got 6 values")
    del stats["proprio"]
    stats["action"]["q99"] = [0.5] * 7
    (root / "dataset_statistics.json").write_text(json.dumps({"ds_a": stats}))
    assert_one_line(lambda: check_openvla(root, "openvla-oft"), root / "dataset_statistics.json",
                    "ds_a.proprio is missing")


def test_family_and_model_type(tmp_path: Path) -> None:
    plain, oft = make_dir(tmp_path / "plain"), make_dir(tmp_path / "oft", "openvla-oft")
    assert_one_line(lambda: check_openvla(plain, "openvla-oft"), plain, "no action_head--<step>_checkpoint.pt",
                    "loads as openvla")
    assert_one_line(lambda: check_openvla(oft, "openvla"), oft, f"is an OpenVLA-OFT checkpoint ({HEAD}.pt)",
                    "load it as openvla-oft")
    torch.save(_heads()[HEAD], oft / "noisy_action_projector--100_checkpoint.pt")
    assert_one_line(lambda: check_openvla(oft, "openvla-oft"), oft / "noisy_action_projector--100_checkpoint.pt",
                    "diffusion action head", "not supported")
    config = json.loads((plain / "config.json").read_text())
    (plain / "config.json").write_text(json.dumps(config | {"model_type": "prismatic"}))
    assert_one_line(lambda: check_openvla(plain, "openvla"), plain / "config.json", "model_type is 'prismatic'")
    (plain / "config.json").write_text(json.dumps(config | {"image_resize_strategy": "letterbox"}))
    assert check_openvla(plain, "openvla")  # the processor's own setting is what counts
    (plain / "tokenizer.json").unlink()
    assert_one_line(lambda: check_openvla(plain, "openvla"), plain, "tokenizer.json missing")


# --- conversion, fingerprint, export --------------------------------------------------------------


def test_convert_then_load_from_safetensors(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    ck = check_openvla(make_dir(tmp_path / "ckpt", "openvla-oft"), "openvla-oft")
    before, digest = read_oft_components(ck), content_hash(ck)
    written = convert_components(ck)
    assert written == [ck.path / f"{HEAD}.safetensors", ck.path / f"{PROPRIO}.safetensors"]
    assert convert_components(ck) == []  # once
    converted = check_openvla(ck.path, "openvla-oft")
    assert converted.components == {"action_head": written[0], "proprio_projector": written[1]}
    assert converted.component_shapes == ck.component_shapes
    monkeypatch.setattr(torch, "load", lambda *a, **k: pytest.fail("a converted directory was unpickled"))
    after = read_oft_components(converted)
    for name, state in before.items():
        assert list(after[name]) == list(state)
        for key, tensor in state.items():
            assert after[name][key].dtype == tensor.dtype and torch.equal(after[name][key], tensor), key
    assert content_hash(converted) == digest  # a .pt and its conversion hash the same


def test_content_hash_follows_the_files(tmp_path: Path) -> None:
    one = check_openvla(make_dir(tmp_path / "one", "openvla-oft"), "openvla-oft")
    two = check_openvla(make_dir(tmp_path / "two", "openvla-oft"), "openvla-oft")
    assert content_hash(one) == content_hash(two)  # same content elsewhere
    torch.save(_heads()[HEAD] | {"module.model.fc2.bias": torch.ones(7, dtype=torch.bfloat16)}, two.path / f"{HEAD}.pt")
    assert content_hash(one) != content_hash(two)
    stats = json.loads((one.path / "dataset_statistics.json").read_text())
    (one.path / "dataset_statistics.json").write_text(json.dumps(stats))  # same numbers, other bytes
    assert content_hash(check_openvla(one.path, "openvla-oft")) != content_hash(two)


def test_export_round_trip(tmp_path: Path) -> None:
    ck = check_openvla(make_dir(tmp_path / "ckpt", "openvla-oft"), "openvla-oft")
    trained = {k: v.float() for k, v in read_state_dict(ck).items()}  # a model run in float32
    heads = {n: {k: v.float() for k, v in s.items()} for n, s in read_oft_components(ck).items()}
    out = export_openvla(ck, trained, tmp_path / "export", heads=heads)
    for file in sorted(ck.path.iterdir()):  # bf16 as stored, the same shard split: the same bytes
        if file.suffix != ".pt":
            assert (out / file.name).read_bytes() == file.read_bytes(), file.name
    again = check_openvla(out, "openvla-oft")
    assert content_hash(again) == content_hash(ck)
    for stem, original in _heads().items():  # upstream's form: module. keys, stored order and dtypes
        written = torch.load(out / f"{stem}.pt", weights_only=True)
        assert list(written) == list(original)
        for key, tensor in original.items():
            assert written[key].dtype == tensor.dtype
            assert written[key].view(torch.uint8).numpy().tobytes() == tensor.view(torch.uint8).numpy().tobytes()
    copy = export_openvla(ck, trained, tmp_path / "copy")  # heads=None: the component files copied unchanged
    assert all((copy / f.name).read_bytes() == f.read_bytes() for f in ck.components.values())


def test_export_refuses_a_non_empty_directory(tmp_path: Path) -> None:
    ck = check_openvla(make_dir(tmp_path / "ckpt"), "openvla")
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "keep.txt").write_text("mine")
    assert_one_line(lambda: export_openvla(ck, read_state_dict(ck), tmp_path / "out"), tmp_path / "out",
                    "not an empty directory")
    assert (tmp_path / "out" / "keep.txt").read_text() == "mine"


def test_export_checks_what_it_writes(tmp_path: Path) -> None:
    ck = check_openvla(make_dir(tmp_path / "ckpt", "openvla-oft"), "openvla-oft")
    state, heads = read_state_dict(ck), read_oft_components(ck)
    missing = {k: v for k, v in state.items() if k != "projector.fc1.weight"}
    assert_one_line(lambda: export_openvla(ck, missing, tmp_path / "a"), tmp_path / "a", "lacks projector.fc1.weight")
    resized = state | {"projector.fc1.weight": torch.zeros(3, 3)}
    assert_one_line(lambda: export_openvla(ck, resized, tmp_path / "b"), tmp_path / "b", "has shape (3, 3)")
    extra = state | {"lora_A.weight": torch.zeros(2)}
    assert_one_line(lambda: export_openvla(ck, extra, tmp_path / "c"), tmp_path / "c", "lora_A.weight is not")
    bad = {"action_head": {k: v for k, v in heads["action_head"].items() if k != "model.fc2.bias"}}
    assert_one_line(lambda: export_openvla(ck, state, tmp_path / "d", heads=bad), tmp_path / "d",
                    "action_head lacks model.fc2.bias")
    assert_one_line(lambda: export_openvla(ck, state, tmp_path / "e", heads={"film": {}}), tmp_path / "e",
                    "film is not a component")
    assert not any(p.name != "ckpt" for p in tmp_path.iterdir())  # nothing left behind


# --- processing the recordings do not reach ---------------------------------------------------------


class _Tokenizer:
    """Stand-in: BOS, one id per word; the recorded prompts need the real tokenizer (references)."""

    pad_token_id = 32000

    def __call__(self, texts: list[str]) -> dict:
        return {"input_ids": [[1] + [100 + len(w) for w in t.split()] for t in texts]}


def test_prompt_and_padding() -> None:
    assert prompt("Open The Drawer") == "In: What action should the robot take to open the drawer?\nOut:"
    tokenizer = _Tokenizer()
    short, long = (row + [EMPTY_TOKEN_ID] for row in tokenizer([prompt("a"), prompt("a b c")])["input_ids"])
    ids, mask = encode_prompts(tokenizer, ["a", "a b c"])
    assert ids.tolist() == [short + [32000] * 2, long] and ids.dtype == torch.int64
    assert mask.tolist() == [[True] * len(short) + [False] * 2, [True] * len(long)]
    ids, mask = encode_prompts(tokenizer, ["a", "a b c"], padding_side="left")
    assert ids.tolist() == [[32000] * 2 + short, long] and mask[0].tolist() == [False] * 2 + [True] * len(short)


def test_action_decoding(tmp_path: Path) -> None:
    ck = check_openvla(make_dir(tmp_path / "ckpt"), "openvla")
    first, last = ck.action_token_ids[0], ck.action_token_ids[-1]
    # the last id is the lowest bin; the two lowest action ids share the top bin centre
    normalized = tokens_to_normalized(torch.tensor([last, last - 1, first + 1, first]), ck)
    centre = 1.0 / (BINS - 1)
    torch.testing.assert_close(normalized, torch.tensor([-1 + centre, -1 + 3 * centre, 1 - centre, 1 - centre],
                                                        dtype=torch.float64))
    actions = unnormalize_actions(torch.tensor([[0.5] * 7]), ck)  # q01/q99 = -1/1: unchanged, gripper untouched
    assert actions.dtype == torch.float64 and torch.equal(actions, torch.full((1, 7), 0.5, dtype=torch.float64))
    with pytest.raises(ValueError, match="actions have 6 dims"):
        unnormalize_actions(torch.zeros(6), ck)


def test_pixel_values_resize_as_the_processor(tmp_path: Path) -> None:
    """An image not at 224x224 is resized by PIL's bicubic (what PrismaticImageProcessor runs), then
    each tower's normalisation; the reference images are 224x224, so this path is checked here."""
    from PIL import Image

    ck = check_openvla(make_dir(tmp_path / "ckpt"), "openvla")
    image = torch.randint(0, 256, (2, 256, 320, 3), generator=torch.Generator().manual_seed(0), dtype=torch.uint8)
    got = pixel_values(image, ck)
    assert got.shape == (2, 6, 224, 224)
    resized = torch.from_numpy(np.stack([np.asarray(Image.fromarray(a).resize((224, 224), Image.BICUBIC))
                                         for a in image.numpy()])).permute(0, 3, 1, 2).float() / 255
    for tower, (mean, std) in enumerate(zip(ck.image_means, ck.image_stds)):
        want = (resized - torch.tensor(mean).view(-1, 1, 1)) / torch.tensor(std).view(-1, 1, 1)
        assert torch.equal(got[:, 3 * tower: 3 * tower + 3], want)
    assert torch.equal(pixel_values(image.permute(0, 3, 1, 2), ck), got)  # channels first
    with pytest.raises(ValueError, match="uint8"):
        pixel_values(image.float(), ck)
    with pytest.raises(ValueError, match="2 camera image"):
        pixel_values([image, image], ck)
