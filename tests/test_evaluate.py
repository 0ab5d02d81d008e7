"""Evaluation of runs: one-step errors, rollout metrics next to the baselines, the deposit
(runout, pile height, density, fronts) against the truth's, the rest test, and the CLI, on
data whose frames are finer than the model's step too."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from data_helpers import SAND
from gns.batches import batch_tensors
from gns.cli import main
from gns.config import Config, ModelConfig
from gns.data.trajectory import Trajectory
from gns.data.windows import collate, trajectory_windows, window_keys
from gns.deposit import front_positions, runout_extent
from gns.evaluate import (
    evaluate_rollouts,
    mean_neighbours,
    one_step_errors,
    one_step_predictions,
    outside_box,
    rest_summary,
    rest_test,
)
from gns.rollout import Rollout, load_rollout, save_rollout
from gns.simulator import LearnedSimulator, Scene
from test_train import damped_motion, make_dataset

pytestmark = pytest.mark.usefixtures("torch_one_thread")

TINY = Config(model=ModelConfig(latent_size=8, mlp_hidden_size=8, message_passing_steps=2))


def zero_acceleration_simulator(context: bool = True) -> LearnedSimulator:
    """A simulator whose decoder outputs 0 and whose normaliser is fresh (mean 0, std 1): it
    predicts zero acceleration, i.e. the constant-velocity step."""
    scene = Scene(dim=2, radius=0.015, particle_types=(3, 5), bounds=((0.1, 0.9),) * 2,
                  walls=True, context_size=1 if context else 0)  # fmt: skip
    simulator = LearnedSimulator(scene, TINY)
    torch.nn.init.zeros_(simulator.model.decoder[-1].weight)
    torch.nn.init.zeros_(simulator.model.decoder[-1].bias)
    return simulator


def test_one_step_errors_of_a_zero_acceleration_model_equal_the_baseline(tmp_path):
    from gns.data import open_dataset

    trajectories = list(open_dataset(make_dataset(tmp_path / "data")))
    errors = one_step_errors(zero_acceleration_simulator(), trajectories)
    # By hand: each window's constant-velocity and static guesses against its next frame.
    total, held, count = 0.0, 0.0, 0
    for t in trajectories:
        x = t.positions.astype(np.float64)
        free = t.particle_type != 3
        for start in range(t.num_frames - 6):
            guess = 2 * x[start + 5] - x[start + 4]
            total += np.mean(np.square(guess - x[start + 6])[free])
            held += np.mean(np.square(x[start + 5] - x[start + 6])[free])
            count += 1
    assert errors["constant_velocity"] == pytest.approx(total / count, rel=1e-6)
    assert errors["static"] == pytest.approx(held / count, rel=1e-6)
    assert errors["model"] == pytest.approx(errors["constant_velocity"], rel=1e-5)


def several_clouds(sizes: tuple[int, ...], frames: int = 10) -> list[Trajectory]:
    """Damped motion of clouds of different sizes, each with a context that changes frame by
    frame (so that a window's own context must reach its own graph)."""
    rng = np.random.default_rng(1)
    out = []
    for key, n in enumerate(sizes):
        t = damped_motion(rng, frames, n, key)
        context = rng.uniform(0.0, 1.0, size=(frames, 1)).astype(np.float32)
        out.append(Trajectory(t.positions, t.particle_type, context, key=key))
    return out


@pytest.mark.parametrize("global_latent", [False, True])
def test_one_step_predictions_packed_together_equal_those_of_each_window_alone(global_latent):
    # One window at a time, as one_step_predictions ran before it packed windows: the oracle.
    scene = Scene(dim=2, radius=0.08, particle_types=(3, 5), bounds=((0.1, 0.9),) * 2,
                  walls=True, context_size=1)  # fmt: skip
    torch.manual_seed(0)
    model = dataclasses.replace(TINY.model, global_latent=global_latent)
    simulator = LearnedSimulator(scene, dataclasses.replace(TINY, model=model)).eval()
    trajectories = several_clouds((24, 40, 17))
    pairs = window_keys(trajectories, 6)
    # A budget of 64 particles packs 1 to 3 windows a batch, of mixed sizes.
    packed = list(one_step_predictions(simulator, trajectories, pairs, max_particles=64))
    assert len(packed) == len(pairs)
    errors = []
    for (k, start), (sequence, truth, predicted, free) in zip(pairs, packed, strict=True):
        batch = collate([next(trajectory_windows(trajectories[k], 6, [start]))])
        t = batch_tensors(batch, torch.device("cpu"))
        with torch.no_grad():
            alone = simulator.predict_positions(
                t["position_sequence"], t["particle_type"], t["n_node"], t["context"]
            )
        assert torch.equal(sequence, t["position_sequence"])
        assert torch.equal(truth, t["next_position"])
        assert torch.equal(free, torch.from_numpy(trajectories[k].particle_type != 3))
        torch.testing.assert_close(predicted, alone, rtol=1e-6, atol=1e-7)
        assert not torch.equal(alone, truth)
        errors.append(float((alone.double() - truth.double())[free].square().mean()))
    # one_step_errors packs every window into one batch here: the mean of the windows' own.
    mean = one_step_errors(simulator, trajectories)["model"]
    assert mean == pytest.approx(np.mean(errors), rel=1e-5)


def synthetic_rollout(predicted_offset: float = 0.0, diverged_at: int | None = None) -> Rollout:
    """Particles falling with constant acceleration g; the prediction is the truth + offset."""
    frames, n = 20, 10
    rng = np.random.default_rng(0)
    start = rng.uniform(0.3, 0.7, size=(n, 2))
    t = np.arange(frames, dtype=np.float64)[:, None, None]
    g = np.array([0.0, -1e-4])
    positions = start[None] + 0.5 * g * t**2
    types = np.full(n, 5)
    types[-1] = 3
    truth = positions[6:]
    predicted = truth + predicted_offset
    predicted[:, -1] = truth[:, -1]
    metadata = {"bounds": [[0.1, 0.9]] * 2, "kinematic_particle_types": [3], "trajectory": 0}
    if diverged_at is not None:
        predicted, truth = predicted[:diverged_at], truth[:diverged_at]
        metadata["diverged_at_step"] = diverged_at
    return Rollout(positions[:6], predicted, truth, types, metadata=metadata)


def test_rollout_metrics_of_a_perfect_model_and_the_baseline_by_hand():
    report = evaluate_rollouts([synthetic_rollout()], horizons=(1, 5, None))
    model, baseline = report["mean"]["model"], report["mean"]["constant_velocity"]
    assert model["mse@full"] == 0.0 and model["ot_mean"] == pytest.approx(0.0, abs=1e-18)
    assert model["mmd_mean"] == pytest.approx(0.0, abs=1e-12) and model["finite"] == 1.0
    # Constant velocity after k steps, by hand: x_t = x_0 + g t^2 / 2, the last history
    # velocity is x_5 - x_4 = 4.5 g, so x_{5+k} - (x_5 + 4.5 g k) = g (k^2 + k) / 2.
    k = np.arange(1, 15, dtype=np.float64)
    miss = (1e-4 * (k * k + k) / 2) ** 2 / 2  # squared miss on one axis of two
    assert baseline["mse@full"] == pytest.approx(miss.mean(), rel=1e-9)
    assert baseline["mse@1"] == pytest.approx(miss[0], rel=1e-9)
    assert baseline["mse@5"] == pytest.approx(miss[:5].mean(), rel=1e-9)
    # Static after k steps: x_{5+k} - x_5 = g ((5 + k)^2 - 25) / 2 = g (k^2 + 10 k) / 2.
    static = report["mean"]["static"]
    fell = (1e-4 * (k * k + 10 * k) / 2) ** 2 / 2
    assert static["mse@full"] == pytest.approx(fell.mean(), rel=1e-9)
    assert static["mse@1"] == pytest.approx(fell[0], rel=1e-9)
    # A rigid shift of every free particle: W2^2 is the squared shift, like the MSE.
    shifted = evaluate_rollouts([synthetic_rollout(predicted_offset=0.01)])["mean"]["model"]
    assert shifted["mse@full"] == pytest.approx(1e-4, rel=1e-9)
    # W2^2 is in squared distance (summed over axes): the shift's squared length, 2e-4.
    assert shifted["ot_mean"] == pytest.approx(2e-4, rel=1e-6)


def test_deposit_of_the_model_the_baselines_and_the_truth_by_hand():
    report = evaluate_rollouts([synthetic_rollout()], horizons=(1, None))
    (entry,) = report["trajectories"]
    truth, static = entry["ground_truth"], entry["static"]
    free = synthetic_rollout().particle_type != 3
    positions = synthetic_rollout().ground_truth_rollout
    # The particles only fall: x never changes, so every runout is that of the start.
    start = positions[0, free]
    assert truth["runout"] == runout_extent(start)
    for name in ("model", "constant_velocity", "static", "ground_truth"):
        assert entry[name]["runout_ratio"] == 1.0
        assert len(entry[name]["front_x_p1"]) == len(entry[name]["front_x_p99"]) == 14
    # Every free particle falls by the same amount, so the 99th percentile of y falls by it
    # too: the static pile (frame 5 held) stands g (19^2 - 5^2) / 2 above the truth's
    # (frame 19), from the box's floor y = 0.1.
    assert truth["pile_height"] == pytest.approx(np.percentile(positions[-1, free, 1], 99) - 0.1)
    assert static["pile_height"] - truth["pile_height"] == pytest.approx(1e-4 * 336 / 2)
    assert static["height_ratio"] == pytest.approx(static["pile_height"] / truth["pile_height"])
    assert entry["model"]["height_ratio"] == truth["height_ratio"] == 1.0
    np.testing.assert_array_equal(
        np.stack([truth["front_x_p1"], truth["front_x_p99"]], axis=1),
        front_positions(positions, free),
    )
    # The means over trajectories, the truth's among them.
    assert report["mean"]["ground_truth"]["runout"] == truth["runout"]
    assert report["mean"]["static"]["height_ratio"] == static["height_ratio"]
    assert "front_x_p1" not in report["mean"]["model"] and "mse" not in report["mean"]["model"]


def test_density_through_the_rollout_against_a_pair_count():
    # The model's frame 7 squeezed to half its size about its centre (a landing that packs),
    # every other frame the truth's: its worst density is that frame's, the last frame's is
    # right. The baselines move the particles rigidly: 1 at every frame.
    rollout = synthetic_rollout()
    rollout.metadata["connectivity_radius"] = radius = 0.15
    free = rollout.particle_type != 3
    frame = rollout.predicted_rollout[7]
    centre = frame[free].mean(axis=0)
    frame[free] = centre + 0.5 * (frame[free] - centre)

    def neighbours(x: np.ndarray) -> float:
        d = np.linalg.norm(x[:, None] - x[None], axis=-1)
        return float(((d <= radius).sum() - len(x)) / len(x))

    (entry,) = evaluate_rollouts([rollout])["trajectories"]
    model, truth = entry["model"], entry["ground_truth"]
    np.testing.assert_allclose(
        model["neighbours_by_frame"], [neighbours(f[free]) for f in rollout.predicted_rollout]
    )
    worst = neighbours(frame[free]) / neighbours(rollout.ground_truth_rollout[7, free])
    assert worst > 1.5
    assert model["density_ratio_max"] == pytest.approx(worst, rel=1e-12)
    assert model["density_ratio"] == truth["density_ratio_max"] == 1.0
    assert entry["static"]["density_ratio_max"] == pytest.approx(1.0, rel=1e-12)
    json.dumps(entry)  # the curves are plain lists
    # A diverged rollout packs infinitely at its worst, in the mean over trajectories too.
    bad = synthetic_rollout(diverged_at=3)
    bad.metadata["connectivity_radius"] = radius
    report = evaluate_rollouts([rollout, bad])
    assert report["mean"]["model"]["density_ratio_max"] == np.inf
    assert report["mean"]["static"]["density_ratio_max"] == pytest.approx(1.0, rel=1e-12)


def test_without_bounds_the_floor_is_the_truths_lowest_particle_at_frame_0():
    rollout = synthetic_rollout()
    del rollout.metadata["bounds"]
    (entry,) = evaluate_rollouts([rollout])["trajectories"]
    free = rollout.particle_type != 3
    floor = rollout.initial_positions[0, :, 1].min()  # kinematic particles included
    top = np.percentile(rollout.ground_truth_rollout[-1, free, 1], 99)
    assert entry["ground_truth"]["pile_height"] == pytest.approx(top - floor, rel=1e-12)
    assert "outside_box" not in entry["ground_truth"]


def test_a_diverged_rollout_is_infinitely_wrong_not_missing():
    good, bad = synthetic_rollout(), synthetic_rollout(diverged_at=3)
    report = evaluate_rollouts([good, bad], horizons=(1, 5, None))
    model = report["mean"]["model"]
    assert model["mse@1"] == 0.0  # both got one step right
    assert model["mse@5"] == np.inf and model["mse@full"] == np.inf
    assert model["finite"] == 0.5
    assert report["trajectories"][1]["diverged_at_step"] == 3
    # It never reached the last frame: no deposit there, but its fronts while it lasted.
    diverged = report["trajectories"][1]["model"]
    assert diverged["runout"] == diverged["runout_ratio"] == diverged["height_ratio"] == np.inf
    assert model["runout_ratio"] == np.inf and len(diverged["front_x_p99"]) == 3
    assert report["mean"]["static"]["runout_ratio"] == 1.0
    first = evaluate_rollouts([synthetic_rollout(diverged_at=0), good])
    assert first["mean"]["model"]["mse@full"] == np.inf
    assert first["mean"]["model"]["runout_ratio"] == np.inf
    assert np.isfinite(first["mean"]["constant_velocity"]["mse@full"])
    assert np.isfinite(first["mean"]["static"]["mse@full"])
    assert first["trajectories"][0]["ground_truth"] is None


def test_outside_box_by_hand():
    positions = np.array([[[0.5, 0.5], [0.95, 0.2]], [[0.05, 0.5], [0.5, 0.5]]])
    assert outside_box(positions, [[0.1, 0.9], [0.1, 0.9]]) == pytest.approx(0.05)
    assert outside_box(positions[:, :1][:1], [[0.1, 0.9], [0.1, 0.9]]) == 0.0


def scipy_mean_neighbours(x: np.ndarray, radius: float, boxsize=None) -> float:
    """The oracle: other particles within radius (inclusive), by scipy's k-d tree."""
    from scipy.spatial import cKDTree

    pairs = cKDTree(x, boxsize=boxsize).query_pairs(radius, output_type="ndarray")
    return 2 * len(pairs) / len(x)


def test_mean_neighbours_against_scipy_open_and_periodic():
    rng = np.random.default_rng(3)
    x = rng.uniform(0.1, 0.9, size=(500, 2))
    assert mean_neighbours(x, 0.05) == pytest.approx(scipy_mean_neighbours(x, 0.05), rel=1e-12)
    bounds = [[0.1, 0.9], [0.1, 0.9]]
    periodic = mean_neighbours(x, 0.05, bounds, [True, True])
    assert periodic == pytest.approx(scipy_mean_neighbours(x - 0.1, 0.05, boxsize=0.8), rel=1e-12)
    assert periodic > mean_neighbours(x, 0.05)  # the images across the edges count
    assert mean_neighbours(np.zeros((0, 2)), 0.05) == 0.0


def test_density_ratio_shows_a_rollout_that_packs_its_particles_closer():
    rollout = synthetic_rollout()
    rng = np.random.default_rng(4)
    n = rollout.initial_positions.shape[1]
    truth = rollout.ground_truth_rollout.copy()
    truth[-1] = rng.uniform(0.3, 0.7, size=(n, 2))
    packed = truth.copy()
    packed[-1] = 0.5 + 0.5 * (truth[-1] - 0.5)  # the last frame shrunk to half its size
    radius = 0.15
    metadata = {**rollout.metadata, "connectivity_radius": radius}
    report = evaluate_rollouts(
        [
            Rollout(
                rollout.initial_positions, packed, truth, rollout.particle_type, metadata=metadata
            )
        ]
    )
    free = rollout.particle_type != 3
    expected = scipy_mean_neighbours(packed[-1, free], radius) / scipy_mean_neighbours(
        truth[-1, free], radius
    )
    assert expected > 1.5  # a real compaction, not a rounding
    assert report["mean"]["model"]["density_ratio"] == pytest.approx(expected, rel=1e-12)
    assert report["mean"]["ground_truth"]["density_ratio"] == 1.0
    neighbours = scipy_mean_neighbours(truth[-1, free], radius)
    assert report["mean"]["ground_truth"]["neighbours"] == pytest.approx(neighbours, rel=1e-12)
    # Without a radius in the metadata there is nothing to count against.
    assert "density_ratio" not in evaluate_rollouts([rollout])["mean"]["model"]


def test_train_rollout_eval_commands_end_to_end(tmp_path, capsys):
    data = make_dataset(tmp_path / "data", frames=14)
    (data / "valid.h5").rename(data / "test.h5")
    config = tmp_path / "tiny.toml"
    config.write_text(
        "[model]\nlatent_size = 8\nmlp_hidden_size = 8\nmessage_passing_steps = 2\n"
        "[train]\nsteps = 4\nlog_every = 2\nvalidate_every = 0\ncheckpoint_every = 2\n"
    )
    run = tmp_path / "run"
    assert main(["train", "--data", str(data), "--out", str(run), "--config", str(config),
                 "--quiet", "--threads", "1"]) == 0  # fmt: skip
    assert main(["rollout", "--run", str(run), "--data", str(data), "--deepmind"]) == 0
    printed = capsys.readouterr().out
    assert "ms/step" in printed and "graph" in printed and "model" in printed
    saved = load_rollout(run / "rollouts/test/rollout_test_1.npz")
    assert saved.num_steps == 14 - 6 and (run / "rollouts/test/rollout_test_1.pkl").exists()
    # --float64 rolls out in float64, close to the float32 rollout over these few steps.
    out64 = tmp_path / "r64"
    args = ["rollout", "--run", str(run), "--data", str(data), "--float64", "--out", str(out64)]
    assert main(args) == 0
    wide = load_rollout(out64 / "rollout_test_1.npz").predicted_rollout
    assert wide.dtype == np.float64
    np.testing.assert_allclose(wide, saved.predicted_rollout, atol=1e-5)
    assert main(["eval", "--run", str(run), "--data", str(data), "--every", "4"]) == 0
    report = json.loads((run / "eval_test.json").read_text())
    assert len(report["trajectories"]) == 2
    deposit = {"runout", "pile_height", "neighbours", "runout_ratio", "height_ratio"}
    deposit |= {"density_ratio"}
    for name in ("model", "constant_velocity", "static"):
        assert {"mse@1", "mse@5", "mse@full", "ot_mean", "mmd_mean", "one_step_mse"} <= set(
            report["mean"][name]
        )
        assert deposit <= set(report["mean"][name])
        for entry in report["trajectories"]:
            assert len(entry[name]["front_x_p1"]) == len(entry[name]["front_x_p99"]) == 8
    assert deposit | {"outside_box"} <= set(report["mean"]["ground_truth"])
    table = capsys.readouterr().out
    assert "const. velocity" in table and "one_step_mse" in table
    header = next(line for line in table.splitlines() if line.startswith("metric"))
    assert header.split() == [
        "metric", "model", "const.", "velocity", "static", "truth", "cv/model", "static/model"
    ]  # fmt: skip
    (runout,) = [line.split() for line in table.splitlines() if line.startswith("runout_ratio")]
    assert [float(v) for v in runout[1:]] == pytest.approx(
        [report["mean"][n]["runout_ratio"] for n in ("model", "constant_velocity", "static")]
        + [1.0],
        rel=1e-3,
    )
    # --run may name a checkpoint file (here the one the rollouts were made with): the report
    # goes beside it.
    checkpoint = Path(load_rollout(out64 / "rollout_test_0.npz").metadata["checkpoint"])
    args = ["eval", "--run", str(checkpoint), "--data", str(data), "--rollouts", str(out64)]
    assert main([*args, "--checkpoint", "best"]) == 2  # best.pt is for run folders
    assert main([*args, "--every", "4", "--rest-steps", "3", "--one-step-windows", "0"]) == 0
    assert "held still for 3 steps" in capsys.readouterr().out
    beside = json.loads((checkpoint.parent / "eval_test.json").read_text())
    assert beside["rollouts"] == [str(out64 / f"rollout_test_{i}.npz") for i in (0, 1)]
    rest = beside["rest"]
    assert rest == rest_summary(rest["trajectories"], 3)
    assert rest["steps"] == 3 and len(rest["trajectories"]) == 2
    assert rest["mean"]["max_displacement"] == max(
        t["max_displacement"] for t in rest["trajectories"]
    )
    assert main([*args, "--rest-steps", "-1"]) == 2
    # Bad input is an error message and exit status 2, not a traceback.
    assert main(["eval", "--run", str(tmp_path / "nowhere"), "--data", str(data)]) == 2
    assert "argument --run: no such file or folder" in capsys.readouterr().err


def test_eval_on_finer_data_scores_the_frames_the_model_steps_between(strided, tmp_path, capsys):
    run, native, converted = strided
    figures = {}
    for name, data in (("native", native), ("converted", converted)):
        rollouts = tmp_path / name
        argv = ["--run", str(run), "--data", str(data)]
        assert main(["rollout", *argv, "--out", str(rollouts)]) == 0
        assert main(["eval", *argv, "--rollouts", str(rollouts), "--rest-steps", "2"]) == 0
        figures[name] = json.loads((run / "eval_test.json").read_text())
        printed = capsys.readouterr().out
        note = "the data's frames are 2.5 ms apart, the model's steps 7.5 ms: every 3rd frame"
        assert (f"one-step errors and rest test: {note}" in printed) == (name == "native")
    ours, theirs = figures["native"], figures["converted"]
    assert (ours["frame_stride"], theirs["frame_stride"]) == (3, 1)
    # The same frames as on the data gns convert wrote (the oracle), so the same figures: the
    # rollouts', the one-step errors (over the same 3 windows of each test trajectory) and the
    # rest test (the last frame of those taken, frame 24).
    assert ours["mean"] == theirs["mean"] and ours["rest"] == theirs["rest"]
    assert ours["mean"]["model"]["one_step_mse"] > 0

    # Rollouts that say they ran on other frames than the checkpoint reads are refused.
    made = tmp_path / "native"
    for path in made.glob("*.npz"):
        r = load_rollout(path)
        r.metadata["frame_stride"] = 1
        save_rollout(path, r)
    (run / "eval_test.json").unlink()
    argv = ["eval", "--run", str(run), "--data", str(native), "--rollouts", str(made)]
    assert main(argv) == 2
    assert (
        f"gns eval: error: the rollouts in {made} were made at frame stride 1, but "
        in capsys.readouterr().err
    )
    assert not (run / "eval_test.json").exists()


def held_pile(context: bool) -> Trajectory:
    """A 6 x 6 lattice of spacing 0.01 (neighbours at 0.01 and 0.014 within the radius 0.015,
    the next at 0.02: no pair near the radius), whose last step moved by 1e-4 and 3e-4; its
    corner particle is kinematic (type 3)."""
    lattice = np.stack(np.meshgrid(np.arange(6), np.arange(6)), -1).reshape(-1, 2)
    last = 0.4 + 0.01 * lattice
    frames = np.repeat(last[None], 8, axis=0)
    frames[-2, :] -= (1e-4, 0.0)
    frames[-2, 5] -= (0.0, 3e-4)
    types = np.full(len(last), 5)
    types[0] = 3
    rng = np.random.default_rng(0)
    step_context = rng.normal(size=(8, 1)) if context else None
    return Trajectory(positions=frames, particle_type=types, step_context=step_context)


@pytest.mark.parametrize("context", [False, True])
def test_a_model_of_zero_acceleration_keeps_a_held_pile_exactly(context):
    pile = held_pile(context)
    result = rest_test(zero_acceleration_simulator(context), pile, 7)
    assert result["density_ratio"] == 1.0
    assert result["max_displacement"] == 0.0 and result["outside_box"] == 0.0
    # The data's last step, by hand: particle 5 moved by (1e-4, 3e-4).
    assert result["truth_speed"] == pytest.approx(np.hypot(1e-4, 3e-4), rel=1e-4)


def test_a_held_pile_falls_as_semi_implicit_euler_says_and_leaves_the_box():
    simulator = zero_acceleration_simulator(context=False)
    g = 4e-4  # per step squared; the fresh normaliser (mean 0, std 1) passes it through
    with torch.no_grad():
        simulator.model.decoder[-1].bias.copy_(torch.tensor([0.0, -g]))
    pile = held_pile(context=False)
    steps = 40
    result = rest_test(simulator, pile, steps)
    # From rest, v_k = -k g and x_K = x_0 - g K (K + 1) / 2 (0.328); the kinematic corner
    # stays, the rest falls as one: the same packing, the lowest row from 0.4 to 0.072, below
    # the floor at 0.1. Float32 positions: each step's velocity (a difference of positions)
    # is off by up to an ulp of 0.4 (3e-8), and 40 steps add up to 40 * 41 / 2 of them.
    fall = g * steps * (steps + 1) / 2
    assert result["max_displacement"] == pytest.approx(fall, abs=3e-5)
    assert result["density_ratio"] == 1.0
    assert result["outside_box"] == pytest.approx(0.1 - (0.4 - fall), abs=3e-5)


def test_a_one_frame_trajectory_has_no_truth_speed_but_is_still_held():
    pile = held_pile(context=False)
    single = Trajectory(positions=pile.positions[-1:], particle_type=pile.particle_type)
    result = rest_test(zero_acceleration_simulator(context=False), single, 3)
    assert np.isnan(result["truth_speed"]) and result["max_displacement"] == 0.0


def test_rest_summary_is_the_mean_density_and_the_worst_pile():
    results = [
        {"truth_speed": 1e-4, "density_ratio": 1.0, "max_displacement": 0.01, "outside_box": 0.0},
        {"truth_speed": 3e-4, "density_ratio": 2.0, "max_displacement": 0.03, "outside_box": 0.1},
    ]
    summary = rest_summary(results, 5)
    assert summary["steps"] == 5 and summary["trajectories"] == results
    assert summary["mean"] == {
        "truth_speed": 3e-4,
        "density_ratio": 1.5,
        "max_displacement": 0.03,
        "outside_box": 0.1,
    }
    with pytest.raises(ValueError, match="no rest test results"):
        rest_summary([], 5)


def test_rest_test_needs_a_step():
    with pytest.raises(ValueError, match="at least 1 step, got 0"):
        rest_test(zero_acceleration_simulator(), held_pile(context=True), 0)


# ------------------------------------------------------------------- the real sand data


@pytest.fixture(scope="module")
def sand_test_split():
    if not (SAND / "manifest.json").is_file():
        pytest.skip("shared/data/sand2d-taichi not present")
    from gns.data import open_dataset

    return open_dataset(SAND, "test")


def test_the_deposit_of_real_sand_against_itself_and_the_baselines(sand_test_split):
    """The 8 test trajectories of sand2d-taichi scored as if the truth were the model: the
    truth's own ratios are exactly 1; blocks that spread over the floor end 0.65-0.8 wide
    (the box is 0.8 wide); the baselines, which start from frame 5, keep each block its width."""
    metadata = sand_test_split.metadata
    facts = {
        "bounds": [list(pair) for pair in metadata.bounds],
        "connectivity_radius": metadata.default_connectivity_radius,
        "periodic": [False, False],
        "kinematic_particle_types": [3],
    }
    rollouts = []
    for i in range(len(sand_test_split)):
        x = sand_test_split[i].positions
        metadata_i = {**facts, "trajectory": i}
        rollouts.append(
            Rollout(x[:6], x[6:], x[6:], sand_test_split[i].particle_type, metadata=metadata_i)
        )
    # OT and MMD on the first predicted frame only: the deposit is what is checked here.
    report = evaluate_rollouts(rollouts, horizons=(None,), distribution_every=10**6)
    for entry, r in zip(report["trajectories"], rollouts, strict=True):
        truth, model = entry["ground_truth"], entry["model"]
        for figures in (truth, model):
            assert figures["runout_ratio"] == figures["height_ratio"] == 1.0
            assert figures["density_ratio"] == 1.0
        assert 0.6 < truth["runout"] <= 0.8 and 0 < truth["pile_height"] < 0.2
        fronts = np.subtract(truth["front_x_p99"], truth["front_x_p1"])
        assert fronts[-1] == pytest.approx(truth["runout"], rel=1e-12)
        assert fronts[-1] > 3 * fronts[0]  # a 0.2-wide block spreads over the floor
        # The static baseline keeps the last input frame: its deposit is that frame's.
        held = r.initial_positions[-1]
        assert entry["static"]["runout"] == pytest.approx(runout_extent(held), rel=1e-12)
        # Every particle of a block moves alike by frame 5 (falling or thrown as one), so
        # constant velocity carries it along rigidly: as narrow as the static one, under a
        # third of the truth's width, never spreading.
        velocity = entry["constant_velocity"]
        assert velocity["runout"] == pytest.approx(entry["static"]["runout"], rel=1e-3)
        assert velocity["runout_ratio"] < 1 / 3 and entry["static"]["runout_ratio"] < 1 / 3
        # Held where it was, the block stands at least 3x higher than the spread deposit.
        assert entry["static"]["height_ratio"] > 3
    # Constant velocity carries some blocks through the floor: below it at the end.
    assert min(e["constant_velocity"]["pile_height"] for e in report["trajectories"]) < 0
    assert report["mean"]["ground_truth"]["runout_ratio"] == 1.0


def test_rollouts_scored_in_threads_equal_those_scored_one_at_a_time():
    # Diverged, shifted and plain rollouts, OT and MMD on every frame: the threaded scores are
    # bit-identical to one thread's, in the rollouts' order.
    rollouts = [
        synthetic_rollout(),
        synthetic_rollout(predicted_offset=0.01),
        synthetic_rollout(diverged_at=3),
        synthetic_rollout(predicted_offset=-0.02),
    ]
    one = evaluate_rollouts(rollouts, horizons=(1, 5, None), workers=1)
    many = evaluate_rollouts(rollouts, horizons=(1, 5, None), workers=3)
    assert json.dumps(one, sort_keys=True, default=str) == json.dumps(
        many, sort_keys=True, default=str
    )
    with pytest.raises(ValueError, match="workers must be a whole number >= 1, got 0"):
        evaluate_rollouts(rollouts, workers=0)
