"""The two baselines a learned simulator's rollouts are compared with (gns.evaluate, gns.report):
`constant_velocity_rollout` (every particle keeps its last velocity) and `static_rollout` (every
particle stays where the last input frame has it). Both take numpy arrays, time-major
(C + 1, N, D) input frames with the most recent last, and return float64 rollouts
(num_steps, N, D); kinematic particles can take the ground truth, as in learned rollouts.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from gns.metric_inputs import FloatArray, float_array
from gns.periodic import minimum_image, wrap

__all__ = ["constant_velocity_rollout", "static_rollout"]


def _baseline_start(
    initial_positions: ArrayLike,
    num_steps: int,
    min_frames: int,
    kinematic_mask: ArrayLike | None,
    ground_truth: ArrayLike | None,
) -> FloatArray:
    """The checked input frames (C + 1, N, D) of a baseline rollout of num_steps frames."""
    positions = float_array("initial_positions", initial_positions, "(C + 1, N, D)", 3)
    if positions.shape[0] < min_frames:
        raise ValueError(
            f"initial_positions needs at least {min_frames} frames (C + 1, N, D), "
            f"got {positions.shape}"
        )
    if not np.isfinite(positions).all():
        raise ValueError("initial_positions holds NaN or Inf")
    if isinstance(num_steps, bool) or not isinstance(num_steps, int | np.integer) or num_steps < 1:
        raise ValueError(f"num_steps must be a positive integer, got {num_steps!r}")
    if (kinematic_mask is None) != (ground_truth is None):
        raise ValueError("kinematic_mask and ground_truth must be given together, or neither")
    return positions


def _kinematic_from_truth(
    rollout: FloatArray, kinematic_mask: ArrayLike | None, ground_truth: ArrayLike | None
) -> FloatArray:
    """`rollout` (S, N, D) with the kinematic particles set to `ground_truth` (S, N, D), as in
    learned rollouts: the baselines are not asked to predict what the scene prescribes."""
    if kinematic_mask is None or ground_truth is None:
        return rollout
    num_steps, n, d = rollout.shape
    kinematic = np.asarray(kinematic_mask)
    if kinematic.dtype != np.bool_ or kinematic.shape != (n,):
        raise ValueError(
            f"kinematic_mask must be a boolean array of shape ({n},), "
            f"got {kinematic.dtype} {kinematic.shape}"
        )
    truth = float_array("ground_truth", ground_truth, "(num_steps, N, D)", 3)
    if truth.shape != (num_steps, n, d):
        raise ValueError(
            f"ground_truth must have shape (num_steps, N, D) = {(num_steps, n, d)}, "
            f"got {truth.shape}"
        )
    rollout[:, kinematic] = truth[:, kinematic]
    return rollout


def constant_velocity_rollout(
    initial_positions: ArrayLike,
    num_steps: int,
    *,
    kinematic_mask: ArrayLike | None = None,
    ground_truth: ArrayLike | None = None,
    bounds: ArrayLike | None = None,
    period: FloatArray | None = None,
) -> FloatArray:
    """The reference baseline: every particle keeps its last velocity.

    initial_positions: (C + 1, N, D), time-major, most recent last, C >= 1.
    Returns (num_steps, N, D): x_{t+1} = x_t + v with v = x[-1] - x[-2]. On the periodic axes
    of `period` (gns.periodic; `bounds` (D, 2) then gives the box) v is the minimum image and
    the positions are wrapped back into the box, as the data's are. Kinematic particles
    (`kinematic_mask` (N,) bool) take `ground_truth` (num_steps, N, D) instead, as in learned
    rollouts; the two must be given together.
    """
    positions = _baseline_start(initial_positions, num_steps, 2, kinematic_mask, ground_truth)
    last, velocity = positions[-1], minimum_image(positions[-1] - positions[-2], period)
    steps = np.arange(1, num_steps + 1, dtype=np.float64)[:, None, None]
    rollout: FloatArray = last[None] + steps * velocity[None]
    if period is not None:
        if bounds is None:
            raise ValueError("constant_velocity_rollout: a period needs the box's bounds")
        rollout = wrap(rollout, np.asarray(bounds, dtype=np.float64)[:, 0], period)
    return _kinematic_from_truth(rollout, kinematic_mask, ground_truth)


def static_rollout(
    initial_positions: ArrayLike,
    num_steps: int,
    *,
    kinematic_mask: ArrayLike | None = None,
    ground_truth: ArrayLike | None = None,
) -> FloatArray:
    """The static baseline: every particle stays where the last input frame has it.

    initial_positions: (C + 1, N, D), time-major, most recent last (one frame is enough).
    Returns (num_steps, N, D), each frame equal to initial_positions[-1]; kinematic particles
    (`kinematic_mask` (N,) bool) take `ground_truth` (num_steps, N, D) instead, as in
    `constant_velocity_rollout`. Sand that comes to rest ends near where it was: late in a
    rollout this baseline is much harder to beat than constant velocity, whose particles keep
    flying through the floor and the walls.
    """
    positions = _baseline_start(initial_positions, num_steps, 1, kinematic_mask, ground_truth)
    rollout: FloatArray = np.repeat(positions[-1:], num_steps, axis=0)
    return _kinematic_from_truth(rollout, kinematic_mask, ground_truth)
