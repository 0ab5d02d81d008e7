"""3D end to end through the command line: a hand-made dataset of particles in free fall inside
a box (3 axes, y up), written by gns.data.write_dataset in the DeepMind layout, then `gns
train` (a tiny model, a few dozen steps), `gns rollout` and `gns eval`. Free fall has an
answer to check the 3D path against: every particle's acceleration is -g dt^2 per frame along
y and nothing along x and z, so the dataset's statistics say so and constant velocity misses
each step by exactly g dt^2 in y (k(k + 1)/2 g dt^2 after k steps)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from gns.cli import main
from gns.data import Trajectory, open_dataset, write_dataset
from gns.rollout import load_rollout

pytestmark = pytest.mark.usefixtures("torch_one_thread")

G = 9.81  # m/s^2, along -y
DT = 0.01  # s per frame
GDT2 = G * DT**2  # the change of a free particle's per-frame velocity each frame
FRAMES = 14  # the model reads 6: 8 steps to roll out
HISTORY = 6
BOUNDS = [[0.0, 1.0], [0.0, 1.0], [0.0, 1.0]]
RADIUS = 0.15


def free_fall(
    rng: np.random.Generator, particles: int = 16, obstacles: int = 2, frames: int = FRAMES
) -> Trajectory:
    """`particles` thrown inside the unit box (type 5) falling freely, y up, none reaching a
    wall within `frames`, and `obstacles` static boundary particles (type 3) near the floor."""
    start = rng.uniform([0.25, 0.55, 0.25], [0.75, 0.8, 0.75], size=(particles, 3))
    velocity = rng.uniform(-0.3, 0.3, size=(particles, 3))
    t = DT * np.arange(frames)[:, None, None]
    moving = start + velocity * t + 0.5 * np.array([0.0, -G, 0.0]) * t**2
    fixed = rng.uniform([0.2, 0.05, 0.2], [0.8, 0.1, 0.8], size=(obstacles, 3))
    positions = np.concatenate([moving, np.broadcast_to(fixed, (frames, obstacles, 3))], axis=1)
    types = np.array([5] * particles + [3] * obstacles, dtype=np.int64)
    return Trajectory(positions.astype(np.float32), types)


def write_free_fall(folder, layout: str, particles: int = 16, train: int = 3, test: int = 2):
    """A free-fall dataset at `folder`: train and test splits, metadata with dim 3."""
    rng = np.random.default_rng(0)
    splits = {
        "train": [free_fall(rng, particles) for _ in range(train)],
        "test": [free_fall(rng, particles) for _ in range(test)],
    }
    write_dataset(folder, splits, dt=DT, bounds=BOUNDS, connectivity_radius=RADIUS, layout=layout)
    return folder


def test_free_fall_in_3d_trains_rolls_out_and_evaluates(tmp_path):
    data = write_free_fall(tmp_path / "data", "deepmind")
    metadata = json.loads((data / "metadata.json").read_text())
    assert metadata["dim"] == 3 and len(metadata["bounds"]) == 3
    # The statistics (of the free particles): acceleration -g dt^2 along y only, and the same
    # for every particle in every frame.
    np.testing.assert_allclose(metadata["acc_mean"], [0.0, -GDT2, 0.0], rtol=1e-3, atol=1e-7)
    assert max(metadata["acc_std"]) < 1e-3 * GDT2
    assert len(metadata["vel_mean"]) == len(metadata["vel_std"]) == 3

    config = tmp_path / "tiny.toml"
    config.write_text(
        "[model]\nlatent_size = 8\nmlp_hidden_size = 8\nmessage_passing_steps = 2\n"
        "[train]\nsteps = 30\nlog_every = 10\nvalidate_every = 0\ncheckpoint_every = 30\n"
    )
    run = tmp_path / "run"
    cpu = ["--device", "cpu", "--threads", "1"]
    assert main(["train", "--data", str(data), "--out", str(run), "--config", str(config),
                 "--quiet", *cpu]) == 0  # fmt: skip
    assert main(["rollout", "--run", str(run), "--data", str(data), *cpu]) == 0
    test = list(open_dataset(data, "test"))
    n = test[0].n_particles
    for i, trajectory in enumerate(test):
        saved = load_rollout(run / f"rollouts/test/rollout_test_{i}.npz")
        predicted = saved.predicted_rollout
        assert predicted.shape == (FRAMES - HISTORY, n, 3) and np.isfinite(predicted).all()
        np.testing.assert_array_equal(saved.ground_truth_rollout, trajectory.positions[HISTORY:])
        # The obstacles are held to the ground truth.
        still = trajectory.particle_type == 3
        np.testing.assert_array_equal(predicted[:, still], trajectory.positions[HISTORY:, still])

    assert main(["eval", "--run", str(run), "--data", str(data), *cpu]) == 0
    report = json.loads((run / "eval_test.json").read_text())
    model, constant = report["mean"]["model"], report["mean"]["constant_velocity"]
    for name in ("mse@1", "mse@full", "one_step_mse"):
        assert np.isfinite(model[name]) and np.isfinite(constant[name]), name
    # Constant velocity misses a free particle's next position by g dt^2 in y and by nothing
    # in x and z: the MSE (mean over the 3 axes) is (g dt^2)^2 / 3, up to float32 positions.
    one_step = GDT2**2 / 3
    assert constant["one_step_mse"] == pytest.approx(one_step, rel=2e-3)
    assert constant["mse@1"] == pytest.approx(one_step, rel=2e-3)
    # ~0 next to the error of standing still (a per-frame velocity of up to 3e-3 per axis).
    assert constant["one_step_mse"] < 0.05 * report["mean"]["static"]["one_step_mse"]
    # After k steps it is k(k + 1)/2 g dt^2 behind, in every trajectory.
    k = np.arange(1, FRAMES - HISTORY + 1)
    curve = (k * (k + 1) / 2 * GDT2) ** 2 / 3
    for entry in report["trajectories"]:
        np.testing.assert_allclose(entry["constant_velocity"]["mse"], curve, rtol=2e-3)
