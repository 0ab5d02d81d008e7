"""benches/load.py runs end to end (--quick, one model, idle and busy); no assertions on time."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "benches" / "load.py"


def test_load_benchmark_quick_prints_a_row_per_policy_and_condition():
    result = subprocess.run(
        [sys.executable, str(BENCH), "--quick", "--models", "3-32", "--particles", "60"]
        + ["--steps", "4", "--policies", "before", "1 thread", "gns default"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    header = next(line for line in lines if line.startswith("| model"))
    assert header.count("median") == 2 and "idle" in header and "busy" in header
    rows = {line.split("|")[2].strip(): line.split("|") for line in lines if "GNS-3-32" in line}
    assert list(rows) == ["before", "1 thread", "gns default"]
    # Cells: model, policy, then per condition: median (range), mean, x before, ran with.
    assert rows["before"][5].strip() == rows["before"][9].strip() == "1.00"  # its own ratio
    assert "1 thr. fp32" in rows["1 thread"][6] and "1 thr. fp32" in rows["1 thread"][10]
    for cells in rows.values():
        assert float(cells[3].split()[0]) > 0 and float(cells[7].split()[0]) > 0
