"""benches/train.py runs end to end (--quick: a tiny network, one thread, one step) and keeps
every tensor on the device it is given; no assertions on time."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest
from data_helpers import SAND
from device_check import STAND_IN, stand_in_device

BENCH = Path(__file__).resolve().parents[1] / "benches" / "train.py"
TITLES = ("batch", "N", "data ms", "step ms", "total ms", "data%", "windows/s", "particles/s")


def run_bench(*args: str) -> subprocess.CompletedProcess[str]:
    """benches/train.py --quick on one thread, one measured step, with `args`."""
    return subprocess.run(
        [sys.executable, str(BENCH), "--quick", "--threads", "1", "--steps", "1", *args],
        capture_output=True,
        text=True,
        timeout=300,
    )


def table_rows(out: str) -> list[list[str]]:
    header = next(line for line in out.splitlines() if line.lstrip().startswith("batch"))
    assert all(title in header for title in TITLES)
    lines = out.splitlines()
    start = lines.index(header) + 2  # below the rule
    return [line.split() for line in lines[start:] if line.strip()]


def test_train_benchmark_quick_prints_its_table_on_generated_data(tmp_path):
    missing = tmp_path / "no-sand-here"
    result = run_bench("--batch-sizes", "1", "3", "--sand", str(missing))
    assert result.returncode == 0, result.stderr
    out = result.stdout
    assert f"not found at {missing}: training on a generated lattice" in out
    assert "GNS-2-8" in out and "shrunk by --quick" in out and "Adam: " in out
    rows = table_rows(out)
    assert [r[0] for r in rows] == ["1", "3"]
    # One window of 120 particles, then three (the lattice's trajectories have 120-123).
    assert int(rows[0][1]) in range(120, 124) and int(rows[1][1]) in range(360, 370)
    assert all(float(r[-2]) > 0 for r in rows)  # windows/s


@pytest.mark.skipif(not SAND.is_dir(), reason="sand2d-taichi data not available")
def test_train_benchmark_reads_the_real_sand():
    result = run_bench("--batch-sizes", "2", "--sand", str(SAND))
    assert result.returncode == 0, result.stderr
    assert "data: sand2d-taichi train, 12 trajectories" in result.stdout
    assert table_rows(result.stdout)[0][:2] == ["2", str(2 * 656)]


def test_train_benchmark_keeps_every_tensor_on_the_device(monkeypatch):
    # What would mix devices on CUDA raises here (tests/device_check.py's stand-in device).
    monkeypatch.syspath_prepend(str(BENCH.parent))
    monkeypatch.setattr(sys, "argv", [str(BENCH), "--quick", "--threads", "1", "--steps", "1"])
    spec = importlib.util.spec_from_file_location("bench_train", BENCH)
    assert spec is not None and spec.loader is not None
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    config = bench.bench_config()  # GNS-2-8 (--quick)
    _, scene, trajectories, statistics = bench.generated_data(config, 40)
    with stand_in_device(monkeypatch):
        r = bench.measure(scene, trajectories, statistics, config, 2, STAND_IN)
    assert 2 * 40 <= r["particles"] <= 2 * 43  # two windows of the 40-43-particle lattices
    assert len(r["step"]) == 1
