"""Unit tests of dvla.learn.ppo and dvla.learn.policies (no simulator)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dvla.learn.optstate import optimizer_from_tensors, optimizer_to_tensors

from dvla.config import PPOConfig
from dvla.learn.grpo import grpo_advantages
from dvla.learn.policies import MLPPolicy, Policy, make_policy, register_policy
from dvla.learn.ppo import PPOLearner, Trajectories, compute_gae, gae_batch

GAMMA, LAM = 0.5, 0.5


def _gae_case():
    """One env, 4 steps: the episode is truncated after step 1, terminated after step 3.

    values v = [1, 2, 3, 4]; next_values: step 0 -> v1 = 2, step 1 -> V(final_obs) = 10,
    step 2 -> v3 = 4, step 3 -> V(final_obs) = 7 (ignored: terminated).
    """
    r = np.array([[1.0], [1.0], [1.0], [1.0]], np.float32)
    v = np.array([[1.0], [2.0], [3.0], [4.0]], np.float32)
    nv = np.array([[2.0], [10.0], [4.0], [7.0]], np.float32)
    term = np.array([[0], [0], [0], [1]], bool)
    end = np.array([[0], [1], [0], [1]], bool)
    # deltas: d0 = 1 + .5*2 - 1 = 1; d1 = 1 + .5*10 - 2 = 4 (truncation bootstraps);
    #         d2 = 1 + .5*4 - 3 = 0; d3 = 1 + 0 - 4 = -3 (termination does not).
    # advantages: A3 = -3; A2 = 0 + .25*A3 = -0.75; A1 = 4 (recursion cut at the episode end);
    #             A0 = 1 + .25*4 = 2.
    expected = np.array([[2.0], [4.0], [-0.75], [-3.0]], np.float32)
    return r, v, nv, term, end, expected


def test_gae_hand_computed_numpy():
    r, v, nv, term, end, expected = _gae_case()
    adv, ret = compute_gae(r, v, nv, term, end, GAMMA, LAM)
    np.testing.assert_allclose(adv, expected, rtol=1e-6)
    np.testing.assert_allclose(ret, expected + v, rtol=1e-6)


def test_gae_hand_computed_torch():
    r, v, nv, term, end, expected = _gae_case()
    t = torch.as_tensor
    adv, ret = compute_gae(t(r), t(v), t(nv), t(term), t(end), GAMMA, LAM)
    assert isinstance(adv, torch.Tensor) and adv.dtype == torch.float32  # torch in, torch out, dtype kept
    np.testing.assert_allclose(adv.numpy(), expected, rtol=1e-6)
    np.testing.assert_allclose(ret.numpy(), expected + v, rtol=1e-6)


def test_gae_lambda_one_no_ends_is_discounted_return_minus_value():
    rng = np.random.default_rng(0)
    r = rng.normal(size=(6, 3)).astype(np.float32)
    v = rng.normal(size=(6, 3)).astype(np.float32)
    nv = np.vstack([v[1:], rng.normal(size=(1, 3)).astype(np.float32)])
    zeros = np.zeros((6, 3), bool)
    adv, ret = compute_gae(r, v, nv, zeros, zeros, 0.9, 1.0)
    g = nv[-1].copy()
    for t in range(5, -1, -1):
        g = r[t] + 0.9 * g
        np.testing.assert_allclose(ret[t], g, rtol=1e-5, atol=1e-5)


def test_grpo_advantages():
    adv = grpo_advantages(np.array([1.0, 3.0, 10.0, 10.0, 5.0]), np.array([7, 7, 2, 2, 9]))
    np.testing.assert_allclose(adv, [-1.0, 1.0, 0.0, 0.0, 0.0], atol=1e-6)
    t = grpo_advantages(torch.tensor([0.0, 2.0, 4.0]), torch.tensor([1, 1, 1]))
    assert isinstance(t, torch.Tensor) and t.dtype == torch.float32  # torch in, torch out, dtype kept
    std = np.std([0.0, 2.0, 4.0])
    np.testing.assert_allclose(t.numpy(), [-2 / std, 0.0, 2 / std], rtol=1e-5)
    with pytest.raises(ValueError):
        grpo_advantages(np.zeros(3), np.zeros(2))


def test_mlp_policy_protocol_and_shapes():
    torch.manual_seed(0)
    policy = make_policy("mlp", 5, 2, hidden=(16, 16))
    assert isinstance(policy, MLPPolicy) and isinstance(policy, Policy)
    obs = torch.randn(7, 5)
    action, logprob, value = policy.act(obs)
    assert action.shape == (7, 2) and logprob.shape == (7,) and value.shape == (7,)
    assert not action.requires_grad
    mean, _, _ = policy.act(obs, deterministic=True)
    torch.testing.assert_close(mean, policy.actor(obs))
    lp, ent, val = policy.evaluate(obs, action)
    torch.testing.assert_close(lp, logprob)
    assert ent.shape == (7,) and lp.requires_grad
    torch.testing.assert_close(policy.log_std.detach(), torch.full((2,), -0.5))


def test_make_policy_by_module_path_and_errors():
    assert isinstance(make_policy("dvla.learn.policies:MLPPolicy", 3, 1), MLPPolicy)
    with pytest.raises(ValueError):
        make_policy("no-such-policy", 3, 1)

    @register_policy("test-tiny")
    class Tiny(MLPPolicy):
        def __init__(self, obs_dim, act_dim):
            super().__init__(obs_dim, act_dim, hidden=(4,))

    assert isinstance(make_policy("test-tiny", 3, 1), Tiny)


def _fixed_batch(n=512, obs_dim=4, act_dim=2, seed=0):
    """Actions correlated with obs and advantages favouring a target action: learnable."""
    g = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    policy = MLPPolicy(obs_dim, act_dim, hidden=(32, 32))
    obs = torch.randn(n, obs_dim, generator=g)
    action, logprob, value = policy.act(obs)
    target = obs[:, :act_dim].tanh()
    advantages = -((action - target) ** 2).sum(-1)
    returns = obs[:, 0] * 2.0
    batch = dict(obs=obs, actions=action, logprobs=logprob, advantages=advantages, returns=returns, values=value)
    return policy, batch


def _surrogate(policy, batch):
    with torch.no_grad():
        lp, _, v = policy.evaluate(batch["obs"], batch["actions"])
        adv = batch["advantages"]
        adv = (adv - adv.mean()) / (adv.std(unbiased=False) + 1e-8)
        return float(-(adv * (lp - batch["logprobs"]).exp()).mean()), float(((v - batch["returns"]) ** 2).mean())


def test_ppo_update_reduces_losses_on_fixed_batch():
    policy, batch = _fixed_batch()
    cfg = PPOConfig(update_epochs=8, minibatches=4, batch_steps=512, lr=1e-3, target_kl=None)
    learner = PPOLearner(policy, cfg, "cpu", seed=0)
    pg0, v0 = _surrogate(policy, batch)
    for _ in range(3):
        stats = learner.update(batch)
    pg1, v1 = _surrogate(policy, batch)
    assert pg1 < pg0 - 0.01
    assert v1 < 0.5 * v0
    for key in ("pg_loss", "v_loss", "entropy", "approx_kl", "clipfrac", "epochs_run", "update_s"):
        assert np.isfinite(stats[key]), key
    assert stats["lr"] == 1e-3
    assert stats["epochs_run"] == 8


def test_ppo_target_kl_stops_early_and_checkpoint_roundtrip():
    policy, batch = _fixed_batch()
    cfg = PPOConfig(update_epochs=50, minibatches=4, batch_steps=512, lr=3e-3, target_kl=0.01)
    learner = PPOLearner(policy, cfg, "cpu", seed=0)
    stats = learner.update(batch)
    assert stats["early_stop"] == 1.0 and stats["epochs_run"] < 50
    # the optimizer state survives the tensors-and-JSON form checkpoints use (no pickle)
    tensors, meta = optimizer_to_tensors(learner.optimizer.state_dict())
    other_policy, _ = _fixed_batch(seed=1)
    other = PPOLearner(other_policy, cfg, "cpu")
    other.optimizer.load_state_dict(optimizer_from_tensors(tensors, meta, other.optimizer.state_dict()))
    for a, b in zip(learner.optimizer.state.values(), other.optimizer.state.values()):
        for k in a:
            torch.testing.assert_close(a[k], b[k])


def test_ppo_rejects_bad_batches():
    policy, batch = _fixed_batch(n=8)
    learner = PPOLearner(policy, PPOConfig(minibatches=16, batch_steps=16), "cpu")
    with pytest.raises(ValueError):
        learner.update(batch)
    with pytest.raises(KeyError):
        learner.update({k: v for k, v in batch.items() if k != "returns"})


@pytest.mark.parametrize("bootstrap_terminated", [False, True])
def test_gae_batch_of_two_stacked_chunks_matches_manual_gae(bootstrap_terminated):
    torch.manual_seed(0)
    cfg = PPOConfig(gamma=0.8, gae_lambda=0.9, reward_scale=2.0, terminal_bootstrap=bootstrap_terminated)
    policy = MLPPolicy(3, 1, hidden=(8,))
    rng = np.random.default_rng(1)
    T, N = 5, 2
    chunk = {
        "obs": rng.normal(size=(T, N, 3)).astype(np.float32),
        "actions": rng.normal(size=(T, N, 1)).astype(np.float32),
        "logprobs": rng.normal(size=(T, N)).astype(np.float32),
        "rewards": rng.normal(size=(T, N)).astype(np.float32),
        "terminated": np.zeros((T, N), bool),
        "truncated": np.zeros((T, N), bool),
        "success": np.zeros((T, N), bool),
        "final_obs": np.zeros((T, N, 3), np.float32),
        "next_obs": rng.normal(size=(N, 3)).astype(np.float32),
    }
    chunk["terminated"][1, 0] = True
    chunk["truncated"][3, 1] = True
    chunk["final_obs"][1, 0] = rng.normal(size=3)
    chunk["final_obs"][3, 1] = rng.normal(size=3)
    # The same chunk twice, side by side, as the actor's slots stack them: [T, 2N].
    side = {k: torch.as_tensor(np.concatenate([v, v], axis=0 if k == "next_obs" else 1)) for k, v in chunk.items()}
    for k in ("obs", "final_obs", "next_obs"):
        side[k] = {"state": side[k]}
    batch = gae_batch(policy, Trajectories(**side), cfg)
    assert batch["obs"].shape == (2 * T * N, 3) and batch["advantages"].shape == (2 * T * N,)

    with torch.no_grad():
        V = lambda x: policy.value(torch.as_tensor(x)).numpy()  # noqa: E731
        v = V(chunk["obs"].reshape(-1, 3)).reshape(T, N)
        nv = np.vstack([v[1:], V(chunk["next_obs"])[None]])
        nv[1, 0] = V(chunk["final_obs"][1, 0][None])[0]
        nv[3, 1] = V(chunk["final_obs"][3, 1][None])[0]
    end = chunk["terminated"] | chunk["truncated"]
    # Bootstrapping a termination treats it like a time limit: the episode still ends there.
    term = chunk["terminated"] & (not bootstrap_terminated)
    adv, ret = compute_gae(chunk["rewards"] * 2.0, v, nv, term, end, 0.8, 0.9)
    both = lambda x: np.concatenate([x, x], axis=1).reshape(-1)  # noqa: E731
    np.testing.assert_allclose(batch["advantages"].numpy(), both(adv), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(batch["returns"].numpy(), both(ret), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(batch["values"].numpy(), both(v), rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(batch["actions"].numpy(), both(chunk["actions"][..., 0])[:, None])


def test_obs_norm_statistics_travel_with_the_state_dict():
    torch.manual_seed(0)
    policy = MLPPolicy(3, 1, hidden=(8,), obs_norm=True)
    x = torch.randn(100, 3) * torch.tensor([1.0, 5.0, 0.1]) + 2.0
    policy.observe(x[:30])
    policy.observe(x[30:])  # two batches give the same statistics as one
    torch.testing.assert_close(policy.obs_mean, x.mean(0))
    torch.testing.assert_close(policy.obs_var, x.var(0, unbiased=False), rtol=1e-4, atol=1e-6)
    copy = MLPPolicy(3, 1, hidden=(8,), obs_norm=True)
    copy.load_state_dict(policy.state_dict())
    torch.testing.assert_close(copy.value(x), policy.value(x))
    # The learner feeds every batch to observe().
    _, batch = _fixed_batch(n=64)
    normed = MLPPolicy(4, 2, hidden=(8,), obs_norm=True)
    PPOLearner(normed, PPOConfig(minibatches=2, batch_steps=64), "cpu").update(batch)
    assert float(normed.obs_count) == 64


def test_decoupled_equals_plain_ppo_on_fresh_data():
    """With lag 0 (behaviour == policy at the start of the update) both objectives coincide."""
    results = []
    for decoupled in (False, True):
        policy, batch = _fixed_batch(seed=3)
        cfg = PPOConfig(update_epochs=2, minibatches=4, batch_steps=512, lr=1e-3, target_kl=None)
        PPOLearner(policy, cfg, "cpu", seed=0, decoupled=decoupled).update(batch)
        results.append([p.detach().clone() for p in policy.parameters()])
    for a, b in zip(*results):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)


def test_decoupled_learns_from_stale_data():
    """Data acted on by an older policy: the update still improves the surrogate."""
    policy, batch = _fixed_batch(seed=4)
    with torch.no_grad():
        for p in policy.actor.parameters():
            p.add_(0.05 * torch.randn_like(p))  # the learner has moved on since the data was sampled
    cfg = PPOConfig(update_epochs=4, minibatches=4, batch_steps=512, lr=1e-3, target_kl=None)
    learner = PPOLearner(policy, cfg, "cpu", seed=0)
    assert learner.decoupled
    pg0, _ = _surrogate(policy, batch)
    stats = learner.update(batch)
    pg1, _ = _surrogate(policy, batch)
    assert stats["behaviour_kl"] > 0 and pg1 < pg0


def test_learner_uses_fused_adam_and_steps_like_the_default():
    from dvla.learn.ppo import make_adam

    torch.manual_seed(0)
    a, b = torch.nn.Linear(8, 4), torch.nn.Linear(8, 4)
    b.load_state_dict(a.state_dict())
    fused, plain = make_adam(a.parameters(), lr=1e-2, eps=1e-5), torch.optim.Adam(b.parameters(), lr=1e-2, eps=1e-5)
    assert fused.param_groups[0]["fused"] is True
    x = torch.randn(32, 8)
    for _ in range(20):
        for net, opt in ((a, fused), (b, plain)):
            opt.zero_grad()
            net(x).pow(2).mean().backward()
            opt.step()
    for p, q in zip(a.parameters(), b.parameters()):
        assert torch.allclose(p, q, atol=1e-5)


def _trajectories(T=8, N=8, obs_dim=4, act_dim=2, seed=0):
    rng = np.random.default_rng(seed)
    t = lambda *shape: torch.as_tensor(rng.normal(size=shape).astype(np.float32))  # noqa: E731
    no = torch.zeros(T, N, dtype=torch.bool)
    return Trajectories(obs={"state": t(T, N, obs_dim)}, actions=t(T, N, act_dim), logprobs=t(T, N) - 2.0,
                        rewards=t(T, N), terminated=no, truncated=no.clone(), success=no.clone(),
                        final_obs={"state": torch.zeros(T, N, obs_dim)}, next_obs={"state": t(N, obs_dim)})


@pytest.mark.parametrize("poison", ["rewards", "logprobs", "obs_huge"])
def test_non_finite_update_is_refused_and_restores_the_parameters(poison):
    """A batch with a NaN reward or a NaN behaviour log-prob (past ingest validation), or finite
    observations that overflow the normalisation statistics: the update is refused, parameters
    and buffers stay exactly as they were, and the refusal is counted."""
    torch.manual_seed(0)
    policy = MLPPolicy(4, 2, hidden=(32, 32), obs_norm=True)
    cfg = PPOConfig(update_epochs=2, minibatches=2, batch_steps=64, lr=1e-3, target_kl=None)
    learner = PPOLearner(policy, cfg, "cpu", seed=0)
    good = _trajectories()
    learner.update(gae_batch(policy, good, cfg))  # a good update first: Adam state, statistics
    before = {k: v.clone() for k, v in policy.state_dict().items()}
    bad = _trajectories()
    if poison == "obs_huge":
        bad.obs["state"][5, 0, 0] = 3e38  # finite, but its square overflows the running variance
    else:
        getattr(bad, poison)[5, 3] = float("nan")
    stats = learner.update(gae_batch(policy, bad, cfg))
    assert stats["refused_nonfinite"] == 1.0 and learner.updates_refused_nonfinite == 1
    for k, v in policy.state_dict().items():
        assert torch.isfinite(v).all(), k
        assert torch.equal(v, before[k]), k
    stats = learner.update(gae_batch(policy, good, cfg))  # and it goes on learning from good data
    assert stats["refused_nonfinite"] == 0.0 and learner.updates_refused_nonfinite == 1
    assert any(not torch.equal(v, before[k]) for k, v in policy.state_dict().items())

