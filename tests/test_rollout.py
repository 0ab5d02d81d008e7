"""Rollouts: constant-velocity extrapolation by hand, kinematic particles held to ground truth,
a slow step-by-step oracle, step timings, divergence, files (ours and DeepMind's pickle), a short
rollout on the real sand data, and a model of one frame spacing on data with finer frames
(`gns rollout` against the same checkpoint on `gns convert --frame-stride`'s frames)."""

from __future__ import annotations

import dataclasses
import pickle
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from data_helpers import SAND
from gns.config import Config, ModelConfig, NormalizationConfig
from gns.data import Metadata, Trajectory, open_dataset
from gns.rollout import (
    TIMING_PARTS,
    Rollout,
    RolloutDiverged,
    load_rollout,
    rollout,
    save_deepmind_pickle,
    save_rollout,
)
from gns.simulator import LearnedSimulator, Scene

TINY = ModelConfig(latent_size=16, mlp_hidden_size=16, message_passing_steps=2)
BOX = ((0.1, 0.9), (0.1, 0.9))
C = TINY.velocity_history
KINEMATIC, FREE = 3, 5

pytestmark = pytest.mark.usefixtures("torch_one_thread")


def statistics(context=False):
    """Per-frame statistics of a plausible flow, so an untrained model moves particles by
    about acc_std per step instead of by O(1)."""
    return Metadata(
        bounds=BOX,
        sequence_length=20,
        default_connectivity_radius=0.1,
        dim=2,
        dt=0.0025,
        vel_mean=(1e-4, -2e-4),
        vel_std=(1e-3, 1e-3),
        acc_mean=(0.0, -1e-5),
        acc_std=(1e-4, 1e-4),
        context_mean=(0.5,) if context else None,
        context_std=(0.3,) if context else None,
    )


def simulator(context=False, material=False, source="metadata"):
    torch.manual_seed(0)
    scene = Scene(
        dim=2,
        radius=0.1,
        particle_types=(KINEMATIC, FREE),
        bounds=BOX,
        walls=True,
        context_size=1 if context else 0,
        material_property_size=1 if material else 0,
    )
    config = Config(model=TINY, normalization=NormalizationConfig(source=source))
    stats = statistics(context) if source == "metadata" else None
    return LearnedSimulator(scene, config, statistics=stats)


def trajectory(frames=14, n=30, num_kinematic=5, seed=0, context=False, material=False):
    """Particles drifting inside the box with jittered velocities; the first num_kinematic are
    kinematic (obstacle) particles on their own prescribed paths."""
    rng = np.random.default_rng(seed)
    start = rng.uniform(0.3, 0.7, size=(1, n, 2))
    velocity = rng.normal(0.0, 2e-3, size=(frames, n, 2)).cumsum(0) / 4 + 1e-3
    positions = start + velocity.cumsum(0)
    types = np.full(n, FREE)
    types[:num_kinematic] = KINEMATIC
    step_context = None
    if context:
        # Changes every frame, so reading the wrong frame changes the prediction.
        step_context = np.linspace(0.0, 1.5, frames, dtype=np.float32)[:, None]
    return Trajectory(
        positions=positions.astype(np.float32),
        particle_type=types,
        step_context=step_context,
        material_property=np.float32(0.7) if material else None,
        key=3,
        source="<test>",
    )


# ---------------------------------------------------------------------- what a rollout computes


def test_zero_acceleration_gives_constant_velocity_extrapolation():
    # Fresh running statistics are mean 0, std 1 and a zero last decoder layer outputs 0, so
    # the de-normalised acceleration is exactly 0: x_{t+1} = x_t + (x_t - x_{t-1}).
    sim = simulator(source="running").double()
    last = sim.model.decoder[-1]
    assert isinstance(last, torch.nn.Linear)
    torch.nn.init.zeros_(last.weight)
    torch.nn.init.zeros_(last.bias)
    traj = trajectory(frames=10, num_kinematic=0)
    steps = 12  # past the end of the trajectory: allowed without kinematic particles
    r = rollout(sim, traj, num_steps=steps)

    x = traj.positions.astype(np.float64)
    velocity = x[C] - x[C - 1]
    k = np.arange(1, steps + 1, dtype=np.float64)[:, None, None]
    np.testing.assert_allclose(r.predicted_rollout, x[C] + k * velocity, rtol=0, atol=1e-13)
    assert r.predicted_rollout.dtype == np.float64  # the simulator's precision, never less
    assert r.ground_truth_rollout is None  # the trajectory does not cover 12 steps


