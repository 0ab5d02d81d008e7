"""How far apart two point clouds are as distributions: optimal transport and MMD (sections
B.4, C.4). Both compare the two clouds as uniform empirical distributions, so they need no
particle correspondence and are invariant to permutations of the particles (B.4).

All functions take numpy arrays (anything `np.asarray` accepts) of points (N, D) and (M, D),
which must be finite (gns.metrics.evaluate_rollout scores a diverged frame inf before it gets
here), compute in float64 and return Python floats.

Optimal transport is the squared 2-Wasserstein distance W2^2 between the uniform distributions
on the two point sets, in squared position units (the same units as the MSE):

- exact: with N == M an assignment problem on squared distances; W2^2 is the mean matched cost.
  With N != M the uniform weights 1/N and 1/M are integer multiples of 1/L for L = lcm(N, M);
  an optimal transportation plan with integer supplies has integer entries, so repeating every
  point of x L/N times and of y L/M times turns the problem into an exact L x L assignment (no
  LP solver). `exact_max_points` bounds L. The assignment is solved by lapx's Jonker-Volgenant
  solver (`lap.lapjvh`, float64; scipy's `linear_sum_assignment` where lapx is not installed)
  on a preconditioned cost with the same optimal assignments (`_assignment_cost`): the
  Gaussian (affine) optimal map between the two clouds is taken out first, which leaves the
  solver far fewer conflicts to resolve between two clouds far apart. W2^2 is then the mean of
  the original squared distances over the assignment found, so it equals the plain
  assignment's to float round-off.
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
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, Literal, get_args

import numpy as np
from numpy.typing import ArrayLike
from scipy.optimize import linear_sum_assignment  # type: ignore[import-untyped]
from scipy.spatial.distance import cdist  # type: ignore[import-untyped]

from gns.metric_inputs import FloatArray, point_pair
from gns.periodic import minimum_image

__all__ = [
    "DEFAULT_MEMORY_BYTES",
    "EXACT_MAX_POINTS",
    "OT_METHODS",
    "OtMethod",
    "SinkhornConvergenceError",
    "SinkhornResult",
    "exact_optimal_transport",
    "mmd",
    "optimal_transport",
    "sinkhorn",
]

# How `optimal_transport` solves: exact, Sinkhorn, or exact when small enough.
OtMethod = Literal["auto", "exact", "sinkhorn"]
# The largest assignment "auto" solves exactly: 8 L^2 bytes (134 MB) for its cost matrix. Exact
# took 0.72 s on 2290 3D points where Sinkhorn took 58 s (a sand-3d demo frame), and 4.1 s at
# 4096 (2026-11-25, Zen 4, the other core busy; scipy's solver, before the preconditioned
# lapx one, which took 5 times less on sand2d-taichi's frames: docs/performance.md).
EXACT_MAX_POINTS = 4096
OT_METHODS: tuple[OtMethod, ...] = get_args(OtMethod)
# Row-sum error to which Sinkhorn solves the annealing stages before the last one.
_STAGE_TOLERANCE = 1e-2
# Bytes of float64 scratch per block of pairwise work (distances, kernels, Sinkhorn blocks).
DEFAULT_MEMORY_BYTES = 64 * 2**20


def _find_lapjvh() -> Callable[..., Any] | None:
    """lapx's lapjvh, the fast exact assignment solver; None where the module `lap` is missing
    or is the older `lap` package, which installs the same module without lapjvh."""
    try:
        import lap
    except ImportError:
        return None
    found: Callable[..., Any] | None = getattr(lap, "lapjvh", None)
    return found


_lapjvh = _find_lapjvh()


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


# --------------------------------------------------------------------------- pairwise blocks


def _rows_per_block(columns: int, arrays: int, memory_bytes: int) -> int:
    """Rows of a (rows, columns) float64 block so that `arrays` such blocks fit in memory."""
    return max(1, memory_bytes // (8 * arrays * max(columns, 1)))


def _on_torus(period: ArrayLike | None) -> bool:
    """Whether `period` (gns.periodic) makes any axis periodic."""
    return period is not None and bool(np.any(np.asarray(period) > 0))


def _squared_distances(
    a: FloatArray, b: FloatArray, period: FloatArray | None = None
) -> FloatArray:
    """|a_i - b_j|^2, (n, m), from coordinate differences: exact zeros for equal points and no
    cancellation (|a|^2 + |b|^2 - 2 a.b loses everything when points are close and far from 0).
    With a `period` (gns.periodic), the minimum image on its periodic axes: the torus.
    Without one, scipy's cdist: the same sum of squared coordinate differences, a few times
    faster than the loop below."""
    if not _on_torus(period):
        out: FloatArray = cdist(a, b, "sqeuclidean")
        return out
    out = np.zeros((a.shape[0], b.shape[0]))
    for d in range(a.shape[1]):
        diff = a[:, d, None] - b[None, :, d]
        if period is not None and period[d] > 0:
            diff -= period[d] * np.round(diff / period[d])
        out += diff * diff
    return out


def _blocks(
    a: FloatArray, b: FloatArray, memory_bytes: int, period: FloatArray | None = None
) -> Iterator[tuple[slice, FloatArray]]:
    """Row blocks (rows of a, squared distances (rows, m)) of the a-to-b cost matrix."""
    step = _rows_per_block(b.shape[0], 3, memory_bytes)
    for start in range(0, a.shape[0], step):
        rows = slice(start, min(start + step, a.shape[0]))
        yield rows, _squared_distances(a[rows], b, period)


# --------------------------------------------------------------------------- optimal transport


def _assignment_size(n: int, m: int) -> int:
    return n if n == m else math.lcm(n, m)


def exact_optimal_transport(
    x: ArrayLike,
    y: ArrayLike,
    *,
    exact_max_points: int = EXACT_MAX_POINTS,
    period: FloatArray | None = None,
) -> float:
    """Exact W2^2 between the uniform distributions on x (N, D) and y (M, D) (on the torus of
    `period` when given, gns.periodic).

    Solves an L x L assignment, L = N if N == M else lcm(N, M) (points repeated L/N and L/M
    times); raises ValueError when L > exact_max_points, since the cost matrix takes 8 L^2 bytes
    and the solver O(L^3) time. The assignment is lapx's `lapjvh` (scipy's
    `linear_sum_assignment` without lapx) on the preconditioned cost of `_assignment_cost`;
    the value is the mean squared distance over it, scipy's own to float round-off.
    """
    xs, ys = point_pair(x, y)
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
    return _assignment_cost(xs, ys, period)


def _solve_assignment(cost: FloatArray) -> tuple[np.ndarray, np.ndarray]:
    """An optimal assignment (rows, cols) of the square cost matrix: lapx's Jonker-Volgenant
    solver in float64 (several times faster than scipy's on clouds of sand), else scipy's."""
    if _lapjvh is not None:
        rows, cols = _lapjvh(cost, return_cost=False, precision="float64")
        return np.asarray(rows), np.asarray(cols)
    rows, cols = linear_sum_assignment(cost)
    return rows, cols


def _gaussian_map_factor(x: FloatArray, y: FloatArray) -> FloatArray | None:
    """S = A^(1/2) for the optimal affine map x -> mean(y) + A (x - mean(x)) between Gaussians
    of the clouds' means and covariances (A = Sx^-1/2 (Sx^1/2 Sy Sx^1/2)^1/2 Sx^-1/2, symmetric
    positive definite), or None where a covariance is (nearly) singular."""

    def symmetric_power(m: FloatArray, power: float) -> tuple[FloatArray, FloatArray]:
        w, v = np.linalg.eigh(m)
        return (v * w**power) @ v.T, w

    sx = np.cov(x, rowvar=False, bias=True).reshape(x.shape[1], x.shape[1])
    sy = np.cov(y, rowvar=False, bias=True).reshape(y.shape[1], y.shape[1])
    for w in (np.linalg.eigvalsh(sx), np.linalg.eigvalsh(sy)):
        if not np.all(np.isfinite(w)) or w.min() <= 1e-9 * max(w.max(), 0.0):
            return None
    root, _ = symmetric_power(sx, 0.5)
    inverse_root, _ = symmetric_power(sx, -0.5)
    middle, _ = symmetric_power(root @ sy @ root, 0.5)
    a = inverse_root @ middle @ inverse_root
    factor, w = symmetric_power(0.5 * (a + a.T), 0.5)
    if not np.all(np.isfinite(factor)) or w.min() <= 1e-9 * w.max():
        return None
    return factor


def _assignment_cost(xs: FloatArray, ys: FloatArray, period: FloatArray | None) -> float:
    """Mean |x_i - y_sigma(i)|^2 over an optimal assignment sigma of equally many points.

    The solver gets a preconditioned cost with the same optimal assignments: with the
    Gaussian map's A (`_gaussian_map_factor`, S = A^1/2) and centred points, p_i = S (x_i -
    mean x) and q_j = S^-1 (y_j - mean y), |p_i - q_j|^2 equals |x_i - y_j|^2 plus a term of
    row i plus a term of column j (expand both), which adds the same constant to every
    assignment's total. It is small where the affine map is right, so most rows find their
    column at once. The figure itself is the mean of the original squared distances over the
    assignment found. On a torus (`period`) the squared distances are solved as they are.
    """
    if _on_torus(period):
        solved = _squared_distances(xs, ys, period)
    else:
        xc, yc = xs - xs.mean(axis=0), ys - ys.mean(axis=0)
        factor = _gaussian_map_factor(xc, yc) if xs.shape[0] > 1 else None
        if factor is None:  # the translation alone: the mean difference taken out
            solved = _squared_distances(xc, yc)
        else:
            solved = _squared_distances(xc @ factor, yc @ np.linalg.inv(factor))
    rows, cols = _solve_assignment(solved)
    # Only the L matched distances, not the whole L x L matrix of original costs (which took
    # a tenth of the time of gns eval's OT on sand2d-taichi, beside the solver).
    matched = minimum_image(xs[rows] - ys[cols], None if period is None else np.asarray(period))
    return float(np.mean(np.sum(matched * matched, axis=1)))


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
    xs, ys = point_pair(x, y)
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
    method: OtMethod = "auto",
    exact_max_points: int = EXACT_MAX_POINTS,
    epsilon: float = 1e-2,
    max_iterations: int = 10_000,
    tolerance: float = 1e-6,
    memory_bytes: int = DEFAULT_MEMORY_BYTES,
    period: FloatArray | None = None,
) -> float:
    """Squared 2-Wasserstein distance between the uniform distributions on x (N, D), y (M, D);
    on the torus of `period` (gns.periodic) with the exact solver only (ValueError otherwise).

    method "exact": `exact_optimal_transport` (ValueError if its L x L assignment, L = N for
    N == M else lcm(N, M), exceeds exact_max_points); "sinkhorn": the transport cost of
    `sinkhorn` (an upper bound, within epsilon * mean cost * log(min(N, M)) of W2^2); "auto":
    exact when L <= exact_max_points, else Sinkhorn.
    """
    if method not in OT_METHODS:
        raise ValueError(f"method must be 'auto', 'exact' or 'sinkhorn', got {method!r}")
    xs, ys = point_pair(x, y)
    small = _assignment_size(xs.shape[0], ys.shape[0]) <= exact_max_points
    if method == "exact" or (method == "auto" and small):
        return exact_optimal_transport(xs, ys, exact_max_points=exact_max_points, period=period)
    if period is not None:
        raise ValueError(
            f"optimal transport on a periodic box is exact only: {xs.shape[0]} and "
            f"{ys.shape[0]} points need more than exact_max_points={exact_max_points}"
        )
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


def _kernel_sum(
    a: FloatArray,
    b: FloatArray,
    bandwidth: float,
    memory_bytes: int,
    period: FloatArray | None = None,
) -> float:
    """sum_ij exp(-|a_i - b_j|^2 / (2 bandwidth^2)), in row blocks."""
    total = 0.0
    scale = -0.5 / bandwidth**2
    for _, block in _blocks(a, b, memory_bytes, period):
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
    period: FloatArray | None = None,
) -> float:
    """Squared MMD between point sets x (N, D) and y (M, D) with the Gaussian kernel
    exp(-|a - b|^2 / (2 bandwidth^2)), bandwidth in position units; |a - b| the minimum image
    on the periodic axes of `period` (gns.periodic) when given.

    Biased (default): mean k(x, x') + mean k(y, y') - 2 mean k(x, y) over all pairs, diagonals
    included; >= 0 (rounding below 0 is clamped) and exactly 0 when y equals x. Unbiased:
    diagonals excluded from the first two means (needs N, M >= 2); may be negative.
    """
    xs, ys = point_pair(x, y)
    if not bandwidth > 0 or not math.isfinite(bandwidth):
        raise ValueError(f"bandwidth must be a positive number, got {bandwidth}")
    n, m = int(xs.shape[0]), int(ys.shape[0])
    # The same routine for all three sums, so that y == x gives bit-identical terms and 0.
    kxx = _kernel_sum(xs, xs, bandwidth, memory_bytes, period)
    kyy = _kernel_sum(ys, ys, bandwidth, memory_bytes, period)
    kxy = _kernel_sum(xs, ys, bandwidth, memory_bytes, period) / (n * m)
    if not unbiased:
        return max(0.0, kxx / n**2 + kyy / m**2 - 2 * kxy)
    if n < 2 or m < 2:
        raise ValueError(f"the unbiased MMD needs at least 2 points per set, got {n} and {m}")
    # k(a, a) = exp(0) = 1 exactly, so the diagonal sums are n and m.
    return (kxx - n) / (n * (n - 1)) + (kyy - m) / (m * (m - 1)) - 2 * kxy
