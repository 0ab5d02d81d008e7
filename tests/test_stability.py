"""The fast, deterministic part of benches/stability.py: every case passes, each in a forked
child with a time and memory limit (a crash or hang would be a failed case, not a dead run)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benches" / "stability.py"


def load():
    spec = importlib.util.spec_from_file_location("stability_bench", BENCH)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


stability = load()
QUICK = [i for i, case in enumerate(stability.CASES) if case.quick]


@pytest.mark.parametrize("index", QUICK, ids=[stability.CASES[i].name for i in QUICK])
def test_case_passes(index):
    passed, happened, _ = stability.run_case(index)
    assert passed, happened


def test_a_crashing_or_hanging_case_is_a_failed_row(monkeypatch):
    import os
    import signal
    import time

    cases = [
        stability.Case("t", "crash", "", lambda: os.kill(os.getpid(), signal.SIGSEGV)),
        stability.Case("t", "hang", "", lambda: time.sleep(60), timeout=1.0),
        stability.Case("t", "wrong", "", lambda: stability.refused(lambda: None, "x")),
    ]
    monkeypatch.setattr(stability, "CASES", cases)
    crash, hang, wrong = (stability.run_case(i) for i in range(3))
    assert crash[:2] == (False, f"crashed: signal {signal.SIGSEGV}")
    assert hang[0] is False and hang[1].startswith("hung")
    assert wrong[0] is False and "no ValueError" in wrong[1]
