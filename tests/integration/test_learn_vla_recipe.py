"""The pieces of `dvla bench learn-vla` (benchmarks/learn_vla.py) at toy size, on real ManiSkill
envs: an expert run's policy replayed on a state env group with an rgb env group of the same task
in lock-step (the recorded observations are exactly what a rollout sees), a tiny-vla cloned from
those episodes and saved as a warm start that `task.init_weights` loads into the RL task's policy.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from benchmarks.learn_vla import (NOISE_STD, PERCEPT_LABELS, clone, demo_tokens, evaluate, first_episodes, load_demos,
                                  observed_as, record_demos, record_scenes)
from dvla.learn import make_policy
from dvla.learn.envs import probe_spec
from dvla.learn.vla.tokenizer import instruction_tokenizer
from dvla.orchestrator.topology import load_topology
from dvla.replication import replicated_tensors
from dvla.roles.checkpoint import CheckpointError, load_init_weights, optimizer_tensors, save_checkpoint

ROOT = Path(__file__).resolve().parents[2]
STEPS = 6  # steps per episode (the time limit: a random expert solves nothing)

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def expert_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A run directory as a finished state run leaves it: its topology and a current checkpoint
    (an untrained MLP: the recording machinery, not the expert's skill, is under test)."""
    run = tmp_path_factory.mktemp("expert")
    text = (ROOT / "topologies" / "tiny.yaml").read_text()
    assert "  chunk_steps: 10\n" in text
    (run / "topology.yaml").write_text(text.replace("  chunk_steps: 10\n", f"  chunk_steps: 10\n  max_episode_steps: {STEPS}\n"))
    task = load_topology(run / "topology.yaml").task
    torch.manual_seed(3)
    obs_spec, act_dim = probe_spec(task)
    policy = make_policy(task.policy, obs_spec, act_dim, **task.policy_kwargs)
    with torch.no_grad():
        for p in policy.parameters():
            p.add_(0.3 * torch.randn_like(p))  # an arm that moves
    opt = torch.optim.Adam(policy.parameters())
    save_checkpoint(run / "checkpoints", policy.state_dict(), optimizer_tensors(opt), 5, 1000, "unchecked")
    return run


@pytest.fixture(scope="module")
def recorded(expert_run: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Any, Path, dict[str, Any]]:
    """(the RL task, its demos file, what record_demos returned): three episodes of the expert."""
    base = load_topology(ROOT / "topologies" / "local-vla-rl.yaml").task
    task = dataclasses.replace(base, image_size=32, max_episode_steps=STEPS)  # the RL task, its observations recorded
    out = tmp_path_factory.mktemp("demos") / "demos.npz"
    meta = record_demos(expert_run, task, out, episodes=3, n_envs=2, solved_only=False, progress=lambda _m: None)
    return task, out, meta


