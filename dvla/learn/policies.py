"""Policies the actor trains and the rollouts run, and the registry naming them.

A task names its policy with ``TaskConfig.policy``: a registry name (``"mlp"``, ``"tiny-vla"``)
or ``"module:Class"`` for a user policy, built by :func:`make_policy` as
``Class(obs, act_dim, **TaskConfig.policy_kwargs)`` (``obs``: :func:`policy_obs_arg`). A policy
is a ``torch.nn.Module`` with ``act``, ``evaluate`` and ``value`` (:class:`Policy`), optionally
``observe``, ``sample`` and ``extras_spec``; docs/policies.md is the full protocol, including
what a user policy must respect for weight replication.
"""

from __future__ import annotations

import importlib
import inspect
import math
from typing import Any, Callable, Mapping, Protocol, Sequence, runtime_checkable

import torch
from torch import Tensor, nn
from torch.distributions import Normal

from .group import all_reduce_sum

__all__ = ["Policy", "MLPPolicy", "register_policy", "make_policy", "policy_obs_arg", "registered_policies",
           "sample_actions", "extras_spec", "policy_base_hash"]


@runtime_checkable
class Policy(Protocol):
    """What the learner, the rollouts and the evaluator call on a policy (see module docstring)."""

    def act(self, obs: Tensor, deterministic: bool = False) -> tuple[Tensor, Tensor, Tensor]: ...

    def evaluate(self, obs: Tensor, action: Tensor) -> tuple[Tensor, Tensor, Tensor]: ...

    def value(self, obs: Tensor) -> Tensor: ...

    def parameters(self, recurse: bool = True) -> Any: ...

    def state_dict(self, *args: Any, **kwargs: Any) -> Any: ...

    def load_state_dict(self, state_dict: Any, strict: bool = True, assign: bool = False) -> Any: ...


def sample_actions(policy: Any, obs: Any, deterministic: bool = False,
                   generator: torch.Generator | None = None) -> tuple[Tensor, Tensor, dict[str, Tensor]]:
    """(action, logprob, extras) from the policy's optional ``sample``, else from ``act`` (value
    dropped). ``generator`` goes to a ``sample``/``act`` that takes one; others use torch's global one."""
    sample = getattr(policy, "sample", None)
    extra = {"generator": generator} if generator is not None and _takes_generator(sample or policy.act) else {}
    if sample is not None:
        out = sample(obs, deterministic, **extra)
        return (out[0], out[1], out[2]) if len(out) == 3 else (out[0], out[1], {})
    action, logprob, _ = policy.act(obs, deterministic, **extra)
    return action, logprob, {}


def extras_spec(policy: Any) -> dict[str, Any]:
    """The per-step tensors the policy ships besides the action (name -> ArraySpec; {} for none)."""
    return dict(getattr(policy, "extras_spec", None) or {})


def policy_base_hash(policy: Any) -> str:
    """Content hash of the policy's frozen base checkpoint ("" when the whole policy replicates)."""
    return str(getattr(policy, "base_hash", "") or "")


_HALF_LOG_2PI = 0.5 * math.log(2 * math.pi)

_REGISTRY: dict[str, type] = {}


def register_policy(name: str) -> Callable[[type], type]:
    """Class decorator adding a policy to the registry under ``name``."""

    def add(cls: type) -> type:
        if name in _REGISTRY and _REGISTRY[name] is not cls:
            raise ValueError(f"policy name {name!r} is already registered to {_REGISTRY[name]!r}")
        _REGISTRY[name] = cls
        return cls

    return add


def registered_policies() -> list[str]:
    return sorted(set(_REGISTRY) | set(_LAZY))


#: built-in policies living in their own modules, imported on first use (torch models of the
#: VLA package are not needed by state-only runs)
_LAZY: dict[str, str] = {
    "tiny-vla": "dvla.learn.vla.model",
    # Hugging Face checkpoints (docs/policies.md): token actions and flow matching
    "vla-tokens": "dvla.learn.vla.token_action",
    "vla-flow": "dvla.learn.vla.flow",
    # LeRobot's published flow-matching VLAs, loaded natively (docs/policies.md)
    "pi0": "dvla.learn.vla.published",
    "pi05": "dvla.learn.vla.published",
    "smolvla": "dvla.learn.vla.published",
    # OpenVLA / OpenVLA-OFT checkpoints (the Prismatic Hugging Face layout), loaded natively
    "openvla": "dvla.learn.vla.openvla_policy",
    "openvla-oft": "dvla.learn.vla.openvla_policy",
}


