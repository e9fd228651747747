"""The learning algorithm: advantage estimation (GAE, GRPO) and the PPO update.

Data reaches the actor as trajectory *chunks*: ``T`` consecutive steps of ``N`` envs acted on by
one (possibly slightly stale) policy version. The actor stacks chunks side by side into
:class:`Trajectories` (dvla/roles/slots.py); :func:`gae_batch` (or
:func:`~dvla.learn.grpo.grpo_batch`) turns them into a flat training batch, and
:class:`PPOLearner` runs the clipped-surrogate update on it.

Stale data: every transition carries the log-probability of the *behaviour* policy that acted.
By default (decoupled PPO, Hilton et al. 2021) the clip applies to the ratio against the policy
at the start of the update and the staleness is corrected by an importance weight proximal /
behaviour truncated at ``is_clip``: clipping against the behaviour policy (plain PPO) starts
most samples outside the clip range once the data lags a version.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np
import torch
from torch import Tensor, nn

from dvla.config import PPOConfig

__all__ = ["compute_gae", "Trajectories", "gae_batch", "PPOLearner"]

log = logging.getLogger("dvla.ppo")


# --- advantages -------------------------------------------------------------------------------


def _float_mask(x: Any, like: Any) -> Any:
    if isinstance(like, Tensor):
        return torch.as_tensor(x, device=like.device).to(like.dtype)
    return np.asarray(x).astype(np.asarray(like).dtype)


def compute_gae(rewards, values, next_values, terminated, episode_end, gamma: float, lam: float):
    """Generalised advantage estimation over ``[T, N]`` arrays (all numpy or all torch).

    ``next_values[t]`` is the value of the state actually reached after step t: the value of the
    pre-reset ``final_obs`` where the episode ended, of the next observation otherwise.
    ``terminated`` drops that bootstrap (a terminal state is worth nothing); ``episode_end``
    (terminated or truncated) stops the recursion so advantages never leak across episodes.
    Steps past the last row bootstrap from ``next_values`` alone.

    Returns ``(advantages, returns)`` with ``returns = advantages + values``.
    """
    not_term = 1 - _float_mask(terminated, values)
    not_end = 1 - _float_mask(episode_end, values)
    deltas = rewards + gamma * not_term * next_values - values
    zeros_like = torch.zeros_like if isinstance(deltas, Tensor) else np.zeros_like
    advantages = zeros_like(deltas)
    running = zeros_like(deltas[0])
    for t in range(deltas.shape[0] - 1, -1, -1):
        running = deltas[t] + gamma * lam * not_end[t] * running
        advantages[t] = running
    return advantages, advantages + values


@dataclass
class Trajectories:
    """The per-step fields of several trajectory chunks as tensors, their env columns side by side
    (``[T, N, ...]``, ``next_obs`` ``[N, ...]``): what the actor stacks from its slots for one
    update. Each field is the chunk's (dvla/fabric/messages.py, ``TrajectoryChunk``); ``logprobs``
    are the behaviour policy's, observations dicts of tensors (``{"state"}`` for flat ones).
    """

    obs: dict[str, Tensor]
    actions: Tensor
    logprobs: Tensor
    rewards: Tensor
    terminated: Tensor
    truncated: Tensor
    success: Tensor
    next_obs: dict[str, Tensor]
    final_obs: dict[str, Tensor]
    extras: dict[str, Tensor] = field(default_factory=dict)

    @property
    def steps(self) -> int:
        """Transitions held (T * N)."""
        return self.rewards.numel()

    def training_batch(self, advantages: Tensor, returns: Tensor, values: Tensor) -> dict[str, Any]:
        """The flat ``[T*N, ...]`` batch :meth:`PPOLearner.update` takes."""
        n = self.steps
        return {
            "obs": _policy_obs(self.obs, 2),
            "actions": self.actions.reshape(n, -1),
            "logprobs": self.logprobs.reshape(n),
            "advantages": advantages.reshape(n),
            "returns": returns.reshape(n),
            "values": values.reshape(n),
            "extras": {k: v.reshape(n, *v.shape[2:]) for k, v in self.extras.items()},
        }


@torch.no_grad()
def gae_batch(policy: nn.Module, b: Trajectories, cfg: PPOConfig) -> dict[str, Any]:
    """The PPO batch of ``b``, with GAE from ``policy``'s critic.

    Values come from the learner's critic, not the rollout's stale one, so bootstrap and baseline
    are one function. ``cfg.terminal_bootstrap`` bootstraps terminated episodes from
    ``V(final_obs)`` like truncated ones (ManiSkill terminates on success while its dense reward
    keeps paying near the goal; docs/topology.md).
    """
    T, N = b.rewards.shape
    ended = b.terminated | b.truncated
    values = policy.value(_policy_obs(b.obs, 2)).reshape(T, N)
    next_values = torch.empty_like(values)
    next_values[:-1] = values[1:]
    next_values[-1] = policy.value(_policy_obs(b.next_obs, 1)).reshape(N)
    rows = ended.reshape(-1).nonzero().squeeze(1)
    if rows.numel():  # V(final_obs) only where an episode ended (elsewhere final_obs is zeros)
        next_values.view(-1)[rows] = policy.value(_take(_policy_obs(b.final_obs, 2), rows))
    no_bootstrap = torch.zeros_like(b.terminated) if cfg.terminal_bootstrap else b.terminated
    adv, ret = compute_gae(
        b.rewards * cfg.reward_scale, values, next_values, no_bootstrap, ended, cfg.gamma, cfg.gae_lambda
    )
    return b.training_batch(adv, ret, values)


def _policy_obs(obs: Mapping[str, Tensor], lead: int) -> Any:
    """Observations as the policy takes them: the ``lead`` leading axes ([T, N] or [N]) merged
    into one; the bare tensor for flat observations, the dict for structured ones."""
    flat = {k: v.reshape(-1, *v.shape[lead:]) for k, v in obs.items()}
    return flat["state"] if set(flat) == {"state"} else flat


# --- the update --------------------------------------------------------------------------------

BATCH_KEYS = ("obs", "actions", "logprobs", "advantages", "returns")


class PPOLearner:
    """Clipped-surrogate PPO on batches of (possibly stale) transitions.

    The ``target_kl`` early stop measures how far *this update* moved the policy (KL to the
    policy at its start), not the staleness the batch arrived with: otherwise data a few versions
    old could stop every update before its first step.

    In a learner group (``group``, dvla/learn/group.py) gradients are averaged by DDP and each
    minibatch's advantage moments and KL estimate are summed over the ranks, so every rank takes
    the same normalisation, early stop and optimizer step.

    An update that meets a non-finite gradient norm, or leaves a non-finite parameter or buffer,
    is refused: parameters and buffers are restored, ``updates_refused_nonfinite`` counts it and
    the statistics carry ``refused_nonfinite`` = 1 (the caller must not publish a version for it).
    """

    def __init__(
        self,
        policy: nn.Module,
        cfg: PPOConfig,
        device: Any = "cpu",
        seed: int | None = None,
        *,
        decoupled: bool | None = None,
        is_clip: float | None = None,
        group: Any = None,
    ):
        self.policy = policy
        self.cfg = cfg
        # the keywords override the config's fields (scripts/tune_ppo.py compares both objectives)
        self.decoupled = cfg.decoupled if decoupled is None else decoupled
        self.is_clip = cfg.is_clip if is_clip is None else is_clip
        self.device = torch.device(device)
        #: what the optimizer updates: parameters that require grad (a frozen base does not)
        self._trainable = [p for p in policy.parameters() if p.requires_grad]
        self.optimizer = make_adam(self._trainable, lr=cfg.lr, eps=1e-5)
        self._gen = torch.Generator()
        if seed is not None:
            self._gen.manual_seed(seed)
        self.group = group
        #: the training forward (policy.evaluate, through DDP in a group of several ranks)
        self._forward = group.train_module(policy) if group is not None else policy.evaluate
        #: updates refused for a non-finite gradient norm, parameter or buffer
        self.updates_refused_nonfinite = 0
        self._kept: list[Tensor] = []  # parameters and buffers before the update, to restore

    def _tensors(self, batch: Mapping[str, Any]) -> dict[str, Tensor]:
        missing = [k for k in BATCH_KEYS if k not in batch]
        if missing:
            raise KeyError(f"batch lacks {missing}")
        out = {k: torch.as_tensor(batch[k], dtype=torch.float32, device=self.device) for k in BATCH_KEYS if k != "obs"}
        out["obs"] = _obs_tensors(batch["obs"], self.device)
        out["extras"] = {k: torch.as_tensor(v, device=self.device) for k, v in (batch.get("extras") or {}).items()}
        obs = out["obs"]
        shapes = {k: tuple(v.shape) for k, v in out.items() if k not in ("obs", "extras")}
        shapes |= {f"extras.{k}": tuple(v.shape) for k, v in out["extras"].items()}
        shapes |= {f"obs.{k}": tuple(v.shape) for k, v in obs.items()} if isinstance(obs, Mapping) else {"obs": tuple(obs.shape)}
        size = _obs_len(obs)
        if any(shape[0] != size for shape in shapes.values()):
            raise ValueError(f"batch arrays disagree on length: {shapes}")
        if size < self.cfg.minibatches:
            raise ValueError(f"batch of {size} is smaller than minibatches={self.cfg.minibatches}")
        return out

    def update(self, batch: Mapping[str, Any]) -> dict[str, float]:
        """Run up to ``update_epochs`` passes of minibatch SGD on ``batch``; return statistics."""
        started = time.perf_counter()
        cfg = self.cfg
        b = self._tensors(batch)
        size = _obs_len(b["obs"])
        state = self._state()
        self._keep(state)
        observe = getattr(self.policy, "observe", None)
        if callable(observe):
            observe(b["obs"])
        with torch.no_grad():
            start_logprobs = torch.cat([
                _evaluate(self.policy.evaluate, _take(b["obs"], rows), b["actions"][rows], _take(b["extras"], rows))[0]
                for rows in _slices(size, cfg.micro_batch or size, self.device)
            ])
        behaviour_kl = _approx_kl(start_logprobs - b["logprobs"])
        behaviour_gap = float((start_logprobs - b["logprobs"]).abs().max())
        mb_size = size // cfg.minibatches
        stats: dict[str, list[float]] = {k: [] for k in ("pg_loss", "v_loss", "entropy", "approx_kl", "clipfrac")}
        epochs_run, stopped, refused = 0, False, ""
        for _ in range(cfg.update_epochs):
            order = torch.randperm(size, generator=self._gen).to(self.device)
            for start in range(0, mb_size * cfg.minibatches, mb_size):
                idx = order[start : start + mb_size]
                mb = {k: _take(v, idx) for k, v in b.items()}
                adv = mb["advantages"].double()
                # One sum over the group: the advantage moments every rank normalises with.
                n, a_sum, a_sq = self._sum([adv.numel(), adv.sum(), adv.square().sum()])
                adv_mean = a_sum / n
                adv_std = max(a_sq / n - adv_mean * adv_mean, 0.0) ** 0.5
                # Micro-batches: each slice's loss weighted by its share, so the summed gradient
                # is the minibatch's while only one slice's activations are alive.
                self.optimizer.zero_grad(set_to_none=True)
                kl_sum, parts = 0.0, {}
                slices = _slices(mb_size, cfg.micro_batch or mb_size, self.device)
                for i, rows in enumerate(slices):
                    part = {k: _take(v, rows) for k, v in mb.items()}
                    with self._no_sync(last=i == len(slices) - 1):
                        logprob, entropy, value = _evaluate(self._forward, part["obs"], part["actions"], part["extras"])
                        start_lp = start_logprobs[idx[rows]]
                        kl_sum += _kl_sum(logprob.detach() - start_lp)
                        loss, got = self._loss(part, start_lp, logprob, entropy, value, adv_mean, adv_std)
                        (loss * (rows.numel() / mb_size)).backward()
                    for k, v in got.items():
                        parts[k] = parts.get(k, 0.0) + v * rows.numel() / mb_size
                kl = self._sum([kl_sum])[0] / n
                if cfg.target_kl is not None and kl > cfg.target_kl:
                    self.optimizer.zero_grad(set_to_none=True)
                    stopped = True
                    break
                grad_norm = float(nn.utils.clip_grad_norm_(self._trainable, cfg.max_grad_norm))
                # DDP averaged the gradients, so every rank sees the same norm and refuses together.
                if not math.isfinite(grad_norm):
                    refused = f"gradient norm {grad_norm}"
                    self.optimizer.zero_grad(set_to_none=True)
                    break
                self.optimizer.step()
                for k, v in parts.items():
                    stats[k].append(v)
                stats["approx_kl"].append(kl)
            epochs_run += 1
            if stopped or refused:
                break
        # Summed so the group refuses together even if one rank went bad alone.
        if self._sum([not _all_finite(state)])[0] > 0 and not refused:
            refused = "a non-finite parameter or buffer after the update"
        if refused:
            self._restore(state)
            self.updates_refused_nonfinite += 1
            log.warning("update refused (%d so far): %s; parameters and buffers restored",
                        self.updates_refused_nonfinite, refused)
        out = {k: float(np.mean(v)) if v else float("nan") for k, v in stats.items()}
        out.update(
            refused_nonfinite=float(bool(refused)),
            epochs_run=epochs_run,
            early_stop=float(stopped),
            behaviour_kl=behaviour_kl,
            behaviour_gap=behaviour_gap,
            lr=self.optimizer.param_groups[0]["lr"],
            batch_size=size,
            update_s=time.perf_counter() - started,
        )
        return out

    def _no_sync(self, last: bool) -> Any:
        """DDP's ``no_sync`` for all but a minibatch's last micro-batch (one all-reduce of the
        accumulated gradients per step instead of one per micro-batch)."""
        no_sync = getattr(self._forward, "no_sync", None)
        return no_sync() if no_sync is not None and not last else contextlib.nullcontext()

    def _state(self) -> list[Tensor]:
        """Trainable parameters and floating-point buffers (observation statistics): what an
        update changes."""
        return [*self._trainable, *(t for t in self.policy.buffers() if t.is_floating_point())]

    @torch.no_grad()
    def _keep(self, state: list[Tensor]) -> None:
        if len(self._kept) != len(state) or any(k.shape != t.shape for k, t in zip(self._kept, state)):
            self._kept = [t.detach().clone() for t in state]
            return
        for k, t in zip(self._kept, state):
            k.copy_(t)

    @torch.no_grad()
    def _restore(self, state: list[Tensor]) -> None:
        for k, t in zip(self._kept, state):
            t.copy_(k)

    def _sum(self, values: list[Any]) -> list[float]:
        values = [float(v) for v in values]
        return self.group.sum(values) if self.group is not None else values

    def _loss(
        self, mb: dict[str, Tensor], start_logprob: Tensor, logprob: Tensor, entropy: Tensor, value: Tensor,
        adv_mean: float, adv_std: float,
    ) -> tuple[Tensor, dict]:
        cfg = self.cfg
        # Per-minibatch normalisation (over the whole group's minibatch) keeps the step size
        # independent of the reward scale.
        adv = (mb["advantages"] - adv_mean) / (adv_std + 1e-8)
        if self.decoupled:
            ratio = (logprob - start_logprob).exp()
            weight = (start_logprob - mb["logprobs"]).exp().clamp(max=self.is_clip)
        else:
            ratio = (logprob - mb["logprobs"]).exp()
            weight = torch.ones_like(ratio)
        surrogate = torch.max(-adv * ratio, -adv * ratio.clamp(1 - cfg.clip, 1 + cfg.clip))
        pg_loss = (weight * surrogate).mean()
        v_loss = 0.5 * (value - mb["returns"]).pow(2).mean()
        ent = entropy.mean()
        loss = pg_loss + cfg.vf_coef * v_loss - cfg.ent_coef * ent
        with torch.no_grad():
            clipfrac = ((ratio - 1).abs() > cfg.clip).float().mean().item()
        return loss, {"pg_loss": pg_loss.item(), "v_loss": v_loss.item(), "entropy": ent.item(), "clipfrac": clipfrac}

def make_adam(params: Any, **kwargs: Any) -> torch.optim.Adam:
    """Adam with the fused kernel (one kernel for all parameters) where this PyTorch has it."""
    params = list(params)
    try:
        return torch.optim.Adam(params, fused=True, **kwargs)
    except (RuntimeError, TypeError, ValueError):
        return torch.optim.Adam(params, **kwargs)


def _all_finite(tensors: list[Tensor]) -> bool:
    """Whether every value of every tensor is finite (one device sync)."""
    return bool(torch.stack([torch.isfinite(t).all() for t in tensors]).all()) if tensors else True


def _obs_tensors(obs: Any, device: torch.device) -> Any:
    """Flat observations as float32; a dict keeps each array's dtype (images stay uint8)."""
    if isinstance(obs, Mapping):
        return {k: torch.as_tensor(v, device=device) for k, v in obs.items()}
    return torch.as_tensor(obs, dtype=torch.float32, device=device)


def _obs_len(obs: Any) -> int:
    return int(next(iter(obs.values())).shape[0]) if isinstance(obs, Mapping) else int(obs.shape[0])


def _evaluate(fn: Any, obs: Any, actions: Tensor, extras: Mapping[str, Tensor]) -> tuple[Tensor, Tensor, Tensor]:
    """``fn(obs, actions)``, with the policy's extras when it declares any (docs/policies.md)."""
    return fn(obs, actions, extras) if extras else fn(obs, actions)


def _slices(size: int, step: int, device: Any) -> list[Tensor]:
    """Row indices [0, size) in consecutive slices of at most ``step`` rows."""
    return [torch.arange(i, min(i + step, size), device=device) for i in range(0, size, step)]


def _take(v: Any, idx: Tensor) -> Any:
    return {k: a[idx] for k, a in v.items()} if isinstance(v, Mapping) else v[idx]


def _approx_kl(log_ratio: Tensor) -> float:
    return _kl_sum(log_ratio) / max(1, log_ratio.numel())


def _kl_sum(log_ratio: Tensor) -> float:
    # The low-variance, always non-negative estimator k3 = (r - 1) - log r (Schulman 2020), summed.
    return float(((log_ratio.exp() - 1) - log_ratio).double().sum())
