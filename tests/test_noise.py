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
from gns.noise import (
    NOISE_FUNCTIONS,
    correlated,
    only_last,
    random_walk,
    sample_noise,
    wall_push,
)

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


def test_wall_push_moves_only_particles_at_a_wall_into_it():
    """|N(0, std R)| into the nearest wall for free particles within R of it; nothing
    elsewhere, on kinematic particles or along an axis without walls."""
    radius, std = 0.05, 0.5
    g = torch.Generator().manual_seed(7)
    x = torch.rand(N, 2, generator=g, dtype=torch.float64)
    bounds = torch.tensor([[0.0, 1.0], [0.0, 1.0]], dtype=torch.float64)
    kinematic = torch.arange(N) % 10 == 0
    shift = wall_push(x, bounds, (1,), radius, std, kinematic=kinematic, generator=g)
    low, high = x[:, 1] < radius, x[:, 1] > 1 - radius
    free = ~kinematic
    assert (shift[:, 0] == 0).all()  # axis 0 has no walls here
    assert (shift[~(low | high) | kinematic] == 0).all()
    assert (shift[low & free, 1] <= 0).all() and (shift[high & free, 1] >= 0).all()
    depth = shift[(low | high) & free, 1].abs()
    assert depth.numel() > 1000
    # The mean of |N(0, s)| is s sqrt(2 / pi); its standard error s sqrt(1 - 2 / pi) / sqrt(n).
    s = std * radius
    error = abs(depth.mean().item() - s * math.sqrt(2 / math.pi))
    assert error < 5 * s * math.sqrt(1 - 2 / math.pi) / math.sqrt(depth.numel())