def policy_module(spec: str) -> str | None:
    """The module that defines policy ``spec`` when it is not one of those registered at import
    (a family of its own, or a ``module:Class`` plugin); None otherwise."""
    if ":" in spec:
        return spec.partition(":")[0]
    return _LAZY.get(spec) if spec not in _REGISTRY else None


def _policy_class(spec: str) -> type:
    if ":" in spec:
        module_name, _, attr = spec.partition(":")
        cls = getattr(importlib.import_module(module_name), attr, None)
        if cls is None:
            raise ValueError(f"{spec!r}: module {module_name!r} has no attribute {attr!r}")
        return cls
    if spec not in _REGISTRY and spec in _LAZY:
        importlib.import_module(_LAZY[spec])
    if spec not in _REGISTRY:
        raise ValueError(f"unknown policy {spec!r}; registered: {registered_policies()}")
    return _REGISTRY[spec]


def policy_obs_arg(obs_spec: Mapping[str, Any]) -> Any:
    """The first constructor argument for observations described by ``obs_spec``: the int D for
    flat observations (``{"state": (D,) float32}``), the spec itself otherwise."""
    if set(obs_spec) == {"state"}:
        return int(obs_spec["state"].shape[0])
    return dict(obs_spec)


def make_policy(spec: str, obs: Any, act_dim: int, **kwargs: Any) -> nn.Module:
    """Build a policy from a registry name or ``"module:Class"``; ``obs`` is an int D or an ObsSpec
    (:func:`policy_obs_arg`)."""
    if isinstance(obs, Mapping):
        obs = policy_obs_arg(obs)
    try:
        policy = _policy_class(spec)(obs, act_dim, **kwargs)
    except TypeError as err:
        raise TypeError(f"policy {spec!r} with policy_kwargs {sorted(kwargs)}: {err}") from err
    missing = [m for m in ("act", "evaluate", "value", "state_dict") if not callable(getattr(policy, m, None))]
    if missing:
        raise TypeError(f"policy {spec!r} lacks {missing}; see dvla.learn.policies for the protocol")
    return policy


@torch.no_grad()
def fold_moments(mean: Tensor, var: Tensor, count: Tensor, x: Tensor) -> None:
    """Fold the rows of ``x`` [n, D] into running ``mean``/``var``/``count`` buffers in place (Chan et
    al.'s parallel update), with the batch's moments summed over the learner group first so the
    buffers stay identical on every rank."""
    x = x.to(torch.float64)
    moments = torch.cat([x.new_tensor([x.shape[0]]), x.sum(0), x.square().sum(0)])
    n_all, s, sq = all_reduce_sum(moments).split([1, x.shape[1], x.shape[1]])
    n = float(n_all)
    if n == 0:
        return
    batch_mean = s / n
    batch_var = (sq / n - batch_mean.square()).clamp(min=0)
    old = count.to(torch.float64)
    total = old + n
    delta = batch_mean - mean.to(torch.float64)
    m2 = var.to(torch.float64) * old + batch_var * n + delta.square() * old * n / total
    mean.add_((delta * n / total).to(mean.dtype))
    var.copy_(m2 / total)
    count.copy_(total)


_TAKES_GENERATOR: dict[Any, bool] = {}


def _takes_generator(method: Any) -> bool:
    key = getattr(method, "__func__", method)
    if key not in _TAKES_GENERATOR:
        _TAKES_GENERATOR[key] = "generator" in inspect.signature(method).parameters
    return _TAKES_GENERATOR[key]


def _layer(n_in: int, n_out: int, std: float) -> nn.Linear:
    # Orthogonal weights and zero biases keep early activations well scaled (CleanRL-style init).
    layer = nn.Linear(n_in, n_out)
    nn.init.orthogonal_(layer.weight, std)
    nn.init.zeros_(layer.bias)
    return layer


