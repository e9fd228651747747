"""The rollout's sampling noise: reproducible per (process seed, env group, step), independent
across all three (torch's CPU generator keeps only a seed's low 32 bits)."""

import torch

from dvla.roles.rollout import noise_seed


def draw(seed: int, group: int, step: int, device: str = "cpu") -> torch.Tensor:
    g = torch.Generator(device=device)
    g.manual_seed(noise_seed(seed, group, step))
    return torch.randn(4, 8, generator=g, device=device)


def test_same_inputs_same_noise():
    assert torch.equal(draw(2001, 1, 37), draw(2001, 1, 37))


def test_groups_rollouts_and_runs_draw_different_noise_at_the_same_step():
    # rollouts of one run (process seeds 2000 + index), their two env groups, other runs' seeds
    keys = [(s, g, 37) for s in (1000, 1001, 2000, 2001, 5003) for g in (0, 1)]
    draws = [draw(*k) for k in keys]
    for i in range(len(keys)):
        for j in range(i + 1, len(keys)):
            assert not torch.allclose(draws[i], draws[j]), (keys[i], keys[j])


def test_steps_draw_different_noise():
    assert not torch.allclose(draw(2001, 0, 10), draw(2001, 0, 11))


def test_seed_uses_the_low_32_bits():
    # what the CPU generator keeps must differ wherever any input differs
    low = {noise_seed(s, g, t) % 2**32 for s in range(4) for g in range(2) for t in range(64)}
    assert len(low) == 4 * 2 * 64


def test_negative_seed_is_accepted():
    assert draw(-3, 0, 1).shape == (4, 8)
