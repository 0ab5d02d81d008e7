"""The one door to the Rust core: numpy or torch in, the same kind out.

Dtype and contiguity are fixed here, once, so the core can be strict: float32 and float64 pass
through unchanged, integer (and float16) positions are widened to float64 exactly, anything else
is rejected. Torch tensors are accepted and the results come back as tensors on the same device.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from gns import _core

__all__ = [
    "Obstacle",
    "RadiusSearcher",
    "euler_step",
    "nearest_obstacle_features",
    "obstacle_features",
    "radius_graph",
    "wall_features",
]

DEFAULT_MAX_EDGES: int = _core.DEFAULT_MAX_EDGES
_METHODS = ("cells", "kdtree", "brute")


def _is_torch(x: Any) -> bool:
    return type(x).__module__.startswith("torch") and hasattr(x, "detach")


def _to_numpy(x: Any) -> np.ndarray:
    if _is_torch(x):
        return x.detach().cpu().numpy()
    return np.asarray(x)


def _like(result: Any, template: Any) -> Any:
    """Returns numpy results as tensors on the template's device when it is a tensor."""
    if not _is_torch(template):
        return result
    import torch

    if isinstance(result, tuple):
        return tuple(_like(r, template) for r in result)
    return torch.from_numpy(result).to(template.device)


def _floats(name: str, x: Any, dtype: np.dtype | None = None) -> np.ndarray:
    """A C-contiguous 2-D float32/float64 array; widens integers exactly, rejects the rest."""
    a = _to_numpy(x)
    if a.ndim != 2:
        raise ValueError(f"{name} must be a 2-D array (N, D), got shape {a.shape}")
    if dtype is not None:
        if a.dtype != dtype:
            raise ValueError(f"{name} must have dtype {dtype} like the positions, got {a.dtype}")
    elif a.dtype not in (np.float32, np.float64):
        if a.dtype.kind in "iub" or a.dtype == np.float16:
            a = a.astype(np.float64)
        else:
            raise ValueError(f"{name} must hold real numbers (float32 or float64), got {a.dtype}")
    return np.ascontiguousarray(a)


def _n_node(n_node: Any) -> np.ndarray | None:
    if n_node is None:
        return None
    a = _to_numpy(n_node)
    if a.ndim == 1 and a.size == 0:
        a = a.astype(np.int64)  # np.asarray([]) is float64; no graphs is valid for N = 0
    if a.ndim != 1 or a.dtype.kind not in "iu":
        raise ValueError(f"n_node must be a 1-D array of integers, got {a.dtype} shape {a.shape}")
    return np.ascontiguousarray(a, dtype=np.int64)


def _box(box: Any, dim: int) -> list[float] | None:
    if box is None:
        return None
    b = np.asarray(_to_numpy(box), dtype=np.float64)
    if b.shape != (dim,):
        raise ValueError(f"box must hold one length per axis, shape ({dim},), got {b.shape}")
    return [float(v) for v in b]


def _periodic(periodic: Any, dim: int) -> list[bool] | None:
    if periodic is None:
        return None
    if isinstance(periodic, (bool, np.bool_)):
        return [bool(periodic)] * dim
    p = list(periodic)
    if len(p) != dim or not all(isinstance(v, (bool, np.bool_)) for v in p):
        raise ValueError(f"periodic must be a bool or {dim} bools (one per axis), got {periodic!r}")
    return [bool(v) for v in p]


def _max_edges(max_edges: Any) -> int | None:
    if max_edges is None:
        return None
    if isinstance(max_edges, bool) or int(max_edges) != max_edges or max_edges < 0:
        raise ValueError(f"max_edges must be a whole number >= 0, got {max_edges!r}")
    return int(max_edges)


def _graph_args(
    positions: Any,
    radius: float,
    n_node: Any,
    box: Any,
    periodic: Any,
    max_edges: Any,
    method: str,
) -> tuple[np.ndarray, dict[str, Any]]:
    x = _floats("positions", positions)
    if method not in _METHODS:
        raise ValueError(f"method must be one of {_METHODS}, got {method!r}")
    kwargs = dict(
        n_node=_n_node(n_node),
        box=_box(box, x.shape[1]),
        periodic=_periodic(periodic, x.shape[1]),
        max_edges=_max_edges(max_edges),
        method=method,
    )
    return x, kwargs


