"""`gns report` run end to end: each row against an independent computation from the dataset
and the saved rollouts (numpy), the MPM rows (native reproduces the data exactly, its deposit
included; a failing cheaper setting is a row, not a crash), the static baseline and the
deposit figures against the ground truth's, the rest test, a diverged learned rollout, datasets
not made by `gns generate`, data whose frames are finer than the model's step (every row
against the report on `gns convert --frame-stride`'s frames), the tables parsing back, the
conclusion opening the report, bad arguments refused before any work, and a failed report
leaving the earlier one in place. The report's pieces on hand-made inputs (scores, conclusion
sentences, figures, the VTK writer, argument parsing) are in test_report_parts.py."""

from __future__ import annotations

import csv
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
from gns.plots import RolloutFigure
from gns.report import MpmVariant, conclusion, report
from gns.rollout import load_rollout
from gns.train import train
from scipy.spatial.distance import pdist

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
    assert [native.values[k] for k in DEPOSIT_COLUMNS] == [1.0] * len(DEPOSIT_COLUMNS)
    truth = json.loads((generated_report.out / "table.json").read_text())["deposits"]
    for ours, theirs in zip(native.deposits, truth["ground_truth"]["trajectories"], strict=True):
        assert ours["runout"] == theirs["runout"] and ours["pile_height"] == theirs["pile_height"]
        assert ours["front_x_p99"].tolist() == theirs["front_x_p99"]
    assert native.seconds_per_frame > 0
    coarse = rows[("MPM", "grid 20 (dx 0.05)")]
    # A coarser grid is a different simulation of the same particles: nonzero, finite error.
    assert coarse.status == "ok" and coarse.seconds_per_frame > 0
    assert all(0 < value < math.inf for value in coarse.values.values())


DEPOSIT_COLUMNS = ("runout_ratio", "height_ratio", "density_ratio", "density_ratio_max")


def brute_neighbours(x: np.ndarray, radius: float) -> float:
    """Mean number of other particles closer than radius, from every pair's distance."""
    return 2 * int((pdist(x) < radius).sum()) / len(x)


def test_static_row_holds_the_last_input_frame(generated, generated_report):
    (row,) = [r for r in generated_report.rows if r.method == "static"]
    assert row.role == "baseline" and row.seconds_per_frame > 0
    test = open_dataset(generated / "data", "test")
    radius = test.metadata.default_connectivity_radius
    full, runout_ratios, packed_ratios = [], [], []
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
        # Its density against the truth's in every predicted frame, at the worst frame.
        still = brute_neighbours(held[free], radius)
        packed_ratios.append(max(still / brute_neighbours(y[free], radius) for y in x[HISTORY:]))
    assert row.values["mse@full"] == pytest.approx(np.mean(full), rel=1e-9)
    assert row.values["runout_ratio"] == pytest.approx(np.mean(runout_ratios), rel=1e-9)
    assert row.values["density_ratio_max"] == pytest.approx(np.mean(packed_ratios), rel=1e-9)
    # The worst frame is no better than the last.
    assert row.values["density_ratio_max"] >= row.values["density_ratio"]


def test_deposit_columns_and_the_truths_own_deposit_in_table_json(generated, generated_report):
    out = generated_report.out
    payload = json.loads((out / "table.json").read_text())
    assert set(DEPOSIT_COLUMNS) <= set(payload["columns"])
    header = (out / "table.md").read_text().splitlines()[0]
    assert "| runout ratio | height ratio | density ratio | density ratio max |" in header
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


def test_a_model_with_enforced_walls_says_so_with_its_corrections(generated, tmp_path):
    from gns.checkpoints import export_model

    export_model(generated / "run", tmp_path / "walled", enforce_walls=True)
    result = report(
        tmp_path / "walled",
        generated / "data",
        out=tmp_path / "report",
        mpm=["none"],
        every=4,
        animation_frames=0,
        vtk_every=0,
        progress=False,
    )
    (row,) = [r for r in result.rows if r.method == "GNS"]
    saved = [load_rollout(f) for f in (result.out / "rollouts").glob("*/rollout_test_*.npz")]
    assert len(saved) == 2 and all(r.metadata["enforce_walls"] for r in saved)
    moved = sum(r.metadata["wall_corrections"] for r in saved)
    assert f"walls enforced: {moved} particle-steps put back on a wall" in row.setting
    assert row.status == "ok" and "walls" not in row.short  # the figures' label stays short
    assert moved > 0  # the untrained model pushes particles through the walls
    # On the walls as the rollout's float32 holds them.
    bounds = np.array(saved[0].metadata["bounds"], dtype=np.float32)
    for r in saved:
        free = r.particle_type != 3
        inside = (r.predicted_rollout[:, free] >= bounds[:, 0]) & (
            r.predicted_rollout[:, free] <= bounds[:, 1]
        )
        assert inside.all()


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
        ({"labels": ["a", "b"]}, "2 labels for 1 checkpoints"),
        ({"headline": 1}, "headline must index the 1 checkpoints, got 1"),
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


def test_the_conclusion_opens_the_report(generated_report):
    out, rows = generated_report.out, generated_report.rows
    payload = json.loads((out / "table.json").read_text())
    truth = payload["deposits"]["ground_truth"]["mean"]
    sentences = conclusion(rows, payload["columns"], payload["context"]["steps"], truth)
    assert payload["context"]["conclusion"] == sentences and len(sentences) >= 5
    # First, plainly, where the best learned row stands against the simulator's settings.
    assert sentences[0].startswith("Where it stands against the reference simulator (")
    sentences_after = sentences[1:]
    assert sentences_after[0].startswith("Over the full 8-frame rollouts GNS")
    assert "and" in sentences_after[0] and "than the static baseline" in sentences_after[0]
    assert sentences_after[1].startswith("Where the sand stops (the last frame")
    assert f"against the truth's {truth['runout']:.3g}" in sentences_after[1]
    assert sentences_after[2].startswith("Held still for 2 steps")
    assert any("the reference simulator at its native settings" in s for s in sentences)
    markdown = (out / "report.md").read_text().splitlines()
    assert markdown[2] == "**In short.** " + " ".join(sentences)
    html = (out / "report.html").read_text()
    assert html.index("<b>In short.</b>") < html.index("<table>")
