"""`gns report`: each row against an independent computation from the dataset and the saved
rollouts (numpy, brute-force optimal transport), the MPM rows (native reproduces the data
exactly, its deposit included; a failing cheaper setting is a row, not a crash), the static
baseline and the deposit figures against the ground truth's, the rest test, datasets not made
by `gns generate`, data whose frames are finer than the model's step (every row against the
report on `gns convert --frame-stride`'s frames), the tables parsing back, the VTK writer against
a small XML reader, and bad arguments."""

from __future__ import annotations

import csv
import itertools
import json
import math
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import torch
from data_helpers import metadata_dict, random_walk, write_metadata
from gns import mpm
from gns.config import Config, ModelConfig, TrainConfig
from gns.data import convert, open_dataset
from gns.data.h5 import write_h5
from gns.deposit import front_positions, pile_height, runout_extent
from gns.evaluate import rest_summary, rest_test
from gns.mpm.generate import generate, preset_scene
from gns.plots import (
    RolloutFigure,
    Series,
    animation_frames,
    error_over_time,
    error_vs_time,
    front_over_time,
)
from gns.report import (
    MpmVariant,
    Row,
    conclusion,
    parse_horizons,
    parse_mpm_variants,
    report,
    score,
    table_columns,
)
from gns.rollout import load_rollout
from gns.train import train
from gns.vtk import write_series

HISTORY = 6  # velocity_history 5 + 1: the frames every rollout starts from
TINY = Config(
    model=ModelConfig(latent_size=8, mlp_hidden_size=8, message_passing_steps=1, precision="fp32"),
    train=TrainConfig(steps=2, log_every=1, validate_every=0, checkpoint_every=1),
)


@pytest.fixture(scope="module")
def one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def generated(tmp_path_factory, one_thread):
    """A `gns generate` sand dataset (2 test trajectories of 14 frames) and a 2-step run."""
    root = tmp_path_factory.mktemp("generated")
    generate("sand", root / "data", 1, 0, 2, seed=0, frames=14, progress=False)
    train(root / "data", root / "run", TINY, device="cpu", progress=False)
    return root


@pytest.fixture(scope="module")
def generated_report(generated):
    return report(
        generated / "run",
        generated / "data",
        checkpoints=["latest"],
        out=generated / "report",
        horizons=(1, 5, None),
        every=3,
        mpm=["native", "grid=20"],
        animation_frames=0,
        vtk_every=0,
        rest_steps=2,
        progress=False,
    )


def rows_by_method(result):
    return {(row.method, row.setting.split(",")[0]): row for row in result.rows}


def test_constant_velocity_row_is_the_hand_computed_baseline(generated, generated_report):
    (row,) = [r for r in generated_report.rows if r.method == "constant velocity"]
    test = open_dataset(generated / "data", "test")
    full, first5 = [], []
    for trajectory in test:
        x = trajectory.positions.astype(np.float64)
        free = trajectory.particle_type != 3
        # x(t + 1) = x(t) + (x(t) - x(t - 1)) from the last two history frames.
        steps = np.arange(1, len(x) - HISTORY + 1)[:, None, None]
        guess = x[HISTORY - 1] + steps * (x[HISTORY - 1] - x[HISTORY - 2])
        squared = ((guess - x[HISTORY:])[:, free] ** 2).mean(axis=(1, 2))
        full.append(squared.mean())
        first5.append(squared[:5].mean())
    assert row.trajectories == 2
    assert row.values["mse@full"] == pytest.approx(np.mean(full), rel=1e-9)
    assert row.values["mse@5"] == pytest.approx(np.mean(first5), rel=1e-9)


def test_native_mpm_reproduces_the_ground_truth_exactly(generated_report):
    rows = rows_by_method(generated_report)
    native = rows[("MPM", "grid 40 (dx 0.025)")]
    assert "native" in native.setting and native.status == "ok"
    errors = {key: value for key, value in native.values.items() if "@" in key}
    assert errors and all(value == 0.0 for value in errors.values())
    # The same frames: the same deposit as the truth's, exactly.
    assert [native.values[k] for k in DEPOSIT_COLUMNS] == [1.0, 1.0, 1.0]
    truth = json.loads((generated_report.out / "table.json").read_text())["deposits"]
    for ours, theirs in zip(native.deposits, truth["ground_truth"]["trajectories"], strict=True):
        assert ours["runout"] == theirs["runout"] and ours["pile_height"] == theirs["pile_height"]
        assert ours["front_x_p99"].tolist() == theirs["front_x_p99"]
    assert native.seconds_per_frame > 0
    coarse = rows[("MPM", "grid 20 (dx 0.05)")]
    # A coarser grid is a different simulation of the same particles: nonzero, finite error.
    assert coarse.status == "ok" and coarse.seconds_per_frame > 0
    assert all(0 < value < math.inf for value in coarse.values.values())


DEPOSIT_COLUMNS = ("runout_ratio", "height_ratio", "density_ratio")


