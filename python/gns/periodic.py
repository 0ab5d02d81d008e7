"""Differences of positions in a box whose periodic axes wrap (LagrangeBench's SPH datasets).

A particle that leaves such an axis at the top re-enters at the bottom, so the raw difference of
its positions in two frames is off by the box length. Every difference of positions taken
outside the model (statistics, the constant-velocity baseline, MSE, OT and MMD) goes through
`minimum_image`; the model's own (velocities, targets, edges) does so in torch
(LearnedSimulator.displacement).

A `period` is (D,) float64: the box length on each periodic axis and 0 on the others; None
means no periodic axis, and everything here is then the identity.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["minimum_image", "period_of", "wrap"]


def period_of(
    bounds: Sequence[Sequence[float]] | None, periodic: Sequence[bool] | None
) -> np.ndarray | None:
    """The period of a box `bounds` ((lo, hi) per axis) with per-axis `periodic` flags; None
    when no axis is periodic. ValueError when a periodic axis has no bounds."""
    if periodic is None or not any(periodic):
        return None
    if bounds is None or len(bounds) != len(periodic):
        raise ValueError(
            f"periodic axes {list(periodic)} need the box's bounds, one (lo, hi) per axis; got "
            f"{bounds!r}"
        )
    lengths = np.array([float(hi) - float(lo) for lo, hi in bounds])
    return np.where(np.asarray(periodic, bool), lengths, 0.0)


def minimum_image(d: ArrayLike, period: np.ndarray | None) -> np.ndarray:
    """d (..., D) with each periodic component folded into [-L/2, L/2]: the shortest way round."""
    out = np.asarray(d, dtype=np.float64)
    if period is None:
        return out
    safe = np.where(period > 0, period, 1.0)
    folded = out - safe * np.round(out / safe)
    return np.where(period > 0, folded, out)


def wrap(x: ArrayLike, lower: ArrayLike, period: np.ndarray | None) -> np.ndarray:
    """Positions x (..., D) folded back into [lower, lower + L) on the periodic axes."""
    out = np.asarray(x, dtype=np.float64)
    if period is None:
        return out
    lo = np.asarray(lower, dtype=np.float64)
    safe = np.where(period > 0, period, 1.0)
    return np.where(period > 0, lo + np.mod(out - lo, safe), out)
