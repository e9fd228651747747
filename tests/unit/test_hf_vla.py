"""The transformers-based VLA policies (vla-tokens, vla-flow) on tiny random checkpoints, CPU."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from dvla.learn.spec import ArraySpec
from dvla.learn.vla.build import save_random_checkpoint, vlm_config
from dvla.learn.vla.checkpoint import CheckpointError, check_checkpoint, content_hash
from dvla.learn.vla.flow import ActionExpert, FlowVLA
from dvla.learn.vla.hf_backbone import tokenize_instruction
from dvla.learn.vla.token_action import TokenActionVLA

ACTION_DIM, CHUNK = 8, 2
ACT_DIM = ACTION_DIM * CHUNK
# two 64 px cameras (resized to the test vision tower's 32 px), Panda proprio, 8 instruction ids
SPEC = {"rgb": ArraySpec((64, 64, 6), "uint8"), "proprio": ArraySpec((18,), "float32"),
        "tokens": ArraySpec((8,), "int32")}
FAMILIES = [("tokens", TokenActionVLA, {}), ("flow", FlowVLA, {"method": "noise"}),
            ("flow", FlowVLA, {"method": "sde"})]
IDS = ["tokens", "flow-noise", "flow-sde"]


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory):
    root = tmp_path_factory.mktemp("hf_vla")
    return {family: save_random_checkpoint(root / family, family, action_dim=ACTION_DIM, max_chunk=4)
            for family in ("tokens", "flow")}


def make(ckpt, family, cls, kw, **more):
    return cls(SPEC, ACT_DIM, checkpoint=str(ckpt[family]), **kw, **more)


def obs_batch(policy, b: int = 3, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    ids = tokenize_instruction(policy.backbone.tokenizer, "push the cube to the red and white target", 8)
    tokens = torch.as_tensor(np.stack([ids] * b))
    tokens[1:, 3:] = policy.backbone.pad_id  # shorter instructions: pads are masked
    return {"rgb": torch.randint(0, 256, (b, 64, 64, 6), generator=g).to(torch.uint8),
            "proprio": torch.randn(b, 18, generator=g), "tokens": tokens}


def replicated_bytes(policy) -> int:
    """Bytes that replicate: floating state-dict entries of trainable parameters + floating buffers."""
    params = dict(policy.named_parameters())
    buffers = {n for n, _ in policy.named_buffers()}
    return sum(t.numel() * t.element_size() for n, t in policy.state_dict().items()
               if t.is_floating_point() and ((n in params and params[n].requires_grad) or n in buffers))


# --- the protocol ----------------------------------------------------------------------------


@pytest.mark.parametrize("family,cls,kw", FAMILIES, ids=IDS)
def test_sample_then_evaluate_match_and_training_moves_only_the_trainable(ckpt, family, cls, kw):
    policy = make(ckpt, family, cls, kw, lora={"r": 4})
    obs = obs_batch(policy)
    action, logprob, extras = policy.sample(obs, generator=torch.Generator().manual_seed(1))
    assert action.shape == (3, ACT_DIM) and action.dtype == logprob.dtype == torch.float32
    assert logprob.shape == (3,) and torch.isfinite(logprob).all()
    assert set(extras) == set(policy.extras_spec)
    for name, spec in policy.extras_spec.items():
        assert extras[name].shape == (3, *spec.shape) and str(extras[name].dtype) == f"torch.{spec.dtype}"
    new_logprob, entropy, value = policy.evaluate(obs, action, extras)
    assert torch.allclose(new_logprob, logprob, atol=1e-4, rtol=0), (new_logprob, logprob)
    assert entropy.dtype == value.dtype == torch.float32 and entropy.shape == value.shape == (3,)
    # minibatches of another composition than the rollout's batch give the same log-probs
    one = policy.evaluate({k: v[1:2] for k, v in obs.items()}, action[1:2], {k: v[1:2] for k, v in extras.items()})
    assert torch.allclose(one[0], logprob[1:2], atol=1e-4, rtol=0)
    _, _, acted_value = policy.act(obs, generator=torch.Generator().manual_seed(1))
    assert torch.allclose(acted_value, policy.value(obs), atol=1e-5)

    # every trainable tensor gets a gradient (DDP needs it); only they move in a step
    (new_logprob.mean() + entropy.mean() + value.square().mean()).backward()
    assert [n for n, p in policy.named_parameters() if p.requires_grad and p.grad is None] == []
    frozen = {n: p.detach().clone() for n, p in policy.named_parameters() if not p.requires_grad}
    trained = {n: p.detach().clone() for n, p in policy.named_parameters() if p.requires_grad}
    assert frozen and any("lora_" in n for n in trained) and any("value_head" in n for n in trained)
    optim = torch.optim.Adam([p for p in policy.parameters() if p.requires_grad], lr=1e-2)
    optim.zero_grad()
    (-policy.evaluate(obs, action, extras)[0].mean()).backward()
    optim.step()
    after, _, _ = policy.evaluate(obs, action, extras)
    assert (after - new_logprob).abs().max() > 1e-4
    assert all(torch.equal(p, frozen[n]) for n, p in policy.named_parameters() if n in frozen)


@pytest.mark.parametrize("family,cls,kw", FAMILIES, ids=IDS)
def test_deterministic_is_reproducible_and_seeds_differ(ckpt, family, cls, kw):
    policy = make(ckpt, family, cls, kw)
    obs = obs_batch(policy, 2)
    a1, lp1, _ = policy.sample(obs, deterministic=True)
    a2, lp2, ex = policy.sample(obs, deterministic=True)
    assert torch.equal(a1, a2) and torch.equal(lp1, lp2) and torch.isfinite(lp1).all()
    assert torch.allclose(policy.evaluate(obs, a1, ex)[0], lp1, atol=1e-4, rtol=0)
    s0 = policy.sample(obs, generator=torch.Generator().manual_seed(0))[0]
    assert torch.equal(s0, policy.sample(obs, generator=torch.Generator().manual_seed(0))[0])
    assert not torch.equal(s0, policy.sample(obs, generator=torch.Generator().manual_seed(1))[0])
    assert not torch.equal(s0, a1)


@pytest.mark.parametrize("family,cls,kw", FAMILIES[:2], ids=IDS[:2])
def test_padding_changes_nothing(ckpt, family, cls, kw):
    short = make(ckpt, family, cls, kw, lora={"r": 4})
    long = cls({**SPEC, "tokens": ArraySpec((13,), "int32")}, ACT_DIM, checkpoint=str(ckpt[family]), lora={"r": 4})
    obs = obs_batch(short)
    padded = {**obs, "tokens": torch.cat([obs["tokens"], torch.full((3, 5), short.backbone.pad_id)], 1)}
    a, lp, _ = short.sample(obs, deterministic=True)
    b, lp_long, _ = long.sample(padded, deterministic=True)
    assert torch.allclose(a, b, atol=1e-5) and torch.allclose(lp, lp_long, atol=1e-4)
    assert torch.allclose(short.value(obs), long.value(padded), atol=1e-5)


@pytest.mark.parametrize("family,cls,kw", FAMILIES[:2], ids=IDS[:2])
def test_lora_replicates_under_five_percent_and_full_finetuning_everything(ckpt, family, cls, kw):
    lora = make(ckpt, family, cls, kw, lora={"r": 4})
    total = sum(p.numel() * p.element_size() for p in lora.parameters())
    assert replicated_bytes(lora) / total <= 0.05
    assert all(not p.requires_grad for n, p in lora.backbone.named_parameters() if "lora_" not in n)
    full = make(ckpt, family, cls, kw)
    # all but SigLIP's final norm, which Llava never reads (frozen, see hf_backbone._never_read)
    assert replicated_bytes(full) / sum(p.numel() * p.element_size() for p in full.parameters()) > 0.99
    assert full.base_hash == ("" if family == "flow" else content_hash(ckpt[family]))


def test_base_hash_follows_the_files(ckpt, tmp_path):
    a = make(ckpt, "tokens", TokenActionVLA, {}, lora={"r": 4})
    b = make(ckpt, "tokens", TokenActionVLA, {}, lora={"r": 4})
    assert a.base_hash == b.base_hash == content_hash(ckpt["tokens"]) and len(a.base_hash) == 32
    assert a.state_dict().keys() == b.state_dict().keys()  # same layout, same seeded adapters
    assert all(torch.equal(x, y) for x, y in zip(a.state_dict().values(), b.state_dict().values()))
    copy = shutil.copytree(ckpt["tokens"], tmp_path / "copy")
    assert content_hash(copy) == a.base_hash
    save_random_checkpoint(copy, "tokens", action_dim=ACTION_DIM, max_chunk=4, seed=1)
    assert make({"tokens": copy}, "tokens", TokenActionVLA, {}, lora={"r": 4}).base_hash != a.base_hash


@pytest.mark.parametrize("family,cls,kw", FAMILIES, ids=IDS)
def test_bfloat16_samples_and_evaluates_in_float32(ckpt, family, cls, kw):
    policy = make(ckpt, family, cls, kw, lora={"r": 4}, dtype="bfloat16")
    # the frozen base is bf16; what trains (adapters, heads) stays float32 for the optimizer
    assert {p.dtype for p in policy.parameters() if not p.requires_grad} == {torch.bfloat16}
    assert {p.dtype for p in policy.parameters() if p.requires_grad} == {torch.float32}
    obs = obs_batch(policy)
    action, logprob, extras = policy.sample(obs, generator=torch.Generator().manual_seed(2))
    new_logprob, entropy, value = policy.evaluate(obs, action, extras)
    for t in (action, logprob, new_logprob, entropy, value):
        assert t.dtype == torch.float32 and torch.isfinite(t).all()
    # bf16 matmuls round to 8 mantissa bits and their result may depend on the batch's shape
    # (evaluate runs the flow expert on B*K rows, sample on B), so the match is looser
    assert torch.allclose(new_logprob, logprob, atol=1e-2, rtol=1e-3)


# --- checkpoints and bad input ---------------------------------------------------------------


def one_line_error(exc_type, fn, *needles):
    with pytest.raises(exc_type) as info:
        fn()
    msg = str(info.value)
    assert "\n" not in msg and all(str(n) in msg for n in needles), msg
    return msg


def broken(ckpt, tmp_path, family="tokens"):
    return shutil.copytree(ckpt[family], tmp_path / "broken")


def test_checkpoint_errors_are_one_line_naming_path_and_problem(ckpt, tmp_path):
    assert check_checkpoint(ckpt["tokens"], "tokens").action_dim == ACTION_DIM
    one_line_error(CheckpointError, lambda: check_checkpoint(tmp_path / "nope", "tokens"), tmp_path / "nope",
                   "does not exist")
    (tmp_path / "file").write_text("x")
    one_line_error(CheckpointError, lambda: check_checkpoint(tmp_path / "file", "tokens"), "not a directory")
    for name, needle in (("config.json", "config.json"), ("model.safetensors", "safetensors"),
                         ("tokenizer.json", "tokenizer"), ("dvla_policy.json", "dvla_policy.json")):
        path = broken(ckpt, tmp_path)
        (path / name).unlink()
        one_line_error(CheckpointError, lambda: TokenActionVLA(SPEC, ACT_DIM, checkpoint=str(path)), path, needle)
        shutil.rmtree(path)
    path = broken(ckpt, tmp_path)
    (path / "dvla_policy.json").write_text("{not json")
    one_line_error(CheckpointError, lambda: check_checkpoint(path, "tokens"), "dvla_policy.json", "not JSON")
    (path / "dvla_policy.json").write_text(json.dumps({"family": "tokens", "action_dim": 8}))
    one_line_error(CheckpointError, lambda: check_checkpoint(path, "tokens"), "missing key", "n_bins")
    settings = json.loads((ckpt["tokens"] / "dvla_policy.json").read_text())
    (path / "dvla_policy.json").write_text(json.dumps({**settings, "n_bins": "many"}))
    one_line_error(CheckpointError, lambda: check_checkpoint(path, "tokens"), "dvla_policy.json", "bad value", "many")
    (path / "model.safetensors.index.json").write_text(json.dumps({"weight_map": {"w": "model-00002.safetensors"}}))
    one_line_error(CheckpointError, lambda: check_checkpoint(path, "tokens"), path, "model-00002.safetensors")


def test_wrong_family_both_ways_and_flow_without_expert(ckpt, tmp_path):
    one_line_error(CheckpointError, lambda: make(ckpt, "flow", TokenActionVLA, {}), ckpt["flow"],
                   "is a 'flow' checkpoint (dvla_policy.json family), policy vla-tokens needs 'tokens'")
    one_line_error(CheckpointError, lambda: FlowVLA(SPEC, ACT_DIM, checkpoint=str(ckpt["tokens"])), ckpt["tokens"],
                   "is a 'tokens' checkpoint", "vla-flow needs 'flow'")
    path = broken(ckpt, tmp_path, "flow")
    (path / "action_expert.safetensors").unlink()
    one_line_error(CheckpointError, lambda: check_checkpoint(path, "flow"), path, "action_expert.safetensors")


def test_corrupt_weights_and_unloadable_models_are_one_line(ckpt, tmp_path):
    path = broken(ckpt, tmp_path)
    weights = path / "model.safetensors"
    data = weights.read_bytes()
    weights.write_bytes(data[: len(data) // 2])
    one_line_error(CheckpointError, lambda: TokenActionVLA(SPEC, ACT_DIM, checkpoint=str(path)), weights, "truncated")
    weights.write_bytes(b"\xff" * 64)
    one_line_error(CheckpointError, lambda: check_checkpoint(path, "tokens"), weights, "corrupt")
    weights.write_bytes(data)
    config = json.loads((path / "config.json").read_text())
    (path / "config.json").write_text(json.dumps({**config, "model_type": "no-such-model"}))
    one_line_error(CheckpointError, lambda: TokenActionVLA(SPEC, ACT_DIM, checkpoint=str(path)), path,
                   "cannot load the model")


def test_bad_policy_arguments(ckpt):
    one_line_error(ValueError, lambda: TokenActionVLA(SPEC, 12, checkpoint=str(ckpt["tokens"])), ckpt["tokens"],
                   "act_dim 12", "action_dim 8")
    one_line_error(ValueError, lambda: FlowVLA(SPEC, 40, checkpoint=str(ckpt["flow"])), ckpt["flow"],
                   "chunk of 5", "max_chunk 4")
    with pytest.raises(TypeError, match="rgb"):
        TokenActionVLA({"proprio": SPEC["proprio"]}, ACT_DIM, checkpoint=str(ckpt["tokens"]))
    one_line_error(ValueError, lambda: make(ckpt, "tokens", TokenActionVLA, {}, lora={"rank": 4}), "lora", "rank")
    one_line_error(ValueError, lambda: make(ckpt, "tokens", TokenActionVLA, {}, lora={"target_modules": ["nope"]}),
                   "policy_kwargs.lora", ckpt["tokens"])
    # targets naming only the LM's MLP adapt the LM; the expert (no such layers) stays frozen
    mlp_only = make(ckpt, "flow", FlowVLA, {}, lora={"r": 2, "target_modules": ["gate_proj", "up_proj"]})
    adapted = [n for n, p in mlp_only.named_parameters() if p.requires_grad and "lora_" in n]
    assert adapted and all("mlp" in n and "expert" not in n for n in adapted)
    one_line_error(ValueError, lambda: make(ckpt, "flow", FlowVLA, {"method": "ode"}), "method", "ode")
    one_line_error(ValueError, lambda: make(ckpt, "tokens", TokenActionVLA, {}, dtype="float16"), "dtype", "float16")
    hashed = {**SPEC, "tokens": ArraySpec((8,), "int32", vocab=4096)}
    one_line_error(ValueError, lambda: TokenActionVLA(hashed, ACT_DIM, checkpoint=str(ckpt["tokens"])),
                   "4095", "checkpoint's tokenizer")


def test_tokenizer_and_action_bounds(ckpt, tmp_path):
    policy = make(ckpt, "tokens", TokenActionVLA, {})
    tok = policy.backbone.tokenizer
    ids = tokenize_instruction(tok, "Push the CUBE, to the zebra!", 10)
    assert ids.dtype == np.int32 and ids[0] == tok.bos_token_id and list(ids[-3:]) == [tok.pad_token_id] * 3
    assert ids[1] == tok.convert_tokens_to_ids("push") and ids[6] == tok.unk_token_id
    # bounds from dvla_policy.json: actions land in [low, high] per robot dimension
    path = broken(ckpt, tmp_path)
    settings = json.loads((path / "dvla_policy.json").read_text())
    settings.update(action_low=[10.0] * ACTION_DIM, action_high=[12.0] * ACTION_DIM)
    (path / "dvla_policy.json").write_text(json.dumps(settings))
    policy = TokenActionVLA(SPEC, ACT_DIM, checkpoint=str(path))
    action, logprob, extras = policy.sample(obs_batch(policy))
    assert (action > 10).all() and (action < 12).all()
    # without extras the bins come back from the action itself
    assert torch.allclose(policy.evaluate(obs_batch(policy), action)[0], logprob, atol=1e-4, rtol=0)


def test_half_billion_sizes_on_the_meta_device():
    from transformers import AutoModelForImageTextToText

    with torch.device("meta"):
        tokens = AutoModelForImageTextToText.from_config(vlm_config("tokens", "0.5b", 300))
        flow = AutoModelForImageTextToText.from_config(vlm_config("flow", "0.5b", 300))
        expert = ActionExpert(1024, 7, 8, width=512, layers=18, heads=8, mlp=2048)
    count = lambda m: sum(p.numel() for p in m.parameters())  # noqa: E731
    assert 0.4e9 < count(tokens) < 0.6e9 and 0.4e9 < count(flow) + count(expert) < 0.6e9


def test_envs_tokenise_instructions_with_the_checkpoints_tokenizer(ckpt):
    """With policy_kwargs.checkpoint set, instructions become that tokenizer's ids (the hashed
    tokenizer otherwise): the ids the policy's embedding reads, per episode's instruction."""
    from transformers import AutoTokenizer

    from dvla.learn.vla.tokenizer import DEFAULT_VOCAB_SIZE, instruction_tokenizer, tokenize

    tok = AutoTokenizer.from_pretrained(str(ckpt["flow"]), local_files_only=True)
    it = instruction_tokenizer({"checkpoint": str(ckpt["flow"])}, 10)
    assert it.vocab == len(tok) and it.pad_id == tok.pad_token_id and it.source.endswith("flow")
    for text in ("push the cube to the red and white target", "put the black bowl on the plate"):
        ids = it.encode(text)
        want = tok(text)["input_ids"]
        assert ids.dtype == np.int32 and ids.shape == (10,)
        assert list(ids[: len(want)]) == want and set(ids[len(want):].tolist()) <= {it.pad_id}
    assert it.encode("pick up the cube").tolist() != it.encode("open the drawer").tolist()
    hashed = instruction_tokenizer({}, 10)
    assert hashed.source == "hashed" and hashed.vocab == DEFAULT_VOCAB_SIZE
    np.testing.assert_array_equal(hashed.encode("push the cube"), tokenize("push the cube", 10))
    # a directory without tokenizer files (e.g. a tiny-vla kwarg named checkpoint) keeps the hashed one
    assert instruction_tokenizer({"checkpoint": "/nonexistent"}, 10).source == "hashed"


@pytest.mark.filterwarnings("ignore:CUDA is not available")  # autocast on "cuda" here, without one
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_forwards_on_cuda_never_use_cudnn_attention(dtype):
    """PyTorch's cuDNN attention failed on PaliGemma's bf16 prefix on an H200 (docs/benchmarks.md,
    "VLA"): the policies' forward context turns it off on CUDA, and only there and only inside."""
    import types

    from dvla.learn.vla.hf_backbone import HFBackbone

    bb = types.SimpleNamespace(dtype=dtype)
    assert torch.backends.cuda.cudnn_sdp_enabled()
    with HFBackbone.forward_context(bb, torch.device("cuda")):  # sets the kernel flags; needs no GPU
        assert not torch.backends.cuda.cudnn_sdp_enabled()
        assert torch.backends.cuda.flash_sdp_enabled() and torch.backends.cuda.mem_efficient_sdp_enabled()
        assert torch.backends.cuda.math_sdp_enabled()
    assert torch.backends.cuda.cudnn_sdp_enabled()
    with HFBackbone.forward_context(bb, torch.device("cpu")):
        assert torch.backends.cuda.cudnn_sdp_enabled()
        assert torch.is_autocast_enabled("cpu") == (dtype == torch.bfloat16)
