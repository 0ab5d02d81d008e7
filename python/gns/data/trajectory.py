"""`Trajectory`: one simulated trajectory, checked on construction."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gns.data.errors import DatasetError


@dataclass(frozen=True, eq=False)
class Trajectory:
    """One trajectory of T frames of N particles in D dimensions.

    positions: (T, N, D) float32, T = sequence_length + 1 frames.
    particle_type: (N,) int64.
    step_context: (T, C) float32 global features per frame, or None.
    material_property: () or (N,) float32 (geoelements' per-trajectory material feature), or None.
    key: the trajectory's index in its split; source: the file it came from.
    obstacles: static obstacle shapes, polylines as (K, D) vertex arrays (metadata.json's
        "obstacles", attached by gns.data.Dataset), or None.

    Construction converts dtypes and rejects wrong shapes, inconsistent particle counts and
    non-finite values with a DatasetError naming `source` and `key`.
    """

    positions: np.ndarray
    particle_type: np.ndarray
    step_context: np.ndarray | None = None
    material_property: np.ndarray | None = None
    key: int = 0
    source: str = "<memory>"
    obstacles: tuple[np.ndarray, ...] | None = None

    def __post_init__(self) -> None:
        def fail(problem: str) -> DatasetError:
            return DatasetError(self.source, problem, self.key)

        positions = np.asarray(self.positions)
        if positions.ndim != 3:
            raise fail(f"positions must be (T, N, D), got shape {positions.shape}")
        if not np.issubdtype(positions.dtype, np.floating):
            raise fail(f"positions must be floating point, got {positions.dtype}")
        t, n, d = positions.shape
        if t < 1 or n < 1 or d not in (1, 2, 3):
            raise fail(f"positions have an unusable shape {positions.shape}")
        positions = np.ascontiguousarray(positions, dtype=np.float32)
        if not np.isfinite(positions).all():
            bad = np.argwhere(~np.isfinite(positions))[0]
            raise fail(
                f"positions hold non-finite values (first at frame {bad[0]}, particle {bad[1]})"
            )

        types = np.asarray(self.particle_type)
        if types.ndim == 0:
            types = np.full(n, types)
        if types.ndim != 1 or types.shape[0] != n:
            raise fail(f"particle_type has shape {types.shape} but positions have {n} particles")
        if not np.issubdtype(types.dtype, np.integer):
            if not (np.isfinite(types).all() and np.array_equal(types, np.round(types))):
                raise fail(f"particle_type must hold integers, got {types.dtype} values")
        types = np.ascontiguousarray(types, dtype=np.int64)

        context = self.step_context
        if context is not None:
            context = np.asarray(context)
            if context.ndim == 1:
                context = context[:, None]
            if context.ndim != 2 or context.shape[0] != t:
                raise fail(f"step_context must be (T={t}, C), got shape {context.shape}")
            context = np.ascontiguousarray(context, dtype=np.float32)
            if not np.isfinite(context).all():
                raise fail("step_context holds non-finite values")

        material = self.material_property
        if material is not None:
            material = np.asarray(material)
            if material.shape not in ((), (1,), (n,)):
                raise fail(f"material_property must be a scalar or ({n},), got {material.shape}")
            if material.shape == (1,) and n != 1:
                material = material.reshape(())
            material = np.array(material, dtype=np.float32, order="C")  # keeps 0-d shape
            if not np.isfinite(material).all():
                raise fail("material_property holds non-finite values")

        if self.obstacles is not None:
            polylines = tuple(np.asarray(v, dtype=np.float64) for v in self.obstacles)
            for k, v in enumerate(polylines):
                problem = polyline_problem(v, d)
                if problem is not None:
                    raise fail(f"obstacle {k} {problem}")
            object.__setattr__(self, "obstacles", polylines)

        object.__setattr__(self, "positions", positions)
        object.__setattr__(self, "particle_type", types)
        object.__setattr__(self, "step_context", context)
        object.__setattr__(self, "material_property", material)
        object.__setattr__(self, "key", int(self.key))

    @property
    def num_frames(self) -> int:
        """T = sequence_length + 1."""
        return int(self.positions.shape[0])

    @property
    def n_particles(self) -> int:
        return int(self.positions.shape[1])

    @property
    def dim(self) -> int:
        return int(self.positions.shape[2])

    @property
    def nbytes(self) -> int:
        """Bytes of array payload (what a reader had to decode)."""
        total = self.positions.nbytes + self.particle_type.nbytes
        for extra in (self.step_context, self.material_property):
            if extra is not None:
                total += extra.nbytes
        return total


def polyline_problem(vertices: np.ndarray, dim: int) -> str | None:
    """What is wrong with an obstacle polyline's vertices (K >= 2 finite points of `dim`
    coordinates), or None: the one check of Trajectory.obstacles and metadata.json's."""
    if vertices.ndim != 2 or vertices.shape[0] < 2 or vertices.shape[1] != dim:
        return f"has vertices of shape {vertices.shape}; expected (K >= 2, {dim})"
    if not np.isfinite(vertices).all():
        return "has non-finite vertices"
    return None
