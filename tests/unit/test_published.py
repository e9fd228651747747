"""The LeRobot flow families as dvla policies (dvla/learn/vla/published.py), on the reference
checkpoints: dvla observations -> LeRobot's un-normalised chunk, sample/evaluate agree for the
same weights, LoRA trains and replicates only adapters and heads, export round trips."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from dvla.learn.policies import make_policy, policy_base_hash
from dvla.learn.spec import ArraySpec
from dvla.learn.vla.checkpoint import CheckpointError
from dvla.replication import replicated_tensors
from tests.references.conftest import load_reference, reference_dir

FAMILIES = ("pi0", "pi05", "smolvla")
TASKS = ("pick up the red block and put it in the bowl", "open the top drawer")


def _obs_spec(n_cams: int, size: int, n_state: int, vocab: int, length: int = 24) -> dict:
    return {"rgb": ArraySpec((size, size, 3 * n_cams), "uint8"), "proprio": ArraySpec((n_state,), "float32"),
            "tokens": ArraySpec((length,), "int32", vocab=vocab)}


def _reference_obs(family: str, policy) -> dict:
    """The reference's raw inputs as dvla observations: cameras side by side on the channel axis,
    the raw state as proprio, the tasks in ids of the checkpoint's tokenizer (as the env makes them)."""
    from dvla.learn.vla.tokenizer import tokenize_instruction

    ref = load_reference(family)
    cams = [k for k in ref if k.startswith("input.observation.images.")]
    order = [f"input.{name}" for name in policy.ck.cameras]
    assert sorted(order) == sorted(cams)
    rgb = torch.cat([ref[k].permute(0, 2, 3, 1) for k in order], -1).contiguous()
    tokens = np.stack([tokenize_instruction(policy.tokenizer, t, 24) for t in TASKS])
    return {"rgb": rgb, "proprio": ref["input.observation.state"], "tokens": torch.from_numpy(tokens)}


def _policy(family: str, **kwargs):
    d = reference_dir(family)
    ck_cfg = json.loads((d / "config.json").read_text())
    feats = ck_cfg["input_features"]
    cams = [k for k, v in feats.items() if v["type"] == "VISUAL"]
    size = feats[cams[0]]["shape"][-1]
    spec = _obs_spec(len(cams), size, feats["observation.state"]["shape"][0], vocab=512)
    act = ck_cfg["output_features"]["action"]["shape"][0]
    return make_policy(family, spec, kwargs.pop("act_dim", act * 2), checkpoint=str(d), **kwargs)


@pytest.mark.parametrize("family", FAMILIES)
def test_dvla_observations_give_lerobots_actions(family: str) -> None:
    """Raw images, state and task text through dvla's observation path (the env's tokens, the
    policy's prompt, resize, normalisation) and the recorded noise: LeRobot's un-normalised chunk."""
    torch.manual_seed(0)
    policy = _policy(family)
    ref = load_reference(family)
    got = policy.predict_chunk(_reference_obs(family, policy), ref["noise"])
    torch.testing.assert_close(got, ref["output.actions"], atol=1e-4, rtol=0)


@pytest.mark.parametrize("family", FAMILIES)
def test_learner_logprobs_equal_the_rollouts_for_the_same_weights(family: str) -> None:
    policy = _policy(family, lora={"r": 4}, act_dim=7 * 3)
    obs = _reference_obs(family, policy)
    g = torch.Generator().manual_seed(3)
    action, logprob, extras = policy.sample(obs, generator=g)
    assert action.shape == (2, 21) and logprob.shape == (2,) and torch.isfinite(logprob).all()
    assert extras["chain"].shape == (2, policy.steps, 3, 7) and extras["x0"].shape == (2, 50, 32)
    lp, entropy, value = policy.evaluate(obs, action, extras)
    torch.testing.assert_close(lp, logprob, atol=1e-4, rtol=0)
    assert torch.isfinite(entropy).all() and value.shape == (2,)
    # the executed chain's last link is the action (normalised), so the action is what the log-prob is of
    torch.testing.assert_close(policy._to_action(extras["chain"][:, -1]), action)
    # deterministic: no noise anywhere, the same action twice
    a1, _, _ = policy.sample(obs, deterministic=True)
    a2, _, _ = policy.sample(obs, deterministic=True)
    assert torch.equal(a1, a2)


