"""The command line refuses misuse before any work: exit status 2, one error line naming the
flag and the value, no traceback, and no output folder left behind. Paths it records resolve
from any working directory."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
from gns import checkpoints
from gns.cli import main
from gns.data import DatasetError
from gns.mpm import generate
from gns.rollout import load_rollout, save_rollout
from test_train import make_dataset, trained_run

pytestmark = pytest.mark.usefixtures("torch_one_thread")

FRAMES = 14  # the model reads 6: 8 steps to roll out


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> tuple[Path, Path]:
    """(run folder, dataset) of a GNS trained for 2 steps; the test split has 2 trajectories."""
    return trained_run(tmp_path_factory.mktemp("trained"), 2, frames=FRAMES)


@pytest.fixture
def untrained(tmp_path) -> tuple[Path, Path]:
    """(run folder without checkpoints, dataset): enough for every check made before work."""
    data = make_dataset(tmp_path / "data", trajectories=2, frames=FRAMES)
    (data / "valid.h5").rename(data / "test.h5")
    (tmp_path / "run").mkdir()
    return tmp_path / "run", data


def refused(capsys, argv: list[str], *expected: str) -> str:
    """Run `gns ARGV`: exit status 2, no traceback, and the one error line, which is the last
    line of stderr (argparse puts its usage above it) and holds each of `expected`."""
    assert main(argv) == 2
    captured = capsys.readouterr()
    lines = captured.err.splitlines()
    errors = [line for line in lines if ": error: " in line]
    assert len(errors) == 1 and errors[0] == lines[-1], captured.err
    assert "Traceback" not in captured.err
    for text in expected:
        assert text in errors[0]
    return errors[0]


# (argv after the command's required arguments, what the error line must say). `{out}` is the
# output folder that must not exist afterwards, `{tmp}` the test's folder.
Case = tuple[list[str], list[str]]

TRAIN: list[Case] = [
    (["--config", "{tmp}/missing.toml"], ["argument --config: no such file: ", "missing.toml"]),
    (["--config", "{tmp}"], ["argument --config: ", "is a folder, not a file"]),
    (["--steps", "0"], ["argument --steps: must be a whole number >= 1, got 0"]),
    (["--steps", "-3"], ["argument --steps: must be a whole number >= 1, got -3"]),
    (["--threads", "0"], ["argument --threads: must be a whole number >= 1, got 0"]),
    (
        ["--time-limit", "-1"],
        ["argument --time-limit: must be a positive number of minutes, got -1"],
    ),
    (["--time-limit", "nan"], ["--time-limit: must be a positive number of minutes, got nan"]),
    (["--device", "gpu"], ["argument --device: expected auto, cpu, cuda", "got gpu"]),
]
ROLLOUT: list[Case] = [
    (["--trajectories", "-1"], ["argument --trajectories: must be a whole number >= 0, got -1"]),
    (["--steps", "0"], ["argument --steps: must be a whole number >= 1, got 0"]),
    (["--steps", "-2"], ["argument --steps: must be a whole number >= 1, got -2"]),
    (["--escape-distance", "0"], ["argument --escape-distance: must be a positive number, got 0"]),
    (["--escape-distance", "-1"], ["--escape-distance: must be a positive number, got -1"]),
    (["--escape-distance", "nan"], ["--escape-distance: must be a positive number, got nan"]),
]
EVAL: list[Case] = [
    (["--rollouts", "{tmp}/nowhere"], ["argument --rollouts: no such folder: ", "nowhere"]),
    (["--every", "0"], ["argument --every: must be a whole number >= 1, got 0"]),
    (["--one-step-windows", "-1"], ["--one-step-windows: must be a whole number >= 0, got -1"]),
    (["--rest-steps", "-1"], ["argument --rest-steps: must be a whole number >= 0, got -1"]),
]
GENERATE: list[Case] = [
    (["--n-train", "-1"], ["argument --n-train: must be a whole number >= 1, got -1"]),
    (["--n-train", "0"], ["argument --n-train: must be a whole number >= 1, got 0"]),
    (["--n-test", "-1"], ["argument --n-test: must be a whole number >= 0, got -1"]),
    (["--workers", "0"], ["argument --workers: must be a whole number >= 1, got 0"]),
    (["--frames", "1"], ["argument --frames: must be a whole number >= 3, got 1"]),
    (["--seed", "-1"], ["argument --seed: must be a whole number >= 0, got -1"]),
    (["--preset", "lava"], ["argument --preset: unknown preset 'lava'; expected one of ", "sand"]),
]
REPORT: list[Case] = [
    (["--trajectories", "0"], ["argument --trajectories: must be a whole number >= 1, got 0"]),
    (["--every", "0"], ["argument --every: must be a whole number >= 1, got 0"]),
    (["--animation-frames", "-1"], ["--animation-frames: must be a whole number >= 0, got -1"]),
    (["--vtk-every", "-1"], ["argument --vtk-every: must be a whole number >= 0, got -1"]),
    (["--horizons", "1", "0"], ["argument --horizons: ", "got '0'"]),
    (["--horizons", "ten"], ["argument --horizons: ", "got 'ten'"]),
    (["--mpm", "grid=-3"], ["argument --mpm: MPM setting 'grid=-3'"]),
    (["--mpm", "none", "native"], ["argument --mpm: MPM setting 'none' cannot be combined"]),
    (["--rest-steps", "-1"], ["argument --rest-steps: must be a whole number >= 0, got -1"]),
    (["--rest-steps", "two"], ["argument --rest-steps: must be a whole number >= 0, got two"]),
]
DEMO: list[Case] = [
    (["--trajectories", "2", "0", "1"], ["--trajectories: must be a whole number >= 1, got 0"]),
    (["--train-minutes", "0"], ["--train-minutes: must be a positive number of minutes, got 0"]),
    (["--steps", "0"], ["argument --steps: must be a whole number >= 1, got 0"]),
    (["--frames", "3"], ["argument --frames: must be a whole number >= 8, got 3"]),
    (["--workers", "0"], ["argument --workers: must be a whole number >= 1, got 0"]),
    (["--preset", "lava"], ["argument --preset: unknown preset 'lava'; expected one of "]),
]


def commands(run: Path, data: Path, out: Path) -> dict[str, list[str]]:
    """Each command with its required arguments, writing to `out`."""
    common = ["--run", str(run), "--data", str(data)]
    return {
        "train": ["train", "--data", str(data), "--out", str(out)],
        "rollout": ["rollout", *common, "--out", str(out)],
        # eval writes into the run folder: `out` is the run folder there.
        "eval": ["eval", "--run", str(out), "--data", str(data)],
        "generate": ["generate", "--preset", "sand", "--out", str(out), "--n-train", "1"],
        "report": ["report", *common, "--out", str(out)],
        "demo": ["demo", "--out", str(out)],
    }


@pytest.mark.parametrize(
    ("command", "extra", "expected"),
    [
        (command, extra, expected)
        for command, cases in (
            ("train", TRAIN),
            ("rollout", ROLLOUT),
            ("eval", EVAL),
            ("generate", GENERATE),
            ("report", REPORT),
            ("demo", DEMO),
        )
        for extra, expected in cases
    ],
)
def test_a_bad_flag_is_refused_before_any_work(
    command, extra, expected, untrained, tmp_path, capsys
):
    run, data = untrained
    out = tmp_path / "out"
    argv = commands(run, data, out)[command]
    if command == "eval":
        out.mkdir()  # eval's --run must exist; what must not appear is its eval_test.json
    line = refused(capsys, [*argv, *(x.format(tmp=tmp_path) for x in extra)], *expected)
    assert line.startswith(f"gns {command}: error: ")
    if command == "eval":
        assert list(out.iterdir()) == []
    else:
        assert not out.exists()


def test_missing_input_paths_name_the_flag(untrained, tmp_path, capsys):
    run, data = untrained
    nowhere = str(tmp_path / "nowhere")
    out = tmp_path / "out"
    refused(
        capsys,
        ["train", "--data", nowhere, "--out", str(out)],
        "gns train: error: argument --data: no such file or folder: ",
        nowhere,
    )
    for command in ("rollout", "report"):
        refused(
            capsys,
            [command, "--run", nowhere, "--data", str(data), "--out", str(out)],
            f"gns {command}: error: argument --run: no such file or folder: {nowhere}",
        )
    refused(
        capsys,
        ["eval", "--run", str(run), "--data", nowhere],
        f"argument --data: no such file or folder: {nowhere}",
    )
    assert not out.exists() and list(run.iterdir()) == []


def test_trajectory_indices_past_the_split_are_refused_before_the_checkpoint(untrained, capsys):
    run, data = untrained  # no checkpoint: the indices are checked first
    line = refused(
        capsys,
        ["rollout", "--run", str(run), "--data", str(data), "--trajectories", "1", "99", "2"],
        "gns rollout: error: argument --trajectories: expected indices 0 to 1 (the test split "
        "has 2 trajectories), got 99 2",
    )
    assert "99" in line
    assert not (run / "rollouts").exists()


def test_errors_of_the_work_are_one_line_and_leave_no_folder(untrained, tmp_path, capsys):
    run, data = untrained
    out = tmp_path / "out"
    # A run folder without checkpoints (a ValueError of gns.checkpoints).
    refused(capsys, ["rollout", "--run", str(run), "--data", str(data)], "no checkpoints in")
    assert not (run / "rollouts").exists()
    # A folder that is not a dataset (gns.data.DatasetError).
    empty = tmp_path / "empty"
    empty.mkdir()
    refused(
        capsys,
        ["train", "--data", str(empty), "--out", str(out)],
        f"gns train: error: {empty}: neither metadata.json nor manifest.json found",
    )
    # A split the dataset does not have.
    refused(
        capsys,
        ["rollout", "--run", str(run), "--data", str(data), "--split", "nope"],
        "gns rollout: error: ",
        "no nope.tfrecord",
    )
    # A config file that is not TOML.
    bad = tmp_path / "bad.toml"
    bad.write_text("[train\n")
    refused(
        capsys,
        ["train", "--data", str(data), "--out", str(out), "--config", str(bad)],
        f"gns train: error: {bad}: not valid TOML/JSON",
    )
    # An eval with no rollouts to read.
    refused(
        capsys,
        ["eval", "--run", str(run), "--data", str(data)],
        "gns eval: error: no rollouts in ",
    )
    assert not out.exists() and list(run.iterdir()) == []


@pytest.mark.parametrize(
    "error",
    [
        FileNotFoundError(2, "No such file or directory", "x.h5"),
        NotADirectoryError(20, "Not a directory", "x/y"),
        PermissionError(13, "Permission denied", "out"),
        DatasetError("x.h5", "truncated record", 3),
        ValueError("a setting out of range"),
    ],
)
def test_input_errors_of_the_work_are_one_line(error, tmp_path, capsys, monkeypatch):
    def fail(*args: object, **kwargs: object) -> None:
        raise error

    monkeypatch.setattr(generate, "generate", fail)
    argv = ["generate", "--preset", "sand", "--out", str(tmp_path / "out"), "--n-train", "1"]
    assert refused(capsys, argv) == f"gns generate: error: {error}"


def test_an_existing_file_as_rollout_out_is_refused(untrained, tmp_path, capsys):
    run, data = untrained
    taken = tmp_path / "taken"
    taken.write_text("")
    refused(
        capsys,
        ["rollout", "--run", str(run), "--data", str(data), "--out", str(taken)],
        f"argument --out: {taken} exists and is not a folder",
    )


def test_no_traceback_from_the_gns_process(untrained, tmp_path):
    run, data = untrained
    for extra in (["--config", "missing.toml"], ["--time-limit", "-1"]):
        done = subprocess.run(
            [sys.executable, "-m", "gns", "train", "--data", str(data), "--out", "out", *extra],
            cwd=tmp_path,
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert done.returncode == 2 and "Traceback" not in done.stderr
        assert done.stderr.splitlines()[-1].startswith("gns train: error: argument ")
        assert not (tmp_path / "out").exists()


def test_help_returns_zero(capsys):
    assert main(["rollout", "--help"]) == 0
    assert "--trajectories" in capsys.readouterr().out


def test_eval_and_report_help_say_what_the_deposit_figures_are(capsys):
    assert main(["eval", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())  # argparse wraps lines
    for words in (
        "static (every particle stays where the last input frame has it)",
        "runout, the 99th minus the 1st percentile of x",
        "pile_height, the 99th percentile of y minus the floor (the box's lower y bound, else "
        "the ground truth's lowest y at frame 0)",
        "runout_ratio, height_ratio, density_ratio, each over the ground truth's",
        "front_x_p1 and front_x_p99",
        "of the last frame",
    ):
        assert words in text, words
    assert main(["report", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "--rest-steps K" in text and "constant-velocity and static baselines" in text
    assert "height ratio, the 99th percentile of y above the box's floor" in text
    assert "density ratio max, that ratio at its worst frame" in text


# ------------------------------------------------------------------- with a trained run


def test_too_many_steps_leave_no_rollout_folder(trained, tmp_path, capsys):
    run, data = trained
    out = tmp_path / "rollouts"
    argv = ["rollout", "--run", str(run), "--data", str(data), "--out", str(out)]
    refused(capsys, [*argv, "--steps", "1000"], "gns rollout: error: ")
    assert not out.exists()


def poisoned_after(calls: int) -> Callable[..., object]:
    """load_simulator whose decoder predicts an infinite acceleration for two free particles
    after `calls` steps."""
    original = checkpoints.load_simulator

    def load(*args: object, **kwargs: object) -> object:
        simulator = original(*args, **kwargs)
        seen = 0

        def poison(module: object, inputs: object, output: torch.Tensor) -> torch.Tensor:
            nonlocal seen
            seen += 1
            if seen > calls:
                output = output.clone()
                output[:2] = float("inf")  # the last two particles are kinematic
            return output

        simulator.model.decoder.register_forward_hook(poison)
        return simulator

    return load


def test_a_diverged_rollout_names_the_file_its_finite_steps_went_to(
    trained, tmp_path, capsys, monkeypatch
):
    run, data = trained
    monkeypatch.setattr(checkpoints, "load_simulator", poisoned_after(3))
    out = tmp_path / "rollouts"
    argv = ["rollout", "--run", str(run), "--data", str(data), "--out", str(out)]
    assert main([*argv, "--trajectories", "1"]) == 1
    err = capsys.readouterr().err
    saved = out / "rollout_test_1.npz"
    assert err.startswith("trajectory 1: rollout diverged at step 3 ")
    assert err.rstrip().endswith(f"; the 3 finite steps before it are saved in {saved}")
    assert ".rollout" not in err and err.count("steps before it") == 1
    assert len(err.splitlines()) == 1
    assert load_rollout(saved).num_steps == 3


def test_rollouts_record_absolute_paths_and_eval_reads_them_anywhere(
    trained, tmp_path, capsys, monkeypatch
):
    run, data = trained
    # Relative arguments, as typed in the run's parent folder.
    monkeypatch.chdir(run.parent)
    out = tmp_path / "rollouts"
    argv = ["rollout", "--run", run.name, "--data", data.name, "--out", str(out)]
    assert main([*argv, "--trajectories", "0", "--steps", "2"]) == 0
    metadata = load_rollout(out / "rollout_test_0.npz").metadata
    checkpoint = checkpoints.choose_checkpoint(run).resolve()
    assert metadata["dataset"] == str(data.resolve())
    assert metadata["checkpoint"] == str(checkpoint)

    monkeypatch.chdir(tmp_path)  # elsewhere: the recorded paths still work
    argv = ["eval", "--run", str(run), "--data", str(data), "--rollouts", str(out)]
    argv += ["--every", "2", "--one-step-windows", "4"]
    assert main(argv) == 0
    written = json.loads((run / "eval_test.json").read_text())
    assert written["one_step_checkpoint"] == str(checkpoint)
    assert written["rollouts"] == [str(out / "rollout_test_0.npz")]
    capsys.readouterr()


def test_precision_fixes_what_the_network_runs_in(trained, tmp_path, capsys, monkeypatch):
    """--precision overrides the model's "auto" (which picks bf16 where it is native and timed
    faster, so figures differ between machines): rollouts record it, eval's one-step errors
    run in it, and bf16 with --float64 is refused."""
    import gns.rollout

    run, data = trained
    # A machine where "auto" would keep bf16: native, and any speed-up enough.
    monkeypatch.setattr(gns.rollout, "native_bf16", lambda device: True)
    monkeypatch.setattr(gns.rollout, "BF16_SPEEDUP", 0.0)
    argv = ["rollout", "--run", str(run), "--data", str(data), "--trajectories", "0"]
    argv += ["--steps", "4"]
    ran = {}
    for precision in (None, "fp32", "bf16"):
        out = tmp_path / str(precision)
        flag = [] if precision is None else ["--precision", precision]
        assert main([*argv, "--out", str(out), *flag]) == 0
        ran[precision] = load_rollout(out / "rollout_test_0.npz")
    assert ran[None].metadata["precision"] == "bf16"
    assert ran["fp32"].metadata["precision"] == "fp32"
    assert ran["bf16"].metadata["precision"] == "bf16"
    fp32, bf16 = ran["fp32"].predicted_rollout, ran["bf16"].predicted_rollout
    assert torch.isfinite(torch.from_numpy(bf16)).all() and (fp32 != bf16).any()
    one_step = {}
    for precision in ("fp32", "bf16"):
        ev = ["eval", "--run", str(run), "--data", str(data), "--rollouts", str(tmp_path / "fp32")]
        assert main([*ev, "--one-step-windows", "8", "--precision", precision]) == 0
        written = json.loads((run / "eval_test.json").read_text())
        one_step[precision] = written["mean"]["model"]["one_step_mse"]
    assert one_step["fp32"] != one_step["bf16"]
    refused(capsys, [*argv, "--float64", "--precision", "bf16"], "--precision: expected auto or")


def test_eval_refuses_rollouts_of_another_model_than_run_names(trained, tmp_path, capsys):
    """--run names the model whose one-step errors and rest test eval gives: rollouts made
    by another one (here the run, while --run names a model exported from it) are refused."""
    run, data = trained
    made = tmp_path / "made"
    assert main(["rollout", "--run", str(run), "--data", str(data), "--out", str(made),
                 "--trajectories", "0", "--steps", "2"]) == 0  # fmt: skip
    assert main(["export", "--run", str(run), "--out", str(tmp_path / "other")]) == 0
    argv = ["eval", "--data", str(data), "--rollouts", str(made), "--one-step-windows", "4"]
    recorded = checkpoints.choose_checkpoint(run).resolve()
    capsys.readouterr()
    assert main([*argv, "--run", str(tmp_path / "other")]) == 2
    err = capsys.readouterr().err
    assert f"were made with {recorded}, which is not --run {tmp_path / 'other'}'s" in err
    assert not (tmp_path / "other" / "eval_test.json").exists()
    assert main([*argv, "--run", str(run)]) == 0  # the rollouts' own run


def recorded_as(source: Path, folder: Path, checkpoint: str) -> Path:
    """A copy of the rollout `source` in `folder` recording `checkpoint`, as older versions
    recorded it (relative to where they ran)."""
    rollout = load_rollout(source)
    rollout.metadata["checkpoint"] = checkpoint
    folder.mkdir()
    save_rollout(folder / source.name, rollout)
    return folder


def test_eval_finds_a_relative_recorded_checkpoint_from_here_or_the_run(
    trained, tmp_path, capsys, monkeypatch
):
    run, data = trained
    first = tmp_path / "first"
    assert main(["rollout", "--run", str(run), "--data", str(data), "--out", str(first),
                 "--trajectories", "0", "--steps", "2"]) == 0  # fmt: skip
    checkpoint = checkpoints.choose_checkpoint(run)
    inside = checkpoint.relative_to(run)  # e.g. made with `--run .` in the run folder
    from_parent = checkpoint.relative_to(run.parent)  # made with `--run run` beside it
    argv = ["eval", "--run", str(run), "--data", str(data), "--every", "2"]
    argv += ["--one-step-windows", "4"]
    monkeypatch.chdir(run.parent)
    for name, recorded in (("inside", inside), ("beside", from_parent)):
        folder = recorded_as(first / "rollout_test_0.npz", tmp_path / name, str(recorded))
        assert main([*argv, "--rollouts", str(folder)]) == 0
        written = json.loads((run / "eval_test.json").read_text())
        assert written["one_step_checkpoint"] == str(checkpoint.resolve())
    capsys.readouterr()
    (run / "eval_test.json").unlink()
    folder = recorded_as(first / "rollout_test_0.npz", tmp_path / "gone", "old/step_1.pt")
    refused(
        capsys,
        [*argv, "--rollouts", str(folder)],
        "gns eval: error: the rollouts were made with checkpoint old/step_1.pt, which is not at "
        f"{run.parent / 'old/step_1.pt'} nor at {run / 'old/step_1.pt'}; pass --checkpoint",
    )
    assert not (run / "eval_test.json").exists()


# ------------------------------------------------------------------- frame spacings


def with_dt(data: Path, folder: Path, dt: float) -> Path:
    """A copy of the dataset `data` whose metadata says its frames are `dt` seconds apart."""
    shutil.copytree(data, folder)
    raw = json.loads((folder / "metadata.json").read_text())
    raw["dt"] = dt
    (folder / "metadata.json").write_text(json.dumps(raw))
    return folder


@pytest.mark.parametrize(
    ("dt", "problem"),
    [
        (0.002, "the data's frames are 2 ms apart: 7.5 ms is not a whole multiple of 2 ms; "),
        (0.0225, "the data's frames are 22.5 ms apart: its frames are farther apart than the "),
    ],
)
def test_data_whose_spacing_does_not_divide_the_models_step_is_refused_before_any_folder(
    strided, tmp_path, capsys, dt, problem
):
    run, native, _ = strided
    data = with_dt(native, tmp_path / "data", dt)
    out = tmp_path / "out"
    expected = ["the model steps 7.5 ms at a time, ", problem, "rolls out on frames 7.5 ms apart"]
    common = ["--run", str(run), "--data", str(data), "--out", str(out)]
    for command in ("rollout", "report"):
        line = refused(capsys, [command, *common], *expected)
        assert line.startswith(f"gns {command}: error: ")
        assert not out.exists()
    # eval, on rollouts made on the native data: its one-step errors on this data are refused.
    rollouts = tmp_path / "rollouts"
    argv = ["rollout", "--run", str(run), "--data", str(native), "--out", str(rollouts)]
    assert main([*argv, "--trajectories", "0"]) == 0
    argv = ["eval", "--run", str(run), "--data", str(data), "--rollouts", str(rollouts)]
    assert refused(capsys, argv, *expected).startswith("gns eval: error: ")
    assert not (run / "eval_test.json").exists()
