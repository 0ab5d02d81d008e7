"""Synthetic trajectories and dataset folders shared by the tests/test_data_*.py files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from gns.data import Trajectory

SAND = Path(__file__).resolve().parents[2] / "shared/data/sand2d-taichi"


def random_walk(
    rng: np.random.Generator,
    frames: int,
    particles: int,
    dim: int = 2,
    kinematic: int = 0,
    context: int = 0,
    material: str | None = None,
    key: int = 0,
) -> Trajectory:
    """Particles drifting under 'gravity' inside [0.1, 0.9]^dim; the last `kinematic` are type 3."""
    start = rng.uniform(0.3, 0.7, size=(1, particles, dim))
    steps = rng.normal(0.0, 1e-3, size=(frames, particles, dim))
    steps[..., -1] -= 1e-4 * np.arange(frames)[:, None]
    positions = np.clip(start + np.cumsum(steps, axis=0), 0.1, 0.9).astype(np.float32)
    types = np.full(particles, 5, dtype=np.int64)
    if kinematic:
        types[-kinematic:] = 3
        positions[:, -kinematic:] = positions[0, -kinematic:]
    step_context = None
    if context:
        step_context = rng.normal(size=(frames, context)).astype(np.float32)
    material_property = None
    if material == "scalar":
        material_property = np.float32(rng.uniform(0.3, 0.9))
    elif material == "particle":
        material_property = rng.uniform(0.3, 0.9, size=particles).astype(np.float32)
    return Trajectory(positions, types, step_context, material_property, key=key)


def metadata_dict(dim: int = 2, sequence_length: int = 9, **extra: object) -> dict:
    out: dict = {
        "bounds": [[0.1, 0.9]] * dim,
        "sequence_length": sequence_length,
        "default_connectivity_radius": 0.015,
        "dim": dim,
        "dt": 0.0025,
    }
    out.update(extra)
    return out


def write_metadata(folder: Path, raw: dict) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "metadata.json").write_text(json.dumps(raw))


def assert_same(a: Trajectory, b: Trajectory) -> None:
    """Exact equality of every array, dtypes included."""
    assert a.positions.dtype == b.positions.dtype == np.float32
    assert a.particle_type.dtype == b.particle_type.dtype == np.int64
    np.testing.assert_array_equal(a.positions, b.positions)
    np.testing.assert_array_equal(a.particle_type, b.particle_type)
    for name in ("step_context", "material_property"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            assert x.dtype == y.dtype
            np.testing.assert_array_equal(x, y)
