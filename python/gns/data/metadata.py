"""`Metadata`: the facts of a dataset (metadata.json), checked on load.

Readers of other projects' metadata keep keys they do not know in `extra` and write them back, so
converting a dataset loses nothing; only the keys gns relies on are interpreted and checked.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from gns.data.errors import DatasetError
from gns.data.trajectory import polyline_problem
from gns.files import write_json_atomic
from gns.periodic import period_of

DEFAULT_KINEMATIC_TYPES = frozenset({3})
LAGRANGEBENCH_KINEMATIC_TYPES = frozenset({1, 2, -1})

STATISTICS_KEYS = ("vel_mean", "vel_std", "acc_mean", "acc_std")
_REQUIRED = ("bounds", "dim", "default_connectivity_radius", "dt")
_KNOWN = (
    *_REQUIRED,
    "sequence_length",
    *STATISTICS_KEYS,
    "context_mean",
    "context_std",
    "kinematic_particle_types",
    "periodic_boundary_conditions",
    "material_feature_len",
    "boundary_augment",
)


@dataclass(frozen=True)
class Metadata:
    """Dataset facts. Statistics are per frame (never divided by dt), one value per axis.

    bounds: D pairs (lo, hi). sequence_length: transitions per trajectory (trajectories hold
    sequence_length + 1 frames). dt: physical seconds per frame (the model works with dt = 1).
    kinematic_particle_types: types that get no noise, no loss and ground truth in rollouts.
    periodic_boundary_conditions: one flag per axis.
    """

    bounds: tuple[tuple[float, float], ...]
    sequence_length: int
    default_connectivity_radius: float
    dim: int
    dt: float
    vel_mean: tuple[float, ...] | None = None
    vel_std: tuple[float, ...] | None = None
    acc_mean: tuple[float, ...] | None = None
    acc_std: tuple[float, ...] | None = None
    context_mean: tuple[float, ...] | None = None
    context_std: tuple[float, ...] | None = None
    kinematic_particle_types: frozenset[int] = DEFAULT_KINEMATIC_TYPES
    periodic_boundary_conditions: tuple[bool, ...] = ()
    material_feature_len: int = 0
    boundary_augment: float = 1.0
    extra: Mapping[str, Any] = field(default_factory=dict)
    source: str = "<memory>"

    def __post_init__(self) -> None:
        def fail(problem: str) -> DatasetError:
            return DatasetError(self.source, problem)

        if self.dim not in (1, 2, 3):
            raise fail(f"dim must be 1, 2 or 3, got {self.dim}")
        if len(self.bounds) != self.dim:
            raise fail(f"bounds has {len(self.bounds)} pairs for dim {self.dim}")
        for axis, (lo, hi) in enumerate(self.bounds):
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                raise fail(f"bounds[{axis}] = [{lo}, {hi}] is not an interval lo < hi")
        if not (self.default_connectivity_radius > 0 and math.isfinite(self.dt) and self.dt > 0):
            raise fail(
                "default_connectivity_radius and dt must be positive, got "
                f"{self.default_connectivity_radius} and {self.dt}"
            )
        if self.sequence_length < 1:
            raise fail(f"sequence_length must be at least 1, got {self.sequence_length}")
        for name in STATISTICS_KEYS:
            values = getattr(self, name)
            if values is not None:
                if len(values) != self.dim:
                    raise fail(f"{name} has {len(values)} values for dim {self.dim}")
                if not all(math.isfinite(v) for v in values):
                    raise fail(f"{name} holds non-finite values {list(values)}")
                if name.endswith("_std") and any(v < 0 for v in values):
                    raise fail(f"{name} holds negative values {list(values)}")
        if (self.context_mean is None) != (self.context_std is None):
            raise fail("context_mean and context_std must be given together")
        if self.context_mean is not None and len(self.context_mean) != len(self.context_std or ()):
            raise fail("context_mean and context_std differ in length")
        if not self.periodic_boundary_conditions:
            object.__setattr__(self, "periodic_boundary_conditions", (False,) * self.dim)
        elif len(self.periodic_boundary_conditions) != self.dim:
            raise fail(
                f"periodic_boundary_conditions has {len(self.periodic_boundary_conditions)} "
                f"flags for dim {self.dim}"
            )

    # ------------------------------------------------------------------ loading and saving

    @classmethod
    def from_dict(
        cls,
        raw: Mapping[str, Any],
        source: str | os.PathLike[str] = "<memory>",
        *,
        split: str = "train",
        default_kinematic: frozenset[int] = DEFAULT_KINEMATIC_TYPES,
    ) -> Metadata:
        """Interpret a metadata.json dict; missing or malformed keys raise DatasetError."""
        src = os.fspath(source)

        def fail(problem: str) -> DatasetError:
            return DatasetError(src, problem)

        missing = [k for k in _REQUIRED if k not in raw]
        # LagrangeBench counts steps per split instead of one sequence_length.
        lb_key = "sequence_length_train" if split == "train" else "sequence_length_test"
        if "sequence_length" not in raw and lb_key not in raw:
            missing.append("sequence_length")
        if missing:
            raise fail(f"metadata lacks required key(s) {', '.join(missing)}")

        def floats(name: str) -> tuple[float, ...] | None:
            value = raw.get(name)
            if value is None:
                return None
            try:
                return tuple(float(v) for v in _as_list(value))
            except (TypeError, ValueError) as err:
                raise fail(f"{name} must be a list of numbers, got {value!r}") from err

        try:
            bounds = tuple((float(lo), float(hi)) for lo, hi in raw["bounds"])
            dim = int(raw["dim"])
            radius = float(raw["default_connectivity_radius"])
            dt = float(raw["dt"])
            sequence_length = int(raw.get("sequence_length", raw.get(lb_key)))
            kinematic = frozenset(
                int(v) for v in raw.get("kinematic_particle_types", default_kinematic)
            )
            periodic = tuple(bool(v) for v in raw.get("periodic_boundary_conditions", ()))
            material_len = int(raw.get("material_feature_len", 0))
            augment = float(raw.get("boundary_augment", 1.0))
        except (TypeError, ValueError) as err:
            raise fail(f"malformed metadata value: {err}") from err
        extra = {k: v for k, v in raw.items() if k not in _KNOWN}
        return cls(
            bounds=bounds,
            sequence_length=sequence_length,
            default_connectivity_radius=radius,
            dim=dim,
            dt=dt,
            vel_mean=floats("vel_mean"),
            vel_std=floats("vel_std"),
            acc_mean=floats("acc_mean"),
            acc_std=floats("acc_std"),
            context_mean=floats("context_mean"),
            context_std=floats("context_std"),
            kinematic_particle_types=kinematic,
            periodic_boundary_conditions=periodic,
            material_feature_len=material_len,
            boundary_augment=augment,
            extra=extra,
            source=src,
        )

    @classmethod
    def from_json(
        cls,
        path: str | os.PathLike[str],
        *,
        split: str = "train",
        default_kinematic: frozenset[int] = DEFAULT_KINEMATIC_TYPES,
    ) -> Metadata:
        """Read and check a metadata.json file."""
        try:
            with open(path, encoding="utf-8") as f:
                raw = json.load(f)
        except FileNotFoundError as err:
            raise DatasetError(path, "metadata.json not found") from err
        except json.JSONDecodeError as err:
            raise DatasetError(path, f"not valid JSON: {err}") from err
        if not isinstance(raw, dict):
            raise DatasetError(path, "metadata.json must hold a JSON object")
        return cls.from_dict(raw, path, split=split, default_kinematic=default_kinematic)

    def to_dict(self) -> dict[str, Any]:
        """The metadata.json dict: DeepMind's keys first, then ours, then the kept extras."""
        out: dict[str, Any] = {
            "bounds": [list(pair) for pair in self.bounds],
            "sequence_length": self.sequence_length,
            "default_connectivity_radius": self.default_connectivity_radius,
            "dim": self.dim,
            "dt": self.dt,
        }
        for name in (*STATISTICS_KEYS, "context_mean", "context_std"):
            value = getattr(self, name)
            if value is not None:
                out[name] = list(value)
        out["kinematic_particle_types"] = sorted(self.kinematic_particle_types)
        if any(self.periodic_boundary_conditions):
            out["periodic_boundary_conditions"] = list(self.periodic_boundary_conditions)
        if self.material_feature_len:
            out["material_feature_len"] = self.material_feature_len
        if self.boundary_augment != 1.0:
            out["boundary_augment"] = self.boundary_augment
        for key, value in self.extra.items():
            out.setdefault(key, value)
        return out

    def write_json(self, path: str | os.PathLike[str]) -> None:
        """Write metadata.json atomically."""
        write_json_atomic(path, self.to_dict())

    @property
    def period(self) -> Any:
        """(D,) the box length on each periodic axis, 0 on the others, or None without
        periodic axes (gns.periodic): what differences of positions wrap by."""
        return period_of(self.bounds, self.periodic_boundary_conditions)

    @property
    def has_obstacles(self) -> bool:
        """metadata.json has an "obstacles" entry (static shapes per trajectory)."""
        return "obstacles" in self.extra

    def obstacles(self, split: str) -> dict[int, tuple[np.ndarray, ...]] | None:
        """The static obstacle shapes of each trajectory of `split`, by trajectory key: polylines
        as (K, dim) float64 vertex arrays, K >= 2. None when the metadata has no "obstacles";
        a split it has no entry for has none ({}). The layout, written by `gns generate`:

            "obstacles": {"train": {"0": [{"polyline": [[x, y], [x, y], ...]}, ...], ...}, ...}
        """
        if not self.has_obstacles:
            return None
        entry = self.extra["obstacles"]

        def fail(problem: str) -> DatasetError:
            return DatasetError(self.source, f"metadata's obstacles: {problem}")

        if not isinstance(entry, Mapping):
            raise fail(f"expected {{split: {{key: [shapes]}}}}, got {type(entry).__name__}")
        per_key = entry.get(split, {})
        if not isinstance(per_key, Mapping):
            raise fail(f"{split!r} must map trajectory keys to shape lists")
        out: dict[int, tuple[np.ndarray, ...]] = {}
        for key, shapes in per_key.items():
            try:
                index = int(key)
            except ValueError as err:
                raise fail(f"{split!r} has the key {key!r}; expected a trajectory key") from err
            if not isinstance(shapes, list):
                raise fail(f"{split!r} trajectory {key}: expected a list of shapes")
            polylines = []
            for k, shape in enumerate(shapes):
                if not (isinstance(shape, Mapping) and set(shape) == {"polyline"}):
                    raise fail(
                        f"{split!r} trajectory {key} shape {k} is {shape!r}; expected "
                        '{"polyline": [[x, y], ...]}'
                    )
                try:
                    vertices = np.asarray(shape["polyline"], dtype=np.float64)
                except (TypeError, ValueError) as err:
                    raise fail(f"{split!r} trajectory {key} shape {k}: {err}") from err
                problem = polyline_problem(vertices, self.dim)
                if problem is not None:
                    raise fail(f"{split!r} trajectory {key} shape {k} {problem}")
                polylines.append(vertices)
            out[index] = tuple(polylines)
        return out

    @property
    def has_statistics(self) -> bool:
        return all(getattr(self, name) is not None for name in STATISTICS_KEYS)

    def replace(self, **changes: Any) -> Metadata:
        return dataclasses.replace(self, **changes)


def obstacles_json(polylines: Sequence[Any]) -> list[dict[str, Any]]:
    """One trajectory's entry in metadata.json's "obstacles": each polyline's vertices."""
    return [{"polyline": np.asarray(v, dtype=np.float64).tolist()} for v in polylines]


def _as_list(value: Any) -> Sequence[Any]:
    return list(value) if isinstance(value, (list, tuple)) else [value]
