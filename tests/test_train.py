"""Training: exact resume, the schedule, the loss definition, checkpoints, logs and DDP."""

from __future__ import annotations

import csv
import dataclasses
import math
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch
from data_helpers import metadata_dict, write_metadata
from gns.checkpoints import (
    CHECKPOINT_FORMAT,
    choose_checkpoint,
    latest_checkpoint,
    load_checkpoint,
    load_simulator,
    save_checkpoint,
)
from gns.config import Config, ModelConfig, NoiseConfig, TrainConfig
from gns.data import Trajectory, open_dataset
from gns.data.h5 import write_h5
from gns.data.windows import WindowSampler
from gns.noise import sample_noise
from gns.train import TrainingStep, batch_tensors, train
from gns.validation import better_validation, stays_in_box, validate

pytestmark = pytest.mark.usefixtures("torch_one_thread")

TINY = ModelConfig(latent_size=8, mlp_hidden_size=8, message_passing_steps=2)


def damped_motion(rng: np.random.Generator, frames: int, particles: int, key: int) -> Trajectory:
    """Free particles whose velocity shrinks by 10% a frame: acceleration = -0.1 velocity, a
    rule the model can learn; two static kinematic particles; a 1-wide context."""
    velocity = rng.normal(0.0, 1e-3, size=(particles, 2))
    positions = [rng.uniform(0.3, 0.7, size=(particles, 2))]
    for _ in range(frames - 1):
        velocity = 0.9 * velocity
        positions.append(positions[-1] + velocity)
    stacked = np.stack(positions).astype(np.float32)
    types = np.full(particles, 5)
    types[-2:] = 3
    stacked[:, -2:] = stacked[0, -2:]
    context = np.full((frames, 1), 0.5, dtype=np.float32)
    return Trajectory(stacked, types, context, key=key)


def make_dataset(folder: Path, trajectories: int = 6, frames: int = 12, particles: int = 24):
    """A small h5 dataset of damped motion (train: all, valid: the first two)."""
    rng = np.random.default_rng(0)
    items = [damped_motion(rng, frames, particles, k) for k in range(trajectories)]
    write_metadata(folder, metadata_dict(sequence_length=frames - 1))
    write_h5(folder / "train.h5", items)
    write_h5(folder / "valid.h5", items[:2])
    return folder


def config(steps: int, **train: object) -> Config:
    settings: dict = dict(
        steps=steps,
        log_every=2,
        checkpoint_every=3,
        validate_every=0,
        trajectories_in_memory=2,
        learning_rate=1e-3,
    )
    settings.update(train)
    return Config(model=TINY, train=TrainConfig(**settings))


def trained_run(root: Path, steps: int, frames: int = 12) -> tuple[Path, Path]:
    """(run folder, dataset) of a GNS trained for `steps` steps on one thread, on a dataset of
    2 trajectories whose valid split is renamed test (what rollouts and evals read)."""
    data = make_dataset(root / "data", trajectories=2, frames=frames)
    (data / "valid.h5").rename(data / "test.h5")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        train(data, root / "run", config(steps), progress=False)
    finally:
        torch.set_num_threads(threads)
    return root / "run", data


def parameters(simulator) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in simulator.state_dict().items()}


def read_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


