"""LeRobot / openpi policy directories (dvla.learn.vla.lerobot_format) and the processing on them
(lerobot_processing), on small directories written here: what is read, the one-line error for each
kind of broken directory, the Hugging Face cache lookup (a temporary cache, never the network), the
openpi and base-checkpoint layouts, every normalisation mode, image resizing and export."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors import safe_open
from safetensors.numpy import save_file

from dvla.learn.vla.checkpoint import CheckpointError
from dvla.learn.vla.lerobot_format import (ACTION_KEY, STATE_KEY, check_lerobot, content_hash, export_lerobot,
                                           read_state_dict, resolve_checkpoint)
from dvla.learn.vla.lerobot_processing import Normalizer, model_images, pad_to, resize_with_pad

STATE_DIM, ACTION_DIM, WIDTH = 4, 3, 8
CAMERAS = ("observation.images.top", "observation.images.wrist")
STATS_FILE = "policy_preprocessor_step_1_normalizer_processor.safetensors"
UNSTATS_FILE = "policy_postprocessor_step_0_unnormalizer_processor.safetensors"
TOKENIZER_JSON = '{"version": "1.0", "model": {"type": "WordLevel", "vocab": {"[UNK]": 0}, "unk_token": "[UNK]"}}'


@pytest.fixture(autouse=True)
def _empty_hub_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """Every test sees an empty Hugging Face cache of its own and no network."""
    cache = tmp_path / "hf-home"
    monkeypatch.setenv("HF_HOME", str(cache))
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    for var in ("HF_HUB_CACHE", "HUGGINGFACE_HUB_CACHE"):
        monkeypatch.delenv(var, raising=False)
    return cache / "hub"


def _weights(family: str, prefix: str = "model.") -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    shapes = {"action_in_proj.weight": (WIDTH, 32), "action_out_proj.weight": (32, WIDTH)}
    if family == "smolvla":
        shapes |= {"vlm_with_expert.vlm.model.text_model.norm.weight": (WIDTH,), "state_proj.weight": (WIDTH, 32)}
    else:
        shapes |= {"paligemma_with_expert.paligemma.lm_head.weight": (16, WIDTH)}
        shapes |= {"state_proj.weight": (WIDTH, 32)} if family == "pi0" else {"time_mlp_in.weight": (WIDTH, WIDTH)}
    return {prefix + k: rng.standard_normal(s).astype(np.float32) for k, s in shapes.items()}


def _stats(span_zero: bool = False) -> dict[str, np.ndarray]:
    out = {}
    for key, dim in ((STATE_KEY, STATE_DIM), (ACTION_KEY, ACTION_DIM)):
        mean = np.linspace(-0.5, 0.5, dim).astype(np.float32)
        std = np.linspace(0.5, 1.5, dim).astype(np.float32)
        for name, value in {"mean": mean, "std": std, "min": mean - 3 * std, "max": mean + 3 * std,
                            "q01": mean - 2 * std, "q10": mean - std, "q90": mean + std, "q99": mean + 2 * std}.items():
            out[f"{key}.{name}"] = value.astype(np.float32)
        if span_zero:  # one constant dim: every span is 0 there
            for name in ("min", "max", "q01", "q10", "q90", "q99"):
                out[f"{key}.{name}"][0] = mean[0]
    return out


def make_dir(root: Path, family: str = "pi0", *, mode: str = "MEAN_STD", base: bool = False,
             tokenizer: bool = True, span_zero: bool = False) -> Path:
    """A LeRobot-written directory in miniature: the files and keys LeRobot writes, tiny tensors."""
    root.mkdir(parents=True)
    save_file(_weights(family), str(root / "model.safetensors"))
    visual = {c: {"type": "VISUAL", "shape": [3, 224, 224]} for c in CAMERAS}
    config = {"type": family, "input_features": visual | {STATE_KEY: {"type": "STATE", "shape": [STATE_DIM]}},
              "output_features": {ACTION_KEY: {"type": "ACTION", "shape": [ACTION_DIM]}}, "chunk_size": 10,
              "n_action_steps": 5, "max_state_dim": 32, "max_action_dim": 32, "tokenizer_max_length": 48,
              "normalization_mapping": {"VISUAL": "IDENTITY", "STATE": mode, "ACTION": mode}}
    tokenizer_name = "google/paligemma-3b-pt-224"
    if family == "smolvla":
        config |= {"vlm_model_name": "./backbone", "resize_imgs_with_padding": [512, 384], "num_steps": 7}
        (root / "backbone").mkdir()
        (root / "backbone" / "config.json").write_text("{}")
        (root / "backbone" / "tokenizer.json").write_text(TOKENIZER_JSON)
        tokenizer_name = "./backbone"
    else:
        config |= {"num_inference_steps": 7, "image_resolution": [224, 224]}
        if tokenizer:
            (root / "tokenizer").mkdir()
            (root / "tokenizer" / "tokenizer.json").write_text(TOKENIZER_JSON)
    (root / "config.json").write_text(json.dumps(config))
    norm_map = config["normalization_mapping"]
    features = {} if base else {**visual, STATE_KEY: {"type": "STATE", "shape": [STATE_DIM]},
                                ACTION_KEY: {"type": "ACTION", "shape": [ACTION_DIM]}}
    normalizer = {"registry_name": "normalizer_processor", "config": {"eps": 1e-8, "features": features,
                                                                      "norm_map": norm_map}}
    unnormalizer = {"registry_name": "unnormalizer_processor",
                    "config": {"eps": 1e-8, "features": {} if base else {ACTION_KEY: features[ACTION_KEY]},
                               "norm_map": norm_map}}
    if not base:
        normalizer["state_file"], unnormalizer["state_file"] = STATS_FILE, UNSTATS_FILE
        save_file(_stats(span_zero), str(root / STATS_FILE))
        save_file(_stats(span_zero), str(root / UNSTATS_FILE))
    tok_step = {"registry_name": "tokenizer_processor",
                "config": {"max_length": 48, "padding": "longest" if family == "smolvla" else "max_length",
                           "padding_side": "right", "truncation": True, "tokenizer_name": tokenizer_name}}
    (root / "policy_preprocessor.json").write_text(json.dumps({"name": "policy_preprocessor", "steps": [
        {"registry_name": "to_batch_processor", "config": {}}, normalizer, tok_step]}))
    (root / "policy_postprocessor.json").write_text(json.dumps({"name": "policy_postprocessor",
                                                                "steps": [unnormalizer]}))
    return root


def make_openpi_dir(root: Path, family: str = "pi0") -> Path:
    """openpi's convert_jax_model_to_pytorch.py output in miniature (stats under assets/<robot>/)."""
    root.mkdir(parents=True)
    save_file(_weights(family, prefix=""), str(root / "model.safetensors"))
    (root / "config.json").write_text(json.dumps({"action_dim": 32, "action_horizon": 10, "precision": "float32",
                                                  "paligemma_variant": "gemma_2b",
                                                  "action_expert_variant": "gemma_300m"}))
    stats = _stats()
    norm_stats = {name: {s: stats[f"{key}.{s}"].tolist() for s in ("mean", "std", "q01", "q99")}
                  for key, name in ((STATE_KEY, "state"), (ACTION_KEY, "actions"))}
    (root / "assets" / "trossen").mkdir(parents=True)
    (root / "assets" / "trossen" / "norm_stats.json").write_text(json.dumps({"norm_stats": norm_stats}))
    return root