def test_demos_replay_the_expert_with_rendered_observations_and_a_clone_warm_starts_the_vla(
        expert_run: Path, recorded: tuple[Any, Path, dict[str, Any]], tmp_path: Path) -> None:
    task, out, meta = recorded
    with pytest.raises(ValueError, match="task.env is 'PushCube-v1'"):
        observed_as(load_topology(expert_run / "topology.yaml").task, dataclasses.replace(task, env="PickCube-v1"))
    demos = load_demos(out)
    assert json.loads(Path(f"{out}.json").read_text()) == json.loads(json.dumps(meta))
    n = len(demos["action"])
    assert meta["episodes"] == 3 and meta["transitions"] == n == 3 * STEPS
    assert demos["rgb"].shape == (n, 32, 32, 3) and demos["rgb"].dtype == np.uint8 and demos["rgb"].std() > 0
    assert demos["proprio"].shape == (n, 25) and demos["action"].shape == (n, 8)
    # PushCube: the goal's and cube's xy from the simulator, a perception's labels; the goal stays put
    assert tuple(demos["label_names"]) == PERCEPT_LABELS and demos["labels"].shape == (n, 4)
    assert np.abs(demos["labels"]).max() < 0.4
    for e in range(3):
        goal = demos["labels"][demos["episode"] == e, :2]
        assert np.ptp(goal, axis=0).max() < 1e-6 and np.linalg.norm(goal[0] - demos["labels"][demos["episode"] == e][0, 2:]) > 0.05
    assert np.abs(demos["action"]).max() <= 1.0 and np.abs(demos["action"]).max() > 0.05  # clipped, and moving
    assert sorted(set(demos["episode"].tolist())) == [0, 1, 2] and np.all(np.diff(demos["episode"]) >= 0)
    assert demos["reward"].shape == (n,) and np.isfinite(demos["reward"]).all() and demos["reward"].std() > 0
    assert demos["terminated"].shape == (n,) and not demos["terminated"].any()  # time limits, no successes
    # every episode kept (failures too), and the expert's success is what it solved, not what was kept
    assert meta["solved_only"] is False and meta["episodes_played"] >= 3 and meta["expert_success"] == 0.0
    # the arm moves within an episode as the actions say (consecutive joint states differ)
    first = demos["proprio"][demos["episode"] == 0]
    assert np.abs(np.diff(first[:, :9], axis=0)).max() > 1e-3

    from dvla.learn.vla.instructions import instruction_for

    want = instruction_tokenizer(task.policy_kwargs, task.instruction_tokens, task.policy).encode(instruction_for(task.env))
    assert (demos["tokens"] == want).all()
    # the instruction's text is kept with every step, so another policy's tokenizer can read it
    assert [str(t) for t in demos["instruction_text"]] == [instruction_for(task.env)]
    assert demos["instruction_id"].shape == (n,) and not demos["instruction_id"].any()
    assert (demo_tokens(task, demos) == demos["tokens"]).all()
    assert len(first_episodes(demos, 2)["action"]) == 2 * STEPS
    with pytest.raises(ValueError, match="4 episodes asked"):
        first_episodes(demos, 4)

    warm = tmp_path / "warm.safetensors"
    res = clone(task, demos, warm, epochs=6, batch=8, lr=3e-3, progress=lambda _m: None)
    assert res["losses"][-1] < res["losses"][0], res["losses"]  # the expert's actions grew likelier
    assert res["value_losses"][-1] < res["value_losses"][0], res["value_losses"]  # and the critic its returns
    cloned = res["policy"]
    obs_spec, act_dim = probe_spec(task)
    fresh = make_policy(task.policy, obs_spec, act_dim, **task.policy_kwargs)
    load_init_weights(warm, fresh)
    for k, v in replicated_tensors(cloned).items():
        assert torch.equal(replicated_tensors(fresh)[k], v), k
    assert torch.allclose(fresh.log_std.exp(), torch.full_like(fresh.log_std, NOISE_STD))  # the noise it acts with
    got = evaluate(task, warm, episodes=2, n_envs=2)
    assert got["episodes"] == 2 and 0.0 <= got["success_once"] <= 1.0


def test_a_hugging_face_vla_is_cloned_from_the_same_demos_through_its_own_tokenizer(
        recorded: tuple[Any, Path, dict[str, Any]], tmp_path: Path) -> None:
    """Demos recorded for tiny-vla clone a vla-tokens checkpoint: the recorded instruction text is
    tokenised by the checkpoint's own tokenizer (other ids, another length), the images are the
    task's size (the checkpoint's vision tower reads 32 px), and images of another size are refused."""
    from dvla.learn.vla.build import main as build
    from dvla.learn.vla.instructions import instruction_for

    task, out, _meta = recorded
    assert build([str(tmp_path / "ckpt"), "--family", "tokens"]) == 0
    hf = dataclasses.replace(task, policy="vla-tokens", instruction_tokens=12,
                             policy_kwargs={"checkpoint": str(tmp_path / "ckpt"), "lora": {"r": 4}})
    demos = load_demos(out)
    n = len(demos["action"])
    tokens = demo_tokens(hf, demos)
    want = instruction_tokenizer(hf.policy_kwargs, 12, "vla-tokens").encode(instruction_for(task.env))
    assert tokens.shape == (n, 12) and (tokens == want).all()
    assert not np.array_equal(tokens[:, :12], demos["tokens"][:, :12])  # not the hashed ids the demos hold
    # a file recorded before the text was kept: the task's instruction (here the env's default)
    older = {k: v for k, v in demos.items() if k not in ("instruction_text", "instruction_id")}
    assert (demo_tokens(hf, older) == tokens).all()

    res = clone(hf, demos, tmp_path / "warm.safetensors", epochs=5, batch=8, lr=3e-3, progress=lambda _m: None)
    assert res["losses"][-1] < res["losses"][0], res["losses"]
    obs_spec, act_dim = probe_spec(hf)
    fresh = make_policy(hf.policy, obs_spec, act_dim, **hf.policy_kwargs)
    load_init_weights(tmp_path / "warm.safetensors", fresh)
    for k, v in replicated_tensors(res["policy"]).items():
        assert torch.equal(replicated_tensors(fresh)[k], v), k
    with pytest.raises(ValueError, match="task.image_size 64"):
        clone(dataclasses.replace(hf, image_size=64), demos, tmp_path / "no.safetensors", epochs=1)


