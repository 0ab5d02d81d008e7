"""Write, read, compare exactly: every layout, every writer, and `convert` between them."""

from __future__ import annotations

import json
import struct
import zipfile

import h5py
import numpy as np
import pytest
from data_helpers import assert_same, metadata_dict, random_walk, write_metadata
from gns.data import DatasetError, convert, crc32c, open_dataset
from gns.data.deepmind import write_tfrecord
from gns.data.h5 import write_h5
from gns.data.npz import write_npz


def trajectories(seed: int, context: int = 0, material: str | None = None, count: int = 3):
    rng = np.random.default_rng(seed)
    # Particle counts differ between trajectories, as in the paper's datasets.
    return [
        random_walk(rng, 10, 5 + 3 * i, kinematic=1, context=context, material=material, key=i)
        for i in range(count)
    ]


def test_tfrecord_round_trip_with_step_context(tmp_path):
    items = trajectories(0, context=2)
    write_metadata(tmp_path, metadata_dict(context_mean=[0, 0], context_std=[1, 1]))
    assert write_tfrecord(tmp_path / "train.tfrecord", items) == 3
    dataset = open_dataset(tmp_path)
    assert dataset.layout == "deepmind" and len(dataset) == 3
    for a, b in zip(items, dataset, strict=True):
        assert_same(a, b)


def test_tfrecord_framing_follows_the_spec(tmp_path):
    """Parse the written file with struct and the textbook CRC, not with our reader."""
    items = trajectories(1, count=2)
    path = tmp_path / "x.tfrecord"
    write_tfrecord(path, items)
    raw = path.read_bytes()
    pos, records = 0, 0

    def masked(data: bytes) -> int:
        crc = 0xFFFFFFFF
        for byte in data:
            crc ^= byte
            for _ in range(8):
                crc = (crc >> 1) ^ (0x82F63B78 if crc & 1 else 0)
        crc ^= 0xFFFFFFFF
        return (((crc >> 15) | (crc << 17)) + 0xA282EAD8) & 0xFFFFFFFF

    while pos < len(raw):
        (length,) = struct.unpack_from("<Q", raw, pos)
        assert struct.unpack_from("<I", raw, pos + 8)[0] == masked(raw[pos : pos + 8])
        data = raw[pos + 12 : pos + 12 + length]
        assert struct.unpack_from("<I", raw, pos + 12 + length)[0] == masked(data)
        # The positions of every frame appear verbatim as little-endian float32 bytes.
        for frame in items[records].positions:
            assert frame.astype("<f4").tobytes() in data
        pos += 16 + length
        records += 1
    assert pos == len(raw) and records == 2
    assert crc32c(b"123456789") == 0xE3069283


@pytest.mark.parametrize("variant", ["A", "B"])
@pytest.mark.parametrize("material", [None, "scalar", "particle"])
def test_npz_round_trip(tmp_path, variant, material):
    items = trajectories(2, material=material)
    write_metadata(tmp_path, metadata_dict())
    write_npz(tmp_path / "valid.npz", items, variant=variant)
    dataset = open_dataset(tmp_path, "valid")
    assert dataset.layout == "npz" and len(dataset) == 3
    for a, b in zip(items, dataset, strict=True):
        assert_same(a, b)


def test_npz_written_file_is_what_geoelements_loads(tmp_path):
    """A peer loads it with np.load(allow_pickle=True) and indexes the tuple."""
    items = trajectories(3, material="scalar")
    write_npz(tmp_path / "train.npz", items)
    with np.load(tmp_path / "train.npz", allow_pickle=True) as data:
        keys = list(data.keys())
        assert keys == ["trajectory0", "trajectory1", "trajectory2"]
        for key, item in zip(keys, items, strict=True):
            positions, types, material = data[key]
            np.testing.assert_array_equal(positions, item.positions)
            np.testing.assert_array_equal(types, item.particle_type)
            assert float(material) == float(item.material_property)


def test_npz_reads_numpy_savez_variant_b(tmp_path):
    """Variant B as a user makes it: np.savez with an object array of tuples."""
    items = trajectories(4)
    table = np.empty((3, 2), dtype=object)
    for i, t in enumerate(items):
        table[i, 0], table[i, 1] = t.positions.astype(np.float64), t.particle_type.astype(np.int32)
    np.savez_compressed(tmp_path / "test.npz", gns_data=table)
    write_metadata(tmp_path, metadata_dict())
    for a, b in zip(items, open_dataset(tmp_path, "test"), strict=True):
        assert_same(a, b)


def test_npz_scalar_particle_type_is_broadcast(tmp_path):
    positions = np.random.default_rng(5).uniform(0.2, 0.8, (10, 4, 2)).astype(np.float32)
    row = np.empty(2, dtype=object)
    row[0], row[1] = positions, np.int64(6)
    np.savez(tmp_path / "train.npz", trajectory0=row)
    write_metadata(tmp_path, metadata_dict())
    trajectory = open_dataset(tmp_path)[0]
    np.testing.assert_array_equal(trajectory.particle_type, [6, 6, 6, 6])


@pytest.mark.parametrize("context", [0, 1])
def test_h5_round_trip(tmp_path, context):
    items = trajectories(6, context=context, material="particle")
    write_metadata(tmp_path, metadata_dict())
    write_h5(tmp_path / "train.h5", items)
    dataset = open_dataset(tmp_path)
    assert dataset.layout == "h5"
    for a, b in zip(items, dataset, strict=True):
        assert_same(a, b)


