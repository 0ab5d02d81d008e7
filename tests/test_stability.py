"""The fast, deterministic part of benches/stability.py: every case passes, each in a child
process with a time and memory limit (a crash or hang would be a failed case, not a dead run)."""

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


def test_a_crashing_or_hanging_case_is_a_failed_row():
    import signal

    crash, hang, wrong = (stability.run_case(i, self_test=True) for i in range(3))
    assert crash[:2] == (False, f"crashed: signal {signal.SIGSEGV}")
    assert hang[0] is False and hang[1].startswith("hung")
    assert wrong[0] is False and "no ValueError" in wrong[1]


def test_cases_survive_a_parent_that_used_the_rust_thread_pool():
    # A forked child of this process would inherit a pool without threads and hang.
    import gns
    import numpy as np

    gns.radius_graph(np.random.default_rng(0).random((50_000, 2)), 0.01)
    index = next(i for i, c in enumerate(stability.CASES) if c.name == "far outliers")
    passed, happened, _ = stability.run_case(index)
    assert passed, happened
