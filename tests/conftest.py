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
    """precision="auto" means bf16 on CPUs with AMX/AVX512-BF16 and on CUDA: tests that compare
    with fp32 oracles would then measure bf16 round-off on some machines and not on others.
    Here "auto" is always fp32; bf16 is tested where a test asks for it by name."""
    import gns.model

    original = gns.model.resolve_precision

    def fp32_auto(precision, device):
        return original("fp32" if precision == "auto" else precision, device)

    monkeypatch.setattr(gns.model, "resolve_precision", fp32_auto)
