"""The padded (static-capacity) edge list: LearnedSimulator.edge_bucket pads each step's edges
to a multiple of the bucket with edges the network ignores (gns.simulator.pad_edges), so that
a rollout keeps its tensor shapes (for CUDA graphs). On the CPU it must give the unpadded
results to float32 round-off: rollouts, one-step predictions, training losses and gradients,
on both implementations and with a global latent."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from gns.config import Config, ModelConfig
from gns.data.trajectory import Trajectory
from gns.data.windows import window_keys
from gns.evaluate import one_step_predictions
from gns.model import EDGE_BLOCK
from gns.rollout import rollout
from gns.simulator import LearnedSimulator, Scene, edge_capacity, pad_edges
from gns.train import TrainingStep

pytestmark = pytest.mark.usefixtures("torch_one_thread")

RADIUS = 0.03
# Smaller than a step's ~2.5k edges, so that the padding is most of a bucket in some steps
# and the fast path's cache-sized edge blocks (EDGE_BLOCK) hold real and padding edges both.
BUCKET = 1000
CASES = [("plain", False), ("fast", False), ("fast", True)]


def cloud(frames: int = 12, n: int = 200, seed: int = 0) -> Trajectory:
    """n particles (two of them kinematic, held still) in a 0.2-wide patch, ~13 neighbours
    each within RADIUS, drifting and swirling, with a context that changes per frame."""
    rng = np.random.default_rng(seed)
    x0 = rng.uniform(0.4, 0.6, size=(n, 2))
    t = np.arange(frames)[:, None, None]
    swirl = np.stack([-(x0[:, 1] - 0.5), x0[:, 0] - 0.5], axis=1)
    positions = (x0[None] + 2e-3 * t * swirl[None] + 1e-4 * t**2).astype(np.float32)
    types = np.full(n, 5)
    types[:2] = 3
    positions[:, :2] = positions[0, :2]
    context = rng.uniform(0.0, 1.0, size=(frames, 1)).astype(np.float32)
    return Trajectory(positions, types, context, key=seed)


def simulator(implementation: str, global_latent: bool, bucket: int = 0) -> LearnedSimulator:
    scene = Scene(dim=2, radius=RADIUS, particle_types=(3, 5), bounds=((0.1, 0.9),) * 2,
                  walls=True, context_size=1)  # fmt: skip
    model = ModelConfig(
        latent_size=16,
        mlp_hidden_size=16,
        message_passing_steps=3,
        implementation=implementation,
        precision="fp32",
        global_latent=global_latent,
    )
    torch.manual_seed(0)  # the same weights, padded or not
    sim = LearnedSimulator(scene, Config(model=model))
    # Statistics of the data's scale, so the untrained model moves particles at its speed
    # and each step has its own graph.
    sequence = torch.from_numpy(cloud().positions[:6]).transpose(0, 1)
    acceleration = 1e-4 * torch.randn(200, 2, generator=torch.Generator().manual_seed(0))
    sim.update_statistics(sequence, acceleration, torch.full((200,), 5))
    sim.edge_bucket = bucket
    return sim


def test_the_capacity_is_the_next_multiple_of_the_bucket():
    assert [edge_capacity(e, 4096) for e in (0, 1, 4096, 4097)] == [0, 4096, 4096, 8192]
    with pytest.raises(ValueError, match="positive"):
        edge_capacity(10, 0)


def test_padding_edges_follow_the_real_ones_with_zero_features_and_mask():
    senders, receivers = torch.tensor([0, 1, 2]), torch.tensor([1, 2, 0])
    features = torch.rand(3, 3)
    s, r, f, mask = pad_edges(senders, receivers, features, n=3, capacity=8)
    assert s.tolist() == [0, 1, 2, 0, 1, 2, 0, 1]
    assert r.tolist() == [1, 2, 0, 0, 1, 2, 0, 1]
    assert torch.equal(f[:3], features) and not f[3:].any()
    assert mask.tolist() == [1.0] * 3 + [0.0] * 5
    with pytest.raises(ValueError, match="below"):
        pad_edges(senders, receivers, features, n=3, capacity=2)


@pytest.mark.parametrize("implementation", ["plain", "fast"])
def test_without_their_mask_the_padding_edges_would_change_every_result(implementation):
    # What the tests below rely on: padding that is not masked is not harmless.
    sim = simulator(implementation, False, BUCKET).eval()
    trajectory = cloud()
    sequence = torch.from_numpy(trajectory.positions[:6]).transpose(0, 1)
    types = torch.from_numpy(trajectory.particle_type)
    context = torch.from_numpy(trajectory.step_context[5])
    with torch.no_grad():
        f = sim.features(sequence, types, None, context)
        keys = ("node_features", "edge_features", "senders", "receivers", "global_features")
        masked = sim.model(*(f[k] for k in keys), edge_mask=f["edge_mask"])
        unmasked = sim.model(*(f[k] for k in keys))
    assert f["edge_mask"] is not None and not f["edge_mask"].all()
    assert not torch.allclose(masked, unmasked, rtol=1e-3, atol=1e-3)


@pytest.mark.parametrize(("implementation", "global_latent"), CASES)
def test_a_padded_rollout_equals_the_unpadded_one_with_fixed_shapes(implementation, global_latent):
    trajectory = cloud()
    plain = rollout(simulator(implementation, global_latent), trajectory, num_steps=5)
    padded_sim = simulator(implementation, global_latent, BUCKET)
    shapes = []
    padded_sim.model.register_forward_hook(
        lambda module, args, kwargs, out: shapes.append(
            (args[1].shape[0], int(kwargs["edge_mask"].sum()))
        ),
        with_kwargs=True,
    )
    padded = rollout(padded_sim, trajectory, num_steps=5)
    # Positions near 0.5 whose steps are ~1e-4: a relative tolerance would hide the
    # accelerations; a few float32 ulps of position would not.
    np.testing.assert_allclose(padded.predicted_rollout, plain.predicted_rollout, rtol=0, atol=3e-7)
    # Every step a whole number of buckets, and the real edges' count changes between steps.
    assert all(e % BUCKET == 0 and real < e for e, real in shapes)
    assert len({real for _, real in shapes}) > 1 and shapes[0][0] > EDGE_BLOCK


@pytest.mark.parametrize(("implementation", "global_latent"), CASES)
def test_padded_one_step_predictions_equal_the_unpadded_ones(implementation, global_latent):
    trajectories = [cloud(seed=0), cloud(n=150, seed=1)]
    pairs = window_keys(trajectories, 6)
    outputs = [
        [p[2] for p in one_step_predictions(sim, trajectories, pairs, max_particles=400)]
        for sim in (
            simulator(implementation, global_latent).eval(),
            simulator(implementation, global_latent, BUCKET).eval(),
        )
    ]
    for plain, padded in zip(*outputs, strict=True):
        torch.testing.assert_close(padded, plain, rtol=0, atol=2e-7)  # see the rollout's


@pytest.mark.parametrize(("implementation", "global_latent"), CASES)
def test_padded_training_loss_and_gradients_equal_the_unpadded_ones(implementation, global_latent):
    trajectory = cloud()
    positions = torch.from_numpy(trajectory.positions).transpose(0, 1)  # (N, T, D)
    sequence, next_position = positions[:, :6], positions[:, 6]
    types = torch.from_numpy(trajectory.particle_type)
    context = torch.from_numpy(trajectory.step_context[5])
    results = []
    for bucket in (0, BUCKET):
        sim = simulator(implementation, global_latent, bucket).train()
        noise = sim.sample_noise(sequence, types, torch.Generator().manual_seed(1))
        loss_sum, count = TrainingStep(sim)(sequence, next_position, noise, types, None, context)
        loss = loss_sum / count
        loss.backward()
        grads = {k: p.grad.clone() for k, p in sim.named_parameters() if p.grad is not None}
        results.append((loss.detach(), grads))
    (loss, grads), (padded_loss, padded_grads) = results
    torch.testing.assert_close(padded_loss, loss, rtol=1e-5, atol=0)
    assert grads.keys() == padded_grads.keys() and len(grads) > 10
    for name, grad in grads.items():
        torch.testing.assert_close(padded_grads[name], grad, rtol=1e-4, atol=1e-6, msg=name)
