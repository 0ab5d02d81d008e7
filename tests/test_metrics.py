"""Evaluation metrics (B.4, C.4) against independent oracles.

Oracles: hand-computed numbers, brute force over all permutations (exact OT), scipy's LP solver
(exact OT between sets of different sizes), analytic identities of W2 (translation, the
mean/centred split), a direct double loop (MMD), the closed form of MMD^2 between Gaussians,
kinematics (constant velocity and constant acceleration) for the baselines, and the geometry
of lattices whose percentiles fall on lattice sites (the deposit: runout, fronts, height).

Statistical tolerances (seeds are fixed) allow 5 standard errors, a false failure about once
in 3.5 million runs.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from data_helpers import SAND
from gns import distances
from gns.baselines import constant_velocity_rollout, static_rollout
from gns.deposit import (
    deposit,
    deposit_ratios,
    front_positions,
    pile_base,
    pile_floor,
    pile_height,
    ratio_of,
    runout_extent,
)
from gns.distances import (
    SinkhornConvergenceError,
    exact_optimal_transport,
    mmd,
    optimal_transport,
    sinkhorn,
)
from gns.metrics import evaluate_rollout, horizon_mse, mse_over_time, one_step_mse
from scipy.optimize import linear_sum_assignment, linprog


def brute_force_ot(x, y):
    """min over permutations p of mean_i |x_i - y_p(i)|^2, N == M <= 7."""
    cost = ((x[:, None, :] - y[None, :, :]) ** 2).sum(-1)
    perms = np.array(list(itertools.permutations(range(len(x)))))
    return cost[np.arange(len(x)), perms].mean(axis=1).min()


def lp_ot(x, y):
    """The transportation LP over couplings with marginals 1/N and 1/M, solved by HiGHS."""
    n, m = len(x), len(y)
    cost = ((x[:, None, :] - y[None, :, :]) ** 2).sum(-1)
    rows = np.kron(np.eye(n), np.ones((1, m)))  # sum_j P_ij
    cols = np.kron(np.ones((1, n)), np.eye(m))  # sum_i P_ij
    a_eq = np.vstack([rows, cols])
    b_eq = np.concatenate([np.full(n, 1 / n), np.full(m, 1 / m)])
    result = linprog(cost.ravel(), A_eq=a_eq, b_eq=b_eq, bounds=(0, None), method="highs")
    assert result.success
    return result.fun


def loop_mmd(x, y, bandwidth, unbiased=False):
    def k(a, b):
        return math.exp(
            -sum((ai - bi) ** 2 for ai, bi in zip(a, b, strict=True)) / (2 * bandwidth**2)
        )

    def mean_k(a, b, skip_diagonal):
        total, count = 0.0, 0
        for i, ai in enumerate(a):
            for j, bj in enumerate(b):
                if skip_diagonal and i == j:
                    continue
                total += k(ai, bj)
                count += 1
        return total / count

    return mean_k(x, x, unbiased) + mean_k(y, y, unbiased) - 2 * mean_k(x, y, skip_diagonal=False)


# --------------------------------------------------------------------------- MSE


def rollout_pair():
    """T = 2, N = 3, D = 2 with hand-picked errors."""
    truth = np.arange(12, dtype=float).reshape(2, 3, 2)
    error = np.array([[[1, 0], [0, 2], [3, 4]], [[0, 0], [1, 1], [0, -2]]], dtype=float)
    return truth + error, truth


def test_mse_over_time_matches_hand_computation():
    predicted, truth = rollout_pair()
    # Frame 0: (1 + 4 + 25) / 6 = 5; frame 1: (0 + 2 + 4) / 6 = 1.
    np.testing.assert_allclose(mse_over_time(predicted, truth), [5.0, 1.0], rtol=1e-15)
    # Particles 0 and 2 only: (1 + 25) / 4 = 6.5 and (0 + 4) / 4 = 1.
    mask = np.array([True, False, True])
    np.testing.assert_allclose(mse_over_time(predicted, truth, mask), [6.5, 1.0], rtol=1e-15)
    assert one_step_mse(predicted[0], truth[0], mask) == pytest.approx(6.5, rel=1e-15)


def test_mse_over_time_matches_a_loop_on_random_rollouts():
    rng = np.random.default_rng(0)
    predicted, truth = rng.normal(size=(4, 5, 3)), rng.normal(size=(4, 5, 3))
    mask = np.array([True, False, True, True, False])
    expected = []
    for t in range(4):
        terms = [
            (predicted[t, i, d] - truth[t, i, d]) ** 2
            for i in range(5)
            if mask[i]
            for d in range(3)
        ]
        expected.append(sum(terms) / len(terms))
    np.testing.assert_allclose(mse_over_time(predicted, truth, mask), expected, rtol=1e-13)


def test_a_diverged_rollout_raises_or_scores_inf_never_nan():
    predicted, truth = rollout_pair()
    predicted[1, 2, 0] = np.nan
    with pytest.raises(ValueError, match=r"predicted.*frame 1, particle 2.*diverged"):
        mse_over_time(predicted, truth)
    per_frame = mse_over_time(predicted, truth, nonfinite="inf")
    assert per_frame[0] == 5.0 and per_frame[1] == np.inf
    assert horizon_mse(per_frame, (1, None)) == {"mse@1": 5.0, "mse@full": np.inf}
    # A prediction so large that its square overflows has diverged as well.
    predicted[1, 2, 0] = 1e200
    assert mse_over_time(predicted, truth)[1] == np.inf
    truth[0, 0, 1] = np.inf
    with pytest.raises(ValueError, match="ground_truth"):
        mse_over_time(predicted, truth, nonfinite="inf")


@pytest.mark.parametrize(
    ("predicted_shape", "truth_shape", "mask", "match"),
    [
        ((2, 3, 2), (2, 3, 3), None, r"same shape \(T, N, D\)"),
        ((3, 2), (3, 2), None, r"predicted must be .*\(T, N, D\), got \(3, 2\)"),
        ((0, 3, 2), (0, 3, 2), None, r"non-empty"),
        ((2, 3, 2), (2, 3, 2), np.array([1, 0, 1]), r"mask must be a boolean array of shape"),
        ((2, 3, 2), (2, 3, 2), np.array([True, False]), r"shape \(3,\)"),
        ((2, 3, 2), (2, 3, 2), np.zeros(3, dtype=bool), r"selects no particle"),
    ],
)
def test_mse_rejects_bad_shapes_and_masks(predicted_shape, truth_shape, mask, match):
    with pytest.raises(ValueError, match=match):
        mse_over_time(np.zeros(predicted_shape), np.zeros(truth_shape), mask)


def test_mse_rejects_an_unknown_nonfinite_policy():
    with pytest.raises(ValueError, match="nonfinite"):
        mse_over_time(np.zeros((1, 1, 1)), np.zeros((1, 1, 1)), nonfinite="ignore")


def test_horizon_means_match_hand_sums_and_skip_horizons_past_the_end():
    per_frame = np.array([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
    result = horizon_mse(per_frame, (1, 5, 6, 10, None))
    # (1 + 2 + 3 + 4 + 5) / 5 = 3; all six: 21 / 6 = 3.5; 10 > 6 frames is left out.
    assert result == {"mse@1": 1.0, "mse@5": 3.0, "mse@6": 3.5, "mse@full": 3.5}
    assert list(horizon_mse(per_frame, name="ot")) == ["ot@1", "ot@5", "ot@full"]


@pytest.mark.parametrize("horizon", [0, -1, 2.5, True, "5"])
def test_horizon_mse_rejects_bad_horizons(horizon):
    with pytest.raises(ValueError, match="horizons must be positive integers"):
        horizon_mse([1.0, 2.0], (horizon,))


@pytest.mark.parametrize("values", [[1.0, np.nan], [1.0, -1.0], [], [[1.0]]])
def test_horizon_mse_rejects_nan_negative_or_misshapen_errors(values):
    with pytest.raises(ValueError, match="per_frame_mse"):
        horizon_mse(values)


# --------------------------------------------------------------------------- exact OT


@pytest.mark.parametrize(
    ("n", "d", "seed"), [(1, 2, 0), (2, 1, 1), (5, 2, 2), (6, 3, 3), (7, 2, 4)]
)
def test_exact_ot_equals_brute_force_over_all_permutations(n, d, seed):
    rng = np.random.default_rng(seed)
    x, y = rng.normal(size=(n, d)), rng.normal(size=(n, d))
    expected = brute_force_ot(x, y)
    assert exact_optimal_transport(x, y) == pytest.approx(expected, rel=1e-12)
    assert optimal_transport(x, y, method="exact") == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize(("n", "m", "seed"), [(3, 5, 0), (4, 6, 1), (2, 7, 2), (6, 4, 3)])
def test_exact_ot_between_sets_of_different_sizes_equals_the_transportation_lp(n, m, seed):
    rng = np.random.default_rng(seed)
    x, y = rng.normal(size=(n, 2)), rng.normal(size=(m, 2))
    assert exact_optimal_transport(x, y) == pytest.approx(lp_ot(x, y), rel=1e-9)


def test_exact_ot_of_a_translated_set_is_the_squared_translation():
    rng = np.random.default_rng(5)
    x = rng.random((50, 3))
    for t in ([0.0, 0.0, 0.0], [1e-3, 0.0, -2e-3], [0.2, -0.1, 0.05], [5.0, 3.0, -4.0]):
        expected = float(np.dot(t, t))
        assert exact_optimal_transport(x, x + np.array(t)) == pytest.approx(expected, rel=1e-9)
    # Exactly zero, whatever the order of the particles.
    assert exact_optimal_transport(x, x[rng.permutation(50)]) == 0.0


def test_exact_ot_splits_into_mean_shift_and_centred_parts_and_ignores_order():
    rng = np.random.default_rng(6)
    x, y = rng.random((40, 2)), rng.random((40, 2)) ** 2 + 0.3
    shift = float(np.sum((x.mean(0) - y.mean(0)) ** 2))
    centred = exact_optimal_transport(x - x.mean(0), y - y.mean(0))
    total = exact_optimal_transport(x, y)
    assert total == pytest.approx(shift + centred, rel=1e-10)
    assert exact_optimal_transport(x[::-1], y[rng.permutation(40)]) == pytest.approx(total, 1e-12)
    assert exact_optimal_transport(3 * x, 3 * y) == pytest.approx(9 * total, rel=1e-12)


def test_exact_ot_between_gaussian_samples_is_the_squared_mean_difference():
    # W2^2 = |mean(x) - mean(y)|^2 + W2^2(centred x, centred y). The first term has standard
    # error 2 |m1 - m2| s sqrt(2 / n) about |m1 - m2|^2; the second, between two samples of the
    # same Gaussian, is of order s^2 log(n) / n (0.035 s^2 measured at n = 1000): allow s^2.
    n, s = 600, 0.1
    m1, m2 = np.array([0.2, -0.1]), np.array([1.0, 0.5])
    rng = np.random.default_rng(7)
    x, y = rng.normal(m1, s, (n, 2)), rng.normal(m2, s, (n, 2))
    w2 = exact_optimal_transport(x, y)
    squared_shift = float(np.sum((m1 - m2) ** 2))
    standard_error = 2 * math.sqrt(squared_shift) * s * math.sqrt(2 / n)
    assert abs(w2 - squared_shift) < 5 * standard_error + s**2
    # Jensen: no coupling moves the mean for less than the squared mean difference.
    assert w2 >= float(np.sum((x.mean(0) - y.mean(0)) ** 2))


def scipy_assignment_ot(x, y):
    """The oracle: scipy's assignment on squared distances from a plain double loop over axes."""
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    cost = ((x[:, None, :] - y[None, :, :]) ** 2).sum(axis=-1)
    rows, cols = linear_sum_assignment(cost)
    return float(np.mean(cost[rows, cols]))