def test_lagrangebench_h5_as_written_by_hand(tmp_path):
    rng = np.random.default_rng(7)
    positions = [rng.uniform(0, 1, (10, n, 2)).astype(np.float64) for n in (4, 6)]
    types = [np.array([0, 0, 1, 2]), np.array([0, 0, 0, 0, 1, -1])]
    with h5py.File(tmp_path / "train.h5", "w") as f:
        for i, (p, t) in enumerate(zip(positions, types, strict=True)):
            group = f.create_group(f"{i:05d}")
            group["position"] = p
            group["particle_type"] = t
    raw = metadata_dict(periodic_boundary_conditions=[True, True], sequence_length_train=9)
    raw["bounds"] = [[0.0, 1.0], [0.0, 1.0]]
    del raw["sequence_length"]
    write_metadata(tmp_path, raw)
    dataset = open_dataset(tmp_path)
    assert dataset.layout == "lagrangebench"
    assert dataset.metadata.kinematic_particle_types == frozenset({1, 2, -1})
    assert dataset.metadata.periodic_boundary_conditions == (True, True)
    assert dataset.metadata.sequence_length == 9
    for i in range(2):
        np.testing.assert_array_equal(dataset[i].positions, positions[i].astype(np.float32))
        np.testing.assert_array_equal(dataset[i].particle_type, types[i])


def test_lagrangebench_writer_round_trip(tmp_path):
    items = trajectories(8)
    write_h5(tmp_path / "train.h5", items, layout="lagrangebench")
    write_metadata(tmp_path, metadata_dict(kinematic_particle_types=[3]))
    dataset = open_dataset(tmp_path)
    assert dataset.layout == "lagrangebench"
    assert dataset.metadata.kinematic_particle_types == frozenset({3})
    for a, b in zip(items, dataset, strict=True):
        assert_same(a, b)


def test_opening_one_file_takes_its_split_from_the_name(tmp_path):
    items = trajectories(9)
    write_metadata(tmp_path, metadata_dict())
    write_h5(tmp_path / "test.h5", items)
    dataset = open_dataset(tmp_path / "test.h5")
    assert dataset.split == "test" and len(dataset) == 3


def make_source(folder, seed=10):
    """A DeepMind folder with train/valid/test and a constant one-feature step_context."""
    rng = np.random.default_rng(seed)
    splits = {}
    for split, count in (("train", 3), ("valid", 1), ("test", 2)):
        items = []
        for i in range(count):
            t = random_walk(rng, 10, 6 + i, kinematic=2, key=i)
            angle = np.float32(rng.uniform(0.3, 0.9))
            items.append(
                type(t)(t.positions, t.particle_type, np.full((10, 1), angle, np.float32), key=i)
            )
        splits[split] = items
    write_metadata(folder, metadata_dict())
    for split, items in splits.items():
        write_tfrecord(folder / f"{split}.tfrecord", items)
    return splits


@pytest.mark.parametrize("chain", [("npz", "deepmind"), ("h5", "npz", "deepmind")])
def test_convert_chain_returns_to_the_same_data(tmp_path, chain):
    splits = make_source(tmp_path / "src")
    src = tmp_path / "src"
    for i, layout in enumerate(chain):
        dst = tmp_path / f"step{i}_{layout}"
        counts = convert(src, dst, layout)
        assert counts == {"train": 3, "valid": 1, "test": 2}
        src = dst
    meta = json.loads((src / "metadata.json").read_text())
    assert {"vel_mean", "vel_std", "acc_mean", "acc_std", "context_mean", "context_std"} <= set(
        meta
    )
    for split, items in splits.items():
        for a, b in zip(items, open_dataset(src, split), strict=True):
            assert_same(a, b)


def test_convert_to_npz_turns_constant_context_into_material(tmp_path):
    splits = make_source(tmp_path / "src")
    convert(tmp_path / "src", tmp_path / "npz", "npz")
    back = open_dataset(tmp_path / "npz", "test")
    assert back[1].step_context is None
    assert back[1].material_property == splits["test"][1].step_context[0, 0]
    assert back.metadata.material_feature_len == 1
    assert back.metadata.context_mean is None


def test_convert_refuses_what_the_target_cannot_hold_and_leaves_nothing(tmp_path):
    write_metadata(tmp_path / "src", metadata_dict())
    write_tfrecord(tmp_path / "src" / "train.tfrecord", trajectories(11, context=2))
    with pytest.raises(DatasetError, match="per-frame step_context"):
        convert(tmp_path / "src", tmp_path / "out", "npz")
    assert not (tmp_path / "out").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["src"]


def test_convert_into_a_non_empty_folder_is_refused(tmp_path):
    make_source(tmp_path / "src")
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "keep.txt").write_text("mine")
    with pytest.raises(DatasetError, match="not an empty folder"):
        convert(tmp_path / "src", tmp_path / "out", "h5")
    assert [p.name for p in (tmp_path / "out").iterdir()] == ["keep.txt"]


def test_failed_write_leaves_the_old_file(tmp_path):
    path = tmp_path / "train.npz"
    write_npz(path, trajectories(12))
    before = path.read_bytes()

    def broken():
        yield from trajectories(13, count=1)
        raise RuntimeError("disk on fire")

    with pytest.raises(RuntimeError):
        write_npz(path, broken())
    assert path.read_bytes() == before
    assert zipfile.is_zipfile(path)
    assert [p.name for p in tmp_path.iterdir()] == ["train.npz"]
