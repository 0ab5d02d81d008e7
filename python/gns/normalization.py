"""Feature normalisation: (x - mean) / std per column, with statistics that live in state_dict.

RunningNormalizer (B.2) keeps the exact mean and variance of everything it has been shown, from
a count, a sum and a sum of squares in float64 (not a moving average, which would drift in
cycles with the data order). The sums are taken around a fixed shift, the mean of the first
batch, so that E[x^2] - E[x]^2 does not cancel away the variance of values far from zero.

FixedNormalizer holds given statistics, e.g. metadata.json's, optionally with the std inflated
to sqrt(std^2 + noise_std^2) so that noisy inputs normalise to about unit variance.

Both treat a std below `min_std` as 1 (formats.md): a constant column is centred, not divided
by a tiny number.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch
from torch import Tensor, nn

__all__ = ["FixedNormalizer", "Normalizer", "RunningNormalizer"]


class Normalizer(nn.Module):
    """Common interface: mean and std (size,) float64; normalize / inverse on (..., size)."""

    def __init__(self, size: int, min_std: float = 1e-7) -> None:
        super().__init__()
        if size < 1:
            raise ValueError(f"a normalizer needs at least one column, got size {size}")
        self.size = size
        self.min_std = float(min_std)

    @property
    def mean(self) -> Tensor:
        raise NotImplementedError

    @property
    def raw_std(self) -> Tensor:
        raise NotImplementedError

    @property
    def std(self) -> Tensor:
        std = self.raw_std
        return torch.where(std < self.min_std, torch.ones_like(std), std)

    def update(self, values: Tensor, mask: Tensor | None = None) -> None:
        """Add rows of `values` (..., size) where `mask` (...) is true; fixed statistics ignore
        it (they are given, not learned)."""

    def _check(self, x: Tensor) -> None:
        if x.shape[-1] != self.size:
            raise ValueError(f"expected features of width {self.size}, got shape {tuple(x.shape)}")

    def normalize(self, x: Tensor) -> Tensor:
        self._check(x)
        return (x - self.mean.to(x.dtype)) / self.std.to(x.dtype)

    def inverse(self, x: Tensor) -> Tensor:
        self._check(x)
        return x * self.std.to(x.dtype) + self.mean.to(x.dtype)

    def extra_repr(self) -> str:
        return f"size={self.size}, min_std={self.min_std}"


class RunningNormalizer(Normalizer):
    """Exact statistics of all rows passed to `update` so far; mean 0, std 1 before the first."""

    count: Tensor
    shift: Tensor
    sum: Tensor
    sum_squares: Tensor

    def __init__(self, size: int, min_std: float = 1e-7) -> None:
        super().__init__(size, min_std)
        # In distributed training, an in-place sum over ranks (e.g. dist.all_reduce) so every
        # rank holds the statistics of all ranks' data; every rank must then call update.
        self.all_reduce: Callable[[Tensor], None] | None = None
        f64 = torch.float64
        self.register_buffer("count", torch.zeros((), dtype=f64))
        self.register_buffer("shift", torch.zeros(size, dtype=f64))
        self.register_buffer("sum", torch.zeros(size, dtype=f64))
        self.register_buffer("sum_squares", torch.zeros(size, dtype=f64))

    @torch.no_grad()
    def update(self, values: Tensor, mask: Tensor | None = None) -> None:
        self._check(values)
        rows = values.detach().reshape(-1, self.size).to(torch.float64)
        if mask is not None:
            rows = rows[mask.reshape(-1).to(torch.bool)]
        reduce = self.all_reduce
        if reduce is None and rows.shape[0] == 0:
            return
        # No .item(): keeps the update free of host-device synchronisation.
        first = self.count == 0
        if reduce is None:
            batch_mean = rows.mean(dim=0)
        else:
            # Distributed training: the shift is the mean of the whole first global batch.
            totals = torch.cat([rows.new_tensor([rows.shape[0]]), rows.sum(dim=0)])
            reduce(totals)
            batch_mean = totals[1:] / totals[0].clamp(min=1.0)
            first = first & (totals[0] > 0)
        self.shift.copy_(torch.where(first, batch_mean, self.shift))
        centred = rows - self.shift
        sums = torch.cat(
            [rows.new_tensor([rows.shape[0]]), centred.sum(dim=0), (centred * centred).sum(dim=0)]
        )
        if reduce is not None:
            reduce(sums)
        self.count += sums[0]
        self.sum += sums[1 : 1 + self.size]
        self.sum_squares += sums[1 + self.size :]

    @property
    def mean(self) -> Tensor:
        count = self.count.clamp(min=1.0)
        return torch.where(
            self.count > 0, self.shift + self.sum / count, torch.zeros_like(self.sum)
        )

    @property
    def raw_std(self) -> Tensor:
        count = self.count.clamp(min=1.0)
        centred_mean = self.sum / count
        variance = torch.clamp(self.sum_squares / count - centred_mean * centred_mean, min=0.0)
        return torch.where(self.count > 0, torch.sqrt(variance), torch.ones_like(variance))


class FixedNormalizer(Normalizer):
    """Given statistics; std is inflated to sqrt(std^2 + noise_std^2)."""

    fixed_mean: Tensor
    fixed_std: Tensor

    def __init__(
        self,
        mean: Sequence[float] | Tensor,
        std: Sequence[float] | Tensor,
        *,
        noise_std: float = 0.0,
        min_std: float = 1e-7,
    ) -> None:
        mean_t = torch.as_tensor(mean, dtype=torch.float64).reshape(-1).clone()
        std_t = torch.as_tensor(std, dtype=torch.float64).reshape(-1).clone()
        if mean_t.shape != std_t.shape:
            raise ValueError(
                f"mean and std differ in length: {mean_t.shape[0]} and {std_t.shape[0]}"
            )
        if not (torch.isfinite(mean_t).all() and torch.isfinite(std_t).all()) or (std_t < 0).any():
            raise ValueError(f"statistics must be finite with std >= 0, got {mean_t}, {std_t}")
        if not (math.isfinite(noise_std) and noise_std >= 0):
            raise ValueError(f"noise_std must be finite and >= 0, got {noise_std}")
        super().__init__(mean_t.shape[0], min_std)
        self.register_buffer("fixed_mean", mean_t)
        self.register_buffer("fixed_std", torch.sqrt(std_t * std_t + noise_std**2))

    @property
    def mean(self) -> Tensor:
        return self.fixed_mean

    @property
    def raw_std(self) -> Tensor:
        return self.fixed_std
