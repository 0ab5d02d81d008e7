"""Shared fixtures."""

import pytest


@pytest.fixture
def torch_one_thread():
    """Tiny models run fastest on one thread, and intra-op threads spin badly on a busy machine."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(autouse=True)
def fp32_unless_asked(monkeypatch):
    """A rollout with precision "auto" tries bf16 where it is native (AVX512-BF16 or AMX CPUs,
    CUDA) and keeps it when it measures faster: tests that compare with fp32 oracles would then
    see bf16 round-off on some machines, at some loads, and not on others. Here rollouts never
    try it; bf16 is tested where a test asks for it by name (test_runtime.py)."""
    import gns.rollout

    monkeypatch.setattr(gns.rollout, "native_bf16", lambda device: False)


@pytest.fixture(scope="session")
def strided(tmp_path_factory):
    """(run, native data, converted data) of test_rollout.strided_run: a model of 7.5 ms steps
    and data with 2.5 ms frames, made once for every test that needs it."""
    import torch
    from test_rollout import strided_run

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return strided_run(tmp_path_factory.mktemp("strided"))
    finally:
        torch.set_num_threads(threads)