def test_kinematic_particles_follow_the_ground_truth_and_free_ones_do_not():
    traj = trajectory(frames=16, num_kinematic=6)
    r = rollout(simulator(), traj)
    assert r.num_steps == 16 - (C + 1)
    kinematic = traj.particle_type == KINEMATIC
    assert r.ground_truth_rollout is not None
    np.testing.assert_array_equal(
        r.predicted_rollout[:, kinematic], r.ground_truth_rollout[:, kinematic]
    )
    for step in range(r.num_steps):
        assert np.any(
            r.predicted_rollout[step, ~kinematic] != r.ground_truth_rollout[step, ~kinematic]
        )


def slow_rollout(sim, traj, steps, context_offset=0):
    """The definition, one predict_positions call per step on the previous C + 1 frames."""
    frames = list(traj.positions[: C + 1].astype(np.float32))
    types = torch.from_numpy(traj.particle_type)
    kinematic = traj.particle_type == KINEMATIC
    material = torch.from_numpy(traj.material_property)
    sim.eval()
    with torch.no_grad():
        for t in range(steps):
            sequence = torch.from_numpy(np.stack(frames[-(C + 1) :], axis=1))  # (N, C + 1, D)
            context = torch.from_numpy(traj.step_context[t + C + context_offset])
            nxt = sim.predict_positions(
                sequence, types, context=context, material_property=material
            )
            nxt = nxt.numpy().copy()
            nxt[kinematic] = traj.positions[C + 1 + t][kinematic]
            frames.append(nxt)
    return np.stack(frames[C + 1 :])


def test_each_step_is_predict_positions_on_the_previous_frames():
    sim = simulator(context=True, material=True)
    traj = trajectory(frames=16, context=True, material=True)
    sim.train()
    r = rollout(sim, traj, num_steps=8)
    assert sim.training  # the mode it had is restored
    want = slow_rollout(sim, traj, 8)
    np.testing.assert_allclose(r.predicted_rollout, want, rtol=0, atol=1e-6)
    # The test can tell the context frame apart: one frame later gives another rollout.
    later = slow_rollout(sim, traj, 8, context_offset=1)
    assert np.abs(later - want).max() > 1e-5
    # The context of every input frame is kept, frame-aligned.
    assert r.step_context is not None
    np.testing.assert_array_equal(r.step_context, traj.step_context[: C + 8])


def test_history_is_the_first_frames_and_ground_truth_the_rest():
    traj = trajectory(frames=15)
    r = rollout(simulator(), traj, num_steps=4)
    np.testing.assert_array_equal(r.initial_positions, traj.positions[: C + 1])
    assert r.ground_truth_rollout is not None
    np.testing.assert_array_equal(r.ground_truth_rollout, traj.positions[C + 1 : C + 5])
    np.testing.assert_array_equal(r.particle_type, traj.particle_type)
    assert r.predicted_trajectory.shape == (C + 5, 30, 2)
    assert r.metadata["trajectory"] == 3 and r.metadata["num_steps"] == 4
    assert r.metadata["velocity_history"] == C and r.metadata["bounds"] == [[0.1, 0.9]] * 2


def test_timings_are_positive_per_step_and_part():
    r = rollout(simulator(), trajectory(frames=12))
    assert set(r.timings) == set(TIMING_PARTS)
    for seconds in r.timings.values():
        assert seconds.shape == (12 - (C + 1),) and seconds.dtype == np.float64
        assert np.isfinite(seconds).all() and (seconds > 0).all()


# ---------------------------------------------------------------------- loud failures