def cache_repo(cache: Path, repo_id: str, source: Path) -> Path:
    """Put ``source``'s files into a Hugging Face cache as huggingface_hub lays a download out."""
    repo = cache / f"models--{repo_id.replace('/', '--')}"
    snapshot = repo / "snapshots" / ("0" * 40)
    shutil.copytree(source, snapshot)
    (repo / "refs").mkdir(parents=True)
    (repo / "refs" / "main").write_text("0" * 40)
    return snapshot


def assert_one_line(call, path: Path | str, *fragments: str) -> None:
    """``call()`` raises a CheckpointError of one line that starts with ``path`` and holds ``fragments``."""
    with pytest.raises(CheckpointError) as info:
        call()
    message = str(info.value)
    assert "\n" not in message and message.startswith(str(path)), message
    for fragment in fragments:
        assert fragment in message, message


# --- what is read -------------------------------------------------------------------------------


@pytest.mark.parametrize("family", ["pi0", "pi05", "smolvla"])
def test_reads_a_lerobot_directory(tmp_path: Path, family: str) -> None:
    ck = check_lerobot(make_dir(tmp_path / "ckpt", family), family)
    assert (ck.family, ck.layout, ck.key_prefix) == (family, "lerobot", "model.")
    assert ck.cameras == CAMERAS
    assert ck.image_size == ((384, 512) if family == "smolvla" else (224, 224))  # smolvla's config is (W, H)
    assert (ck.state_dim, ck.action_dim, ck.chunk_size, ck.n_action_steps, ck.num_steps) == (STATE_DIM, ACTION_DIM,
                                                                                             10, 5, 7)
    assert (ck.max_state_dim, ck.max_action_dim, ck.tokenizer_max_length) == (32, 32, 48)
    assert ck.tokenizer_settings["padding"] == ("longest" if family == "smolvla" else "max_length")
    assert ck.stats[STATE_KEY]["mean"] == tuple(float(x) for x in _stats()[f"{STATE_KEY}.mean"])
    assert len(ck.stats[ACTION_KEY]["q99"]) == ACTION_DIM
    assert ck.tokenizer_dir == ck.path / ("backbone" if family == "smolvla" else "tokenizer")
    assert ck.vlm_dir == (ck.path / "backbone" if family == "smolvla" else None)
    assert [p.name for p in ck.processor_files] == ["policy_preprocessor.json", STATS_FILE,
                                                    "policy_postprocessor.json", UNSTATS_FILE]
    assert list(read_state_dict(ck)) == sorted(k[len("model."):] for k in _weights(family))  # the file's order


