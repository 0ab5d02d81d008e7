"""`gns demo` end to end at the tiny size (every output file exists and decodes, the tables
parse, every number is finite, a second run resumes), and training's wall-clock time limit
(stops with a checkpoint; resuming from it equals an uninterrupted run)."""

from __future__ import annotations

import csv
import json
import math
import re
import shutil
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import torch
from data_helpers import metadata_dict, random_walk, write_metadata
from gns.checkpoints import choose_checkpoint, latest_checkpoint, load_checkpoint, model_location
from gns.cli import main
from gns.config import Config, ModelConfig, TrainConfig, from_dict
from gns.data import at_frame_stride, open_dataset
from gns.data.h5 import write_h5
from gns.demo import SIZES, demo, demo_config, finetune_config, headline
from gns.train import train
from PIL import Image

pytestmark = pytest.mark.usefixtures("torch_one_thread")

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def read_vtp(path):
    """NumberOfPoints and the (N, 3) points of a VTK XML PolyData file, parsed here."""
    piece = ET.parse(path).getroot().find("./PolyData/Piece")
    count = int(piece.get("NumberOfPoints"))
    points = np.array(piece.find("./Points/DataArray").text.split(), dtype=float)
    return count, points.reshape(-1, 3)


def test_tiny_demo_writes_a_complete_report_and_resumes(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--size", "tiny", "--workers", "1"]) == 0
    err = capsys.readouterr().err
    for phase in ("[1/3] generating", "[2/3] training", "[3/3] rolling out"):
        assert phase in err
    report = out / "report"
    test = open_dataset(out / "data", "test")
    # The shipped sand2d-taichi model steps over 3 of the preset's 2.5 ms frames: every row
    # predicts every 3rd frame (gns.report).
    (trajectory,) = [at_frame_stride(t, 3) for t in test]
    n, frames = trajectory.n_particles, trajectory.num_frames
    assert test.metadata.dt == 0.0025 and frames == 10

    expected = [
        "report.md",
        "report.html",
        "table.md",
        "table.csv",
        "table.json",
        "error_vs_time.png",
        "error_over_time.png",
        "rollout_test_0.gif",
        "vtk/ground_truth.pvd",
        "vtk/prediction.pvd",
    ]
    for name in expected:
        assert (report / name).is_file() and (report / name).stat().st_size > 0, name

    for name in ("error_vs_time.png", "error_over_time.png"):
        assert (report / name).read_bytes()[:8] == PNG_SIGNATURE
        with Image.open(report / name) as image:
            assert image.format == "PNG" and min(image.size) > 100
            image.load()
    with Image.open(report / "rollout_test_0.gif") as gif:
        assert gif.format == "GIF" and gif.n_frames == frames  # fewer frames than the cap
        gif.seek(gif.n_frames - 1)
        gif.load()

    for series in ("ground_truth", "prediction"):
        entries = ET.parse(report / f"vtk/{series}.pvd").getroot().findall("./Collection/DataSet")
        assert len(entries) == frames
        for entry in entries:
            count, points = read_vtp(report / "vtk" / entry.get("file"))
            assert count == n and points.shape == (n, 3) and np.isfinite(points).all()
    _, first = read_vtp(report / "vtk/ground_truth_000000.vtp")
    np.testing.assert_allclose(first[:, :2], trajectory.positions[0], rtol=1e-6)

    payload = json.loads((report / "table.json").read_text())
    methods = [row["method"] for row in payload["rows"]]
    # Three GNS rows (the shipped model, its fine-tuning, the model from scratch), five MPM
    # settings (auto: native, 0.6 and 0.5 of the grid, twice the CFL number, both), the
    # baselines; each GNS row's rollouts saved.
    baselines = ["constant velocity", "static"]
    assert methods == ["GNS"] * 3 + ["MPM"] * 5 + baselines
    settings = sorted(row["setting"].split(":")[0] for row in payload["rows"][:3])
    assert settings[0].startswith("fine-tuned") and settings[1:] == [
        "from scratch",
        "shipped sand2d-taichi",
    ]
    assert len(list(report.glob("rollouts/*/rollout_test_0.npz"))) == 3
    with open(report / "table.csv", newline="") as f:
        records = list(csv.DictReader(f))
    assert len(records) == len(payload["rows"])
    text = ("method", "setting", "device", "status", "diverged_at_step")
    numbers = [c for c in payload["columns"] if c not in text]
    for record, row in zip(records, payload["rows"], strict=True):
        if row["status"].startswith("failed: "):
            # A cheaper simulator setting that did not hold: said so, and no numbers.
            assert row["method"] == "MPM" and row["ms_per_frame"] is None
            continue
        assert row["status"] == "ok" and row["diverged_at_step"] is None
        for column in numbers:
            if column.endswith("_ms") and row["method"] != "GNS":
                assert record[column] == "" and row[column] is None  # no time split
                continue
            value = float(record[column])
            assert math.isfinite(value) and value >= 0 and value == row[column], column
        if row["method"] == "GNS":
            parts = sum(row[f"{p}_ms"] for p in ("graph", "features", "model", "integration"))
            assert parts == pytest.approx(row["ms_per_frame"], rel=1e-9)
    native = payload["rows"][-7]
    assert "native" in native["setting"] and native["status"] == "ok"
    assert all(native[c] == 0.0 for c in numbers if "@" in c)
    assert [row["status"] for row in payload["rows"] if row["method"] != "MPM"] == ["ok"] * (
        len(methods) - 5
    )

    markdown = (report / "report.md").read_text()
    for link in re.findall(r"\]\(([^)]+)\)", markdown):
        assert (report / link).is_file(), link
    assert "gns demo --out" in markdown and "logical CPUs" in markdown
    # The conclusion speaks of the headline, the first row, chosen on validation.
    headline = payload["rows"][0]["setting"].split(":")[0]
    assert markdown.splitlines()[2].startswith(
        "**In short.** Where it stands against the reference simulator (5 settings, "
    )
    assert f"Headline (the row the conclusion speaks of): {headline}, the best on the valid " in (
        markdown
    )
    # Both trainings validated on every valid trajectory over rollouts as long as the test
    # rollouts (issues 22 and 41); the fine-tuning validated the shipped model as its step 0.
    for run in ("finetune", "scratch"):
        train_config = load_checkpoint(latest_checkpoint(out / run))["config"]["train"]
        assert train_config["validation_rollout_steps"] == frames - 6 == 4
        assert train_config["validation_rollouts"] == 1
    assert (out / "finetune/valid.csv").read_text().splitlines()[1].startswith("0,")
    if shutil.which("ffmpeg") is None:
        assert "MP4 animation: no ffmpeg executable on PATH" in markdown
    else:
        assert (report / "rollout_test_0.mp4").stat().st_size > 0
    html = (report / "report.html").read_text()
    assert html.count("<tr>") == 1 + len(payload["rows"])

    # A second run reuses the dataset and the finished training and rewrites the report.
    trained = [(out / f"{run}.json").read_text() for run in ("finetune", "scratch")]
    assert main(["demo", "--out", str(out), "--size", "tiny", "--workers", "1"]) == 0
    err = capsys.readouterr().err
    assert "reusing the dataset" in err
    assert "finetune finished earlier (step 4)" in err and "scratch finished earlier" in err
    assert [(out / f"{run}.json").read_text() for run in ("finetune", "scratch")] == trained
    # Other arguments in the same folder are refused, not mixed in.
    with pytest.raises(ValueError, match="other arguments"):
        demo(out, size="tiny", seed=1)


def test_demo_rejects_unknown_sizes_and_bad_overrides(tmp_path):
    with pytest.raises(ValueError, match="unknown preset 'lava'"):
        demo(tmp_path / "p", preset="lava")
    with pytest.raises(ValueError, match="unknown demo size 'huge'"):
        demo(tmp_path / "a", size="huge")
    with pytest.raises(ValueError, match="three counts >= 1"):
        demo(tmp_path / "b", size="tiny", trajectories=(2, 0, 1))
    with pytest.raises(ValueError, match="train_minutes must be a positive number, got 0"):
        demo(tmp_path / "c", size="tiny", train_minutes=0)
    with pytest.raises(ValueError, match="frames must be a whole number >= 8, got 7"):
        demo(tmp_path / "d", size="tiny", frames=7)
    with pytest.raises(ValueError, match="train_minutes must be a positive number, got inf"):
        demo(tmp_path / "e", size="tiny", train_minutes=math.inf)
    with pytest.raises(ValueError, match="seed must be a whole number >= 0, got -1"):
        demo(tmp_path / "f", size="tiny", seed=-1)
    with pytest.raises(ValueError, match="workers must be a whole number >= 1, got 0"):
        demo(tmp_path / "g", size="tiny", workers=0)
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="no CUDA device"):
            demo(tmp_path / "h", size="tiny", device="cuda")
    # Nothing written before the arguments are checked: no OUT, so no demo.json that a
    # corrected command would refuse as "other arguments".
    assert not any(tmp_path.iterdir())


