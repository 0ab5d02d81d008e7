"""Statistics against plain numpy, `validate_dataset`, and the stats / validate / convert CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest
from data_helpers import metadata_dict, random_walk, write_metadata
from gns.cli import main
from gns.data import Trajectory, compute_statistics, open_dataset, validate_dataset
from gns.data.deepmind import write_tfrecord
from gns.data.npz import write_npz
from gns.data.stats import RunningMoments


def dataset_items(seed=0):
    rng = np.random.default_rng(seed)
    return [random_walk(rng, 10, 6 + i, kinematic=2, key=i) for i in range(4)]


def numpy_statistics(items, kinematic=(3,)):
    """Concatenate everything, then np.mean / np.std: nothing shared with the module."""
    vel, acc = [], []
    for t in items:
        x = t.positions[:, ~np.isin(t.particle_type, kinematic)].astype(np.float64)
        v = x[1:] - x[:-1]
        vel.append(v.reshape(-1, x.shape[2]))
        acc.append((v[1:] - v[:-1]).reshape(-1, x.shape[2]))
    vel, acc = np.concatenate(vel), np.concatenate(acc)
    return vel.mean(0), vel.std(0), acc.mean(0), acc.std(0), len(vel), len(acc)


def test_statistics_match_numpy_and_skip_kinematic_particles():
    items = dataset_items()
    stats = compute_statistics(items, {3})
    vm, vs, am, as_, nv, na = numpy_statistics(items)
    np.testing.assert_allclose(stats.vel_mean, vm, rtol=0, atol=1e-10 * vs.max())
    np.testing.assert_allclose(stats.vel_std, vs, rtol=1e-10)
    np.testing.assert_allclose(stats.acc_mean, am, rtol=0, atol=1e-10 * as_.max())
    np.testing.assert_allclose(stats.acc_std, as_, rtol=1e-10)
    assert (
        (stats.vel_count, stats.acc_count) == (nv, na) == (9 * 22, 8 * 22)
    )  # 4+5+6+7 free particles
    # With no kinematic set, the static particles pull the velocity std down.
    assert np.all(compute_statistics(items, set()).vel_std < stats.vel_std)


def test_running_moments_survive_a_large_offset():
    rng = np.random.default_rng(1)
    values = 1e6 + rng.normal(0, 1e-3, size=(100_000, 2))
    moments = RunningMoments()
    for chunk in np.array_split(values, 7):
        moments.add(chunk)
    np.testing.assert_allclose(moments.std, values.std(0), rtol=1e-6)
    np.testing.assert_allclose(moments.mean, values.mean(0), rtol=1e-14)


@pytest.fixture
def good(tmp_path):
    items = dataset_items()
    stats = numpy_statistics(items)
    raw = metadata_dict(
        vel_mean=stats[0].tolist(),
        vel_std=stats[1].tolist(),
        acc_mean=stats[2].tolist(),
        acc_std=stats[3].tolist(),
    )
    write_metadata(tmp_path, raw)
    write_tfrecord(tmp_path / "train.tfrecord", items)
    write_tfrecord(tmp_path / "test.tfrecord", items[:1])
    return tmp_path, raw, items


def test_sound_dataset_has_no_problems(good):
    assert validate_dataset(good[0]) == []


def test_statistics_divided_by_dt_are_recognised(good):
    folder, raw, _ = good
    raw["vel_std"] = [v / raw["dt"] for v in raw["vel_std"]]
    raw["acc_std"] = [v / raw["dt"] ** 2 for v in raw["acc_std"]]
    write_metadata(folder, raw)
    messages = [str(p) for p in validate_dataset(folder)]
    assert len(messages) == 2
    assert all("divided by dt" in m and "per-frame" in m for m in messages)


def test_off_by_one_sequence_length_is_explained(good):
    folder, raw, _ = good
    raw["sequence_length"] = 10  # records hold 10 frames = 9 transitions
    write_metadata(folder, raw)
    problems = validate_dataset(folder)
    assert len(problems) == 5  # 4 train + 1 test trajectories
    assert all("off by one" in p.message for p in problems)
    assert problems[0].trajectory == 0 and "train.tfrecord" in problems[0].file


def test_every_problem_is_listed_not_just_the_first(good):
    folder, raw, items = good
    del raw["acc_std"]
    raw["bounds"] = [[0.1, 0.5], [0.1, 0.9]]
    write_metadata(folder, raw)
    bad = items[2].positions.copy()
    bad[3, 0, 0] = np.nan
    raw_bytes = bytearray((folder / "test.tfrecord").read_bytes())
    raw_bytes[-1] ^= 1  # damage the only test record's payload checksum
    (folder / "test.tfrecord").write_bytes(bytes(raw_bytes))
    messages = [str(p) for p in validate_dataset(folder)]
    assert any("lacks acc_std" in m for m in messages)
    assert any("outside bounds [0.1, 0.5]" in m for m in messages)
    assert any("test.tfrecord: trajectory 0: payload checksum mismatch" in m for m in messages)


def test_unknown_particle_types_and_missing_context(good):
    folder, raw, items = good
    odd = Trajectory(items[0].positions, np.full(items[0].n_particles, 11), key=0)
    write_tfrecord(folder / "test.tfrecord", [odd])
    raw["context_mean"], raw["context_std"] = [0.0], [1.0]
    write_metadata(folder, raw)
    messages = [str(p) for p in validate_dataset(folder)]
    assert any("unknown particle types [11]" in m for m in messages)
    assert any("no step_context" in m for m in messages)


def test_cli_stats_write_then_validate(tmp_path, capsys):
    items = dataset_items(3)
    write_metadata(tmp_path, metadata_dict(note="kept"))
    write_npz(tmp_path / "train.npz", items)
    assert main(["validate", str(tmp_path)]) == 1
    assert "lacks vel_mean" in capsys.readouterr().out
    assert main(["stats", str(tmp_path), "--write"]) == 0
    out = capsys.readouterr().out
    assert "vel_std" in out and "wrote statistics" in out
    written = json.loads((tmp_path / "metadata.json").read_text())
    assert written["note"] == "kept"
    np.testing.assert_allclose(written["acc_std"], numpy_statistics(items)[3], rtol=1e-10)
    assert [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")] == []
    assert main(["validate", str(tmp_path)]) == 0


def test_cli_convert_and_error_exit(tmp_path, capsys):
    write_metadata(tmp_path / "src", metadata_dict())
    write_npz(tmp_path / "src" / "train.npz", dataset_items(4))
    assert main(["convert", str(tmp_path / "src"), str(tmp_path / "dm"), "--to", "deepmind"]) == 0
    assert open_dataset(tmp_path / "dm").layout == "deepmind"
    assert main(["validate", str(tmp_path / "dm")]) == 0
    capsys.readouterr()
    assert main(["stats", str(tmp_path / "nowhere")]) == 2
    assert "no such file or folder" in capsys.readouterr().err


def test_convert_writes_several_sources_one_after_another_with_their_whole_statistics(tmp_path):
    a, b = dataset_items(0), dataset_items(1)[:2]
    # Each source's metadata carries statistics of its own, which the whole must not keep.
    for name, items in (("a", a), ("b", b)):
        write_metadata(
            tmp_path / name,
            metadata_dict(vel_mean=[0, 0], vel_std=[9, 9], acc_mean=[0, 0], acc_std=[9, 9]),
        )
        write_npz(tmp_path / name / "train.npz", items)
    src = [str(tmp_path / n) for n in ("a", "b", "b")]  # b twice: its windows twice as often
    assert main(["convert", *src, str(tmp_path / "ab"), "--to", "h5"]) == 0
    written = list(open_dataset(tmp_path / "ab"))
    assert len(written) == 4 + 2 + 2
    for got, expected in zip(written, a + b + b, strict=True):
        np.testing.assert_array_equal(got.positions, expected.positions)
    meta = open_dataset(tmp_path / "ab").metadata
    _, vs, _, as_, _, _ = numpy_statistics(a + b + b)
    np.testing.assert_allclose(meta.vel_std, vs, rtol=1e-8)
    np.testing.assert_allclose(meta.acc_std, as_, rtol=1e-8)


def test_convert_refuses_sources_of_different_scenes_and_writes_nothing(tmp_path, capsys):
    write_metadata(tmp_path / "a", metadata_dict())
    write_npz(tmp_path / "a" / "train.npz", dataset_items(0))
    write_metadata(tmp_path / "b", metadata_dict(dt=0.0075))
    write_npz(tmp_path / "b" / "train.npz", dataset_items(1))
    args = ["convert", str(tmp_path / "a"), str(tmp_path / "b"), str(tmp_path / "ab")]
    assert main([*args, "--to", "h5"]) == 2
    assert "its dt is 0.0075 but" in capsys.readouterr().err
    assert not (tmp_path / "ab").exists()
