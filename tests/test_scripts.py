"""The diagnostics in scripts/: what they print against figures computed here from the data."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from gns.checkpoints import load_simulator
from gns.data import at_frame_stride, open_dataset
from gns.rollout import rollout

SCRIPTS = Path(__file__).resolve().parent.parent / "scripts"

pytestmark = pytest.mark.usefixtures("torch_one_thread")


def run_script(name: str, *args: str) -> list[str]:
    done = subprocess.run(
        [sys.executable, str(SCRIPTS / name), *args], capture_output=True, text=True, check=True
    )
    return done.stdout.splitlines()


def table_rows(lines: list[str]) -> list[list[str]]:
    """The cells of a markdown table's body rows."""
    rows = [line.strip("|").split("|") for line in lines if line.startswith("| ")]
    return [[cell.strip() for cell in row] for row in rows[1:]]


def test_acceleration_fit_bins_every_window_and_sizes_the_target_from_the_data(strided):
    run, native, _ = strided
    lines = run_script("acceleration_fit.py", str(run), str(native), "test", "--every", "1")
    # The oracle: the same windows' true accelerations, from the native frames at stride 3, of
    # the free particles (type 3, kinematic, follows the truth and does not count).
    simulator = load_simulator(run)
    test = open_dataset(native, "test")
    history = simulator.config.model.velocity_history + 1
    accelerations = []
    for trajectory in test:
        p = at_frame_stride(trajectory, 3).positions.astype(np.float64)
        a = p[history:] - 2 * p[history - 1 : -1] + p[history - 2 : -2]
        accelerations.append(a[:, trajectory.particle_type != 3].reshape(-1, 2))
    true = np.concatenate(accelerations)
    head = lines[0]
    assert f"{len(true)} particle-steps from {len(test)} trajectories" in head
    assert f"true acceleration std {true.std(axis=0)} a step" in head
    rows = table_rows(lines)
    assert rows, lines
    assert sum(float(row[1]) for row in rows) == pytest.approx(1.0, abs=0.01)
    assert sum(float(row[4]) for row in rows) == pytest.approx(1.0, abs=0.02)


def test_runout_from_later_starts_matches_a_rollout_measured_here(strided):
    run, native, _ = strided
    simulator = load_simulator(run)
    test = open_dataset(native, "test")
    frames = len(at_frame_stride(test[0], 3).positions)
    last = frames - (simulator.config.model.velocity_history + 2)  # one step to predict
    lines = run_script("runout_from_later_starts.py", str(run), str(native), "test", "--starts",
                       "0", str(last))  # fmt: skip
    rows = table_rows(lines)
    assert [row[0] for row in rows] == [*map(str, range(len(test))), "mean"]

    def width(frame: np.ndarray, free: np.ndarray) -> float:
        x = frame[free, 0]
        return float(np.percentile(x, 99) - np.percentile(x, 1))

    for index, trajectory in enumerate(test):
        free = trajectory.particle_type != 3  # the kinematic type does not count, as in gns eval
        strided_trajectory = at_frame_stride(trajectory, 3)
        truth = width(strided_trajectory.positions[-1], free)
        whole = rollout(simulator, strided_trajectory).predicted_trajectory[-1]
        assert float(rows[index][1]) == pytest.approx(width(whole, free) / truth, abs=0.006)
        # From the last start the model predicts one step of slow motion: the truth's width.
        assert float(rows[index][2]) == pytest.approx(1.0, abs=0.02)
