"""Evaluation metrics of the GNS (sections B.4, C.4): rollout MSE and the summary of a rollout's
errors against the ground truth (`evaluate_rollout`: MSE at horizons, optimal transport, MMD).

The other metrics have modules of their own, and the public ones are importable from here too:
  gns.distances   optimal transport (exact and Sinkhorn) and MMD between two point clouds
  gns.deposit     where the sand stops: runout, fronts, pile height, packing, and their ratios
  gns.baselines   the constant-velocity and static rollouts the models are compared with

All functions take numpy arrays (anything `np.asarray` accepts), compute in float64 and return
Python floats or float64 arrays. Positions are time-major: a rollout is (T, N, D) with frame 0
the first *predicted* frame (the one-step prediction), N particles and D spatial dimensions.

MSE (`mse_over_time`, `horizon_mse`, `one_step_mse`) compares particle i with particle i: it
needs the particle correspondence. Optimal transport and MMD compare the two point clouds as
uniform empirical distributions and so are invariant to permutations of the particles (B.4).

Diverged rollouts. A prediction with NaN or Inf means the rollout diverged; that must show in
the report, never vanish into a mean. With `nonfinite="raise"` (the default) such input raises
ValueError naming the first bad frame and particle; with `nonfinite="inf"` every frame holding a
non-finite prediction scores +inf for every metric, so horizon means that include it are +inf
too. No metric ever returns NaN. Non-finite ground truth is a data error and always raises.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from gns.baselines import constant_velocity_rollout
from gns.distances import (
    EXACT_MAX_POINTS,
    OtMethod,
    SinkhornConvergenceError,
    SinkhornResult,
    exact_optimal_transport,
    mmd,
    optimal_transport,
    sinkhorn,
)
from gns.metric_inputs import FloatArray, Nonfinite, float_array, particle_mask, rollout_pair
from gns.periodic import minimum_image

# Re-exported: optimal transport, MMD and the constant-velocity baseline are the README's and
# docs' gns.metrics.
__all__ = [
    "DEFAULT_HORIZONS",
    "SinkhornConvergenceError",
    "SinkhornResult",
    "constant_velocity_rollout",
    "evaluate_rollout",
    "exact_optimal_transport",
    "horizon_mse",
    "mmd",
    "mse_over_time",
    "one_step_mse",
    "optimal_transport",
    "sinkhorn",
]

# Rollout horizons in frames; None is the full rollout.
DEFAULT_HORIZONS: tuple[int | None, ...] = (1, 5, 10, 20, 50, 100, None)


# --------------------------------------------------------------------------- MSE


def mse_over_time(
    predicted: ArrayLike,
    ground_truth: ArrayLike,
    mask: ArrayLike | None = None,
    *,
    nonfinite: Nonfinite = "raise",
    period: FloatArray | None = None,
) -> FloatArray:
    """Per-frame mean squared error, (T,): mean over the particles selected by `mask` (N,) bool
    (default all) and over the D dimensions of (predicted - ground_truth)^2, both (T, N, D);
    the difference is the minimum image on the periodic axes of `period` (gns.periodic).

    Non-finite predictions raise ValueError, or with nonfinite="inf" give +inf for their frame.
    A finite prediction so large that its square overflows also gives +inf: it diverged too.
    """
    pred, truth, finite = rollout_pair(predicted, ground_truth, nonfinite)
    keep = particle_mask(mask, pred.shape[1])
    with np.errstate(over="ignore", invalid="ignore"):
        error = minimum_image(pred[:, keep] - truth[:, keep], period)
        per_frame: FloatArray = np.mean(error**2, axis=(1, 2))
    per_frame[~finite] = np.inf
    return per_frame


def one_step_mse(
    predicted_next: ArrayLike,
    ground_truth_next: ArrayLike,
    mask: ArrayLike | None = None,
    *,
    nonfinite: Nonfinite = "raise",
) -> float:
    """MSE of one predicted frame: mean of (predicted_next - ground_truth_next)^2, both (N, D),
    over the particles in `mask` (N,) bool and the D dimensions."""
    pred = float_array("predicted_next", predicted_next, "(N, D)", 2)
    truth = float_array("ground_truth_next", ground_truth_next, "(N, D)", 2)
    return float(mse_over_time(pred[None], truth[None], mask, nonfinite=nonfinite)[0])


def horizon_mse(
    per_frame_mse: ArrayLike,
    horizons: Sequence[int | None] = DEFAULT_HORIZONS,
    *,
    name: str = "mse",
) -> dict[str, float]:
    """Mean of the per-frame errors (T,) over the first h predicted frames, for each h.

    Keys are f"{name}@{h}" and f"{name}@full" for None (the whole rollout), in the order of
    `horizons`. A horizon longer than the rollout (h > T) is omitted rather than silently
    averaged over fewer frames, so a key present always means exactly h frames. Values may be
    +inf (a diverged frame); NaN or negative values are rejected.
    """
    errors = float_array("per_frame_mse", per_frame_mse, "(T,)", 1)
    if np.isnan(errors).any() or (errors < 0).any():
        raise ValueError("per_frame_mse must hold non-negative numbers (inf allowed), no NaN")
    out: dict[str, float] = {}
    for h in horizons:
        if h is None:
            out[f"{name}@full"] = float(np.mean(errors))
            continue
        if isinstance(h, bool) or not isinstance(h, int | np.integer) or h < 1:
            raise ValueError(f"horizons must be positive integers or None, got {h!r}")
        if h <= errors.shape[0]:
            out[f"{name}@{int(h)}"] = float(np.mean(errors[:h]))
    return out


# --------------------------------------------------------------------------- summary


def evaluate_rollout(
    predicted: ArrayLike,
    ground_truth: ArrayLike,
    *,
    mask: ArrayLike | None = None,
    horizons: Sequence[int | None] = DEFAULT_HORIZONS,
    distribution_every: int = 1,
    bandwidth: float = 0.1,
    ot_method: OtMethod = "auto",
    exact_max_points: int = EXACT_MAX_POINTS,
    epsilon: float = 1e-2,
    nonfinite: Nonfinite = "raise",
    period: FloatArray | None = None,
) -> dict[str, Any]:
    """All metrics of one rollout: predicted and ground_truth (T, N, D), mask (N,) bool of the
    particles that count (e.g. the non-kinematic ones; default all); on the periodic axes of
    `period` (gns.periodic) every metric takes the minimum image (MSE, OT and MMD on the torus).

    Returns a dict of
      "mse": (T,) per-frame MSE;  "mse@h" / "mse@full": floats from `horizon_mse`;
      "frames": (K,) int64, the frames 0, s, 2s, ... (s = distribution_every) that get the
          distributional metrics, which cost O(N^2) or more per frame;
      "ot": (K,) W2^2 per evaluated frame (`optimal_transport`); "ot_mean": their mean;
      "ot_points": how many particles OT compared (see below);
      "mmd": (K,) biased MMD^2 per evaluated frame (`mmd`); "mmd_mean": their mean.
    OT and MMD compare the masked particles of both frames. With ot_method "auto" and more
    masked particles than exact_max_points, OT compares a fixed random subset of that many
    particles (the same in both frames and in every frame, drawn from seed 0), solved exactly:
    entropic OT at that size took 58 s a frame against 0.7 s for the exact assignment of
    2290 particles, and reports mostly its own blur. With nonfinite="inf" a diverged
    frame scores inf for all three metrics (and so do the means that include it). A Sinkhorn
    frame that does not converge raises SinkhornConvergenceError rather than report a guess.
    """
    pred, truth, finite = rollout_pair(predicted, ground_truth, nonfinite)
    keep = particle_mask(mask, pred.shape[1])
    if (
        isinstance(distribution_every, bool)
        or not isinstance(distribution_every, int | np.integer)
        or distribution_every < 1
    ):
        raise ValueError(
            f"distribution_every must be a positive integer, got {distribution_every!r}"
        )
    per_frame = mse_over_time(pred, truth, keep, nonfinite=nonfinite, period=period)
    frames = np.arange(0, pred.shape[0], distribution_every, dtype=np.int64)
    ot = np.full(frames.shape, np.inf)
    discrepancy = np.full(frames.shape, np.inf)
    counted = int(np.count_nonzero(keep))
    subset = np.arange(counted)
    if ot_method == "auto" and counted > exact_max_points:
        subset = np.sort(np.random.default_rng(0).choice(counted, exact_max_points, replace=False))
    for k, t in enumerate(frames):
        if not finite[t]:
            continue
        a, b = pred[t, keep], truth[t, keep]
        ot[k] = optimal_transport(
            a[subset],
            b[subset],
            method=ot_method,
            exact_max_points=exact_max_points,
            epsilon=epsilon,
            period=period,
        )
        discrepancy[k] = mmd(a, b, bandwidth, period=period)
    summary: dict[str, Any] = {"mse": per_frame}
    summary.update(horizon_mse(per_frame, horizons))
    summary.update(
        frames=frames,
        ot=ot,
        ot_mean=float(np.mean(ot)),
        ot_points=len(subset),
        mmd=discrepancy,
        mmd_mean=float(np.mean(discrepancy)),
    )
    return summary
