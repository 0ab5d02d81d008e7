"""`gns report`: each row against an independent computation from the dataset and the saved
rollouts (numpy, brute-force optimal transport), the MPM rows (native reproduces the data
exactly; a failing cheaper setting is a row, not a crash), datasets not made by `gns generate`,
the tables parsing back, the VTK writer against a small XML reader, and bad arguments."""

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
from gns.data import open_dataset
from gns.data.h5 import write_h5
from gns.generate import generate, preset_scene
from gns.report import MpmVariant, parse_horizons, parse_mpm_variants, report, score
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
    assert native.values and all(value == 0.0 for value in native.values.values())
    assert native.seconds_per_frame > 0
    coarse = rows[("MPM", "grid 20 (dx 0.05)")]
    # A coarser grid is a different simulation of the same particles: nonzero, finite error.
    assert coarse.status == "ok" and coarse.seconds_per_frame > 0
    assert all(0 < value < math.inf for value in coarse.values.values())


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
    import gns.rollout as rollout_module

    real = rollout_module.rollout

    def diverge_after_three_steps(simulator, trajectory, **kw):
        if kw.get("num_steps") is not None:  # the warm-up
            return real(simulator, trajectory, **kw)
        partial = real(simulator, trajectory, num_steps=3)
        raise rollout_module.RolloutDiverged("diverged at step 3", partial, 3, 1)

    monkeypatch.setattr(rollout_module, "rollout", diverge_after_three_steps)
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
    assert row.values["mse@1"] < math.inf and row.values["mse@full"] == math.inf
    assert "inf" in (result.out / "table.md").read_text()
    record = json.loads((result.out / "table.json").read_text())["rows"][0]
    assert record["mse@full"] is None and record["mse@1"] == row.values["mse@1"]
    # VTK has only the finite frames of the prediction: 6 history + 3 predicted, every 2nd.
    pvd = ET.parse(result.out / "vtk/prediction.pvd").getroot()
    assert len(pvd.findall("./Collection/DataSet")) == len(range(0, 9, 2))
    assert "MPM rows: none asked for" in (result.out / "report.md").read_text()


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
    assert [r.method for r in result.rows] == ["GNS", "constant velocity"]
    (reason,) = [item for item in result.left_out if item.startswith("MPM rows")]
    assert "not written by `gns generate`" in reason
    assert reason in (result.out / "report.md").read_text()


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


def test_bad_report_arguments_name_the_value(generated):
    run, data = generated / "run", generated / "data"
    with pytest.raises(ValueError, match="between 1 and 2.*got 3"):
        report(run, data, trajectories=3, out=generated / "bad", progress=False)
    with pytest.raises(ValueError, match="every must be a whole number >= 1, got 0"):
        report(run, data, every=0, out=generated / "bad", progress=False)
    with pytest.raises(ValueError, match="does not exist"):
        report(run, data, checkpoints=[str(generated / "nope.pt")], progress=False)
