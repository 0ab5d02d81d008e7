"""Enforced walls (scene.enforce_walls): a rollout puts free particles that a step takes past a
wall back on it and counts every correction; the oracle is the definition written out in numpy
on a network whose output is exactly zero (each step then extrapolates the last velocity).
Also: the setting travels with a model (export, old checkpoints, fine-tuning), validation
counts the corrections and `gns eval` reports them."""

from __future__ import annotations

import dataclasses
import shutil

import numpy as np
import pytest
import torch
from gns.checkpoints import MODEL_FILE, export_model, load_checkpoint, load_simulator
from gns.cli import main
from gns.config import Config, NormalizationConfig, SceneConfig, TrainConfig
from gns.data import Trajectory
from gns.evaluate import evaluate_rollouts
from gns.rollout import load_rollout, rollout, rollout_files
from gns.simulator import LearnedSimulator, Scene
from gns.train import train
from gns.validation import validate
from test_rollout import BOX, FREE, KINEMATIC, TINY, C
from test_train import config, read_csv, trained_run

pytestmark = pytest.mark.usefixtures("torch_one_thread")

LO = np.array([b[0] for b in BOX])
HI = np.array([b[1] for b in BOX])


def still_network(periodic=(False, False), enforce_walls=False) -> LearnedSimulator:
    """A float64 simulator whose network outputs exactly 0: fresh running statistics are mean 0,
    std 1, and a zero last decoder layer gives 0, so x_{t+1} = x_t + (x_t - x_{t-1})."""
    torch.manual_seed(0)
    scene = Scene(
        dim=2, radius=0.1, particle_types=(KINEMATIC, FREE), bounds=BOX, periodic=periodic
    )
    config = Config(
        model=TINY,
        normalization=NormalizationConfig(source="running"),
        scene=SceneConfig(enforce_walls=enforce_walls),
    )
    simulator = LearnedSimulator(scene, config).double()
    last = simulator.model.decoder[-1]
    torch.nn.init.zeros_(last.weight)
    torch.nn.init.zeros_(last.bias)
    return simulator


def heading_for_the_walls(frames=16) -> Trajectory:
    """Free particles moving straight at the floor, the right wall and a corner at up to 0.04
    a frame, one at rest in the middle, and a kinematic particle whose prescribed path goes
    through the floor (it must follow it: it is not the model's to correct)."""
    start = np.array([[0.3, 0.3], [0.8, 0.5], [0.75, 0.2], [0.5, 0.5], [0.4, 0.25]])
    velocity = np.array([[0.0, -0.03], [0.02, 0.0], [0.04, -0.025], [0.0, 0.0], [0.0, -0.02]])
    t = np.arange(frames)[:, None, None]
    types = np.array([FREE, FREE, FREE, FREE, KINEMATIC])
    return Trajectory(
        positions=(start + t * velocity).astype(np.float64),
        particle_type=types,
        key=0,
        source="<test>",
    )


def definition(trajectory: Trajectory, steps: int, periodic=(False, False)):
    """The rollout by hand: extrapolate, wrap periodic axes, put free particles past a wall on
    it, hold kinematic ones to their path. Returns (positions, corrections, largest move)."""
    x = list(trajectory.positions[: C + 1])
    free = trajectory.particle_type != KINEMATIC
    periodic = np.array(periodic)
    corrections, largest = 0, 0.0
    for step in range(steps):
        nxt = 2 * x[-1] - x[-2]
        nxt = np.where(periodic, LO + np.mod(nxt - LO, HI - LO), nxt)
        placed = np.where(periodic, nxt, np.clip(nxt, LO, HI))
        moved = np.linalg.norm(placed - nxt, axis=1) * free
        placed[~free] = trajectory.positions[C + 1 + step][~free]
        corrections += int((moved > 0).sum())
        largest = max(largest, float(moved.max()))
        x.append(placed)
    return np.array(x[C + 1 :]), corrections, largest


def test_particles_past_a_wall_are_put_on_it_and_every_correction_is_counted():
    trajectory = heading_for_the_walls()
    steps = trajectory.num_frames - (C + 1)
    expected, corrections, largest = definition(trajectory, steps)
    assert corrections >= 4 and largest > 0.01  # the case corrects, so the test can fail

    r = rollout(still_network(), trajectory, enforce_walls=True)
    np.testing.assert_allclose(r.predicted_rollout, expected, rtol=0, atol=1e-12)
    assert r.metadata["enforce_walls"] is True
    assert r.metadata["wall_corrections"] == corrections
    assert r.metadata["wall_correction_max"] == pytest.approx(largest, abs=1e-12)
    # The kinematic particle went through the floor, as prescribed.
    assert r.predicted_rollout[-1, 4, 1] < LO[1] - 0.05

    # Without the walls the same particles leave the box, and nothing is counted.
    free = rollout(still_network(), trajectory)
    assert free.metadata["enforce_walls"] is False
    assert "wall_corrections" not in free.metadata
    assert (free.predicted_rollout[-1, :3] < LO).any() and (free.predicted_rollout > HI).any()


def test_the_models_own_setting_is_the_default_and_an_argument_overrides_it():
    trajectory = heading_for_the_walls()
    enforced = still_network(enforce_walls=True)
    assert rollout(enforced, trajectory).metadata["wall_corrections"] > 0
    assert rollout(enforced, trajectory, enforce_walls=False).metadata["enforce_walls"] is False