@pytest.mark.parametrize("use_lapx", [True, False])
@pytest.mark.parametrize(("n", "d"), [(2, 2), (30, 2), (200, 2), (656, 2), (40, 3), (300, 3)])
def test_exact_ot_equals_scipys_assignment_on_random_clouds(n, d, use_lapx, monkeypatch):
    """The preconditioned solver (gns.distances._assignment_cost) against scipy's assignment
    on the plain squared distances: clouds overlapping, far apart, stretched, and one squeezed
    flat (its covariance singular, so only the translation is taken out)."""
    if not use_lapx:
        monkeypatch.setattr(distances, "_lapjvh", None)
    elif distances._lapjvh is None:
        pytest.skip("lapx not installed")
    rng = np.random.default_rng(1000 * n + d)
    x = rng.random((n, d))
    stretch = np.diag(np.linspace(3.0, 0.2, d))
    flat = rng.random((n, d)) * np.r_[1.0, np.zeros(d - 1)]
    for y in (
        rng.random((n, d)),
        rng.normal(2.0, 0.1, (n, d)),
        (rng.random((n, d)) - 0.5) @ stretch + 0.3,
        flat,
        x[rng.permutation(n)] + 1e-7 * rng.normal(size=(n, d)),
    ):
        expected = scipy_assignment_ot(x, y)
        assert exact_optimal_transport(x, y) == pytest.approx(expected, rel=1e-12, abs=1e-300)
        assert exact_optimal_transport(y, x) == pytest.approx(expected, rel=1e-12, abs=1e-300)


