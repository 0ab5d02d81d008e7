"""The noise types of C.2: statistics, structure, and kinematic particles left alone.

Statistical tolerances come from the sample size: the sample std of n normal values has a
standard error of about sigma / sqrt(2 n), a sample correlation one of about 1 / sqrt(n); we
allow 5 standard errors (a false failure about once in 3.5 million runs; the seeds are fixed).
"""

from __future__ import annotations

import math

import pytest
import torch
from gns.config import NoiseConfig
from gns.noise import NOISE_FUNCTIONS, correlated, only_last, random_walk, sample_noise

N, C, D = 20_000, 5, 2
SIGMA = 3e-4


def sequence(n=N, c=C, d=D, dtype=torch.float32):
    g = torch.Generator().manual_seed(123)
    start = torch.rand(n, 1, d, generator=g, dtype=dtype)
    return start + 1e-3 * torch.randn(n, c + 1, d, generator=g, dtype=dtype).cumsum(1)


def velocity_noise(position_noise):
    return (position_noise[:, 1:] - position_noise[:, :-1]).double()


def assert_std(samples, sigma):
    n = samples.numel()
    std = samples.double().pow(2).mean().sqrt().item()  # the noise has mean zero
    assert abs(std - sigma) < 5 * sigma / math.sqrt(2 * n), (std, sigma, n)


def assert_uncorrelated(a, b):
    a, b = a.reshape(-1).double(), b.reshape(-1).double()
    r = torch.corrcoef(torch.stack([a, b]))[0, 1].item()
    assert abs(r) < 5 / math.sqrt(a.numel()), r


@pytest.mark.parametrize("kind", sorted(NOISE_FUNCTIONS))
def test_every_type_has_the_configured_std_at_the_last_velocity(kind):
    g = torch.Generator().manual_seed(1)
    noise = NOISE_FUNCTIONS[kind](sequence(), SIGMA, generator=g)
    assert noise.shape == (N, C + 1, D) and noise.dtype == torch.float32
    assert_std(velocity_noise(noise)[:, -1], SIGMA)
    # Positions are adjusted from velocities: the oldest position is left as it is.
    assert torch.count_nonzero(noise[:, 0]) == 0


def test_random_walk_is_a_random_walk_of_velocity_increments():
    g = torch.Generator().manual_seed(2)
    v = velocity_noise(random_walk(sequence(), SIGMA, generator=g))
    increments = torch.cat([v[:, :1], v[:, 1:] - v[:, :-1]], dim=1)  # (N, C, D)
    for k in range(C):
        assert_std(increments[:, k], SIGMA / math.sqrt(C))
        # The walk's std grows as sqrt(step): sigma * sqrt((k + 1) / C).
        assert_std(v[:, k], SIGMA * math.sqrt((k + 1) / C))
    for k in range(C - 1):
        assert_uncorrelated(increments[:, k], increments[:, k + 1])


def test_uncorrelated_noise_is_independent_per_step():
    g = torch.Generator().manual_seed(3)
    v = velocity_noise(NOISE_FUNCTIONS["uncorrelated"](sequence(), SIGMA, generator=g))
    for k in range(C):
        assert_std(v[:, k], SIGMA)
    for k in range(C - 1):
        assert_uncorrelated(v[:, k], v[:, k + 1])


def test_correlated_noise_is_the_same_on_every_velocity():
    g = torch.Generator().manual_seed(4)
    noise = correlated(sequence(n=500, dtype=torch.float64), SIGMA, generator=g)
    v = velocity_noise(noise)
    torch.testing.assert_close(v, v[:, :1].expand_as(v), rtol=0, atol=1e-18)
    # Hence the position noise grows linearly: k times the velocity noise.
    steps = torch.arange(C + 1, dtype=torch.float64)[None, :, None]
    torch.testing.assert_close(noise, steps * v[:, :1], rtol=1e-12, atol=1e-18)


def test_only_last_moves_only_the_most_recent_position():
    g = torch.Generator().manual_seed(5)
    noise = only_last(sequence(n=500), SIGMA, generator=g)
    assert torch.count_nonzero(noise[:, :-1]) == 0
    assert torch.count_nonzero(noise[:, -1]) == noise[:, -1].numel()


@pytest.mark.parametrize("kind", sorted(NOISE_FUNCTIONS))
def test_kinematic_particles_get_no_noise(kind):
    g = torch.Generator().manual_seed(6)
    kinematic = torch.zeros(1000, dtype=torch.bool)
    kinematic[::3] = True
    noise = NOISE_FUNCTIONS[kind](sequence(n=1000), SIGMA, kinematic=kinematic, generator=g)
    assert torch.count_nonzero(noise[kinematic]) == 0
    assert torch.count_nonzero(noise[~kinematic][:, -1]) == noise[~kinematic][:, -1].numel()


def test_noise_is_reproducible_from_the_generator_and_follows_the_dtype():
    x = sequence(n=100, dtype=torch.float64)
    a = random_walk(x, generator=torch.Generator().manual_seed(7))
    b = random_walk(x, generator=torch.Generator().manual_seed(7))
    c = random_walk(x, generator=torch.Generator().manual_seed(8))
    assert torch.equal(a, b) and not torch.equal(a, c)
    assert a.dtype == torch.float64


def test_sample_noise_dispatches_on_the_config():
    g = torch.Generator().manual_seed(9)
    noise = sample_noise(NoiseConfig(type="only_last", std=1e-3), sequence(), generator=g)
    assert torch.count_nonzero(noise[:, :-1]) == 0
    assert_std(velocity_noise(noise)[:, -1], 1e-3)
    silent = sample_noise(NoiseConfig(std=0.0), sequence(n=10))
    assert torch.count_nonzero(silent) == 0


def test_a_sequence_without_velocities_is_rejected():
    with pytest.raises(ValueError, match="C >= 1"):
        random_walk(torch.zeros(4, 1, 2))
