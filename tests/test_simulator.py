"""LearnedSimulator: features from the scene, the Euler postprocess and its inverse, training
targets, kinematic particles, periodic boxes, and a short overfit on the real sand data."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from gns import euler_step
from gns.config import Config, ModelConfig, NoiseConfig, NormalizationConfig, SceneConfig
from gns.data import Metadata, open_dataset, trajectory_windows
from gns.simulator import LearnedSimulator, Scene

SAND = Path(__file__).resolve().parents[2] / "shared/data/sand2d-taichi"
TINY = ModelConfig(latent_size=16, mlp_hidden_size=16, message_passing_steps=2)
BOX = ((0.1, 0.9), (0.1, 0.9))
EPS32 = float(np.finfo(np.float32).eps)


pytestmark = pytest.mark.usefixtures("torch_one_thread")


def config(**model):
    return Config(model=ModelConfig(**{**TINY.__dict__, **model}))


def scene(**changes):
    base = dict(dim=2, radius=0.1, particle_types=(3, 5, 6), bounds=BOX, walls=True)
    return Scene(**{**base, **changes})


def window(n=60, dim=2, seed=0, steps=6, dtype=torch.float32):
    """(N, steps, D) positions drifting inside the box, and their types (some kinematic)."""
    g = torch.Generator().manual_seed(seed)
    start = 0.15 + 0.7 * torch.rand(n, 1, dim, generator=g, dtype=torch.float64)
    walk = 2e-3 * torch.randn(n, steps, dim, generator=g, dtype=torch.float64).cumsum(1)
    types = torch.tensor([5, 6, 3])[torch.randint(0, 3, (n,), generator=g)]
    return (start + walk).to(dtype), types


def fixed_statistics(dim=2, acc_std=1e-4):
    return Metadata(
        bounds=BOX if dim == 2 else BOX + ((0.1, 0.9),),
        sequence_length=10,
        default_connectivity_radius=0.1,
        dim=dim,
        dt=0.0025,
        vel_mean=(1e-4,) * dim,
        vel_std=(1e-3,) * dim,
        acc_mean=(-2e-5,) * dim,
        acc_std=(acc_std,) * dim,
    )


def metadata_config(noise_std=3e-4, **model):
    return Config(
        model=ModelConfig(**{**TINY.__dict__, **model}),
        noise=NoiseConfig(std=noise_std),
        normalization=NormalizationConfig(source="metadata"),
    )


# ---------------------------------------------------------------------- build what the scene needs


@pytest.mark.parametrize("dim", [2, 3])
def test_input_widths_follow_the_scene(dim):
    bounds = ((0.1, 0.9),) * dim
    c = TINY.velocity_history
    base = LearnedSimulator(Scene(dim=dim, radius=0.1, particle_types=(5,)), config())
    assert base.node_input_size == c * dim and base.edge_input_size == dim + 1
    assert base.particle_type_embedding is None and base.context_normalizer is None
    assert base.model.global_encoder is None

    walls = LearnedSimulator(
        Scene(dim=dim, radius=0.1, particle_types=(5,), bounds=bounds, walls=True), config()
    )
    assert walls.node_input_size == base.node_input_size + 2 * dim

    bounds_only = Scene(dim=dim, radius=0.1, particle_types=(5,), bounds=bounds, walls=False)
    assert LearnedSimulator(bounds_only, config()).node_input_size == base.node_input_size

    types = LearnedSimulator(Scene(dim=dim, radius=0.1, particle_types=(3, 5)), config())
    assert types.particle_type_embedding is not None
    assert types.particle_type_embedding.weight.shape == (2, 16)
    assert types.node_input_size == base.node_input_size + 16

    context = Scene(dim=dim, radius=0.1, particle_types=(5,), context_size=3)
    appended = LearnedSimulator(context, config())
    assert appended.node_input_size == base.node_input_size + 3
    assert appended.model.global_encoder is None
    global_ = LearnedSimulator(context, config(global_latent=True))
    assert global_.node_input_size == base.node_input_size
    assert global_.model.global_encoder[0].in_features == 3

    material = Scene(dim=dim, radius=0.1, particle_types=(5,), material_property_size=1)
    assert LearnedSimulator(material, config()).node_input_size == base.node_input_size + 1


def test_periodic_axes_get_no_wall_features():
    s = scene(periodic=(True, False))
    assert s.wall_axes == (1,)
    assert LearnedSimulator(s, config()).node_input_size == 5 * 2 + 2 + 16


@pytest.mark.skipif(not (SAND / "manifest.json").is_file(), reason="sand2d-taichi not present")
def test_scene_from_the_sand_dataset():
    dataset = open_dataset(SAND, "train")
    s = Scene.from_dataset(dataset)
    assert s.particle_types == (6,) and s.dim == 2 and s.radius == 0.015
    assert s.context_size == 1 and s.material_property_size == 0  # the angle once, not twice
    assert s.wall_axes == (0, 1) and s.kinematic_particle_types == (3,)
    sim = LearnedSimulator(s, config())
    assert sim.node_input_size == 10 + 4 + 1 and sim.particle_type_embedding is None
    both = Scene.from_dataset(dataset, SceneConfig(material_property=True, walls=False))
    assert both.material_property_size == 1 and both.wall_axes == ()
    # Physical gravity becomes per-frame gravity: g dt^2 (README: free fall ~ -6.1e-5).
    fall = Scene.from_metadata(dataset.metadata, (6,), SceneConfig(gravity=(0.0, -9.81)))
    assert fall.gravity == pytest.approx((0.0, -9.81 * 0.0025**2))


# ---------------------------------------------------------------------- features


def test_node_and_edge_features_by_hand():
    positions, types = window(n=80, seed=1, dtype=torch.float64)
    sim = LearnedSimulator(scene(), config()).double()
    f = sim.features(positions, types)
    x = positions.numpy()
    nodes = f["node_features"].detach().numpy()
    # Velocities, per frame, unnormalised before any statistics were gathered.
    np.testing.assert_allclose(nodes[:, :10], np.diff(x, axis=1).reshape(80, 10), rtol=1e-12)
    last = x[:, -1]
    lo, hi = np.array(BOX).T
    walls = np.clip(np.concatenate([last - lo, hi - last], axis=1) / 0.1, -1, 1)
    np.testing.assert_allclose(nodes[:, 10:14], walls, rtol=1e-12)
    embedding = sim.particle_type_embedding.weight.detach().numpy()
    rows = np.searchsorted([3, 5, 6], types.numpy())
    np.testing.assert_allclose(nodes[:, 14:], embedding[rows])

    distance = np.linalg.norm(last[None, :] - last[:, None], axis=-1)  # [receiver, sender]
    want = sorted(zip(*np.nonzero(distance <= 0.1), strict=True))
    senders, receivers = f["senders"].numpy(), f["receivers"].numpy()
    assert list(zip(receivers, senders, strict=True)) == want
    edges = f["edge_features"].numpy()
    np.testing.assert_allclose(edges[:, :2], (last[senders] - last[receivers]) / 0.1, atol=1e-12)
    np.testing.assert_allclose(edges[:, 2], distance[receivers, senders] / 0.1, atol=1e-12)


def test_wall_clip_from_the_config_overrides_the_metadata():
    meta = fixed_statistics()
    assert Scene.from_metadata(meta, (5,)).wall_clip == 1.0  # the paper's clip at R
    wide = Scene.from_metadata(meta, (5,), SceneConfig(wall_clip=3.0))
    assert wide.wall_clip == 3.0
    # Points 0.05..0.45 from the lower walls: clipped at 3 R = 0.3, no longer at R = 0.1.
    last = np.stack([np.linspace(0.15, 0.55, 9)] * 2, axis=1)
    positions = torch.tensor(np.repeat(last[:, None], 6, axis=1))
    nodes = LearnedSimulator(wide, config()).double().features(positions, torch.full((9,), 5))
    lo, hi = np.array(BOX).T
    want = np.clip(np.concatenate([last - lo, hi - last], axis=1) / 0.1, -3, 3)
    np.testing.assert_allclose(nodes["node_features"][:, 10:14].detach().numpy(), want)
    assert want.max() == 3.0 and 1 < want[3, 0] < 3  # both the clip and the range it opens
    with pytest.raises(ValueError, match=r"wall_clip must be positive, got -1"):
        SceneConfig(wall_clip=-1.0)


def test_self_edges_follow_the_config():
    positions, types = window(seed=2)
    with_self = LearnedSimulator(scene(), config()).features(positions, types)
    without = LearnedSimulator(scene(), config(self_edges=False)).features(positions, types)
    n = positions.shape[0]
    assert with_self["senders"].shape[0] == without["senders"].shape[0] + n
    assert not torch.any(without["senders"] == without["receivers"])


def test_unknown_particle_types_and_wrong_shapes_are_rejected():
    positions, types = window(seed=3)
    sim = LearnedSimulator(scene(), config())
    with pytest.raises(ValueError, match=r"particle types \[7\]"):
        sim(positions, torch.where(types == 5, 7, types))
    with pytest.raises(ValueError, match=r"\(N, 6, 2\)"):
        sim(positions[:, 1:], types)
    with_context = LearnedSimulator(scene(context_size=1), config())
    with pytest.raises(ValueError, match="context"):
        with_context(positions, types)
    with pytest.raises(ValueError, match=r"context must be \(1, 1\)"):
        with_context(positions, types, context=torch.zeros(3))


# ---------------------------------------------------------------------- postprocess and inverse


def test_postprocess_is_semi_implicit_euler_like_the_rust_core():
    positions, types = window(seed=4)
    sim = LearnedSimulator(scene(), metadata_config(), statistics=fixed_statistics())
    normalized = torch.randn(positions.shape[0], 2, generator=torch.Generator().manual_seed(5))
    acceleration = (normalized.double() * math.sqrt(1e-8 + 9e-8) - 2e-5).float()
    x, v = positions[:, -1], positions[:, -1] - positions[:, -2]
    want_x, _ = euler_step(x, v, acceleration)
    got = sim.decoder_postprocess(normalized, positions)
    assert got.dtype == torch.float32
    torch.testing.assert_close(got, want_x, rtol=0, atol=4 * EPS32)


def test_postprocess_and_its_inverse_compose_to_the_identity_in_float64():
    positions, types = window(seed=6, dtype=torch.float64)
    sim = LearnedSimulator(scene(), metadata_config(), statistics=fixed_statistics())
    a = torch.randn(positions.shape[0], 2, dtype=torch.float64)
    next_position = sim.decoder_postprocess(a, positions)
    torch.testing.assert_close(sim.target_normalized_acceleration(next_position, positions), a)
    target_next = positions[:, -1] + 1e-3 * torch.randn_like(positions[:, -1])
    target = sim.target_normalized_acceleration(target_next, positions)
    torch.testing.assert_close(sim.decoder_postprocess(target, positions), target_next)


def test_postprocess_and_its_inverse_compose_to_the_identity_in_float32():
    positions, types = window(seed=7)
    acc_std = 1e-4
    sim = LearnedSimulator(
        scene(), metadata_config(noise_std=0.0), statistics=fixed_statistics(acc_std=acc_std)
    )
    a = torch.randn(positions.shape[0], 2, generator=torch.Generator().manual_seed(8))
    next_position = sim.decoder_postprocess(a, positions)
    # One float32 rounding of a position (|x| < 1) is eps / 2; a few such, in acceleration stds.
    tolerance = 4 * EPS32 / acc_std
    back = sim.target_normalized_acceleration(next_position, positions)
    torch.testing.assert_close(back, a, rtol=0, atol=tolerance)


@pytest.mark.parametrize("fraction", [0.0, 1.0, 0.3])
def test_targets_correct_the_configured_fraction_of_the_input_noise(fraction):
    positions, types = window(seed=9, dtype=torch.float64)
    cfg = Config(model=TINY, noise=NoiseConfig(std=3e-4, correct_position_fraction=fraction))
    sim = LearnedSimulator(scene(), cfg)
    clean, next_position = positions[:, :-1], positions[:, -1]
    noise = sim.sample_noise(clean, types, torch.Generator().manual_seed(10))
    noisy = clean + noise
    target = sim.target_normalized_acceleration(next_position, noisy, noise)
    predicted = sim.decoder_postprocess(target, noisy)
    # Fraction 0: the next velocity is the true one, so the input position noise is kept;
    # fraction 1: the next position is the true one; in between, the mix.
    want = next_position + (1 - fraction) * noise[:, -1]
    torch.testing.assert_close(predicted, want)
    if fraction == 0.0:
        torch.testing.assert_close(predicted - noisy[:, -1], next_position - clean[:, -1])


def test_add_gravity_makes_a_zero_residual_free_fall():
    positions, types = window(seed=11, dtype=torch.float64)
    g = (0.0, -6.1e-5)
    stats = fixed_statistics().replace(acc_mean=g)
    sim = LearnedSimulator(
        scene(gravity=g), metadata_config(add_gravity=True), statistics=stats
    ).double()
    torch.testing.assert_close(
        sim.acceleration_normalizer.mean, torch.zeros(2, dtype=torch.float64)
    )
    x, v = positions[:, -1], positions[:, -1] - positions[:, -2]
    got = sim.decoder_postprocess(torch.zeros_like(x), positions)
    torch.testing.assert_close(got, x + v + torch.tensor(g, dtype=torch.float64))
    with pytest.raises(ValueError, match="gravity"):
        LearnedSimulator(scene(), config(add_gravity=True))


# ---------------------------------------------------------------------- statistics and kinematics


def test_metadata_statistics_are_inflated_by_the_noise():
    sim = LearnedSimulator(scene(), metadata_config(noise_std=3e-4), statistics=fixed_statistics())
    vel = torch.full((2,), math.sqrt(1e-3**2 + 3e-4**2), dtype=torch.float64)
    acc = torch.full((2,), math.sqrt(1e-4**2 + 3e-4**2), dtype=torch.float64)
    torch.testing.assert_close(sim.velocity_normalizer.std, vel)
    torch.testing.assert_close(sim.acceleration_normalizer.std, acc)
    with pytest.raises(ValueError, match="vel_mean"):
        LearnedSimulator(
            scene(), metadata_config(), statistics=fixed_statistics().replace(vel_mean=None)
        )


def test_running_statistics_are_taken_after_noise_over_free_particles_only():
    positions, types = window(n=200, seed=12, dtype=torch.float64, steps=7)
    cfg = Config(model=TINY, noise=NoiseConfig(std=3e-4))
    sim = LearnedSimulator(scene(), cfg).double()
    clean, next_position = positions[:, :-1], positions[:, -1]
    noise = sim.sample_noise(clean, types, torch.Generator().manual_seed(13))
    kinematic = (types == 3).numpy()
    assert kinematic.any() and torch.count_nonzero(noise[types == 3]) == 0

    sim.eval()
    sim.predict_accelerations(next_position, clean, noise, types)
    assert sim.velocity_normalizer.count.item() == 0  # no statistics outside training
    sim.train()
    predicted, target = sim.predict_accelerations(next_position, clean, noise, types)

    noisy = (clean + noise).numpy()[~kinematic]
    velocities = np.diff(noisy, axis=1)
    accelerations = (
        (next_position.numpy()[~kinematic] + noise[:, -1].numpy()[~kinematic])
        - 2 * (noisy[:, -1])
        + noisy[:, -2]
    )
    np.testing.assert_allclose(sim.velocity_normalizer.mean, velocities.reshape(-1, 2).mean(0))
    np.testing.assert_allclose(sim.velocity_normalizer.std, velocities.reshape(-1, 2).std(0))
    np.testing.assert_allclose(sim.acceleration_normalizer.mean, accelerations.mean(0))
    np.testing.assert_allclose(sim.acceleration_normalizer.std, accelerations.std(0))
    # The target is the inverse of the postprocess, normalised by the statistics just updated.
    twin = sim.target_normalized_acceleration(next_position, clean + noise, noise)
    torch.testing.assert_close(target, twin)
    assert predicted.shape == target.shape == (200, 2)
    assert torch.equal(sim.kinematic_mask(types), types == 3)


def test_the_kinematic_set_is_configurable():
    positions, types = window(seed=14)
    sim = LearnedSimulator(scene(kinematic_particle_types=(5, 6)), config())
    noise = sim.sample_noise(positions[:, :-1], types, torch.Generator().manual_seed(15))
    assert torch.count_nonzero(noise[types != 3]) == 0
    assert torch.count_nonzero(noise[types == 3][:, -1]) == noise[types == 3][:, -1].numel()


# ---------------------------------------------------------------------- symmetries and batching


def test_the_simulator_is_permutation_equivariant():
    torch.manual_seed(16)
    positions, types = window(n=120, seed=17, steps=7)
    sim = LearnedSimulator(scene(context_size=2), config())
    context = torch.tensor([0.4, -1.0])
    out = sim(positions[:, :-1], types, context=context)
    perm = torch.randperm(120, generator=torch.Generator().manual_seed(18))
    # Edges are rebuilt by the Rust core for the permuted particles (a different edge order).
    out_perm = sim(positions[perm, :-1], types[perm], context=context)
    torch.testing.assert_close(out_perm, out[perm], rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("global_latent", [False, True])
def test_a_batch_of_graphs_equals_each_graph_alone(global_latent):
    torch.manual_seed(19)
    a, ta = window(n=50, seed=20, steps=7)
    b, tb = window(n=70, seed=21, steps=7)  # overlapping in space: only n_node keeps them apart
    sim = LearnedSimulator(scene(context_size=1), config(global_latent=global_latent))
    ca, cb = torch.tensor([[0.2]]), torch.tensor([[0.9]])
    batched = sim(
        torch.cat([a, b])[:, :-1],
        torch.cat([ta, tb]),
        n_node=torch.tensor([50, 70]),
        context=torch.cat([ca, cb]),
    )
    alone = torch.cat([sim(a[:, :-1], ta, context=ca), sim(b[:, :-1], tb, context=cb)])
    torch.testing.assert_close(batched, alone, rtol=1e-4, atol=1e-5)


def test_periodic_boxes_use_minimum_images():
    s = Scene(
        dim=2, radius=0.05, particle_types=(5,), bounds=((0.0, 1.0), (0.0, 1.0)),
        walls=True, periodic=(True, False),
    )  # fmt: skip
    sim = LearnedSimulator(s, config()).double()
    # Particle 0 crosses x = 1 -> 0 at the last step; particle 1 sits near x = 0.
    x0 = torch.tensor(
        [[0.95, 0.5], [0.96, 0.5], [0.97, 0.5], [0.98, 0.5], [0.99, 0.5], [0.002, 0.5]]
    )
    x1 = torch.full((6, 2), 0.5).index_fill_(1, torch.tensor([0]), 0.03)
    positions = torch.stack([x0, x1]).double()
    velocities = sim.velocity_sequence(positions)
    torch.testing.assert_close(
        velocities[0, :, 0], torch.tensor([0.01, 0.01, 0.01, 0.01, 0.012]).double()
    )
    f = sim.features(positions, torch.tensor([5, 5]))
    cross = (f["senders"] == 0) & (f["receivers"] == 1)
    assert cross.sum() == 1
    torch.testing.assert_close(
        f["edge_features"][cross], torch.tensor([[-0.028 / 0.05, 0.0, 0.028 / 0.05]]).double()
    )
    assert f["node_features"].shape[1] == 10 + 2  # walls on the y axis only
    # The Euler step wraps back into the box, and the inverse sees through the wrap.
    a = torch.zeros(2, 2, dtype=torch.float64)
    nxt = sim.decoder_postprocess(a, positions)
    torch.testing.assert_close(nxt[0], torch.tensor([0.014, 0.5]).double())
    torch.testing.assert_close(sim.target_normalized_acceleration(nxt, positions), a)


def test_state_dict_restores_predictions_including_statistics():
    positions, types = window(seed=22, steps=7)
    sim = LearnedSimulator(scene(), config())
    sim.train()
    noise = sim.sample_noise(positions[:, :-1], types, torch.Generator().manual_seed(23))
    sim.predict_accelerations(positions[:, -1], positions[:, :-1], noise, types)
    other = LearnedSimulator(scene(), config())
    other.load_state_dict(sim.state_dict())
    assert other.velocity_normalizer.count.item() > 0
    torch.testing.assert_close(other(positions[:, :-1], types), sim(positions[:, :-1], types))


# ---------------------------------------------------------------------- learning


@pytest.mark.skipif(not (SAND / "manifest.json").is_file(), reason="sand2d-taichi not present")
def test_overfits_one_window_of_the_real_sand_data():
    torch.manual_seed(24)
    dataset = open_dataset(SAND, "train")
    w = next(trajectory_windows(dataset[0], starts=[100]))
    positions = torch.from_numpy(w.positions.transpose(1, 0, 2).copy())  # (N, 7, 2)
    types = torch.from_numpy(w.particle_type)
    context = torch.from_numpy(w.step_context)
    cfg = Config(model=TINY, noise=NoiseConfig(std=0.0))
    sim = LearnedSimulator(Scene.from_dataset(dataset), cfg)
    optimizer = torch.optim.Adam(sim.parameters(), lr=1e-3)
    noise = torch.zeros_like(positions[:, :-1])
    losses = []
    for _ in range(200):
        predicted, target = sim.predict_accelerations(
            positions[:, -1], positions[:, :-1], noise, types, context=context
        )
        loss = ((predicted - target) ** 2).sum(-1).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    assert losses[-1] < losses[0] / 10, (losses[0], losses[-1])


def test_obstacle_and_material_features_by_hand():
    from gns import Obstacle

    floor = Obstacle.cuboid([0.5, 0.2], [0.4, 0.05])  # top surface at y = 0.25
    s = Scene(dim=2, radius=0.1, particle_types=(5,), material_property_size=1)
    sim = LearnedSimulator(s, config(), obstacles=[floor])
    assert sim.node_input_size == 10 + 2 + 1
    last = torch.tensor([[0.5, 0.3], [0.5, 0.6]], dtype=torch.float64)
    positions = last[:, None, :].expand(2, 6, 2).contiguous()
    f = sim.double().features(positions, torch.tensor([5, 5]), material_property=0.7)
    nodes = f["node_features"]
    # Nearest surface point minus position, / R, within R; zero beyond.
    want = torch.tensor([[0.0, -0.5, 0.7], [0.0, 0.0, 0.7]], dtype=torch.float64)
    torch.testing.assert_close(nodes[:, 10:], want)
