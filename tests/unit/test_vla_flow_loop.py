"""vla-flow's denoising loop: the same actions, log-probs and chains as a plain re-implementation.

The reference below is the loop written the straightforward way (every step recomputes the time
embedding, the context's keys and values and the mask, as the first version of ``vla-flow`` did),
from the policy's public modules. Any change to the optimised loop that moves a value fails here.
"""

from __future__ import annotations

import collections
import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from dvla.learn.spec import ArraySpec
from dvla.learn.vla.build import save_random_checkpoint
from dvla.learn.vla.flow import FlowVLA
from dvla.learn.vla.hf_backbone import tokenize_instruction

ACTION_DIM, CHUNK = 8, 2
ACT_DIM = ACTION_DIM * CHUNK
SPEC = {"rgb": ArraySpec((64, 64, 6), "uint8"), "proprio": ArraySpec((18,), "float32"),
        "tokens": ArraySpec((8,), "int32")}
TIGHT = {"atol": 1e-5, "rtol": 1e-5}  # float32; only summation order may differ


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory):
    return save_random_checkpoint(tmp_path_factory.mktemp("flow_loop") / "flow", "flow", action_dim=ACTION_DIM,
                                  max_chunk=4)


def obs_batch(policy, b: int = 3) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    tokens = torch.as_tensor(np.stack([tokenize_instruction(policy.backbone.tokenizer, "push the cube", 8)] * b))
    tokens[1:, 3:] = policy.backbone.pad_id
    return {"rgb": torch.randint(0, 256, (b, 64, 64, 6), generator=g).to(torch.uint8),
            "proprio": torch.randn(b, 18, generator=g), "tokens": tokens}


# --- the reference: one plain expert forward per step ------------------------------------------


