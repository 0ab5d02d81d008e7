"""The overburden feature (gns.overburden): the column above each particle, against a double
loop over all pairs, hand-made columns, and its place among the simulator's inputs."""

from __future__ import annotations

import dataclasses

import gns.overburden
import pytest
import torch
from gns.checkpoints import simulator_from_checkpoint
from gns.config import Config, ModelConfig, NormalizationConfig, SceneConfig, to_dict
from gns.overburden import overburden
from gns.simulator import LearnedSimulator, Scene

pytestmark = pytest.mark.usefixtures("torch_one_thread")

TINY = ModelConfig(latent_size=16, mlp_hidden_size=16, message_passing_steps=2)


def every_pair(position, velocity, up, half_width, free, n_node):
    """The definition, pair by pair: j above i along up, laterally closer than half_width,
    free, in i's graph."""
    up = up / up.norm()
    graph = torch.repeat_interleave(torch.arange(len(n_node)), n_node)
    out = torch.zeros(len(position), 2, dtype=position.dtype)
    for i in range(len(position)):
        for j in range(len(position)):
            d = position[j] - position[i]
            height = d @ up
            beside = (d - height * up).norm()
            if graph[i] == graph[j] and height > 0 and beside < half_width and free[j]:
                out[i, 0] += 1
                out[i, 1] += velocity[j] @ up
    return out


@pytest.mark.parametrize("chunk", [None, 50])
@pytest.mark.parametrize("dim", [2, 3])
def test_the_column_above_matches_every_pair(dim, chunk, monkeypatch):
    if chunk:  # the candidate pairs taken a few rows at a time
        monkeypatch.setattr(gns.overburden, "_PAIRS", chunk)
    g = torch.Generator().manual_seed(0)
    n_node = torch.tensor([90, 70])
    # Both graphs in the same place: only n_node keeps their columns apart.
    position = torch.rand(160, dim, generator=g, dtype=torch.float64)
    velocity = torch.randn(160, dim, generator=g, dtype=torch.float64)
    up = torch.randn(dim, generator=g, dtype=torch.float64)  # any direction, any length
    free = torch.rand(160, generator=g) > 0.2
    got = overburden(position, velocity, up, 0.15, free, n_node)
    want = every_pair(position, velocity, up, 0.15, free, n_node)
    assert want[:, 0].max() >= 5  # columns with something in them
    torch.testing.assert_close(got, want)


def test_a_stack_by_hand():
    # A stack of 5 free particles (one 0.1 off the axis), a kinematic one on top, one beside.
    position = torch.tensor([[0, 0], [0, 1], [0.1, 2], [0, 3], [0, 4], [0, 5], [1, 0.4]])
    velocity = torch.tensor([[0.0, -1.0], [0, -1], [0, -2], [0, -1], [0, -3], [0, -9], [0, -1]])
    free = torch.tensor([True, True, True, True, True, False, True])
    got = overburden(position, velocity, torch.tensor([0.0, 9.81]), 0.5, free)
    # Up is the given vector's direction: the sum of the velocities above along it.
    assert got[:, 0].tolist() == [4, 3, 2, 1, 0, 0, 0]
    assert got[:, 1].tolist() == [-7, -6, -4, -3, 0, 0, 0]
    # With gravity along -x, "above" is to the right: only the lone particle at x = 1 sees
    # nothing there; particle 0 has 1 above it within 0.5 of its line (the one at (1, 0.4)).
    side = overburden(position, velocity, torch.tensor([1.0, 0.0]), 0.5, free)
    assert side[0, 0] == 1 and side[6, 0] == 0


