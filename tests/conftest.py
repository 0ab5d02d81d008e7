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