def test_scenes_for_the_perception_are_labelled_pictures_of_the_arm_in_the_demos_poses(
        recorded: tuple[Any, Path, dict[str, Any]], tmp_path: Path) -> None:
    """record_scenes: rendered PushCube pictures at the task's size with the goal's and cube's
    table xy read back from the simulator; the same seed gives the same scenes."""
    task, out, _meta = recorded
    demos = load_demos(out)
    with pytest.raises(ValueError, match="PickCube-v1"):
        record_scenes(dataclasses.replace(task, env="PickCube-v1"), demos, tmp_path / "x.npz", 2)
    a, b = tmp_path / "a.npz", tmp_path / "b.npz"
    meta = record_scenes(task, demos, a, 5, seed=11, progress=lambda _m: None)
    record_scenes(task, demos, b, 5, seed=11, progress=lambda _m: None)
    sa, sb = load_demos(a), load_demos(b)
    assert meta["scenes"] == 5 and tuple(sa["label_names"]) == PERCEPT_LABELS
    assert sa["rgb"].shape == (5, 32, 32, 3) and sa["rgb"].dtype == np.uint8 and sa["rgb"].std() > 5
    assert sa["labels"].shape == (5, 4) and np.isfinite(sa["labels"]).all() and np.abs(sa["labels"]).max() < 0.4
    goal, cube = sa["labels"][:, :2], sa["labels"][:, 2:]
    assert np.linalg.norm(goal - cube, axis=1).max() > 0.02 and len({tuple(g) for g in goal.round(4)}) == 5
    assert all(not np.array_equal(sa["rgb"][0], x) for x in sa["rgb"][1:])  # every scene is another picture
    np.testing.assert_array_equal(sa["rgb"], sb["rgb"])
    np.testing.assert_array_equal(sa["labels"], sb["labels"])


def test_the_bench_pretrains_a_perception_and_clones_the_warm_start_with_it(
        recorded: tuple[Any, Path, dict[str, Any]], tmp_path: Path) -> None:
    """run_bench's stages before RL (no seeds: no RL run) from recorded demos: scenes rendered, a
    perception pretrained to the given file, the RL topology derived with it as tiny-vla's
    ``percept``, and the warm start cloned through that topology (it holds the perception's token
    input, so it loads into the derived task's policy and not into the plain one)."""
    from benchmarks.learn_vla import Recipe, run_bench, with_percept

    task, demos_file, _meta = recorded
    text = (ROOT / "topologies" / "local-vla-rl.yaml").read_text()
    assert "  image_size: 64\n" in text and "  patch_size: 8\n" in text
    topo = tmp_path / "rl.yaml"
    topo.write_text(text.replace("  image_size: 64\n", f"  image_size: 32\n  max_episode_steps: {STEPS}\n"))
    with pytest.raises(ValueError, match="a perception is a tiny-vla option"):
        with_percept(ROOT / "topologies" / "local.yaml", tmp_path / "p.safetensors", tmp_path / "x.yaml")
    recipe = Recipe(topology=topo, seeds=(), demos_file=demos_file, scenes=64, percept_epochs=1, clone_epochs=2,
                    warm_eval=2)
    work = tmp_path / "work"
    work.mkdir()
    doc = run_bench(recipe, work, progress=lambda _m: None, warm_out=tmp_path / "warm.safetensors",
                    percept_out=tmp_path / "percept.safetensors")
    assert doc["scenes"]["scenes"] == 64 and doc["percept"]["file"] == str(tmp_path / "percept.safetensors")
    assert doc["percept"]["held_out_from"] == "demos" and len(doc["percept"]["epochs"]) == 1
    assert len(doc["clone"]["losses"]) == 2 and doc["warm"]["episodes"] == 2 and doc["runs"] == []
    derived = load_topology(work / "rl-topology.yaml").task
    assert derived.policy_kwargs["percept"] == str(tmp_path / "percept.safetensors")
    assert derived.policy_kwargs["proprio_stats"] == "fixed" and derived.image_size == 32
    obs_spec, act_dim = probe_spec(derived)
    with_p = make_policy(derived.policy, obs_spec, act_dim, **derived.policy_kwargs)
    load_init_weights(tmp_path / "warm.safetensors", with_p)
    assert with_p.proprio_count.item() > 0  # the demonstrations' statistics came with the warm start
    assert torch.allclose(with_p.log_std.exp(), torch.full_like(with_p.log_std, NOISE_STD))
    plain = load_topology(topo).task
    without = make_policy(plain.policy, obs_spec, act_dim, **plain.policy_kwargs)
    with pytest.raises(CheckpointError, match="warm.safetensors: .* has shape"):
        load_init_weights(tmp_path / "warm.safetensors", without)
