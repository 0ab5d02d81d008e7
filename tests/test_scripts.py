"""The diagnostics in scripts/: what they print against figures computed here from the data."""

from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from gns.checkpoints import load_simulator
from gns.data import at_frame_stride, open_dataset
from gns.mpm import lattice
from gns.probes import block_history, kick_removed
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


def load_script(name: str):
    """A script in scripts/ as a module, to call its functions with a stand-in simulator."""
    spec = importlib.util.spec_from_file_location(name.removesuffix(".py"), SCRIPTS / name)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


class Stepper:
    """A stand-in simulator that steps its input by the Euler update with `acceleration` (per
    step^2, along y) and keeps what it was given."""

    def __init__(self, dt: float, acceleration: float, velocity_history: int = 5):
        self.scene = SimpleNamespace(dt=dt)
        self.config = SimpleNamespace(model=SimpleNamespace(velocity_history=velocity_history))
        self.acceleration = acceleration

    def predict_positions(self, positions, particle_type, context=None):
        self.given = positions.numpy().astype(np.float64)
        last, before = positions[:, -1].double(), positions[:, -2].double()
        return 2 * last - before + torch.tensor([0.0, self.acceleration], dtype=torch.float64)


@pytest.mark.parametrize("fraction", [1.0, 0.0, 0.5])
def test_free_fall_probe_reads_a_simulators_fall_in_g(fraction):
    probe = load_script("free_fall_probe.py")
    dt = 0.0075
    g_step = 9.81 * dt**2
    stepper = Stepper(dt, -fraction * g_step)
    block = lattice((0.4, 0.45), (0.2, 0.2), 1 / 128)
    mean, bottom, top = probe.fall_in_g(stepper, block, 0.5, 6)
    assert (mean, bottom, top) == pytest.approx((fraction,) * 3, abs=1e-9)
    # What the simulator was given: 6 frames of free fall (every step's acceleration -g along y,
    # none along x), at rest in the last, the block itself there.
    history = stepper.given
    assert history.shape == (len(block), 6, 2)
    acceleration = history[:, 2:] - 2 * history[:, 1:-1] + history[:, :-2]
    # (float32 positions near 0.5: round-off 3e-8 against 5.5e-4 a step)
    np.testing.assert_allclose(acceleration[..., 1], -g_step, rtol=1e-3)
    np.testing.assert_allclose(acceleration[..., 0], 0.0, atol=1e-7)
    np.testing.assert_allclose(history[:, -1], history[:, -2], atol=1e-7)
    np.testing.assert_allclose(history[:, -1], block, atol=1e-7)
    # --speed: falling at 1.5 m/s at the last input frame, still at g throughout.
    mean, _, _ = probe.fall_in_g(stepper, block, 0.5, 6, 1.5)
    assert mean == pytest.approx(fraction, abs=1e-9)
    history = stepper.given
    acceleration = history[:, 2:] - 2 * history[:, 1:-1] + history[:, :-2]
    np.testing.assert_allclose(acceleration[..., 1], -g_step, rtol=1e-3)
    np.testing.assert_allclose(
        history[:, -1] - history[:, -2], [[0.0, -1.5 * dt]] * len(block), atol=1e-7
    )


def test_free_fall_probe_averages_a_prediction_over_the_training_noise():
    """A stepper that continues its input at g, given noisy input, is off by the noise in
    each draw (the training's random walk, its last velocity's std as asked); averaged over
    the draws and read against the clean input, the fall is g again."""
    probe = load_script("free_fall_probe.py")
    dt, std = 0.0075, 2e-4
    g_step = 9.81 * dt**2
    stepper = Stepper(dt, -g_step)
    block = lattice((0.4, 0.45), (0.2, 0.2), 1 / 128)
    mean, bottom, top = probe.fall_in_g(stepper, block, 0.5, 6, noise=std, draws=200)
    noise = stepper.given - block_history(block, 6, g_step)  # the last draw's
    assert np.std(noise[:, -1] - noise[:, -2]) == pytest.approx(std, rel=0.1)
    # One draw moves a particle's fall by about 3 std (1 g); the mean over a row's 26
    # particles and 200 draws by 0.02 g, over all 676 by 0.003 g.
    assert (bottom, top) == pytest.approx((1.0, 1.0), abs=0.1)
    assert mean == pytest.approx(1.0, abs=0.02)


class Smoother(Stepper):
    """A stand-in that falls at g and removes the share `up` of each particle's last velocity
    deviation from the block's median velocity where it points up, `down` where it points down."""

    def __init__(self, dt: float, up: float, down: float):
        super().__init__(dt, -9.81 * dt**2)
        self.up, self.down = up, down

    def predict_positions(self, positions, particle_type, context=None):
        following = super().predict_positions(positions, particle_type, context)
        velocity = (positions[:, -1] - positions[:, -2]).double()
        deviation = velocity - velocity.median(dim=0).values
        share = torch.where(deviation > 0, self.up, self.down)
        return following - share * deviation


@pytest.mark.parametrize("up, down", [(1.0, 1.0), (0.0, 0.0), (0.8, 0.3)])
def test_the_kick_probe_reads_the_share_of_a_kick_a_simulator_undoes(up, down):
    """The top row's kick out of the block is up, the bottom row's down, the middle row's
    (out, in) is (down, up): each reads the stand-in's share for that direction."""
    dt = 0.0075
    block = lattice((0.4, 0.45), (0.2, 0.2), 1 / 128)
    removed = kick_removed(Smoother(dt, up, down), block, None, 0, 1e-3)
    assert list(removed) == ["bottom", "middle", "top"]
    expected = {"bottom": (down, up), "middle": (down, up), "top": (up, down)}
    for row, pair in expected.items():
        # float32 positions near 0.5 against a kick of 1e-3: round-off below 1e-4 of it
        assert removed[row] == pytest.approx(pair, abs=1e-3), row
    with pytest.raises(ValueError, match="kick must be a finite number > 0, got 0.0"):
        kick_removed(Smoother(dt, up, down), block, None, 0, 0.0)


def test_free_fall_probe_runs_on_a_trained_model(strided):
    run, _, _ = strided
    [line] = run_script("free_fall_probe.py", str(run))
    assert re.fullmatch(
        rf"{re.escape(str(run))}: falls at -?\d+\.\d\d g \(bottom row -?\d+\.\d\d g, top row "
        r"-?\d+\.\d\d g\)",
        line,
    ), line
    _, kick = run_script("free_fall_probe.py", str(run), "--kick", "1e-3")
    share = r"-?\d+\.\d\d / -?\d+\.\d\d"
    assert re.fullmatch(
        rf"{re.escape(str(run))}: undoes of a kick of 0.001 \(out / in\): bottom {share}, "
        rf"middle {share}, top {share}",
        kick,
    ), kick


def test_free_fall_probe_names_a_model_it_cannot_find(tmp_path):
    missing = tmp_path / "step_000003000.pt"
    done = subprocess.run(
        [sys.executable, str(SCRIPTS / "free_fall_probe.py"), str(missing)],
        capture_output=True,
        text=True,
    )
    assert done.returncode == 1 and "Traceback" not in done.stderr, done.stderr
    assert done.stderr.startswith(f"{missing}: no such file or folder"), done.stderr
