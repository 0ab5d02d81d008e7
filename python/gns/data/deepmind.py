"""The DeepMind learning_to_simulate layout: one SequenceExample per TFRecord record.

context `key` (int64) and `particle_type` (raw little-endian int64 bytes); feature_lists
`position` (T steps of raw float32 (N, D) bytes) and optional `step_context` (T steps of float32
(C,) bytes). The reader needs `dim` from metadata.json to shape positions.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from gns.data.errors import DatasetError
from gns.data.protobuf import (
    Feature,
    ProtobufError,
    SequenceExample,
    parse_sequence_example,
    serialize_sequence_example,
)
from gns.data.tfrecord import TFRecordFile, write_records
from gns.data.trajectory import Trajectory


def _single_bytes(feature: Feature, name: str) -> bytes:
    if feature.kind != "bytes" or len(feature.values) != 1:
        raise ProtobufError(f"{name} must be a bytes_list with one value")
    value = feature.values[0]
    assert isinstance(value, bytes)
    return value


def decode_trajectory(data: bytes, dim: int, source: str, index: int) -> Trajectory:
    """Trajectory from one serialized SequenceExample; positions reshaped to (T, N, dim)."""
    try:
        example = parse_sequence_example(data)
        if "particle_type" not in example.context:
            raise ProtobufError("context lacks particle_type")
        if "position" not in example.feature_lists:
            raise ProtobufError("feature_lists lack position")
        raw_types = _single_bytes(example.context["particle_type"], "particle_type")
        if len(raw_types) % 8:
            raise ProtobufError(f"particle_type has {len(raw_types)} bytes, not int64s")
        types = np.frombuffer(raw_types, "<i8")
        key_feature = example.context.get("key")
        if key_feature is not None and (
            key_feature.kind != "int64" or len(key_feature.values) != 1
        ):
            raise ProtobufError("key must be an int64_list with one value")
        steps = example.feature_lists["position"]
        frames = [_single_bytes(f, "position") for f in steps]
        context = None
        if "step_context" in example.feature_lists:
            context_steps = example.feature_lists["step_context"]
            raw_context = [_single_bytes(f, "step_context") for f in context_steps]
            if len({len(c) for c in raw_context}) > 1:
                raise ProtobufError("step_context steps differ in length")
            context = np.frombuffer(b"".join(raw_context), "<f4").reshape(len(raw_context), -1)
    except ProtobufError as err:
        raise DatasetError(source, f"bad SequenceExample: {err}", index) from err

    sizes = {len(f) for f in frames}
    if not frames:
        raise DatasetError(source, "position has no steps", index)
    if len(sizes) != 1:
        counts = sorted({s // (4 * dim) for s in sizes})
        raise DatasetError(source, f"inconsistent particle counts across frames: {counts}", index)
    frame_bytes = sizes.pop()
    if frame_bytes % (4 * dim):
        raise DatasetError(
            source, f"a position frame of {frame_bytes} bytes is not float32 (N, {dim})", index
        )
    n = frame_bytes // (4 * dim)
    if n != types.size:
        raise DatasetError(
            source, f"position frames hold {n} particles but particle_type has {types.size}", index
        )
    positions = np.frombuffer(b"".join(frames), "<f4").reshape(len(frames), n, dim)
    if context is not None and context.shape[0] != positions.shape[0]:
        raise DatasetError(
            source,
            f"step_context has {context.shape[0]} steps but position has {positions.shape[0]}",
            index,
        )
    # The record index, not the stored key, names the trajectory: it is what a user can seek to.
    return Trajectory(positions, types, context, None, key=index, source=source)


def encode_trajectory(trajectory: Trajectory, key: int) -> bytes:
    """Serialized SequenceExample of one trajectory (float32 / int64 little endian)."""
    example = SequenceExample(
        context={
            "key": Feature("int64", np.array([key], dtype=np.int64)),
            "particle_type": Feature("bytes", (trajectory.particle_type.astype("<i8").tobytes(),)),
        },
        feature_lists={
            "position": [
                Feature("bytes", (frame.astype("<f4").tobytes(),)) for frame in trajectory.positions
            ]
        },
    )
    if trajectory.step_context is not None:
        example.feature_lists["step_context"] = [
            Feature("bytes", (step.astype("<f4").tobytes(),)) for step in trajectory.step_context
        ]
    return serialize_sequence_example(example)


class TFRecordSource:
    """Trajectories of one .tfrecord file, read record by record."""

    layout = "deepmind"

    def __init__(self, path: str | os.PathLike[str], dim: int) -> None:
        self.path = Path(path)
        self.dim = dim
        self.records = TFRecordFile(path)

    def __len__(self) -> int:
        return len(self.records)

    def read(self, index: int) -> Trajectory:
        return decode_trajectory(self.records.read(index), self.dim, str(self.path), index)

    @property
    def files(self) -> list[Path]:
        return [self.path]


def write_tfrecord(path: str | os.PathLike[str], trajectories: Iterable[Trajectory]) -> int:
    """Write trajectories as DeepMind records (atomically); returns how many were written."""
    return write_records(path, (encode_trajectory(t, i) for i, t in enumerate(trajectories)))