def test_static_row_holds_the_last_input_frame(generated, generated_report):
    (row,) = [r for r in generated_report.rows if r.method == "static"]
    assert row.role == "baseline" and row.seconds_per_frame > 0
    test = open_dataset(generated / "data", "test")
    full, runout_ratios = [], []
    for trajectory, deposit in zip(test, row.deposits, strict=True):
        x = trajectory.positions.astype(np.float64)
        free = trajectory.particle_type != 3
        squared = ((x[HISTORY - 1] - x[HISTORY:])[:, free] ** 2).mean(axis=(1, 2))
        full.append(squared.mean())
        # Its deposit is the last input frame's, in every frame; the floor is the box's.
        held, last = x[HISTORY - 1], x[-1]
        assert deposit["runout"] == pytest.approx(runout_extent(held, free), rel=1e-12)
        floor = test.metadata.bounds[1][0]
        assert deposit["pile_height"] == pytest.approx(pile_height(held, free, floor), rel=1e-12)
        fronts = front_positions(held[None], free)[0]
        assert np.all(deposit["front_x_p1"] == fronts[0])
        assert np.all(deposit["front_x_p99"] == fronts[1])
        runout_ratios.append(runout_extent(held, free) / runout_extent(last, free))
    assert row.values["mse@full"] == pytest.approx(np.mean(full), rel=1e-9)
    assert row.values["runout_ratio"] == pytest.approx(np.mean(runout_ratios), rel=1e-9)


def test_deposit_columns_and_the_truths_own_deposit_in_table_json(generated, generated_report):
    out = generated_report.out
    payload = json.loads((out / "table.json").read_text())
    assert set(DEPOSIT_COLUMNS) <= set(payload["columns"])
    header = (out / "table.md").read_text().splitlines()[0]
    assert "| runout ratio | height ratio | density ratio |" in header
    test = open_dataset(generated / "data", "test")
    truth = payload["deposits"]["ground_truth"]
    for trajectory, deposit in zip(test, truth["trajectories"], strict=True):
        x, free = trajectory.positions, trajectory.particle_type != 3
        assert deposit["runout"] == pytest.approx(runout_extent(x[-1], free), rel=1e-12)
        predicted = front_positions(x[HISTORY:], free)
        np.testing.assert_array_equal(deposit["front_x_p1"], predicted[:, 0])
    assert truth["mean"]["runout"] == pytest.approx(
        np.mean([d["runout"] for d in truth["trajectories"]]), rel=1e-12
    )
    # Every row's per-trajectory figures, whose means are the table's.
    assert [r["method"] for r in payload["deposits"]["rows"]] == [
        r["method"] for r in payload["rows"]
    ]
    for record, deposits in zip(payload["rows"], payload["deposits"]["rows"], strict=True):
        for column in DEPOSIT_COLUMNS:
            per_trajectory = [d[column] for d in deposits["trajectories"]]
            assert record[column] == pytest.approx(np.mean(per_trajectory), rel=1e-12)
            assert deposits["mean"][column] == record[column]
    # The learned rollouts carry their deposit.
    (saved,) = (out / "rollouts").glob("*/rollout_test_1.npz")
    metrics = load_rollout(saved).metrics
    (learned,) = [r for r in payload["deposits"]["rows"] if r["method"] == "GNS"]
    assert metrics["runout"] == learned["trajectories"][1]["runout"]
    assert metrics["front_x_p99"].tolist() == learned["trajectories"][1]["front_x_p99"]
    assert (out / "fronts.png").is_file() and "fronts.png" in (out / "report.md").read_text()


def test_the_rest_test_runs_for_every_learned_row_and_shows(generated, generated_report):
    from gns.checkpoints import load_simulator

    out = generated_report.out
    payload = json.loads((out / "table.json").read_text())
    (rest,) = payload["rest"]
    assert rest["method"] == "GNS" and rest["steps"] == 2
    # The same figures as the rest test of the checkpoint on its own.
    simulator = load_simulator(generated / "run/checkpoints/step_000000002.pt", "cpu")
    test = open_dataset(generated / "data", "test")
    alone = rest_summary([rest_test(simulator, t, 2) for t in test], 2)
    for key, value in alone["mean"].items():
        assert rest["mean"][key] == pytest.approx(value, rel=1e-5, abs=1e-9), key
    markdown = (out / "report.md").read_text()
    assert "## Rest test" in markdown and "rolled out 2 steps by each learned model" in markdown
    assert "| density ratio (mean) | largest displacement (worst) |" in markdown
    (row,) = [r for r in generated_report.rows if r.method == "GNS"]
    assert f"Held still for 2 steps, the last frames under {row.short} move" in markdown
    assert "<h2>Rest test</h2>" in (out / "report.html").read_text()


def test_learned_row_is_scored_from_its_saved_rollouts_and_its_time_split_adds_up(
    generated, generated_report
):
    (row,) = [r for r in generated_report.rows if r.method == "GNS"]
    assert "step 2" in row.setting and row.device.startswith("cpu")
    assert sum(row.split.values()) == pytest.approx(row.seconds_per_frame, rel=1e-12)
    assert set(row.split) == {"graph", "features", "model", "integration"}
    assert all(seconds > 0 for seconds in row.split.values())
    per_trajectory = []
    for i in range(2):
        with np.load(generated / f"report/rollouts/step_000000002/rollout_test_{i}.npz") as f:
            predicted, truth = f["predicted_rollout"], f["ground_truth_rollout"]
            free = f["particle_types"] != 3
            # The same per-step timings as the row's.
            assert f["timing_model"].shape == (len(truth),)
        per_trajectory.append(((predicted - truth)[:, free].astype(np.float64) ** 2).mean())
    assert row.values["mse@full"] == pytest.approx(np.mean(per_trajectory), rel=1e-6)


