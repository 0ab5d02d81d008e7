"""scene.wall_basis: Gaussians of where a free step takes each particle, against a loop over
particles, walls and centres, a hand-made landing, its place among the simulator's inputs, bad
values named, and a checkpoint round trip."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from gns.checkpoints import simulator_from_checkpoint
from gns.config import Config, ModelConfig, SceneConfig, to_dict
from gns.simulator import LearnedSimulator, Scene, wall_basis

pytestmark = pytest.mark.usefixtures("torch_one_thread")

TINY = ModelConfig(latent_size=16, mlp_hidden_size=16, message_passing_steps=2)
R, G = 0.02, 9.81 * 0.0075**2


def by_loop(x, bounds, axes, radius, k):
    """The definition, one particle, wall and centre at a time."""
    rows = []
    for p in x:
        row = []
        for side in (0, 1):
            for a in axes:
                d = (p[a] - bounds[a][0]) if side == 0 else (bounds[a][1] - p[a])
                row += [math.exp(-0.5 * ((d / radius - c) / 0.5) ** 2) for c in range(k)]
        rows.append(row)
    return np.array(rows)


@pytest.mark.parametrize(("dim", "axes"), [(2, (0, 1)), (3, (0, 1, 2)), (2, (1,))])
def test_the_basis_matches_the_definition(dim, axes):
    rng = np.random.default_rng(dim)
    x = rng.uniform(-0.05, 1.05, (30, dim))  # some beyond the walls: negative distances
    bounds = [(0.0, 1.0)] * dim
    got = wall_basis(torch.tensor(x), bounds, axes, R, 4)
    np.testing.assert_allclose(got.numpy(), by_loop(x, bounds, axes, R, 4), rtol=1e-12)


def scene(**changes):
    base = dict(
        dim=2, radius=R, particle_types=(6,), bounds=((0.0, 1.0), (0.0, 1.0)), walls=True,
        gravity=(0.0, -G), wall_basis=4,
    )  # fmt: skip
    return Scene(**{**base, **changes})


def falling(x, y, speed, frames=6):
    """One particle in free fall at (x, y) in the last of `frames`, `speed` a step downward
    there: (1, frames, 2)."""
    k = np.arange(-(frames - 1), 1)
    ys = y - speed * k - 0.5 * G * k * (k + 1)
    return torch.tensor(np.stack([np.full(frames, x), ys], axis=1)[None])


def test_a_free_step_to_one_radius_above_the_floor_reads_the_second_gaussian():
    """Where the next free step (last velocity plus gravity) ends 1 R above the floor, the floor's
    Gaussians read exp(-2), 1, exp(-2), exp(-8): the distance now (3 R) is not what counts."""
    sim = LearnedSimulator(scene(), Config(model=TINY))
    plain = LearnedSimulator(scene(wall_basis=0), Config(model=TINY))
    assert sim.node_input_size == plain.node_input_size + 4 * 4
    speed = 2 * R - G  # from 3 R above the floor to 1 R in one free step
    history = falling(0.5, 3 * R, speed)
    features = sim.features(history, torch.tensor([6]))["node_features"][0]
    assert torch.equal(
        features[: plain.node_input_size],
        plain.features(history, torch.tensor([6]))["node_features"][0],
    )
    # Columns: left, floor, right, ceiling walls, 4 Gaussians each.
    floor = features[plain.node_input_size + 4 : plain.node_input_size + 8]
    expected = [math.exp(-2), 1.0, math.exp(-2), math.exp(-8)]
    np.testing.assert_allclose(floor.double().numpy(), expected, rtol=1e-5, atol=1e-6)
    # The same particle at rest 3 R up reads its own height: the third Gaussian.
    resting = falling(0.5, 3 * R, 0.0)
    resting[:, :, 1] = 3 * R
    at_rest = sim.features(resting, torch.tensor([6]))["node_features"][0]
    floor = at_rest[plain.node_input_size + 4 : plain.node_input_size + 8]
    assert int(torch.argmax(floor)) == 3  # 3 R less gravity's 0.03 R
    # The scene's bounds are what it reads (the floor probe moves them): a floor 1 R higher.
    sim.scene = dataclasses.replace(sim.scene, bounds=((0.0, 1.0), (R, 1.0)))
    higher = sim.features(resting, torch.tensor([6]))["node_features"][0]
    assert int(torch.argmax(higher[plain.node_input_size + 4 : plain.node_input_size + 8])) == 2


def test_bad_values_are_named():
    with pytest.raises(ValueError, match="wall_basis must be an integer >= 0, got -1"):
        SceneConfig(wall_basis=-1)
    with pytest.raises(ValueError, match="got 2.5"):
        SceneConfig(wall_basis=2.5)
    with pytest.raises(ValueError, match="got True"):
        SceneConfig(wall_basis=True)
    with pytest.raises(ValueError, match="wall_basis = 3 needs walls = true"):
        SceneConfig(wall_basis=3, walls=False)
    with pytest.raises(ValueError, match="wall_basis = 2 needs walls"):
        scene(walls=False, wall_basis=2)


def test_the_basis_survives_a_checkpoint():
    sim = LearnedSimulator(scene(), Config(model=TINY))
    state = {"scene": dataclasses.asdict(sim.scene), "config": to_dict(Config(model=TINY))}
    state.update(statistics=None, model=sim.state_dict())
    loaded = simulator_from_checkpoint(state)
    assert loaded.scene.wall_basis == 4
    history = falling(0.3, 5 * R, R)
    types = torch.tensor([6])
    torch.testing.assert_close(
        loaded.features(history, types)["node_features"],
        sim.features(history, types)["node_features"],
    )
