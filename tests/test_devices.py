"""Every step of training, rollout and evaluation keeps its tensors on the simulator's device.

CI has no GPU, so the device is a stand-in (tests/device_check.py): CPU memory that reports
another device and fails, as CUDA does, on any operation that mixes it with CPU tensors. The
oracle: the same work on the CPU, whose results the stand-in must reproduce bit for bit.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from device_check import STAND_IN, DeviceMixing, OnDevice, stand_in_device
from gns.checkpoints import load_checkpoint, simulator_from_checkpoint
from gns.config import Config, ModelConfig, TrainConfig
from gns.data import Trajectory, open_dataset
from gns.evaluate import one_step_errors, rest_test
from gns.ops import Obstacle
from gns.rollout import rollout
from gns.simulator import LearnedSimulator, Scene
from gns.train import train
from test_train import make_dataset

pytestmark = pytest.mark.usefixtures("torch_one_thread")


def test_the_stand_in_device_fails_where_cuda_fails(monkeypatch):
    """The harness itself: without this, a green test_devices would prove nothing."""
    with stand_in_device(monkeypatch) as transfers:
        x = torch.arange(6.0).reshape(3, 2).to(STAND_IN)
        assert isinstance(x, OnDevice) and x.device == STAND_IN
        with pytest.raises(DeviceMixing, match="same device"):
            x + torch.ones(3, 2)
        with pytest.raises(DeviceMixing):
            x.index_select(0, torch.tensor([0, 2]))  # a CPU index, as in the old rollout
        with pytest.raises(DeviceMixing):
            torch.isin(torch.tensor([1, 3]).to(STAND_IN), torch.tensor([3]))
        with pytest.raises(TypeError, match="numpy"):
            x.numpy()
        with pytest.raises(DeviceMixing, match="generator"):
            torch.randn(3, generator=torch.Generator(), device=STAND_IN)
        # What CUDA allows: CPU scalars, Python scalars, copies, and results read back.
        y = x * torch.tensor(2.0) + 1.0
        y = torch.where(y > 4.0, y, 0.0)
        assert isinstance(y, OnDevice)
        assert y.cpu().tolist() == [[0.0, 0.0], [5.0, 7.0], [9.0, 11.0]]
        noise = torch.randn(2, generator=torch.Generator(device=STAND_IN), device=STAND_IN)
        assert noise.device == STAND_IN
        host = torch.zeros(3, 2)
        host.copy_(x)
        assert host.tolist() == x.cpu().tolist() and float(x.sum()) == 15.0
    assert transfers.to_device == [(3, 2), (2,)] and transfers.to_host == [(3, 2)] * 3


def rich_scene_trajectory(periodic: bool, overburden: bool = False) -> tuple[Scene, Trajectory]:
    """Every kind of input: walls (or a periodic axis), two particle types with a kinematic
    one, a context, a material property; the overburden and the wall basis (with gravity)
    where asked."""
    rng = np.random.default_rng(3)
    n, frames = 40, 14
    start = rng.uniform(0.2, 0.8, (n, 2))
    velocity = rng.normal(0.0, 2e-3, (n, 2))
    positions = start + velocity * np.arange(frames)[:, None, None]
    types = np.full(n, 5)
    types[:4] = 3
    positions[:, :4] = start[:4]
    scene = Scene(
        2,
        0.1,
        (3, 5),
        bounds=((0.0, 1.0), (0.0, 1.0)),
        walls=True,
        periodic=(periodic, False),
        context_size=1,
        material_property_size=1,
        gravity=(0.0, -1e-4) if overburden else None,
        overburden=overburden,
        wall_basis=3 if overburden else 0,
    )
    trajectory = Trajectory(
        positions.astype(np.float32),
        types,
        step_context=np.full((frames, 1), 0.3, dtype=np.float32),
        material_property=np.full(n, 0.6, dtype=np.float32),
    )
    return scene, trajectory


def simulator_for(scene: Scene, global_latent: bool, obstacles: bool) -> LearnedSimulator:
    torch.manual_seed(0)
    model = ModelConfig(
        latent_size=8, mlp_hidden_size=8, message_passing_steps=2, global_latent=global_latent
    )
    shapes = [Obstacle.polyline([[0.1, 0.5], [0.4, 0.45]])] if obstacles else []
    simulator = LearnedSimulator(scene, Config(model=model), obstacles=shapes)
    # Statistics of the data's size, so that the rollout stays in the box.
    for normalizer in (simulator.velocity_normalizer, simulator.acceleration_normalizer):
        normalizer.update(torch.randn(50, 2, dtype=torch.float64) * 1e-3)
    simulator.context_normalizer.update(torch.tensor([[0.3], [0.5]]))
    if simulator.overburden_normalizer is not None:
        simulator.overburden_normalizer.update(torch.tensor([[0.0, 0.0], [6.0, -1e-2]]))
    return simulator


@pytest.mark.parametrize(
    ("periodic", "global_latent", "obstacles", "overburden"),
    [(False, False, False, False), (True, True, True, False), (False, True, False, True)],
)
def test_a_rollout_on_the_device_equals_the_cpu_one_and_moves_little(
    monkeypatch, periodic, global_latent, obstacles, overburden
):
    scene, trajectory = rich_scene_trajectory(periodic, overburden)
    reference = rollout(simulator_for(scene, global_latent, obstacles), trajectory)
    counts = []
    for steps in (4, 8):
        simulator = simulator_for(scene, global_latent, obstacles)
        with stand_in_device(monkeypatch) as transfers:
            result = rollout(simulator, trajectory, num_steps=steps, device=STAND_IN)
            assert next(simulator.parameters()).device == STAND_IN
        np.testing.assert_array_equal(result.predicted_rollout, reference.predicted_rollout[:steps])
        assert result.metadata["device"] == str(STAND_IN)
        counts.append((len(transfers.to_host), len(transfers.to_device)))
        monkeypatch.undo()
    # Per step: the most recent positions to the host once (for the Rust core); back come the
    # edges, the periodic shifts when there are any, and the wall and obstacle distances.
    per_step = [(b - a) / 4 for a, b in zip(counts[0], counts[1], strict=True)]
    assert per_step == [1.0, 3.0 if periodic else 2.0]


def test_training_validation_and_evaluation_on_the_device_equal_the_cpu(tmp_path, monkeypatch):
    data = make_dataset(tmp_path / "data")
    settings = TrainConfig(
        steps=4,
        log_every=2,
        checkpoint_every=2,
        validate_every=2,
        validation_windows=3,
        validation_rollouts=1,
        validation_rollout_steps=3,
        trajectories_in_memory=2,
        learning_rate=1e-3,
        loss_steps=2,
    )
    model = ModelConfig(latent_size=8, mlp_hidden_size=8, message_passing_steps=2)
    config = Config(model=model, train=settings)
    on_cpu = train(data, tmp_path / "cpu", config, progress=False)
    with stand_in_device(monkeypatch):
        on_device = train(data, tmp_path / "device", config, progress=False, device=STAND_IN)
        assert next(on_device.parameters()).device == STAND_IN
        trajectories = list(open_dataset(data, "valid"))
        errors = one_step_errors(on_device, trajectories, device=STAND_IN)
        rest = rest_test(on_device, trajectories[0], 3, device=STAND_IN)
    # The checkpoints hold CPU tensors, loadable on a machine without the device.
    for name in ("step_000000004.pt", "best.pt"):
        state = load_checkpoint(tmp_path / "device/checkpoints" / name)
        assert all(type(v) is torch.Tensor for v in state["model"].values())
        reference = load_checkpoint(tmp_path / "cpu/checkpoints" / name)
        assert state["step"] == reference["step"]
        for key, value in reference["model"].items():
            assert torch.equal(state["model"][key], value), (name, key)
    assert (tmp_path / "device/valid.csv").read_text() == (tmp_path / "cpu/valid.csv").read_text()
    assert errors == one_step_errors(on_cpu, trajectories)
    assert rest == rest_test(on_cpu, trajectories[0], 3)
    # Resuming onto the device continues from a CPU checkpoint.
    with stand_in_device(monkeypatch):
        resumed = train(
            data,
            tmp_path / "device",
            dataclasses.replace(config, train=dataclasses.replace(settings, steps=6)),
            resume=True,
            progress=False,
            device=STAND_IN,
        )
        assert next(resumed.parameters()).device == STAND_IN
    assert simulator_from_checkpoint(load_checkpoint(tmp_path / "device/checkpoints/best.pt"))
