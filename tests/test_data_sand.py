"""The real sand2d-taichi trajectories (shared/data), checked against independent numpy."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from data_helpers import SAND, assert_same
from gns.data import compute_statistics, convert, open_dataset, validate_dataset

pytestmark = pytest.mark.skipif(
    not (SAND / "manifest.json").is_file(), reason="shared/data/sand2d-taichi not present"
)


def load_trusted(name):
    """The data as a user who trusts the file would load it: plain np.load with pickles."""
    with np.load(SAND / name, allow_pickle=True) as data:
        positions, types = data["trajectory0"]
    return np.asarray(positions), np.asarray(types)


def per_frame_stats(positions):
    x = positions.astype(np.float64)
    v = x[1:] - x[:-1]
    a = v[1:] - v[:-1]
    return v.reshape(-1, 2), a.reshape(-1, 2)


def test_sand_00_reads_exactly_and_has_the_documented_statistics():
    positions, types = load_trusted("sand_00.npz")
    dataset = open_dataset(SAND, "train")
    (index,) = [i for i, f in enumerate(dataset.files) if f.name == "sand_00.npz"]
    trajectory = dataset[index]
    np.testing.assert_array_equal(trajectory.positions, positions)
    np.testing.assert_array_equal(trajectory.particle_type, types)
    assert trajectory.positions.shape == (350, 656, 2)
    stats = compute_statistics([trajectory])
    vel, acc = per_frame_stats(positions)
    np.testing.assert_allclose(stats.vel_std, vel.std(0), rtol=1e-9)
    np.testing.assert_allclose(stats.acc_std, acc.std(0), rtol=1e-9)
    np.testing.assert_allclose(stats.acc_mean, acc.mean(0), rtol=0, atol=1e-9 * acc.std(0).max())
    # README: vel std ~ [8.8e-4, 8.9e-4], acc std ~ [5.6e-5, 7.5e-5]
    np.testing.assert_allclose(stats.vel_std, [8.8e-4, 8.9e-4], rtol=0.02)
    np.testing.assert_allclose(stats.acc_std, [5.6e-5, 7.5e-5], rtol=0.02)


def test_manifest_metadata_split_and_friction_feature():
    manifest = json.loads((SAND / "manifest.json").read_text())
    angle = {t["file"]: t["friction_angle_deg"] for t in manifest["trajectories"]}
    names = {s: [f.name for f in open_dataset(SAND, s).files] for s in ("train", "valid", "test")}
    assert [len(names[s]) for s in ("train", "valid", "test")] == [12, 4, 8]
    assert sorted(sum(names.values(), [])) == sorted(angle)
    assert names["valid"] == ["sand_02.npz", "sand_13.npz", "sand_32.npz", "sand_43.npz"]
    assert names["test"] == [f"sand_{a}{b}.npz" for a in (0, 1, 3, 4) for b in (4, 5)]
    for split in ("train", "valid", "test"):  # every angle appears in every split
        assert {angle[n] for n in names[split]} == {20, 25, 35, 40}

    valid = open_dataset(SAND, "valid")
    meta = valid.metadata
    assert meta.bounds == ((0.1, 0.9), (0.1, 0.9))
    assert (meta.dt, meta.default_connectivity_radius, meta.dim) == (0.0025, 0.015, 2)
    assert meta.sequence_length == 349
    trajectory = valid[1]  # sand_13: 25 degrees
    assert trajectory.step_context.shape == (350, 1)
    np.testing.assert_array_equal(trajectory.step_context, np.float32(math.tan(math.radians(25))))
    assert trajectory.material_property == np.float32(math.tan(math.radians(25)))


def test_statistics_are_those_of_the_train_split():
    meta = open_dataset(SAND, "test").metadata
    vel, acc, tans = [], [], []
    manifest = {
        t["file"]: t for t in json.loads((SAND / "manifest.json").read_text())["trajectories"]
    }
    for f in open_dataset(SAND, "train").files:
        v, a = per_frame_stats(load_trusted(f.name)[0])
        vel.append(v)
        acc.append(a)
        tans.append(math.tan(math.radians(manifest[f.name]["friction_angle_deg"])))
    vel, acc = np.concatenate(vel), np.concatenate(acc)
    np.testing.assert_allclose(meta.vel_mean, vel.mean(0), rtol=0, atol=1e-9 * vel.std(0).max())
    np.testing.assert_allclose(meta.vel_std, vel.std(0), rtol=1e-8)
    np.testing.assert_allclose(meta.acc_mean, acc.mean(0), rtol=0, atol=1e-9 * acc.std(0).max())
    np.testing.assert_allclose(meta.acc_std, acc.std(0), rtol=1e-8)
    # Every train trajectory has 350 frames, so the context mean is the mean of the tangents.
    np.testing.assert_allclose(meta.context_mean, [np.mean(np.float32(tans))], rtol=1e-6)


def test_sand_converts_to_deepmind_and_validates(tmp_path):
    convert(SAND, tmp_path / "dm", "deepmind", splits=["valid"])
    converted = open_dataset(tmp_path / "dm", "valid")
    original = open_dataset(SAND, "valid")
    assert converted.metadata.vel_std == original.metadata.vel_std
    for a, b in zip(original, converted, strict=True):
        assert_same(type(a)(a.positions, a.particle_type, a.step_context, None, key=a.key), b)
    # The manifest folder itself is sound.
    assert validate_dataset(SAND) == []


def test_frame_stride_keeps_every_kth_frame_all_train_phases_and_restates_statistics(tmp_path):
    k = 3
    convert(SAND, tmp_path / "s", "h5", splits=["train", "test"], frame_stride=k)
    frames = (350 - k) // k + 1  # the length of the last phase, 116: frames 2, 5, ..., 347
    meta = open_dataset(tmp_path / "s", "test").metadata
    assert (meta.dt, meta.sequence_length) == (0.0025 * k, frames - 1)

    test = open_dataset(tmp_path / "s", "test")
    originals = open_dataset(SAND, "test").files
    assert len(test) == len(originals)
    for trajectory, f in zip(test, originals, strict=True):  # phase 0: starts at frame 0
        np.testing.assert_array_equal(
            trajectory.positions, load_trusted(f.name)[0][0 : 3 * frames : 3]
        )

    train = open_dataset(tmp_path / "s", "train")
    strided = [
        load_trusted(f.name)[0][p : p + k * frames : k]
        for f in open_dataset(SAND, "train").files
        for p in range(k)
    ]
    assert len(train) == len(strided) == 12 * k
    for trajectory, expected in zip(train, strided, strict=True):
        assert trajectory.positions.shape == (frames, 656, 2)
        np.testing.assert_array_equal(trajectory.positions, expected)
        assert trajectory.step_context.shape == (frames, 1)
        assert np.all(trajectory.step_context == trajectory.step_context[0, 0])

    vel, acc = zip(*(per_frame_stats(x) for x in strided), strict=True)
    vel, acc = np.concatenate(vel), np.concatenate(acc)
    np.testing.assert_allclose(meta.vel_std, vel.std(0), rtol=1e-8)
    np.testing.assert_allclose(meta.acc_std, acc.std(0), rtol=1e-8)
    # A coarser step: accelerations grow (k^2 = 9x for smooth motion, less across impacts,
    # which a longer step averages: 6.7-7x here).
    assert np.all(
        np.asarray(meta.acc_std) > 5 * np.asarray(open_dataset(SAND, "test").metadata.acc_std)
    )


@pytest.mark.parametrize("stride", [0, -2, 2.5, True, 349])
def test_a_bad_frame_stride_is_refused_and_writes_nothing(tmp_path, stride):
    with pytest.raises(ValueError, match="frame_stride"):
        convert(SAND, tmp_path / "s", "h5", splits=["test"], frame_stride=stride)
    assert not (tmp_path / "s").exists()