def test_exact_ot_equals_scipys_assignment_on_real_sand():
    """Frames of sand2d-taichi (656 particles): a pile against its own later frames, against
    another trajectory's (far apart, shaped differently) and against a slightly moved copy."""
    if not (SAND / "manifest.json").is_file():
        pytest.skip("shared/data/sand2d-taichi not present")
    from gns.data import open_dataset

    dataset = open_dataset(SAND, "test")
    first, second = dataset[0].positions, dataset[1].positions
    rng = np.random.default_rng(9)
    pairs = [
        (first[0], first[60]),
        (first[30], first[-1]),
        (first[-1], second[-1]),
        (first[100], second[200]),
        (first[200], first[200] + 1e-5 * rng.normal(size=first[200].shape)),
    ]
    for x, y in pairs:
        expected = scipy_assignment_ot(x, y)
        assert exact_optimal_transport(x, y) == pytest.approx(expected, rel=1e-12)


def test_exact_ot_refuses_problems_beyond_exact_max_points():
    rng = np.random.default_rng(8)
    with pytest.raises(ValueError, match=r"between 30 and 30 points.*exact_max_points=20"):
        exact_optimal_transport(rng.random((30, 2)), rng.random((30, 2)), exact_max_points=20)
    # 7 and 11 points need a 77 x 77 assignment.
    with pytest.raises(ValueError, match=r"77 x 77"):
        optimal_transport(
            rng.random((7, 2)), rng.random((11, 2)), method="exact", exact_max_points=50
        )


@pytest.mark.parametrize(
    ("x", "y", "match"),
    [
        (np.zeros((3, 2)), np.zeros((3, 3)), r"same dimension D"),
        (np.zeros(3), np.zeros((3, 1)), r"x must be .*\(N, D\)"),
        (np.zeros((3, 2)), np.zeros((0, 2)), r"y must be a non-empty"),
        (np.array([[0.0, np.nan]]), np.zeros((1, 2)), r"x holds NaN or Inf"),
        (np.zeros((1, 2)), np.array([[np.inf, 0.0]]), r"y holds NaN or Inf"),
    ],
)
def test_distribution_metrics_reject_bad_point_sets(x, y, match):
    for metric in (optimal_transport, mmd, sinkhorn):
        with pytest.raises(ValueError, match=match):
            metric(x, y)


def test_rollout_ot_beyond_exact_max_points_is_exact_on_a_fixed_subset():
    """More particles than exact_max_points: OT of a rigidly shifted rollout is still the
    squared shift (true of every subset), and it equals brute force (scipy's assignment) on
    the subset the docstring names: the same seed-0 draw of particles in every frame."""
    rng = np.random.default_rng(3)
    truth = rng.random((3, 300, 3))
    shift = np.array([0.01, -0.02, 0.005])
    shifted = evaluate_rollout(truth + shift, truth, exact_max_points=100)
    assert shifted["ot_points"] == 100
    np.testing.assert_allclose(shifted["ot"], shift @ shift, rtol=1e-9)
    noisy = truth + 0.03 * rng.standard_normal(truth.shape)
    result = evaluate_rollout(noisy, truth, exact_max_points=100)
    subset = np.sort(np.random.default_rng(0).choice(300, 100, replace=False))
    for t in range(3):
        a, b = noisy[t, subset], truth[t, subset]
        cost = ((a[:, None] - b[None]) ** 2).sum(-1)
        rows, cols = linear_sum_assignment(cost)
        assert result["ot"][t] == pytest.approx(cost[rows, cols].mean(), rel=1e-12)
    # At or below the limit every particle counts.
    assert evaluate_rollout(noisy, truth, exact_max_points=300)["ot_points"] == 300


def test_optimal_transport_rejects_an_unknown_method():
    with pytest.raises(ValueError, match="method"):
        optimal_transport(np.zeros((2, 2)), np.ones((2, 2)), method="emd")


# --------------------------------------------------------------------------- Sinkhorn


def test_sinkhorn_brackets_the_exact_value_with_a_gap_that_shrinks_with_epsilon():
    # Sinkhorn's iteration count depends on the instance; this one converges at every epsilon.
    rng = np.random.default_rng(3)
    x, y = rng.random((40, 2)), rng.random((40, 2))
    exact = exact_optimal_transport(x, y)
    max_cost = float(((x[:, None] - y[None]) ** 2).sum(-1).max())
    gaps = []
    for epsilon in (1e-1, 3e-2, 1e-2, 3e-3):
        result = sinkhorn(x, y, epsilon=epsilon)
        # Never below the optimum (a true coupling) nor the dual bound above it; above it by at
        # most the entropic bias eps log N plus what the unmatched mass can cost.
        assert result.lower_bound <= exact * (1 + 1e-12) <= result.cost * (1 + 1e-12)
        slack = result.epsilon * math.log(40) + 2 * result.marginal_error * max_cost
        assert result.cost - exact <= slack
        assert result.marginal_error <= 1e-6
        gaps.append(result.cost - exact)
    assert all(later < earlier for earlier, later in itertools.pairwise(gaps))
    assert gaps[-1] < 0.05 * gaps[0]


def test_sinkhorn_between_sets_of_different_sizes_agrees_with_exact():
    rng = np.random.default_rng(10)
    x, y = rng.random((20, 3)), rng.random((30, 3))
    exact = exact_optimal_transport(x, y)
    assert exact == pytest.approx(lp_ot(x, y), rel=1e-9)
    result = sinkhorn(x, y, epsilon=1e-2)
    assert result.lower_bound <= exact * (1 + 1e-12) <= result.cost * (1 + 1e-12)
    assert result.cost - exact <= result.epsilon * math.log(20) + 1e-5