def test_the_format_module_imports_no_torch() -> None:
    code = ("import sys, dvla.learn.vla.lerobot_format; "
            "sys.exit('torch' in sys.modules or 'transformers' in sys.modules)")
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0


# --- one line per broken directory -----------------------------------------------------------------


def test_missing_config(tmp_path: Path) -> None:
    root = make_dir(tmp_path / "ckpt")
    (root / "config.json").unlink()
    assert_one_line(lambda: check_lerobot(root, "pi0"), root, "config.json missing")


def test_other_family(tmp_path: Path) -> None:
    root = make_dir(tmp_path / "ckpt", "smolvla")
    assert_one_line(lambda: check_lerobot(root, "pi05"), root, "is a 'smolvla' checkpoint, policy pi05 needs 'pi05'")


def test_config_and_weights_disagree(tmp_path: Path) -> None:
    root = make_dir(tmp_path / "ckpt", "pi0")
    config = json.loads((root / "config.json").read_text())
    (root / "config.json").write_text(json.dumps(config | {"type": "pi05"}))
    assert_one_line(lambda: check_lerobot(root, "pi05"), root, "config.json says 'pi05' but the weights are 'pi0'")
    (root / "config.json").write_text(json.dumps(config | {"max_action_dim": 24}))
    assert_one_line(lambda: check_lerobot(root, "pi0"), root, "max_action_dim 24", "action_in_proj.weight takes 32")


def test_truncated_weights(tmp_path: Path) -> None:
    root = make_dir(tmp_path / "ckpt")
    data = (root / "model.safetensors").read_bytes()
    (root / "model.safetensors").write_bytes(data[:-100])
    assert_one_line(lambda: check_lerobot(root, "pi0"), root / "model.safetensors", "truncated safetensors file")


def test_missing_stats_file(tmp_path: Path) -> None:
    root = make_dir(tmp_path / "ckpt")
    (root / STATS_FILE).unlink()
    assert_one_line(lambda: check_lerobot(root, "pi0"), root,
                    f"{STATS_FILE} missing (named by policy_preprocessor.json, step normalizer_processor)")


def test_stats_lacking_what_the_mode_needs(tmp_path: Path) -> None:
    root = make_dir(tmp_path / "ckpt", mode="QUANTILES")
    save_file({k: v for k, v in _stats().items() if k != f"{STATE_KEY}.q01"}, str(root / STATS_FILE))
    assert_one_line(lambda: check_lerobot(root, "pi0"), root / STATS_FILE,
                    "QUANTILES normalisation of observation.state needs observation.state.q01")


