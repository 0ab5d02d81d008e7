"""Model folders: `gns export` (one checkpoint or the average of the last few), loading a model
folder or a shipped model by name, and where outputs of a model folder go."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest
import torch
from data_helpers import SAND as SAND2D
from gns import checkpoints
from gns.checkpoints import (
    MODEL_FILE,
    WEIGHTS_KEYS,
    choose_checkpoint,
    export_model,
    load_checkpoint,
    load_simulator,
    model_location,
    shipped_models,
)
from gns.cli import main
from test_train import trained_run

pytestmark = pytest.mark.usefixtures("torch_one_thread")


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> tuple[Path, Path]:
    """(run folder with step_3, step_6 and step_9 checkpoints, dataset with a test split)."""
    return trained_run(tmp_path_factory.mktemp("models"), 9, frames=14)


def steps_of(run: Path) -> list[Path]:
    return sorted((run / "checkpoints").glob("step_*.pt"))


def test_export_keeps_the_weights_a_rollout_needs_and_nothing_else(run, tmp_path):
    folder, _ = run
    state = export_model(folder, tmp_path / "m", checkpoint="latest")
    written = load_checkpoint(tmp_path / "m" / MODEL_FILE)
    assert set(written) == set(WEIGHTS_KEYS)
    latest = load_checkpoint(steps_of(folder)[-1])
    assert written["step"] == latest["step"] == state["step"] == 9
    for name, value in latest["model"].items():
        torch.testing.assert_close(written["model"][name], value, rtol=0, atol=0)
    # Without the optimizer's moments the file is about a third of a step checkpoint.
    size = (tmp_path / "m" / MODEL_FILE).stat().st_size
    assert size < 0.6 * steps_of(folder)[-1].stat().st_size


def test_an_averaged_export_is_the_mean_of_the_parameters_and_the_newest_buffers(run, tmp_path):
    folder, _ = run
    state = export_model(folder, tmp_path / "m", average=2)
    assert state["averaged_steps"] == [6, 9]
    six, nine = (load_checkpoint(p)["model"] for p in steps_of(folder)[-2:])
    simulator = load_simulator(tmp_path / "m")
    parameters = dict(simulator.named_parameters())
    assert parameters, "the model has parameters"
    for name, value in simulator.state_dict().items():
        if name in parameters:
            # The oracle: elementwise (a + b) / 2 of the two files.
            torch.testing.assert_close(value, (six[name] + nine[name]) / 2)
            assert not torch.equal(six[name], nine[name]) or name.endswith("bias")
        else:
            torch.testing.assert_close(value, nine[name], rtol=0, atol=0)


def test_export_refuses_what_it_cannot_average(run, tmp_path):
    folder, _ = run
    with pytest.raises(ValueError, match="average=5 needs 5 step_.*found 3"):
        export_model(folder, tmp_path / "m", average=5)
    with pytest.raises(ValueError, match="average must be an integer >= 1, got 0"):
        export_model(folder, tmp_path / "m", average=0)
    with pytest.raises(ValueError, match="drop 'best'"):
        export_model(folder, tmp_path / "m", checkpoint="best", average=2)
    assert not (tmp_path / "m").exists()


def test_checkpoints_of_a_resumed_run_average_unless_the_model_changed(run, tmp_path):
    """A run resumed with another --steps records another [train] section from then on; its
    checkpoints are still one model. A changed [model] section is refused, named."""
    folder, _ = run
    copy = tmp_path / "run"
    (copy / "checkpoints").mkdir(parents=True)
    for path in steps_of(folder):
        state = load_checkpoint(path)
        if state["step"] == 9:
            state["config"]["train"]["steps"] = 1000
            state["config"]["noise"]["std"] = 0.5 * state["config"]["noise"]["std"]
        torch.save(state, copy / "checkpoints" / path.name)
    assert export_model(copy, tmp_path / "m", average=2)["averaged_steps"] == [6, 9]
    last = copy / "checkpoints" / steps_of(folder)[-1].name
    state = load_checkpoint(last)
    state["config"]["model"]["latent_size"] += 1
    torch.save(state, last)
    with pytest.raises(ValueError, match=r"different models \(step 6 and step 9 differ in model\)"):
        export_model(copy, tmp_path / "m2", average=2)


def test_a_model_folder_rolls_out_and_writes_beside_the_working_directory(
    run, tmp_path, monkeypatch
):
    folder, data = run
    assert main(["export", "--run", str(folder), "--out", str(tmp_path / "mine")]) == 0
    assert choose_checkpoint(tmp_path / "mine") == tmp_path / "mine" / MODEL_FILE
    with pytest.raises(ValueError, match="picks from a run folder, but .* is a model folder"):
        choose_checkpoint(tmp_path / "mine", "latest")
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    argv = ["--run", str(tmp_path / "mine"), "--data", str(data), "--threads", "1"]
    assert main(["rollout", *argv]) == 0
    assert main(["eval", *argv, "--one-step-windows", "8"]) == 0
    # The model folder keeps its weights and nothing else; outputs go to ./mine.
    assert sorted(os.listdir(tmp_path / "mine")) == [MODEL_FILE]
    assert sorted(p.name for p in (work / "mine" / "rollouts" / "test").iterdir()) == [
        "rollout_test_0.npz",
        "rollout_test_1.npz",
    ]
    assert (work / "mine" / "eval_test.json").is_file()
    # Rollouts kept elsewhere: the eval still lands in ./mine, made if need be.
    (work / "mine" / "rollouts").rename(tmp_path / "kept")
    (work / "mine" / "eval_test.json").unlink()
    (work / "mine").rmdir()
    kept = ["--rollouts", str(tmp_path / "kept" / "test"), "--one-step-windows", "0"]
    assert main(["eval", *argv, *kept]) == 0
    assert (work / "mine" / "eval_test.json").is_file()
    # So does a report, rather than into the model folder (a shipped one may be read-only).
    assert main(["report", *argv, "--animation-frames", "0", "--vtk-every", "0", "--quiet"]) == 0
    assert (work / "mine" / "report_test" / "report.md").is_file()
    assert sorted(os.listdir(tmp_path / "mine")) == [MODEL_FILE]


def test_written_files_get_the_usual_permissions(run, tmp_path):
    # mkstemp's temporaries are private (0600); a model or dataset others read must not be.
    folder, _ = run
    umask = os.umask(0o022)
    os.umask(umask)
    export_model(folder, tmp_path / "m")
    mode = stat.S_IMODE((tmp_path / "m" / MODEL_FILE).stat().st_mode)
    assert mode == 0o666 & ~umask


def test_an_unknown_model_name_lists_the_shipped_ones(capsys):
    with pytest.raises(ValueError, match="nor a shipped model of that name"):
        model_location("no-such-model")
    assert main(["rollout", "--run", "no-such-model", "--data", "."]) == 2
    assert "shipped:" in capsys.readouterr().err


@pytest.mark.parametrize("name", shipped_models())
def test_a_shipped_model_loads_by_name_and_has_its_card(name, tmp_path, monkeypatch):
    simulator = load_simulator(name)
    folder = checkpoints.SHIPPED_MODELS / name
    assert model_location(name) == folder
    # Its outputs' folder ./NAME, which holds no model, does not hide it.
    monkeypatch.chdir(tmp_path)
    (tmp_path / name / "rollouts").mkdir(parents=True)
    assert model_location(name) == folder
    card = (folder / "README.md").read_text(encoding="utf-8")
    # The card says how it was made and how to check it.
    for needed in ("gns train", "gns export", "gns eval", "Known failure"):
        assert needed in card, needed
    assert simulator.scene.dt is not None, "a shipped model knows its frame spacing"
    # Inference only: a few MB.
    assert (folder / MODEL_FILE).stat().st_size < 8e6


@pytest.mark.skipif(not (SAND2D / "manifest.json").is_file(), reason="../shared not present")
@pytest.mark.parametrize("name", [n for n in shipped_models() if n == "sand2d-taichi"])
def test_the_sand_model_rolls_out_on_taichis_native_frames_by_name(name, tmp_path):
    """No convert step: the model steps every 3rd of the 2.5 ms frames, as it was trained."""
    from gns.rollout import load_rollout

    out = tmp_path / "r"
    argv = ["rollout", "--run", name, "--data", str(SAND2D), "--trajectories", "0"]
    assert main([*argv, "--steps", "4", "--out", str(out), "--threads", "1"]) == 0
    rollout = load_rollout(out / "rollout_test_0.npz")
    assert rollout.metadata["frame_stride"] == 3
    assert rollout.predicted_rollout.shape == (4, 656, 2)
    assert torch.isfinite(torch.from_numpy(rollout.predicted_rollout)).all()


@pytest.mark.slow
@pytest.mark.skipif(not (SAND2D / "manifest.json").is_file(), reason="../shared not present")
@pytest.mark.parametrize("name", [n for n in shipped_models() if n == "sand2d-taichi"])
def test_the_sand_model_gives_its_cards_figures(name):
    """The card's per-trajectory MSE, for the first and last test trajectory (a block at rest,
    one thrown), read from the card itself: a change to the features, the model or the
    rollout that changes what the shipped weights do fails here. The card's first MSE column
    is of fp32 rollouts, as these are (the next, of bf16 ones, moves by up to 22%); other CPUs
    round differently and a sand rollout amplifies that, hence 5%."""
    import re

    import numpy as np
    from gns.data import at_frame_stride, open_dataset
    from gns.rollout import rollout

    card = (checkpoints.SHIPPED_MODELS / name / "README.md").read_text(encoding="utf-8")
    simulator = load_simulator(name)
    dataset = open_dataset(SAND2D, "test")
    stride = simulator.frame_stride_for(dataset.metadata)
    for index in (0, len(dataset) - 1):
        trajectory = dataset[index]
        stem = Path(trajectory.source).stem
        (figure,) = re.findall(rf"^\| {stem} \([^)]*\) \| ([0-9.e+-]+) \|", card, re.MULTILINE)
        result = rollout(simulator, at_frame_stride(trajectory, stride))
        mse = float(np.mean((result.predicted_rollout - result.ground_truth_rollout) ** 2))
        assert mse == pytest.approx(float(figure), rel=0.05), stem
