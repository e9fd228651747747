"""A policy written outside dvla, as a user would: only torch, and the protocol of docs/policies.md.

Select it in a topology with ``policy: my_policy:SharedTrunkPolicy`` and this directory on
PYTHONPATH. One tanh trunk feeds both the Gaussian mean and the value (dvla's ``mlp`` policy
keeps two separate networks), so a run with it is recognisable by its parameter names.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn
from torch.distributions import Normal


class SharedTrunkPolicy(nn.Module):
    def __init__(self, obs, act_dim: int, width: int = 64, init_log_std: float = -0.5):
        super().__init__()
        if not isinstance(obs, int):
            raise TypeError(f"SharedTrunkPolicy reads flat observations (obs_mode: state), got {obs!r}")
        self.trunk = nn.Sequential(nn.Linear(obs, width), nn.Tanh(), nn.Linear(width, width), nn.Tanh())
        self.mean = nn.Linear(width, act_dim)
        self.critic = nn.Linear(width, 1)
        nn.init.zeros_(self.mean.bias)
        self.mean.weight.data.mul_(0.01)  # start near the zero action
        self.log_std = nn.Parameter(torch.full((act_dim,), float(init_log_std)))

    def _forward(self, obs: Tensor) -> tuple[Normal, Tensor]:
        h = self.trunk(obs)
        mean = self.mean(h)
        return Normal(mean, self.log_std.exp().expand_as(mean)), self.critic(h).squeeze(-1)

    @torch.no_grad()
    def act(self, obs: Tensor, deterministic: bool = False) -> tuple[Tensor, Tensor, Tensor]:
        dist, value = self._forward(obs)
        action = dist.mean if deterministic else dist.sample()
        return action, dist.log_prob(action).sum(-1), value

    def evaluate(self, obs: Tensor, action: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        dist, value = self._forward(obs)
        return dist.log_prob(action).sum(-1), dist.entropy().sum(-1), value

    def value(self, obs: Tensor) -> Tensor:
        return self._forward(obs)[1]