def test_tables_parse_back_to_the_same_rows(generated_report):
    out = generated_report.out
    payload = json.loads((out / "table.json").read_text())
    with open(out / "table.csv", newline="") as f:
        records = list(csv.DictReader(f))
    assert [r["method"] for r in records] == [r["method"] for r in payload["rows"]]
    assert list(records[0]) == payload["columns"]
    for from_csv, from_json in zip(records, payload["rows"], strict=True):
        for column, value in from_json.items():
            if isinstance(value, float):
                assert float(from_csv[column]) == value
            elif value is None:
                assert from_csv[column] == ""
            else:
                assert from_csv[column] == str(value)
    # Horizon 10 is longer than the 8 predicted frames: no column rather than a shorter mean.
    assert "mse@5" in payload["columns"] and "mse@10" not in payload["columns"]
    markdown = (out / "table.md").read_text().splitlines()
    assert len(markdown) == 2 + len(payload["rows"])
    report_md = (out / "report.md").read_text()
    assert "one predicted frame in k = 3 only (frames 1, 4, 7, ..." in report_md
    assert "logical CPUs" in report_md and "torch" in report_md


def brute_force_w2(a, b):
    """W2^2 between equal-size uniform point sets by trying every matching."""
    return min(
        np.mean(np.sum((a - b[list(p)]) ** 2, axis=1))
        for p in itertools.permutations(range(len(b)))
    )


def test_score_matches_numpy_and_brute_force_transport():
    rng = np.random.default_rng(3)
    truth = rng.uniform(size=(7, 5, 2))
    predicted = truth + rng.normal(0, 0.05, size=truth.shape)
    mask = np.array([True, True, True, True, False])
    scores = score(predicted, truth, mask, (1, 4, None), every=3)
    squared = ((predicted - truth)[:, mask] ** 2).mean(axis=(1, 2))
    assert scores["mse@1"] == pytest.approx(squared[0])
    assert scores["mse@4"] == pytest.approx(squared[:4].mean())
    assert scores["mse@full"] == pytest.approx(squared.mean())
    w2 = [brute_force_w2(predicted[t, mask], truth[t, mask]) for t in (0, 3, 6)]
    assert scores["ot@1"] == pytest.approx(w2[0])
    assert scores["ot@4"] == pytest.approx(np.mean(w2[:2]))  # frames 0 and 3
    assert scores["ot@full"] == pytest.approx(np.mean(w2))
    # A diverged (NaN-padded) rollout scores inf from the first bad frame on, never a number.
    predicted[2:] = np.nan
    diverged = score(predicted, truth, mask, (1, None), every=3)
    assert diverged["mse@1"] == pytest.approx(squared[0])
    assert diverged["mse@full"] == math.inf and diverged["ot@full"] == math.inf


def test_a_failing_cheaper_setting_is_a_row_that_says_so(generated, monkeypatch):
    real = mpm.simulate

    def unstable_above_cfl_1(scene, frames, **kw):
        if scene.cfl > 1:
            raise ValueError("frame 3: NaN in the particle velocities")
        return real(scene, frames, **kw)

    monkeypatch.setattr(mpm, "simulate", unstable_above_cfl_1)
    result = report(
        generated / "run",
        generated / "data",
        out=generated / "failing",
        trajectories=1,
        mpm=["cfl=2"],
        every=4,
        animation_frames=0,
        vtk_every=0,
        progress=False,
    )
    (failed,) = [r for r in result.rows if r.method == "MPM"]
    assert failed.status.startswith("failed") and "NaN" in failed.status
    assert failed.seconds_per_frame is None and failed.values == {}
    payload = json.loads((result.out / "table.json").read_text())
    (record,) = [r for r in payload["rows"] if r["method"] == "MPM"]
    assert record["ms_per_frame"] is None and record["mse@full"] is None
    assert "| n/a |" in (result.out / "table.md").read_text()


def test_a_diverged_learned_rollout_is_reported_as_diverged(generated, monkeypatch):
    import gns.plots
    import gns.rollout as rollout_module

    real = rollout_module.rollout

    def diverge_after_three_steps(simulator, trajectory, **kw):
        if kw.get("num_steps") is not None:  # the warm-up
            return real(simulator, trajectory, **kw)
        partial = real(simulator, trajectory, num_steps=3)
        raise rollout_module.RolloutDiverged("diverged at step 3", partial, 3, 1)

    # What the GIF's prediction panel shows at each frame it draws.
    panels = {}
    draw = RolloutFigure.draw

    def recorded(figure, t):
        image = draw(figure, t)
        panels[t] = (figure.notice.get_text(), figure.scatters[1].get_offsets().copy())
        return image

    monkeypatch.setattr(rollout_module, "rollout", diverge_after_three_steps)
    monkeypatch.setattr(gns.plots.RolloutFigure, "draw", recorded)
    result = report(
        generated / "run",
        generated / "data",
        out=generated / "diverged",
        trajectories=1,
        mpm=["none"],
        every=4,
        animation_frames=5,
        vtk_every=2,
        progress=False,
    )
    (row,) = [r for r in result.rows if r.method == "GNS"]
    assert row.status.startswith("diverged") and "trajectory 0 at step 3" in row.status
    assert row.diverged == [(0, 3)] and row.diverged_at == 3
    assert row.values["mse@1"] < math.inf and row.values["mse@full"] == math.inf
    # It never reached the last frame: no deposit there.
    assert all(row.values[k] == math.inf for k in DEPOSIT_COLUMNS)
    assert "inf" in (result.out / "table.md").read_text()
    payload = json.loads((result.out / "table.json").read_text())
    record, baseline, static = payload["rows"]
    assert record["mse@full"] is None and record["mse@1"] == row.values["mse@1"]
    assert record["runout_ratio"] is None and static["runout_ratio"] > 0
    assert record["diverged_at_step"] == 3 and baseline["diverged_at_step"] is None
    # Its fronts while it lasted, none after (strict JSON: null).
    fronts = payload["deposits"]["rows"][0]["trajectories"][0]["front_x_p99"]
    assert all(f is not None for f in fronts[:3]) and set(fronts[3:]) == {None}
    # VTK has only the finite frames of the prediction: 6 history + 3 predicted, every 2nd.
    pvd = ET.parse(result.out / "vtk/prediction.pvd").getroot()
    assert len(pvd.findall("./Collection/DataSet")) == len(range(0, 9, 2))
    markdown = (result.out / "report.md").read_text()
    assert "MPM rows: none asked for" in markdown
    assert "VTK prediction after frame 8: the prediction diverged at frame 9" in markdown
    assert f"{row.short} diverged: trajectory 0 at step 3 (1 of 1 trajectory)" in markdown
    # The GIF animates the prediction up to its last finite frame (8 = 6 + 3 - 1), then says
    # where it diverged, over that last state, instead of an empty panel.
    (saved,) = (result.out / "rollouts").glob("*/rollout_test_0.npz")
    last = np.load(saved)["predicted_rollout"][-1]
    assert {8, 9, 13} <= set(panels) and len(panels) <= 5
    assert panels[8][0] == "" and np.allclose(panels[8][1], last)
    for t in (9, 13):
        assert panels[t][0] == "diverged at frame 9" and np.allclose(panels[t][1], last)


