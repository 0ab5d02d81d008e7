"""Particle frames as VTK files for ParaView, written here (no vtk dependency).

    write_series(folder, "prediction", positions, dt=0.0025, point_data={"particle_type": t})

writes folder/prediction_000000.vtp ... (one XML PolyData file per frame: the particles as
points with one vertex cell each, so ParaView draws them without a glyph filter) and
folder/prediction.pvd, the time-series index ParaView opens as one animated dataset. The files
are ASCII: larger than binary ones, but readable by anything that parses XML, which is what a
check of them needs. 2D positions get z = 0 (VTK points are always 3D).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from gns.files import write_bytes_atomic

__all__ = ["write_pvd", "write_series", "write_vtp"]

# VTK's names for the numpy kinds written here.
_VTK_TYPES = {"i": "Int32", "u": "Int32", "b": "Int32", "f": "Float32"}


def _points3(positions: np.ndarray) -> np.ndarray:
    points = np.asarray(positions, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] not in (1, 2, 3):
        raise ValueError(f"positions must be (N, D) with D in 1..3, got {points.shape}")
    if not np.isfinite(points).all():
        raise ValueError("positions hold NaN or Inf; VTK frames must be finite")
    return np.pad(points, ((0, 0), (0, 3 - points.shape[1])))


def _numbers(values: np.ndarray) -> str:
    if values.dtype.kind == "f":
        return " ".join(f"{v:.7g}" for v in values.ravel())
    return " ".join(str(int(v)) for v in values.ravel())


def _data_array(name: str, values: np.ndarray, n: int) -> str:
    array = np.asarray(values)
    if array.shape[:1] != (n,) or array.ndim > 2:
        raise ValueError(f"point data {name!r} must be ({n},) or ({n}, K), got {array.shape}")
    if array.dtype.kind not in _VTK_TYPES:
        raise ValueError(f"point data {name!r} must be numbers, got {array.dtype}")
    components = 1 if array.ndim == 1 else array.shape[1]
    return (
        f'<DataArray type="{_VTK_TYPES[array.dtype.kind]}" Name={quoteattr(name)} '
        f'NumberOfComponents="{components}" format="ascii">{_numbers(array)}</DataArray>'
    )


def write_vtp(
    path: str | os.PathLike[str],
    positions: np.ndarray,
    point_data: Mapping[str, np.ndarray] | None = None,
) -> None:
    """One frame, positions (N, D), as a VTK XML PolyData file (atomically). point_data: arrays
    (N,) or (N, K) of numbers shown as colourable fields in ParaView."""
    points = _points3(positions)
    n = points.shape[0]
    arrays = "".join(_data_array(k, v, n) for k, v in (point_data or {}).items())
    text = (
        '<?xml version="1.0"?>\n'
        '<VTKFile type="PolyData" version="0.1" byte_order="LittleEndian">\n'
        "<PolyData>\n"
        f'<Piece NumberOfPoints="{n}" NumberOfVerts="{n}" NumberOfLines="0" '
        'NumberOfStrips="0" NumberOfPolys="0">\n'
        f"<PointData>{arrays}</PointData>\n"
        '<Points><DataArray type="Float32" NumberOfComponents="3" format="ascii">'
        f"{_numbers(points)}</DataArray></Points>\n"
        "<Verts>"
        f'<DataArray type="Int64" Name="connectivity" format="ascii">{_numbers(np.arange(n))}'
        "</DataArray>"
        f'<DataArray type="Int64" Name="offsets" format="ascii">{_numbers(np.arange(1, n + 1))}'
        "</DataArray>"
        "</Verts>\n"
        "</Piece>\n"
        "</PolyData>\n"
        "</VTKFile>\n"
    )
    write_bytes_atomic(path, text.encode("ascii"))


def write_pvd(
    path: str | os.PathLike[str], files: list[str], times: list[float] | np.ndarray
) -> None:
    """The ParaView collection file of a time series: `files` (relative to path's folder) at
    `times` (physical seconds)."""
    if len(files) != len(times):
        raise ValueError(f"{len(files)} files but {len(times)} times")
    entries = "".join(
        f'<DataSet timestep="{float(t):.9g}" part="0" file={quoteattr(f)}/>\n'
        for f, t in zip(files, times, strict=True)
    )
    text = (
        '<?xml version="1.0"?>\n'
        '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">\n'
        f"<Collection>\n{entries}</Collection>\n"
        "</VTKFile>\n"
    )
    write_bytes_atomic(path, text.encode("ascii"))


def write_series(
    folder: str | os.PathLike[str],
    name: str,
    positions: np.ndarray,
    *,
    dt: float = 1.0,
    first_frame: int = 0,
    every: int = 1,
    point_data: Mapping[str, np.ndarray] | None = None,
    frame_data: Mapping[str, np.ndarray] | None = None,
) -> Path:
    """Frames 0, every, 2 every, ... of positions (T, N, D) as folder/{name}_{frame:06d}.vtp
    plus folder/{name}.pvd; returns the .pvd path. Frame numbers and times count from
    `first_frame` (time = frame * dt), so a prediction and its ground truth line up in ParaView.
    point_data: arrays (N,) or (N, K), the same in every frame (e.g. the particle type);
    frame_data: arrays (T, N) or (T, N, K), one slice per frame (e.g. an error)."""
    frames = np.asarray(positions)
    if frames.ndim != 3:
        raise ValueError(f"positions must be (T, N, D), got {frames.shape}")
    if isinstance(every, bool) or not isinstance(every, int) or every < 1:
        raise ValueError(f"every must be a positive integer, got {every!r}")
    per_frame = {key: np.asarray(value) for key, value in (frame_data or {}).items()}
    for key, value in per_frame.items():
        if value.shape[:2] != frames.shape[:2]:
            raise ValueError(
                f"frame data {key!r} must be (T, N, ...) = {frames.shape[:2]}, got {value.shape}"
            )
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    files, times = [], []
    for t in range(0, frames.shape[0], every):
        frame = first_frame + t
        data = dict(point_data or {})
        data.update({key: value[t] for key, value in per_frame.items()})
        file = f"{name}_{frame:06d}.vtp"
        write_vtp(folder / file, frames[t], data)
        files.append(file)
        times.append(frame * dt)
    pvd = folder / f"{name}.pvd"
    write_pvd(pvd, files, times)
    return pvd
