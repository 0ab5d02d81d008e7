"""What a measurement ran on, for reports and benchmarks (no heavy imports: torch is imported
by machine_info, when called)."""

from __future__ import annotations

import os
import platform
from pathlib import Path
from typing import Any

__all__ = ["cpu_name", "machine_info", "rust_threads"]


def cpu_name() -> str:
    """The CPU's model name from /proc/cpuinfo (Linux), else what `platform` knows."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown CPU"


def rust_threads() -> int:
    """The threads of the Rust core (MPM, radius graphs), which runs on rayon's global pool:
    RAYON_NUM_THREADS when it is a positive whole number, else one per logical CPU."""
    cores = os.cpu_count() or 1
    rayon = os.environ.get("RAYON_NUM_THREADS")
    return int(rayon) if rayon and rayon.isdigit() and int(rayon) > 0 else cores


def machine_info() -> dict[str, Any]:
    """What the timings were measured on (gns report's context)."""
    import torch

    info = {
        "cpu": cpu_name(),
        "logical_cpus": os.cpu_count() or 1,
        "torch_threads": torch.get_num_threads(),
        "rust_threads": rust_threads(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "cuda": torch.cuda.get_device_name() if torch.cuda.is_available() else None,
        # Other work on the machine slows every row; the timings mean little without it.
        "load_average": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
    }
    return info