def test_datasets_not_made_by_generate_get_no_mpm_rows_and_say_why(tmp_path, one_thread):
    rng = np.random.default_rng(0)
    items = [random_walk(rng, 12, 20, key=k) for k in range(2)]
    write_metadata(tmp_path / "data", metadata_dict(sequence_length=11))
    write_h5(tmp_path / "data/train.h5", items)
    write_h5(tmp_path / "data/test.h5", items[:1])
    train(tmp_path / "data", tmp_path / "run", TINY, device="cpu", progress=False)
    result = report(
        tmp_path / "run",
        tmp_path / "data",
        out=tmp_path / "report",
        animation_frames=0,
        vtk_every=0,
        progress=False,
    )
    assert [r.method for r in result.rows] == ["GNS", "constant velocity", "static"]
    (reason,) = [item for item in result.left_out if item.startswith("MPM rows")]
    assert "not written by `gns generate`" in reason
    assert reason in (result.out / "report.md").read_text()


@pytest.fixture(scope="module")
def strided_generated(tmp_path_factory, one_thread):
    """A `gns generate` sand dataset at its 2.5 ms frames (1 test trajectory of 27 frames),
    the same converted to every 3rd frame (9 frames, 7.5 ms apart), and a run trained 2 steps
    on the converted one: a model that steps 7.5 ms."""
    root = tmp_path_factory.mktemp("strided_generated")
    generate("sand", root / "native", 1, 0, 1, seed=0, frames=27, progress=False)
    convert(root / "native", root / "converted", "deepmind", frame_stride=3)
    train(root / "converted", root / "run", TINY, device="cpu", progress=False)
    return root


def test_on_finer_data_every_row_is_scored_and_timed_at_the_models_frames(strided_generated):
    root = strided_generated
    assert open_dataset(root / "native", "test").metadata.dt == 0.0025
    results = {
        name: report(
            root / "run",
            root / name,
            out=root / f"report_{name}",
            horizons=(1, None),
            every=2,
            mpm=["native"],
            animation_frames=0,
            vtk_every=1 if name == "native" else 0,
            progress=False,
        )
        for name in ("native", "converted")
    }
    ours, theirs = results["native"], results["converted"]
    # The oracle: the same report on the frames gns convert wrote. The same rows (the GNS,
    # the MPM re-run at its own 2.5 ms frames and taken at every 3rd, both baselines), scored
    # the same, exactly.
    assert [r.method for r in ours.rows] == ["GNS", "MPM", "constant velocity", "static"]
    for a, b in zip(ours.rows, theirs.rows, strict=True):
        assert (a.method, a.setting, a.values) == (b.method, b.setting, b.values)
        np.testing.assert_array_equal(a.curve, b.curve)
    native_mpm = ours.rows[1]
    assert all(v == 0.0 for k, v in native_mpm.values.items() if "@" in k)
    assert native_mpm.seconds_per_frame > 0
    (saved,) = (ours.out / "rollouts").glob("*/rollout_test_0.npz")
    rollout = load_rollout(saved)
    assert rollout.num_steps == 9 - HISTORY and rollout.metadata["frame_stride"] == 3
    # What the report says: the stride, and times per step of the model.
    context = json.loads((ours.out / "table.json").read_text())["context"]
    assert (context["frame_stride"], context["dataset_dt"], context["frames"]) == (3, 0.0025, 9)
    assert context["dt"] == pytest.approx(0.0075, rel=1e-12) and context["mpm_frame_stride"] == 3
    assert json.loads((theirs.out / "table.json").read_text())["context"]["frame_stride"] == 1
    markdown = (ours.out / "report.md").read_text()
    assert (
        "- Frame stride 3: the data's frames are 2.5 ms apart, the model's steps 7.5 ms: every "
        "3rd frame, from frame 0" in markdown
    )
    assert "| ms per 7.5 ms step |" in markdown and "per 7.5 ms step" in context["conclusion"][0]
    assert "the 3 frames of its own it simulates per frame here, 2.5 ms apart" in markdown
    assert "| ms per 7.5 ms step |" in (ours.out / "table.md").read_text()
    # The ParaView files are 7.5 ms apart too.
    pvd = ET.parse(ours.out / "vtk/ground_truth.pvd").getroot()
    times = [float(e.get("timestep")) for e in pvd.findall("./Collection/DataSet")]
    assert times == pytest.approx(0.0075 * np.arange(9))


