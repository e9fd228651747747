"""tiny-vla's frozen, pretrained perception (``policy_kwargs.percept``): the file format and its
errors, that it learns to place an object in a picture, and that inside tiny-vla it is read but
never trained nor replicated."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest
import torch

from benchmarks.learn_vla import pretrain_percept
from dvla.learn.envs import ArraySpec
from dvla.learn.policies import make_policy
from dvla.learn.vla.percept import Percept, load_percept, save_percept
from dvla.replication import replicated_tensors

SPEC = {"rgb": ArraySpec((32, 32, 3), "uint8"), "proprio": ArraySpec((6,), "float32")}


def squares(n: int, seed: int = 0, size: int = 24) -> dict[str, np.ndarray]:
    """Pictures of one white 4 px square on a noisy grey field, labelled with its centre (px)."""
    rng = np.random.default_rng(seed)
    rgb = rng.integers(60, 100, (n, size, size, 3)).astype(np.uint8)
    corner = rng.integers(0, size - 4, (n, 2))
    for img, (y, x) in zip(rgb, corner):
        img[y:y + 4, x:x + 4] = 255
    labels = (corner + 2).astype(np.float32)[:, ::-1].copy()  # x, y of the centre
    return {"rgb": rgb, "labels": labels, "label_names": np.array(["x", "y"])}


def test_pretraining_learns_where_the_object_is(tmp_path):
    torch.manual_seed(0)
    scenes = squares(500)
    out = tmp_path / "p.safetensors"
    doc = pretrain_percept(scenes, out, epochs=6, batch=32, lr=3e-3, progress=lambda _m: None)
    first, last = doc["epochs"][0]["held_out_rms"], doc["epochs"][-1]["held_out_rms"]
    spread = float(scenes["labels"].std(0).mean())  # ~6 px: what guessing the mean scores
    assert max(last.values()) < 0.25 * spread, (first, last)
    net = load_percept(out)
    assert net.labels == ("x", "y")
    test = squares(64, seed=1)
    with torch.no_grad():
        err = net.estimate(torch.from_numpy(test["rgb"])) - torch.from_numpy(test["labels"])
    assert err.pow(2).mean().sqrt().item() < 0.25 * spread  # fresh pictures, as well as held-out ones


def test_labelled_demonstrations_train_it_too_and_are_what_it_is_measured_on(tmp_path):
    scenes = squares(300)
    demos = {**squares(200, seed=2), "episode": np.repeat(np.arange(20), 10)}
    doc = pretrain_percept(scenes, tmp_path / "p.safetensors", epochs=1, batch=32, demos=demos,
                           progress=lambda _m: None)
    # every 10th of the 20 episodes held out (2 x 10 pictures); the rest and every scene trained on
    assert doc["held_out_from"] == "demos" and doc["held_out_pictures"] == 20 and doc["train_pictures"] == 480
    unlabelled = {k: v for k, v in demos.items() if k != "labels"}
    with pytest.raises(ValueError, match="carry no labels"):
        pretrain_percept(scenes, tmp_path / "q.safetensors", epochs=1, demos=unlabelled, progress=lambda _m: None)
    with pytest.raises(ValueError, match="held_out"):
        pretrain_percept(scenes, tmp_path / "q.safetensors", epochs=1, held_out=0.0, progress=lambda _m: None)


def test_round_trip_and_errors_naming_the_file(tmp_path):
    torch.manual_seed(0)
    net = Percept(3, keypoints=4, channels=8, labels=("a", "b", "c"))
    net.sd.fill_(2.0)
    path = tmp_path / "p.safetensors"
    save_percept(net, path)
    back = load_percept(path)
    img = torch.randint(0, 256, (2, 16, 16, 3), dtype=torch.uint8)
    assert torch.equal(back(img), net(img)) and back.labels == ("a", "b", "c")
    with pytest.raises(FileNotFoundError, match="nope.safetensors"):
        load_percept(tmp_path / "nope.safetensors")
    junk = tmp_path / "junk.safetensors"
    junk.write_bytes(b"not a safetensors file")
    with pytest.raises(ValueError, match="junk.safetensors: not a safetensors"):
        load_percept(junk)
    from safetensors.torch import save_file

    bare = tmp_path / "bare.safetensors"
    save_file({k: v.contiguous() for k, v in net.state_dict().items()}, str(bare))  # no metadata
    with pytest.raises(ValueError, match="bare.safetensors: metadata needs"):
        load_percept(bare)
    bad = tmp_path / "nan.safetensors"
    net.head[0].weight.data[0, 0] = float("nan")
    save_percept(net, bad)
    with pytest.raises(ValueError, match="nan.safetensors: non-finite values in head.0.weight"):
        load_percept(bad)
    wrong = tmp_path / "wrong.safetensors"
    header = json.dumps({"__metadata__": {"outputs": "5", "keypoints": "4", "channels": "8"}}).encode()
    wrong.write_bytes(struct.pack("<Q", len(header)) + header)
    with pytest.raises(ValueError, match="wrong.safetensors: tensors do not match"):
        load_percept(wrong)


def test_tiny_vla_reads_the_percept_frozen_and_does_not_replicate_it(tmp_path):
    torch.manual_seed(0)
    path = tmp_path / "p.safetensors"
    save_percept(Percept(4, keypoints=4, channels=8), path)
    policy = make_policy("tiny-vla", SPEC, 2, percept=str(path))
    plain = make_policy("tiny-vla", SPEC, 2)
    frozen = {n for n, p in policy.named_parameters() if not p.requires_grad}
    assert frozen and all(n.startswith("percept.") for n in frozen)
    # the estimates join the proprioception's token: its projection reads 6 + 4 inputs
    assert policy.proprio_in.weight.shape[1] == 10 and plain.proprio_in.weight.shape[1] == 6
    sent = replicated_tensors(policy)
    assert not frozen & set(sent) and set(sent) == set(replicated_tensors(plain))
    g = torch.Generator().manual_seed(1)
    obs = {"rgb": torch.randint(0, 256, (4, 32, 32, 3), generator=g).to(torch.uint8), "proprio": torch.randn(4, 6)}
    logprob, _entropy, value = policy.evaluate(obs, torch.zeros(4, 2))
    (logprob.sum() + value.sum()).backward()
    assert all(p.grad is None for n, p in policy.named_parameters() if n in frozen)
    assert policy.proprio_in.weight.grad[:, 6:].abs().sum() > 0  # the estimates' columns learn
    # the estimates reach the readouts: zeroing their columns of the projection changes the value
    before = policy.value(obs)
    with torch.no_grad():
        policy.proprio_in.weight[:, 6:] = 0
    assert not torch.allclose(before, policy.value(obs))


def test_a_perception_file_is_checked_before_anything_starts(tmp_path):
    """tiny-vla's policy_kwargs.percept: a missing file, a file that is not a perception, or a
    value that is not a path is one problem line naming the key and the path; a real file passes."""
    from dvla.orchestrator.topology import TopologyError, parse_topology
    from tests.unit.test_topology import MINIMAL, _problems

    good = tmp_path / "p.safetensors"
    save_percept(Percept(4, keypoints=4, channels=8), good)
    junk = tmp_path / "junk.safetensors"
    junk.write_bytes(b"\x10\x00\x00\x00\x00\x00\x00\x00{\"a\": 1}        ")
    base = MINIMAL + "task:\n  obs_mode: rgb\n  policy: tiny-vla\n"
    cases = {str(tmp_path / "nope.safetensors"): "No such file", str(junk): "not a perception file"}
    for path, what in cases.items():
        problems = _problems(base + f"  policy_kwargs: {{percept: {path}}}\n")
        assert len(problems) == 1 and problems[0].path == "task.policy_kwargs.percept", (path, problems)
        assert path in problems[0].message and what in problems[0].message and "\n" not in problems[0].message
    (problem,) = _problems(base + "  policy_kwargs: {percept: 3}\n")
    assert problem.path == "task.policy_kwargs.percept" and "got 3" in problem.message
    assert parse_topology(base + f"  policy_kwargs: {{percept: {good}}}\n", "t.yaml").task.policy_kwargs["percept"] == str(good)
    with pytest.raises(TopologyError, match="policy_kwargs.percept"):
        parse_topology(base + f"  policy_kwargs: {{percept: {junk}}}\n", "t.yaml")
