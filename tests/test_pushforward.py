"""The pushforward trick (train.pushforward): the input is pushed forward by the model itself,
without gradient, before the one-step loss."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from gns.batches import batch_tensors
from gns.checkpoints import load_simulator
from gns.config import TrainConfig
from gns.data import open_dataset
from gns.data.windows import WindowSampler
from gns.train import TrainingStep, _pushforward_steps, _split_targets, train
from test_train import config, make_dataset, parameters, trained_run

pytestmark = pytest.mark.usefixtures("torch_one_thread")


def batch(data, simulator, extra: int):
    """A batch of 2 windows with `extra` frames past the first target, and its input noise."""
    history = simulator.config.model.velocity_history + 1
    sampler = WindowSampler(open_dataset(data, "train"), history + extra, seed=3)
    t = batch_tensors(sampler.next_batch(2), torch.device("cpu"))
    sequence, targets = _split_targets(t, history)
    generator = torch.Generator().manual_seed(5)
    noise = simulator.sample_noise(sequence, t["particle_type"], generator)
    return t, sequence, targets, noise


def gradients(loss_and_count, simulator) -> dict[str, torch.Tensor]:
    simulator.zero_grad()
    squared, count = loss_and_count
    (squared / count).backward()
    return {k: p.grad.clone() for k, p in simulator.named_parameters() if p.grad is not None}


def test_the_loss_is_one_step_from_the_models_own_rollout_without_its_gradient(tmp_path):
    run, data = trained_run(tmp_path / "a", steps=6)
    simulator = load_simulator(run).eval()  # eval: the running statistics stay as they are
    t, sequence, targets, noise = batch(data, simulator, extra=2)
    args = (t["particle_type"], t["n_node"], t["context"], t["material_property"])
    step = TrainingStep(simulator)

    pushed = step(
        sequence, targets[:, 0], noise, *args, later_positions=targets[:, 1:], pushforward=2
    )
    pushed_grads = gradients(pushed, simulator)

    # The oracle: two steps of the rollout path (predict_positions) from the noisy input, the
    # kinematic particles on the ground truth, then the plain one-step loss from there.
    noisy = sequence + noise
    kinematic = simulator.kinematic_mask(t["particle_type"])[:, None]
    with torch.no_grad():
        for truth in (targets[:, 0], targets[:, 1]):
            reached = simulator.predict_positions(noisy, *args[:3])
            reached = torch.where(kinematic, truth, reached)
            noisy = torch.cat([noisy[:, 1:], reached[:, None]], 1)
    by_hand = step(noisy - noise, targets[:, 2], noise, *args)
    hand_grads = gradients(by_hand, simulator)

    assert torch.allclose(pushed[0], by_hand[0], rtol=1e-5)
    assert pushed[1] == by_hand[1]
    for name, grad in hand_grads.items():  # no gradient through the pushed steps
        assert torch.allclose(pushed_grads[name], grad, rtol=1e-4, atol=1e-7), name
    # The test can fail: the unpushed loss is another number.
    plain = step(sequence, targets[:, 0], noise, *args)
    assert not torch.allclose(plain[0], pushed[0], rtol=1e-2)


def test_a_run_with_pushforward_resumes_exactly(tmp_path):
    data = make_dataset(tmp_path / "data", frames=14)
    settings = lambda steps: config(steps, pushforward=(1.0, 1.0, 1.0))  # noqa: E731
    straight = train(data, tmp_path / "a", settings(12), progress=False)
    train(data, tmp_path / "b", settings(5), progress=False)
    resumed = train(data, tmp_path / "b", settings(12), resume=True, progress=False)
    a, b = parameters(straight), parameters(resumed)
    for key in a:
        assert torch.equal(a[key], b[key]), key
    # ... and pushing forward changed what was learned.
    plain = parameters(train(data, tmp_path / "c", config(12), progress=False))
    assert any(not torch.equal(a[k], plain[k]) for k in a)


def test_the_number_of_pushed_steps_follows_the_weights():
    settings = TrainConfig(pushforward=(6.0, 0.0, 2.0), seed=4)
    drawn = np.array([_pushforward_steps(settings, step) for step in range(4000)])
    assert set(drawn) == {0, 2}
    assert abs((drawn == 2).mean() - 0.25) < 0.03  # 4000 draws: sd 0.007
    again = [_pushforward_steps(settings, step) for step in range(50)]
    assert again == list(drawn[:50])  # from (seed, step) alone
    assert _pushforward_steps(dataclasses.replace(settings, pushforward=()), 7) == 0


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        ({"pushforward": (1.0, -1.0)}, r"weights >= 0 with a positive sum, got \[1.0, -1.0\]"),
        ({"pushforward": (0.0, 0.0)}, "positive sum"),
        ({"pushforward": (1.0, 1.0), "loss_steps": 2}, "are alternatives"),
    ],
)
def test_bad_pushforward_settings_are_refused(settings, message):
    with pytest.raises(ValueError, match=message):
        TrainConfig(**settings)