def test_sinkhorn_stays_finite_and_within_its_bound_at_tiny_epsilon():
    # Log-domain updates: at epsilon 1e-10 of the mean cost a kernel exp(-C / eps) would
    # underflow to 0 everywhere. Nearly equal clouds keep the iteration count small.
    rng = np.random.default_rng(11)
    x = rng.random((30, 2))
    y = x + 1e-4 * rng.standard_normal((30, 2))
    exact = exact_optimal_transport(x, y)
    max_cost = float(((x[:, None] - y[None]) ** 2).sum(-1).max())
    for epsilon in (1e-4, 1e-7, 1e-10):
        result = sinkhorn(x, y, epsilon=epsilon)
        assert result.lower_bound <= exact * (1 + 1e-9) <= result.cost * (1 + 1e-9)
        slack = result.epsilon * math.log(30) + 2 * result.marginal_error * max_cost
        assert result.cost - exact <= slack


def test_sinkhorn_cost_is_that_of_a_true_coupling_even_far_from_convergence():
    # With a loose tolerance the entropic plan's row sums are off by up to 30 %; the reported
    # cost is taken after rounding to a coupling, so it still cannot undercut the optimum.
    for seed in range(4):
        rng = np.random.default_rng(seed)
        x, y = rng.random((40, 2)), rng.random((40, 2))
        exact = exact_optimal_transport(x, y)
        max_cost = float(((x[:, None] - y[None]) ** 2).sum(-1).max())
        for tolerance in (0.3, 0.1, 0.03):
            result = sinkhorn(x, y, epsilon=1e-3, tolerance=tolerance)
            assert result.marginal_error <= tolerance
            assert exact <= result.cost
            slack = result.epsilon * math.log(40) + 2 * result.marginal_error * max_cost
            assert result.cost - exact <= slack


def test_sinkhorn_is_scale_covariant_and_exact_for_single_points():
    rng = np.random.default_rng(12)
    x, y = rng.random((15, 2)), rng.random((15, 2)) + 0.5
    base = sinkhorn(x, y).cost
    assert sinkhorn(4 * x, 4 * y).cost == pytest.approx(16 * base, rel=1e-9)
    assert sinkhorn([[0.0, 0.0]], [[3.0, 4.0]]).cost == pytest.approx(25.0, rel=1e-12)
    assert sinkhorn(np.ones((3, 2)), np.ones((5, 2))).cost == 0.0


def test_sinkhorn_in_row_blocks_equals_the_cached_cost_matrix():
    rng = np.random.default_rng(13)
    x, y = rng.random((25, 2)), rng.random((35, 2))
    cached = sinkhorn(x, y)
    # 1 KiB cannot hold the 25 x 35 matrix: every pass recomputes one row at a time.
    blocked = sinkhorn(x, y, memory_bytes=1024)
    assert blocked.cost == pytest.approx(cached.cost, rel=1e-9)
    assert blocked.lower_bound == pytest.approx(cached.lower_bound, rel=1e-9)
    assert abs(blocked.iterations - cached.iterations) <= 1


def test_sinkhorn_raises_when_it_does_not_converge():
    rng = np.random.default_rng(14)
    x, y = rng.random((20, 2)), rng.random((20, 2))
    with pytest.raises(SinkhornConvergenceError, match="did not converge in 3 iterations"):
        sinkhorn(x, y, epsilon=1e-3, max_iterations=3)
    with pytest.raises(ValueError, match="epsilon > 0"):
        sinkhorn(x, y, epsilon=0.0)
    with pytest.raises(ValueError, match="overrelaxation"):
        sinkhorn(x, y, overrelaxation=2.0)


def test_auto_uses_exact_up_to_the_limit_and_sinkhorn_beyond():
    rng = np.random.default_rng(15)
    x, y = rng.random((12, 2)), rng.random((12, 2))
    exact = exact_optimal_transport(x, y)
    assert optimal_transport(x, y) == exact
    beyond = optimal_transport(x, y, exact_max_points=11, epsilon=0.1)
    assert beyond == sinkhorn(x, y, epsilon=0.1).cost
    assert beyond > exact
    # 12 and 18 points need a 36 x 36 assignment: over a limit of 30, auto falls back.
    z = rng.random((18, 2))
    assert (
        optimal_transport(x, z, exact_max_points=30, epsilon=0.1)
        == sinkhorn(x, z, epsilon=0.1).cost
    )
    assert optimal_transport(x, z, exact_max_points=36) == pytest.approx(lp_ot(x, z), rel=1e-9)


# --------------------------------------------------------------------------- MMD


@pytest.mark.parametrize(
    ("n", "m", "d", "bandwidth"), [(7, 9, 2, 0.1), (6, 6, 3, 0.37), (1, 4, 1, 1.0)]
)
def test_mmd_equals_a_double_loop(n, m, d, bandwidth):
    rng = np.random.default_rng(n + m + d)
    x, y = 0.2 * rng.random((n, d)), 0.2 * rng.random((m, d))
    expected = loop_mmd(x.tolist(), y.tolist(), bandwidth)
    assert mmd(x, y, bandwidth) == pytest.approx(expected, rel=1e-12)
    # In one-row blocks too.
    assert mmd(x, y, bandwidth, memory_bytes=64) == pytest.approx(expected, rel=1e-12)
    if n >= 2:
        unbiased = loop_mmd(x.tolist(), y.tolist(), bandwidth, unbiased=True)
        assert mmd(x, y, bandwidth, unbiased=True) == pytest.approx(unbiased, rel=1e-10)


def test_mmd_is_exactly_zero_for_identical_sets_and_invariant_to_order_and_scale():
    rng = np.random.default_rng(16)
    x = rng.random((300, 2))
    assert mmd(x, x.copy()) == 0.0
    assert mmd(x, x.copy(), memory_bytes=4096) == 0.0
    assert mmd(x, x[rng.permutation(300)]) == pytest.approx(0.0, abs=1e-14)
    y = rng.random((200, 2)) * 0.8
    assert mmd(3 * x, 3 * y, bandwidth=0.3) == pytest.approx(mmd(x, y, bandwidth=0.1), rel=1e-12)
    assert mmd(x, y) > 0


