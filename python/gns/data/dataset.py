"""`open_dataset`: detect a dataset's layout and give its trajectories and metadata.

Layouts:
  "deepmind"       folder with metadata.json and {split}.tfrecord
  "npz"            folder with metadata.json and {split}.npz (geoelements, variants A and B)
  "h5"             folder with metadata.json and {split}.h5 whose groups hold `positions`
  "lagrangebench"  folder with metadata.json and {split}.h5 whose groups hold `position`
  "manifest"       folder with manifest.json and one npz per trajectory (no metadata.json)
A path to one data file is also accepted; its split is its file stem and metadata.json is read
from beside it. Trajectories are read from disk when indexed, never all at once.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import Protocol, overload

from gns.data.deepmind import TFRecordSource
from gns.data.errors import DatasetError
from gns.data.h5 import H5Source
from gns.data.manifest import ManifestSource
from gns.data.metadata import (
    DEFAULT_KINEMATIC_TYPES,
    LAGRANGEBENCH_KINEMATIC_TYPES,
    Metadata,
)
from gns.data.npz import NpzSource
from gns.data.trajectory import Trajectory

SPLITS = ("train", "valid", "test")
_SUFFIXES = (".tfrecord", ".npz", ".h5", ".hdf5")


class TrajectorySource(Protocol):
    layout: str

    def __len__(self) -> int: ...

    def read(self, index: int) -> Trajectory: ...

    @property
    def files(self) -> list[Path]: ...


class Dataset(Sequence[Trajectory]):
    """The trajectories of one split plus the dataset's metadata.

    `dataset[i]` reads trajectory i from disk (positions (T, N, D) float32, particle_type (N,)
    int64, ...) and checks it against the metadata's dim.
    """

    def __init__(
        self, path: Path, split: str, metadata: Metadata, source: TrajectorySource
    ) -> None:
        self.path = path
        self.split = split
        self.metadata = metadata
        self.source = source
        self._obstacles = metadata.obstacles(split)

    @property
    def layout(self) -> str:
        return self.source.layout

    @property
    def files(self) -> list[Path]:
        return self.source.files

    def __len__(self) -> int:
        return len(self.source)

    @overload
    def __getitem__(self, index: int) -> Trajectory: ...

    @overload
    def __getitem__(self, index: slice) -> list[Trajectory]: ...

    def __getitem__(self, index: int | slice) -> Trajectory | list[Trajectory]:
        if isinstance(index, slice):
            return [self[i] for i in range(*index.indices(len(self)))]
        if index < 0:
            index += len(self)
        if not 0 <= index < len(self):
            raise IndexError(f"trajectory {index} out of range ({len(self)} in {self.split})")
        trajectory = self.source.read(index)
        if trajectory.dim != self.metadata.dim:
            raise DatasetError(
                trajectory.source,
                f"positions have {trajectory.dim} dimensions but metadata says dim "
                f"{self.metadata.dim}",
                index,
            )
        if self._obstacles is not None:
            if trajectory.key not in self._obstacles:
                raise DatasetError(
                    trajectory.source,
                    f"metadata.json's obstacles have no entry for trajectory key "
                    f"{trajectory.key} of the {self.split} split",
                    index,
                )
            trajectory = dataclasses.replace(trajectory, obstacles=self._obstacles[trajectory.key])
        return trajectory

    def __iter__(self) -> Iterator[Trajectory]:
        for i in range(len(self)):
            yield self[i]

    def __repr__(self) -> str:
        return (
            f"Dataset({str(self.path)!r}, split={self.split!r}, layout={self.layout!r}, "
            f"trajectories={len(self)})"
        )


def _split_file(folder: Path, split: str) -> Path | None:
    for suffix in _SUFFIXES:
        candidate = folder / f"{split}{suffix}"
        if candidate.is_file():
            return candidate
    return None


def available_splits(path: str | os.PathLike[str]) -> list[str]:
    """The splits present at `path` (a dataset folder or one data file)."""
    p = Path(path)
    if p.is_file():
        return [p.stem]
    if (p / "metadata.json").is_file():
        return [s for s in SPLITS if _split_file(p, s) is not None]
    if (p / "manifest.json").is_file():
        return list(SPLITS)
    return []


def _open_source(data_file: Path, dim: int) -> TrajectorySource:
    suffix = data_file.suffix.lower()
    if suffix == ".tfrecord":
        return TFRecordSource(data_file, dim)
    if suffix == ".npz":
        return NpzSource(data_file)
    if suffix in (".h5", ".hdf5"):
        return H5Source(data_file)
    raise DatasetError(data_file, f"unknown data file type {suffix!r}")


def open_dataset(
    path: str | os.PathLike[str],
    split: str = "train",
    *,
    kinematic_particle_types: Iterable[int] | None = None,
) -> Dataset:
    """Open one split of the dataset at `path`, whatever its layout.

    kinematic_particle_types overrides the dataset's setting (metadata key
    `kinematic_particle_types`, else {1, 2, -1} for LagrangeBench and {3} otherwise).
    """
    p = Path(path)
    if not p.exists():
        raise DatasetError(p, "no such file or folder")
    data_file: Path | None
    if p.is_file():
        folder, data_file, split = p.parent, p, p.stem
    elif (p / "metadata.json").is_file():
        folder, data_file = p, _split_file(p, split)
    elif (p / "manifest.json").is_file():
        manifest = ManifestSource(p, split)
        metadata = manifest.metadata()
        if kinematic_particle_types is not None:
            metadata = metadata.replace(
                kinematic_particle_types=frozenset(int(t) for t in kinematic_particle_types)
            )
        return Dataset(p, split, metadata, manifest)
    else:
        raise DatasetError(p, "neither metadata.json nor manifest.json found")

    if data_file is None:
        raise DatasetError(p, f"no {split}.tfrecord, {split}.npz or {split}.h5 here")
    metadata_path = folder / "metadata.json"
    metadata = Metadata.from_json(metadata_path, split=split)
    source = _open_source(data_file, metadata.dim)
    if kinematic_particle_types is not None:
        kinematic = frozenset(int(t) for t in kinematic_particle_types)
    elif "kinematic_particle_types" in _raw_keys(metadata_path):
        kinematic = metadata.kinematic_particle_types
    elif source.layout == "lagrangebench":
        kinematic = LAGRANGEBENCH_KINEMATIC_TYPES
    else:
        kinematic = DEFAULT_KINEMATIC_TYPES
    metadata = metadata.replace(kinematic_particle_types=kinematic)
    return Dataset(p, split, metadata, source)


def _raw_keys(metadata_path: Path) -> set[str]:
    with open(metadata_path, encoding="utf-8") as f:
        return set(json.load(f))