@pytest.mark.parametrize(
    "settings",
    [{}, {"mirror_axes": (0, 1)}, {"early_steps": 2, "early_repeat": 3}, {"std_min": 0.0}],
)
def test_resume_continues_exactly(tmp_path, settings):
    data = make_dataset(tmp_path / "data")
    # 6 trajectories, 2 in memory, 6 windows each at batch 2: chunks change every 6 steps, and
    # the 21 steps cross epochs, so the sampler, noise stream and optimiser state all matter
    # (and with mirroring, which windows are mirrored; with early windows, the longer epochs;
    # with noise.std_min, each window's std).
    settings = dict(settings)
    noise = NoiseConfig(std_min=settings.pop("std_min", None))
    cfg = lambda steps: dataclasses.replace(config(steps, **settings), noise=noise)  # noqa: E731
    straight = train(data, tmp_path / "a", cfg(21), progress=False)
    train(data, tmp_path / "b", cfg(8), progress=False)
    resumed = train(data, tmp_path / "b", cfg(21), resume=True, progress=False)
    a, b = parameters(straight), parameters(resumed)
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(a[key], b[key]), key
    # The logged losses of the resumed run are those of the uninterrupted one, each step once.
    rows_a, rows_b = read_csv(tmp_path / "a/train.csv"), read_csv(tmp_path / "b/train.csv")
    assert [r["step"] for r in rows_b] == [r["step"] for r in rows_a]
    assert [r["loss"] for r in rows_b] == [r["loss"] for r in rows_a]
    # The running statistics came through too (they are part of the model's state).
    count = a["velocity_normalizer.count"]
    assert count > 0


def test_training_draws_the_noise_of_each_window_of_a_batch(tmp_path, monkeypatch):
    """noise.std_min draws a std per window: training passes the windows' sizes along, and
    the windows of one batch get different stds."""
    from gns.simulator import LearnedSimulator

    seen = []
    draw = LearnedSimulator.sample_noise

    def spy(self, sequence, particle_type, generator=None, n_node=None):
        state = generator.get_state()
        noise = draw(self, sequence, particle_type, generator, n_node)
        # The same draw at the fixed std: each window's noise is it scaled by its own factor.
        fixed = sample_noise(
            NoiseConfig(std=1e-3), sequence, generator=torch.Generator().set_state(state)
        )
        free = ~self.kinematic_mask(particle_type)
        assert torch.count_nonzero(noise[~free]) == 0
        seen.append((n_node.tolist(), free, noise[:, 1:] / fixed[:, 1:]))
        return noise

    monkeypatch.setattr(LearnedSimulator, "sample_noise", spy)
    data = make_dataset(tmp_path / "data")
    cfg = dataclasses.replace(config(3), noise=NoiseConfig(std=1e-3, std_min=0.0))
    train(data, tmp_path / "run", cfg, progress=False)
    assert len(seen) == 3
    for n_node, free, ratio in seen:
        assert len(n_node) == 2 and sum(n_node) == len(ratio)
        scales = []
        for window, moving in zip(
            torch.split(ratio, n_node), torch.split(free, n_node), strict=True
        ):
            window = window[moving]
            torch.testing.assert_close(window, window[:1, :1].expand_as(window))
            scales.append(float(window[0, 0, 0]))
        assert 0 <= min(scales) and max(scales) <= 1 and scales[0] != scales[1], scales


def test_a_run_trained_on_a_gpu_resumes_on_the_cpu(tmp_path, capsys):
    # A CUDA run's checkpoint holds its noise generator's state: 16 bytes (Philox's seed and
    # offset), which the CPU's generator (5056 bytes) cannot take. Make such a checkpoint from
    # a CPU run and resume it here: the run goes on, says so, and is the same run each time.
    data = make_dataset(tmp_path / "data")
    train(data, tmp_path / "gpu", config(9), progress=False)
    path = latest_checkpoint(tmp_path / "gpu")
    state = load_checkpoint(path, resume=True)
    cuda_state = torch.tensor([7, 0, 0, 0, 0, 0, 0, 0, 24, 0, 0, 0, 0, 0, 0, 0], dtype=torch.uint8)
    state["noise_generator"] = [cuda_state]
    save_checkpoint(path, state)
    for copy in ("a", "b"):
        (tmp_path / copy / "checkpoints").mkdir(parents=True)
        (tmp_path / copy / "checkpoints" / path.name).write_bytes(path.read_bytes())
    capsys.readouterr()
    a = train(data, tmp_path / "a", config(15), resume=True, progress=False)
    assert "noise stream was drawn on another kind of device than cpu" in capsys.readouterr().err
    b = train(data, tmp_path / "b", config(15), resume=True, progress=False)
    assert load_checkpoint(latest_checkpoint(tmp_path / "a"))["step"] == 15
    resumed_a, resumed_b = parameters(a), parameters(b)
    for key, value in resumed_a.items():
        assert torch.equal(value, resumed_b[key]), key
    # Training went on: the weights moved on from the step-9 weights.
    assert any(not torch.equal(v, state["model"][k]) for k, v in resumed_a.items())


