"""`gns.data.write_dataset`: one's own arrays -> a dataset folder that reads back exactly,
validates clean and carries the statistics numpy computes; bad input is refused by name and
leaves nothing behind."""

from __future__ import annotations

import json

import numpy as np
import pytest
from data_helpers import assert_same, random_walk
from gns.data import (
    DatasetError,
    Trajectory,
    open_dataset,
    validate_dataset,
    write_dataset,
)

BOUNDS = [[0.1, 0.9], [0.1, 0.9]]
ARGS = {"dt": 0.0025, "bounds": BOUNDS, "connectivity_radius": 0.015}


def make_splits(seed: int = 0, context: int = 0, material: str | None = None):
    rng = np.random.default_rng(seed)
    # Particle counts differ between trajectories, as in real datasets; the last particle of
    # each is kinematic (type 3), which the statistics must leave out.
    return {
        split: [
            random_walk(rng, 12, 6 + 2 * i, kinematic=1, context=context, material=material)
            for i in range(count)
        ]
        for split, count in (("train", 3), ("valid", 1), ("test", 2))
    }


def numpy_statistics(trajectories, kinematic=(3,)):
    """Per-frame velocity and acceleration of the non-kinematic particles: np.diff, np.mean,
    np.std over everything concatenated (nothing shared with gns.data.stats)."""
    vel, acc = [], []
    for t in trajectories:
        x = t.positions[:, ~np.isin(t.particle_type, kinematic)].astype(np.float64)
        v = np.diff(x, axis=0)
        vel.append(v.reshape(-1, x.shape[2]))
        acc.append(np.diff(v, axis=0).reshape(-1, x.shape[2]))
    vel, acc = np.concatenate(vel), np.concatenate(acc)
    return vel.mean(0), vel.std(0), acc.mean(0), acc.std(0)


@pytest.mark.parametrize(
    ("layout", "context", "material"),
    [("deepmind", 2, None), ("deepmind", 0, None), ("npz", 0, "scalar"), ("h5", 1, "particle")],
)
def test_round_trip_reads_back_exactly_and_validates_clean(tmp_path, layout, context, material):
    splits = make_splits(context=context, material=material)
    written = write_dataset(tmp_path / "data", splits, layout=layout, **ARGS)

    assert validate_dataset(tmp_path / "data") == []
    for split, trajectories in splits.items():
        dataset = open_dataset(tmp_path / "data", split)
        assert dataset.layout == layout and len(dataset) == len(trajectories)
        for ours, theirs in zip(trajectories, dataset, strict=True):
            assert_same(ours, theirs)

    raw = json.loads((tmp_path / "data/metadata.json").read_text())
    assert raw["bounds"] == BOUNDS and raw["dt"] == 0.0025 and raw["dim"] == 2
    assert raw["default_connectivity_radius"] == 0.015
    assert raw["sequence_length"] == 11  # transitions: 12 frames
    assert raw["kinematic_particle_types"] == [3]
    for name, expected in zip(
        ("vel_mean", "vel_std", "acc_mean", "acc_std"),
        numpy_statistics(splits["train"]),
        strict=True,
    ):
        np.testing.assert_allclose(raw[name], expected, rtol=1e-9, atol=1e-15)
        assert list(getattr(written, name)) == raw[name]
    if context:
        stacked = np.concatenate([t.step_context for t in splits["train"]]).astype(np.float64)
        np.testing.assert_allclose(raw["context_mean"], stacked.mean(0), rtol=1e-9)
        np.testing.assert_allclose(raw["context_std"], stacked.std(0), rtol=1e-9)
    else:
        assert "context_mean" not in raw
    assert raw.get("material_feature_len", 0) == (1 if material else 0)