def test_demo_validates_on_every_valid_trajectory_over_the_test_rollouts_length():
    # The report rolls out every frame after the first C + 1 of each test trajectory; best.pt
    # must be chosen on rollouts as long (issue 22: chosen on 50 frames, it diverged by 155)
    # and on every valid trajectory (issue 41: chosen on 2, it merely stayed in the box).
    shipped = load_checkpoint(choose_checkpoint(model_location("sand2d-taichi")))
    shipped_config = from_dict(Config, shipped["config"])
    for size in SIZES.values():
        scratch = demo_config(size, 10, 110, 4)
        tuned = finetune_config(shipped_config, size, 10, 110, 4)
        for config in (scratch, tuned):
            assert config.train.validation_rollout_steps == 110
            assert config.train.validation_rollouts == 4
            assert config.train.validate_every == size.validate_every
        # Fine-tuning may change only [noise] and [train] (gns.train refuses the rest).
        assert (tuned.model, tuned.scene, tuned.noise) == (
            shipped_config.model,
            shipped_config.scene,
            shipped_config.noise,
        )
        assert tuned.train.learning_rate < shipped_config.train.learning_rate * 1.01


def test_the_headline_is_in_the_box_first_then_the_lowest_validation_mse():
    def candidate(value, in_box):
        return {"record": {"step": 1, "value": value, "in_box": in_box}}

    # An early checkpoint with a low MSE that let a particle out loses to one in the box.
    assert headline([candidate(1e-4, False), candidate(5e-3, True), candidate(6e-3, True)]) == 1
    assert headline([candidate(2e-3, True), candidate(1e-3, True)]) == 1
    assert headline([candidate(1e-3, True), candidate(1e-3, True)]) == 0  # the first of equals
    assert headline([candidate(2e-3, False), candidate(1e-3, False)]) == 1