def test_checkpoints_at_different_frame_spacings_are_refused_before_any_work(
    strided_generated, generated
):
    out = strided_generated / "mixed"
    with pytest.raises(
        ValueError, match="step over different frames of the data .*every 3.*every 1"
    ):
        report(
            strided_generated / "run",
            strided_generated / "native",
            checkpoints=["latest", str(next((generated / "run/checkpoints").glob("step_*.pt")))],
            out=out,
            progress=False,
        )
    assert not out.exists()


def test_a_coarser_grid_keeps_every_particle_where_it_was(generated):
    scene, _, seed = preset_scene("sand", 0, "test", 0)
    for grid in (20, 13, 7):
        coarse = MpmVariant(grid=grid).apply(scene)
        assert coarse.grid == grid and coarse.spacing == pytest.approx(scene.spacing)
        np.testing.assert_allclose(
            mpm.particles(coarse, seed)["positions"],
            mpm.particles(scene, seed)["positions"],
            rtol=0,
            atol=1e-12,
        )


def test_vtk_series_reads_back_with_an_independent_xml_reader(tmp_path):
    rng = np.random.default_rng(1)
    positions = rng.uniform(size=(5, 7, 2)).astype(np.float32)
    types = np.array([5, 5, 6, 6, 6, 3, 3])
    error = rng.uniform(size=(5, 7)).astype(np.float32)
    pvd = write_series(
        tmp_path,
        "pred",
        positions,
        dt=0.01,
        first_frame=6,
        every=2,
        point_data={"particle_type": types},
        frame_data={"error": error},
    )
    entries = ET.parse(pvd).getroot().findall("./Collection/DataSet")
    assert [float(e.get("timestep")) for e in entries] == pytest.approx([0.06, 0.08, 0.10])
    for k, entry in zip((0, 2, 4), entries, strict=True):
        piece = ET.parse(tmp_path / entry.get("file")).getroot().find("./PolyData/Piece")
        assert piece.get("NumberOfPoints") == "7" and piece.get("NumberOfVerts") == "7"
        points = np.array(piece.find("./Points/DataArray").text.split(), float).reshape(7, 3)
        np.testing.assert_allclose(points[:, :2], positions[k], rtol=1e-6)
        assert np.all(points[:, 2] == 0)
        arrays = {a.get("Name"): a for a in piece.findall("./PointData/DataArray")}
        assert [int(v) for v in arrays["particle_type"].text.split()] == types.tolist()
        np.testing.assert_allclose(
            np.array(arrays["error"].text.split(), float), error[k], rtol=1e-6
        )
        offsets = piece.find("./Verts/DataArray[@Name='offsets']").text.split()
        assert [int(v) for v in offsets] == list(range(1, 8))
    with pytest.raises(ValueError, match="NaN or Inf"):
        write_series(tmp_path, "bad", np.full((1, 2, 2), np.nan))


@pytest.mark.parametrize(
    ("values", "message"),
    [(["0"], "'0'"), (["ten"], "'ten'"), (["1.5"], "'1.5'"), ([], "at least one")],
)
def test_bad_horizons_raise_value_error(values, message):
    with pytest.raises(ValueError, match=message):
        parse_horizons(values)


def test_horizons_and_mpm_settings_parse():
    assert parse_horizons(["1", "10", "full", "10"]) == (1, 10, None)
    assert parse_mpm_variants(["auto"], 40, 0.4) == [
        MpmVariant(),
        MpmVariant(grid=24),
        MpmVariant(grid=20),
        MpmVariant(cfl=0.8),
        MpmVariant(grid=24, cfl=0.8),
    ]
    assert parse_mpm_variants(["native", "grid=30,cfl=0.5"], 40, 0.4) == [
        MpmVariant(),
        MpmVariant(grid=30, cfl=0.5),
    ]
    assert parse_mpm_variants(["none"], 40, 0.4) == []
    for bad in (["grid=1"], ["cfl=-1"], ["grid=2.5"], ["speed=2"], ["none", "native"]):
        with pytest.raises(ValueError, match="MPM setting"):
            parse_mpm_variants(bad, 40, 0.4)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"trajectories": 3}, "between 1 and 2.*got 3"),
        ({"trajectories": 0}, "between 1 and 2.*got 0"),
        ({"every": 0}, "every must be a whole number >= 1, got 0"),
        ({"animation_frames": -1}, "animation_frames must be a whole number >= 0, got -1"),
        ({"vtk_every": -2}, "vtk_every must be a whole number >= 0, got -2"),
        ({"rest_steps": -1}, "rest_steps must be a whole number >= 0, got -1"),
        ({"horizons": ["1", "0"]}, "a horizon must be a positive whole number"),
        ({"mpm": ["grid=-3"]}, "MPM setting 'grid=-3'"),
        ({"mpm": ["native", "none"]}, "cannot be combined"),
        ({"checkpoints": ["nope.pt"]}, "does not exist"),
        ({"checkpoints": []}, "at least one checkpoint"),
    ],
)
def test_bad_report_arguments_are_refused_before_any_work(generated, monkeypatch, change, message):
    import gns.report

    def no_work(*args, **kwargs):
        raise AssertionError("a rollout started before every argument was checked")

    monkeypatch.setattr(gns.report, "_learned_row", no_work)
    out = generated / "refused" / "report"
    arguments = {"out": out, "progress": False, **change}
    with pytest.raises(ValueError, match=message):
        report(generated / "run", generated / "data", **arguments)
    assert not (generated / "refused").exists()


def report_files(folder):
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*"))