def test_npz_keeps_a_constant_one_feature_context_as_the_material(tmp_path):
    rng = np.random.default_rng(3)
    train = [random_walk(rng, 8, 5) for _ in range(2)]
    angles = [0.5, 0.7]
    with_context = [
        Trajectory(t.positions, t.particle_type, np.full((8, 1), a))
        for t, a in zip(train, angles, strict=True)
    ]
    write_dataset(tmp_path / "d", {"train": with_context}, layout="npz", **ARGS)
    assert validate_dataset(tmp_path / "d") == []
    read = open_dataset(tmp_path / "d")
    assert [float(t.material_property) for t in read] == pytest.approx(angles)
    assert all(t.step_context is None for t in read)


def test_mappings_and_lazy_iterables_give_the_same_folder_as_trajectories(tmp_path):
    splits = make_splits(seed=1, context=1)
    write_dataset(tmp_path / "a", splits, **ARGS)
    as_mappings = {
        split: (
            {
                "positions": t.positions.astype(np.float64),
                "particle_type": t.particle_type,
                "step_context": c,
            }
            for t in trajectories
            # float64 positions and a 1-D context, as a user's arrays may come.
            for c in [t.step_context[:, 0].astype(np.float64)]
        )
        for split, trajectories in splits.items()
    }
    write_dataset(tmp_path / "b", as_mappings, **ARGS)
    for name in ("metadata.json", "train.tfrecord", "valid.tfrecord", "test.tfrecord"):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes(), name


def test_periodic_axes_need_positions_inside_the_bounds(tmp_path):
    positions = np.full((4, 2, 2), 0.5)
    positions[:, :, 0] += np.array([[0.0], [0.1], [0.2], [0.405]])  # 0.905: past 0.9 by 0.005
    positions[:, 1, 1] -= 1e-3 * np.arange(4)
    train = [Trajectory(positions, [5, 5])]
    # Within the connectivity radius of a wall is fine on a walled axis ...
    write_dataset(tmp_path / "walls", {"train": train}, **ARGS)
    assert validate_dataset(tmp_path / "walls") == []
    # ... but a periodic axis wraps positions into [lo, hi].
    with pytest.raises(DatasetError, match=r"axis 0 outside bounds \[0.1, 0.9\].*frame 3"):
        write_dataset(tmp_path / "periodic", {"train": train}, periodic=[True, False], **ARGS)


def good_train():
    return [random_walk(np.random.default_rng(5), 6, 4)]


def with_positions(positions, types=(5, 5, 5)):
    return {"train": [{"positions": positions, "particle_type": np.array(types)}]}


def moving(frames=6, particles=3, dim=2):
    x = np.full((frames, particles, dim), 0.5)
    x[..., -1] -= 1e-3 * np.arange(frames)[:, None] ** 2
    return x


def with_nan():
    x = moving()
    x[4, 2, 1] = np.nan
    return x


