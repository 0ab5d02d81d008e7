"""Fine-tuning (`gns train --init-from MODEL`): a new run that starts from a trained model's
weights and running statistics, with only [noise] and [train] changeable."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch
from gns.checkpoints import (
    MODEL_FILE,
    choose_checkpoint,
    latest_checkpoint,
    load_checkpoint,
    load_simulator,
    model_location,
)
from gns.cli import main
from gns.config import ModelConfig, TrainConfig
from gns.data import write_dataset
from gns.train import train
from test_train import config, make_dataset, parameters, read_csv, trained_run


def weights(simulator) -> dict[str, torch.Tensor]:
    """The learned parameters (not the normalisers' running sums)."""
    return {k: v.detach().clone() for k, v in simulator.named_parameters()}


def largest_difference(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> float:
    assert a.keys() == b.keys()
    return max(float((a[k] - b[k]).abs().max()) for k in a)


def test_fine_tuning_starts_from_the_model_and_adds_to_its_statistics(tmp_path):
    run, _ = trained_run(tmp_path / "a", steps=6)
    source = load_simulator(run, checkpoint="latest")
    data = make_dataset(tmp_path / "other")  # the same scene, other trajectories
    # A learning rate so small that one Adam step (which moves each weight by about lr) leaves
    # the weights where they started: the start itself is what is compared.
    tiny = config(1, learning_rate=1e-9, learning_rate_final=1e-9)
    tuned = train(data, tmp_path / "b", tiny, progress=False, init_from=run)
    fresh = train(data, tmp_path / "c", tiny, progress=False)

    assert largest_difference(weights(tuned), weights(source)) < 1e-6
    assert largest_difference(weights(fresh), weights(source)) > 1e-3  # the test can fail
    # The running statistics go on from the model's: what it had seen, plus the one batch the
    # fresh run (same seed, so the same windows and noise) saw.
    for name in ("velocity_normalizer", "acceleration_normalizer", "context_normalizer"):
        counts = [getattr(s, name).count for s in (tuned, source, fresh)]
        assert counts[0] == counts[1] + counts[2], name
    saved = load_checkpoint(latest_checkpoint(tmp_path / "b"))
    assert saved["init_from"] == str(run)
    assert saved["step"] == 1  # the step count starts anew


def test_fine_tuning_trains_with_its_own_noise(tmp_path):
    run, data = trained_run(tmp_path / "a", steps=4)
    source = load_simulator(run, checkpoint="latest")
    quieter = dataclasses.replace(
        source.config,
        noise=dataclasses.replace(source.config.noise, std=source.config.noise.std / 10),
        train=config(3).train,
    )
    tuned = train(data, tmp_path / "b", quieter, progress=False, init_from=run)
    assert tuned.config == quieter
    # The noise it draws is the run's: std / 10 at the last input frame (random walk).
    sequence = torch.zeros(20000, source.config.model.velocity_history + 1, 2)
    noise = tuned.sample_noise(sequence, torch.full((20000,), 5), torch.Generator().manual_seed(0))
    last_velocity = noise[:, -1] - noise[:, -2]
    assert abs(float(last_velocity.std()) / quieter.noise.std - 1) < 0.05
    # ... so training differs from fine-tuning with the model's own noise (the test can fail).
    same = train(
        data,
        tmp_path / "c",
        dataclasses.replace(quieter, noise=source.config.noise),
        progress=False,
        init_from=run,
    )
    assert largest_difference(weights(tuned), weights(same)) > 0


@pytest.mark.usefixtures("torch_one_thread")  # a fixed thread count: the same sums every step
def test_a_fine_tuned_run_resumes_exactly(tmp_path):
    run, data = trained_run(tmp_path / "a", steps=4)
    straight = train(data, tmp_path / "b", config(6), progress=False, init_from=run)
    train(data, tmp_path / "c", config(3), progress=False, init_from=run)
    resumed = train(data, tmp_path / "c", config(6), progress=False, resume=True)
    a, b = parameters(straight), parameters(resumed)
    for key in a:
        assert torch.equal(a[key], b[key]), key
    assert load_checkpoint(latest_checkpoint(tmp_path / "c"))["init_from"] == str(run)


def test_fine_tuning_refuses_another_network_scene_or_a_resume(tmp_path):
    run, data = trained_run(tmp_path / "a", steps=2)
    wider = dataclasses.replace(
        config(2), model=ModelConfig(latent_size=16, mlp_hidden_size=8, message_passing_steps=2)
    )
    with pytest.raises(ValueError, match=r"config's \[model\] differ from the model's"):
        train(data, tmp_path / "b", wider, progress=False, init_from=run)

    coarser = make_dataset(tmp_path / "coarser")
    meta = json.loads((coarser / "metadata.json").read_text())
    meta["dt"] = 0.005
    (coarser / "metadata.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=r"dt 0.005 \(the model's: 0.0025\)"):
        train(coarser, tmp_path / "c", config(2), progress=False, init_from=run)

    train(data, tmp_path / "d", config(2), progress=False)
    with pytest.raises(ValueError, match="--init-from starts a new run"):
        train(data, tmp_path / "d", config(4), progress=False, resume=True, init_from=run)
    assert not (tmp_path / "b").exists() and not (tmp_path / "c").exists()


def test_the_command_line_fine_tunes_with_the_models_own_config(tmp_path):
    run, data = trained_run(tmp_path / "a", steps=2)
    argv = ["train", "--data", str(data), "--out", str(tmp_path / "b"), "--init-from", str(run)]
    assert main([*argv, "--steps", "1", "--quiet", "--threads", "1"]) == 0
    tuned = load_checkpoint(latest_checkpoint(tmp_path / "b"))
    assert tuned["config"]["model"] == load_checkpoint(latest_checkpoint(run))["config"]["model"]
    assert tuned["init_from"] == str(run)


@pytest.mark.parametrize("old_format", [False, True])
def test_the_shipped_model_fine_tunes_on_data_of_its_scene(tmp_path, old_format):
    """The shipped model fine-tunes on data of its own scene (walls seen from 20 radii, no
    obstacles), and so does the same model saved as checkpoint format 2, before the scene had
    obstacle features (the shipped model's format until 2026-11-26)."""
    shipped = load_simulator("sand2d-taichi")
    init_from = "sand2d-taichi"
    if old_format:
        state = load_checkpoint(choose_checkpoint(model_location("sand2d-taichi")))
        for key in ("obstacles", "obstacle_clip"):
            del state["scene"][key]
        state["format"] = "gns-checkpoint-2"
        (tmp_path / "old").mkdir()
        torch.save(state, tmp_path / "old" / MODEL_FILE)
        init_from = tmp_path / "old"
    scene = shipped.scene
    rng = np.random.default_rng(0)
    x = 0.4 + 0.2 * rng.random((1, 40, 2)) + np.zeros((12, 1, 1))
    trajectory = {
        "positions": x.astype(np.float32),
        "particle_type": np.full(40, 6),
        "material_property": np.float32(0.6),
    }
    write_dataset(
        tmp_path / "d",
        {"train": [trajectory]},
        dt=scene.dt,
        bounds=scene.bounds,
        connectivity_radius=scene.radius,
    )
    short = TrainConfig(steps=2, validate_every=0, checkpoint_every=2)
    config = dataclasses.replace(shipped.config, train=short)
    train(tmp_path / "d", tmp_path / "b", config, progress=False, init_from=init_from)
    tuned = load_simulator(tmp_path / "b")
    assert tuned.scene == scene


def test_fine_tuning_validates_its_start_so_best_is_never_worse(tmp_path):
    run, _ = trained_run(tmp_path / "a", steps=6)
    data = make_dataset(tmp_path / "other")  # has a valid split
    source = load_simulator(run, checkpoint="latest")
    # A learning rate so large that the first steps wreck the weights: no later validation
    # can beat the start, so best.pt must be the starting weights, validated as step 0.
    wild = config(4, learning_rate=1.0, learning_rate_final=1.0, validate_every=2)
    wild = dataclasses.replace(wild, train=dataclasses.replace(wild.train, validation_rollouts=2))
    train(data, tmp_path / "b", wild, progress=False, init_from=run)
    steps = [row["step"] for row in read_csv(tmp_path / "b" / "valid.csv")]
    assert steps == ["0", "2", "4"]
    rollout = [float(row["rollout_mse"]) for row in read_csv(tmp_path / "b" / "valid.csv")]
    assert rollout[0] < min(rollout[1:])  # the test can fail: the wild steps did get worse
    best = load_checkpoint(tmp_path / "b" / "checkpoints" / "best.pt")
    assert best["best"]["step"] == 0 and best["step"] == 0
    kept = load_simulator(tmp_path / "b", checkpoint="best")
    assert largest_difference(weights(kept), weights(source)) == 0.0


def test_a_time_limited_run_validates_its_last_step(tmp_path):
    data = make_dataset(tmp_path / "data")
    # The limit has passed after the first step; validation every 100 steps would never run.
    train(data, tmp_path / "run", config(50, validate_every=100), progress=False, time_limit=1e-9)
    assert [row["step"] for row in read_csv(tmp_path / "run" / "valid.csv")] == ["1"]
    assert load_checkpoint(tmp_path / "run" / "checkpoints" / "best.pt")["step"] == 1