def test_a_periodic_axis_wraps_and_is_never_put_on_a_wall():
    trajectory = heading_for_the_walls(frames=30)  # long enough to cross x = 0.9
    periodic = (True, False)
    steps = trajectory.num_frames - (C + 1)
    expected, corrections, _ = definition(trajectory, steps, periodic)
    r = rollout(still_network(periodic), trajectory, enforce_walls=True)
    np.testing.assert_allclose(r.predicted_rollout, expected, rtol=0, atol=1e-12)
    assert r.metadata["wall_corrections"] == corrections
    # Particle 1 moves along x only, past x = 0.9 in the data: wrapped, kept inside.
    x = r.predicted_rollout[:, 1, 0]
    assert trajectory.positions[-1, 1, 0] > HI[0] and ((x >= LO[0]) & (x <= HI[0])).all()


def test_walls_need_bounds():
    scene = Scene(dim=2, radius=0.1, particle_types=(FREE,), walls=False)
    simulator = LearnedSimulator(scene, Config(model=TINY))
    trajectory = heading_for_the_walls()
    trajectory = dataclasses.replace(trajectory, particle_type=np.full(5, FREE))
    with pytest.raises(ValueError, match="enforce_walls needs the scene's bounds"):
        rollout(simulator, trajectory, enforce_walls=True)


# ------------------------------------------------------------ the setting travels with a model


def test_export_sets_the_walls_and_older_checkpoints_read_as_free(tmp_path):
    run, data = trained_run(tmp_path / "run", steps=2)
    assert not load_simulator(run).config.scene.enforce_walls
    assert main(["export", "--run", str(run), "--out", str(tmp_path / "m"), "--enforce-walls"]) == 0
    assert load_simulator(tmp_path / "m").config.scene.enforce_walls
    # A checkpoint written before the setting existed has no such key: the walls are free.
    state = load_checkpoint(tmp_path / "m" / MODEL_FILE)
    del state["config"]["scene"]["enforce_walls"]
    torch.save(state, tmp_path / "old.pt")
    assert not load_simulator(tmp_path / "old.pt").config.scene.enforce_walls
    state = export_model(tmp_path / "m", tmp_path / "m2", enforce_walls=False)
    assert state["config"]["scene"]["enforce_walls"] is False


def test_fine_tuning_may_turn_the_walls_on_and_validation_counts_the_corrections(tmp_path):
    run, data = trained_run(tmp_path / "run", steps=2)
    shutil.copy(data / "test.h5", data / "valid.h5")
    validated = config(1, validate_every=1, validation_rollouts=1, validation_rollout_steps=3)
    walls = dataclasses.replace(validated, scene=SceneConfig(enforce_walls=True))
    tuned = train(data, tmp_path / "tuned", walls, progress=False, init_from=run)
    assert tuned.config.scene.enforce_walls
    logged = read_csv(tmp_path / "tuned" / "valid.csv")
    assert logged and all(float(row["wall_corrections"]) >= 0 for row in logged)

    # Validation of the still network on trajectories heading for the walls: the corrections
    # of its rollouts, summed.
    trajectory = heading_for_the_walls()
    steps = trajectory.num_frames - (C + 1)
    _, corrections, _ = definition(trajectory, steps)
    settings = TrainConfig(
        validation_windows=0, validation_rollouts=2, validation_rollout_steps=steps
    )
    figures = validate(still_network(enforce_walls=True), [trajectory] * 2, settings, "cpu")
    assert figures["wall_corrections"] == 2 * corrections
    assert figures["rollout_outside_box"] == 0  # the walls held them
    assert "wall_corrections" not in validate(still_network(), [trajectory], settings, "cpu")


def test_eval_reports_the_corrections_mean_and_worst():
    trajectory = heading_for_the_walls()
    short = dataclasses.replace(trajectory, positions=trajectory.positions[:8])
    rollouts = [rollout(still_network(), t, enforce_walls=True) for t in (trajectory, short)]
    report = evaluate_rollouts(rollouts, workers=1)
    counts = [r.metadata["wall_corrections"] for r in rollouts]
    moves = [r.metadata["wall_correction_max"] for r in rollouts]
    assert counts[0] > counts[1] > 0
    per_rollout = [entry["model"]["wall_corrections"] for entry in report["trajectories"]]
    assert per_rollout == counts
    assert report["mean"]["model"]["wall_corrections"] == pytest.approx(np.mean(counts))
    assert report["mean"]["model"]["wall_correction_max"] == pytest.approx(max(moves))
    assert "wall_corrections" not in report["mean"]["constant_velocity"]


def test_the_command_line_rolls_out_with_the_models_walls_and_eval_reports_them(
    tmp_path, capsys, monkeypatch
):
    monkeypatch.chdir(tmp_path)  # where eval writes a model folder's figures
    run, data = trained_run(tmp_path / "run", steps=2)
    model = tmp_path / "walled"
    assert main(["export", "--run", str(run), "--out", str(model), "--enforce-walls"]) == 0
    common = ["--run", str(model), "--data", str(data), "--threads", "1"]
    for flag, out in (([], "on"), (["--no-enforce-walls"], "off")):
        argv = ["rollout", *common, "--out", str(tmp_path / out), *flag]
        assert main(argv) == 0
    printed = capsys.readouterr().out
    assert printed.count("walls put back") == 2  # two trajectories, walls on
    on = [load_rollout(f) for f in rollout_files(tmp_path / "on", "test")]
    off = [load_rollout(f) for f in rollout_files(tmp_path / "off", "test")]
    assert [r.metadata["enforce_walls"] for r in on + off] == [True] * 2 + [False] * 2
    argv = ["eval", *common, "--rollouts", str(tmp_path / "on"), "--one-step-windows", "0"]
    assert main(argv) == 0
    rows = {line.split()[0]: line.split() for line in capsys.readouterr().out.splitlines() if line}
    expected = np.mean([r.metadata["wall_corrections"] for r in on])
    assert float(rows["wall_corrections"][1]) == pytest.approx(expected, rel=1e-3)