def quick_report(generated, out, **kw):
    """One trajectory, no MPM rows, no animation, no VTK: a report in about a second."""
    settings = dict(trajectories=1, mpm=["none"], animation_frames=0, vtk_every=0)
    return report(
        generated / "run", generated / "data", out=out, progress=False, **{**settings, **kw}
    )


def test_a_failed_report_leaves_no_folder_and_keeps_the_earlier_report(generated, monkeypatch):
    import gns.report

    def fails(*args, **kwargs):
        raise RuntimeError("the machine went away")

    out = generated / "atomic" / "new" / "report"
    monkeypatch.setattr(gns.report, "_constant_velocity_row", fails)
    with pytest.raises(RuntimeError, match="went away"):
        quick_report(generated, out)
    # Neither the folder, nor its temporary twin, nor the parents made for it remain.
    assert not (generated / "atomic").exists()
    monkeypatch.undo()

    earlier = quick_report(generated, out, horizons=(1, 2))
    before = report_files(out)
    (out / "stale.txt").write_text("from an older report")
    monkeypatch.setattr(gns.report, "_constant_velocity_row", fails)
    with pytest.raises(RuntimeError):
        quick_report(generated, out)
    assert report_files(out) == sorted([*before, "stale.txt"])  # untouched
    assert [p.name for p in out.parent.iterdir()] == ["report"]
    monkeypatch.undo()

    # A finished report replaces the earlier one as a whole: no file of it lingers.
    again = quick_report(generated, out)
    assert not (out / "stale.txt").exists() and again.out == earlier.out == out
    assert "mse@2" not in json.loads((out / "table.json").read_text())["columns"]
    assert all(path.is_file() and path.parent == out for path in again.files.values())
    assert [p.name for p in out.parent.iterdir()] == ["report"]


def test_a_folder_that_is_not_a_report_is_refused_before_any_work(generated):
    out = generated / "not_a_report"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match="is not a gns report folder"):
        quick_report(generated, out)
    assert report_files(out) == ["notes.txt"]


# ---------------------------------------------------------------------------------- conclusion


def row(short, role, seconds, values, native=False, diverged=(), trajectories=2):
    method = short.split()[0] if role != "baseline" else short
    return Row(
        method,
        short,
        "cpu",
        seconds_per_frame=seconds,
        values=values,
        trajectories=trajectories,
        short=short,
        role=role,
        native=native,
        diverged=list(diverged),
    )


def values(one, ten, full):
    return {"mse@1": one, "mse@10": ten, "mse@full": full}


COLUMNS = table_columns((1, 10, None), 155)


def test_conclusion_says_who_wins_where_by_how_much_and_at_what_cost():
    rows = [
        # best.pt: the best early on, then diverged on trajectory 0 at step 12.
        row("GNS best.pt (step 500)", "learned", 1.9e-3, values(1e-8, 2e-8, math.inf),
            diverged=[(0, 12)]),
        row("GNS latest.pt (step 4000)", "learned", 2e-3, values(2e-8, 5e-8, 1e-4)),
        row("MPM grid 40 (native)", "mpm", 6e-3, values(0.0, 0.0, 0.0), native=True),
        row("MPM grid 24", "mpm", 3e-3, values(4e-8, 1e-7, 2e-4)),
        row("constant velocity", "baseline", 1e-5, values(3e-8, 4e-8, 3e-4)),
    ]  # fmt: skip
    assert conclusion(rows, COLUMNS, 155) == [
        "Over the full 155-frame rollouts GNS latest.pt (step 4000) has 3.0x lower MSE than "
        "constant velocity (0.0001 against 0.0003) at 2.0 ms per frame, 3.0x faster than the "
        "reference simulator at its native settings (6.0 ms).",
        "Lowest MSE, leaving out the MPM at its native settings (it is the ground truth): the "
        "first predicted frame: GNS best.pt (step 500), 3.0x lower MSE than constant velocity; "
        "the first 10 predicted frames: GNS best.pt (step 500), 2.0x lower MSE than constant "
        "velocity; the full 155-frame rollouts: GNS latest.pt (step 4000), 3.0x lower MSE than "
        "constant velocity.",
        "Against the reference simulator at cheaper settings over the full 155-frame rollouts, "
        "GNS latest.pt (step 4000) has 2.0x lower MSE than MPM grid 24 (0.0002 at 3.0 ms per "
        "frame, 1.5x faster than it).",
        "GNS best.pt (step 500) diverged: trajectory 0 at step 12 (1 of 2 trajectories); its "
        "later frames count as infinitely wrong.",
    ]


def test_conclusion_stays_true_when_the_model_loses_and_there_is_no_simulator():
    rows = [
        row("GNS latest.pt (step 20)", "learned", 4e-3, values(1e-8, 9e-8, 6e-4)),
        row("constant velocity", "baseline", 1e-5, values(2e-8, 3e-8, 2e-4)),
    ]
    assert conclusion(rows, COLUMNS, 155) == [
        "Over the full 155-frame rollouts GNS latest.pt (step 20) has 3.0x higher MSE than "
        "constant velocity (0.0006 against 0.0002) at 4.0 ms per frame; the reference "
        "simulator was not run (see Left out).",
        "Lowest MSE: the first predicted frame: GNS latest.pt (step 20), 2.0x lower MSE than "
        "constant velocity; the first 10 predicted frames: constant velocity, 3.0x lower MSE "
        "than GNS latest.pt (step 20); the full 155-frame rollouts: constant velocity, 3.0x "
        "lower MSE than GNS latest.pt (step 20).",
        "No learned rollout diverged.",
    ]


