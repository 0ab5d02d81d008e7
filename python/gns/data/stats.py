"""Velocity and acceleration statistics, per frame, exactly as the model normalises them.

velocity_t = x_t - x_{t-1} and acceleration_t = v_{t+1} - v_t in frame units (never divided by
dt). Mean and std are per axis over every non-kinematic particle and every frame of the given
trajectories (the training split). Sums are kept in float64 around a fixed shift (the first
batch's mean) so that sum-of-squares does not lose the variance to cancellation.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from gns.data.metadata import DEFAULT_KINEMATIC_TYPES, Metadata
from gns.data.trajectory import Trajectory
from gns.periodic import minimum_image


class RunningMoments:
    """Exact running mean and (population) std per column of (M, K) batches."""

    def __init__(self) -> None:
        self.count = 0
        self.shift: np.ndarray | None = None
        self.sum: np.ndarray | None = None
        self.sum_squares: np.ndarray | None = None

    def add(self, values: np.ndarray) -> None:
        """values: (M, K); float64 accumulation."""
        values = np.asarray(values, dtype=np.float64)
        if values.shape[0] == 0:
            return
        if self.shift is None:
            self.shift = values.mean(axis=0)
            self.sum = np.zeros_like(self.shift)
            self.sum_squares = np.zeros_like(self.shift)
        assert self.sum is not None and self.sum_squares is not None
        centred = values - self.shift
        self.sum += centred.sum(axis=0)
        self.sum_squares += np.einsum("mk,mk->k", centred, centred)
        self.count += values.shape[0]

    @property
    def mean(self) -> np.ndarray:
        if self.count == 0 or self.shift is None or self.sum is None:
            raise ValueError("no values were added")
        return self.shift + self.sum / self.count

    @property
    def std(self) -> np.ndarray:
        if self.count == 0 or self.sum is None or self.sum_squares is None:
            raise ValueError("no values were added")
        centred_mean = self.sum / self.count
        variance = self.sum_squares / self.count - centred_mean**2
        return np.sqrt(np.maximum(variance, 0.0))


@dataclass(frozen=True)
class Statistics:
    """Per-axis statistics (D,) and how many samples each rests on."""

    vel_mean: np.ndarray
    vel_std: np.ndarray
    acc_mean: np.ndarray
    acc_std: np.ndarray
    vel_count: int
    acc_count: int
    context_mean: np.ndarray | None = None
    context_std: np.ndarray | None = None

    def apply_to(self, metadata: Metadata) -> Metadata:
        """A copy of `metadata` carrying these statistics."""

        def listed(a: np.ndarray | None) -> tuple[float, ...] | None:
            return None if a is None else tuple(float(v) for v in a)

        return metadata.replace(
            vel_mean=listed(self.vel_mean),
            vel_std=listed(self.vel_std),
            acc_mean=listed(self.acc_mean),
            acc_std=listed(self.acc_std),
            context_mean=listed(self.context_mean),
            context_std=listed(self.context_std),
        )


class StatisticsAccumulator:
    """Adds trajectories one at a time (streaming); `result()` gives the Statistics."""

    def __init__(
        self,
        kinematic_particle_types: Iterable[int] = DEFAULT_KINEMATIC_TYPES,
        period: np.ndarray | None = None,
    ) -> None:
        """period (gns.periodic): velocities are minimum images on its periodic axes, so a
        particle crossing a periodic box is not counted as fast."""
        self.kinematic = np.array(sorted(set(kinematic_particle_types)), dtype=np.int64)
        self.period = period
        self.velocity = RunningMoments()
        self.acceleration = RunningMoments()
        self.context = RunningMoments()

    def add(self, trajectory: Trajectory) -> None:
        if trajectory.step_context is not None:
            self.context.add(trajectory.step_context)
        free = ~np.isin(trajectory.particle_type, self.kinematic)
        if not free.any():
            return
        positions = trajectory.positions[:, free].astype(np.float64)
        vel = minimum_image(np.diff(positions, axis=0), self.period)  # (T-1, n_free, D)
        acc = np.diff(vel, axis=0)  # (T-2, n_free, D)
        d = positions.shape[2]
        self.velocity.add(vel.reshape(-1, d))
        self.acceleration.add(acc.reshape(-1, d))

    def result(self) -> Statistics:
        """Raises ValueError if no trajectory had 3 frames and a non-kinematic particle."""
        if self.acceleration.count == 0:
            raise ValueError(
                "no statistics: need trajectories with at least 3 frames and a non-kinematic "
                "particle"
            )
        return Statistics(
            vel_mean=self.velocity.mean,
            vel_std=self.velocity.std,
            acc_mean=self.acceleration.mean,
            acc_std=self.acceleration.std,
            vel_count=self.velocity.count,
            acc_count=self.acceleration.count,
            context_mean=self.context.mean if self.context.count else None,
            context_std=self.context.std if self.context.count else None,
        )


def compute_statistics(
    trajectories: Iterable[Trajectory],
    kinematic_particle_types: Iterable[int] = DEFAULT_KINEMATIC_TYPES,
    period: np.ndarray | None = None,
) -> Statistics:
    """Statistics over `trajectories`, skipping particles whose type is kinematic (minimum
    images on the periodic axes of `period`, gns.periodic)."""
    accumulator = StatisticsAccumulator(kinematic_particle_types, period)
    for trajectory in trajectories:
        accumulator.add(trajectory)
    return accumulator.result()
