"""TFRecord framing, without TensorFlow.

Each record is `uint64 length | uint32 masked_crc32c(length) | data | uint32 masked_crc32c(data)`
(little endian). Both checksums are verified. `TFRecordFile` indexes record offsets once by
hopping over headers, then reads single records on demand, so a dataset larger than memory
streams from disk.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Iterable, Iterator
from pathlib import Path

from gns.data.crc32c import masked_crc32c
from gns.data.errors import DatasetError
from gns.files import atomic_file

_HEADER = struct.Struct("<QI")
_FOOTER = struct.Struct("<I")


def encode_record(data: bytes) -> bytes:
    """Frame one record: header, payload and payload checksum."""
    length = struct.pack("<Q", len(data))
    return length + _FOOTER.pack(masked_crc32c(length)) + data + _FOOTER.pack(masked_crc32c(data))


class TFRecordFile:
    """Random access to the records of one .tfrecord file.

    Indexing reads 12 bytes per record and verifies the length checksum; `read(i)` reads one
    record and verifies the payload checksum.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.offsets: list[int] = []  # where each payload starts
        self.lengths: list[int] = []
        try:
            size = self.path.stat().st_size
            with open(self.path, "rb") as f:
                pos = 0
                while pos < size:
                    index = len(self.offsets)
                    header = f.read(_HEADER.size)
                    if len(header) < _HEADER.size:
                        raise DatasetError(
                            self.path,
                            f"truncated record header ({len(header)} of 12 bytes at byte {pos})",
                            index,
                        )
                    length, length_crc = _HEADER.unpack(header)
                    if masked_crc32c(header[:8]) != length_crc:
                        raise DatasetError(
                            self.path, f"length checksum mismatch at byte {pos}", index
                        )
                    end = pos + _HEADER.size + length + _FOOTER.size
                    if end > size:
                        raise DatasetError(
                            self.path,
                            f"truncated record: needs {end - pos} bytes, file ends after "
                            f"{size - pos}",
                            index,
                        )
                    self.offsets.append(pos + _HEADER.size)
                    self.lengths.append(length)
                    pos = end
                    f.seek(pos)
        except OSError as err:
            raise DatasetError(self.path, f"cannot read: {err}") from err

    def __len__(self) -> int:
        return len(self.offsets)

    @property
    def nbytes(self) -> int:
        return sum(self.lengths)

    def read(self, index: int) -> bytes:
        """The payload of record `index`, checksum verified."""
        if not 0 <= index < len(self.offsets):
            raise IndexError(f"{self.path}: record {index} out of range ({len(self)} records)")
        length = self.lengths[index]
        with open(self.path, "rb") as f:
            f.seek(self.offsets[index])
            blob = f.read(length + _FOOTER.size)
        if len(blob) != length + _FOOTER.size:
            raise DatasetError(self.path, "file shrank while reading", index)
        data = blob[:length]
        (expected,) = _FOOTER.unpack(blob[length:])
        if masked_crc32c(data) != expected:
            raise DatasetError(self.path, "payload checksum mismatch (damaged record)", index)
        return data

    def __iter__(self) -> Iterator[bytes]:
        for i in range(len(self)):
            yield self.read(i)


def write_records(path: str | os.PathLike[str], records: Iterable[bytes]) -> int:
    """Write framed records atomically; return how many were written."""
    count = 0
    with atomic_file(path) as tmp, open(tmp, "wb") as f:
        for data in records:
            f.write(encode_record(data))
            count += 1
    return count