def test_resume_from_a_mid_run_checkpoint_redoes_later_steps_and_logs(tmp_path):
    data = make_dataset(tmp_path / "data")
    train(data, tmp_path / "run", config(12), progress=False)
    final = parameters(load_simulator(tmp_path / "run"))
    # A crash after step 9: the step-12 checkpoint never got written.
    (tmp_path / "run/checkpoints/step_000000012.pt").unlink()
    resumed = train(data, tmp_path / "run", None, resume=True, progress=False)
    for key, value in parameters(resumed).items():
        assert torch.equal(value, final[key]), key
    steps = [int(r["step"]) for r in read_csv(tmp_path / "run/train.csv")]
    assert steps == sorted(set(steps)) == [2, 4, 6, 8, 10, 12]


def test_checkpoints_are_kept_pruned_and_self_contained(tmp_path):
    data = make_dataset(tmp_path / "data")
    train(data, tmp_path / "run", config(10, keep_checkpoints=2), progress=False)
    names = sorted(p.name for p in (tmp_path / "run/checkpoints").iterdir())
    # Every 3 steps and at the end; only the newest two kept; no temporary files left.
    assert names == ["step_000000009.pt", "step_000000010.pt"]
    state = load_checkpoint(latest_checkpoint(tmp_path / "run"))
    assert state["step"] == 10 and state["config"]["model"]["latent_size"] == 8
    assert state["scene"]["context_size"] == 1


def as_written_before_frame_spacing(path: Path) -> None:
    """Rewrite the checkpoint at `path` as gns wrote it before checkpoints recorded the
    training data's frame spacing: format 1, no dt in the scene."""
    state = load_checkpoint(path, resume=True)
    del state["scene"]["dt"]
    state["format"] = "gns-checkpoint-1"
    save_checkpoint(path, state)


def test_the_model_knows_its_frame_spacing_and_old_checkpoints_still_load(tmp_path):
    data = make_dataset(tmp_path / "data")
    train(data, tmp_path / "run", config(3), progress=False)
    path = latest_checkpoint(tmp_path / "run")
    state = load_checkpoint(path)
    assert state["format"] == CHECKPOINT_FORMAT and state["scene"]["dt"] == 0.0025
    simulator = load_simulator(path)
    assert simulator.frame_dt == 0.0025
    finer = open_dataset(data).metadata.replace(dt=0.00125)
    assert simulator.frame_stride_for(finer) == 2
    with pytest.raises(ValueError, match="2.5 ms is not a whole multiple of 1 ms"):
        simulator.frame_stride_for(finer.replace(dt=0.001))

    # Written before: the same model, which does not know its spacing and reads every frame.
    as_written_before_frame_spacing(path)
    old = load_simulator(path)
    assert old.frame_dt is None and old.frame_stride_for(finer.replace(dt=0.001)) == 1
    for key, value in parameters(old).items():
        assert torch.equal(value, parameters(simulator)[key]), key
    # Resumed on its data, such a run records the spacing from then on.
    train(data, tmp_path / "run", config(6), resume=True, progress=False)
    resumed = load_checkpoint(latest_checkpoint(tmp_path / "run"))
    assert resumed["format"] == CHECKPOINT_FORMAT and resumed["scene"]["dt"] == 0.0025
    # A format this version does not know is refused by name.
    state["format"] = "gns-checkpoint-9"
    save_checkpoint(tmp_path / "future.pt", state)
    with pytest.raises(ValueError, match="'gns-checkpoint-9'; expected gns-checkpoint-1 or "):
        load_checkpoint(tmp_path / "future.pt")


