"""Bad or damaged input: every case raises a ValueError naming the file, trajectory and problem."""

from __future__ import annotations

import io
import pickle
import zipfile

import h5py
import numpy as np
import pytest
from data_helpers import metadata_dict, random_walk, write_metadata
from gns.data import DatasetError, Metadata, Trajectory, open_dataset
from gns.data.deepmind import write_tfrecord
from gns.data.npz import restricted_loads, write_npz
from gns.data.protobuf import Feature, SequenceExample, serialize_sequence_example
from gns.data.tfrecord import encode_record, write_records


def three(seed=0):
    rng = np.random.default_rng(seed)
    return [random_walk(rng, 10, 4, key=i) for i in range(3)]


@pytest.fixture
def deepmind(tmp_path):
    write_metadata(tmp_path, metadata_dict())
    write_tfrecord(tmp_path / "train.tfrecord", three())
    return tmp_path


def record_offsets(path):
    raw = path.read_bytes()
    offsets, pos = [], 0
    while pos < len(raw):
        offsets.append(pos)
        pos += 16 + int.from_bytes(raw[pos : pos + 8], "little")
    return raw, offsets


def test_truncated_record(deepmind):
    path = deepmind / "train.tfrecord"
    raw, offsets = record_offsets(path)
    path.write_bytes(raw[: offsets[2] + 40])
    with pytest.raises(DatasetError, match="truncated record") as err:
        open_dataset(deepmind)
    assert str(path) in str(err.value) and "trajectory 2" in str(err.value)


def test_truncated_header(deepmind):
    path = deepmind / "train.tfrecord"
    raw, offsets = record_offsets(path)
    path.write_bytes(raw[: offsets[1] + 5])
    with pytest.raises(DatasetError, match="truncated record header") as err:
        open_dataset(deepmind)
    assert "trajectory 1" in str(err.value)


def test_payload_checksum_mismatch(deepmind):
    path = deepmind / "train.tfrecord"
    raw, offsets = bytearray(path.read_bytes()), record_offsets(path)[1]
    raw[offsets[1] + 12 + 30] ^= 0x01  # one bit inside the second payload
    path.write_bytes(bytes(raw))
    dataset = open_dataset(deepmind)  # the index only checks lengths
    dataset[0]
    with pytest.raises(DatasetError, match="payload checksum mismatch") as err:
        dataset[1]
    assert str(path) in str(err.value) and "trajectory 1" in str(err.value)


def test_length_checksum_mismatch(deepmind):
    path = deepmind / "train.tfrecord"
    raw = bytearray(path.read_bytes())
    raw[8] ^= 0xFF
    path.write_bytes(bytes(raw))
    with pytest.raises(DatasetError, match="length checksum mismatch.*") as err:
        open_dataset(deepmind)
    assert "trajectory 0" in str(err.value)


def test_payload_that_is_not_a_sequence_example(tmp_path):
    write_metadata(tmp_path, metadata_dict())
    write_records(tmp_path / "train.tfrecord", [b"\x0a\x7fnot protobuf"])
    with pytest.raises(DatasetError, match="bad SequenceExample"):
        open_dataset(tmp_path)[0]


def test_inconsistent_particle_counts_in_a_record(tmp_path):
    frames = [np.zeros((4, 2), "<f4"), np.zeros((5, 2), "<f4")]
    example = SequenceExample(
        context={"particle_type": Feature("bytes", (np.full(4, 5, "<i8").tobytes(),))},
        feature_lists={"position": [Feature("bytes", (f.tobytes(),)) for f in frames]},
    )
    write_metadata(tmp_path, metadata_dict())
    (tmp_path / "train.tfrecord").write_bytes(encode_record(serialize_sequence_example(example)))
    with pytest.raises(DatasetError, match=r"inconsistent particle counts.*\[4, 5\]") as err:
        open_dataset(tmp_path)[0]
    assert "trajectory 0" in str(err.value)


def test_particle_type_length_differs_from_positions(tmp_path):
    row = np.empty(2, dtype=object)
    row[0], row[1] = np.zeros((10, 4, 2), np.float32), np.full(3, 5)
    np.savez(tmp_path / "train.npz", a=row, b=row)
    write_metadata(tmp_path, metadata_dict())
    with pytest.raises(DatasetError, match="particle_type has shape") as err:
        open_dataset(tmp_path)[1]
    assert "train.npz: trajectory 1" in str(err.value)