# ---------------------------------------------------------------------------- time limit

SETTINGS = Config(
    model=ModelConfig(latent_size=8, mlp_hidden_size=8, message_passing_steps=2, precision="fp32"),
    train=TrainConfig(
        steps=5, log_every=2, validate_every=0, checkpoint_every=100, learning_rate=1e-3
    ),
)


@pytest.fixture
def dataset(tmp_path):
    rng = np.random.default_rng(0)
    items = [random_walk(rng, 12, 16, key=k) for k in range(3)]
    write_metadata(tmp_path / "data", metadata_dict(sequence_length=11))
    write_h5(tmp_path / "data/train.h5", items)
    return tmp_path / "data"


def weights(simulator):
    return {k: v.detach().clone() for k, v in simulator.state_dict().items()}


def test_time_limit_stops_with_a_checkpoint_and_resuming_equals_an_uninterrupted_run(
    dataset, tmp_path, capsys
):
    # A limit that has passed after the first step: training stops there.
    train(dataset, tmp_path / "limited", SETTINGS, device="cpu", progress=False, time_limit=1e-9)
    assert "time limit" in capsys.readouterr().err
    checkpoint = latest_checkpoint(tmp_path / "limited")
    assert checkpoint.name == "step_000000001.pt"
    assert len(list((tmp_path / "limited/checkpoints").glob("step_*.pt"))) == 1
    resumed = train(dataset, tmp_path / "limited", None, resume=True, device="cpu", progress=False)
    whole = train(dataset, tmp_path / "whole", SETTINGS, device="cpu", progress=False)
    for key, value in weights(whole).items():
        assert torch.equal(weights(resumed)[key], value), key
    assert latest_checkpoint(tmp_path / "limited").name == "step_000000005.pt"


def test_a_generous_time_limit_changes_nothing(dataset, tmp_path):
    limited = train(
        dataset, tmp_path / "a", SETTINGS, device="cpu", progress=False, time_limit=3600
    )
    plain = train(dataset, tmp_path / "b", SETTINGS, device="cpu", progress=False)
    for key, value in weights(plain).items():
        assert torch.equal(weights(limited)[key], value), key


@pytest.mark.parametrize("limit", [0, -1.0, math.inf, math.nan])
def test_bad_time_limits_raise_value_error(dataset, tmp_path, limit):
    with pytest.raises(ValueError, match=f"time_limit must be a positive number.*{limit}"):
        train(dataset, tmp_path / "run", SETTINGS, device="cpu", progress=False, time_limit=limit)


def test_cli_time_limit_is_in_minutes(dataset, tmp_path, monkeypatch):
    import gns.train

    seen = {}
    monkeypatch.setattr(gns.train, "train", lambda *a, **kw: seen.update(kw))
    assert (
        main(["train", "--data", str(dataset), "--out", str(tmp_path), "--time-limit", "1.5"]) == 0
    )
    assert seen["time_limit"] == 90.0


def test_tiny_3d_demo_reruns_its_scenes_and_draws_two_views(tmp_path):
    """`gns demo --preset boxbath` (the cheapest 3D preset): the report's native MPM row
    re-runs each test scene from the preset (3D, a rigid cube) to the data's own frames, and
    the animation shows the 3D positions from two sides."""
    out = tmp_path / "demo3d"
    argv = ["demo", "--out", str(out), "--size", "tiny", "--preset", "boxbath", "--workers", "1"]
    assert main(argv) == 0
    report = out / "report"
    (trajectory,) = list(open_dataset(out / "data", "test"))
    assert trajectory.dim == 3 and set(np.unique(trajectory.particle_type)) == {0, 5}
    (saved,) = report.glob("rollouts/*/rollout_test_0.npz")  # one row: no shipped 3D model
    rollout = np.load(saved)
    assert rollout["predicted_rollout"].shape[1:] == (trajectory.n_particles, 3)
    rows = json.loads((report / "table.json").read_text())["rows"]
    native = next(row for row in rows if row["method"] == "MPM" and "native" in row["setting"])
    assert native["status"] == "ok" and native["mse@full"] == 0.0
    with Image.open(report / "rollout_test_0.gif") as gif:
        assert gif.n_frames == trajectory.num_frames and gif.size[0] > 2 * gif.size[1]
    assert "from two sides" in (report / "report.md").read_text()
