"""The checks every metric of gns.metrics, gns.distances, gns.deposit and gns.baselines makes
of its inputs: shapes, particle masks and finiteness, converted to float64 numpy arrays.

Positions are time-major: a rollout is (T, N, D), one frame or point set (N, D). Non-finite
predictions follow the metric's `nonfinite` policy (see gns.metrics): "raise" raises ValueError
naming the first bad frame and particle, "inf" lets the caller score the frame +inf. Non-finite
ground truth is a data error and always raises.
"""

from __future__ import annotations

from typing import Literal, get_args

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "NONFINITE",
    "FloatArray",
    "Nonfinite",
    "check_nonfinite",
    "finite_frames",
    "finite_points",
    "float_array",
    "particle_mask",
    "point_pair",
    "rollout_pair",
]

FloatArray = NDArray[np.float64]
Nonfinite = Literal["raise", "inf"]
NONFINITE: tuple[Nonfinite, ...] = get_args(Nonfinite)


def float_array(name: str, value: ArrayLike, shape: str, ndim: int) -> FloatArray:
    array = np.asarray(value, dtype=np.float64)
    if array.ndim != ndim or 0 in array.shape:
        raise ValueError(f"{name} must be a non-empty array of shape {shape}, got {array.shape}")
    return array


def finite_points(name: str, value: ArrayLike) -> FloatArray:
    points = float_array(name, value, "(N, D)", 2)
    if not np.isfinite(points).all():
        raise ValueError(f"{name} holds NaN or Inf; point sets must be finite")
    return points


def point_pair(x: ArrayLike, y: ArrayLike) -> tuple[FloatArray, FloatArray]:
    xs, ys = finite_points("x", x), finite_points("y", y)
    if xs.shape[1] != ys.shape[1]:
        raise ValueError(
            f"x and y must have the same dimension D, got x {xs.shape} and y {ys.shape}"
        )
    return xs, ys


def particle_mask(mask: ArrayLike | None, n: int) -> NDArray[np.bool_]:
    if mask is None:
        return np.ones(n, dtype=bool)
    m = np.asarray(mask)
    # An integer array would silently index particles instead of selecting them.
    if m.dtype != np.bool_ or m.shape != (n,):
        raise ValueError(f"mask must be a boolean array of shape ({n},), got {m.dtype} {m.shape}")
    if not m.any():
        raise ValueError("mask selects no particle; at least one particle must count")
    return m


def check_nonfinite(nonfinite: str) -> None:
    if nonfinite not in NONFINITE:
        raise ValueError(f"nonfinite must be 'raise' or 'inf', got {nonfinite!r}")


def finite_frames(name: str, rollout: FloatArray, nonfinite: str) -> NDArray[np.bool_]:
    """(T,) True where frame t of `rollout` (T, N, D) is all finite; raises per `nonfinite`."""
    finite: NDArray[np.bool_] = np.asarray(np.isfinite(rollout).all(axis=(1, 2)))
    if not finite.all() and nonfinite == "raise":
        t, i = np.argwhere(~np.isfinite(rollout).all(axis=2))[0]
        raise ValueError(
            f"{name} holds NaN or Inf (first at frame {t}, particle {i}): the rollout diverged; "
            "pass nonfinite='inf' to score diverged frames as inf"
        )
    return finite


def rollout_pair(
    predicted: ArrayLike, ground_truth: ArrayLike, nonfinite: str
) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
    check_nonfinite(nonfinite)
    pred = float_array("predicted", predicted, "(T, N, D)", 3)
    truth = float_array("ground_truth", ground_truth, "(T, N, D)", 3)
    if pred.shape != truth.shape:
        raise ValueError(
            f"predicted and ground_truth must have the same shape (T, N, D), "
            f"got {pred.shape} and {truth.shape}"
        )
    if not np.isfinite(truth).all():
        raise ValueError("ground_truth holds NaN or Inf; the reference data must be finite")
    return pred, truth, finite_frames("predicted", pred, nonfinite)
