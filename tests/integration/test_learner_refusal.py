"""A learner group (two gloo ranks in spawned processes) refuses a non-finite update together:
one rank's batch holds a NaN reward, both ranks refuse, restore and keep identical parameters."""

from __future__ import annotations

import torch

from dvla.config import PPOConfig
from dvla.learn.policies import MLPPolicy
from dvla.learn.ppo import PPOLearner, gae_batch
from tests.unit.test_ppo import _trajectories


def _refusing_rank(rank: int, port: int, out: str) -> None:
    from dvla.config import GroupRank
    from dvla.learn.group import LearnerGroup

    spec = GroupRank(rank=rank, world_size=2, init_method=f"tcp://127.0.0.1:{port}", backend="gloo",
                     strategy="ddp", timeout_s=60, members=("a0", "a1"))
    group = LearnerGroup(spec, torch.device("cpu"))
    try:
        torch.manual_seed(0)
        policy = MLPPolicy(4, 2, hidden=(16,), obs_norm=True)
        cfg = PPOConfig(update_epochs=2, minibatches=2, batch_steps=64, lr=1e-3, target_kl=None)
        learner = PPOLearner(policy, cfg, "cpu", seed=0, group=group)
        before = [p.detach().clone() for p in policy.state_dict().values()]
        bad = _trajectories(seed=rank)
        if rank == 1:  # one rank's batch only: the whole group must refuse
            bad.rewards[2, 2] = float("nan")
        stats = learner.update(gae_batch(policy, bad, cfg))
        same = all(torch.equal(a, b) for a, b in zip(before, policy.state_dict().values()))
        stats2 = learner.update(gae_batch(policy, _trajectories(seed=rank), cfg))  # the group goes on
        torch.save({"refused": stats["refused_nonfinite"], "same": same, "then": stats2["refused_nonfinite"],
                    "params": [p.detach().clone() for p in policy.parameters()]}, out)
    finally:
        group.close()


def test_a_learner_group_refuses_a_non_finite_update_on_every_rank(tmp_path):
    import socket

    import torch.multiprocessing as mp

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    procs = [mp.get_context("spawn").Process(target=_refusing_rank, args=(r, port, str(tmp_path / f"{r}.pt")))
             for r in range(2)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(120)
        assert p.exitcode == 0
    r0, r1 = (torch.load(tmp_path / f"{r}.pt") for r in range(2))
    assert r0["refused"] == r1["refused"] == 1.0 and r0["same"] and r1["same"]
    assert r0["then"] == r1["then"] == 0.0
    for a, b in zip(r0["params"], r1["params"]):
        assert torch.equal(a, b)
