"""``tiny-vla``: a small vision-language-action policy for structured (``obs_mode="rgb"``) observations.

One transformer encoder reads ``[ACT] [VAL] | image patches | proprioception | instruction words``
(padding words masked); ``[ACT]`` reads the mean of a Gaussian over the action (learned
state-independent log-std; with ``task.action_chunk`` K, K actions side by side), ``[VAL]`` the
value. Sizes: ``policy_kwargs`` on top of a named preset (``size``, default ``tiny``, about 0.4 M
parameters; ``1b`` for GPU machines: see :data:`PRESETS`). ``policy_kwargs.percept``: a pretrained
perception file (:mod:`.percept`), loaded frozen by every role; its estimates from the image join
the proprioception's token.
"""

from __future__ import annotations

import math
from typing import Any, Mapping

import torch
from torch import Tensor, nn
from torch.distributions import Normal

from ..policies import fold_moments, register_policy
from .tokenizer import PAD_ID

__all__ = ["TinyVLA", "PRESETS", "preset_kwargs", "count_parameters"]

PRESETS: dict[str, dict[str, int]] = {
    "tiny": dict(d_model=64, layers=2, heads=4, patch_size=8),
    "small": dict(d_model=128, layers=4, heads=4, patch_size=8),
    "base": dict(d_model=256, layers=6, heads=8, patch_size=8),
    # GPU machines: ~1.0e9 parameters (20 blocks of 12 * 2048^2), 224 px images, 14 px patches
    "1b": dict(d_model=2048, layers=20, heads=16, patch_size=14),
}
"""Named sizes; explicit ``policy_kwargs`` override a preset's entries."""


def preset_kwargs(size: str, **overrides: int) -> dict[str, int]:
    """A preset's sizes updated with ``overrides``."""
    if size not in PRESETS:
        raise ValueError(f"policy_kwargs.size: unknown tiny-vla size {size!r} (expected one of {', '.join(PRESETS)})")
    return {**PRESETS[size], **overrides}


def _spec_shape(spec: Any) -> tuple[int, ...]:
    return tuple(int(x) for x in spec.shape)


