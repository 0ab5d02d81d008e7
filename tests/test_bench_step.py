"""benches/step.py runs end to end (--quick, small sizes, one thread); no assertions on time."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "benches" / "step.py"


def test_step_benchmark_quick_prints_its_table(tmp_path):
    missing = tmp_path / "no-sand-here"
    result = subprocess.run(
        [sys.executable, str(BENCH), "--quick", "--threads", "1", "--reps", "1"]
        + ["--sizes", "120", "--sand", str(missing)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr
    out = result.stdout
    assert "torch threads" in out and "fp32 matmul" in out
    header = next(line for line in out.splitlines() if line.startswith("case"))
    for title in ("rollout ms", "graph", "feat", "model", "integ", "graph%", "train ms", "% mm"):
        assert title in header
    assert f"not found at {missing}: skipped" in out
    (row,) = [line for line in out.splitlines() if line.startswith("120 particles")]
    assert "plain fp32" in row and len(row.split()) >= 17
    assert "FlopCounterMode" in out
