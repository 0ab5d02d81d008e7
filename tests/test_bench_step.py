"""benches/step.py runs end to end (--quick, small sizes, one thread); no assertions on time."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "benches" / "step.py"


def run_bench(*args: str) -> subprocess.CompletedProcess[str]:
    """benches/step.py --quick on one thread, one repeat, with `args`."""
    return subprocess.run(
        [sys.executable, str(BENCH), "--quick", "--threads", "1", "--reps", "1", *args],
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_step_benchmark_quick_prints_its_table(tmp_path):
    missing = tmp_path / "no-sand-here"
    result = run_bench("--sizes", "120", "--sand", str(missing))
    assert result.returncode == 0, result.stderr
    out = result.stdout
    assert "torch threads" in out and "fp32 matmul" in out
    header = next(line for line in out.splitlines() if line.startswith("case"))
    for title in ("rollout ms", "graph", "feat", "model", "integ", "graph%", "train ms", "% mm"):
        assert title in header
    assert f"not found at {missing}: skipped" in out
    rows = [line for line in out.splitlines() if line.startswith("120 particles")]
    # plain and fast, and fast bf16 where bf16 is native (AVX512-BF16 / AMX CPUs).
    assert [r.split()[2:4] for r in rows][:2] == [["plain", "fp32"], ["fast", "fp32"]]
    assert len(rows) == (2 if "fast bf16: not run" in out else 3)
    assert all(len(r.split()) >= 19 for r in rows)
    assert header.count("x plain") == 2
    assert "FlopCounterMode agrees" in out  # the plain model's FLOPs for every row
    if "fast bf16: not run" not in out:  # a machine with native bf16
        assert "bf16 matmul" in out


def test_step_benchmark_runs_the_bf16_variant_on_request(tmp_path):
    result = run_bench("--sizes", "40", "--sand", "", "--variants", "fast", "bf16")
    assert result.returncode == 0, result.stderr
    rows = [line for line in result.stdout.splitlines() if line.startswith("40 particles")]
    assert [r.split()[2:4] for r in rows] == [["fast", "fp32"], ["fast", "bf16"]]
    assert all(r.split()[9] == "-" for r in rows)  # no plain row, no ratio
    assert "bf16 matmul" in result.stdout


def test_step_benchmark_says_why_bf16_was_not_run(tmp_path):
    # Left out by --variants, it is not "not native" (issue 40: the H100 was told it was).
    result = run_bench("--sizes", "40", "--sand", "", "--variants", "fast")
    assert result.returncode == 0, result.stderr
    assert "fast bf16: not run (--variants fast leaves it out)" in result.stdout
    assert "not native" not in result.stdout
