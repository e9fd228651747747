"""The VLA pieces that need no simulator: tokeniser, instruction table, tiny-vla, dict-obs
slots and PPO batches."""

from __future__ import annotations

import threading

import numpy as np
import pytest
import torch

from dvla.config import PPOConfig
from dvla.fabric.messages import ChunkSpec, TrajectoryChunk
from dvla.learn.envs import ArraySpec
from dvla.learn.policies import make_policy, registered_policies
from dvla.learn.ppo import PPOLearner
from dvla.learn.vla.instructions import INSTRUCTIONS, instruction_for
from dvla.learn.vla.model import PRESETS, TinyVLA, count_parameters
from dvla.learn.vla.tokenizer import BOS_ID, PAD_ID, tokenize, word_id, words
from dvla.replication import ParamLayout, flatten, unflatten_into
from dvla.roles.slots import SlotPool

SPEC = {
    "rgb": ArraySpec((32, 32, 3), "uint8"),
    "proprio": ArraySpec((18,), "float32"),
    "tokens": ArraySpec((8,), "int32", vocab=4096),
}


def obs_batch(b: int, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {
        "rgb": torch.randint(0, 256, (b, 32, 32, 3), generator=g).to(torch.uint8),
        "proprio": torch.randn(b, 18, generator=g) * 3 + 1,
        "tokens": torch.as_tensor(np.stack([tokenize("push the cube", 8)] * b)),
    }


# --- tokeniser -------------------------------------------------------------------------------


def test_word_ids_are_standard_fnv1a_32():
    # Published FNV-1a 32-bit test vectors: "a" -> 0xe40c292c, "foobar" -> 0xbf9cf968.
    assert word_id("a") == 2 + 0xE40C292C % 4094
    assert word_id("foobar") == 2 + 0xBF9CF968 % 4094
    assert word_id("foobar", vocab_size=100) == 2 + 0xBF9CF968 % 98


def test_tokenize_lowercases_splits_pads_and_truncates():
    ids = tokenize("Push the CUBE, then push!", 8)
    assert ids.dtype == np.int32 and ids.shape == (8,)
    assert ids[0] == BOS_ID
    assert list(ids[1:6]) == [word_id(w) for w in ("push", "the", "cube", "then", "push")]
    assert ids[1] == ids[5] and list(ids[6:]) == [PAD_ID, PAD_ID]
    assert list(tokenize("push the cube then push", 3)) == [BOS_ID, word_id("push"), word_id("the")]
    assert list(tokenize("", 3)) == [BOS_ID, PAD_ID, PAD_ID]
    assert words("Pick-up cube #2") == ["pick", "up", "cube", "2"]
    assert all(2 <= i < 64 for i in tokenize("a b c d e f g h", 9, vocab_size=64)[1:])
    with pytest.raises(ValueError, match="length"):
        tokenize("x", 0)


def test_instruction_table_and_its_error_naming_the_key():
    assert instruction_for("PushCube-v1") == INSTRUCTIONS["PushCube-v1"]
    with pytest.raises(ValueError, match="task.instruction"):
        instruction_for("NoSuchTask-v9")


# --- tiny-vla --------------------------------------------------------------------------------


def test_tiny_vla_is_registered_and_acts():
    assert "tiny-vla" in registered_policies()
    torch.manual_seed(0)
    policy = make_policy("tiny-vla", SPEC, 8, patch_size=8)
    obs = obs_batch(5)
    action, logprob, value = policy.act(obs)
    assert action.shape == (5, 8) and logprob.shape == (5,) and value.shape == (5,)
    lp, ent, v = policy.evaluate(obs, action)
    torch.testing.assert_close(lp, logprob)
    torch.testing.assert_close(v, value)
    assert ent.shape == (5,) and torch.isfinite(ent).all()
    mean, _, _ = policy.act(obs, deterministic=True)
    assert not torch.equal(mean, action)
    # The instruction matters: other words give another action mean.
    other = dict(obs, tokens=torch.as_tensor(np.stack([tokenize("pick up the cube", 8)] * 5)))
    assert not torch.allclose(policy.act(other, deterministic=True)[0], mean)


def test_tiny_vla_sizes_and_bad_kwargs():
    tiny = make_policy("tiny-vla", SPEC, 8)
    small = make_policy("tiny-vla", SPEC, 8, size="small")
    assert 2e5 < count_parameters(tiny) < 8e5 < count_parameters(small)
    assert small.d_model == PRESETS["small"]["d_model"]
    assert make_policy("tiny-vla", SPEC, 8, size="small", d_model=64).d_model == 64  # kwargs beat presets
    big_spec = dict(SPEC, rgb=ArraySpec((224, 224, 3), "uint8"))
    big = TinyVLA(big_spec, 8, size="1b", device="meta")  # counted, never allocated
    assert 0.9e9 < count_parameters(big) < 1.2e9
    with pytest.raises(ValueError, match="patch_size"):
        make_policy("tiny-vla", SPEC, 8, patch_size=5)
    with pytest.raises(ValueError, match="size"):
        make_policy("tiny-vla", SPEC, 8, size="huge")
    with pytest.raises(TypeError, match="obs_mode: rgb"):
        make_policy("tiny-vla", {"state": ArraySpec((35,), "float32")}, 8)
    with pytest.raises(TypeError, match="tiny-vla"):
        make_policy("mlp", SPEC, 8)
    with pytest.raises(TypeError, match="policy_kwargs"):
        make_policy("tiny-vla", SPEC, 8, widht=3)


def test_tiny_vla_replicates_through_a_flat_layout():
    torch.manual_seed(1)
    a, b = make_policy("tiny-vla", SPEC, 8), make_policy("tiny-vla", SPEC, 8)
    a.observe(obs_batch(16))  # running proprio statistics are part of what replicates
    layout = ParamLayout.from_state_dict(a.state_dict())
    assert "proprio_mean" in layout.names and all(d == "float32" for d in layout.dtypes)
    flat = np.empty(layout.numel, np.float32)
    flatten(a.state_dict(), layout, out=flat)
    unflatten_into(flat, b, layout)
    obs = obs_batch(3)
    torch.testing.assert_close(a.act(obs, deterministic=True)[0], b.act(obs, deterministic=True)[0])


def test_ppo_update_on_dict_observations_moves_the_policy():
    torch.manual_seed(2)
    policy = make_policy("tiny-vla", SPEC, 4)
    obs = obs_batch(32)
    action, logprob, _ = policy.act(obs)
    adv = torch.where(action[:, 0] > 0, 1.0, -1.0)  # reward pushing action 0 up
    before = policy.act(obs, deterministic=True)[0][:, 0].mean()
    learner = PPOLearner(policy, PPOConfig(lr=3e-3, update_epochs=4, minibatches=2, target_kl=None), seed=0)
    stats = learner.update({"obs": obs, "actions": action, "logprobs": logprob, "advantages": adv, "returns": adv})
    assert stats["epochs_run"] == 4 and np.isfinite(stats["pg_loss"])
    assert policy.act(obs, deterministic=True)[0][:, 0].mean() > before
    assert policy.proprio_count.item() == 32  # observe() saw the batch


# --- the actor's slots keep image dtypes -------------------------------------------------------


def _chunk(T: int, n: int, rng: np.random.Generator, rgb_dtype=np.uint8) -> TrajectoryChunk:
    obs = {
        "rgb": rng.integers(0, 256, (T, n, 32, 32, 3)).astype(rgb_dtype),
        "proprio": rng.standard_normal((T, n, 18)).astype(np.float32),
        "tokens": np.broadcast_to(tokenize("push", 8), (T, n, 8)).astype(np.int32),
    }
    zeros = {k: np.zeros_like(v) for k, v in obs.items()}
    tn = lambda dt: np.zeros((T, n), dt)  # noqa: E731
    return TrajectoryChunk(
        rollout="r", seq=0, policy_version=3, env_steps=T * n, obs=obs, actions=np.ones((T, n, 8), np.float32),
        logprobs=tn(np.float32), rewards=tn(np.float32), terminated=tn(bool), truncated=tn(bool), success=tn(bool),
        next_obs={k: v[-1] for k, v in obs.items()}, final_obs=zeros,
    )


def test_slots_carry_structured_observations_in_their_dtypes():
    rng = np.random.default_rng(0)
    spec = ChunkSpec(obs=SPEC, act_dim=8, T=4, N=2)
    pool = SlotPool(spec, n_slots=3)
    a, b = _chunk(4, 2, rng), _chunk(4, 1, rng)
    assert spec.problem(a) is None and spec.problem(b) is None
    stop = threading.Event()
    sa, sb = pool.acquire(stop), pool.acquire(stop)
    pool.fill(sa, a)
    pool.fill(sb, b)
    assert (pool.steps(sa), pool.steps(sb)) == (8, 4)
    batch = pool.stack([sa, sb], torch.device("cpu"))
    assert batch.obs["rgb"].dtype == torch.uint8 and batch.obs["rgb"].shape == (4, 3, 32, 32, 3)
    assert batch.obs["tokens"].dtype == torch.int32 and batch.steps == 12
    np.testing.assert_array_equal(batch.obs["rgb"][:, :2].numpy(), a.obs["rgb"])
    np.testing.assert_array_equal(batch.obs["rgb"][:, 2:].numpy(), b.obs["rgb"])
    np.testing.assert_array_equal(batch.next_obs["proprio"][2].numpy(), b.next_obs["proprio"][0])
    # what a slot could not hold never reaches one: the run's spec refuses it first
    assert spec.problem(_chunk(4, 1, rng, rgb_dtype=np.int32))[0] == "shape"
    code, detail = ChunkSpec(obs={"state": ArraySpec((35,), "float32")}, act_dim=8, T=4, N=2).problem(a)
    assert code == "shape" and "obs keys" in detail


def test_fixed_proprio_statistics_stay_as_loaded():
    """`proprio_stats: fixed` keeps a warm start's statistics (the learner's `observe` folds
    nothing) or, holding none, takes the first batch's and keeps them; `running` folds every
    batch; anything else is refused naming the key."""
    running = make_policy("tiny-vla", SPEC, 8, size="tiny")
    fixed = make_policy("tiny-vla", SPEC, 8, size="tiny", proprio_stats="fixed")
    loaded = {"proprio_mean": torch.full((SPEC["proprio"].shape[0],), 0.5), "proprio_count": torch.tensor(100.0)}
    fixed.load_state_dict(loaded, strict=False)
    batch = obs_batch(16)
    running.observe(batch)
    fixed.observe(batch)
    assert float(running.proprio_count) == 16 and not torch.equal(running.proprio_mean, torch.zeros_like(running.proprio_mean))
    assert float(fixed.proprio_count) == 100 and torch.equal(fixed.proprio_mean, loaded["proprio_mean"])
    fresh = make_policy("tiny-vla", SPEC, 8, size="tiny", proprio_stats="fixed")
    fresh.observe(batch)
    first = fresh.proprio_mean.clone()
    assert float(fresh.proprio_count) == 16 and torch.allclose(first, running.proprio_mean)
    fresh.observe(obs_batch(16, seed=1))
    assert float(fresh.proprio_count) == 16 and torch.equal(fresh.proprio_mean, first)
    with pytest.raises(ValueError, match="proprio_stats"):
        make_policy("tiny-vla", SPEC, 8, size="tiny", proprio_stats="frozen")