def test_wall_push_through_only_moves_only_particles_it_takes_past_the_wall():
    """With through_only, a particle at gap g from a wall is shifted with probability
    P(|N(0, s)| > g) = 2 (1 - Phi(g / s)), always past the wall; the rest keep their place."""
    radius, std = 0.05, 0.5
    s = std * radius
    g = torch.Generator().manual_seed(11)
    gap = torch.tensor([0.25 * s, s, 2 * s, 2 * radius], dtype=torch.float64).repeat(N // 4)
    x = torch.stack([torch.full_like(gap, 0.5), gap], dim=1)  # above the floor at y = 0
    bounds = torch.tensor([[0.0, 1.0], [0.0, 1.0]], dtype=torch.float64)
    shift = wall_push(x, bounds, (1,), radius, std, through_only=True, generator=g)
    moved = shift[:, 1] != 0
    assert (shift[:, 0] == 0).all()
    assert (x[moved, 1] + shift[moved, 1] < 0).all()  # every shifted particle ends in the floor
    n = N // 4
    for k, ratio in enumerate((0.25, 1.0, 2.0, 2 * radius / s)):
        expected = math.erfc(ratio / math.sqrt(2))  # 2 (1 - Phi(ratio))
        fraction = moved[k::4].double().mean().item()
        assert abs(fraction - expected) <= 5 * math.sqrt(expected * (1 - expected) / n) + 1e-12


def test_the_simulator_passes_through_only_on():
    """noise.wall_push_through_only reaches the shift: a particle half a radius above the
    floor is shifted by wall_push 0.1 alone, not with through_only (5 sigma away)."""
    from gns.config import Config, ModelConfig
    from gns.simulator import LearnedSimulator, Scene

    scene = Scene(dim=2, radius=0.05, particle_types=(5,), bounds=((0, 1), (0, 1)), walls=True)
    model = ModelConfig(latent_size=8, mlp_hidden_size=8, message_passing_steps=1)
    seq = torch.tensor([[0.5, 0.025]], dtype=torch.float64)[:, None].repeat(1, C + 1, 1)
    for through_only, moved in ((False, True), (True, False)):
        noise = NoiseConfig(std=0.0, wall_push=0.1, wall_push_through_only=through_only)
        simulator = LearnedSimulator(scene, Config(model=model, noise=noise)).double()
        shift = simulator.sample_wall_push(seq, torch.tensor([5]), torch.Generator().manual_seed(0))
        assert shift is not None and bool(shift[0, 1] != 0) is moved


def test_the_target_of_a_pushed_particle_is_the_true_next_position(monkeypatch):
    """Through the training step: the input moves into the floor by s, the target acceleration
    pushes it back by s (the clean one minus s), whatever correct_position_fraction keeps."""
    from gns.config import Config, ModelConfig
    from gns.simulator import LearnedSimulator, Scene
    from gns.train import TrainingStep

    scene = Scene(dim=2, radius=0.05, particle_types=(5,), bounds=((0, 1), (0, 1)), walls=True)
    model = ModelConfig(latent_size=8, mlp_hidden_size=8, message_passing_steps=1)
    noise = NoiseConfig(std=0.0, correct_position_fraction=0.1, wall_push=1.0)
    simulator = LearnedSimulator(scene, Config(model=model, noise=noise)).double()
    x = torch.tensor([[0.5, 0.02], [0.5, 0.5]], dtype=torch.float64)
    seq = x[:, None].repeat(1, C + 1, 1)
    seq[:, :, 0] += 1e-3 * torch.arange(C + 1)  # moving along x at 1e-3 a frame
    truth = seq[:, -1] + torch.tensor([1e-3, -2e-4], dtype=torch.float64)
    g = torch.Generator().manual_seed(0)
    shift = simulator.sample_wall_push(seq, torch.tensor([5, 5]), g)
    assert shift is not None and shift[0, 1] < 0 and (shift[1] == 0).all()
    seen = {}

    def spy(next_position, position_sequence, position_sequence_noise, *args, **kwargs):
        keep = 1 - noise.correct_position_fraction
        noisy = position_sequence + position_sequence_noise
        seen["acceleration"] = (
            next_position + keep * position_sequence_noise[:, -1] - 2 * noisy[:, -1] + noisy[:, -2]
        )
        return torch.zeros(2, 2), torch.zeros(2, 2)

    monkeypatch.setattr(simulator, "predict_accelerations", spy)
    zero = torch.zeros_like(seq)
    TrainingStep(simulator)(seq, truth, zero, torch.tensor([5, 5]), wall_shift=shift)
    clean = truth - 2 * seq[:, -1] + seq[:, -2]
    torch.testing.assert_close(seen["acceleration"], clean - shift)


@pytest.mark.parametrize("kind", sorted(NOISE_FUNCTIONS))
def test_exact_last_position_keeps_the_velocity_noise_and_clears_the_last_position(kind):
    """The same draw with and without noise.exact_last_position: identical velocity noise,
    none on the most recent position, none at all on kinematic particles."""
    kinematic = torch.zeros(2000, dtype=torch.bool)
    kinematic[::4] = True
    x = sequence(n=2000, dtype=torch.float64)
    drawn = {}
    for exact in (False, True):
        config = NoiseConfig(type=kind, std=SIGMA, exact_last_position=exact)
        g = torch.Generator().manual_seed(10)
        drawn[exact] = sample_noise(config, x, kinematic=kinematic, generator=g)
    torch.testing.assert_close(
        velocity_noise(drawn[True]), velocity_noise(drawn[False]), rtol=0, atol=1e-15
    )
    assert torch.count_nonzero(drawn[True][:, -1]) == 0
    assert torch.count_nonzero(drawn[True][kinematic]) == 0
    assert_std(velocity_noise(drawn[True])[~kinematic][:, -1], SIGMA)


def test_std_min_gives_each_window_its_own_std_between_std_min_and_std():
    """400 windows of 50 particles: each window's noise is the fixed-std draw scaled by one
    factor, its measured std within [std_min, std] up to sampling error, and the factors
    spread uniformly over that range (Kolmogorov-Smirnov against scipy's uniform)."""
    from scipy import stats

    n_node = torch.full((400,), 50)
    x = sequence(n=20000, dtype=torch.float64)
    fixed = sample_noise(NoiseConfig(std=1e-3), x, generator=torch.Generator().manual_seed(3))
    config = NoiseConfig(std=1e-3, std_min=2e-4)
    mixed = sample_noise(config, x, n_node=n_node, generator=torch.Generator().manual_seed(3))
    ratio = (mixed[:, 1:] / fixed[:, 1:]).reshape(400, -1)  # the walk starts at 0
    scale = ratio[:, :1]
    torch.testing.assert_close(ratio, scale.expand_as(ratio), rtol=1e-12, atol=0)
    last = velocity_noise(mixed)[:, -1].reshape(400, -1)  # 100 values a window
    std = last.pow(2).mean(dim=1).sqrt()
    assert torch.all(std > 2e-4 * 0.7) and torch.all(std < 1e-3 * 1.3), std
    assert stats.kstest(1e-3 * scale.flatten().numpy(), stats.uniform(2e-4, 8e-4).cdf).pvalue > 1e-3
    # One window without n_node; n_node that miscounts the particles is refused.
    one = sample_noise(config, x[:50], generator=torch.Generator().manual_seed(3))
    alone = sample_noise(NoiseConfig(std=1e-3), x[:50], generator=torch.Generator().manual_seed(3))
    assert torch.unique((one[:, 1:] / alone[:, 1:]).round(decimals=9)).numel() == 1
    with pytest.raises(ValueError, match="n_node sums to 500, not the 20000 particles"):
        sample_noise(config, x, n_node=torch.full((10,), 50))
    with pytest.raises(ValueError, match="std_min must be in \\[0, std = 0.001\\], got 0.002"):
        NoiseConfig(std=1e-3, std_min=2e-3)


@pytest.mark.parametrize("fraction", [0.0, 0.1, 1.0])
def test_with_an_exact_last_position_the_target_is_the_true_next_step(fraction):
    """The target acceleration, applied to the noisy input by the Euler update, lands on the
    true next position whatever correct_position_fraction says: all the velocity noise is
    taken back (checked against the update written out, not the simulator's inverse)."""
    from gns.config import Config, ModelConfig
    from gns.simulator import LearnedSimulator, Scene

    scene = Scene(dim=2, radius=0.05, particle_types=(5,), bounds=((0, 1), (0, 1)))
    model = ModelConfig(latent_size=8, mlp_hidden_size=8, message_passing_steps=1)
    config = NoiseConfig(std=1e-3, correct_position_fraction=fraction, exact_last_position=True)
    simulator = LearnedSimulator(scene, Config(model=model, noise=config)).double()
    seq = sequence(n=50, dtype=torch.float64)
    truth = seq[:, -1] + (seq[:, -1] - seq[:, -2]) + 1e-4
    noise = simulator.sample_noise(seq, torch.full((50,), 5), torch.Generator().manual_seed(11))
    noisy = seq + noise
    assert torch.count_nonzero(noise[:, -2]) > 0
    target = simulator.target_normalized_acceleration(truth, noisy, noise)
    acceleration = simulator.acceleration_normalizer.inverse(target)
    reached = noisy[:, -1] + (noisy[:, -1] - noisy[:, -2]) + acceleration
    torch.testing.assert_close(reached, truth, rtol=0, atol=1e-12)