def test_mmd_between_gaussian_samples_matches_the_closed_form():
    # For N(m1, s^2 I) and N(m2, s^2 I) in D dimensions under exp(-|a - b|^2 / (2 bw^2)):
    # E k(X, X') = (bw^2 / (bw^2 + 2 s^2))^(D/2) since X - X' ~ N(0, 2 s^2 I), and E k(X, Y)
    # carries the extra factor exp(-|m1 - m2|^2 / (2 (bw^2 + 2 s^2))). The unbiased estimate
    # had a standard error of 0.0083 over 20 seeds at n = 2000 (1 / sqrt(n) scaling).
    n, s, bandwidth, d = 3000, 0.1, 0.1, 2
    shift = np.array([0.1, 0.0])
    ratio = bandwidth**2 / (bandwidth**2 + 2 * s**2)
    expected = (
        2 * ratio ** (d / 2) * (1 - math.exp(-shift @ shift / (2 * (bandwidth**2 + 2 * s**2))))
    )
    rng = np.random.default_rng(17)
    x, y = rng.normal(0.0, s, (n, d)), rng.normal(shift, s, (n, d))
    standard_error = 0.0083 * math.sqrt(2000 / n)
    assert abs(mmd(x, y, bandwidth, unbiased=True) - expected) < 5 * standard_error
    # The biased statistic adds the diagonal terms, (1 - E k(X, X')) / n per set.
    biased_shift = 2 * (1 - ratio ** (d / 2)) / n
    assert mmd(x, y, bandwidth) - mmd(x, y, bandwidth, unbiased=True) == pytest.approx(
        biased_shift, rel=0.05
    )


def test_mmd_rejects_a_bad_bandwidth_and_tiny_unbiased_sets():
    x = np.zeros((3, 2))
    for bandwidth in (0.0, -0.1, math.inf, math.nan):
        with pytest.raises(ValueError, match="bandwidth"):
            mmd(x, x, bandwidth)
    with pytest.raises(ValueError, match="at least 2 points"):
        mmd(x[:1], x, unbiased=True)


# --------------------------------------------------------------------------- baseline


def test_constant_velocity_baseline_is_exact_on_a_constant_velocity_trajectory():
    rng = np.random.default_rng(18)
    start, velocity = rng.random((10, 3)), 1e-2 * rng.standard_normal((10, 3))
    frames = np.arange(-5, 21, dtype=float)[:, None, None]  # C + 1 = 6 inputs, 20 steps
    trajectory = start + frames * velocity
    rollout = constant_velocity_rollout(trajectory[:6], 20)
    assert rollout.shape == (20, 10, 3)
    np.testing.assert_allclose(rollout, trajectory[6:], rtol=0, atol=1e-13)
    np.testing.assert_allclose(mse_over_time(rollout, trajectory[6:]), 0.0, atol=1e-26)


def test_constant_velocity_baseline_misses_half_a_t_squared_under_constant_acceleration():
    # x(k) = x0 + v0 k + a k^2 / 2, inputs at k = -2, -1, 0. The last velocity is
    # x(0) - x(-1) = v0 - a / 2, so the baseline predicts x0 + k (v0 - a / 2) and misses
    # x(k) - prediction = a k^2 / 2 + a k / 2 = a k (k + 1) / 2.
    rng = np.random.default_rng(19)
    x0, v0, a = rng.random((8, 2)), 1e-2 * rng.standard_normal((8, 2)), 1e-3 * rng.random((8, 2))
    k = np.arange(-2, 11, dtype=float)[:, None, None]
    trajectory = x0 + v0 * k + 0.5 * a * k**2
    rollout = constant_velocity_rollout(trajectory[:3], 10)
    steps = np.arange(1, 11, dtype=float)[:, None, None]
    np.testing.assert_allclose(trajectory[3:] - rollout, a * steps * (steps + 1) / 2, atol=1e-15)
    expected_mse = [np.mean((a * t * (t + 1) / 2) ** 2) for t in range(1, 11)]
    np.testing.assert_allclose(mse_over_time(rollout, trajectory[3:]), expected_mse, rtol=1e-9)


def test_kinematic_particles_follow_ground_truth_in_the_baseline():
    rng = np.random.default_rng(20)
    history = rng.random((3, 4, 2))
    truth = rng.random((5, 4, 2))
    kinematic = np.array([False, True, False, True])
    rollout = constant_velocity_rollout(history, 5, kinematic_mask=kinematic, ground_truth=truth)
    np.testing.assert_array_equal(rollout[:, kinematic], truth[:, kinematic])
    free = constant_velocity_rollout(history, 5)
    np.testing.assert_array_equal(rollout[:, ~kinematic], free[:, ~kinematic])


@pytest.mark.parametrize(
    ("history", "steps", "kwargs", "match"),
    [
        (np.zeros((1, 4, 2)), 3, {}, r"at least 2 frames"),
        (np.zeros((4, 2)), 3, {}, r"initial_positions must be .*\(C \+ 1, N, D\)"),
        (np.full((2, 4, 2), np.nan), 3, {}, r"NaN or Inf"),
        (np.zeros((2, 4, 2)), 0, {}, r"num_steps must be a positive integer"),
        (np.zeros((2, 4, 2)), 3, {"kinematic_mask": np.ones(4, bool)}, r"given together"),
        (np.zeros((2, 4, 2)), 3, {"ground_truth": np.zeros((3, 4, 2))}, r"given together"),
        (
            np.zeros((2, 4, 2)),
            3,
            {"kinematic_mask": np.ones(4, bool), "ground_truth": np.zeros((2, 4, 2))},
            r"ground_truth must have shape \(num_steps, N, D\) = \(3, 4, 2\)",
        ),
        (
            np.zeros((2, 4, 2)),
            3,
            {"kinematic_mask": np.ones(4, int), "ground_truth": np.zeros((3, 4, 2))},
            r"kinematic_mask must be a boolean array of shape \(4,\)",
        ),
    ],
)
def test_constant_velocity_baseline_rejects_bad_input(history, steps, kwargs, match):
    with pytest.raises(ValueError, match=match):
        constant_velocity_rollout(history, steps, **kwargs)


