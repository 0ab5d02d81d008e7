# Stubs for the Rust extension (rust/python.rs); checked by `python -m mypy.stubtest gns._core`.
from collections.abc import Callable
from typing import Any, final

import numpy as np
import numpy.typing as npt

__all__ = [
    "DEFAULT_MAX_EDGES",
    "Obstacle",
    "RadiusSearcher",
    "euler_step",
    "mpm_simulate",
    "nearest_obstacle_features",
    "obstacle_features",
    "radius_graph",
    "wall_features",
]

DEFAULT_MAX_EDGES: int

def radius_graph(
    positions: npt.NDArray[np.floating[Any]],
    radius: float,
    *,
    n_node: npt.NDArray[np.int64] | None = None,
    self_edges: bool = True,
    box: list[float] | None = None,
    periodic: list[bool] | None = None,
    max_edges: int | None = None,
    method: str = "cells",
    return_shifts: bool = False,
) -> Any: ...

@final
class RadiusSearcher:
    @property
    def num_threads(self) -> int | None: ...
    def __new__(cls, num_threads: int | None = None) -> RadiusSearcher: ...
    def search(
        self,
        positions: npt.NDArray[np.floating[Any]],
        radius: float,
        *,
        n_node: npt.NDArray[np.int64] | None = None,
        self_edges: bool = True,
        box: list[float] | None = None,
        periodic: list[bool] | None = None,
        max_edges: int | None = None,
        method: str = "cells",
        return_shifts: bool = False,
    ) -> Any: ...

def wall_features(
    positions: npt.NDArray[np.floating[Any]],
    bounds: npt.NDArray[np.float64],
    radius: float,
    clip: float = 1.0,
) -> npt.NDArray[np.floating[Any]]: ...

@final
class Obstacle:
    @staticmethod
    def polyline(vertices: npt.NDArray[np.float64], closed: bool = False) -> Obstacle: ...
    @staticmethod
    def cuboid(center: list[float], half_extents: list[float]) -> Obstacle: ...
    @staticmethod
    def trimesh(
        vertices: npt.NDArray[np.float64], triangles: npt.NDArray[np.uint32]
    ) -> Obstacle: ...
    @property
    def dim(self) -> int: ...

def obstacle_features(
    positions: npt.NDArray[np.floating[Any]], obstacles: list[Obstacle], radius: float
) -> npt.NDArray[np.floating[Any]]: ...
def nearest_obstacle_features(
    positions: npt.NDArray[np.floating[Any]],
    obstacles: list[Obstacle],
    radius: float,
    clip: float,
) -> npt.NDArray[np.floating[Any]]: ...
def euler_step(
    position: npt.NDArray[np.floating[Any]],
    velocity: npt.NDArray[np.floating[Any]],
    acceleration: npt.NDArray[np.floating[Any]],
    dt: float = 1.0,
) -> tuple[npt.NDArray[np.floating[Any]], npt.NDArray[np.floating[Any]]]: ...
def mpm_simulate(
    positions: npt.NDArray[np.float64],
    velocities: npt.NDArray[np.float64],
    material: npt.NDArray[np.uint32],
    materials: list[tuple[str, float, list[float]]],
    particle_volume: float,
    frames: int,
    *,
    grid: int,
    bounds: list[list[float]],
    wall: str,
    wall_friction: float,
    gravity: list[float],
    frame_dt: float,
    cfl: float,
    max_substeps: int,
    progress: Callable[[int], object] | None = None,
    threads: Callable[[float], int] | None = None,
    frame_gravity: npt.NDArray[np.floating[Any]] | None = None,
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float64], npt.NDArray[np.uint32]]: ...