def test_existing_run_is_not_overwritten_and_resume_needs_a_checkpoint(tmp_path):
    data = make_dataset(tmp_path / "data")
    with pytest.raises(ValueError, match="no checkpoint"):
        train(data, tmp_path / "empty", config(3), resume=True, progress=False)
    train(data, tmp_path / "run", config(3), progress=False)
    with pytest.raises(ValueError, match="already holds checkpoints"):
        train(data, tmp_path / "run", config(3), progress=False)
    other = Config(
        model=ModelConfig(latent_size=16, message_passing_steps=2), train=config(6).train
    )
    with pytest.raises(ValueError, match="differ"):
        train(data, tmp_path / "run", other, resume=True, progress=False)


def test_learning_rate_follows_the_papers_schedule(tmp_path):
    tc = TrainConfig()
    # alpha(j) = alpha_final + (alpha_start - alpha_final) * 0.1^(j / 5e6), by hand:
    assert tc.learning_rate_at(0) == pytest.approx(1e-4)
    assert tc.learning_rate_at(5_000_000) == pytest.approx(1e-6 + 99e-6 * 0.1)
    assert tc.learning_rate_at(10_000_000) == pytest.approx(1e-6 + 99e-6 * 0.01)
    data = make_dataset(tmp_path / "data")
    fast = dict(learning_rate=1e-2, learning_rate_final=1e-3, learning_rate_decay_steps=4.0)
    train(data, tmp_path / "run", config(8, **fast), progress=False)
    for row in read_csv(tmp_path / "run/train.csv"):
        j = int(row["step"]) - 1  # the rate used by the last step of each logged interval
        expected = 1e-3 + (1e-2 - 1e-3) * 0.1 ** (j / 4.0)
        assert float(row["learning_rate"]) == pytest.approx(expected, rel=1e-6)


def test_max_grad_norm_bounds_every_update_and_the_log_shows_the_norm_before_clipping(tmp_path):
    data = make_dataset(tmp_path / "data")
    cfg = lambda **kw: config(4, log_every=1, **kw)  # noqa: E731
    lr = 1e-3
    # A learning rate of 1e-30 leaves float32 weights as initialised: the starting point.
    start = parameters(
        train(
            data,
            tmp_path / "start",
            cfg(learning_rate=1e-30, learning_rate_final=0.0),
            progress=False,
        )
    )
    free = parameters(train(data, tmp_path / "free", cfg(), progress=False))
    loose = parameters(train(data, tmp_path / "loose", cfg(max_grad_norm=1e30), progress=False))
    tight = parameters(train(data, tmp_path / "tight", cfg(max_grad_norm=1e-12), progress=False))
    weights = [k for k in start if "normalizer" not in k]
    moved = lambda run: max(float((run[k] - start[k]).abs().max()) for k in weights)  # noqa: E731
    # Adam's first step moves a weight by about the learning rate whatever the gradient's
    # scale; a gradient cut to norm 1e-12 is far below Adam's eps (1e-8), so 4 steps move a
    # weight by at most 4 * lr * 1e-12 / 1e-8.
    assert moved(free) > 0.5 * lr
    assert moved(tight) < 4 * lr * 1e-4 * 1.01
    for k in start:  # a bound never reached changes nothing, bit for bit
        assert torch.equal(loose[k], free[k]), k
    rows = {name: read_csv(tmp_path / name / "train.csv") for name in ("free", "tight")}
    assert [float(r["clipped"]) for r in rows["tight"]] == [1.0] * 4
    assert [float(r["clipped"]) for r in rows["free"]] == [0.0] * 4
    # The same first batch from the same weights: the logged norm is the one before clipping.
    first = float(rows["free"][0]["grad_norm"])
    assert first > 0 and float(rows["tight"][0]["grad_norm"]) == pytest.approx(first, rel=1e-6)
    for bad in (0.0, -1.0, math.nan):
        with pytest.raises(ValueError, match="max_grad_norm"):
            TrainConfig(max_grad_norm=bad)