def test_static_baseline_holds_the_last_input_frame_and_kinematic_particles_follow_truth():
    rng = np.random.default_rng(23)
    history, truth = rng.random((3, 4, 2)), rng.random((5, 4, 2))
    rollout = static_rollout(history, 5)
    assert rollout.shape == (5, 4, 2) and rollout.dtype == np.float64
    for frame in rollout:
        np.testing.assert_array_equal(frame, history[-1])
    # Exact on a scene at rest; one input frame is enough (no velocity is read).
    np.testing.assert_array_equal(static_rollout(history[-1:], 2), rollout[:2])
    kinematic = np.array([True, False, False, True])
    held = static_rollout(history, 5, kinematic_mask=kinematic, ground_truth=truth)
    np.testing.assert_array_equal(held[:, kinematic], truth[:, kinematic])
    np.testing.assert_array_equal(held[:, ~kinematic], rollout[:, ~kinematic])
    # Under constant acceleration a from rest at the last input frame it misses a k^2 / 2.
    a = 1e-3
    k = np.arange(6, dtype=float)[:, None, None]
    falling = np.zeros((6, 1, 2)) + np.array([0.0, -0.5 * a]) * k**2
    missed = falling[1:] - static_rollout(falling[:1], 5)
    np.testing.assert_allclose(missed[:, 0, 1], -0.5 * a * np.arange(1, 6) ** 2, rtol=1e-12)


@pytest.mark.parametrize(
    ("history", "steps", "kwargs", "match"),
    [
        (np.zeros((4, 2)), 3, {}, r"initial_positions must be .*\(C \+ 1, N, D\)"),
        (np.full((2, 4, 2), np.inf), 3, {}, r"NaN or Inf"),
        (np.zeros((1, 4, 2)), 0, {}, r"num_steps must be a positive integer"),
        (np.zeros((1, 4, 2)), 3, {"ground_truth": np.zeros((3, 4, 2))}, r"given together"),
        (
            np.zeros((1, 4, 2)),
            3,
            {"kinematic_mask": np.ones(3, bool), "ground_truth": np.zeros((3, 4, 2))},
            r"kinematic_mask must be a boolean array of shape \(4,\)",
        ),
    ],
)
def test_static_baseline_rejects_bad_input(history, steps, kwargs, match):
    with pytest.raises(ValueError, match=match):
        static_rollout(history, steps, **kwargs)


# --------------------------------------------------------------------------- deposit


def lattice(columns: int, rows: int, spacing: float, origin=(0.0, 0.0)) -> np.ndarray:
    """(columns * rows, 2) particles on a rectangular lattice, x fastest."""
    i, j = np.meshgrid(np.arange(columns), np.arange(rows))
    return np.asarray(origin) + spacing * np.stack([i.ravel(), j.ravel()], axis=1)


# A 101 x 101 lattice of spacing 0.01 on [0, 1]^2: of its 10201 particles 101 share every x
# (and every y). Sorted, the p-th percentile lies at index p / 100 * 10200: 102 (the second
# column, x = 0.01) for p = 1 and 10098 (the 100th column, x = 0.99) for p = 99; both indices
# fall inside a block of 101 equal values, so no interpolation reaches a neighbouring column.
SQUARE = lattice(101, 101, 0.01)


def test_runout_of_a_lattice_is_the_width_between_its_second_and_second_last_columns():
    assert runout_extent(SQUARE) == pytest.approx(0.98, abs=1e-12)
    # Only x counts, and a translation moves nothing.
    tall = lattice(101, 7, 0.01, origin=(0.3, 0.2))
    assert runout_extent(tall) == pytest.approx(0.98, abs=1e-12)
    # Eleven particles at x = 0 ... 10: the percentiles fall between particles 0 and 1
    # (0.1 of the way) and 9 and 10 (0.9 of the way): 9.9 - 0.1.
    line = np.stack([np.arange(11.0), np.zeros(11)], axis=1)
    assert runout_extent(line) == pytest.approx(9.8, abs=1e-12)
    assert runout_extent(line[:1]) == 0.0  # a single particle has no width


def test_runout_ignores_a_grain_thrown_far_out_and_masked_particles():
    far = np.vstack([SQUARE, [[5.0, 0.0]]])
    # 10202 particles: the 1st percentile lies at index 102.01 and the 99th at 10098.99,
    # still between equal values (x = 0.01, x = 0.99); the grain at x = 5 moves neither.
    assert runout_extent(far) == pytest.approx(0.98, abs=1e-12)
    # 300 kinematic particles at x = -3 (a wall) count only when the mask lets them in: then
    # of 10501 sorted values the 1st percentile (index 105) is on the wall and the 99th
    # (index 10395, the square's 10095th: x = 0.99) is not.
    wall = np.vstack([SQUARE, np.column_stack([np.full(300, -3.0), np.linspace(0, 1, 300)])])
    sand = np.arange(len(wall)) < len(SQUARE)
    assert runout_extent(wall, sand) == pytest.approx(0.98, abs=1e-12)
    assert runout_extent(wall) == pytest.approx(3.99, abs=1e-12)


def test_fronts_of_a_translating_and_a_spreading_block():
    # Frame t: the square moved by 0.1 t along x, then stretched about x = 0.5 by 1 + t / 4.
    t = np.arange(4, dtype=float)
    moved = SQUARE[None] + np.array([0.1, 0.0]) * t[:, None, None]
    fronts = front_positions(moved)
    assert fronts.shape == (4, 2)
    np.testing.assert_allclose(fronts, np.stack([0.01 + 0.1 * t, 0.99 + 0.1 * t], 1), atol=1e-12)
    scale = 1 + t / 4
    spread = SQUARE[None].repeat(4, axis=0)
    spread[..., 0] = 0.5 + (SQUARE[:, 0] - 0.5) * scale[:, None]
    expected = np.stack([0.5 - 0.49 * scale, 0.5 + 0.49 * scale], axis=1)
    np.testing.assert_allclose(front_positions(spread), expected, atol=1e-12)
    # Each frame's width is its runout.
    for frame, (left, right) in zip(spread, front_positions(spread), strict=True):
        assert runout_extent(frame) == pytest.approx(right - left, abs=1e-12)