@register_policy("tiny-vla")
class TinyVLA(nn.Module):
    """Patch + word + proprioception transformer with Gaussian action and value readouts. ``obs``
    needs ``rgb``; ``proprio`` and ``tokens`` are optional. ``observe`` keeps running moments of
    ``proprio`` in buffers that replicate with the weights, so joints of any scale arrive standardised.
    """

    def __init__(
        self,
        obs: Mapping[str, Any],
        act_dim: int,
        *,
        size: str = "tiny",
        d_model: int | None = None,
        layers: int | None = None,
        heads: int | None = None,
        patch_size: int | None = None,
        mlp_ratio: int = 4,
        init_log_std: float = -0.5,
        proprio_stats: str = "running",
        percept: str | None = None,
        device: Any = None,
    ):
        super().__init__()
        if not isinstance(obs, Mapping) or "rgb" not in obs:
            raise TypeError(
                f"tiny-vla needs structured observations with an 'rgb' image (obs_mode: rgb), got {obs!r}"
            )
        sizes = preset_kwargs(size, **{
            k: int(v) for k, v in
            (("d_model", d_model), ("layers", layers), ("heads", heads), ("patch_size", patch_size)) if v is not None
        })
        d_model, layers, heads, patch_size = sizes["d_model"], sizes["layers"], sizes["heads"], sizes["patch_size"]
        h, w, c = _spec_shape(obs["rgb"])
        if patch_size < 1 or h % patch_size or w % patch_size:
            raise ValueError(f"policy_kwargs.patch_size: {patch_size} must divide the image size {h}x{w}")
        if d_model % heads:
            raise ValueError(f"policy_kwargs.d_model: {d_model} must be a multiple of heads={heads}")
        if proprio_stats not in ("running", "fixed"):
            raise ValueError(f"policy_kwargs.proprio_stats: {proprio_stats!r} (expected 'running' or 'fixed')")
        #: "fixed": the proprio statistics are folded from the first batch observed (a clone's
        #: demonstrations) or loaded (a warm start's), and then stay: `observe` folds nothing more
        self.proprio_stats = proprio_stats
        self.act_dim = int(act_dim)
        self.d_model = d_model
        factory = {"device": device}
        self.patchify = nn.Conv2d(c, d_model, kernel_size=patch_size, stride=patch_size, **factory)
        n_patches = (h // patch_size) * (w // patch_size)
        self.patch_pos = nn.Parameter(torch.zeros(1, n_patches, d_model, **factory))
        self.readout = nn.Parameter(torch.zeros(1, 2, d_model, **factory))  # [ACT], [VAL]
        self.n_proprio = _spec_shape(obs["proprio"])[0] if "proprio" in obs else 0
        if self.n_proprio:
            self.register_buffer("proprio_mean", torch.zeros(self.n_proprio, **factory))
            self.register_buffer("proprio_var", torch.ones(self.n_proprio, **factory))
            self.register_buffer("proprio_count", torch.zeros((), **factory))
        self.percept: nn.Module | None = None
        if percept:  # frozen: not learnt, not replicated; every role loads the same file
            from .percept import load_percept

            self.percept = load_percept(percept, device=device).requires_grad_(False)
        n_in = self.n_proprio + (self.percept.outputs if self.percept is not None else 0)
        if n_in:  # one token: the standardised proprioception, then the perception's estimates
            self.proprio_in = nn.Linear(n_in, d_model, **factory)
        self.n_words = _spec_shape(obs["tokens"])[0] if "tokens" in obs else 0
        if self.n_words:
            vocab = getattr(obs["tokens"], "vocab", None)
            if not vocab:
                raise ValueError("tiny-vla: the 'tokens' observation spec does not say its vocab size")
            self.word_embed = nn.Embedding(int(vocab), d_model, **factory)
            self.word_pos = nn.Parameter(torch.zeros(1, self.n_words, d_model, **factory))
        block = nn.TransformerEncoderLayer(
            d_model, heads, dim_feedforward=mlp_ratio * d_model, dropout=0.0,
            activation="gelu", batch_first=True, norm_first=True, **factory,
        )
        self.encoder = nn.TransformerEncoder(block, layers, enable_nested_tensor=False)
        self.norm = nn.LayerNorm(d_model, **factory)
        self.mean_head = nn.Linear(d_model, self.act_dim, **factory)
        self.value_head = nn.Linear(d_model, 1, **factory)
        self.log_std = nn.Parameter(torch.full((self.act_dim,), float(init_log_std), **factory))
        if device is None or torch.device(device).type != "meta":
            self._init_weights()

    def _init_weights(self) -> None:
        for p in (self.patch_pos, self.readout, *([self.word_pos] if self.n_words else [])):
            nn.init.normal_(p, std=0.02)
        # Near-zero initial mean action (as the MLP policy): the untrained arm stays still.
        nn.init.orthogonal_(self.mean_head.weight, 0.01)
        nn.init.zeros_(self.mean_head.bias)
        nn.init.orthogonal_(self.value_head.weight, 1.0)
        nn.init.zeros_(self.value_head.bias)

    # --- inputs -------------------------------------------------------------------------------

    @torch.no_grad()
    def observe(self, obs: Mapping[str, Tensor]) -> None:
        """Fold a batch's proprioception into the running statistics (Chan's parallel update);
        with ``proprio_stats: fixed`` only while none are held yet (the first batch, or nothing
        loaded)."""
        if not self.n_proprio or (self.proprio_stats == "fixed" and float(self.proprio_count) > 0):
            return
        fold_moments(self.proprio_mean, self.proprio_var, self.proprio_count, obs["proprio"].reshape(-1, self.n_proprio))

    def _encode(self, obs: Mapping[str, Tensor]) -> Tensor:
        """[B, 2, d_model]: the two readout tokens after the encoder."""
        rgb = obs["rgb"]
        b = rgb.shape[0]
        dtype = self.readout.dtype
        img = rgb.to(dtype).permute(0, 3, 1, 2) / 255.0 - 0.5
        parts = [self.readout.expand(b, -1, -1), self.patchify(img).flatten(2).transpose(1, 2) + self.patch_pos]
        masks = [torch.zeros(b, parts[0].shape[1] + parts[1].shape[1], dtype=torch.bool, device=rgb.device)]
        known = []
        if self.n_proprio:
            p = obs["proprio"].to(dtype)
            known.append(((p - self.proprio_mean) / (self.proprio_var + 1e-8).sqrt()).clamp(-10.0, 10.0))
        if self.percept is not None:
            with torch.no_grad():  # already standardised by the perception's own label statistics
                known.append(self.percept(rgb).to(dtype).clamp(-10.0, 10.0))
        if known:
            parts.append(self.proprio_in(torch.cat(known, 1)).unsqueeze(1))
            masks.append(torch.zeros(b, 1, dtype=torch.bool, device=rgb.device))
        if self.n_words:
            ids = obs["tokens"].long()
            parts.append(self.word_embed(ids) + self.word_pos)
            masks.append(ids == PAD_ID)
        x = self.encoder(torch.cat(parts, 1), src_key_padding_mask=torch.cat(masks, 1))
        return self.norm(x[:, :2])

    # --- the policy protocol ------------------------------------------------------------------

    def _heads(self, obs: Mapping[str, Tensor]) -> tuple[Normal, Tensor]:
        z = self._encode(obs)
        mean = self.mean_head(z[:, 0])
        return Normal(mean, self.log_std.exp().expand_as(mean)), self.value_head(z[:, 1]).squeeze(-1)

    def value(self, obs: Mapping[str, Tensor]) -> Tensor:
        return self.value_head(self._encode(obs)[:, 1]).squeeze(-1)

    @torch.no_grad()
    def act(self, obs: Mapping[str, Tensor], deterministic: bool = False,
            generator: torch.Generator | None = None) -> tuple[Tensor, Tensor, Tensor]:
        dist, value = self._heads(obs)
        mean = dist.mean
        noise = torch.randn(mean.shape, generator=generator, dtype=mean.dtype, device=mean.device)
        action = mean if deterministic else mean + dist.stddev * noise
        return action, dist.log_prob(action).sum(-1), value

    def evaluate(self, obs: Mapping[str, Tensor], action: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        dist, value = self._heads(obs)
        return dist.log_prob(action).sum(-1), dist.entropy().sum(-1), value


def count_parameters(module: nn.Module) -> int:
    """Number of parameter elements (works on meta-device modules)."""
    return sum(math.prod(p.shape) for p in module.parameters())
