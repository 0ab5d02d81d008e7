"""geoelements npz files, read without letting a pickle run code.

Variant A: one member per trajectory, each a pickled object array holding
(positions, particle_type[, material_property]); trajectory order = member order.
Variant B: one member `gns_data`, an object array (n_traj, 2 or 3) of the same tuples.
Per-trajectory files (one member `trajectory0`) are variant A with one trajectory.

Members are read with zipfile and the .npy header parsed by numpy.lib.format; an object member's
pickle goes through `RestrictedUnpickler`, which can build numpy arrays, dtypes and numpy scalars
and nothing else, so a hostile file cannot import or call anything. np.load(allow_pickle=True)
is never used.
"""

from __future__ import annotations

import io
import os
import pickle
import zipfile
import zlib
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from gns.data.errors import DatasetError
from gns.data.trajectory import Trajectory
from gns.files import atomic_file

# The callables numpy's own pickles name, taken from live objects so both numpy 1.x
# (numpy.core.multiarray) and 2.x (numpy._core.multiarray) resolve without importing either.
_RECONSTRUCT = np.empty(0).__reduce__()[0]
_SCALAR = np.float64(0).__reduce__()[0]
_ALLOWED: dict[tuple[str, str], Any] = {
    ("numpy.core.multiarray", "_reconstruct"): _RECONSTRUCT,
    ("numpy._core.multiarray", "_reconstruct"): _RECONSTRUCT,
    ("numpy.core.multiarray", "scalar"): _SCALAR,
    ("numpy._core.multiarray", "scalar"): _SCALAR,
    ("numpy", "ndarray"): np.ndarray,
    ("numpy", "dtype"): np.dtype,
}


class RestrictedUnpickler(pickle.Unpickler):
    """Unpickles numpy arrays, dtypes, numpy scalars, tuples, lists and plain numbers only."""

    def find_class(self, module: str, name: str) -> Any:
        try:
            return _ALLOWED[(module, name)]
        except KeyError:
            raise pickle.UnpicklingError(
                f"refusing to unpickle global {module}.{name}: only numpy arrays are allowed"
            ) from None

    def persistent_load(self, pid: Any) -> Any:
        raise pickle.UnpicklingError("refusing persistent ids")


def restricted_loads(data: bytes) -> Any:
    """Unpickle `data` with `RestrictedUnpickler` and check the result holds only arrays."""
    value = RestrictedUnpickler(io.BytesIO(data)).load()
    _check_plain(value)
    return value


def _check_plain(value: Any, depth: int = 0) -> None:
    if depth > 8:
        raise pickle.UnpicklingError("objects nested too deeply")
    if isinstance(value, np.ndarray):
        if value.dtype.hasobject:
            if value.dtype != np.dtype(object):
                raise pickle.UnpicklingError("structured arrays with objects are not allowed")
            for item in value.flat:
                _check_plain(item, depth + 1)
    elif isinstance(value, (tuple, list)):
        for item in value:
            _check_plain(item, depth + 1)
    elif isinstance(value, np.generic):
        if value.dtype.hasobject:
            raise pickle.UnpicklingError("object scalars are not allowed")
    elif not isinstance(value, (bool, int, float)):
        raise pickle.UnpicklingError(f"unexpected pickled object of type {type(value).__name__}")


def read_member(archive: zipfile.ZipFile, name: str) -> Any:
    """One .npy member: a plain array, or the restricted unpickling of an object array."""
    with archive.open(name) as f:
        version = np.lib.format.read_magic(f)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(f)
        elif version in ((2, 0), (3, 0)):
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(f)
        else:
            raise ValueError(f"unsupported .npy version {version}")
        payload = f.read()
    if dtype.hasobject:
        value = restricted_loads(payload)
        if not isinstance(value, np.ndarray) or value.shape != tuple(shape):
            raise ValueError(f"pickled member does not match its header shape {shape}")
        return value
    count = int(np.prod(shape, dtype=np.int64))
    if len(payload) < count * dtype.itemsize:
        raise ValueError(f"member {name} is truncated")
    array = np.frombuffer(payload, dtype, count)
    return array.reshape(shape, order="F" if fortran else "C")


def _items(value: Any) -> list[Any]:
    """The (positions, particle_type[, material_property]) items of one stored trajectory."""
    if isinstance(value, np.ndarray) and value.dtype == object:
        if value.ndim == 0:
            value = value.item()
        elif value.ndim == 1:
            return list(value)
    if isinstance(value, (tuple, list)):
        return list(value)
    raise ValueError(f"expected a (positions, particle_type[, material]) tuple, got {type(value)}")