def test_pile_height_is_the_second_highest_row_above_the_floor():
    # Rows at y = 0.1, 0.11, ..., 1.1: the 99th percentile is the 100th row, y = 1.09.
    pile = lattice(101, 101, 0.01, origin=(0.2, 0.1))
    assert pile_height(pile, None, 0.1) == pytest.approx(0.99, abs=1e-12)
    assert pile_height(pile, None, 0.0) == pytest.approx(1.09, abs=1e-12)
    # A lid of kinematic particles above it does not count; the mask keeps it out.
    lid = np.column_stack([np.linspace(0.2, 1.2, 200), np.full(200, 3.0)])
    sand = np.arange(len(pile) + 200) < len(pile)
    assert pile_height(np.vstack([pile, lid]), sand, 0.1) == pytest.approx(0.99, abs=1e-12)
    # A layer two rows thick: of its 100 sorted y the 99th percentile (index 98.01) is on the
    # upper row. A column of 11 particles at y = 0 ... 10: 0.9 of the way from 9 to 10.
    layer = lattice(50, 2, 0.01, origin=(0.0, 0.1))
    assert pile_height(layer, None, 0.1) == pytest.approx(0.01, abs=1e-12)
    column = np.stack([np.zeros(11), np.arange(11.0)], axis=1)
    assert pile_height(column, None, 0.0) == pytest.approx(9.9, abs=1e-12)


def test_pile_base_is_the_second_lowest_row_above_the_floor():
    # Rows at y = 0.1, 0.11, ..., 1.1: the 1st percentile is the second row, y = 0.11; the
    # same pile lifted 0.05 off its floor reads the gap.
    pile = lattice(101, 101, 0.01, origin=(0.2, 0.1))
    assert pile_base(pile, None, 0.1) == pytest.approx(0.01, abs=1e-12)
    assert pile_base(pile + [0.0, 0.05], None, 0.1) == pytest.approx(0.06, abs=1e-12)
    # A column of 11 at y = 0 ... 10: 0.1 of the way from 0 to 1; one particle under the floor
    # alone does not move it far, and masked out not at all.
    column = np.stack([np.zeros(11), np.arange(11.0)], axis=1)
    assert pile_base(column, None, 0.0) == pytest.approx(0.1, abs=1e-12)
    sunk = np.vstack([column, [[0.0, -5.0]]])
    assert pile_base(sunk, np.arange(12) < 11, 0.0) == pytest.approx(0.1, abs=1e-12)
    assert pile_base(sunk, None, 0.0) == pytest.approx(-5.0 + 0.11 * 5.0, abs=1e-12)
    with pytest.raises(ValueError, match="floor must be a finite number"):
        pile_base(column, None, math.inf)
    assert pile_base(np.vstack([column, [[np.nan, 0.0]]]), None, 0.0, nonfinite="inf") == math.inf


def test_pile_floor_is_the_box_floor_or_the_lowest_particle_of_frame_0():
    frame = np.array([[0.5, 0.3], [0.6, 0.12], [0.2, 0.7]])
    assert pile_floor([[0.0, 1.0], [0.1, 0.9]], frame) == 0.1
    assert pile_floor(None, frame) == 0.12
    with pytest.raises(ValueError, match="at least 2 dimensions"):
        pile_floor(None, frame[:, :1])
    with pytest.raises(ValueError, match="pairs"):
        pile_floor([[0.0, 1.0]], frame)


def test_deposit_of_a_diverged_frame_raises_or_is_inf_never_nan():
    frames = np.stack([SQUARE, SQUARE + 0.1])
    frames[1, 7, 1] = np.nan
    with pytest.raises(ValueError, match="NaN or Inf"):
        runout_extent(frames[1])
    with pytest.raises(ValueError, match="frame 1, particle 7"):
        front_positions(frames)
    assert runout_extent(frames[1], nonfinite="inf") == math.inf
    assert pile_height(frames[1], None, 0.0, nonfinite="inf") == math.inf
    fronts = front_positions(frames, nonfinite="inf")
    np.testing.assert_allclose(fronts[0], [0.01, 0.99], atol=1e-12)
    assert np.all(fronts[1] == math.inf)
    # A masked-out non-finite particle does not count.
    free = np.arange(len(SQUARE)) != 7
    assert runout_extent(frames[1], free) == pytest.approx(0.98, abs=1e-12)
    with pytest.raises(ValueError, match="floor must be a finite number"):
        pile_height(SQUARE, None, math.nan)
    with pytest.raises(ValueError, match="at least 2 dimensions"):
        pile_height(SQUARE[:, :1], None, 0.0)
    with pytest.raises(ValueError, match="mask must be a boolean array"):
        runout_extent(SQUARE, np.ones(len(SQUARE), int))


def test_deposit_of_a_lattice_and_of_it_stretched_against_it():
    # The square lattice (spacing 0.01) and the same particles 2x as far apart in x and at
    # 0.6x in y (spacing 0.02 and 0.006), both resting on y = 0, radius 0.015. Neighbours by
    # hand, no pair near the radius: the square has its 2 * 101 * 100 axial pairs (0.01) and
    # 2 * 100^2 diagonal ones (0.0141) within it, the next at 0.02 beyond; the stretched one
    # only the pairs one and two rows apart in each column (0.006, 0.012), 101 * (100 + 99).
    stretched = SQUARE * np.array([2.0, 0.6])
    frames = np.stack([SQUARE, stretched])
    free = np.ones(len(SQUARE), bool)
    ours = deposit(frames, free, 0.0, radius=0.015)
    truth = deposit(np.stack([SQUARE, SQUARE]), free, 0.0, radius=0.015)
    n = len(SQUARE)
    assert truth["neighbours"] == pytest.approx(2 * (2 * 101 * 100 + 2 * 100**2) / n, rel=1e-12)
    assert ours["neighbours"] == pytest.approx(2 * 101 * 199 / n, rel=1e-12)
    assert ours["runout"] == pytest.approx(1.96, abs=1e-12)
    assert ours["pile_height"] == pytest.approx(0.594, abs=1e-12)
    assert ours["pile_base"] == pytest.approx(0.006, abs=1e-12)  # the second row, squeezed
    np.testing.assert_allclose(ours["front_x_p1"], [0.01, 0.02], atol=1e-12)
    np.testing.assert_allclose(ours["front_x_p99"], [0.99, 1.98], atol=1e-12)
    ratios = deposit_ratios(ours, truth)
    assert ratios["runout_ratio"] == pytest.approx(2.0, rel=1e-12)
    assert ratios["height_ratio"] == pytest.approx(0.6, rel=1e-12)
    assert ratios["density_ratio"] == pytest.approx(101 * 199 / (2 * 101 * 100 + 2 * 100**2))
    assert deposit_ratios(truth, truth) == dict.fromkeys(ratios, 1.0)
    # Without a floor or a radius those figures are not made up; a diverged last frame is inf.
    assert set(deposit(frames, free, None)) == {"runout", "front_x_p1", "front_x_p99"}
    frames[1, 3] = np.nan
    broken = deposit(frames, free, 0.0, radius=0.015)
    assert broken["runout"] == broken["pile_height"] == broken["neighbours"] == math.inf
    assert deposit_ratios(broken, truth)["density_ratio"] == math.inf


