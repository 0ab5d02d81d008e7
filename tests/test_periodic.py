"""Periodic boxes (LagrangeBench's SPH datasets) outside the model: statistics, the
constant-velocity baseline and every metric take minimum images (issue 26). Oracles: a
constant-velocity flow across a periodic axis, whose velocity std, acceleration and baseline
error are exactly zero, and wrapped cases small enough to do by hand."""

from __future__ import annotations

import json

import numpy as np
import pytest
from gns.baselines import constant_velocity_rollout
from gns.cli import main
from gns.data import open_dataset, write_dataset
from gns.distances import exact_optimal_transport, mmd, optimal_transport
from gns.metrics import evaluate_rollout, mse_over_time
from gns.periodic import minimum_image, period_of, wrap

BOUNDS = ((0.0, 1.0), (0.0, 0.5))
PERIOD = period_of(BOUNDS, (True, False))  # x wraps at 1.0, y does not
VELOCITY = np.array([0.13, 0.01])  # a frame: x crosses the box about every 8 frames


def flow(frames=20, n=12, seed=0):
    """(frames, n, 2): particles at constant velocity, x wrapped into [0, 1)."""
    start = np.random.default_rng(seed).uniform((0.0, 0.1), (1.0, 0.2), (n, 2))
    x = start[None] + np.arange(frames)[:, None, None] * VELOCITY
    return wrap(x, (0.0, 0.0), PERIOD)


def test_the_period_and_the_minimum_image():
    assert PERIOD.tolist() == [1.0, 0.0]
    assert period_of(BOUNDS, (False, False)) is None
    np.testing.assert_allclose(
        minimum_image([[0.98, 0.4], [-0.7, -0.4]], PERIOD), [[-0.02, 0.4], [0.3, -0.4]]
    )
    np.testing.assert_allclose(
        wrap([[1.25, 0.7], [-0.25, -0.1]], (0.0, 0.0), PERIOD), [[0.25, 0.7], [0.75, -0.1]]
    )
    with pytest.raises(ValueError, match="need the box's bounds"):
        period_of(None, (True, False))


def test_stats_of_a_wrapped_constant_velocity_flow_are_exact(tmp_path, capsys):
    """gns stats on the flow: velocity mean v and std 0, acceleration 0 (raw differences of
    the wrapped positions would give x velocities of -0.87 at every crossing)."""
    x = flow()
    assert np.any(np.diff(x[..., 0], axis=0) < -0.5)  # the data does wrap
    types = np.full(x.shape[1], 5)
    meta = write_dataset(
        tmp_path / "d",
        {"train": [{"positions": x.astype(np.float32), "particle_type": types}]},
        dt=0.01,
        bounds=BOUNDS,
        connectivity_radius=0.05,
        periodic=(True, False),
    )
    np.testing.assert_allclose(meta.vel_mean, VELOCITY, atol=1e-6)
    np.testing.assert_allclose(meta.vel_std, 0.0, atol=1e-6)
    np.testing.assert_allclose(meta.acc_mean, 0.0, atol=1e-6)
    np.testing.assert_allclose(meta.acc_std, 0.0, atol=1e-6)
    written = json.loads((tmp_path / "d" / "metadata.json").read_text())
    assert max(written["vel_std"]) < 1e-6
    assert written["periodic_boundary_conditions"] == [True, False]
    # `gns stats` recomputes them from the data: the same, printed per axis.
    assert main(["stats", str(tmp_path / "d")]) == 0
    rows = [line.split() for line in capsys.readouterr().out.splitlines() if line.startswith("   ")]
    printed = np.array([[float(v) for v in row[1:]] for row in rows])  # vel mean, std, acc ...
    np.testing.assert_allclose(printed[:, 0], VELOCITY, atol=1e-6)
    np.testing.assert_allclose(printed[:, 1:], 0.0, atol=1e-6)


def test_constant_velocity_reproduces_the_flow_and_scores_zero():
    x = flow()
    history = 6
    baseline = constant_velocity_rollout(
        x[:history], len(x) - history, bounds=BOUNDS, period=PERIOD
    )
    np.testing.assert_allclose(baseline, x[history:], atol=1e-12)
    metrics = evaluate_rollout(baseline, x[history:], period=PERIOD)
    assert (
        metrics["mse@full"] < 1e-24 and max(metrics["ot"]) < 1e-24 and max(metrics["mmd"]) < 1e-12
    )
    # Without the period the same baseline runs off the box and the raw error is large.
    raw = constant_velocity_rollout(x[:history], len(x) - history)
    assert evaluate_rollout(raw, x[history:])["mse@full"] > 0.01
    with pytest.raises(ValueError, match="needs the box's bounds"):
        constant_velocity_rollout(x[:history], 3, period=PERIOD)