def radius_graph(
    positions: Any,
    radius: float,
    *,
    n_node: Any = None,
    self_edges: bool = True,
    box: Any = None,
    periodic: Any = None,
    max_edges: int | None = None,
    method: str = "cells",
    return_shifts: bool = False,
) -> Any:
    """Every directed pair (sender j, receiver i) of the same graph with |x_j - x_i| <= radius.

    positions: (N, D) with D in {2, 3}, float32 or float64 (numpy or torch).
    n_node: (G,) graph sizes summing to N (rows in order); no edge crosses graphs.
    self_edges: include i -> i (decided by index; coincident particles are always neighbours).
    box, periodic: (D,) box lengths and per-axis periodic flags (minimum image; a periodic axis
        must be at least 2 * radius long).
    max_edges: raise, naming the count, instead of building more edges (default 2**28).
    method: "cells", "kdtree" or "brute"; all give identical results.
    Returns int64 edges (2, E), row 0 senders, row 1 receivers, sorted by (receiver, sender);
    with return_shifts also int32 shifts (E, D) such that the minimum-image displacement is
    positions[senders] - positions[receivers] + shifts * box.
    """
    x, kwargs = _graph_args(positions, radius, n_node, box, periodic, max_edges, method)
    out = _core.radius_graph(
        x, float(radius), self_edges=bool(self_edges), return_shifts=bool(return_shifts), **kwargs
    )
    return _like(out, positions)


class RadiusSearcher:
    """A radius-graph searcher that reuses its buffers between calls (one per thread of use).

    num_threads: None for the shared pool (RAYON_NUM_THREADS or all cores), else its own pool.
    """

    def __init__(self, num_threads: int | None = None) -> None:
        if num_threads is not None and (
            isinstance(num_threads, bool) or int(num_threads) != num_threads or num_threads < 1
        ):
            raise ValueError(
                f"num_threads must be a whole number >= 1 or None, got {num_threads!r}"
            )
        self._inner = _core.RadiusSearcher(None if num_threads is None else int(num_threads))

    @property
    def num_threads(self) -> int | None:
        return self._inner.num_threads

    def __reduce__(self) -> tuple[Any, ...]:
        # The buffers are a cache, and the core's searcher cannot be pickled: a copy (pickle,
        # copy.deepcopy, e.g. of a LearnedSimulator holding one) starts with empty ones.
        return (RadiusSearcher, (self.num_threads,))

    def __call__(
        self,
        positions: Any,
        radius: float,
        *,
        n_node: Any = None,
        self_edges: bool = True,
        box: Any = None,
        periodic: Any = None,
        max_edges: int | None = None,
        method: str = "cells",
        return_shifts: bool = False,
    ) -> Any:
        """Same arguments and result as radius_graph."""
        x, kwargs = _graph_args(positions, radius, n_node, box, periodic, max_edges, method)
        out = self._inner.search(
            x,
            float(radius),
            self_edges=bool(self_edges),
            return_shifts=bool(return_shifts),
            **kwargs,
        )
        return _like(out, positions)


def _coords(name: str, values: Any, dim: int | None = None, rows: str = "K") -> np.ndarray:
    """Shape coordinates as a C-contiguous float64 (rows, dim) array; exact for ints and float32."""
    a = np.asarray(_to_numpy(values))
    if a.dtype.kind not in "iuf":
        raise ValueError(f"{name} must hold real numbers, got {a.dtype}")
    if a.ndim != 2 or (dim is not None and a.shape[1] != dim):
        want = f"({rows}, {dim if dim is not None else 'D'})"
        raise ValueError(f"{name} must have shape {want}, got {a.shape}")
    return np.ascontiguousarray(a, dtype=np.float64)


