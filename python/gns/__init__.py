"""gns: the Graph Network-based Simulator with a Rust core.

The public API; `gns._core` is private and reached only through `gns.ops`. The model (which
needs torch) is imported on first use, so `import gns` stays quick for the Rust core alone.
"""

from typing import Any

from gns.ops import (
    DEFAULT_MAX_EDGES,
    Obstacle,
    RadiusSearcher,
    euler_step,
    obstacle_features,
    radius_graph,
    wall_features,
)

# Name -> module of the torch-based API, loaded lazily (PEP 562).
_LAZY = {
    "CConv": "gns.cconv",
    "Config": "gns.config",
    "load_config": "gns.config",
    "EncodeProcessDecode": "gns.model",
    "LearnedSimulator": "gns.simulator",
    "Scene": "gns.simulator",
    "load_simulator": "gns.checkpoints",
    "Rollout": "gns.rollout",
    "evaluate_rollouts": "gns.evaluate",
}

__all__ = [
    "DEFAULT_MAX_EDGES",
    "CConv",
    "Config",
    "EncodeProcessDecode",
    "LearnedSimulator",
    "Obstacle",
    "RadiusSearcher",
    "Rollout",
    "Scene",
    "euler_step",
    "evaluate_rollouts",
    "load_config",
    "load_simulator",
    "obstacle_features",
    "radius_graph",
    "wall_features",
]
__version__ = "0.1.0"


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'gns' has no attribute {name!r}")