def test_no_tokenizer(tmp_path: Path) -> None:
    root = make_dir(tmp_path / "ckpt", tokenizer=False)
    assert_one_line(lambda: check_lerobot(root, "pi0"), root, "no tokenizer", "'google/paligemma-3b-pt-224'",
                    "policy_kwargs.tokenizer",
                        "hf download google/paligemma-3b-pt-224")
    assert check_lerobot(root, "pi0", need_tokenizer=False).tokenizer_dir is None
    assert_one_line(lambda: check_lerobot(root, "pi0", tokenizer=tmp_path / "nowhere"), tmp_path / "nowhere",
                    "policy_kwargs.tokenizer")


def test_repo_id_not_in_cache(_empty_hub_cache: Path) -> None:
    assert_one_line(lambda: resolve_checkpoint("lerobot/pi05_base"), "lerobot/pi05_base",
                    "not a directory and not in the Hugging Face cache",
                        str(_empty_hub_cache), "download it first: hf download lerobot/pi05_base")
    assert_one_line(lambda: resolve_checkpoint("/no/such/dir"), "/no/such/dir", "does not exist")


def test_repo_id_and_tokenizer_from_the_cache(tmp_path: Path, _empty_hub_cache: Path) -> None:
    snapshot = cache_repo(_empty_hub_cache, "someone/tiny-pi0", make_dir(tmp_path / "src", tokenizer=False))
    tokenizer = cache_repo(_empty_hub_cache, "google/paligemma-3b-pt-224", make_dir(tmp_path / "tok") / "tokenizer")
    assert resolve_checkpoint("someone/tiny-pi0") == snapshot
    ck = check_lerobot("someone/tiny-pi0", "pi0")
    assert (ck.path, ck.tokenizer_dir) == (snapshot, tokenizer)
    assert check_lerobot("someone/tiny-pi0", "pi0", tokenizer="google/paligemma-3b-pt-224").tokenizer_dir == tokenizer


def test_export_refuses_a_non_empty_directory(tmp_path: Path) -> None:
    ck = check_lerobot(make_dir(tmp_path / "ckpt"), "pi0")
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "keep.txt").write_text("mine")
    assert_one_line(lambda: export_lerobot(ck, read_state_dict(ck), tmp_path / "out"), tmp_path / "out",
                    "not an empty directory")
    assert (tmp_path / "out" / "keep.txt").read_text() == "mine"


def test_export_checks_the_state_dict(tmp_path: Path) -> None:
    ck = check_lerobot(make_dir(tmp_path / "ckpt"), "pi0")
    state = read_state_dict(ck)
    missing = {k: v for k, v in state.items() if k != "state_proj.weight"}
    assert_one_line(lambda: export_lerobot(ck, missing, tmp_path / "a"), tmp_path / "a", "lacks state_proj.weight")
    resized = state | {"state_proj.weight": torch.zeros(8, 16)}
    assert_one_line(lambda: export_lerobot(ck, resized, tmp_path / "b"), tmp_path / "b",
                    "state_proj.weight has shape (8, 16)")
    extra = state | {"lora_A.weight": torch.zeros(2)}
    assert_one_line(lambda: export_lerobot(ck, extra, tmp_path / "c"), tmp_path / "c",
                    "lora_A.weight is not a tensor of")
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists() and not (tmp_path / "c").exists()


# --- export -------------------------------------------------------------------------------------------


def test_export_keeps_dtypes_metadata_tied_aliases_and_shards(tmp_path: Path) -> None:
    root = make_dir(tmp_path / "ckpt", "smolvla")
    weights = _weights("smolvla")  # two shards and an index, as large checkpoints come
    names = list(weights)
    save_file({k: weights[k] for k in names[:2]}, str(root / "model-00001-of-00002.safetensors"))
    save_file({k: weights[k] for k in names[2:]}, str(root / "model-00002-of-00002.safetensors"))
    (root / "model.safetensors").unlink()
    (root / "model.safetensors.index.json").write_text(json.dumps({"metadata": {"total_size": 0}, "weight_map": {
        k: f"model-0000{1 + (i >= 2)}-of-00002.safetensors" for i, k in enumerate(names)}}))
    ck = check_lerobot(root, "smolvla")
    assert [p.name for p in ck.weights] == ["model-00001-of-00002.safetensors", "model-00002-of-00002.safetensors"]
    state = read_state_dict(ck, dtype=torch.bfloat16)
    assert all(v.dtype == torch.bfloat16 for v in state.values())
    state["alias.weight"] = state["state_proj.weight"]  # a tied alias is not written
    out = export_lerobot(ck, state, tmp_path / "out", metadata={"dvla": "merged LoRA"})
    again = check_lerobot(out, "smolvla")
    assert [p.name for p in again.weights] == [p.name for p in ck.weights]
    back = read_state_dict(again)
    assert list(back) == list(ck.shapes) and all(torch.equal(back[k], state[k]) for k in back)
    with safe_open(str(again.weights[0]), "pt") as f:
        assert f.metadata() == {"dvla": "merged LoRA"}
    index = json.loads((out / "model.safetensors.index.json").read_text())
    assert index["metadata"]["total_size"] == sum(v.numel() * 2 for v in back.values())
    assert (out / "backbone" / "config.json").is_file() and again.vlm_dir == again.path / "backbone"