def test_conclusion_when_every_learned_row_diverged_and_a_cheaper_simulator_failed():
    rows = [
        row("GNS best.pt (step 500)", "learned", 2e-3, values(1e-8, math.inf, math.inf),
            diverged=[(0, 4), (1, 7)]),
        row("MPM grid 40 (native)", "mpm", 6e-3, values(0.0, 0.0, 0.0), native=True),
        row("MPM grid 12", "mpm", None, {}),
        row("constant velocity", "baseline", 1e-5, values(3e-8, 4e-8, 3e-4)),
    ]  # fmt: skip
    first, winners, diverged = conclusion(rows, COLUMNS, 155)
    assert first.startswith("Over the full 155-frame rollouts no learned model has a finite MSE")
    assert "constant velocity's is 0.0003" in first
    assert winners.endswith(
        "the first 10 predicted frames: constant velocity (every learned model had diverged); "
        "the full 155-frame rollouts: constant velocity (every learned model had diverged)."
    )
    assert diverged.startswith(
        "GNS best.pt (step 500) diverged: trajectory 0 at step 4, trajectory 1 at step 7 "
        "(2 of 2 trajectories)"
    )


def deposit(runout, height, ratios):
    """Row values of a deposit: mean runout and height, and the three ratios."""
    keys = ("runout_ratio", "height_ratio", "density_ratio")
    return {"runout": runout, "pile_height": height, **dict(zip(keys, ratios, strict=True))}


def test_conclusion_says_where_the_sand_stops_against_the_truth_and_the_static_baseline():
    learned = row("GNS best.pt (step 2000)", "learned", 2e-3, values(1e-8, 2e-8, 1e-3))
    learned.values.update(deposit(0.31, 0.08, (0.43, 1.6, 8.5)))
    learned.rest = {
        "steps": 50,
        "mean": {"density_ratio": 1.31, "max_displacement": 0.012, "truth_speed": 1e-4},
    }
    static = row("static", "baseline", 1e-6, values(3e-8, 4e-8, 2e-3))
    static.values.update(deposit(0.2, 0.2, (0.28, 4.0, 1.09)))
    velocity = row("constant velocity", "baseline", 1e-5, values(3e-8, 4e-8, 3e-3))
    truth = {"runout": 0.72, "pile_height": 0.05, "neighbours": 10.0}
    first, where, rest, winners, diverged = conclusion(
        [learned, velocity, static], COLUMNS, 155, truth
    )
    assert first == (
        "Over the full 155-frame rollouts GNS best.pt (step 2000) has 3.0x lower MSE than "
        "constant velocity (0.001 against 0.003) and 2.0x lower MSE than the static baseline "
        "(0.002) at 2.0 ms per frame; the reference simulator was not run (see Left out)."
    )
    assert where == (
        "Where the sand stops (the last frame, means over trajectories): GNS best.pt (step "
        "2000)'s deposit is 0.31 wide against the truth's 0.72 and piles 0.08 high against "
        "0.05; per trajectory its runout is 0.43x the truth's, its height 1.6x, its density "
        "8.5x (the table's ratios); the static baseline's is 0.2 wide and piles 0.2 high "
        "(runout 0.28x, height 4.0x, density 1.1x)."
    )
    assert rest == (
        "Held still for 50 steps, the last frames under GNS best.pt (step 2000) move by at "
        "most 0.012 (the data's own last step: at most 0.0001) and end 1.3x as densely packed "
        "as they started."
    )
    assert winners.startswith("Lowest MSE: the first predicted frame: GNS best.pt")
    assert diverged == "No learned rollout diverged."
    # Without the truth's deposit (or a static row) those parts are left out, not guessed.
    assert conclusion([learned, velocity], COLUMNS, 155)[0].endswith("(see Left out).")
    assert not any(s.startswith("Where") for s in conclusion([learned, velocity], COLUMNS, 155))
    learned.rest["mean"]["max_displacement"] = math.inf
    assert conclusion([learned, velocity], COLUMNS, 155)[1] == (
        "Held still for 50 steps, the last frames under GNS best.pt (step 2000) diverged (see "
        "the rest test)."
    )


def test_the_conclusion_opens_the_report(generated_report):
    out, rows = generated_report.out, generated_report.rows
    payload = json.loads((out / "table.json").read_text())
    truth = payload["deposits"]["ground_truth"]["mean"]
    sentences = conclusion(rows, payload["columns"], payload["context"]["steps"], truth)
    assert payload["context"]["conclusion"] == sentences and len(sentences) >= 5
    assert sentences[0].startswith("Over the full 8-frame rollouts GNS")
    assert "and" in sentences[0] and "than the static baseline" in sentences[0]
    assert sentences[1].startswith("Where the sand stops (the last frame")
    assert f"against the truth's {truth['runout']:.3g}" in sentences[1]
    assert sentences[2].startswith("Held still for 2 steps")
    assert any("the reference simulator at its native settings" in s for s in sentences)
    markdown = (out / "report.md").read_text().splitlines()
    assert markdown[2] == "**In short.** " + " ".join(sentences)
    html = (out / "report.html").read_text()
    assert html.index("<b>In short.</b>") < html.index("<table>")


# ------------------------------------------------------------------------- diverged in figures


def x_marks(ax):
    return [line for line in ax.lines if line.get_marker() == "x"]


def legend_texts(figure):
    return [text.get_text() for legend in figure.legends for text in legend.get_texts()]


