"""The pieces `gns report` is made of, on hand-made inputs (no dataset, no run): the scores
against numpy and brute-force optimal transport, the VTK writer against a small XML reader,
parsing horizons and MPM settings, the conclusion's sentences, the figures and the animation
marking where a rollout diverged, and a learned row's device label. The report run end to end
is in test_report.py."""

from __future__ import annotations

import dataclasses
import itertools
import math
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import torch
from gns import mpm
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
    score,
    table_columns,
)
from gns.report.reference import _coarsest_grid
from gns.vtk import write_series


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
    # A 3D preset at grid 24 whose walls, 0.1 in, need grid 20 at least: auto stops there.
    assert parse_mpm_variants(["auto"], 24, 0.4, min_grid=20) == [
        MpmVariant(),
        MpmVariant(grid=20),
        MpmVariant(cfl=0.8),
        MpmVariant(grid=20, cfl=0.8),
    ]
    scene = mpm.MpmScene([mpm.Block(mpm.Sand(), (0.3,) * 3, (0.2,) * 3)], grid=24)
    assert _coarsest_grid(scene) == 20
    with pytest.raises(ValueError, match="2 dx <= lo"):
        mpm.simulate(dataclasses.replace(scene, grid=19), frames=2)
    mpm.simulate(dataclasses.replace(scene, grid=20), frames=2)
    assert parse_mpm_variants(["native", "grid=30,cfl=0.5"], 40, 0.4) == [
        MpmVariant(),
        MpmVariant(grid=30, cfl=0.5),
    ]
    assert parse_mpm_variants(["none"], 40, 0.4) == []
    for bad in (["grid=1"], ["cfl=-1"], ["grid=2.5"], ["speed=2"], ["none", "native"]):
        with pytest.raises(ValueError, match="MPM setting"):
            parse_mpm_variants(bad, 40, 0.4)


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
        "Where it stands against the reference simulator (2 settings, 3.0 ms to 6.0 ms per "
        "frame): at 2.0 ms per frame GNS latest.pt (step 4000) is faster than every one, and "
        "over the full 155-frame rollouts its MSE is lower than MPM grid 24 and higher than the "
        "other one; it wins (faster and more accurate) against MPM grid 24 at every horizon.",
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


def test_conclusion_says_plainly_where_the_chosen_row_stands_against_the_simulator():
    rows = [
        row("GNS best.pt (step 900)", "learned", 9e-3, values(1e-8, 3e-6, 5e-4)),
        row("GNS latest.pt (step 1000)", "learned", 9e-3, values(1e-8, 2e-6, 1e-4)),
        row("MPM grid 40 (native)", "mpm", 6e-3, values(0.0, 0.0, 0.0), native=True),
        row("MPM grid 24", "mpm", 3e-3, values(4e-8, 1e-7, 2e-4)),
        row("MPM grid 12", "mpm", 1e-2, values(2e-8, 1e-6, 2e-3)),
        row("constant velocity", "baseline", 1e-5, values(3e-8, 4e-8, 3e-3)),
    ]  # fmt: skip
    # By default the row of lowest MSE over the full rollout; a headline chosen elsewhere (on
    # the valid split) is spoken of instead, even when another row did better here.
    first, over, *_ = conclusion(rows, COLUMNS, 155)
    assert first.startswith("Where it stands against the reference simulator (3 settings, ")
    assert "at 9.0 ms per frame GNS latest.pt (step 1000) is faster than MPM grid 12 and " in first
    assert (
        "slower than the other 2, and over the full 155-frame rollouts its MSE is lower " in first
    )
    assert first.endswith(
        "lower than MPM grid 24, MPM grid 12 and higher than the other one; it wins (faster and "
        "more accurate) against MPM grid 12 over the first predicted frame, the full 155-frame "
        "rollouts."
    )
    assert over.startswith("Over the full 155-frame rollouts GNS latest.pt (step 1000) has")
    first, over, *_ = conclusion(rows, COLUMNS, 155, headline=rows[0])
    assert "GNS best.pt (step 900) is faster than MPM grid 12" in first
    assert first.endswith("against MPM grid 12 over the first predicted frame, the full "
                          "155-frame rollouts.")  # fmt: skip
    assert over.startswith("Over the full 155-frame rollouts GNS best.pt (step 900) has")
    # Slower and less accurate than every setting: it wins nowhere, and says so.
    slow = row("GNS best.pt (step 900)", "learned", 5e-2, values(1e-6, 3e-5, 5e-3))
    first = conclusion([slow, *rows[2:]], COLUMNS, 155)[0]
    assert "is slower than every one, and over the full 155-frame rollouts its MSE is higher " in (
        first
    )
    assert first.endswith("it wins in no regime tried here: every setting is more accurate "
                          "than it or faster.")  # fmt: skip
    # A headline that diverged is said to have, not replaced by another row.
    broken = row("GNS best.pt (step 5)", "learned", 2e-3, values(1e-8, math.inf, math.inf),
                 diverged=[(0, 4)])  # fmt: skip
    first = conclusion([broken, *rows[1:]], COLUMNS, 155, headline=broken)[0]
    assert first.startswith(
        "Over the full 155-frame rollouts GNS best.pt (step 5) has no finite MSE (it diverged"
    )


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
    """Row values of a deposit: mean runout and height, and the ratios (the density's at its
    worst frame last, when given)."""
    keys = ("runout_ratio", "height_ratio", "density_ratio", "density_ratio_max")
    return {
        "runout": runout,
        "pile_height": height,
        **dict(zip(keys[: len(ratios)], ratios, strict=True)),
    }


def test_conclusion_says_where_the_sand_stops_against_the_truth_and_the_static_baseline():
    learned = row("GNS best.pt (step 2000)", "learned", 2e-3, values(1e-8, 2e-8, 1e-3))
    learned.values.update(deposit(0.31, 0.08, (0.43, 1.6, 8.5, 9.1)))
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
        "8.5x, 9.1x at its worst frame (the table's ratios); the static baseline's is 0.2 "
        "wide and piles 0.2 high (runout 0.28x, height 4.0x, density 1.1x)."
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
