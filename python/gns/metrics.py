"""Evaluation metrics of the GNS: rollout MSE, optimal transport and MMD (sections B.4, C.4),
the deposit of granular flows (runout, fronts, pile height) and the two baselines.

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

Optimal transport is the squared 2-Wasserstein distance W2^2 between the uniform distributions
on the two point sets, in squared position units (the same units as the MSE):

- exact: with N == M an assignment problem (`scipy.optimize.linear_sum_assignment` on squared
  distances; W2^2 is the mean matched cost). With N != M the uniform weights 1/N and 1/M are
  integer multiples of 1/L for L = lcm(N, M); an optimal transportation plan with integer
  supplies has integer entries, so repeating every point of x L/N times and of y L/M times turns
  the problem into an exact L x L assignment (no LP solver). `exact_max_points` bounds L.
- sinkhorn: log-domain entropic OT (Cuturi 2013) with epsilon annealing and overrelaxation,
  returning the transport cost <P, C> of the entropic plan (rounded to an exact coupling), not
  the regularised objective. `epsilon` is relative to the mean pairwise cost
  mean_ij |x_i - y_j|^2, so the result scales exactly as s^2 when both sets are scaled by s.
  The result is never below W2^2 and, at convergence, above it by at most
  epsilon_absolute * log(min(N, M)) (compare the entropic objective at P_eps and at an optimal
  plan, whose entropy term is at most log(min(N, M))). That bias is real: for two nearly equal
  clouds (a one-step prediction) W2^2 is far below epsilon_absolute and Sinkhorn reports
  mostly its own blur, while smaller epsilons need roughly proportionally more iterations.
  Prefer the exact solver whenever its 8 L^2 bytes fit; Sinkhorn is for clouds beyond that.
  Memory: the N x M cost matrix is cached only if it fits in `memory_bytes`; otherwise it is
  recomputed in row blocks every iteration (slower, but memory stays O(block + (N + M) D)).

MMD is the squared maximum mean discrepancy (Gretton et al. 2012) with the Gaussian kernel
k(a, b) = exp(-|a - b|^2 / (2 bandwidth^2)). The supplement gives only "a Gaussian kernel
bandwidth of sigma = 0.1"; we read sigma as the standard deviation of the kernel, Gretton's
convention. The default is the biased V-statistic (all pairs, diagonals included), which is a
squared RKHS norm, hence >= 0, and exactly 0 for identical sets; `unbiased=True` gives the
U-statistic (no diagonals), unbiased but possibly negative.

The deposit answers what a geotechnical user asks of a granular model: where does the sand stop
and how high does it pile. All three are robust percentiles (1st and 99th, linear
interpolation between order statistics) over the particles a mask selects, in position units:
`runout_extent` (the 99th minus the 1st percentile of x in one frame: how wide the deposit is),
`front_positions` (those two percentiles of x in every frame: how the fronts advance) and
`pile_height` (the 99th percentile of y in one frame above a floor, `pile_floor`). They need no
particle correspondence, so they compare any two simulators of the same scene. `deposit` gathers
them for a rollout's last frame with `mean_neighbours` (how densely it packs; the radius search
is the Rust core's), and `deposit_ratios` sets them against the ground truth's.

Baselines: `constant_velocity_rollout` (every particle keeps its last velocity) and
`static_rollout` (every particle stays where the last input frame has it).
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import linear_sum_assignment  # type: ignore[import-untyped]

__all__ = [
    "DEFAULT_HORIZONS",
    "SinkhornConvergenceError",
    "SinkhornResult",
    "DEPOSIT_CURVES",
    "DEPOSIT_FIGURES",
    "constant_velocity_rollout",
    "deposit",
    "deposit_ratios",
    "evaluate_rollout",
    "exact_optimal_transport",
    "front_positions",
    "horizon_mse",
    "mean_neighbours",
    "mmd",
    "mse_over_time",
    "one_step_mse",
    "optimal_transport",
    "pile_floor",
    "pile_height",
    "ratio_of",
    "runout_extent",
    "sinkhorn",
    "static_rollout",
]

FloatArray = NDArray[np.float64]
Nonfinite = Literal["raise", "inf"]

# Rollout horizons in frames; None is the full rollout.
DEFAULT_HORIZONS: tuple[int | None, ...] = (1, 5, 10, 20, 50, 100, None)
# Row-sum error to which Sinkhorn solves the annealing stages before the last one.
_STAGE_TOLERANCE = 1e-2
# Bytes of float64 scratch per block of pairwise work (distances, kernels, Sinkhorn blocks).
DEFAULT_MEMORY_BYTES = 64 * 2**20


class SinkhornConvergenceError(RuntimeError):
    """Sinkhorn did not reach the marginal tolerance within max_iterations."""


@dataclass(frozen=True)
class SinkhornResult:
    """cost: <P, C> of the entropic plan rounded to a true coupling, an upper bound on W2^2;
    lower_bound: a dual lower bound on W2^2; epsilon: the absolute regularisation (squared
    length units); iterations: Sinkhorn updates done (annealing stages included);
    marginal_error: the L1 distance of the plan's row sums to the uniform weights before
    rounding (its column sums are exact)."""

    cost: float
    lower_bound: float
    epsilon: float
    iterations: int
    marginal_error: float


# --------------------------------------------------------------------------- validation


def _float_array(name: str, value: ArrayLike, shape: str, ndim: int) -> FloatArray:
    array = np.asarray(value, dtype=np.float64)
    if array.ndim != ndim or 0 in array.shape:
        raise ValueError(f"{name} must be a non-empty array of shape {shape}, got {array.shape}")
    return array


def _finite_points(name: str, value: ArrayLike) -> FloatArray:
    points = _float_array(name, value, "(N, D)", 2)
    if not np.isfinite(points).all():
        raise ValueError(f"{name} holds NaN or Inf; point sets must be finite")
    return points


def _point_pair(x: ArrayLike, y: ArrayLike) -> tuple[FloatArray, FloatArray]:
    xs, ys = _finite_points("x", x), _finite_points("y", y)
    if xs.shape[1] != ys.shape[1]:
        raise ValueError(
            f"x and y must have the same dimension D, got x {xs.shape} and y {ys.shape}"
        )
    return xs, ys


def _particle_mask(mask: ArrayLike | None, n: int) -> NDArray[np.bool_]:
    if mask is None:
        return np.ones(n, dtype=bool)
    m = np.asarray(mask)
    # An integer array would silently index particles instead of selecting them.
    if m.dtype != np.bool_ or m.shape != (n,):
        raise ValueError(f"mask must be a boolean array of shape ({n},), got {m.dtype} {m.shape}")
    if not m.any():
        raise ValueError("mask selects no particle; at least one particle must count")
    return m


def _check_nonfinite(nonfinite: str) -> None:
    if nonfinite not in ("raise", "inf"):
        raise ValueError(f"nonfinite must be 'raise' or 'inf', got {nonfinite!r}")


def _finite_frames(name: str, rollout: FloatArray, nonfinite: str) -> NDArray[np.bool_]:
    """(T,) True where frame t of `rollout` (T, N, D) is all finite; raises per `nonfinite`."""
    finite: NDArray[np.bool_] = np.asarray(np.isfinite(rollout).all(axis=(1, 2)))
    if not finite.all() and nonfinite == "raise":
        t, i = np.argwhere(~np.isfinite(rollout).all(axis=2))[0]
        raise ValueError(
            f"{name} holds NaN or Inf (first at frame {t}, particle {i}): the rollout diverged; "
            "pass nonfinite='inf' to score diverged frames as inf"
        )
    return finite


def _rollout_pair(
    predicted: ArrayLike, ground_truth: ArrayLike, nonfinite: str
) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
    _check_nonfinite(nonfinite)
    pred = _float_array("predicted", predicted, "(T, N, D)", 3)
    truth = _float_array("ground_truth", ground_truth, "(T, N, D)", 3)
    if pred.shape != truth.shape:
        raise ValueError(
            f"predicted and ground_truth must have the same shape (T, N, D), "
            f"got {pred.shape} and {truth.shape}"
        )
    if not np.isfinite(truth).all():
        raise ValueError("ground_truth holds NaN or Inf; the reference data must be finite")
    return pred, truth, _finite_frames("predicted", pred, nonfinite)


# --------------------------------------------------------------------------- MSE


def mse_over_time(
    predicted: ArrayLike,
    ground_truth: ArrayLike,
    mask: ArrayLike | None = None,
    *,
    nonfinite: Nonfinite = "raise",
) -> FloatArray:
    """Per-frame mean squared error, (T,): mean over the particles selected by `mask` (N,) bool
    (default all) and over the D dimensions of (predicted - ground_truth)^2, both (T, N, D).

    Non-finite predictions raise ValueError, or with nonfinite="inf" give +inf for their frame.
    A finite prediction so large that its square overflows also gives +inf: it diverged too.
    """
    pred, truth, finite = _rollout_pair(predicted, ground_truth, nonfinite)
    keep = _particle_mask(mask, pred.shape[1])
    with np.errstate(over="ignore", invalid="ignore"):
        per_frame: FloatArray = np.mean((pred[:, keep] - truth[:, keep]) ** 2, axis=(1, 2))
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
    pred = _float_array("predicted_next", predicted_next, "(N, D)", 2)
    truth = _float_array("ground_truth_next", ground_truth_next, "(N, D)", 2)
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
    errors = _float_array("per_frame_mse", per_frame_mse, "(T,)", 1)
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


# --------------------------------------------------------------------------- pairwise blocks


def _rows_per_block(columns: int, arrays: int, memory_bytes: int) -> int:
    """Rows of a (rows, columns) float64 block so that `arrays` such blocks fit in memory."""
    return max(1, memory_bytes // (8 * arrays * max(columns, 1)))


def _squared_distances(a: FloatArray, b: FloatArray) -> FloatArray:
    """|a_i - b_j|^2, (n, m), from coordinate differences: exact zeros for equal points and no
    cancellation (|a|^2 + |b|^2 - 2 a.b loses everything when points are close and far from 0)."""
    out = np.zeros((a.shape[0], b.shape[0]))
    for d in range(a.shape[1]):
        diff = a[:, d, None] - b[None, :, d]
        out += diff * diff
    return out


def _blocks(a: FloatArray, b: FloatArray, memory_bytes: int) -> Iterator[tuple[slice, FloatArray]]:
    """Row blocks (rows of a, squared distances (rows, m)) of the a-to-b cost matrix."""
    step = _rows_per_block(b.shape[0], 3, memory_bytes)
    for start in range(0, a.shape[0], step):
        rows = slice(start, min(start + step, a.shape[0]))
        yield rows, _squared_distances(a[rows], b)


# --------------------------------------------------------------------------- optimal transport


def _assignment_size(n: int, m: int) -> int:
    return n if n == m else math.lcm(n, m)


def exact_optimal_transport(x: ArrayLike, y: ArrayLike, *, exact_max_points: int = 2048) -> float:
    """Exact W2^2 between the uniform distributions on x (N, D) and y (M, D).

    Solves an L x L assignment, L = N if N == M else lcm(N, M) (points repeated L/N and L/M
    times); raises ValueError when L > exact_max_points, since the cost matrix takes 8 L^2 bytes
    and the solver O(L^3) time.
    """
    xs, ys = _point_pair(x, y)
    n, m = xs.shape[0], ys.shape[0]
    size = _assignment_size(n, m)
    if size > exact_max_points:
        raise ValueError(
            f"exact optimal transport between {n} and {m} points needs a {size} x {size} "
            f"assignment, more than exact_max_points={exact_max_points}; raise the limit or "
            "use method='sinkhorn'"
        )
    if n != m:
        xs, ys = np.repeat(xs, size // n, axis=0), np.repeat(ys, size // m, axis=0)
    cost = _squared_distances(xs, ys)
    rows, cols = linear_sum_assignment(cost)
    return float(np.mean(cost[rows, cols]))


def _mean_cost(x: FloatArray, y: FloatArray) -> float:
    """mean_ij |x_i - y_j|^2 in O((N + M) D): var(x) + var(y) + |mean(x) - mean(y)|^2."""
    mx, my = x.mean(axis=0), y.mean(axis=0)
    return float(x.var(axis=0).sum() + y.var(axis=0).sum() + np.sum((mx - my) ** 2))


class _Cost:
    """The N x M squared-distance matrix, cached with its transpose if both fit in memory,
    otherwise recomputed in row blocks on each pass."""

    def __init__(self, x: FloatArray, y: FloatArray, memory_bytes: int) -> None:
        self.x, self.y, self.memory_bytes = x, y, memory_bytes
        self.matrix: FloatArray | None = None
        self.transposed: FloatArray | None = None
        # Cache + transpose + three blocks of scratch.
        if 2 * 8 * x.shape[0] * y.shape[0] <= memory_bytes // 2:
            self.matrix = _squared_distances(x, y)
            self.transposed = np.ascontiguousarray(self.matrix.T)

    def rows(self, transpose: bool) -> Iterator[tuple[slice, FloatArray]]:
        a, b = (self.y, self.x) if transpose else (self.x, self.y)
        cached = self.transposed if transpose else self.matrix
        if cached is None:
            yield from _blocks(a, b, self.memory_bytes)
            return
        step = _rows_per_block(b.shape[0], 2, self.memory_bytes // 2)
        for start in range(0, a.shape[0], step):
            rows = slice(start, min(start + step, a.shape[0]))
            yield rows, cached[rows]


def _softmin(
    cost: _Cost, potential: FloatArray, log_weight: float, eps: float, transpose: bool
) -> FloatArray:
    """The Sinkhorn update in the log domain: for every row i of the (transposed) cost,
    -eps * log sum_j exp(log_weight + (potential_j - C_ij) / eps)."""
    n = cost.y.shape[0] if transpose else cost.x.shape[0]
    out = np.empty(n)
    for rows, block in cost.rows(transpose):
        z = potential[None, :] - block
        z /= eps
        top = z.max(axis=1)
        z -= top[:, None]
        np.exp(z, out=z)
        out[rows] = -eps * (top + log_weight + np.log(z.sum(axis=1)))
    return out


def sinkhorn(
    x: ArrayLike,
    y: ArrayLike,
    *,
    epsilon: float = 1e-2,
    max_iterations: int = 10_000,
    tolerance: float = 1e-6,
    scaling: float = 0.5,
    overrelaxation: float = 1.8,
    memory_bytes: int = DEFAULT_MEMORY_BYTES,
) -> SinkhornResult:
    """Entropic optimal transport between the uniform distributions on x (N, D) and y (M, D).

    epsilon: regularisation relative to the mean pairwise cost mean_ij |x_i - y_j|^2; the
        absolute value is epsilon * mean cost (in the result). The log domain keeps any value
        numerically stable, but iterations grow roughly like 1 / epsilon, while the bias of the
        returned cost over W2^2 is at most epsilon_absolute * log(min(N, M)). The default
        suits clouds of thousands of points (the only ones `optimal_transport` sends here
        by default), where it lies above the squared particle spacing and the plan mixes
        fast; where the absolute epsilon is ~0.01-1 times the squared spacing (small sets)
        the plan is nearly a permutation and convergence can take very many iterations.
    tolerance: stop once the L1 error of the plan's row sums is at most this (column sums are
        exact after every update). Raises SinkhornConvergenceError after max_iterations
        updates in all (annealing stages included) or if the potentials become non-finite.
    scaling: epsilon annealing: start at the squared diameter of both sets, multiply by
        `scaling` per stage down to epsilon, warm-starting each stage from the last; early
        stages are solved only roughly (row error 1e-2).
    overrelaxation: the row potential moves `overrelaxation` times the Sinkhorn step (1 is
        plain Sinkhorn; values in (1, 2) take several times fewer iterations where the plan
        mixes slowly, Thibault et al. 2017). Try 1 if a problem does not converge.
    memory_bytes: float64 scratch budget; the cost matrix is cached only if it fits.

    The returned cost is that of a true coupling: the plan's small row-sum error is removed by
    the rounding of Altschuler, Weed and Rigollet (2017) before <P, C> is taken, so it is never
    below W2^2 (up to rounding). `lower_bound` is the dual value of the c-transformed
    potentials, never above W2^2: together they bracket the exact value.
    """
    xs, ys = _point_pair(x, y)
    if (
        not epsilon > 0
        or not 0 < scaling < 1
        or not tolerance > 0
        or not 0 < overrelaxation < 2
        or max_iterations < 1
    ):
        raise ValueError(
            "need epsilon > 0, 0 < scaling < 1, tolerance > 0, 0 < overrelaxation < 2 and "
            f"max_iterations >= 1, got epsilon={epsilon}, scaling={scaling}, "
            f"tolerance={tolerance}, overrelaxation={overrelaxation}, "
            f"max_iterations={max_iterations}"
        )
    # Centred on a common point: the rounding step uses coordinates, not only differences.
    centre = 0.5 * (xs.mean(axis=0) + ys.mean(axis=0))
    xs, ys = xs - centre, ys - centre
    mean_cost = _mean_cost(xs, ys)
    if mean_cost == 0.0:  # every point of both sets at one location: nothing to transport
        return SinkhornResult(0.0, 0.0, 0.0, 0, 0.0)
    eps = epsilon * mean_cost
    n, m = xs.shape[0], ys.shape[0]
    log_a, log_b = -math.log(n), -math.log(m)
    both = np.concatenate([xs, ys])
    schedule = []
    stage = float(np.sum((both.max(axis=0) - both.min(axis=0)) ** 2))  # squared diameter
    while stage > eps:
        schedule.append(stage)
        stage *= scaling
    schedule.append(eps)

    cost = _Cost(xs, ys, memory_bytes)
    f = np.zeros(n)
    iterations = 0
    with np.errstate(over="ignore"):
        for k, stage in enumerate(schedule):
            last = k == len(schedule) - 1
            target = tolerance if last else max(tolerance, _STAGE_TOLERANCE)
            g = _softmin(cost, f, log_a, stage, transpose=True)
            while True:
                # The f update measures the row sums of the plan (f, g) for free:
                # sum_j P_ij = a_i exp((f_i - f_new_i) / eps).
                f_new = _softmin(cost, g, log_b, stage, transpose=False)
                if not (np.isfinite(f_new).all() and np.isfinite(g).all()):
                    raise SinkhornConvergenceError(
                        "Sinkhorn potentials became non-finite; try overrelaxation=1"
                    )
                row_ratio = np.exp((f - f_new) / stage)
                error = float(np.mean(np.abs(row_ratio - 1.0)))
                if error <= target:
                    break
                if iterations >= max_iterations:
                    raise SinkhornConvergenceError(
                        f"Sinkhorn did not converge in {max_iterations} iterations: row "
                        f"marginal L1 error {error:.3g} > {target:.3g} at epsilon {stage:.3g} "
                        f"(target {eps:.3g}); raise max_iterations or epsilon"
                    )
                # Only f is overrelaxed: g stays the exact column update, so every plan
                # (f, g) checked above has exact column sums.
                f = f + overrelaxation * (f_new - f) if iterations else f_new
                g = _softmin(cost, f, log_a, stage, transpose=True)
                iterations += 1
            if not last:
                f = f_new
    upper = _rounded_cost(cost, f, g, row_ratio, eps)
    lower = _dual_lower_bound(cost, g)
    return SinkhornResult(upper, lower, eps, iterations, error)


def _dual_lower_bound(cost: _Cost, g: FloatArray) -> float:
    """mean(f) + mean(g) for f = g^c and then g = f^c (c-transforms): a feasible pair of the
    unregularised dual (f_i + g_j <= C_ij), so a lower bound on W2^2."""
    f = np.empty(cost.x.shape[0])
    for rows, block in cost.rows(transpose=False):
        f[rows] = (block - g[None, :]).min(axis=1)
    g = np.empty(cost.y.shape[0])
    for rows, block in cost.rows(transpose=True):
        g[rows] = (block - f[None, :]).min(axis=1)
    return float(np.mean(f) + np.mean(g))


def _rounded_cost(
    cost: _Cost, f: FloatArray, g: FloatArray, row_ratio: FloatArray, eps: float
) -> float:
    """<P, C> after projecting the plan P_ij = a_i b_j exp((f_i + g_j - C_ij) / eps), whose
    row sums are a_i * row_ratio_i and whose column sums are exact, onto the couplings.

    Rows with too much mass are scaled down (which leaves columns short), then the missing
    mass is added as the rank-one plan e_r e_c^T / |e_r|_1 (Altschuler et al. 2017, Alg. 2).
    """
    x, y = cost.x, cost.y
    n, m = x.shape[0], y.shape[0]
    log_ab = -math.log(n) - math.log(m)
    shrink = np.minimum(1.0, 1.0 / row_ratio)
    total, columns = 0.0, np.zeros(m)
    for rows, block in cost.rows(transpose=False):
        plan = np.exp((f[rows, None] + g[None, :] - block) / eps + log_ab)
        plan *= shrink[rows, None]
        total += float(np.sum(plan * block))
        columns += plan.sum(axis=0)
    missing_rows = np.maximum(0.0, (1.0 - shrink * row_ratio) / n)
    missing_cols = np.maximum(0.0, 1.0 / m - columns)
    mass = float(missing_rows.sum())
    if mass > 0.0:
        # e_r^T C e_c in closed form from |x - y|^2 = |x|^2 + |y|^2 - 2 x.y (centred inputs).
        mass_c = float(missing_cols.sum())
        cross = (
            mass_c * float(missing_rows @ np.sum(x * x, axis=1))
            + mass * float(missing_cols @ np.sum(y * y, axis=1))
            - 2.0 * float((missing_rows @ x) @ (missing_cols @ y))
        )
        total += max(0.0, cross) / mass
    return total


def optimal_transport(
    x: ArrayLike,
    y: ArrayLike,
    *,
    method: Literal["auto", "exact", "sinkhorn"] = "auto",
    exact_max_points: int = 2048,
    epsilon: float = 1e-2,
    max_iterations: int = 10_000,
    tolerance: float = 1e-6,
    memory_bytes: int = DEFAULT_MEMORY_BYTES,
) -> float:
    """Squared 2-Wasserstein distance between the uniform distributions on x (N, D), y (M, D).

    method "exact": `exact_optimal_transport` (ValueError if its L x L assignment, L = N for
    N == M else lcm(N, M), exceeds exact_max_points); "sinkhorn": the transport cost of
    `sinkhorn` (an upper bound, within epsilon * mean cost * log(min(N, M)) of W2^2); "auto":
    exact when L <= exact_max_points, else Sinkhorn.
    """
    if method not in ("auto", "exact", "sinkhorn"):
        raise ValueError(f"method must be 'auto', 'exact' or 'sinkhorn', got {method!r}")
    xs, ys = _point_pair(x, y)
    small = _assignment_size(xs.shape[0], ys.shape[0]) <= exact_max_points
    if method == "exact" or (method == "auto" and small):
        return exact_optimal_transport(xs, ys, exact_max_points=exact_max_points)
    result = sinkhorn(
        xs,
        ys,
        epsilon=epsilon,
        max_iterations=max_iterations,
        tolerance=tolerance,
        memory_bytes=memory_bytes,
    )
    return result.cost


# --------------------------------------------------------------------------- MMD


def _kernel_sum(a: FloatArray, b: FloatArray, bandwidth: float, memory_bytes: int) -> float:
    """sum_ij exp(-|a_i - b_j|^2 / (2 bandwidth^2)), in row blocks."""
    total = 0.0
    scale = -0.5 / bandwidth**2
    for _, block in _blocks(a, b, memory_bytes):
        block *= scale
        np.exp(block, out=block)
        total += float(block.sum())
    return total


def mmd(
    x: ArrayLike,
    y: ArrayLike,
    bandwidth: float = 0.1,
    *,
    unbiased: bool = False,
    memory_bytes: int = DEFAULT_MEMORY_BYTES,
) -> float:
    """Squared MMD between point sets x (N, D) and y (M, D) with the Gaussian kernel
    exp(-|a - b|^2 / (2 bandwidth^2)), bandwidth in position units.

    Biased (default): mean k(x, x') + mean k(y, y') - 2 mean k(x, y) over all pairs, diagonals
    included; >= 0 (rounding below 0 is clamped) and exactly 0 when y equals x. Unbiased:
    diagonals excluded from the first two means (needs N, M >= 2); may be negative.
    """
    xs, ys = _point_pair(x, y)
    if not bandwidth > 0 or not math.isfinite(bandwidth):
        raise ValueError(f"bandwidth must be a positive number, got {bandwidth}")
    n, m = int(xs.shape[0]), int(ys.shape[0])
    # The same routine for all three sums, so that y == x gives bit-identical terms and 0.
    kxx = _kernel_sum(xs, xs, bandwidth, memory_bytes)
    kyy = _kernel_sum(ys, ys, bandwidth, memory_bytes)
    kxy = _kernel_sum(xs, ys, bandwidth, memory_bytes) / (n * m)
    if not unbiased:
        return max(0.0, kxx / n**2 + kyy / m**2 - 2 * kxy)
    if n < 2 or m < 2:
        raise ValueError(f"the unbiased MMD needs at least 2 points per set, got {n} and {m}")
    # k(a, a) = exp(0) = 1 exactly, so the diagonal sums are n and m.
    return (kxx - n) / (n * (n - 1)) + (kyy - m) / (m * (m - 1)) - 2 * kxy


# --------------------------------------------------------------------------- baselines


def _baseline_start(
    initial_positions: ArrayLike,
    num_steps: int,
    min_frames: int,
    kinematic_mask: ArrayLike | None,
    ground_truth: ArrayLike | None,
) -> FloatArray:
    """The checked input frames (C + 1, N, D) of a baseline rollout of num_steps frames."""
    positions = _float_array("initial_positions", initial_positions, "(C + 1, N, D)", 3)
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
    truth = _float_array("ground_truth", ground_truth, "(num_steps, N, D)", 3)
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
) -> FloatArray:
    """The reference baseline: every particle keeps its last velocity.

    initial_positions: (C + 1, N, D), time-major, most recent last, C >= 1.
    Returns (num_steps, N, D): x_{t+1} = x_t + v with v = x[-1] - x[-2]. Kinematic particles
    (`kinematic_mask` (N,) bool) take `ground_truth` (num_steps, N, D) instead, as in learned
    rollouts; the two must be given together.
    """
    positions = _baseline_start(initial_positions, num_steps, 2, kinematic_mask, ground_truth)
    last, velocity = positions[-1], positions[-1] - positions[-2]
    steps = np.arange(1, num_steps + 1, dtype=np.float64)[:, None, None]
    rollout: FloatArray = last[None] + steps * velocity[None]
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


# --------------------------------------------------------------------------- deposit

# The robust ends of the sand: the 1st and 99th percentiles, so that the 1% of particles
# farthest out on either side (a few grains thrown loose) do not set how wide or high it is.
DEPOSIT_PERCENTILES = (1.0, 99.0)
# x runs along the floor, y up (gravity along -y) in this project's scenes and DeepMind's 2D
# datasets: runout is measured along axis 0, height along axis 1.
RUNOUT_AXIS, HEIGHT_AXIS = 0, 1


def _percentiles(values: FloatArray, axis: int = -1) -> FloatArray:
    """The DEPOSIT_PERCENTILES of `values` along `axis` (first axis of the result: 1st, 99th),
    interpolated linearly between order statistics."""
    result: FloatArray = np.percentile(values, DEPOSIT_PERCENTILES, axis=axis, method="linear")
    return result


def _selected_frame(
    name: str, positions: ArrayLike, mask: ArrayLike | None, axis: int, nonfinite: str
) -> FloatArray | None:
    """The coordinate `axis` of the particles of one frame (N, D) selected by mask; None when
    one of their positions is non-finite and nonfinite == "inf" (raises for "raise")."""
    _check_nonfinite(nonfinite)
    frame = _float_array(name, positions, "(N, D)", 2)
    if frame.shape[1] <= axis:
        raise ValueError(f"{name} needs at least {axis + 1} dimensions, got {frame.shape}")
    selected = frame[_particle_mask(mask, frame.shape[0])]
    if not np.isfinite(selected).all():
        if nonfinite == "raise":
            raise ValueError(
                f"{name} holds NaN or Inf: the rollout diverged; pass nonfinite='inf' to score "
                "it as inf"
            )
        return None
    return selected[:, axis]


def runout_extent(
    positions: ArrayLike, mask: ArrayLike | None = None, *, nonfinite: Nonfinite = "raise"
) -> float:
    """How wide the deposit is: the 99th minus the 1st percentile of x (axis 0) over the
    particles of one frame, positions (N, D), selected by `mask` (N,) bool (default all; pass
    the non-kinematic ones), in position units.

    Percentiles interpolate linearly between order statistics (numpy's default, Hyndman and
    Fan's type 7): of M sorted values v_0 <= ... <= v_{M-1} the p-th percentile lies at index
    p / 100 * (M - 1). The 1% of particles farthest out on either side do not count, so a few
    grains thrown loose do not set the width. A selected particle with a non-finite position
    raises ValueError, or with nonfinite="inf" gives inf.
    """
    x = _selected_frame("positions", positions, mask, RUNOUT_AXIS, nonfinite)
    if x is None:
        return math.inf
    low, high = _percentiles(x)
    return float(high - low)


def front_positions(
    trajectory: ArrayLike, mask: ArrayLike | None = None, *, nonfinite: Nonfinite = "raise"
) -> FloatArray:
    """Where the sand's fronts are in every frame of trajectory (T, N, D): (T, 2), column 0
    the 1st and column 1 the 99th percentile of x (axis 0) over the particles selected by
    `mask` (N,) bool, interpolated as in `runout_extent` (whose value for a frame is column 1
    minus column 0). For a pile spreading both ways these are its left and right fronts.

    A frame in which a selected particle has a non-finite position raises ValueError, or with
    nonfinite="inf" is (inf, inf).
    """
    _check_nonfinite(nonfinite)
    frames = _float_array("trajectory", trajectory, "(T, N, D)", 3)
    selected = frames[:, _particle_mask(mask, frames.shape[1])]
    finite = _finite_frames("trajectory", selected, nonfinite)
    fronts = np.full((frames.shape[0], 2), np.inf)
    if finite.any():
        fronts[finite] = _percentiles(selected[finite, :, RUNOUT_AXIS], axis=1).T
    return fronts


def pile_height(
    positions: ArrayLike,
    mask: ArrayLike | None,
    floor: float,
    *,
    nonfinite: Nonfinite = "raise",
) -> float:
    """How high the deposit piles: the 99th percentile of y (axis 1; D >= 2) over the particles
    of one frame, positions (N, D), selected by `mask` (N,) bool (None: all), minus `floor`
    (see `pile_floor`), in position units. Interpolated as in `runout_extent`; the 1% of
    particles highest up (grains thrown loose, a few riding on top) do not count. A selected
    particle with a non-finite position raises ValueError, or with nonfinite="inf" gives inf.
    """
    if not math.isfinite(floor):
        raise ValueError(f"floor must be a finite number, got {floor}")
    y = _selected_frame("positions", positions, mask, HEIGHT_AXIS, nonfinite)
    if y is None:
        return math.inf
    return float(_percentiles(y)[1] - floor)


def pile_floor(bounds: Sequence[Sequence[float]] | None, first_frame: ArrayLike) -> float:
    """The floor `pile_height` measures from: the lower y bound of the scene's box, bounds
    (D pairs (lo, hi)), when there is one; otherwise the lowest y of any particle of
    `first_frame` (N, D), frame 0 of the ground truth, kinematic particles included (a floor
    made of boundary particles is the floor)."""
    if bounds is not None:
        box = np.asarray(bounds, dtype=np.float64)
        if box.ndim != 2 or box.shape[1] != 2 or box.shape[0] <= HEIGHT_AXIS:
            raise ValueError(f"bounds must be D >= 2 pairs (lo, hi), got {box.tolist()}")
        return float(box[HEIGHT_AXIS, 0])
    frame = _finite_points("first_frame", first_frame)
    if frame.shape[1] <= HEIGHT_AXIS:
        raise ValueError(f"first_frame needs at least 2 dimensions, got {frame.shape}")
    return float(frame[:, HEIGHT_AXIS].min())


# The figures of `deposit` and `deposit_ratios` (scalars) and the fronts of `deposit` (curves).
DEPOSIT_FIGURES = (
    "runout",
    "pile_height",
    "neighbours",
    "runout_ratio",
    "height_ratio",
    "density_ratio",
)
DEPOSIT_CURVES = ("front_x_p1", "front_x_p99")
# Each ratio of `deposit_ratios` and the figure of `deposit` it compares.
_RATIOS = {"runout_ratio": "runout", "height_ratio": "pile_height", "density_ratio": "neighbours"}


def deposit(
    positions: ArrayLike,
    mask: ArrayLike,
    floor: float | None,
    *,
    radius: float | None = None,
    bounds: Sequence[Sequence[float]] | None = None,
    periodic: Sequence[bool] | None = None,
) -> dict[str, Any]:
    """Where the sand of a rollout, positions (S, N, D), ends up, over the particles in `mask`
    (N,) bool (the non-kinematic ones), from its last frame:

      runout        runout_extent: the 99th minus the 1st percentile of x, how wide it lies
      pile_height   pile_height: the 99th percentile of y minus `floor` (see
                    gns.metrics.pile_floor); only with a floor and D >= 2
      neighbours    mean_neighbours: other particles within `radius` per particle (minimum
                    image on `periodic` axes of `bounds`); only with a radius
      front_x_p1, front_x_p99
                    (S,) arrays: the 1st and the 99th percentile of x in every frame
                    (front_positions), how the fronts advance

    A rollout whose last frame is not finite (it diverged) has inf for the three scalars, and
    inf fronts from the first non-finite frame on.
    """
    frames = _float_array("positions", positions, "(S, N, D)", 3)
    keep = _particle_mask(mask, frames.shape[1])
    last = frames[-1]
    fronts = front_positions(frames, keep, nonfinite="inf")
    figures: dict[str, Any] = {"runout": runout_extent(last, keep, nonfinite="inf")}
    if floor is not None and frames.shape[-1] > HEIGHT_AXIS:
        figures["pile_height"] = pile_height(last, keep, floor, nonfinite="inf")
    if radius is not None:
        finite = bool(np.isfinite(last[keep]).all())
        packed = mean_neighbours(last[keep], radius, bounds, periodic) if finite else math.inf
        figures["neighbours"] = packed
    figures.update(front_x_p1=fronts[:, 0], front_x_p99=fronts[:, 1])
    return figures


def ratio_of(ours: float, reference: float) -> float:
    """ours / reference; with a reference of 0 (nothing to divide by), 1 when ours is 0 too,
    else inf: never NaN."""
    if reference == 0:
        return 1.0 if ours == 0 else math.inf
    return ours / reference


def deposit_ratios(ours: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """Two `deposit`s compared, ours over the ground truth's, for the figures both have:
    runout_ratio (runout), height_ratio (pile_height) and density_ratio (neighbours). 1 is
    right; a simulator that loses volume packs its particles ever closer (density_ratio above
    1) and often spreads too little (runout_ratio below 1); inf: ours diverged."""
    return {
        ratio: ratio_of(float(ours[key]), float(truth[key]))
        for ratio, key in _RATIOS.items()
        if key in ours and key in truth
    }


def mean_neighbours(
    positions: ArrayLike,
    radius: float,
    bounds: Sequence[Sequence[float]] | None = None,
    periodic: Sequence[bool] | None = None,
) -> float:
    """The mean number of other particles within `radius` of a particle of one frame (N, D),
    minimum image on periodic axes: how densely the frame is packed."""
    from gns import radius_graph

    x = np.asarray(positions, dtype=np.float64)
    if len(x) == 0:
        return 0.0
    kwargs: dict[str, Any] = {"self_edges": False}
    if periodic is not None and any(periodic):
        if bounds is None:
            raise ValueError("mean_neighbours: periodic axes need the bounds of the box")
        box = np.asarray(bounds, dtype=np.float64)
        x = x - box[:, 0]
        kwargs.update(box=(box[:, 1] - box[:, 0]).tolist(), periodic=list(periodic))
    return radius_graph(x, radius, **kwargs).shape[1] / len(x)


# --------------------------------------------------------------------------- summary


def evaluate_rollout(
    predicted: ArrayLike,
    ground_truth: ArrayLike,
    *,
    mask: ArrayLike | None = None,
    horizons: Sequence[int | None] = DEFAULT_HORIZONS,
    distribution_every: int = 1,
    bandwidth: float = 0.1,
    ot_method: Literal["auto", "exact", "sinkhorn"] = "auto",
    exact_max_points: int = 2048,
    epsilon: float = 1e-2,
    nonfinite: Nonfinite = "raise",
) -> dict[str, Any]:
    """All metrics of one rollout: predicted and ground_truth (T, N, D), mask (N,) bool of the
    particles that count (e.g. the non-kinematic ones; default all).

    Returns a dict of
      "mse": (T,) per-frame MSE;  "mse@h" / "mse@full": floats from `horizon_mse`;
      "frames": (K,) int64, the frames 0, s, 2s, ... (s = distribution_every) that get the
          distributional metrics, which cost O(N^2) or more per frame;
      "ot": (K,) W2^2 per evaluated frame (`optimal_transport`); "ot_mean": their mean;
      "mmd": (K,) biased MMD^2 per evaluated frame (`mmd`); "mmd_mean": their mean.
    OT and MMD compare the masked particles of both frames. With nonfinite="inf" a diverged
    frame scores inf for all three metrics (and so do the means that include it). A Sinkhorn
    frame that does not converge raises SinkhornConvergenceError rather than report a guess.
    """
    pred, truth, finite = _rollout_pair(predicted, ground_truth, nonfinite)
    keep = _particle_mask(mask, pred.shape[1])
    if (
        isinstance(distribution_every, bool)
        or not isinstance(distribution_every, int | np.integer)
        or distribution_every < 1
    ):
        raise ValueError(
            f"distribution_every must be a positive integer, got {distribution_every!r}"
        )
    per_frame = mse_over_time(pred, truth, keep, nonfinite=nonfinite)
    frames = np.arange(0, pred.shape[0], distribution_every, dtype=np.int64)
    ot = np.full(frames.shape, np.inf)
    discrepancy = np.full(frames.shape, np.inf)
    for k, t in enumerate(frames):
        if not finite[t]:
            continue
        a, b = pred[t, keep], truth[t, keep]
        ot[k] = optimal_transport(
            a, b, method=ot_method, exact_max_points=exact_max_points, epsilon=epsilon
        )
        discrepancy[k] = mmd(a, b, bandwidth)
    summary: dict[str, Any] = {"mse": per_frame}
    summary.update(horizon_mse(per_frame, horizons))
    summary.update(
        frames=frames,
        ot=ot,
        ot_mean=float(np.mean(ot)),
        mmd=discrepancy,
        mmd_mean=float(np.mean(discrepancy)),
    )
    return summary
