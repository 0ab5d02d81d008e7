"""Atomic writes: build a file (or folder) under a temporary name, then rename it into place.

A crash or an exception part way leaves the target untouched and removes the temporary, so users
never find a half-written dataset, checkpoint, rollout or report. `claim_folder` makes a folder
the one of a resumable run (gns generate, gns demo), its record written atomically.
"""

from __future__ import annotations

import contextlib
import functools
import json
import os
import shutil
import tempfile
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

__all__ = [
    "atomic_file",
    "atomic_folder",
    "claim_folder",
    "write_bytes_atomic",
    "write_json_atomic",
]


@functools.cache
def _umask() -> int:
    """The process's umask, read once: reading it means setting it, which is not safe while
    other threads create files."""
    umask = os.umask(0)
    os.umask(umask)
    return umask


@contextlib.contextmanager
def atomic_file(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path beside `path`; on success it replaces `path`."""
    target = Path(path)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    # mkstemp makes the file private (0600); the finished one gets the usual permissions.
    tmp.chmod(0o666 & ~_umask())
    try:
        yield tmp
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


@contextlib.contextmanager
def atomic_folder(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary folder beside `path`; on success it is renamed to `path`.

    `path` must not exist or be an empty folder (rename only replaces empty folders).
    """
    target = Path(path)
    if target.exists() and (not target.is_dir() or any(target.iterdir())):
        raise FileExistsError(f"{target}: exists and is not an empty folder")
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent))
    # mkdtemp makes the folder private (0700); the finished one gets the usual permissions.
    tmp.chmod(0o777 & ~_umask())
    try:
        yield tmp
        os.replace(tmp, target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def write_bytes_atomic(path: str | os.PathLike[str], payload: bytes) -> None:
    with atomic_file(path) as tmp:
        tmp.write_bytes(payload)


def write_json_atomic(path: str | os.PathLike[str], payload: Mapping[str, Any]) -> None:
    write_bytes_atomic(path, (json.dumps(payload, indent=1) + "\n").encode("utf-8"))


def claim_folder(
    folder: Path,
    record_name: str,
    arguments: Mapping[str, Any],
    *,
    holds: str,
    resume: str,
    foreign: str,
) -> None:
    """Make `folder` the folder of a resumable run made with `arguments`: one whose record
    (folder/record_name) holds the same arguments is reused; one recording other arguments
    ("{folder} holds {holds} with other arguments ...; {resume}") or holding anything else
    ("{folder} {foreign}") is refused with ValueError; a missing or empty one is created and
    the arguments recorded, atomically."""
    record = folder / record_name
    if record.is_file():
        stored = json.loads(record.read_text(encoding="utf-8"))
        if stored != dict(arguments):
            diff = {k: (stored.get(k), v) for k, v in arguments.items() if stored.get(k) != v}
            raise ValueError(
                f"{folder} holds {holds} with other arguments (name: (theirs, yours)) {diff}; "
                f"{resume}"
            )
        return
    if folder.exists() and any(folder.iterdir()):
        raise ValueError(f"{folder} {foreign}")
    folder.mkdir(parents=True, exist_ok=True)
    write_json_atomic(record, arguments)