def test_content_hash_follows_the_files_not_the_place(tmp_path: Path) -> None:
    ck = check_lerobot(make_dir(tmp_path / "a"), "pi0")
    shutil.copytree(tmp_path / "a", tmp_path / "b")
    assert content_hash(check_lerobot(tmp_path / "b", "pi0")) == content_hash(ck)
    save_file(_stats(span_zero=True), str(tmp_path / "b" / UNSTATS_FILE))
    assert content_hash(check_lerobot(tmp_path / "b", "pi0")) != content_hash(ck)
    (tmp_path / "b" / "tokenizer" / "tokenizer.json").write_text(TOKENIZER_JSON.replace("UNK", "unk"))
    assert len(content_hash(check_lerobot(tmp_path / "b", "pi0"))) == 32


# --- openpi and base layouts --------------------------------------------------------------------------


def test_openpi_layout(tmp_path: Path) -> None:
    root = make_openpi_dir(tmp_path / "openpi")
    tok = make_dir(tmp_path / "tok") / "tokenizer"
    ck = check_lerobot(root, "pi0", tokenizer=tok)
    assert (ck.layout, ck.family, ck.key_prefix, ck.preprocessor) == ("openpi", "pi0", "", None)
    assert (ck.state_dim, ck.action_dim, ck.chunk_size, ck.n_action_steps, ck.tokenizer_max_length) == (
        STATE_DIM, ACTION_DIM, 10, 10, 48)
    assert ck.norm_modes["STATE"] == ck.norm_modes["ACTION"] == "MEAN_STD" and ck.norm_eps == 1e-6
    assert ck.processor_files == (root / "assets" / "trossen" / "norm_stats.json",)
    assert ck.cameras[0] == "observation.images.base_0_rgb" and ck.tokenizer_dir == tok
    state = torch.tensor([[0.3, -1.0, 2.0, 0.0]])
    mean, std = (torch.tensor(_stats()[f"{STATE_KEY}.{s}"]) for s in ("mean", "std"))
    assert torch.allclose(Normalizer(ck).normalize_state(state), (state - mean) / (std + 1e-6))
    assert_one_line(lambda: check_lerobot(root, "pi05", tokenizer=tok), root, "is a 'pi0' checkpoint (openpi layout")
    out = export_lerobot(ck, read_state_dict(ck), tmp_path / "export")  # stays an openpi directory
    assert check_lerobot(out, "pi0", tokenizer=tok).layout == "openpi"
    assert (out / "assets" / "trossen" / "norm_stats.json").read_bytes() == ck.processor_files[0].read_bytes()
    assert (out / "tokenizer" / "tokenizer.json").is_file()  # the tokenizer given travels with the export


def test_openpi_pi05_is_told_by_its_weights(tmp_path: Path) -> None:
    ck = check_lerobot(make_openpi_dir(tmp_path / "openpi", "pi05"), "pi05", need_tokenizer=False)
    assert (ck.family, ck.tokenizer_max_length, ck.norm_modes["ACTION"]) == ("pi05", 200, "QUANTILES")
    assert ck.tokenizer_dir is None


def test_base_checkpoint_normalises_nothing(tmp_path: Path) -> None:
    ck = check_lerobot(make_dir(tmp_path / "base", base=True), "pi0")
    assert ck.stats == {}
    norm = Normalizer(ck)
    assert norm.identity and norm.missing_stats == (STATE_KEY, ACTION_KEY)
    state = torch.randn(2, 6)  # any width up to max_state_dim passes unnormalised
    assert torch.equal(norm.normalize_state(state), state)
    actions = torch.randn(2, 10, 32)
    assert torch.equal(norm.unnormalize_actions(actions), actions[..., :ACTION_DIM])