def test_loss_is_the_mean_over_free_particles_and_ignores_kinematic_targets_and_weights(tmp_path):
    data = make_dataset(tmp_path / "data")
    simulator = train(data, tmp_path / "run", config(2), progress=False)
    simulator.eval()
    from gns.data import open_dataset

    sampler = WindowSampler(open_dataset(data), seed=3)
    t = batch_tensors(sampler.next_batch(2), torch.device("cpu"))
    step = TrainingStep(simulator)
    noise = torch.zeros_like(t["position_sequence"])
    with torch.no_grad():
        squared_sum, count = step(
            t["position_sequence"], t["next_position"], noise, t["particle_type"], t["n_node"],
            t["context"], t["material_property"],
        )  # fmt: skip
    free = ~np.isin(t["particle_type"].numpy(), [3])
    assert int(count) == free.sum() == 2 * (24 - 2)
    # By hand: the normalised target acceleration from positions and the running statistics.
    position = t["position_sequence"].double()
    acceleration = t["next_position"].double() - 2 * position[:, -1] + position[:, -2]
    normalizer = simulator.acceleration_normalizer
    target = (acceleration - normalizer.mean) / normalizer.std
    predicted = (
        simulator(t["position_sequence"], t["particle_type"], t["n_node"], t["context"])
        .detach()
        .double()
    )
    expected = (predicted - target).square().sum(-1)[torch.from_numpy(free)].sum()
    assert float(squared_sum) == pytest.approx(float(expected), rel=1e-5)
    # Moving the kinematic particles' next positions changes nothing.
    moved = t["next_position"].clone()
    moved[~torch.from_numpy(free)] += 0.05
    with torch.no_grad():
        again, _ = step(
            t["position_sequence"], moved, noise, t["particle_type"], t["n_node"], t["context"],
        )  # fmt: skip
    assert float(again) == float(squared_sum)
    # train.huber_delta: twice torch's Huber loss per dimension, with delta at the median error
    # so that half the errors are beyond it and count linearly.
    residual = (predicted - target)[torch.from_numpy(free)]
    delta = float(residual.abs().median())
    huber = TrainingStep(simulator, huber_delta=delta)
    with torch.no_grad():
        robust, _ = huber(
            t["position_sequence"], t["next_position"], noise, t["particle_type"], t["n_node"],
            t["context"], t["material_property"],
        )  # fmt: skip
    oracle = 2 * torch.nn.functional.huber_loss(
        residual, torch.zeros_like(residual), reduction="sum", delta=delta
    )
    assert float(robust) == pytest.approx(float(oracle), rel=1e-5)
    assert float(robust) < float(squared_sum)
    with pytest.raises(ValueError, match="huber_delta must be positive, got -1.0"):
        TrainConfig(huber_delta=-1.0)
    # train.target_weight: each particle's squared error times 1 + w |its target|.
    weighted = TrainingStep(simulator, target_weight=2.5)
    with torch.no_grad():
        heavier, _ = weighted(
            t["position_sequence"], t["next_position"], noise, t["particle_type"], t["n_node"],
            t["context"], t["material_property"],
        )  # fmt: skip
    keep = torch.from_numpy(free)
    by_hand = (predicted - target).square().sum(-1) * (1 + 2.5 * target.norm(dim=-1))
    assert float(heavier) == pytest.approx(float(by_hand[keep].sum()), rel=1e-5)
    with pytest.raises(ValueError, match="target_weight must be >= 0, got nan"):
        TrainConfig(target_weight=float("nan"))
    with pytest.raises(ValueError, match="early_steps must be >= 0, got -1"):
        TrainConfig(early_steps=-1)
    with pytest.raises(ValueError, match="early_repeat must be positive, got 0"):
        TrainConfig(early_repeat=0)