def test_density_ratio_max_is_the_worst_frame_not_the_last():
    # A landing that packs and relaxes: the square lattice squeezed to 0.7 and 0.6 of its size
    # (spacing 0.007, 0.006; no pair near the radius 0.015) in frames 1-2 and back in frame 3,
    # against the lattice held still. Mean neighbours per frame by scipy's pair count.
    from scipy.spatial import cKDTree

    free = np.ones(len(SQUARE), bool)
    ours_frames = np.stack([SQUARE, 0.7 * SQUARE, 0.6 * SQUARE, SQUARE])
    counts = [2 * len(cKDTree(f).query_pairs(0.015)) / len(f) for f in ours_frames]
    ours = deposit(ours_frames, free, 0.0, radius=0.015)
    truth = deposit(np.stack([SQUARE] * 4), free, 0.0, radius=0.015)
    np.testing.assert_allclose(ours["neighbours_by_frame"], counts, rtol=1e-12)
    assert counts[2] > counts[1] > counts[0] == counts[3]
    ratios = deposit_ratios(ours, truth)
    assert ratios["density_ratio"] == 1.0  # the last frame has relaxed
    assert ratios["density_ratio_max"] == pytest.approx(counts[2] / counts[0], rel=1e-12)
    # Diverged at frame 3: inf from there on, and at its worst.
    ours_frames[3, 5] = np.inf
    broken = deposit(ours_frames, free, 0.0, radius=0.015)
    assert broken["neighbours_by_frame"][3] == math.inf
    assert deposit_ratios(broken, truth)["density_ratio_max"] == math.inf
    # Over different frames there is no frame-by-frame ratio to take; the last frame's stays.
    shorter = deposit(np.stack([SQUARE] * 3), free, 0.0, radius=0.015)
    assert "density_ratio_max" not in deposit_ratios(ours, shorter)
    assert deposit_ratios(ours, shorter)["density_ratio"] == 1.0


def test_ratio_of_never_divides_by_zero_into_nan():
    assert ratio_of(3.0, 2.0) == 1.5
    assert ratio_of(0.0, 0.0) == 1.0  # a single particle against a single particle: the same
    assert ratio_of(0.5, 0.0) == math.inf


# --------------------------------------------------------------------------- summary


def test_evaluate_rollout_summarises_a_permuted_translated_rollout():
    # Predicted frame t is the ground truth with its free particles shuffled and moved by
    # shift_t: OT sees only the shift (|shift_t|^2), MSE sees the shuffle too.
    rng = np.random.default_rng(21)
    t_max, n = 10, 6
    truth = rng.random((t_max, n, 2))
    mask = np.array([True, True, True, True, False, True])
    free = np.flatnonzero(mask)
    shifts = 1e-2 * rng.standard_normal((t_max, 2))
    predicted = truth.copy()
    for t in range(t_max):
        predicted[t, free] = truth[t, rng.permutation(free)] + shifts[t]
    result = evaluate_rollout(
        predicted, truth, mask=mask, horizons=(1, 5, 20, None), distribution_every=3
    )
    expected_mse = [np.mean((predicted[t, free] - truth[t, free]) ** 2) for t in range(t_max)]
    np.testing.assert_allclose(result["mse"], expected_mse, rtol=1e-12)
    assert result["mse@1"] == pytest.approx(expected_mse[0], rel=1e-12)
    assert result["mse@5"] == pytest.approx(np.mean(expected_mse[:5]), rel=1e-12)
    assert result["mse@full"] == pytest.approx(np.mean(expected_mse), rel=1e-12)
    assert "mse@20" not in result
    np.testing.assert_array_equal(result["frames"], [0, 3, 6, 9])
    expected_ot = [float(shifts[t] @ shifts[t]) for t in (0, 3, 6, 9)]
    np.testing.assert_allclose(result["ot"], expected_ot, rtol=1e-9)
    assert result["ot_mean"] == pytest.approx(np.mean(expected_ot), rel=1e-9)
    expected_mmd = [
        loop_mmd(predicted[t, free].tolist(), truth[t, free].tolist(), 0.1) for t in (0, 3, 6, 9)
    ]
    np.testing.assert_allclose(result["mmd"], expected_mmd, rtol=1e-10)
    assert result["mmd_mean"] == pytest.approx(np.mean(expected_mmd), rel=1e-10)


def test_evaluate_rollout_reports_a_diverged_frame_as_inf():
    rng = np.random.default_rng(22)
    truth = rng.random((4, 5, 2))
    predicted = truth + 1e-3
    predicted[2, 1, 1] = np.inf
    with pytest.raises(ValueError, match="frame 2, particle 1"):
        evaluate_rollout(predicted, truth)
    result = evaluate_rollout(predicted, truth, nonfinite="inf")
    for key in ("mse", "ot", "mmd"):
        assert np.isinf(result[key][2]) and np.isfinite(result[key][[0, 1, 3]]).all()
    assert result["ot_mean"] == np.inf and result["mmd_mean"] == np.inf
    # Every coordinate is off by 1e-3 before the divergence: MSE 1e-6, OT |(1e-3, 1e-3)|^2.
    assert result["mse@1"] == pytest.approx(1e-6, rel=1e-9) and result["mse@full"] == np.inf
    assert result["ot"][0] == pytest.approx(2e-6, rel=1e-9)
    for every in (0, 1.5, True):
        with pytest.raises(ValueError, match="distribution_every"):
            evaluate_rollout(truth, truth, distribution_every=every)