def test_bad_arguments_are_named():
    x, free = torch.zeros(3, 2), torch.ones(3, dtype=torch.bool)
    with pytest.raises(ValueError, match="half_width must be positive, got 0"):
        overburden(x, x, torch.tensor([0.0, 1.0]), 0.0, free)
    with pytest.raises(ValueError, match="nonzero up"):
        overburden(x, x, torch.zeros(2), 0.1, free)
    with pytest.raises(ValueError, match="n_node sums to 4 but there are 3"):
        overburden(x, x, torch.tensor([0.0, 1.0]), 0.1, free, torch.tensor([2, 2]))
    with pytest.raises(ValueError, match=r"up \(D,\)"):
        overburden(x, x, torch.ones(3), 0.1, free)


def sand_scene(**changes):
    base = dict(
        dim=2, radius=0.03, particle_types=(6,), bounds=((0.0, 1.0), (0.0, 1.0)), walls=True,
        gravity=(0.0, -9.81 * 0.0075**2), overburden=True,
    )  # fmt: skip
    return Scene(**{**base, **changes})


def test_the_scene_needs_gravity_and_no_periodic_axis():
    with pytest.raises(ValueError, match="overburden needs the scene's gravity"):
        sand_scene(gravity=None)
    with pytest.raises(ValueError, match="no periodic axis"):
        sand_scene(periodic=(True, False))
    cfg = Config(model=TINY, normalization=NormalizationConfig(source="metadata"))
    with pytest.raises(ValueError, match="overburden needs normalization.source = 'running'"):
        LearnedSimulator(sand_scene(), cfg)
    assert SceneConfig(overburden=True).overburden


def block(width, height, spacing=0.01, steps=7):
    """A block of sand at rest on the floor, centred at x = 0.5: (N, steps, 2) and its types."""
    xs = torch.arange(0.5 - width / 2, 0.5 + width / 2, spacing)
    ys = torch.arange(spacing / 2, height, spacing)
    grid = torch.cartesian_prod(xs, ys)
    return grid[:, None, :].expand(-1, steps, -1).clone(), torch.full((len(grid),), 6)


def test_the_base_of_a_taller_block_reads_more_weight():
    """Two more inputs; a training step gives them running statistics; the base of a block
    reads the rows above it (raw), so a taller block's a larger normalised input; and the flag
    and the statistics survive a checkpoint."""
    cfg = Config(model=TINY)
    plain = LearnedSimulator(sand_scene(overburden=False), cfg)
    sim = LearnedSimulator(sand_scene(), cfg)
    assert sim.node_input_size == plain.node_input_size + 2

    low, types = block(0.2, 0.1)
    high, high_types = block(0.2, 0.3)
    sim.train()
    positions = torch.cat([low, high])
    noise = torch.zeros_like(positions[:, :-1])
    n_node = torch.tensor([len(low), len(high)])
    both = torch.cat([types, high_types])
    sim.predict_accelerations(positions[:, -1], positions[:, :-1], noise, both, n_node)
    assert sim.overburden_normalizer.count.item() == len(positions)

    def base_input(x, t):
        features = sim.features(x[:, :-1], t)["node_features"]
        bottom_middle = torch.argmin((x[:, -1, 0] - 0.5).abs() + x[:, -1, 1])
        return sim._overburden(x[:, :-1], t, None)[bottom_middle], features[bottom_middle]

    raw_low, f_low = base_input(low, types)
    raw_high, f_high = base_input(high, high_types)
    # The column is R = 0.03 wide: 3 columns of the grid, 9 and 29 rows above.
    assert raw_low[0] == 3 * 9 and raw_high[0] == 3 * 29
    assert raw_low[1] == raw_high[1] == 0  # at rest
    column = 5 * 2 + 4  # velocities, walls, then the overburden's two
    assert f_high[column] > f_low[column]

    state = {"scene": dataclasses.asdict(sim.scene), "config": to_dict(cfg)}
    state.update(statistics=None, model=sim.state_dict())
    loaded = simulator_from_checkpoint(state)
    assert loaded.scene.overburden
    torch.testing.assert_close(
        loaded.features(high[:, :-1], high_types)["node_features"],
        sim.features(high[:, :-1], high_types)["node_features"],
    )