def test_training_reduces_the_loss_and_validates(tmp_path):
    data = make_dataset(tmp_path / "data", trajectories=4, frames=30)
    settings = dict(log_every=20, validate_every=20, validation_windows=8, checkpoint_every=80)
    settings.update(validation_rollouts=1, validation_rollout_steps=5, learning_rate=3e-3)
    cfg = Config(model=TINY, noise=NoiseConfig(std=0.0), train=config(80, **settings).train)
    train(data, tmp_path / "run", cfg, progress=False)
    losses = [float(r["loss"]) for r in read_csv(tmp_path / "run/train.csv")]
    assert losses[-1] < 0.7 * losses[0]
    valid = read_csv(tmp_path / "run/valid.csv")
    assert [int(r["step"]) for r in valid] == [20, 40, 60, 80]
    for row in valid:
        assert np.isfinite(float(row["one_step_mse"])) and np.isfinite(float(row["rollout_mse"]))
        assert 0.0 <= float(row["rollout_outside_box"]) < 0.1
    # best.pt holds the weights of the best validation (rollouts in the box first, then the
    # lowest rollout MSE): validating them again reproduces that row, and a run folder loads
    # them unless latest is asked for.
    radius = load_simulator(tmp_path / "run").scene.radius
    in_box = [
        float(r["rollout_outside_box"]) <= float(r["truth_outside_box"]) + 0.5 * radius
        for r in valid
    ]
    best_row = min(valid, key=lambda r: (not in_box[valid.index(r)], float(r["rollout_mse"])))
    best = load_checkpoint(tmp_path / "run/checkpoints/best.pt")
    assert best["step"] == int(best_row["step"])
    assert choose_checkpoint(tmp_path / "run") == tmp_path / "run/checkpoints/best.pt"
    assert choose_checkpoint(tmp_path / "run", "latest").name == "step_000000080.pt"
    trajectories = list(open_dataset(data, "valid"))
    again = validate(load_simulator(tmp_path / "run"), trajectories, cfg.train, torch.device("cpu"))
    assert again["rollout_mse"] == pytest.approx(float(best_row["rollout_mse"]), rel=1e-5)
    # TensorBoard's own reader sees the same figures.
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(tmp_path / "run/tensorboard"))
    events.Reload()
    logged = [e.value for e in events.Scalars("train/loss")]
    assert logged == pytest.approx(losses, rel=1e-6)


def test_a_nan_loss_stops_training_with_the_step(tmp_path):
    data = make_dataset(tmp_path / "data")
    with pytest.raises(FloatingPointError, match="at step 1"):
        train(data, tmp_path / "run", config(3, learning_rate=float("inf")), progress=False)


DDP_SCRIPT = """
import sys, torch
torch.set_num_threads(1)
from gns.config import Config, ModelConfig, NoiseConfig, TrainConfig
from gns.train import train
import torch.distributed as dist
data, out, steps, batch = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
config = Config(
    model=ModelConfig(latent_size=8, mlp_hidden_size=8, message_passing_steps=2),
    noise=NoiseConfig(std=0.0),
    train=TrainConfig(steps=steps, batch_size=batch, log_every=1, checkpoint_every=steps,
                      validate_every=0, trajectories_in_memory=2, learning_rate=1e-3),
)
simulator = train(data, out, config, progress=False)
rank = dist.get_rank() if dist.is_initialized() else 0
torch.save(simulator.state_dict(), f"{out}/rank{rank}.pt")
"""


def test_ddp_ranks_stay_identical_and_match_one_process_on_the_combined_batch(tmp_path):
    data = make_dataset(tmp_path / "data")
    script = tmp_path / "run_train.py"
    script.write_text(textwrap.dedent(DDP_SCRIPT))
    env = dict(os.environ, OMP_NUM_THREADS="1")
    torchrun = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--standalone",
        "--nproc_per_node",
        "2",
    ]
    subprocess.run(
        [*torchrun, str(script), str(data), str(tmp_path / "ddp"), "6", "1"],
        check=True,
        env=env,
        timeout=300,
    )
    subprocess.run(
        [sys.executable, str(script), str(data), str(tmp_path / "one"), "6", "2"],
        check=True,
        env=env,
        timeout=300,
    )
    rank0 = torch.load(tmp_path / "ddp/rank0.pt")
    rank1 = torch.load(tmp_path / "ddp/rank1.pt")
    single = torch.load(tmp_path / "one/rank0.pt")
    for key in rank0:
        assert torch.equal(rank0[key], rank1[key]), key
        # The same windows, the same global mean loss, summed in another order.
        torch.testing.assert_close(rank0[key], single[key], rtol=1e-4, atol=1e-6, msg=key)
    # Each rank saw its own half of the data: the statistics count both halves.
    assert rank0["acceleration_normalizer.count"] == single["acceleration_normalizer.count"]
    losses_ddp = [float(r["loss"]) for r in read_csv(tmp_path / "ddp/train.csv")]
    losses_one = [float(r["loss"]) for r in read_csv(tmp_path / "one/train.csv")]
    assert losses_ddp == pytest.approx(losses_one, rel=1e-4)


