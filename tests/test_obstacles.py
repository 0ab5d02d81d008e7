"""Static obstacle shapes in the model (issue 26): each trajectory's shapes come from
metadata.json's "obstacles", follow it through a frame stride and a mirror, and reach the
model as the nearest obstacle of its own graph. Oracle: the nearest point of a segment by
projection, in numpy."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from gns import Obstacle, nearest_obstacle_features
from gns.augment import mirror_batch
from gns.checkpoints import load_checkpoint
from gns.cli import main
from gns.config import Config, ModelConfig
from gns.data import DatasetError, open_dataset, write_dataset
from gns.data.convert import convert
from gns.data.metadata import obstacles_json
from gns.data.windows import collate, trajectory_windows
from gns.simulator import LearnedSimulator, Scene

RAMPS = [
    [np.array([[0.2, 0.3], [0.5, 0.2]])],
    [np.array([[0.6, 0.5], [0.8, 0.55], [0.85, 0.7]]), np.array([[0.1, 0.7], [0.3, 0.75]])],
]


def nearest_by_projection(x, polylines, reach):
    """The expected features: unit vector to the nearest point of all segments, times
    1 - d / reach, zero at and beyond reach."""
    out = np.zeros_like(x)
    for i, p in enumerate(x):
        best, nearest = np.inf, None
        for vertices in polylines:
            for a, b in zip(vertices[:-1], vertices[1:], strict=True):
                t = np.clip(np.dot(p - a, b - a) / np.dot(b - a, b - a), 0.0, 1.0)
                q = a + t * (b - a)
                d = np.linalg.norm(q - p)
                if d < best:
                    best, nearest = d, q
        if 0 < best < reach:
            out[i] = (nearest - p) / best * (1 - best / reach)
    return out


def test_the_nearest_obstacle_against_projection_onto_each_segment():
    rng = np.random.default_rng(0)
    x = rng.uniform(0.0, 1.0, (500, 2))
    polylines = RAMPS[0] + RAMPS[1]
    shapes = [Obstacle.polyline(v) for v in polylines]
    for radius, clip in ((0.05, 1.0), (0.02, 6.0)):
        got = nearest_obstacle_features(x, shapes, radius, clip=clip)
        want = nearest_by_projection(x, polylines, radius * clip)
        np.testing.assert_allclose(got, want, atol=1e-12)
        assert (np.linalg.norm(got, axis=1) > 0).sum() > 20  # the test sees obstacles
    # Continuous at the reach: just inside it the feature is ~0; no shapes give zeros.
    a, b = RAMPS[0][0]
    normal = np.array([a[1] - b[1], b[0] - a[0]]) / np.linalg.norm(b - a)
    near = ((a + b) / 2 + 0.0999 * normal)[None]
    assert np.linalg.norm(nearest_obstacle_features(near, shapes[:1], 0.1)) < 2e-3
    assert not nearest_obstacle_features(x, [], 0.1).any()
    with pytest.raises(ValueError, match="clip"):
        nearest_obstacle_features(x, shapes, 0.1, clip=0.0)


def write_ramps(folder, frames=12, layout="deepmind"):
    """Two train and one test trajectory of 30 particles drifting down past their ramps."""
    rng = np.random.default_rng(1)

    def trajectory():
        start = rng.uniform(0.15, 0.85, (30, 2))
        drift = np.arange(frames)[:, None, None] * np.array([0.002, -0.003])
        return {"positions": (start + drift).astype(np.float32), "particle_type": np.full(30, 5)}

    obstacles = {
        "train": {"0": obstacles_json(RAMPS[0]), "1": obstacles_json(RAMPS[1])},
        "test": {"0": obstacles_json(RAMPS[1])},
    }
    write_dataset(
        folder,
        {"train": [trajectory(), trajectory()], "test": [trajectory()]},
        dt=0.0025,
        bounds=((0.0, 1.0), (0.0, 1.0)),
        connectivity_radius=0.05,
        layout=layout,
        extra={"obstacles": obstacles},
    )
    return folder


def assert_same_polylines(got, want):
    assert got is not None and len(got) == len(want)
    for a, b in zip(got, want, strict=True):
        np.testing.assert_array_equal(a, b)


def test_each_trajectory_gets_its_obstacles_and_keeps_them_through_a_frame_stride(tmp_path):
    data = write_ramps(tmp_path / "d")
    train = open_dataset(data, "train")
    for key in (0, 1):
        assert_same_polylines(train[key].obstacles, RAMPS[key])
    strided = tmp_path / "s"
    assert convert(data, strided, "h5", frame_stride=2) == {"train": 4, "test": 1}
    train = open_dataset(strided, "train")
    # Each source trajectory becomes 2 (one per phase), written one after the other.
    for index, source in ((0, 0), (1, 0), (2, 1), (3, 1)):
        assert_same_polylines(train[index].obstacles, RAMPS[source])
    assert_same_polylines(open_dataset(strided, "test")[0].obstacles, RAMPS[1])

    # A trajectory the metadata has no shapes for is refused by key.
    raw = json.loads((data / "metadata.json").read_text())
    del raw["obstacles"]["train"]["1"]
    (data / "metadata.json").write_text(json.dumps(raw))
    with pytest.raises(DatasetError, match="no entry for trajectory key 1"):
        open_dataset(data, "train")[1]
    raw["obstacles"]["train"]["1"] = [{"polyline": [[0.1, 0.2]]}]
    (data / "metadata.json").write_text(json.dumps(raw))
    with pytest.raises(DatasetError, match=r"shape 0 has vertices of shape \(1, 2\)"):
        open_dataset(data, "train")


def test_a_mirrored_window_has_mirrored_obstacles(tmp_path):
    data = write_ramps(tmp_path / "d")
    windows = [next(trajectory_windows(t, 6, [0])) for t in open_dataset(data, "train")]
    batch = collate(windows)
    bounds = ((0.0, 1.0), (0.0, 1.0))
    rng = np.random.default_rng(3)
    mirrored = mirror_batch(batch, [0], bounds, rng)
    flipped = np.random.default_rng(3).random((2, 1)) < 0.5
    for g in range(2):
        x = batch.positions[:, g * 30 : (g + 1) * 30]
        flip = bool(flipped[g, 0])
        np.testing.assert_array_equal(
            mirrored.positions[:, g * 30 : (g + 1) * 30, 0], 1.0 - x[..., 0] if flip else x[..., 0]
        )
        want = [np.column_stack([1.0 - v[:, 0], v[:, 1]]) if flip else v for v in RAMPS[g]]
        assert_same_polylines(mirrored.obstacles[g], want)
        # The mirror keeps each particle's distance to its obstacles.
        features = nearest_by_projection(x[-1].astype(np.float64), RAMPS[g], 0.1)
        after = nearest_by_projection(
            mirrored.positions[-1, g * 30 : (g + 1) * 30].astype(np.float64), want, 0.1
        )
        np.testing.assert_allclose(np.linalg.norm(after, axis=1), np.linalg.norm(features, axis=1))


def tiny_config(**scene):
    model = ModelConfig(latent_size=8, mlp_hidden_size=8, message_passing_steps=1)
    return Config(model=model, scene=Config().scene.__class__(**scene))


def test_each_graph_of_a_batch_sees_its_own_obstacles():
    scene = Scene(dim=2, radius=0.05, particle_types=(5,), obstacles=True, obstacle_clip=2.0)
    simulator = LearnedSimulator(scene, tiny_config()).double()
    rng = np.random.default_rng(2)
    x = rng.uniform(0.1, 0.9, (40, 2))
    sequence = torch.from_numpy(np.repeat(x[:, None], 6, axis=1))
    types = torch.full((40,), 5)
    n_node = torch.tensor([25, 15])
    shapes = [[Obstacle.polyline(v) for v in RAMPS[g]] for g in (0, 1)]
    nodes = simulator.features(sequence, types, n_node, obstacles=shapes)["node_features"]
    want = np.concatenate(
        [nearest_by_projection(x[:25], RAMPS[0], 0.1), nearest_by_projection(x[25:], RAMPS[1], 0.1)]
    )
    np.testing.assert_allclose(nodes[:, -2:].numpy(), want, atol=1e-12)
    assert np.abs(want).sum() > 0
    with pytest.raises(ValueError, match="pass each graph's obstacle shapes"):
        simulator.features(sequence, types, n_node)
    with pytest.raises(ValueError, match="each of the 2 graphs"):
        simulator.features(sequence, types, n_node, obstacles=shapes[:1])


def test_a_dataset_with_obstacles_trains_rolls_out_and_evaluates_from_the_command_line(tmp_path):
    data = write_ramps(tmp_path / "d", frames=14)
    config = tmp_path / "tiny.toml"
    config.write_text(
        "[model]\nlatent_size = 8\nmlp_hidden_size = 8\nmessage_passing_steps = 1\n"
        "[train]\nsteps = 6\nlog_every = 3\nvalidate_every = 0\ncheckpoint_every = 6\n"
        "mirror_axes = [0]\n"
    )
    cpu = ["--device", "cpu", "--threads", "1"]
    run = tmp_path / "run"
    argv = ["train", "--data", str(data), "--out", str(run), "--config", str(config)]
    assert main([*argv, *cpu, "--quiet"]) == 0
    state = load_checkpoint(run / "checkpoints" / "step_000000006.pt")
    assert state["scene"]["obstacles"] is True  # on because the data has obstacles
    assert main(["rollout", "--run", str(run), "--data", str(data), *cpu]) == 0
    assert main(["eval", "--run", str(run), "--data", str(data), *cpu]) == 0
    report = json.loads((run / "eval_test.json").read_text())
    assert np.isfinite(report["mean"]["model"]["mse@full"])

    # Turned off by the config: the same data, no obstacle features.
    config.write_text(config.read_text() + "[scene]\nobstacles = false\n")
    run = tmp_path / "off"
    argv = ["train", "--data", str(data), "--out", str(run), "--config", str(config)]
    assert main([*argv, *cpu, "--quiet"]) == 0
    assert load_checkpoint(run / "checkpoints" / "step_000000006.pt")["scene"]["obstacles"] is False