BAD = [
    # (splits, keyword overrides, error type, message pattern)
    pytest.param(
        with_positions(moving()[:, :, 0]),
        {},
        DatasetError,
        r"splits\['train'\]: trajectory 0: positions must be \(T, N, D\), got shape \(6, 3\)",
        id="positions-2d",
    ),
    pytest.param(
        with_positions(moving(dim=3)),
        {},
        DatasetError,
        r"positions are 3D .* but bounds has 2 axes",
        id="dim-vs-bounds",
    ),
    pytest.param(
        with_positions(with_nan()),
        {},
        DatasetError,
        r"splits\['train'\]: trajectory 0: .*non-finite.*frame 4, particle 2",
        id="nan-position",
    ),
    pytest.param(
        with_positions(moving(), types=(5, 5)),
        {},
        DatasetError,
        r"particle_type has shape \(2,\) but positions have 3 particles",
        id="types-length",
    ),
    pytest.param(
        {"train": good_train(), "valid": [random_walk(np.random.default_rng(6), 7, 4)]},
        {},
        DatasetError,
        r"splits\['valid'\]: trajectory 0: 7 frames, but splits\['train'\]\[0\] has 6",
        id="frame-counts",
    ),
    pytest.param(
        with_positions(moving() + [0.0, 0.45]),
        {},
        DatasetError,
        r"axis 1 outside bounds \[0.1, 0.9\] \+- 0.015: the first is particle 0 at frame 0",
        id="outside-bounds",
    ),
    pytest.param(
        with_positions(moving(), types=(5, 11, 5)),
        {},
        DatasetError,
        r"particle_type holds \[11\]",
        id="unknown-type",
    ),
    pytest.param(
        with_positions(moving(), types=(3, 3, 3)),
        {},
        DatasetError,
        r"every particle has a kinematic type \[3\]",
        id="all-kinematic",
    ),
    pytest.param(
        {
            "train": good_train()
            + [{"positions": moving(), "particle_type": [5, 5, 5], "step_context": np.ones(6)}]
        },
        {},
        DatasetError,
        r"trajectory 1: step_context has 1 features but splits\['train'\]\[0\] has 0",
        id="context-in-some",
    ),
    pytest.param(
        {"train": good_train()}, {"layout": "hdf5"}, ValueError, r"unknown layout 'hdf5'", id="lay"
    ),
    pytest.param(
        {"train": good_train()}, {"dt": 0.0}, ValueError, r"dt must be .* got 0.0", id="dt"
    ),
    pytest.param(
        {"train": good_train()},
        {"bounds": [[0.9, 0.1], [0.1, 0.9]]},
        ValueError,
        r"bounds\[0\] = \[0.9, 0.1\] is not an interval",
        id="bounds",
    ),
    pytest.param(
        {"train": good_train()},
        {"connectivity_radius": -1},
        ValueError,
        r"connectivity_radius must be a positive number, got -1",
        id="radius",
    ),
    pytest.param({"valid": good_train()}, {}, ValueError, r"needs a 'train' split", id="no-train"),
    pytest.param(
        {"train": good_train(), "validation": good_train()},
        {},
        ValueError,
        r"unknown split\(s\) \['validation'\]",
        id="split-name",
    ),
    pytest.param(
        {"train": good_train(), "test": []},
        {},
        ValueError,
        r"splits\['test'\] holds no trajectories",
        id="empty-split",
    ),
    pytest.param(
        {"train": good_train()[0]}, {}, ValueError, r"got one Trajectory", id="not-a-list"
    ),
    pytest.param(
        {"train": good_train()},
        {"extra": {"dt": 1.0}},
        ValueError,
        r"extra must not set .* \['dt'\]",
        id="extra-clash",
    ),
    pytest.param(
        {"train": [{"positions": moving(), "particle_types": [5, 5, 5]}]},
        {},
        DatasetError,
        r"missing \['particle_type'\], unknown \['particle_types'\]",
        id="mapping-keys",
    ),
    pytest.param(
        {"train": [Trajectory(moving(frames=2), [5, 5, 5])]},
        {},
        ValueError,
        r"splits\['train'\]: no statistics: need trajectories with at least 3 frames",
        id="too-short-for-statistics",
    ),
]


@pytest.mark.parametrize(("splits", "overrides", "error", "pattern"), BAD)
def test_bad_input_is_refused_by_name_and_leaves_nothing(
    tmp_path, splits, overrides, error, pattern
):
    with pytest.raises(error, match=pattern):
        write_dataset(tmp_path / "out", splits, **{**ARGS, **overrides})
    assert list(tmp_path.iterdir()) == []  # neither the folder nor a temporary beside it


def test_an_existing_folder_with_files_is_never_touched(tmp_path):
    (tmp_path / "out").mkdir()
    (tmp_path / "out/notes.txt").write_text("mine")
    with pytest.raises(FileExistsError, match="exists and is not an empty folder"):
        write_dataset(tmp_path / "out", {"train": good_train()}, **ARGS)
    assert [p.name for p in (tmp_path / "out").iterdir()] == ["notes.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    # An empty folder is taken (as `gns convert` does).
    (tmp_path / "out/notes.txt").unlink()
    write_dataset(tmp_path / "out", {"train": good_train()}, extra={"made_by": "me"}, **ARGS)
    assert json.loads((tmp_path / "out/metadata.json").read_text())["made_by"] == "me"