def test_validation_prefers_rollouts_that_stay_in_the_box():
    radius = 0.02
    leaves = {"rollout_mse": 0.05, "rollout_outside_box": 0.013, "truth_outside_box": 0.002}
    leaking = {"rollout_mse": 0.01, "rollout_outside_box": 0.3, "truth_outside_box": 0.002}
    # Allowed: the truth's own 0.002 plus half the radius, 0.012 in all: 0.013 is past it.
    assert not stays_in_box(leaves, radius)
    assert stays_in_box({**leaves, "rollout_outside_box": 0.0119}, radius)
    assert stays_in_box({"rollout_mse": 1.0}, radius)  # no bounds: nothing to leave
    first = better_validation(leaking, None, radius)
    assert first == {"value": 0.01, "in_box": False}
    ok = {**leaves, "rollout_outside_box": 0.0119}
    # In the box beats a lower MSE that leaked; then only a lower MSE in the box beats it.
    assert better_validation(ok, first, radius) == {"value": 0.05, "in_box": True}
    assert better_validation(leaking, {"value": 0.05, "in_box": True}, radius) is None
    assert better_validation({**ok, "rollout_mse": 0.04}, {"value": 0.05, "in_box": True}, radius)
    assert (
        better_validation({**ok, "rollout_mse": 0.06}, {"value": 0.05, "in_box": True}, radius)
        is None
    )
    # Records saved before "in_box" existed count as having left the box.
    assert better_validation(ok, {"step": 6000, "value": 0.001}, radius)["in_box"]
    # Without rollouts the one-step MSE decides.
    assert better_validation({"one_step_mse": 2e-8}, None, radius) == {
        "value": 2e-8,
        "in_box": True,
    }
    assert better_validation({}, None, radius) is None


def test_mirror_axes_and_early_windows_change_what_training_sees(tmp_path):
    data = make_dataset(tmp_path / "data")
    plain = parameters(train(data, tmp_path / "a", config(6), progress=False))
    mirrored = parameters(train(data, tmp_path / "b", config(6, mirror_axes=(0,)), progress=False))
    assert any(not torch.equal(plain[k], mirrored[k]) for k in plain)
    early = config(6, early_steps=2, early_repeat=3)
    repeated = parameters(train(data, tmp_path / "c", early, progress=False))
    assert any(not torch.equal(plain[k], repeated[k]) for k in plain)


def test_a_diverging_validation_rollout_is_the_worst_figure_not_a_crash(tmp_path):
    data = make_dataset(tmp_path / "data")
    train(data, tmp_path / "run", config(2), progress=False)
    sim = load_simulator(tmp_path / "run")
    torch.nn.init.constant_(sim.model.decoder[-1].bias, float("nan"))
    trajectories = list(open_dataset(data, "valid"))
    settings = config(2, validation_windows=0, validation_rollouts=2, validation_rollout_steps=4)
    figures = validate(sim, trajectories, settings.train, torch.device("cpu"))
    assert figures["rollout_mse"] == math.inf and figures["rollout_outside_box"] == math.inf
    # The ground truth's own excursion is still measured (finite), and such a validation is
    # never preferred to one that stayed finite.
    assert math.isfinite(figures["truth_outside_box"])
    assert better_validation(figures, {"value": 1.0, "in_box": False}, 0.1) is None