def test_metrics_on_a_wrapped_case_by_hand():
    """Truth at x 0.99, prediction at x 0.01: 0.02 apart across the seam, not 0.98."""
    truth = np.array([[[0.99, 0.25], [0.5, 0.25]]])
    predicted = np.array([[[0.01, 0.25], [0.5, 0.28]]])
    # MSE: ((0.02^2 + 0) + (0 + 0.03^2)) / 4, over 2 particles x 2 axes.
    expected = (0.02**2 + 0.03**2) / 4
    assert mse_over_time(predicted, truth, period=PERIOD)[0] == pytest.approx(expected)
    assert mse_over_time(predicted, truth)[0] == pytest.approx((0.98**2 + 0.03**2) / 4)
    # OT: the matching pairs each point with its own (across the seam); W2^2 = mean cost.
    w2 = exact_optimal_transport(predicted[0], truth[0], period=PERIOD)
    assert w2 == pytest.approx((0.02**2 + 0.03**2) / 2)
    # MMD: a cloud moved by a whole period is the same cloud on the torus.
    cloud = np.random.default_rng(1).uniform((0, 0), (1, 0.5), (40, 2))
    moved = cloud + [1.0, 0.0]
    assert mmd(moved, cloud, period=PERIOD) == pytest.approx(0.0, abs=1e-12)
    assert mmd(moved, cloud) > 0.1
    # Two points each: 0.05 and 0.95 are 0.1 apart round the seam, so W2^2 = 0.1^2 / 2; on
    # the line the best plan crosses over instead: (0.45^2 + 0.45^2) / 2.
    a = np.array([[0.05, 0.25], [0.5, 0.25]])
    b = np.array([[0.95, 0.25], [0.5, 0.25]])
    assert optimal_transport(a, b, period=PERIOD) == pytest.approx(0.1**2 / 2)
    assert optimal_transport(a, b) == pytest.approx(0.45**2)
    with pytest.raises(ValueError, match="periodic box is exact only"):
        optimal_transport(a, b, period=PERIOD, method="sinkhorn")


def test_eval_of_a_periodic_dataset_gives_constant_velocity_zero(tmp_path):
    """Through gns.data and gns.evaluate's baseline path: the metadata's period reaches the
    baseline and the metrics (evaluate_rollouts on a rollout file of the truth itself)."""
    from gns.evaluate import evaluate_rollouts
    from gns.rollout import Rollout

    x = flow(frames=16).astype(np.float32)
    types = np.full(x.shape[1], 5)
    write_dataset(
        tmp_path / "d",
        {"train": [{"positions": x, "particle_type": types}]},
        dt=0.01,
        bounds=BOUNDS,
        connectivity_radius=0.05,
        periodic=(True, False),
    )
    (trajectory,) = open_dataset(tmp_path / "d", "train")
    positions = trajectory.positions.astype(np.float64)
    rollout = Rollout(
        initial_positions=positions[:6],
        predicted_rollout=positions[6:],
        ground_truth_rollout=positions[6:],
        particle_type=types,
        metadata={"bounds": [list(b) for b in BOUNDS], "periodic": [True, False], "trajectory": 0},
    )
    result = evaluate_rollouts([rollout])
    cv = result["mean"]["constant_velocity"]
    # float32 positions: the baseline's error is round-off, not the 0.87 of a raw difference.
    assert cv["mse@full"] < 1e-12 and cv["ot_mean"] < 1e-12


def test_one_step_errors_of_the_wrapped_flow_are_zero_for_constant_velocity_and_its_model(
    tmp_path,
):
    """gns eval's one-step errors: constant velocity is exact on the flow (the issue saw 0.0225),
    and so is a model that predicts zero acceleration (the simulator's minimum images)."""
    import torch
    from gns.config import Config, ModelConfig
    from gns.evaluate import one_step_errors
    from gns.simulator import LearnedSimulator, Scene

    x = flow(frames=14).astype(np.float32)
    write_dataset(
        tmp_path / "d",
        {"train": [{"positions": x, "particle_type": np.full(x.shape[1], 5)}]},
        dt=0.01,
        bounds=BOUNDS,
        connectivity_radius=0.05,
        periodic=(True, False),
    )
    trajectories = list(open_dataset(tmp_path / "d", "train"))
    scene = Scene(dim=2, radius=0.05, particle_types=(5,), bounds=BOUNDS, walls=False,
                  periodic=(True, False))  # fmt: skip
    tiny = Config(model=ModelConfig(latent_size=8, mlp_hidden_size=8, message_passing_steps=1))
    simulator = LearnedSimulator(scene, tiny)
    torch.nn.init.zeros_(simulator.model.decoder[-1].weight)
    torch.nn.init.zeros_(simulator.model.decoder[-1].bias)
    errors = one_step_errors(simulator, trajectories)
    assert errors["constant_velocity"] < 1e-12 and errors["model"] < 1e-12
    # The static guess is off by one frame's motion, |v|^2 / 2 per axis.
    assert errors["static"] == pytest.approx(float(VELOCITY @ VELOCITY) / 2, rel=1e-4)