def test_error_over_time_marks_where_a_series_diverged(tmp_path):
    diverged = Series(
        "GNS best.pt",
        2e-3,
        {"mse@full": math.inf},
        (np.arange(5), np.array([1e-4, 2e-4, 4e-4, math.inf, math.inf])),
        (np.array([0, 3]), np.array([1e-4, math.inf])),
        diverged_at=3,
    )
    fine = Series(
        "constant velocity",
        1e-5,
        {"mse@full": 1e-3},
        (np.arange(5), np.full(5, 1e-3)),
        (np.array([0, 3]), np.full(2, 1e-3)),
    )
    figure = error_over_time([diverged, fine], tmp_path / "over_time.png", first_frame=6)
    mse_panel, ot_panel = figure.axes[:2]
    # The x sits on the last finite point: frame 6 + 2 (MSE) and 6 + 0 (OT, every 3rd frame).
    ((mse_x,),) = [line.get_xydata().tolist() for line in x_marks(mse_panel)]
    ((ot_x,),) = [line.get_xydata().tolist() for line in x_marks(ot_panel)]
    assert mse_x == [8.0, 4e-4] and ot_x == [6.0, 1e-4]
    assert x_marks(mse_panel)[0].get_color() == mse_panel.lines[0].get_color()
    assert legend_texts(figure) == ["GNS best.pt: diverged at step 3", "constant velocity"]


def test_error_vs_time_marks_a_method_that_diverged_before_a_horizon(tmp_path):
    series = [
        Series("GNS best.pt", 2e-3, {"mse@1": 1e-8, "mse@full": math.inf}, diverged_at=3),
        # Diverged at its first step: no time and no finite value, still in the legend.
        Series("GNS latest.pt", None, {"mse@1": math.inf, "mse@full": math.inf}, diverged_at=0),
        Series("constant velocity", 1e-5, {"mse@1": 3e-8, "mse@full": 3e-4}),
    ]
    figure = error_vs_time(series, ["mse"], ["1", "full"], tmp_path / "vs_time.png")
    first, full = figure.axes[:2]
    assert x_marks(first) == [] and len(first.collections) == 2  # both finite at frame 1
    (mark,) = x_marks(full)
    assert mark.get_xdata().tolist() == [2.0]  # at its time per frame, ms
    assert mark.get_transform() == full.get_xaxis_transform()  # on the top edge
    assert legend_texts(figure) == [
        "GNS best.pt: diverged at step 3",
        "GNS latest.pt: diverged at step 0",
        "constant velocity",
    ]


def test_fronts_over_time_draw_the_truth_and_stop_where_a_series_diverged(tmp_path):
    truth = np.stack([0.4 - 0.01 * np.arange(6), 0.6 + 0.01 * np.arange(6)], axis=1)
    diverged = truth.copy()
    diverged[4:] = math.inf
    series = [
        Series("GNS best.pt", 2e-3, {}, diverged_at=4, fronts=diverged),
        Series("static", 1e-6, {}, fronts=np.repeat(truth[:1], 6, axis=0)),
        Series("MPM grid 20", None, {}),  # failed: no fronts, left out
    ]
    figure = front_over_time(series, truth, tmp_path / "fronts.png", first_frame=6)
    assert (tmp_path / "fronts.png").is_file()
    (ax,) = figure.axes
    # Two fronts each for the truth and the two series with fronts, and one x per front at
    # the diverged series' last finite frame (6 + 3).
    marks = x_marks(ax)
    assert len(ax.lines) == 6 + len(marks) and len(marks) == 2
    assert sorted(m.get_xydata().tolist()[0][1] for m in marks) == [truth[3, 0], truth[3, 1]]
    assert all(m.get_xydata()[0, 0] == 9 for m in marks)
    np.testing.assert_array_equal(ax.lines[0].get_xydata()[:, 0], np.arange(6, 12))
    assert legend_texts(figure) == ["ground truth", "GNS best.pt: diverged at step 4", "static"]


def test_the_animation_shows_a_diverged_prediction_up_to_where_it_diverged():
    rng = np.random.default_rng(0)
    truth = rng.uniform(0.2, 0.8, size=(10, 4, 2))
    predicted = truth + 0.01
    predicted[7:] = np.nan
    figure = RolloutFigure(truth, predicted, np.full(4, 6), None, ("a", "b"), 3, 0.0025)
    assert figure.diverged_at == 7
    figure.draw(6)
    assert figure.notice.get_text() == ""
    np.testing.assert_allclose(figure.scatters[1].get_offsets(), predicted[6])
    for t in (7, 9):
        figure.draw(t)
        assert figure.notice.get_text() == "diverged at frame 7"
        np.testing.assert_allclose(figure.scatters[1].get_offsets(), predicted[6])
        np.testing.assert_allclose(figure.scatters[0].get_offsets(), truth[t])
    # Even spacing would skip frames 46 and 47: they replace their neighbours, within the cap.
    frames = animation_frames(100, 10, diverged_at=47).tolist()
    assert len(frames) == 10 and {0, 46, 47, 99} <= set(frames)
    assert animation_frames(100, 10).tolist() == [0, 11, 22, 33, 44, 55, 66, 77, 88, 99]
    assert animation_frames(5, 10, diverged_at=3).tolist() == [0, 1, 2, 3, 4]


def test_a_learned_rows_device_says_what_its_rollouts_ran_with():
    from gns.report.measure import _device_label

    cpu = torch.device("cpu")
    one = [{"torch_threads": 1, "precision": "fp32"}] * 2
    assert _device_label(cpu, one) == "cpu, 1 torch thread, fp32"
    mixed = [{"torch_threads": 2, "precision": "fp32"}, {"torch_threads": 1, "precision": "bf16"}]
    assert _device_label(cpu, mixed) == "cpu, 1-2 torch threads, bf16, fp32"