def test_validation_on_another_dataset_at_finer_frames(tmp_path):
    """--valid-data: a model trained on every 3rd frame validates on the native data's valid
    split at its own step. The oracle: validating on the converted folder's valid split, the
    same frames, gives the same figures."""
    from gns.data import convert

    native = make_dataset(tmp_path / "native", frames=27)
    convert(native, tmp_path / "converted", "h5", frame_stride=3)
    settings = config(
        4,
        validate_every=2,
        validation_windows=4,
        validation_rollouts=1,
        validation_rollout_steps=2,
        checkpoint_every=2,
    )
    train(tmp_path / "converted", tmp_path / "a", settings, progress=False, valid_data=native)
    train(tmp_path / "converted", tmp_path / "b", settings, progress=False)
    ours, theirs = read_csv(tmp_path / "a" / "valid.csv"), read_csv(tmp_path / "b" / "valid.csv")
    assert len(ours) == 2 and ours == theirs
    # A resume validates on the recorded data; at another path (the run moved machines) on the
    # same trajectories (here the converted folder's valid split: the same frames); never on
    # other trajectories (the native data with one particle moved, in another folder).
    train(tmp_path / "converted", tmp_path / "a", None, steps=6, resume=True, progress=False)
    assert [row["step"] for row in read_csv(tmp_path / "a" / "valid.csv")] == ["2", "4", "6"]
    resume = dict(resume=True, progress=False)
    train(
        tmp_path / "converted",
        tmp_path / "a",
        None,
        steps=8,
        **resume,
        valid_data=tmp_path / "converted",
    )
    assert [row["step"] for row in read_csv(tmp_path / "a" / "valid.csv")] == ["2", "4", "6", "8"]
    moved = list(open_dataset(native, "valid"))
    moved[1].positions[9, 3, 0] += 1e-3
    write_metadata(tmp_path / "moved", metadata_dict(sequence_length=26))
    write_h5(tmp_path / "moved" / "valid.h5", moved)
    with pytest.raises(
        ValueError,
        match="other trajectories than those now at .*moved .it validated on .*converted",
    ):
        train(
            tmp_path / "converted",
            tmp_path / "a",
            None,
            steps=10,
            **resume,
            valid_data=tmp_path / "moved",
        )
    # Nor on other trajectories at the recorded path.
    changed = list(open_dataset(tmp_path / "converted", "valid"))
    changed[0].positions[2, 5, 1] += 1e-3
    write_h5(tmp_path / "converted" / "valid.h5", changed)
    with pytest.raises(ValueError, match="other trajectories than those now at .*converted;"):
        train(tmp_path / "converted", tmp_path / "a", None, steps=10, **resume)
    assert [row["step"] for row in read_csv(tmp_path / "a" / "valid.csv")] == ["2", "4", "6", "8"]
    # A checkpoint from before the digest was recorded knows only the path: another is refused
    # even where it holds the same trajectories.
    path = latest_checkpoint(tmp_path / "b")
    state = load_checkpoint(path, resume=True)
    del state["valid_digest"]
    save_checkpoint(path, state)
    with pytest.raises(ValueError, match="validated on its own data, not on .*native;"):
        train(tmp_path / "converted", tmp_path / "b", None, steps=6, **resume, valid_data=native)


def test_validation_data_of_another_kind_is_refused_before_training(tmp_path):
    data = make_dataset(tmp_path / "data")
    from gns.data import write_dataset

    other = tmp_path / "other"
    positions = np.random.default_rng(0).uniform(0.2, 0.8, (12, 5, 3))
    split = [Trajectory(positions, np.full(5, 5))]
    write_dataset(
        other,
        {"train": split, "valid": split},
        dt=0.0025,
        bounds=[[0.1, 0.9]] * 3,
        connectivity_radius=0.015,
        layout="h5",
    )
    settings = config(2, validate_every=1)
    with pytest.raises(
        ValueError, match="dimension 3 with 0 global features, but the model is 2D with 1"
    ):
        train(data, tmp_path / "run", settings, progress=False, valid_data=other)
    with pytest.raises(ValueError):  # no valid split at all
        train(data, tmp_path / "run2", settings, progress=False, valid_data=tmp_path / "data2")
