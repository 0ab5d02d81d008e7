"""gns: the Graph Network-based Simulator with a Rust core.

The public API; `gns._core` is private and reached only through `gns.ops`. The model (which
needs torch) is imported on first use, so `import gns` stays quick for the Rust core alone.
Submodules (`gns.data`, `gns.mpm`, `gns.metrics`, `gns.rollout`, ...) are attributes too,
imported on first touch: `import gns; gns.data.open_dataset(...)` works without importing
`gns.data` first, and only the modules a user touches are loaded (gns.data needs no torch).
"""

import importlib.metadata
import pkgutil
from typing import Any

from gns.ops import (
    DEFAULT_MAX_EDGES,
    Obstacle,
    RadiusSearcher,
    euler_step,
    nearest_obstacle_features,
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

# Submodules reachable as `gns.<name>` after a plain `import gns` (gns.data, gns.mpm, gns.metrics,
# gns.rollout, ...), imported on first touch so that `import gns` does not pay for torch. Listed
# from the package folder (a directory read, no imports) so a new module is covered without
# editing this file; private ones (_core) and the command line (cli, __main__) are left out.
_SUBMODULES = frozenset(
    info.name
    for info in pkgutil.iter_modules(__path__)
    if not info.name.startswith("_") and info.name != "cli"
)

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
    "nearest_obstacle_features",
    "obstacle_features",
    "radius_graph",
    "wall_features",
]
# Cargo.toml's version, through the installed package's metadata (maturin copies it there).
__version__ = importlib.metadata.version("gns")


def __getattr__(name: str) -> Any:
    import importlib

    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    if name in _SUBMODULES:
        # import_module also binds the submodule as an attribute of gns, so this runs once.
        return importlib.import_module(f"gns.{name}")
    raise AttributeError(f"module 'gns' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *_LAZY, *_SUBMODULES})
