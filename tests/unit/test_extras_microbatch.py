"""What a policy ships besides its action (``extras_spec``: a flow chain, action bins) reaches
the learner intact (codec, actor checks, slots, PPO batches), and micro-batches with gradient
accumulation give the same update as whole minibatches."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from torch import nn

from dvla.config import PPOConfig
from dvla.fabric.codec import decode, encode
from dvla.fabric.messages import ArraySpec, ChunkSpec, TrajectoryChunk
from dvla.learn.policies import MLPPolicy, extras_spec, sample_actions
from dvla.learn.ppo import PPOLearner
from dvla.roles.actor import chunk_problem
from dvla.roles.slots import SlotPool

T, N, D, A, K = 4, 3, 5, 2, 3
STATE = {"state": ArraySpec((D,), "float32")}
EXTRAS = {"chain": ArraySpec((K + 1, A), "float32"), "bins": ArraySpec((A,), "int32", vocab=16)}
SPEC = ChunkSpec(obs=STATE, act_dim=A, extras=EXTRAS, T=T, N=N)


class ChainPolicy(nn.Module):
    """A toy policy whose log-prob needs the extras: action = last link of a Gaussian chain."""

    extras_spec = EXTRAS

    def __init__(self) -> None:
        super().__init__()
        self.mean = nn.Linear(D, A)
        self.log_std = nn.Parameter(torch.zeros(A))
        self.v = nn.Linear(D, 1)
        self.seen_extras: list[dict] = []

    def _logp(self, obs, chain):
        dist = torch.distributions.Normal(self.mean(obs).unsqueeze(1), self.log_std.exp())
        return dist.log_prob(chain[:, 1:]).sum((1, 2)), dist.entropy().sum(-1).squeeze(1) * K

    @torch.no_grad()
    def sample(self, obs, deterministic=False, generator=None):
        b = obs.shape[0]
        noise = torch.randn(b, K, A, generator=generator)
        links = self.mean(obs).unsqueeze(1) + self.log_std.exp() * noise
        chain = torch.cat([torch.zeros(b, 1, A), links], 1)
        bins = torch.randint(0, 16, (b, A), generator=generator, dtype=torch.int32)
        return chain[:, -1], self._logp(obs, chain)[0], {"chain": chain, "bins": bins}

    def act(self, obs, deterministic=False, generator=None):
        a, lp, _ = self.sample(obs, deterministic, generator)
        return a, lp, self.value(obs)

    def evaluate(self, obs, action, extras):
        self.seen_extras.append({k: v.shape for k, v in extras.items()})
        torch.testing.assert_close(extras["chain"][:, -1], action)
        lp, ent = self._logp(obs, extras["chain"])
        return lp, ent, self.value(obs)

    def value(self, obs):
        return self.v(obs).squeeze(-1)


def filled_chunk(policy: nn.Module, seed: int = 0) -> TrajectoryChunk:
    c = ChunkSpec(obs=STATE, act_dim=A, extras=extras_spec(policy), T=T, N=N).zeros()
    rng = np.random.default_rng(seed)
    g = torch.Generator().manual_seed(seed)
    for t in range(T):
        obs = rng.standard_normal((N, D), dtype=np.float32)
        a, lp, ex = sample_actions(policy, torch.from_numpy(obs), generator=g)
        c.obs["state"][t], c.actions[t], c.logprobs[t] = obs, a.numpy(), lp.numpy()
        for k, v in ex.items():
            c.extras[k][t] = v.numpy()
    c.rewards[:] = rng.standard_normal((T, N))
    c.next_obs["state"][:] = rng.standard_normal((N, D))
    return dataclasses.replace(c, policy_version=1, seq=1)


def test_extras_cross_the_wire_and_pass_the_actors_checks() -> None:
    policy = ChainPolicy()
    c = decode(encode(filled_chunk(policy)))
    assert c.extras.keys() == EXTRAS.keys() and c.extras["chain"].shape == (T, N, K + 1, A)
    assert c.extras["bins"].dtype == np.int32
    assert chunk_problem(c, SPEC, 1) is None
    # extras the policy does not declare, or missing ones, are a shape problem
    assert chunk_problem(c, dataclasses.replace(SPEC, extras={}), 1)[0] == "shape"
    assert chunk_problem(dataclasses.replace(c, extras={"chain": c.extras["chain"]}), SPEC, 1)[0] == "shape"
    wrong = {**c.extras, "chain": np.zeros((T, N, K, A), np.float32)}
    assert chunk_problem(dataclasses.replace(c, extras=wrong), SPEC, 1)[0] == "shape"
    nan = {**c.extras, "chain": c.extras["chain"].copy()}
    nan["chain"][1, 2, 0, 1] = np.nan
    code, detail = chunk_problem(dataclasses.replace(c, extras=nan), SPEC, 1)
    assert code == "nonfinite" and "chain" in detail
    big = {**c.extras, "bins": np.full((T, N, A), 16, np.int32)}
    assert chunk_problem(dataclasses.replace(c, extras=big), SPEC, 1)[0] == "out_of_range"


def test_the_codec_rejects_extras_that_disagree_on_T_and_N() -> None:
    c = filled_chunk(ChainPolicy())
    bad = dataclasses.replace(c, extras={"chain": np.zeros((T, N + 1, K + 1, A), np.float32)})
    with pytest.raises(Exception, match="extras"):
        decode(encode(bad))


def test_extras_go_through_the_slots_into_the_learners_evaluate() -> None:
    torch.manual_seed(0)
    policy = ChainPolicy()
    slots = SlotPool(SPEC, n_slots=2)
    chunks = [decode(encode(filled_chunk(policy, seed))) for seed in (1, 2)]
    for slot, c in enumerate(chunks):
        slots.fill(slot, c)
    b = slots.stack([0, 1], torch.device("cpu"))
    np.testing.assert_array_equal(b.extras["chain"][:, N:].numpy(), chunks[1].extras["chain"])
    np.testing.assert_array_equal(b.extras["bins"][:, :N].numpy(), chunks[0].extras["bins"])
    batch = b.training_batch(torch.zeros(T, 2 * N), torch.zeros(T, 2 * N), torch.zeros(T, 2 * N))
    assert batch["extras"]["chain"].shape == (T * 2 * N, K + 1, A)
    batch["advantages"] = torch.randn(T * 2 * N)
    learner = PPOLearner(policy, PPOConfig(minibatches=2, update_epochs=1, batch_steps=T * 2 * N, target_kl=None), seed=0)
    stats = learner.update(batch)
    # the rollout's log-probs were of the same weights: the update starts on-policy
    assert stats["behaviour_kl"] < 1e-10
    assert policy.seen_extras and all(s["chain"][1:] == (K + 1, A) for s in policy.seen_extras)


def _batch(n: int, seed: int) -> dict:
    g = torch.Generator().manual_seed(seed)
    return {"obs": torch.randn(n, D, generator=g), "actions": torch.randn(n, A, generator=g),
            "logprobs": torch.randn(n, generator=g) - 2, "advantages": torch.randn(n, generator=g),
            "returns": torch.randn(n, generator=g), "values": torch.zeros(n)}


@pytest.mark.parametrize("micro", [1, 5, 8, 64])
def test_micro_batches_give_the_update_of_whole_minibatches(micro: int) -> None:
    """Gradient accumulation over micro-batches of 1..64 rows (minibatches of 16, one uneven
    split at 5) ends at the same parameters as one pass per minibatch."""
    finals = []
    for micro_batch in (None, micro):
        torch.manual_seed(0)
        policy = MLPPolicy(D, A, hidden=(16, 16), obs_norm=True)
        cfg = PPOConfig(minibatches=4, update_epochs=2, batch_steps=64, target_kl=None, micro_batch=micro_batch)
        stats = PPOLearner(policy, cfg, seed=3).update(_batch(64, 1))
        finals.append((torch.cat([p.detach().flatten() for p in policy.parameters()]), stats))
    (a, sa), (b, sb) = finals
    torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)
    for k in ("pg_loss", "v_loss", "entropy", "approx_kl", "clipfrac"):
        assert sa[k] == pytest.approx(sb[k], rel=1e-4, abs=1e-6), k


def test_micro_batch_must_be_positive() -> None:
    with pytest.raises(ValueError, match="micro_batch"):
        PPOConfig(micro_batch=0)


def test_frozen_parameters_are_not_optimised_or_restored() -> None:
    torch.manual_seed(0)
    policy = MLPPolicy(D, A, hidden=(8, 8))
    policy.critic.requires_grad_(False)
    frozen = [p.detach().clone() for p in policy.critic.parameters()]
    learner = PPOLearner(policy, PPOConfig(minibatches=2, update_epochs=1, batch_steps=16, target_kl=None), seed=0)
    optimised = [p for group in learner.optimizer.param_groups for p in group["params"]]
    assert len(optimised) == len(list(policy.parameters())) - len(frozen)
    learner.update(_batch(16, 2))
    assert all(torch.equal(f, p) for f, p in zip(frozen, policy.critic.parameters()))
