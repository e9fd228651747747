"""OpenVLA and OpenVLA-OFT as dvla policies (dvla/learn/vla/openvla_policy.py) on the tiny
reference checkpoints: dvla observations -> upstream's actions, sample/evaluate log-probs agree
for the same weights, LoRA replicates adapters and heads only, export round trips."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from dvla.learn.policies import make_policy, policy_base_hash
from dvla.learn.spec import ArraySpec
from dvla.learn.vla.checkpoint import CheckpointError
from dvla.replication import replicated_tensors
from tests.references.conftest import oft_reference_root

DIRS = {"openvla": "openvla-tiny", "openvla-oft": "openvla-oft-tiny"}


@pytest.fixture(autouse=True)
def _one_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _reference(family: str) -> tuple[Path, dict, dict]:
    from safetensors.torch import load_file

    root = oft_reference_root()
    name = "openvla" if family == "openvla" else "oft"
    ref = load_file(str(root / "reference" / f"{name}_reference.safetensors"))
    doc = json.loads((root / "reference" / f"{name}_reference.json").read_text())
    return root / DIRS[family], ref, doc


def _setup(family: str, **kwargs):
    path, ref, doc = _reference(family)
    cams = 1 if family == "openvla" else 2
    spec = {"rgb": ArraySpec((224, 224, 3 * cams), "uint8"), "proprio": ArraySpec((8,), "float32"),
            "tokens": ArraySpec((48,), "int32", vocab=32064)}
    act = kwargs.pop("act_dim", 7 if family == "openvla" else 7 * 8)
    policy = make_policy(family, spec, act, checkpoint=str(path), **kwargs)
    from dvla.learn.vla.tokenizer import tokenize_instruction

    images = [ref["image_primary_uint8"]] + ([ref["image_wrist_uint8"]] if cams == 2 else [])
    tokens = tokenize_instruction(policy.tokenizer, doc["instruction"], 48)
    obs = {"rgb": torch.cat(images, -1)[None].repeat(2, 1, 1, 1),
           "proprio": (ref["proprio_raw"].float() if "proprio_raw" in ref else torch.zeros(8))[None].repeat(2, 1),
           "tokens": torch.from_numpy(np.stack([tokens, tokens]))}
    return policy, ref, obs


def test_openvla_acts_as_upstream_greedy_and_its_logprobs_agree() -> None:
    policy, ref, obs = _setup("openvla")
    action, logprob, extras = policy.sample(obs, deterministic=True)
    assert torch.equal(extras["action_tokens"][0].long(), ref["generated_action_token_ids"])
    torch.testing.assert_close(action[0].double(), ref["actions"], atol=1e-5, rtol=0)
    g = torch.Generator().manual_seed(0)
    action, logprob, extras = policy.sample(obs, generator=g)
    lp, entropy, value = policy.evaluate(obs, action, extras)
    torch.testing.assert_close(lp, logprob, atol=1e-4, rtol=0)
    assert value.shape == (2,) and torch.isfinite(entropy).all()


def test_oft_mean_is_upstreams_chunk_and_its_logprobs_agree() -> None:
    policy, ref, obs = _setup("openvla-oft", act_dim=7 * 4)
    torch.testing.assert_close(policy.predict_chunk(obs)[0].double(), ref["actions"], atol=1e-4, rtol=0)
    det, _, _ = policy.sample(obs, deterministic=True)
    torch.testing.assert_close(det[0].double(), ref["actions"][:4].reshape(-1), atol=1e-4, rtol=0)
    action, logprob, extras = policy.sample(obs, generator=torch.Generator().manual_seed(1))
    assert extras["normalized"].shape == (2, 4, 7)
    lp, entropy, value = policy.evaluate(obs, action, extras)
    torch.testing.assert_close(lp, logprob, atol=1e-4, rtol=0)


@pytest.mark.parametrize("family", list(DIRS))
def test_lora_replicates_adapters_and_heads_only_and_export_round_trips(family: str, tmp_path: Path) -> None:
    from dvla.learn.vla.openvla_format import check_openvla, export_openvla, read_state_dict

    policy, _, obs = _setup(family, lora={"r": 4})
    replicated = replicated_tensors(policy)
    assert all(".lora_" in k or k.startswith(("value_head.", "log_std")) for k in replicated), sorted(replicated)[:5]
    assert sum(t.numel() for t in replicated.values()) <= 0.05 * sum(p.numel() for p in policy.model.parameters())
    assert policy_base_hash(policy)
    action, logprob, extras = policy.sample(obs, generator=torch.Generator().manual_seed(2))
    opt = torch.optim.Adam([p for p in policy.parameters() if p.requires_grad], lr=1e-2)
    lp, _, _ = policy.evaluate(obs, action, extras)
    (-lp.mean()).backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for n, p in policy.named_parameters() if "lora_B" in n)
    opt.step()
    # a fresh policy's adapters are zero (peft's B = 0): its export is the checkpoint, byte for byte
    fresh, _, _ = _setup(family, lora={"r": 4})
    out = export_openvla(fresh.ck, fresh.base_state_dict(), tmp_path / "same")
    original, exported = read_state_dict(fresh.ck), read_state_dict(check_openvla(str(out), family))
    assert list(exported) == list(original) and all(torch.equal(exported[k], original[k]) for k in original)
    again = make_policy(family, {k: v for k, v in _spec(family).items()}, fresh.act_dim, checkpoint=str(out))
    a1, _, _ = again.sample(obs, deterministic=True)
    a2, _, _ = fresh.sample(obs, deterministic=True)
    assert torch.equal(a1, a2)


def _spec(family: str) -> dict:
    cams = 1 if family == "openvla" else 2
    return {"rgb": ArraySpec((224, 224, 3 * cams), "uint8"), "proprio": ArraySpec((8,), "float32"),
            "tokens": ArraySpec((48,), "int32", vocab=32064)}


def test_wrong_family_action_size_and_dataset_are_one_line() -> None:
    root = oft_reference_root()
    with pytest.raises(CheckpointError) as err:
        make_policy("openvla-oft", _spec("openvla-oft"), 56, checkpoint=str(root / "openvla-tiny"))
    assert str(root / "openvla-tiny") in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(ValueError, match="one action of 7 dims"):
        make_policy("openvla", _spec("openvla"), 14, checkpoint=str(root / "openvla-tiny"))
    with pytest.raises(CheckpointError, match="no_such_dataset") as err:
        make_policy("openvla", _spec("openvla"), 7, checkpoint=str(root / "openvla-tiny"), dataset="no_such_dataset")
    assert "\n" not in str(err.value)


def test_dvla_convert_writes_the_heads_once_as_safetensors(tmp_path: Path) -> None:
    import shutil
    import subprocess
    import sys

    from dvla.learn.vla.openvla_format import check_openvla, read_oft_components

    src = oft_reference_root() / "openvla-oft-tiny"
    d = tmp_path / "oft"
    shutil.copytree(src, d)
    run = lambda *a: subprocess.run([sys.executable, "-m", "dvla", "convert", *a], capture_output=True, text=True,  # noqa: E731
                                    timeout=120, cwd=Path(__file__).resolve().parents[2])
    first, second, bad = run(str(d)), run(str(d)), run(str(tmp_path / "nope"))
    assert first.returncode == 0 and first.stdout.count("wrote ") == 2, first.stdout + first.stderr
    assert second.returncode == 0 and "nothing to convert" in second.stdout
    assert bad.returncode == 2 and "does not exist" in bad.stderr and "Traceback" not in bad.stderr
    converted = check_openvla(str(d), "openvla-oft")
    assert all(p.suffix == ".safetensors" for p in converted.components.values())
    before = read_oft_components(check_openvla(str(src), "openvla-oft"))
    after = read_oft_components(converted)
    assert all(torch.equal(before[c][k], after[c][k]) for c in before for k in before[c])
