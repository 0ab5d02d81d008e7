"""Normalisers against numpy: exact running statistics (B.2) and metadata statistics."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from gns.normalization import FixedNormalizer, RunningNormalizer


def test_running_statistics_match_numpy_over_all_rows_seen_so_far():
    rng = np.random.default_rng(0)
    normalizer = RunningNormalizer(3)
    seen = []
    # Far from zero with a small spread: a plain float64 sum of squares would lose the variance.
    offset, scale = np.array([1e5, -3.0, 0.0]), np.array([1e-3, 2.0, 5e-4])
    for size in (7, 1, 250, 33, 1000):
        batch = offset + scale * rng.standard_normal((size, 3))
        mask = rng.random(size) < 0.7
        normalizer.update(torch.from_numpy(batch), torch.from_numpy(mask))
        seen.append(batch[mask])
        rows = np.concatenate(seen)
        assert normalizer.count.item() == rows.shape[0]
        np.testing.assert_allclose(normalizer.mean.numpy(), rows.mean(0), rtol=1e-12)
        np.testing.assert_allclose(normalizer.std.numpy(), rows.std(0), rtol=1e-7)


def test_running_statistics_accept_batched_feature_tensors_and_float32():
    rng = np.random.default_rng(1)
    values = rng.normal([1e-4, -8e-4], [9e-4, 1.6e-3], size=(40, 5, 2)).astype(np.float32)
    normalizer = RunningNormalizer(2)
    normalizer.update(torch.from_numpy(values[:25]))
    normalizer.update(torch.from_numpy(values[25:]))
    rows = values.astype(np.float64).reshape(-1, 2)
    np.testing.assert_allclose(normalizer.mean.numpy(), rows.mean(0), rtol=1e-12)
    np.testing.assert_allclose(normalizer.std.numpy(), rows.std(0), rtol=1e-9)
    normalized = normalizer.normalize(torch.from_numpy(values)).double().reshape(-1, 2)
    np.testing.assert_allclose(normalized.mean(0).numpy(), [0, 0], atol=1e-5)
    np.testing.assert_allclose(normalized.std(0, unbiased=False).numpy(), [1, 1], rtol=1e-5)


def test_normalize_and_inverse_compose_to_the_identity():
    torch.manual_seed(0)
    normalizer = RunningNormalizer(4)
    normalizer.update(torch.randn(100, 4, dtype=torch.float64) * 3 + 2)
    x = torch.randn(10, 4, dtype=torch.float64)
    torch.testing.assert_close(normalizer.inverse(normalizer.normalize(x)), x)
    torch.testing.assert_close(normalizer.normalize(normalizer.inverse(x)), x)


def test_before_any_data_the_normalizer_is_the_identity_and_empty_masks_add_nothing():
    normalizer = RunningNormalizer(2)
    x = torch.tensor([[1.5, -2.0]])
    torch.testing.assert_close(normalizer.normalize(x), x)
    normalizer.update(torch.ones(3, 2), torch.zeros(3, dtype=torch.bool))
    assert normalizer.count.item() == 0
    torch.testing.assert_close(normalizer.normalize(x), x)


def test_statistics_live_in_the_state_dict_and_continue_exactly():
    rng = np.random.default_rng(2)
    a, b = rng.normal(size=(50, 2)), rng.normal(3.0, 0.5, size=(70, 2))
    first = RunningNormalizer(2)
    first.update(torch.from_numpy(a))
    second = RunningNormalizer(2)
    second.load_state_dict(first.state_dict())
    second.update(torch.from_numpy(b))
    both = np.concatenate([a, b])
    np.testing.assert_allclose(second.mean.numpy(), both.mean(0), rtol=1e-12)
    np.testing.assert_allclose(second.std.numpy(), both.std(0), rtol=1e-12)
    assert set(first.state_dict()) == {"count", "shift", "sum", "sum_squares"}


def test_a_constant_column_is_centred_not_divided_by_a_tiny_std():
    normalizer = RunningNormalizer(2, min_std=1e-7)
    values = torch.tensor([[0.5, 1.0], [0.5, 3.0]], dtype=torch.float64)
    normalizer.update(values)
    torch.testing.assert_close(normalizer.std, torch.tensor([1.0, 1.0], dtype=torch.float64))
    torch.testing.assert_close(
        normalizer.normalize(torch.tensor([[0.75, 2.0]], dtype=torch.float64)),
        torch.tensor([[0.25, 0.0]], dtype=torch.float64),
    )


def test_fixed_statistics_inflate_the_std_by_the_noise():
    # sqrt(4e-4^2 + 3e-4^2) = 5e-4 and sqrt(0^2 + 3e-4^2) = 3e-4.
    normalizer = FixedNormalizer([1e-4, -2e-4], [4e-4, 0.0], noise_std=3e-4)
    torch.testing.assert_close(normalizer.std, torch.tensor([5e-4, 3e-4], dtype=torch.float64))
    x = torch.tensor([[6e-4, 1e-4]], dtype=torch.float64)
    torch.testing.assert_close(
        normalizer.normalize(x), torch.tensor([[1.0, 1.0]], dtype=torch.float64)
    )
    normalizer.update(torch.ones(5, 2))  # given statistics are not learned
    torch.testing.assert_close(normalizer.mean, torch.tensor([1e-4, -2e-4], dtype=torch.float64))
    plain = FixedNormalizer([0.0], [0.0])
    torch.testing.assert_close(plain.std, torch.ones(1, dtype=torch.float64))


def test_bad_inputs_are_rejected():
    with pytest.raises(ValueError, match="width 3"):
        RunningNormalizer(3).normalize(torch.zeros(4, 2))
    with pytest.raises(ValueError, match="differ in length"):
        FixedNormalizer([0.0, 1.0], [1.0])
    with pytest.raises(ValueError, match="std >= 0"):
        FixedNormalizer([0.0], [-1.0])
