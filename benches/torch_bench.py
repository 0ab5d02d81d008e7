"""What the torch benchmarks (step.py, train.py) share: their threads and device, the machine's
lines above their tables and the CUDA synchronisation around every timed part."""

from __future__ import annotations

import os

import torch
from gns.device import resolve_device
from gns.machine import cpu_name


def bench_device(script: str, threads: int | None, device: str) -> torch.device:
    """Fix torch's CPU threads when asked and resolve --device; a device there is not ends the
    benchmark `script` with its one-line error."""
    if threads is not None:
        torch.set_num_threads(threads)
    try:
        return resolve_device(device)
    except ValueError as err:
        raise SystemExit(f"{script}: {err}") from None


def machine_facts(device: torch.device) -> list[str]:
    """The CPU, torch and its threads, the Rust threads and the device (the GPU's name)."""
    facts = [
        f"cpu: {cpu_name()} ({os.cpu_count()} logical cores)",
        f"torch {torch.__version__}, {torch.get_num_threads()} torch threads, "
        f"Rust threads: {os.environ.get('RAYON_NUM_THREADS', 'all cores')}, device {device}",
    ]
    if device.type == "cuda":
        facts.append(f"gpu: {torch.cuda.get_device_name(device)}")
    return facts


def synchronize(device: torch.device) -> None:
    """Wait for the device's queued work, so that perf_counter times it (no-op on the CPU)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)