def test_nan_output_raises_naming_the_step():
    sim = simulator()
    torch.nn.init.constant_(sim.model.decoder[-1].bias, float("nan"))
    traj = trajectory(frames=12, num_kinematic=4)
    with pytest.raises(RolloutDiverged, match=r"step 0 .*26 of 30 particles") as info:
        rollout(sim, traj)
    assert isinstance(info.value, ValueError)
    assert info.value.step == 0 and info.value.num_nonfinite == 26  # kinematic ones are reset
    assert info.value.rollout.num_steps == 0


def test_divergence_part_way_keeps_the_finite_steps():
    sim = simulator()
    traj = trajectory(frames=14)
    clean = rollout(sim, traj)
    calls = 0

    def poison_after_three(module, inputs, output):
        nonlocal calls
        calls += 1
        if calls > 3:
            output = output.clone()
            output[-2:] = float("inf")  # two free particles
        return output

    handle = sim.model.decoder.register_forward_hook(poison_after_three)
    sim.train()
    try:
        with pytest.raises(RolloutDiverged, match=r"step 3 .*2 of 30") as info:
            rollout(sim, traj)
    finally:
        handle.remove()
    partial = info.value.rollout
    assert info.value.step == 3 and partial.num_steps == 3
    assert partial.metadata["diverged_at_step"] == 3
    np.testing.assert_array_equal(partial.predicted_rollout, clean.predicted_rollout[:3])
    assert partial.ground_truth_rollout is not None and partial.ground_truth_rollout.shape[0] == 3
    assert all(seconds.shape == (3,) for seconds in partial.timings.values())
    assert sim.training  # restored on the way out of the error too


@pytest.mark.parametrize("steps", [0, -2])
def test_num_steps_below_one_is_refused(steps):
    with pytest.raises(ValueError, match=f"num_steps must be at least 1, got {steps}"):
        rollout(simulator(), trajectory(), num_steps=steps)


def test_too_many_steps_with_kinematic_particles_is_refused():
    traj = trajectory(frames=12, num_kinematic=2)
    with pytest.raises(ValueError, match=r"num_steps = 7 .*2 kinematic.*at most 6 steps"):
        rollout(simulator(), traj, num_steps=7)


def test_too_many_steps_for_the_step_context_is_refused():
    traj = trajectory(frames=12, num_kinematic=0, context=True)
    rollout(simulator(context=True), traj, num_steps=7)  # the context reaches frame 11
    with pytest.raises(ValueError, match=r"num_steps = 8 .*step context.*at most 7 steps"):
        rollout(simulator(context=True), traj, num_steps=8)


def test_too_short_a_trajectory_is_refused():
    with pytest.raises(ValueError, match=r"C \+ 1 = 6 frames.*has 5 frames"):
        rollout(simulator(), trajectory(frames=5))
    with pytest.raises(ValueError, match="only the 6 history frames"):
        rollout(simulator(), trajectory(frames=6))


# ---------------------------------------------------------------------- files


def small_rollout(**metrics):
    traj = trajectory(frames=10, context=True)
    r = rollout(simulator(context=True), traj, metadata={"dataset": "synthetic"})
    r.metrics.update(metrics)
    return r