@pytest.mark.parametrize("layout", ["tfrecord", "npz", "h5"])
def test_nan_positions(tmp_path, layout):
    positions = np.full((10, 4, 2), 0.5, np.float32)
    positions[7, 2, 1] = np.nan
    write_metadata(tmp_path, metadata_dict())
    if layout == "tfrecord":
        # Build the record by hand: Trajectory itself refuses NaN.
        example = SequenceExample(
            context={"particle_type": Feature("bytes", (np.full(4, 5, "<i8").tobytes(),))},
            feature_lists={"position": [Feature("bytes", (f.tobytes(),)) for f in positions]},
        )
        (tmp_path / "train.tfrecord").write_bytes(
            encode_record(serialize_sequence_example(example))
        )
    elif layout == "npz":
        row = np.empty(2, dtype=object)
        row[0], row[1] = positions, np.full(4, 5)
        np.savez(tmp_path / "train.npz", t=row)
    else:
        with h5py.File(tmp_path / "train.h5", "w") as f:
            f["00000/positions"] = positions
            f["00000/particle_type"] = np.full(4, 5)
    with pytest.raises(DatasetError, match="non-finite values.*frame 7, particle 2") as err:
        open_dataset(tmp_path)[0]
    assert "trajectory 0" in str(err.value)


class Exploit:
    def __reduce__(self):
        return (print, ("pwned",))


def object_member_bytes(value) -> bytes:
    buffer = io.BytesIO()
    np.lib.format.write_array(buffer, np.array([value, 1], dtype=object), allow_pickle=True)
    return buffer.getvalue()


@pytest.mark.parametrize(
    ("value", "message"),
    [
        (Exploit(), "refusing to unpickle global builtins.print"),
        ({"a": 1}, "unexpected pickled object of type dict"),
        ("text", "unexpected pickled object of type str"),
    ],
)
def test_unknown_pickled_objects_are_refused(tmp_path, capsys, value, message):
    with zipfile.ZipFile(tmp_path / "train.npz", "w") as archive:
        archive.writestr("trajectory0.npy", object_member_bytes(value))
    write_metadata(tmp_path, metadata_dict())
    with pytest.raises(DatasetError, match=message) as err:
        open_dataset(tmp_path)[0]
    assert "train.npz: trajectory 0" in str(err.value)
    assert "pwned" not in capsys.readouterr().out


def test_restricted_unpickler_refuses_numpy_functions_other_than_reconstruct():
    payload = pickle.dumps(np.load, protocol=2)
    with pytest.raises(pickle.UnpicklingError, match="refusing"):
        restricted_loads(payload)
    # ... and accepts what numpy itself writes for arrays and scalars.
    value = restricted_loads(pickle.dumps((np.arange(3.0), np.float64(2.5), np.int32(4))))
    np.testing.assert_array_equal(value[0], [0.0, 1.0, 2.0])
    assert value[1] == 2.5 and value[2] == 4


def test_damaged_zip(tmp_path):
    write_npz(tmp_path / "train.npz", three())
    raw = (tmp_path / "train.npz").read_bytes()
    (tmp_path / "train.npz").write_bytes(raw[: len(raw) // 2])
    write_metadata(tmp_path, metadata_dict())
    with pytest.raises(DatasetError, match="train.npz"):
        open_dataset(tmp_path)


@pytest.mark.parametrize("key", ["bounds", "dt", "dim", "default_connectivity_radius"])
def test_missing_metadata_keys(tmp_path, key):
    raw = metadata_dict()
    del raw[key]
    write_metadata(tmp_path, raw)
    write_npz(tmp_path / "train.npz", three())
    with pytest.raises(DatasetError, match=f"lacks required key.*{key}") as err:
        open_dataset(tmp_path)
    assert "metadata.json" in str(err.value)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"bounds": [[0.9, 0.1], [0.1, 0.9]]}, "not an interval"),
        ({"vel_std": [1.0]}, "vel_std has 1 values for dim 2"),
        ({"dim": 3}, "bounds has 2 pairs for dim 3"),
        ({"dt": "fast"}, "malformed metadata value"),
    ],
)
def test_malformed_metadata(change, message):
    raw = metadata_dict()
    raw.update(change)
    with pytest.raises(DatasetError, match=message):
        Metadata.from_dict(raw, "somewhere/metadata.json")


def test_missing_metadata_file_and_missing_split(tmp_path):
    with pytest.raises(DatasetError, match="neither metadata.json nor manifest.json"):
        open_dataset(tmp_path)
    write_metadata(tmp_path, metadata_dict())
    with pytest.raises(DatasetError, match="no valid.tfrecord"):
        open_dataset(tmp_path, "valid")


def test_dimension_disagreeing_with_metadata(tmp_path):
    write_metadata(tmp_path, metadata_dict(dim=3, bounds=[[0.1, 0.9]] * 3))
    write_npz(tmp_path / "train.npz", three())
    with pytest.raises(DatasetError, match="2 dimensions but metadata says dim 3"):
        open_dataset(tmp_path)[0]


def test_trajectory_rejects_bad_shapes():
    with pytest.raises(ValueError, match=r"positions must be \(T, N, D\)"):
        Trajectory(np.zeros((4, 2), np.float32), np.zeros(4, np.int64))
    with pytest.raises(ValueError, match=r"step_context must be \(T=3, C\)"):
        Trajectory(np.zeros((3, 4, 2)), np.zeros(4, np.int64), np.zeros((2, 1)))
    with pytest.raises(ValueError, match="particle_type must hold integers"):
        Trajectory(np.zeros((3, 4, 2)), np.full(4, 0.5))