def _mlp(n_in: int, hidden: Sequence[int], n_out: int, out_std: float) -> nn.Sequential:
    layers: list[nn.Module] = []
    for width in hidden:
        layers += [_layer(n_in, width, math.sqrt(2)), nn.Tanh()]
        n_in = width
    layers.append(_layer(n_in, n_out, out_std))
    return nn.Sequential(*layers)


@register_policy("mlp")
class MLPPolicy(nn.Module):
    """Gaussian actor and value critic, two separate tanh MLPs; a state-independent log-std, and an
    actor whose last layer starts tiny (initial mean action near zero). ``obs_norm=True``
    standardises observations with running buffers that :meth:`observe` updates and the state
    dict carries, so rollouts normalise exactly like the learner."""

    def __init__(
        self,
        obs_dim: int,
        act_dim: int,
        hidden: Sequence[int] = (256, 256, 256),
        init_log_std: float = -0.5,
        obs_norm: bool = False,
    ):
        super().__init__()
        if isinstance(obs_dim, Mapping):
            raise TypeError(
                f"the mlp policy needs flat observations (obs_mode: state), got {sorted(obs_dim)}; "
                "use policy: tiny-vla for rgb observations"
            )
        self.obs_dim = int(obs_dim)
        self.act_dim = int(act_dim)
        hidden = tuple(int(h) for h in hidden)
        self.actor = _mlp(self.obs_dim, hidden, self.act_dim, 0.01 * math.sqrt(2))
        self.critic = _mlp(self.obs_dim, hidden, 1, 1.0)
        self.log_std = nn.Parameter(torch.full((self.act_dim,), float(init_log_std)))
        self.obs_norm = bool(obs_norm)
        if self.obs_norm:
            self.register_buffer("obs_mean", torch.zeros(self.obs_dim))
            self.register_buffer("obs_var", torch.ones(self.obs_dim))
            self.register_buffer("obs_count", torch.zeros(()))

    @torch.no_grad()
    def observe(self, obs: Tensor) -> None:
        """Fold a batch of observations into the running statistics (no-op without obs_norm)."""
        if not self.obs_norm:
            return
        fold_moments(self.obs_mean, self.obs_var, self.obs_count, obs.reshape(-1, self.obs_dim))

    def _normalise(self, obs: Tensor) -> Tensor:
        if not self.obs_norm:
            return obs
        return ((obs - self.obs_mean) / (self.obs_var + 1e-8).sqrt()).clamp(-10.0, 10.0)

    def _dist(self, obs: Tensor) -> Normal:
        mean = self.actor(self._normalise(obs))
        return Normal(mean, self.log_std.exp().expand_as(mean))

    def value(self, obs: Tensor) -> Tensor:
        return self.critic(self._normalise(obs)).squeeze(-1)

    @torch.no_grad()
    def act(self, obs: Tensor, deterministic: bool = False,
            generator: torch.Generator | None = None) -> tuple[Tensor, Tensor, Tensor]:
        action, logprob = self.sample(obs, deterministic, generator)
        return action, logprob, self.value(obs)

    @torch.no_grad()
    def sample(self, obs: Tensor, deterministic: bool = False,
               generator: torch.Generator | None = None) -> tuple[Tensor, Tensor]:
        """``act`` without the critic. The Gaussian is written out (for a small batch a ``Normal``
        object is a large share of the call); it gives `evaluate`'s ``Normal.log_prob`` value."""
        mean = self.actor(self._normalise(obs))
        log_std = self.log_std.expand_as(mean)
        if deterministic:
            return mean, (-log_std - _HALF_LOG_2PI).sum(-1)
        eps = torch.randn(mean.shape, generator=generator, dtype=mean.dtype, device=mean.device)
        action = mean + log_std.exp() * eps
        return action, (-0.5 * eps.square() - log_std - _HALF_LOG_2PI).sum(-1)

    def evaluate(self, obs: Tensor, action: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        dist = self._dist(obs)
        return dist.log_prob(action).sum(-1), dist.entropy().sum(-1), self.value(obs)
