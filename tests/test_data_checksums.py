"""CRC32C and the protobuf wire format, against published vectors and hand-made bytes."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from gns.data.crc32c import crc32c, masked_crc32c
from gns.data.protobuf import (
    Feature,
    ProtobufError,
    SequenceExample,
    parse_sequence_example,
    serialize_sequence_example,
)
from hypothesis import given, settings
from hypothesis import strategies as st


def bitwise_crc32c(data: bytes) -> int:
    """The textbook bit-at-a-time definition: an oracle sharing no table with the fast path."""
    crc = 0xFFFFFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ (0x82F63B78 if crc & 1 else 0)
    return crc ^ 0xFFFFFFFF


def test_standard_check_value():
    assert crc32c(b"123456789") == 0xE3069283


@pytest.mark.parametrize(
    ("data", "expected"),
    [  # RFC 3720 (iSCSI) appendix B.4
        (bytes(32), 0x8A9136AA),
        (b"\xff" * 32, 0x62A8AB43),
        (bytes(range(32)), 0x46DD794E),
        (bytes(range(31, -1, -1)), 0x113FDB5C),
    ],
)
def test_iscsi_vectors(data, expected):
    assert crc32c(data) == expected


@pytest.mark.parametrize("size", [0, 1, 511, 512, 513, 4095, 65537, 200_003])
def test_fast_path_matches_bitwise_definition(size):
    data = np.random.default_rng(size).integers(0, 256, size, dtype=np.uint8).tobytes()
    if size > 70_000:  # the bitwise oracle is slow; check a prefix and the continuation law
        head = data[:70_000]
        assert crc32c(head) == bitwise_crc32c(head)
        assert crc32c(data[70_000:], crc32c(head)) == crc32c(data)
    else:
        assert crc32c(data) == bitwise_crc32c(data)


@settings(max_examples=60, deadline=None)
@given(st.binary(max_size=3000), st.integers(0, 3000))
def test_continuation_equals_whole(data, cut):
    cut = min(cut, len(data))
    assert crc32c(data[cut:], crc32c(data[:cut])) == crc32c(data)


def test_masked_crc_of_empty_payload():
    # crc32c(b"") = 0, so the mask leaves only its constant.
    assert masked_crc32c(b"") == 0xA282EAD8


def test_crc_accepts_numpy_and_memoryview():
    array = np.arange(1000, dtype=np.float32)
    assert crc32c(array) == crc32c(array.tobytes()) == crc32c(memoryview(array.tobytes()))


# ------------------------------------------------------------------ protobuf


def ld(number: int, payload: bytes) -> bytes:
    """Length-delimited field; payloads in these tests stay below 128 bytes (1-byte lengths)."""
    assert len(payload) < 128
    return bytes([number << 3 | 2, len(payload)]) + payload


def test_parse_hand_made_sequence_example():
    # Unpacked int64 and float values, an unknown field (number 9, varint) and a negative int.
    int_list = b"\x08\x07" + b"\x08" + b"\xff" * 9 + b"\x01"  # values 7, -1 (unpacked varints)
    float_list = b"\x0d" + struct.pack("<f", 1.5) + b"\x0d" + struct.pack("<f", -2.0)
    key_feature = ld(3, int_list)
    types_feature = ld(1, ld(1, np.array([6, 3], "<i8").tobytes()))
    context = ld(1, ld(1, b"key") + ld(2, key_feature)) + ld(
        1, ld(1, b"particle_type") + ld(2, types_feature)
    )
    frame = ld(1, ld(1, np.array([0.25, 0.5], "<f4").tobytes()))
    flist = ld(1, ld(1, b"position") + ld(2, ld(1, frame) + ld(1, frame)))
    flist += ld(1, ld(1, b"ctx") + ld(2, ld(1, ld(2, float_list))))
    data = ld(1, context) + b"\x48\x05" + ld(2, flist)

    example = parse_sequence_example(data)
    assert example.context["key"].kind == "int64"
    assert example.context["key"].values.tolist() == [7, -1]
    assert example.context["particle_type"].values == (np.array([6, 3], "<i8").tobytes(),)
    assert len(example.feature_lists["position"]) == 2
    ctx = example.feature_lists["ctx"][0]
    assert ctx.kind == "float" and ctx.values.tolist() == [1.5, -2.0]


def test_serialize_parse_round_trip():
    example = SequenceExample(
        context={
            "key": Feature("int64", np.array([3, -(2**63), 2**63 - 1], dtype=np.int64)),
            "blob": Feature("bytes", (b"", b"\x00\x01" * 200)),
        },
        feature_lists={
            "f": [Feature("float", np.array([0.1, np.inf, -0.0], np.float32)) for _ in range(3)],
            "empty": [],
        },
    )
    back = parse_sequence_example(serialize_sequence_example(example))
    np.testing.assert_array_equal(back.context["key"].values, example.context["key"].values)
    assert back.context["blob"].values == example.context["blob"].values
    assert len(back.feature_lists["f"]) == 3
    np.testing.assert_array_equal(
        back.feature_lists["f"][2].values, np.array([0.1, np.inf, -0.0], np.float32)
    )
    assert back.feature_lists["empty"] == []


@pytest.mark.parametrize(
    "data",
    [
        b"\x0a\x05\x0a\x03",  # length runs past the end
        b"\x0a",  # truncated length varint
        b"\x0b\x00",  # wire type 3 (groups) is not supported
        b"\x00\x00",  # field number 0
    ],
)
def test_malformed_bytes_raise(data):
    with pytest.raises(ProtobufError):
        parse_sequence_example(data)