def assert_same(a: Rollout, b: Rollout) -> None:
    for name in ("initial_positions", "predicted_rollout", "ground_truth_rollout", "step_context"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype, name
        np.testing.assert_array_equal(x, y, err_msg=name)
    np.testing.assert_array_equal(a.particle_type, b.particle_type)
    assert a.particle_type.dtype == b.particle_type.dtype
    assert a.metadata == b.metadata
    assert a.timings.keys() == b.timings.keys()
    for part in a.timings:
        np.testing.assert_array_equal(a.timings[part], b.timings[part])
    assert a.metrics.keys() == b.metrics.keys()
    for name, value in a.metrics.items():
        np.testing.assert_array_equal(b.metrics[name], value)


def test_save_and_load_round_trip_exactly(tmp_path):
    r = small_rollout(mse_per_step=np.linspace(0, 1, 4), final_mse=0.25, note="untrained")
    path = tmp_path / "rollout.npz"
    save_rollout(path, r)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rollout.npz"]  # no temporary left
    back = load_rollout(path)
    assert_same(r, back)
    assert back.metadata["dataset"] == "synthetic"
    # Plain arrays only: readable without pickle by numpy alone.
    with np.load(path, allow_pickle=False) as npz:
        assert {"timing_graph", "metric_mse_per_step", "initial_positions"} <= set(npz.files)


def test_a_rollout_without_ground_truth_or_context_round_trips(tmp_path):
    sim = simulator()
    r = rollout(sim, trajectory(frames=8, num_kinematic=0), num_steps=5)
    assert r.ground_truth_rollout is None and r.step_context is None
    save_rollout(tmp_path / "r.npz", r)
    back = load_rollout(tmp_path / "r.npz")
    assert back.ground_truth_rollout is None and back.step_context is None
    np.testing.assert_array_equal(back.predicted_rollout, r.predicted_rollout)


def test_a_failed_save_leaves_the_old_file(tmp_path, monkeypatch):
    path = tmp_path / "rollout.npz"
    save_rollout(path, small_rollout())
    before = path.read_bytes()

    def disk_full(file, *args, **kwargs):
        file.write(b"PK\x03\x04 half a zip")
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez", disk_full)
    with pytest.raises(OSError, match="disk full"):
        save_rollout(path, small_rollout())
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rollout.npz"]


def test_metadata_that_is_not_json_is_refused(tmp_path):
    r = small_rollout()
    r.metadata["model"] = object()
    with pytest.raises(ValueError, match="metadata must hold plain JSON"):
        save_rollout(tmp_path / "r.npz", r)
    assert list(tmp_path.iterdir()) == []


def test_load_rejects_damaged_files(tmp_path):
    path = tmp_path / "rollout.npz"
    save_rollout(path, small_rollout())
    payload = path.read_bytes()

    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(payload[: len(payload) // 2])
    with pytest.raises(ValueError, match="truncated.npz: not a readable rollout file"):
        load_rollout(truncated)

    # Flip bytes inside the first member's data: the zip CRC catches it.
    flipped = bytearray(payload)
    with zipfile.ZipFile(path) as z:
        info = z.infolist()[1]
    start = info.header_offset + 30 + len(info.filename) + 200
    flipped[start : start + 8] = bytes(8)
    damaged = tmp_path / "damaged.npz"
    damaged.write_bytes(bytes(flipped))
    with pytest.raises(ValueError, match="damaged.npz"):
        load_rollout(damaged)


def write_npz(path, **arrays):
    with open(path, "wb") as f:
        np.savez(f, **arrays)


def members(path):
    with np.load(path, allow_pickle=False) as npz:
        return {k: npz[k] for k in npz.files}


def test_load_rejects_wrong_members_and_shapes(tmp_path):
    good = tmp_path / "good.npz"
    save_rollout(good, small_rollout())
    arrays = members(good)

    missing = {k: v for k, v in arrays.items() if k != "predicted_rollout"}
    write_npz(tmp_path / "missing.npz", **missing)
    with pytest.raises(ValueError, match=r"missing.npz.*missing members \['predicted_rollout'\]"):
        load_rollout(tmp_path / "missing.npz")

    write_npz(tmp_path / "extra.npz", **arrays, surprise=np.zeros(3))
    with pytest.raises(ValueError, match=r"unknown members \['surprise'\]"):
        load_rollout(tmp_path / "extra.npz")

    shapes = {**arrays, "predicted_rollout": arrays["predicted_rollout"][:, :-1]}
    write_npz(tmp_path / "shape.npz", **shapes)
    with pytest.raises(ValueError, match=r"predicted_rollout must be \(S, 30, 2\)"):
        load_rollout(tmp_path / "shape.npz")

    nan = arrays["predicted_rollout"].copy()
    nan[1, 2, 0] = np.nan
    write_npz(tmp_path / "nan.npz", **{**arrays, "predicted_rollout": nan})
    with pytest.raises(ValueError, match="predicted_rollout holds non-finite"):
        load_rollout(tmp_path / "nan.npz")

    pickled = {**arrays, "metadata": np.array([{"a": 1}], dtype=object)}
    write_npz(tmp_path / "pickled.npz", **pickled)
    with pytest.raises(ValueError, match="pickled.npz"):
        load_rollout(tmp_path / "pickled.npz")


def test_deepmind_pickle_layout(tmp_path):
    r = small_rollout()
    path = tmp_path / "rollout_test_0.pkl"
    save_deepmind_pickle(path, r)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rollout_test_0.pkl"]
    with open(path, "rb") as f:
        data = pickle.load(f)
    assert set(data) == {
        "initial_positions",
        "predicted_rollout",
        "ground_truth_rollout",
        "particle_types",
        "metadata",
        "global_context",
    }
    steps = 10 - (C + 1)
    assert data["initial_positions"].shape == (C + 1, 30, 2)  # time-major, like the rollout
    assert data["predicted_rollout"].shape == data["ground_truth_rollout"].shape == (steps, 30, 2)
    assert data["particle_types"].shape == (30,)
    assert data["global_context"].shape == (C + steps, 1)
    # What render_rollout.py does with it.
    whole = np.concatenate([data["initial_positions"], data["ground_truth_rollout"]], axis=0)
    assert whole.shape == (10, 30, 2)
    assert data["metadata"]["bounds"] == [[0.1, 0.9], [0.1, 0.9]]
    np.testing.assert_array_equal(data["predicted_rollout"], r.predicted_rollout)


def test_deepmind_pickle_needs_ground_truth(tmp_path):
    r = rollout(simulator(), trajectory(frames=8, num_kinematic=0), num_steps=5)
    with pytest.raises(ValueError, match="needs ground_truth_rollout"):
        save_deepmind_pickle(tmp_path / "r.pkl", r)
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------------- real data


@pytest.mark.skipif(not (SAND / "manifest.json").is_file(), reason="sand2d-taichi not present")
def test_ten_steps_on_the_real_sand_data():
    dataset = open_dataset(SAND, "test")
    traj = dataset[0]
    config = Config(model=TINY, normalization=NormalizationConfig(source="metadata"))
    sim = LearnedSimulator.from_metadata(dataset.metadata, np.unique(traj.particle_type), config)
    r = rollout(sim, traj, num_steps=10, metadata={"dataset": "sand2d-taichi"})
    n = traj.n_particles
    assert r.predicted_rollout.shape == (10, n, 2) and r.predicted_rollout.dtype == np.float32
    assert np.isfinite(r.predicted_rollout).all()
    np.testing.assert_array_equal(r.initial_positions, traj.positions[: C + 1])
    assert r.ground_truth_rollout is not None
    np.testing.assert_array_equal(r.ground_truth_rollout, traj.positions[C + 1 : C + 11])
    assert r.step_context is not None and r.step_context.shape == (C + 10, 1)
    assert all(np.isfinite(s).all() and s.shape == (10,) for s in r.timings.values())


def test_particles_far_outside_the_domain_stop_the_rollout_naming_them():
    sim = simulator()
    traj = trajectory(frames=14)
    clean = rollout(sim, traj)
    calls = 0

    def fling_after_two(module, inputs, output):
        # Normalised accelerations of 1e30 from the third step on: the two particles land far
        # outside the box, their positions still finite.
        nonlocal calls
        calls += 1
        if calls > 2:
            output = output.clone()
            output[[7, 11]] = 1e30
        return output

    handle = sim.model.decoder.register_forward_hook(fling_after_two)
    try:
        with pytest.raises(RolloutDiverged, match=r"step 2 .*2 of 30 particles are more than") as e:
            rollout(sim, traj)
        # Without the check the same rollout runs on, with garbage positions.
        free_running = rollout(sim, traj, escape_distance=None)
    finally:
        handle.remove()
    assert e.value.step == 2 and e.value.num_nonfinite == 0
    np.testing.assert_array_equal(e.value.particles, [7, 11])
    assert "particles 7, 11" in str(e.value)
    np.testing.assert_array_equal(e.value.rollout.predicted_rollout, clean.predicted_rollout[:2])
    assert np.abs(free_running.predicted_rollout[2, [7, 11]]).max() > 1e6
    for bad in (0, -1.0, float("nan"), float("inf"), "1"):
        with pytest.raises(ValueError, match="escape_distance must be a positive number"):
            rollout(sim, traj, escape_distance=bad)


def test_a_small_excursion_is_not_divergence_and_float64_rollouts_agree():
    sim = simulator()
    traj = trajectory(frames=14)
    # Move everything half a box length outside: within the default one box length.
    lo = np.array([b[0] for b in BOX], dtype=np.float32)
    hi = np.array([b[1] for b in BOX], dtype=np.float32)
    shifted = dataclasses.replace(traj, positions=traj.positions + 0.5 * (hi - lo)[0])
    rollout(sim, shifted)
    single = rollout(sim, traj)
    double = rollout(sim.double(), traj)
    assert double.predicted_rollout.dtype == np.float64
    assert single.predicted_rollout.dtype == np.float32
    np.testing.assert_allclose(double.predicted_rollout, single.predicted_rollout, atol=1e-5)


# ---------------------------------------------------------------------- frame stride

STRIDE = 3
NATIVE_FRAMES = 27  # a multiple of the stride: frames 0, 3, ..., 24 at stride 3, 9 of them


def strided_run(root: Path) -> tuple[Path, Path, Path]:
    """(run folder, native data, converted data): a GNS trained for 2 steps on `gns convert
    --frame-stride 3` of a dataset with 2.5 ms frames (so it steps 7.5 ms), its test split 2
    trajectories of 27 frames (9 converted)."""
    from gns.data import convert
    from gns.train import train
    from test_train import config, make_dataset

    native = make_dataset(root / "native", frames=NATIVE_FRAMES)
    (native / "valid.h5").rename(native / "test.h5")
    convert(native, root / "converted", "h5", frame_stride=STRIDE)
    train(root / "converted", root / "run", config(2), progress=False)
    return root / "run", native, root / "converted"


def test_a_model_rolls_out_on_finer_data_at_its_own_frame_spacing(strided, tmp_path, capsys):
    from gns.cli import main

    run, native, converted = strided
    common = ["rollout", "--run", str(run)]
    assert main([*common, "--data", str(native), "--out", str(tmp_path / "a")]) == 0
    note = "the data's frames are 2.5 ms apart, the model's steps 7.5 ms: every 3rd frame"
    assert note in capsys.readouterr().out.splitlines()
    # The oracle: the same checkpoint on the frames gns convert wrote.
    assert main([*common, "--data", str(converted), "--out", str(tmp_path / "b")]) == 0
    assert "every 3rd frame" not in capsys.readouterr().out
    for i in (0, 1):
        ours = load_rollout(tmp_path / "a" / f"rollout_test_{i}.npz")
        theirs = load_rollout(tmp_path / "b" / f"rollout_test_{i}.npz")
        assert ours.num_steps == theirs.num_steps == NATIVE_FRAMES // STRIDE - (C + 1)
        for name in ("initial_positions", "predicted_rollout", "ground_truth_rollout"):
            np.testing.assert_array_equal(getattr(ours, name), getattr(theirs, name), name)
        np.testing.assert_array_equal(ours.step_context, theirs.step_context)
        assert (ours.metadata["frame_stride"], ours.metadata["dataset_dt"]) == (3, 0.0025)
        assert theirs.metadata["frame_stride"] == 1
        assert theirs.metadata["dataset_dt"] == pytest.approx(0.0075, rel=1e-12)


def test_a_checkpoint_from_before_frame_spacings_rolls_out_on_every_frame(strided, tmp_path):
    from gns.checkpoints import choose_checkpoint, load_simulator
    from gns.cli import main
    from test_train import as_written_before_frame_spacing

    run, native, _ = strided
    old = tmp_path / "old.pt"
    old.write_bytes(choose_checkpoint(run).read_bytes())
    as_written_before_frame_spacing(old)
    assert main(["rollout", "--run", str(old), "--data", str(native), "--trajectories", "1"]) == 0
    saved = load_rollout(tmp_path / "rollouts/test/rollout_test_1.npz")
    # As before: every frame of the data, the rollout of the library on the trajectory as it is.
    expected = rollout(load_simulator(old), open_dataset(native, "test")[1])
    assert saved.num_steps == NATIVE_FRAMES - (C + 1)
    np.testing.assert_array_equal(saved.predicted_rollout, expected.predicted_rollout)
    assert saved.metadata["frame_stride"] == 1
