"""Just enough of the protobuf wire format to read and write a tf.train.SequenceExample.

    SequenceExample { Features context = 1; FeatureLists feature_lists = 2; }
    Features        { map<string, Feature> feature = 1; }
    FeatureLists    { map<string, FeatureList> feature_list = 1; }
    FeatureList     { repeated Feature feature = 1; }
    Feature         { oneof { BytesList bytes_list = 1; FloatList float_list = 2;
                              Int64List int64_list = 3; } }

A map field is a repeated message { key = 1; value = 2; }. Unknown fields are skipped, as protobuf
requires, so files written by newer TensorFlow versions still parse. Malformed input raises
`ProtobufError` (a ValueError); the caller adds the file and record.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

_VARINT, _FIXED64, _LENGTH, _FIXED32 = 0, 1, 2, 5

FeatureKind = Literal["bytes", "float", "int64"]


class ProtobufError(ValueError):
    """The bytes are not a well-formed SequenceExample."""


@dataclass(frozen=True)
class Feature:
    """One tf.train.Feature: a list of bytes strings, float32 values or int64 values."""

    kind: FeatureKind
    values: tuple[bytes, ...] | np.ndarray


@dataclass
class SequenceExample:
    """context: name -> Feature; feature_lists: name -> one Feature per step."""

    context: dict[str, Feature] = field(default_factory=dict)
    feature_lists: dict[str, list[Feature]] = field(default_factory=dict)


# ----------------------------------------------------------------------------- reading


def _varint(buf: bytes, pos: int, end: int) -> tuple[int, int]:
    result = 0
    shift = 0
    while True:
        if pos >= end:
            raise ProtobufError("truncated varint")
        byte = buf[pos]
        pos += 1
        result |= (byte & 0x7F) << shift
        if not byte & 0x80:
            return result, pos
        shift += 7
        if shift >= 70:
            raise ProtobufError("varint longer than 10 bytes")


def _fields(buf: bytes, pos: int, end: int) -> Iterator[tuple[int, int, int, int]]:
    """Yield (field number, wire type, start, stop); for varints start is the value itself."""
    while pos < end:
        key, pos = _varint(buf, pos, end)
        number, wire = key >> 3, key & 7
        if number == 0:
            raise ProtobufError("field number 0")
        if wire == _VARINT:
            value, pos = _varint(buf, pos, end)
            yield number, wire, value, pos
        elif wire == _LENGTH:
            length, pos = _varint(buf, pos, end)
            stop = pos + length
            if stop > end:
                raise ProtobufError(f"field {number} runs {stop - end} bytes past its message")
            yield number, wire, pos, stop
            pos = stop
        elif wire in (_FIXED32, _FIXED64):
            stop = pos + (4 if wire == _FIXED32 else 8)
            if stop > end:
                raise ProtobufError(f"field {number} truncated")
            yield number, wire, pos, stop
            pos = stop
        else:
            raise ProtobufError(f"unsupported wire type {wire} for field {number}")
    if pos != end:
        raise ProtobufError("message overruns its length")


def _to_int64(value: int) -> int:
    return value - (1 << 64) if value >= 1 << 63 else value


def _parse_feature(buf: bytes, start: int, end: int) -> Feature:
    feature: Feature | None = None
    for number, wire, a, b in _fields(buf, start, end):
        if wire != _LENGTH or number not in (1, 2, 3):
            continue
        if number == 1:
            items = [
                bytes(buf[s:e]) for n, w, s, e in _fields(buf, a, b) if n == 1 and w == _LENGTH
            ]
            feature = Feature("bytes", tuple(items))
        elif number == 2:
            chunks: list[np.ndarray] = []
            for n, w, s, e in _fields(buf, a, b):
                if n != 1:
                    continue
                if w == _LENGTH:  # packed
                    if (e - s) % 4:
                        raise ProtobufError("packed float list length is not a multiple of 4")
                    chunks.append(np.frombuffer(buf, "<f4", (e - s) // 4, s))
                elif w == _FIXED32:
                    chunks.append(np.frombuffer(buf, "<f4", 1, s))
                else:
                    raise ProtobufError(f"float list value has wire type {w}")
            values = np.concatenate(chunks) if chunks else np.zeros(0, np.float32)
            feature = Feature("float", values.astype(np.float32))
        else:
            ints: list[int] = []
            for n, w, s, e in _fields(buf, a, b):
                if n != 1:
                    continue
                if w == _VARINT:
                    ints.append(_to_int64(s))
                elif w == _LENGTH:  # packed
                    pos = s
                    while pos < e:
                        value, pos = _varint(buf, pos, e)
                        ints.append(_to_int64(value))
                else:
                    raise ProtobufError(f"int64 list value has wire type {w}")
            feature = Feature("int64", np.array(ints, dtype=np.int64))
    if feature is None:
        raise ProtobufError("Feature holds no bytes_list, float_list or int64_list")
    return feature


def _map_entries(buf: bytes, start: int, end: int) -> Iterator[tuple[str, int, int]]:
    """Yield (key, value start, value stop) of the entries of map field 1."""
    for number, wire, a, b in _fields(buf, start, end):
        if number != 1 or wire != _LENGTH:
            continue
        key: str | None = None
        value = (b, b)  # an absent value is an empty message
        for n, w, s, e in _fields(buf, a, b):
            if n == 1 and w == _LENGTH:
                try:
                    key = bytes(buf[s:e]).decode("utf-8")
                except UnicodeDecodeError as err:
                    raise ProtobufError("map key is not UTF-8") from err
            elif n == 2 and w == _LENGTH:
                value = (s, e)
        if key is None:
            raise ProtobufError("map entry without a key")
        yield key, value[0], value[1]


def parse_sequence_example(data: bytes) -> SequenceExample:
    """Parse a serialized tf.train.SequenceExample."""
    buf = bytes(data)
    example = SequenceExample()
    for number, wire, a, b in _fields(buf, 0, len(buf)):
        if wire != _LENGTH:
            continue
        if number == 1:
            for key, s, e in _map_entries(buf, a, b):
                example.context[key] = _parse_feature(buf, s, e)
        elif number == 2:
            for key, s, e in _map_entries(buf, a, b):
                steps = [
                    _parse_feature(buf, fs, fe)
                    for n, w, fs, fe in _fields(buf, s, e)
                    if n == 1 and w == _LENGTH
                ]
                example.feature_lists[key] = steps
    return example


# ----------------------------------------------------------------------------- writing


def _encode_varint(value: int) -> bytes:
    if value < 0:
        value += 1 << 64
    out = bytearray()
    while True:
        bits = value & 0x7F
        value >>= 7
        if value:
            out.append(bits | 0x80)
        else:
            out.append(bits)
            return bytes(out)


def _length_field(number: int, payload: bytes) -> bytes:
    return _encode_varint(number << 3 | _LENGTH) + _encode_varint(len(payload)) + payload


def _encode_feature(feature: Feature) -> bytes:
    if feature.kind == "bytes":
        body = b"".join(_length_field(1, bytes(v)) for v in feature.values)
        return _length_field(1, body)
    if feature.kind == "float":
        raw = np.ascontiguousarray(feature.values, dtype="<f4").tobytes()
        return _length_field(2, _length_field(1, raw) if raw else b"")
    if feature.kind == "int64":
        ints = np.asarray(feature.values, dtype=np.int64)
        packed = b"".join(_encode_varint(int(v)) for v in ints)
        return _length_field(3, _length_field(1, packed) if packed else b"")
    raise ProtobufError(f"unknown feature kind {feature.kind!r}")


def _encode_map(entries: Iterator[tuple[str, bytes]]) -> bytes:
    return b"".join(
        _length_field(1, _length_field(1, key.encode("utf-8")) + _length_field(2, value))
        for key, value in entries
    )


def serialize_sequence_example(example: SequenceExample) -> bytes:
    """Serialize to the wire format; map entries are written in sorted key order."""
    context = _encode_map(
        (key, _encode_feature(example.context[key])) for key in sorted(example.context)
    )
    lists = _encode_map(
        (key, b"".join(_length_field(1, _encode_feature(f)) for f in example.feature_lists[key]))
        for key in sorted(example.feature_lists)
    )
    return _length_field(1, context) + _length_field(2, lists)
