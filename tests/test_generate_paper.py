"""The paper's other 2D scenes in `gns generate` (issue 26): waterramps, sandramps,
waterdrop-xl, and continuous with its held-out band of friction angles. Each through the
issue's command (1 train and 1 test trajectory of 40 frames), then its own physics."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from gns import mpm
from gns.cli import main
from gns.data import open_dataset
from gns.data.validate import validate_dataset
from gns.mpm import presets

NEW = ["waterramps", "sandramps", "waterdrop-xl", "continuous"]
G = 9.81


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """made(preset): the folder of the issue's command for that preset, run once."""
    folders = {}

    def make(preset):
        if preset not in folders:
            out = tmp_path_factory.mktemp("paper") / preset
            argv = ["generate", "--preset", preset, "--out", str(out), "--n-train", "1"]
            assert main([*argv, "--n-test", "1", "--frames", "40", "--quiet"]) == 0
            folders[preset] = out
        return folders[preset]

    return make


@pytest.fixture(params=NEW)
def dataset(request, made):
    return request.param, made(request.param)


def test_the_issues_command_gives_finite_data_inside_the_box(dataset):
    preset, out = dataset
    assert [str(problem) for problem in validate_dataset(out)] == []
    for split in ("train", "test"):
        (trajectory,) = open_dataset(out, split)
        box = np.array(open_dataset(out, split).metadata.bounds)
        x = trajectory.positions
        assert x.shape == (40, trajectory.n_particles, 2) and np.isfinite(x).all()
        half_cell = 0.5 / presets.preset_scene(preset, 0, split)[0].grid
        assert np.all(x.min(axis=(0, 1)) >= box[:, 0] - half_cell)
        assert np.all(x.max(axis=(0, 1)) <= box[:, 1] + half_cell)


def test_ramps_hold_one_material_and_static_ramps():
    for preset, kind, frames in (("waterramps", mpm.Water, 601), ("sandramps", mpm.Sand, 401)):
        for index in range(8):
            scene, n_frames, _ = presets.preset_scene(preset, 2, "train", index)
            assert n_frames == frames and 1 <= len(scene.obstacles) <= 3
            assert {type(b.material) for b in scene.blocks} == {kind}


@pytest.mark.parametrize("preset", ["waterramps", "sandramps"])
def test_ramps_obstacles_stay_put_in_the_data(made, preset):
    (trajectory,) = open_dataset(made(preset), "train")
    fixed = trajectory.particle_type == 3
    assert fixed.any()
    np.testing.assert_array_equal(
        trajectory.positions[:, fixed],
        np.broadcast_to(trajectory.positions[:1, fixed], trajectory.positions[:, fixed].shape),
    )


def test_waterdrop_xl_is_a_finer_waterdrop_that_falls_at_g(made):
    """WATERDROP-XL: the drop of waterdrop at 1.5 times the resolution (2.25 times the
    particles) and radius 0.01; at rest in the air, it falls at g."""
    out = made("waterdrop-xl")
    scene, _, seed = presets.preset_scene("waterdrop-xl", 0)
    plain, _, plain_seed = presets.preset_scene("waterdrop", 0)
    assert scene.blocks == plain.blocks and scene.grid == 1.5 * plain.grid
    n, n_plain = (
        len(mpm.particles(s, k)["positions"]) for s, k in ((scene, seed), (plain, plain_seed))
    )
    assert n / n_plain == pytest.approx(2.25, rel=0.1)
    meta = json.loads((out / "metadata.json").read_text())
    assert meta["default_connectivity_radius"] == pytest.approx(0.01)
    (trajectory,) = open_dataset(out, "train")
    y = trajectory.positions[:6, :, 1].astype(np.float64).mean(axis=1)
    acceleration = (y[2:] - 2 * y[1:-1] + y[:-2]) / scene.frame_dt**2
    np.testing.assert_allclose(acceleration, -G, rtol=0.05)


def test_continuous_holds_30_to_55_degrees_out_of_train_only(made):
    out = made("continuous")
    meta = json.loads((out / "metadata.json").read_text())
    assert meta["generator"]["held_out_friction_angle_deg"] == [30.0, 55.0]
    assert meta["generator"]["held_out_of"] == "train"

    def angles(split):
        return np.array(
            [
                presets.preset_scene("continuous", 0, split, i)[0]
                .blocks[0]
                .material.friction_angle_deg
                for i in range(300)
            ]
        )

    train, test = angles("train"), angles("test")
    band = (train > 30) & (train < 55)
    assert not band.any() and train.min() >= 1 and train.max() <= 80
    # Both sides of the band are drawn, in proportion to their widths (29 and 25 degrees).
    assert abs((train < 30).mean() - 29 / 54) < 0.08
    # The test split covers the whole range, the band included.
    inside = ((test > 30) & (test < 55)).mean()
    assert abs(inside - 25 / 79) < 0.08 and test.max() > 70 and test.min() < 10
    # The model sees tan(angle) as the global feature.
    scene = presets.preset_scene("continuous", 0, "test", 0)[0]
    angle = scene.blocks[0].material.friction_angle_deg
    assert scene.context == [pytest.approx(math.tan(math.radians(angle)))]


def test_eval_draws_error_against_friction_angle_with_the_band_marked(
    tmp_path, capsys, monkeypatch
):
    """Figure C.5 from `gns eval` on continuous data: rollouts whose error grows with the
    angle by construction (prediction = truth + angle / 1000 in x) give per-trajectory MSE
    (angle / 1000)^2 / 2 at the angle read back from the global feature, flagged in or out
    of the held-out band."""
    from gns.rollout import Rollout, rollout_path, save_rollout

    data = tmp_path / "data"
    assert main(["generate", "--preset", "continuous", "--out", str(data), "--n-train", "1",
                 "--n-test", "4", "--frames", "10", "--quiet"]) == 0  # fmt: skip
    folder = tmp_path / "run" / "rollouts" / "test"
    folder.mkdir(parents=True)
    expected = []
    for index, t in enumerate(open_dataset(data, "test")):
        angle = math.degrees(math.atan(float(t.step_context[0, 0])))
        x = t.positions.astype(np.float64)
        save_rollout(
            rollout_path(folder, "test", index),
            Rollout(
                initial_positions=x[:6],
                predicted_rollout=x[6:] + [angle / 1000, 0.0],
                ground_truth_rollout=x[6:],
                particle_type=t.particle_type,
                step_context=t.step_context[:-1],
                metadata={"trajectory": index},
            ),
        )
        expected.append((angle, (angle / 1000) ** 2 / 2))
    # Any model names where the output goes (./NAME for a model folder); without one-step
    # errors eval never loads it.
    monkeypatch.chdir(tmp_path)
    argv = ["eval", "--run", "sand2d-taichi", "--rollouts", str(folder), "--data", str(data)]
    assert main([*argv, "--split", "test", "--one-step-windows", "0"]) == 0
    assert "in the band held out of training (30-55 degrees)" in capsys.readouterr().out
    out = tmp_path / "sand2d-taichi"
    written = json.loads((out / "eval_test.json").read_text())["generalisation"]
    assert written["held_out"] == [30.0, 55.0]
    np.testing.assert_allclose(written["angle"], [a for a, _ in expected], rtol=1e-5)
    np.testing.assert_allclose(written["model"], [e for _, e in expected], rtol=1e-4)
    assert written["in_band"] == [30 < a < 55 for a, _ in expected]
    assert (out / "generalisation_test.png").read_bytes()[:4] == b"\x89PNG"