# --- processing --------------------------------------------------------------------------------------


SPANS = {"MIN_MAX": ("min", "max"), "QUANTILES": ("q01", "q99"), "QUANTILE10": ("q10", "q90")}


@pytest.mark.parametrize("mode", ["MEAN_STD", *SPANS])
def test_normalisation_modes(tmp_path: Path, mode: str) -> None:
    ck = check_lerobot(make_dir(tmp_path / "ckpt", mode=mode, span_zero=True), "pi0")
    norm = Normalizer(ck)
    assert not norm.identity and norm.missing_stats == ()
    s = {k.split(".")[-1]: torch.tensor(v) for k, v in _stats(span_zero=True).items() if k.startswith(STATE_KEY)}
    x = torch.tensor([[0.3, -1.0, 2.0, 0.25], [1.0, 0.0, -0.5, 3.0]])
    low, high = SPANS.get(mode, (None, None))
    if mode == "MEAN_STD":
        expected = (x - s["mean"]) / (s["std"] + 1e-8)
    else:  # a zero span (dim 0) divides by eps instead
        span = torch.where(s[high] == s[low], torch.tensor(1e-8), s[high] - s[low])
        expected = 2 * (x - s[low]) / span - 1
    assert torch.allclose(norm.normalize_state(x), expected)
    actions = torch.randn(2, 5, ACTION_DIM)
    back = norm.normalize_actions(norm.unnormalize_actions(pad_to(actions, 32)))  # the padding is cut first
    keep = slice(0 if mode == "MEAN_STD" else 1, None)  # a constant dim cannot be recovered
    assert torch.allclose(back[..., keep], actions[..., keep], atol=1e-5)
    with pytest.raises(ValueError, match="observation.state has 6 dims, the checkpoint takes 4"):
        norm.normalize_state(torch.zeros(1, 6))


def test_resize_with_pad() -> None:
    img = torch.arange(2 * 4, dtype=torch.float32).reshape(1, 1, 2, 4) / 8
    centered = resize_with_pad(img, 4, 4)
    assert torch.equal(centered[0, 0, 1:3], img[0, 0]) and centered[0, 0, [0, 3]].abs().sum() == 0
    top_left = resize_with_pad(img, 4, 4, centered=False)
    assert torch.equal(top_left[0, 0, 2:], img[0, 0]) and top_left[0, 0, :2].abs().sum() == 0
    assert resize_with_pad(img, 2, 4) is img
    half = resize_with_pad(torch.full((2, 3, 8, 16), 200, dtype=torch.uint8), 8, 8)
    assert half.dtype == torch.uint8 and half.shape == (2, 3, 8, 8)
    assert (half[:, :, 2:6] == 200).all() and (half[:, :, :2] == 0).all() and (half[:, :, 6:] == 0).all()
    assert resize_with_pad(torch.full((1, 1, 4, 4), 1.0), 2, 2).max() == 1.0  # float clamped to [0, 1]


@pytest.mark.parametrize("family", ["pi0", "smolvla"])
def test_model_images(tmp_path: Path, family: str) -> None:
    ck = check_lerobot(make_dir(tmp_path / "ckpt", family), family)
    h, w = ck.image_size
    wrist = torch.full((2, h // 2, w, 3), 255, dtype=torch.uint8)  # channels last, half height
    images, masks = model_images({CAMERAS[1]: wrist}, ck)
    assert images[0].shape == (2, 3, h, w) and masks[0].tolist() == [True, True]
    rows = images[0][0, 0, :, 0]
    assert rows.max() == 1.0 and rows.min() == -1.0  # padding is black: -1
    if family == "pi0":  # the missing camera follows, all -1 and masked out
        assert len(images) == 2 and masks[1].tolist() == [False, False] and (images[1] == -1).all()
    else:  # smolvla adds missing cameras only up to config empty_cameras (0 here)
        assert len(images) == 1
    with pytest.raises(ValueError, match="cameras \\['observation.images.left'\\] given"):
        model_images({"observation.images.left": wrist}, ck)