def _attention(attn, x, context, mask=None):
    n, s, w = x.shape
    split = lambda t: t.view(n, -1, attn.heads, w // attn.heads).transpose(1, 2)  # noqa: E731
    out = F.scaled_dot_product_attention(split(attn.q_proj(x)), split(attn.k_proj(context)),
                                         split(attn.v_proj(context)), attn_mask=mask)
    return attn.o_proj(out.transpose(1, 2).reshape(n, s, w))


def _expert(expert, x, t, context, context_mask, extra):
    half = expert.width // 2
    freqs = torch.exp(-math.log(1000.0) * torch.arange(half) / half)
    angles = 100.0 * t.float().unsqueeze(-1) * freqs
    temb = expert.time_out(F.silu(expert.time_in(torch.cat([angles.sin(), angles.cos()], -1))))
    c = x.shape[1]
    h = expert.action_in(x) + expert.positions[:c] + temb.unsqueeze(1)
    if extra is not None:
        h = torch.cat([extra, h], 1)
    mask = context_mask[:, None, None, :]
    for blk in expert.blocks:
        y = blk.norm1(h)
        h = h + _attention(blk.self_attn, y, y)
        h = h + _attention(blk.cross_attn, blk.norm2(h), context, mask)
        h = h + blk.fc2(F.gelu(blk.fc1(blk.norm3(h))))
    return expert.norm(h)[:, -c:]


def _logpdf(x, mu, sigma):
    return -0.5 * ((x - mu) / sigma).square() - sigma.log() - 0.5 * math.log(2 * math.pi)


@torch.no_grad()
def reference_sample(policy, obs, deterministic, generator):
    bb, ex = policy.backbone, policy.expert
    embeds, mask = bb.prefix(obs)
    context = ex.context(bb.run(embeds, mask))
    extra = policy.proprio_in(obs["proprio"].float()).unsqueeze(1)
    b, K = context.shape[0], policy.steps
    shape = (b, policy.chunk, policy.action_dim)
    x = torch.zeros(shape) if deterministic else torch.randn(shape, generator=generator)
    sde = policy.method == "sde"
    drawn = sde and not deterministic
    j = torch.randint(0, K, (b,), generator=generator) if drawn else torch.zeros(b, dtype=torch.long)
    chain, logprob = [x], torch.zeros(b)
    for k in range(K):
        h = _expert(ex, x, torch.full((b,), k) / K, context, mask, extra)
        mu = x + ex.velocity_out(h) / K
        sigma = policy.sigma_min + (policy.sigma_max - policy.sigma_min) * torch.sigmoid(policy.noise_head(h))
        if not deterministic:
            stochastic = torch.ones(b) if not sde else (j == k).float()
            x = mu + sigma * torch.randn(shape, generator=generator) * stochastic.view(b, 1, 1)
        else:
            x = mu
        lp = _logpdf(x, mu, sigma).sum((1, 2))
        logprob += torch.where(j == k, lp, torch.zeros_like(lp)) if sde else lp
        chain.append(x)
    action = policy.low + (x.reshape(b, -1) + 1.0) * 0.5 * (policy.high - policy.low)
    return action, logprob, torch.stack(chain, 1).reshape(b, K + 1, ACT_DIM), j


# --- the tests ---------------------------------------------------------------------------------


@pytest.mark.parametrize("method", ["noise", "sde"])
@pytest.mark.parametrize("deterministic", [False, True])
@pytest.mark.parametrize("lora", [None, {"r": 4}])
def test_loop_gives_the_reference_actions_logprobs_and_chain(ckpt, method, deterministic, lora):
    torch.set_num_threads(1)
    policy = FlowVLA(SPEC, ACT_DIM, checkpoint=str(ckpt), method=method, lora=lora)
    if lora:  # adapters start at zero (B = 0): move them so the test sees them
        with torch.no_grad():
            for name, p in policy.named_parameters():
                if "lora_B" in name:
                    p.copy_(torch.randn(p.shape, generator=torch.Generator().manual_seed(len(name))) * 0.1)
    obs = obs_batch(policy)
    action, logprob, extras = policy.sample(obs, deterministic, generator=torch.Generator().manual_seed(7))
    ref_action, ref_logprob, ref_chain, ref_j = reference_sample(policy, obs, deterministic,
                                                                 torch.Generator().manual_seed(7))
    torch.testing.assert_close(extras["chain"], ref_chain, **TIGHT)
    torch.testing.assert_close(action, ref_action, **TIGHT)
    torch.testing.assert_close(logprob, ref_logprob, **TIGHT)
    if method == "sde":
        assert torch.equal(extras["denoise_index"].view(-1).long(), ref_j)
    if not deterministic:  # a different seed moves the chain: the comparison above is not vacuous
        other = policy.sample(obs, deterministic, generator=torch.Generator().manual_seed(8))[2]["chain"]
        assert (other - ref_chain).abs().max() > 1e-2
    # the learner's replay of the chain (B * K rows, or the B stochastic steps) gives the same log-prob
    torch.testing.assert_close(policy.evaluate(obs, action, extras)[0], logprob, atol=1e-4, rtol=0)
    # a batch of one gives its row of the batch of three (no cross-row leakage in the cached context)
    one = {k: v[1:2] for k, v in obs.items()}
    torch.testing.assert_close(policy.evaluate(one, action[1:2], {k: v[1:2] for k, v in extras.items()})[0],
                               logprob[1:2], atol=1e-4, rtol=0)


def _op_counts(fn) -> collections.Counter:
    from torch.utils._python_dispatch import TorchDispatchMode

    class Count(TorchDispatchMode):
        seen: collections.Counter = collections.Counter()

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            Count.seen[func.__name__.split(".")[0]] += 1
            return func(*args, **(kwargs or {}))

    with Count():
        fn()
    return Count.seen


@pytest.mark.parametrize("method", ["noise", "sde"])
def test_a_denoising_step_is_only_the_experts_work_on_x(ckpt, method):
    """One more step costs the matrix products of the expert on x and nothing the K steps share
    (the context's keys and values, the time embedding); no call reads a tensor on the host."""
    torch.set_num_threads(1)
    counts = {}
    for K in (4, 5):
        policy = FlowVLA(SPEC, ACT_DIM, checkpoint=str(ckpt), method=method, denoise_steps=K)
        obs = obs_batch(policy)
        counts[K] = _op_counts(lambda: policy.sample(obs, generator=torch.Generator().manual_seed(0)))
        assert counts[K]["_local_scalar_dense"] == 0  # .item(), bool(tensor), float(tensor)
    step = counts[5] - counts[4]
    # per block: self-attention q, k, v, o; cross-attention q, o; the MLP's two; then action_in,
    # velocity_out and the noise head
    assert step["addmm"] + step["mm"] == 8 * len(policy.expert.blocks) + 3, step
    assert step["sin"] == step["cos"] == step["silu"] == 0, step