class Obstacle:
    """A static obstacle for obstacle_features (a parry shape), built by the constructors below."""

    def __init__(self, core: _core.Obstacle) -> None:
        self._core = core

    @property
    def dim(self) -> int:
        return self._core.dim

    def __repr__(self) -> str:
        return repr(self._core)

    @staticmethod
    def polyline(vertices: Any, closed: bool = False) -> Obstacle:
        """A 2D polyline through vertices (K, 2); closed=True joins the last vertex to the first."""
        return Obstacle(_core.Obstacle.polyline(_coords("vertices", vertices, 2), bool(closed)))

    @staticmethod
    def cuboid(center: Any, half_extents: Any) -> Obstacle:
        """An axis-aligned box (2D or 3D) from its centre and half extents."""
        c = _coords("center", np.reshape(_to_numpy(center), (1, -1)))
        h = _coords("half_extents", np.reshape(_to_numpy(half_extents), (1, -1)))
        return Obstacle(_core.Obstacle.cuboid(c[0].tolist(), h[0].tolist()))

    @staticmethod
    def trimesh(vertices: Any, triangles: Any) -> Obstacle:
        """A 3D triangle mesh: vertices (V, 3), triangles (T, 3) of vertex indices."""
        v = _coords("vertices", vertices, 3, rows="V")
        t = np.asarray(_to_numpy(triangles))
        if t.ndim != 2 or t.shape[1] != 3 or t.dtype.kind not in "iu":
            raise ValueError(f"triangles must be integers of shape (T, 3), got {t.dtype} {t.shape}")
        if t.size and t.min() < 0:
            raise ValueError(f"triangles refer to vertex {t.min()}; indices must be >= 0")
        return Obstacle(_core.Obstacle.trimesh(v, np.ascontiguousarray(t, dtype=np.uint32)))


def wall_features(positions: Any, bounds: Any, radius: float, *, clip: float = 1.0) -> Any:
    """Distances to the lower then the upper bounds, / radius, clipped to [-clip, clip].

    positions: (N, D); bounds: (D, 2) [lower, upper] per axis. Returns (N, 2 D), the paper's
    layout, in the positions' dtype.
    """
    x = _floats("positions", positions)
    b = _coords("bounds", bounds, 2)
    return _like(_core.wall_features(x, b, float(radius), float(clip)), positions)


def obstacle_features(positions: Any, obstacles: Sequence[Obstacle], radius: float) -> Any:
    """For each obstacle, (nearest surface point - x) / radius if within radius, else 0.

    positions: (N, D); obstacles: K gns.Obstacle of the same dimension. Returns (N, K D).
    """
    x = _floats("positions", positions)
    return _like(_core.obstacle_features(x, _shapes(obstacles), float(radius)), positions)


def _shapes(obstacles: Sequence[Obstacle]) -> list[_core.Obstacle]:
    shapes = []
    for k, o in enumerate(obstacles):
        if not isinstance(o, Obstacle):
            raise ValueError(f"obstacles[{k}] must be a gns.Obstacle, got {type(o).__name__}")
        shapes.append(o._core)
    return shapes


def nearest_obstacle_features(
    positions: Any, obstacles: Sequence[Obstacle], radius: float, *, clip: float = 1.0
) -> Any:
    """The nearest of all `obstacles`, one D-vector per particle whatever their number: the
    unit vector towards the nearest surface point, times 1 - d / (clip radius) (1 at contact,
    0 at clip radii and beyond; 0 on the surface itself, where the direction is undefined).

    positions: (N, D); obstacles: gns.Obstacle shapes of the same dimension (none: zeros).
    Returns (N, D) in the positions' dtype.
    """
    x = _floats("positions", positions)
    shapes = _shapes(obstacles)
    return _like(_core.nearest_obstacle_features(x, shapes, float(radius), float(clip)), positions)


def euler_step(position: Any, velocity: Any, acceleration: Any, dt: float = 1.0) -> Any:
    """Semi-implicit Euler: v' = v + dt a, x' = x + dt v'. Returns (x', v').

    All three (N, D) in one float dtype; non-finite inputs or results raise ValueError.
    """
    x = _floats("position", position)
    v = _floats("velocity", velocity, x.dtype)
    a = _floats("acceleration", acceleration, x.dtype)
    for name, arr in (("velocity", v), ("acceleration", a)):
        if arr.shape != x.shape:
            raise ValueError(
                f"{name} has shape {arr.shape} but position has {x.shape}; they must match"
            )
    return _like(_core.euler_step(x, v, a, float(dt)), position)
