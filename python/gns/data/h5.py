"""HDF5 layouts: LagrangeBench and geoelements' h5 variant (which is also what we write).

Both hold one group per trajectory ("00000", "00001", ...):
LagrangeBench: `position` (T, N, D), `particle_type` (N,).
geoelements / ours: `positions` (T, N, D), `particle_type` (N,), optional `material_property`
(scalar or (N,)) and, ours only, optional `step_context` (T, C).
Groups are read on demand, so a large file is never loaded whole.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

import h5py  # type: ignore[import-untyped]

from gns.data.errors import DatasetError
from gns.data.trajectory import Trajectory
from gns.files import atomic_file

# What h5py raises for a damaged file: OSError mostly, but a damaged object header can come
# out as KeyError ("Unable to synchronously open object") or RuntimeError. Keys are checked
# before they are read, so a KeyError here is damage, not a missing member.
H5_DAMAGE = (OSError, KeyError, RuntimeError)


def _group_order(name: str) -> tuple[int, int | str]:
    return (0, int(name)) if name.isdigit() else (1, name)


class H5Source:
    """Trajectories of one .h5 file; `layout` is "lagrangebench" or "h5"."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        try:
            with h5py.File(self.path, "r") as f:
                self.groups = sorted(
                    (k for k, v in f.items() if isinstance(v, h5py.Group)), key=_group_order
                )
                if not self.groups:
                    raise DatasetError(self.path, "h5 file holds no trajectory groups")
                first = f[self.groups[0]]
                if "position" in first:
                    self.layout, self._positions = "lagrangebench", "position"
                elif "positions" in first:
                    self.layout, self._positions = "h5", "positions"
                else:
                    raise DatasetError(
                        self.path, "group holds neither 'position' nor 'positions'", self.groups[0]
                    )
        except H5_DAMAGE as err:
            raise DatasetError(self.path, f"not a readable HDF5 file: {err}") from err

    def __len__(self) -> int:
        return len(self.groups)

    def read(self, index: int) -> Trajectory:
        if not 0 <= index < len(self):
            raise IndexError(f"{self.path}: trajectory {index} out of range ({len(self)})")
        name = self.groups[index]
        try:
            with h5py.File(self.path, "r") as f:
                group = f[name]
                missing = [k for k in (self._positions, "particle_type") if k not in group]
                if missing:
                    raise DatasetError(self.path, f"group {name} lacks {', '.join(missing)}", index)
                positions = group[self._positions][()]
                types = group["particle_type"][()]
                material = group["material_property"][()] if "material_property" in group else None
                context = group["step_context"][()] if "step_context" in group else None
        except H5_DAMAGE as err:
            raise DatasetError(self.path, f"group {name} is damaged: {err}", index) from err
        return Trajectory(positions, types, context, material, key=index, source=str(self.path))

    @property
    def files(self) -> list[Path]:
        return [self.path]


def write_h5(
    path: str | os.PathLike[str],
    trajectories: Iterable[Trajectory],
    *,
    layout: str = "h5",
) -> int:
    """Write trajectories atomically as `layout` "h5" (ours) or "lagrangebench"; returns count.

    LagrangeBench has no place for step_context or material_property; they are refused there
    rather than dropped.
    """
    if layout not in ("h5", "lagrangebench"):
        raise ValueError(f"layout must be 'h5' or 'lagrangebench', got {layout!r}")
    count = 0
    with atomic_file(path) as tmp, h5py.File(tmp, "w") as f:
        for count, trajectory in enumerate(trajectories, start=1):
            group = f.create_group(f"{count - 1:05d}")
            if layout == "lagrangebench":
                if trajectory.step_context is not None or trajectory.material_property is not None:
                    raise DatasetError(
                        trajectory.source,
                        "LagrangeBench h5 cannot hold step_context or material_property",
                        trajectory.key,
                    )
                group.create_dataset("position", data=trajectory.positions)
            else:
                group.create_dataset("positions", data=trajectory.positions)
                if trajectory.material_property is not None:
                    group.create_dataset("material_property", data=trajectory.material_property)
                if trajectory.step_context is not None:
                    group.create_dataset("step_context", data=trajectory.step_context)
            group.create_dataset("particle_type", data=trajectory.particle_type)
    return count