def _to_trajectory(value: Any, source: str, index: int) -> Trajectory:
    try:
        items = _items(value)
    except ValueError as err:
        raise DatasetError(source, str(err), index) from err
    if len(items) not in (2, 3):
        raise DatasetError(
            source,
            f"expected 2 or 3 items (positions, particle_type[, material]), got {len(items)}",
            index,
        )
    positions, types = np.asarray(items[0]), np.asarray(items[1])
    material = np.asarray(items[2]) if len(items) == 3 else None
    return Trajectory(positions, types, None, material, key=index, source=source)


class NpzSource:
    """Trajectories of one geoelements npz file; variant A members are read on demand."""

    layout = "npz"

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        try:
            with zipfile.ZipFile(self.path) as archive:
                self.members = [n for n in archive.namelist() if n.endswith(".npy")]
                if not self.members:
                    raise DatasetError(self.path, "npz holds no arrays")
                self._rows: list[Any] | None = None
                if self.members == ["gns_data.npy"]:
                    table = self._load(archive, "gns_data.npy", None)
                    if not (isinstance(table, np.ndarray) and table.ndim == 2):
                        raise DatasetError(self.path, "gns_data must be an (n_traj, 2|3) array")
                    self._rows = list(table)
        except (zipfile.BadZipFile, OSError) as err:
            raise DatasetError(self.path, f"not a readable npz file: {err}") from err

    def _load(self, archive: zipfile.ZipFile, member: str, index: int | None) -> Any:
        try:
            return read_member(archive, member)
        except (pickle.UnpicklingError, ValueError, EOFError, TypeError) as err:
            raise DatasetError(self.path, f"member {member}: {err}", index) from err
        except (zipfile.BadZipFile, OSError, zlib.error) as err:
            # zlib.error: a damaged compressed member (it is no OSError or ValueError).
            raise DatasetError(self.path, f"member {member} is damaged: {err}", index) from err

    def __len__(self) -> int:
        return len(self._rows) if self._rows is not None else len(self.members)

    def read(self, index: int) -> Trajectory:
        if not 0 <= index < len(self):
            raise IndexError(f"{self.path}: trajectory {index} out of range ({len(self)})")
        if self._rows is not None:
            return _to_trajectory(self._rows[index], str(self.path), index)
        try:
            with zipfile.ZipFile(self.path) as archive:
                value = self._load(archive, self.members[index], index)
        except (zipfile.BadZipFile, OSError) as err:
            raise DatasetError(self.path, f"not a readable npz file: {err}", index) from err
        return _to_trajectory(value, str(self.path), index)

    @property
    def files(self) -> list[Path]:
        return [self.path]


def _material_of(trajectory: Trajectory) -> np.ndarray | None:
    if trajectory.material_property is not None:
        return trajectory.material_property
    context = trajectory.step_context
    if context is None:
        return None
    # geoelements has no per-frame context; a constant scalar context is its material property.
    if context.shape[1] == 1 and np.all(context == context[0]):
        return context[0, 0].reshape(())
    raise DatasetError(
        trajectory.source,
        "the npz layout cannot hold a per-frame step_context; convert to deepmind or h5",
        trajectory.key,
    )


def write_npz(
    path: str | os.PathLike[str],
    trajectories: Iterable[Trajectory],
    *,
    variant: str = "A",
    compress: bool = True,
) -> int:
    """Write a geoelements npz (variant "A" or "B") atomically; returns the trajectory count."""
    if variant not in ("A", "B"):
        raise ValueError(f"variant must be 'A' or 'B', got {variant!r}")
    rows: list[np.ndarray] = []
    for trajectory in trajectories:
        material = _material_of(trajectory)
        items = [trajectory.positions, trajectory.particle_type]
        if material is not None:
            items.append(material)
        row = np.empty(len(items), dtype=object)
        for i, item in enumerate(items):  # element-wise: numpy would try to broadcast them
            row[i] = item
        rows.append(row)
    if variant == "B":
        widths = {len(r) for r in rows}
        if len(widths) > 1:
            raise ValueError("variant B needs every trajectory to have a material or none")
        table = np.empty((len(rows), widths.pop() if widths else 2), dtype=object)
        for i, row in enumerate(rows):
            for j, item in enumerate(row):
                table[i, j] = item
        members = {"gns_data": table}
    else:
        members = {f"trajectory{i}": row for i, row in enumerate(rows)}
    mode = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    with atomic_file(path) as tmp, zipfile.ZipFile(tmp, "w", mode, allowZip64=True) as archive:
        for name, array in members.items():
            with archive.open(f"{name}.npy", "w", force_zip64=True) as f:
                np.lib.format.write_array(f, array, allow_pickle=True)
    return len(rows)