@pytest.mark.parametrize("family", FAMILIES)
def test_lora_replicates_adapters_and_heads_only_and_learns(family: str) -> None:
    policy = _policy(family, lora={"r": 4}, act_dim=7 * 2)
    model_values = sum(p.numel() for p in policy.model.parameters())
    replicated = replicated_tensors(policy)
    assert all(".lora_" in k or k.startswith(("noise_head.", "value_head.")) for k in replicated), sorted(replicated)[:5]
    assert sum(t.numel() for t in replicated.values()) <= 0.05 * model_values
    assert policy_base_hash(policy)
    obs = _reference_obs(family, policy)
    action, logprob, extras = policy.sample(obs, generator=torch.Generator().manual_seed(1))
    opt = torch.optim.Adam([p for p in policy.parameters() if p.requires_grad], lr=1e-2)
    for _ in range(3):
        lp, _, _ = policy.evaluate(obs, action, extras)
        opt.zero_grad()
        (-lp.mean()).backward()
        assert any(p.grad is not None and p.grad.abs().sum() > 0 for n, p in policy.named_parameters()
                   if "lora_B" in n), "no gradient reaches the adapters"
        opt.step()
    assert policy.evaluate(obs, action, extras)[0].mean() > logprob.mean()


@pytest.mark.parametrize("family", FAMILIES)
def test_export_round_trip(family: str, tmp_path: Path) -> None:
    """load -> export without training -> byte-equal tensors and identical actions; after a LoRA
    change, the merged export acts as the adapted policy does."""
    from dvla.learn.vla.lerobot_format import check_lerobot, export_lerobot, read_state_dict

    policy = _policy(family, lora={"r": 4})
    ref = load_reference(family)
    obs = _reference_obs(family, policy)
    out = export_lerobot(policy.ck, policy.base_state_dict(), tmp_path / "same")
    original = read_state_dict(policy.ck)
    exported = read_state_dict(check_lerobot(str(out), family))
    assert list(exported) == list(original)
    assert all(exported[k].dtype == original[k].dtype and torch.equal(exported[k], original[k]) for k in original)
    again = _reload(policy, out)
    assert torch.equal(again.predict_chunk(obs, ref["noise"]), policy.predict_chunk(obs, ref["noise"]))

    with torch.no_grad():  # a trained adapter: the merged export acts as the adapted policy
        for name, p in policy.named_parameters():
            if "lora_B" in name:
                p.normal_(0, 0.05)
    adapted = policy.predict_chunk(obs, ref["noise"])
    out2 = export_lerobot(policy.ck, policy.base_state_dict(), tmp_path / "merged")
    merged = _reload(policy, out2)
    torch.testing.assert_close(merged.predict_chunk(obs, ref["noise"]), adapted, atol=1e-4, rtol=0)
    assert not torch.allclose(adapted, again.predict_chunk(obs, ref["noise"]), atol=1e-3)


def _reload(policy, path: Path):
    """The policy's family from ``path``; SigLIP's head count of the tiny pi checkpoints, which
    their tensor shapes cannot tell, given as policy_kwargs (an export copies no architecture.json)."""
    extra = {} if policy.family == "smolvla" else {"vision_heads": 4}
    return make_policy(policy.family, _obs_spec_of(policy), policy.act_dim, checkpoint=str(path), **extra)


def _obs_spec_of(policy) -> dict:
    size = policy.ck.image_size[0]
    return _obs_spec(len(policy.ck.cameras), size, policy.ck.state_dim, vocab=512)


def test_wrong_family_and_wrong_action_size_are_one_line(tmp_path: Path) -> None:
    d = reference_dir("pi0")
    spec = _obs_spec(3, 224, 8, vocab=512)
    with pytest.raises(CheckpointError, match=r"pi0.*'pi0'.*smolvla|smolvla.*pi0") as err:
        make_policy("smolvla", spec, 14, checkpoint=str(d))
    assert "\n" not in str(err.value)
    with pytest.raises(ValueError, match="act_dim 8 is not a multiple of the checkpoint's action dimension 7"):
        make_policy("pi0", spec, 8, checkpoint=str(d))
    broken = tmp_path / "pi0"
    shutil.copytree(d, broken)
    (broken / "model.safetensors").write_bytes((d / "model.safetensors").read_bytes()[:1000])
    with pytest.raises(CheckpointError, match="truncated|corrupt") as err:
        make_policy("pi0", spec, 14, checkpoint=str(broken))
    assert str(broken) in str(err.value) and "\n" not in str(err.value)
