"""gns: the Graph Network-based Simulator with a Rust core.

The public API; `gns._core` is private and reached only through `gns.ops`.
"""

from gns.ops import (
    DEFAULT_MAX_EDGES,
    Obstacle,
    RadiusSearcher,
    euler_step,
    obstacle_features,
    radius_graph,
    wall_features,
)

__all__ = [
    "DEFAULT_MAX_EDGES",
    "Obstacle",
    "RadiusSearcher",
    "euler_step",
    "obstacle_features",
    "radius_graph",
    "wall_features",
]
__version__ = "0.1.0"
