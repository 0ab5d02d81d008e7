"""gns.radius_graph and gns.RadiusSearcher against independent oracles: free space.

The oracle is scipy's cKDTree (query_pairs, symmetrised, plus self pairs), built on the
positions converted to float64: gns promises the same metric (dx = x_j - x_i summed over axes
in float64, compared with radius**2 inclusive), so edge arrays are compared exactly. Where the
cKDTree cannot express the case (a periodic box exactly 2 * radius wide) the oracle is brute
force numpy.

This file holds the oracles and helpers (test_graph_periodic.py imports them) and the plain and
batched searches: uniform and clumped clouds of every size, pairs at exactly the radius,
duplicates, batches, far outliers, thread counts and searcher reuse, and the hypothesis
properties. Periodic boxes and the inputs accepted and refused are in test_graph_periodic.py.
"""

from __future__ import annotations

import math

import gns
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

METHODS = ("cells", "kdtree", "brute")
DTYPES = (np.float32, np.float64)
SIZES = (0, 1, 2, 50, 1000, 20000)


# ----------------------------------------------------------------------------- oracles


def sort_edges(senders: np.ndarray, receivers: np.ndarray) -> np.ndarray:
    """(2, E) int64, row 0 senders, row 1 receivers, sorted by (receiver, sender)."""
    senders = np.asarray(senders, dtype=np.int64)
    receivers = np.asarray(receivers, dtype=np.int64)
    order = np.lexsort((senders, receivers))
    return np.stack([senders[order], receivers[order]])


def oracle(x, radius, *, self_edges=True, boxsize=None) -> np.ndarray:
    """cKDTree's radius graph on float64 positions, in gns's layout and order."""
    x64 = np.asarray(x, dtype=np.float64)
    n = len(x64)
    if n == 0:
        return np.zeros((2, 0), dtype=np.int64)
    pairs = cKDTree(x64, boxsize=boxsize).query_pairs(radius, output_type="ndarray")
    senders = [pairs[:, 0], pairs[:, 1]]
    receivers = [pairs[:, 1], pairs[:, 0]]
    if self_edges:
        senders.append(np.arange(n))
        receivers.append(np.arange(n))
    return sort_edges(np.concatenate(senders), np.concatenate(receivers))


def batched_oracle(x, radius, n_node, **kwargs) -> np.ndarray:
    """Per-graph oracle with index offsets; graphs are consecutive row ranges."""
    parts, start = [], 0
    for size in n_node:
        parts.append(oracle(x[start : start + size], radius, **kwargs) + start)
        start += size
    return np.concatenate(parts, axis=1) if parts else np.zeros((2, 0), np.int64)


def wrap(x: np.ndarray, box, periodic) -> np.ndarray:
    """float64 positions folded into [0, L) on the periodic axes."""
    y = np.array(x, dtype=np.float64)
    for d, (length, p) in enumerate(zip(box, periodic, strict=True)):
        if p:
            col = np.mod(y[:, d], length)
            y[:, d] = np.where(col >= length, col - length, col)
    return y


def periodic_oracle(x, radius, box, periodic, *, self_edges=True) -> np.ndarray:
    boxsize = np.where(periodic, np.asarray(box, dtype=np.float64), 0.0)
    return oracle(wrap(x, box, periodic), radius, self_edges=self_edges, boxsize=boxsize)


def min_image(d: np.ndarray, box, periodic) -> np.ndarray:
    """Minimum-image displacement of float64 displacements d (E, D)."""
    d = np.array(d, dtype=np.float64)
    for k, (length, p) in enumerate(zip(box, periodic, strict=True)):
        if p:
            d[:, k] -= length * np.round(d[:, k] / length)
    return d


def brute_min_image(x, radius, box, periodic, *, self_edges=True) -> np.ndarray:
    """All pairs in numpy on wrapped float64 positions; minimum image on periodic axes."""
    y = wrap(x, box, periodic)
    n = len(y)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    i, j = i.ravel(), j.ravel()
    disp = min_image(y[j] - y[i], box, periodic)
    d2 = np.zeros(len(i))
    for k in range(y.shape[1]):
        d2 = d2 + disp[:, k] * disp[:, k]
    keep = d2 <= radius * radius
    if not self_edges:
        keep &= i != j
    return sort_edges(j[keep], i[keep])


def check_shifts(x, edges, shifts, box, periodic, radius) -> None:
    """Shifts turn caller-coordinate differences into the minimum-image displacement."""
    x64 = np.asarray(x, dtype=np.float64)
    box = np.asarray(box, dtype=np.float64)
    flags = np.asarray(periodic, dtype=bool)
    s, r = edges
    assert shifts.dtype == np.int32
    assert shifts.shape == (edges.shape[1], x64.shape[1])
    assert np.all(shifts[:, ~flags] == 0)
    raw = x64[s] - x64[r]
    disp = raw + shifts * box
    expected = min_image(raw, box, flags)
    scale = 1.0 + (np.abs(x64).max() if len(x64) else 0.0)
    atol = 1e-9 * scale
    same = np.abs(disp - expected) <= atol
    # Exactly half a box apart, both images are minimal: either sign is right.
    tie = (np.abs(np.abs(disp) - box / 2) <= atol) & (np.abs(np.abs(expected) - box / 2) <= atol)
    assert np.all(same | (tie & flags)), "shifts do not give the minimum-image displacement"
    assert np.all(np.sqrt((disp * disp).sum(axis=1)) <= radius * (1 + 1e-9) + atol)


def unit_radius(n: int, dim: int, neighbours: float = 14.0) -> float:
    """Radius giving about `neighbours` (self included) for n uniform points in the unit box."""
    n = max(n, 1)
    if dim == 2:
        return math.sqrt(neighbours / (math.pi * n))
    return (neighbours * 3 / (4 * math.pi * n)) ** (1 / 3)


def radius_for(kind: str, n: int, dim: int) -> float:
    return {"tiny": 1e-9, "moderate": unit_radius(n, dim), "large": 2.0}[kind]


def uniform(rng, n, dim, dtype) -> np.ndarray:
    return rng.random((n, dim)).astype(dtype)


def clumped(rng, n, dim, dtype, width) -> np.ndarray:
    """Half the points uniform in the unit box, half in a box `width` wide at (0.3, ...)."""
    x = rng.random((n, dim))
    x[: n // 2] = 0.3 + width * x[: n // 2]
    return rng.permutation(x).astype(dtype)


def search_all(x, radius, **kwargs):
    """radius_graph with every method; returns {method: result}."""
    return {m: gns.radius_graph(x, radius, method=m, **kwargs) for m in METHODS}


def assert_edges(got: np.ndarray, expected: np.ndarray, what: str = "") -> None:
    assert got.dtype == np.int64, what
    assert got.shape == expected.shape, f"{what}: {got.shape} != {expected.shape}"
    assert np.array_equal(got, expected), what


# ----------------------------------------------------------------------------- main sweep


# A complete graph on 20k points would be 400M edges: "large" stops at 1000.
SIZE_RADIUS = [
    (n, k) for n in SIZES for k in ("tiny", "moderate", "large") if n <= 1000 or k != "large"
]


@pytest.mark.parametrize(("n", "radius_kind"), SIZE_RADIUS)
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("dim", [2, 3])
def test_uniform_matches_ckdtree(dim, dtype, n, radius_kind):
    rng = np.random.default_rng([dim, n, len(radius_kind)])
    x = uniform(rng, n, dim, dtype)
    radius = radius_for(radius_kind, n, dim)
    expected = oracle(x, radius)
    if radius_kind == "tiny":
        # Independent of the oracle: random points are isolated at this radius.
        assert_edges(expected, np.stack([np.arange(n), np.arange(n)]))
    if radius_kind == "large" and n:
        assert expected.shape[1] == n * n
    for method in METHODS:
        if method == "brute" and n > 1000 and (dtype == np.float32 or radius_kind == "tiny"):
            continue  # O(N^2): one run per dimension covers brute force at 20k
        got = gns.radius_graph(x, radius, method=method)
        assert_edges(got, expected, method)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("dim", [2, 3])
def test_self_edges_false_matches_ckdtree(dim, dtype):
    rng = np.random.default_rng(7)
    x = uniform(rng, 1000, dim, dtype)
    radius = unit_radius(1000, dim)
    expected = oracle(x, radius, self_edges=False)
    assert np.all(expected[0] != expected[1])
    for method, got in search_all(x, radius, self_edges=False).items():
        assert_edges(got, expected, method)


@pytest.mark.parametrize(
    ("n", "width"),
    [(200, 1e-7), (1000, 1e-3), (1000, 0.125), (20000, 0.25)],
)
@pytest.mark.parametrize("dim", [2, 3])
def test_clumped_matches_ckdtree(dim, n, width):
    rng = np.random.default_rng([dim, n])
    x = clumped(rng, n, dim, np.float64, width)
    radius = unit_radius(n, dim)
    expected = oracle(x, radius)
    for method in METHODS:
        if method == "brute" and n > 1000:
            continue
        assert_edges(gns.radius_graph(x, radius, method=method), expected, method)


@pytest.mark.parametrize("dim", [2, 3])
def test_clump_in_tiny_region_is_complete(dim):
    """100 points within 1e-7 of each other and radius 1e-3: a complete graph among them."""
    rng = np.random.default_rng(3)
    x = np.concatenate([0.5 + 1e-7 * rng.random((100, dim)), rng.random((100, dim))])
    got = gns.radius_graph(x, 1e-3)
    clump = got[:, (got[0] < 100) & (got[1] < 100)]
    assert clump.shape[1] == 100 * 100
    assert_edges(got, oracle(x, 1e-3))


# ----------------------------------------------------------------------------- exact radius


AT_RADIUS = [
    (np.array([[0.0, 0.0], [3.0, 4.0]]), 5.0),
    (np.array([[0.25, -0.5], [3.25, 3.5]]), 5.0),
    (np.array([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0]]), 0.5),
    (np.array([[1.0, 2.0, 3.0], [1.0, 2.0, 3.75]]), 0.75),
    (np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 2.0]]), 3.0),
]


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize(("points", "radius"), AT_RADIUS)
def test_pair_exactly_at_radius_is_included(points, radius, dtype, method):
    x = points.astype(dtype)
    got = gns.radius_graph(x, radius, method=method)
    assert_edges(got, np.array([[0, 1, 0, 1], [0, 0, 1, 1]]), method)
    assert_edges(got, oracle(x, radius), method)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize(("points", "radius"), AT_RADIUS)
def test_pair_a_hair_beyond_radius_is_excluded(points, radius, dtype, method):
    x = points.astype(dtype)
    # Move the second point one ulp (of the dtype) further away along its last moved axis.
    # (As few ulps as it takes for the float64 difference to change.)
    axis = int(np.flatnonzero(x[1] != x[0])[-1])
    away = dtype(np.inf if x[1, axis] > x[0, axis] else -np.inf)
    gap = float(x[1, axis]) - float(x[0, axis])
    while float(x[1, axis]) - float(x[0, axis]) == gap:
        x[1, axis] = np.nextafter(x[1, axis], away)
    assert oracle(x, radius).shape[1] == 2
    self_only = np.array([[0, 1], [0, 1]])
    assert_edges(gns.radius_graph(x, radius, method=method), self_only, method)
    # And the radius a hair smaller than the exact distance.
    x = points.astype(dtype)
    smaller = float(np.nextafter(radius, 0.0))
    assert_edges(gns.radius_graph(x, smaller, method=method), self_only, method)


@pytest.mark.parametrize("radius", [1.0, 2.0, 0.5, math.sqrt(2.0), math.sqrt(5.0), 2.5])
@pytest.mark.parametrize("dim", [2, 3])
def test_lattice_with_radius_on_lattice_distances(dim, radius):
    """Points on a dyadic lattice: many pairs at exactly the radius, on cell boundaries."""
    side = 12 if dim == 2 else 7
    grid = np.stack(np.meshgrid(*[np.arange(side)] * dim, indexing="ij"), -1).reshape(-1, dim)
    x = grid * 0.5 - 1.0
    r = radius * 0.5
    expected = oracle(x, r)
    for method, got in search_all(x, r).items():
        assert_edges(got, expected, method)


@pytest.mark.parametrize("dim", [2, 3])
def test_near_radius_pairs_agree_with_ckdtree(dim):
    """Pairs placed within a few ulps of the radius: every method draws the line like scipy."""
    rng = np.random.default_rng(11)
    n, radius = 400, 0.0625
    centres = rng.random((n, dim)) * 4
    u = rng.normal(size=(n, dim))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    x = np.concatenate([centres, centres + radius * u])
    expected = oracle(x, radius)
    for method, got in search_all(x, radius).items():
        assert_edges(got, expected, method)


# ----------------------------------------------------------------------------- duplicates


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("dim", [2, 3])
def test_coincident_points_are_neighbours(dim, dtype):
    rng = np.random.default_rng(5)
    x = rng.random((60, dim)).astype(dtype)
    x[10:15] = x[3]  # six copies of one point: indices 3 and 10..14
    x[40] = x[20]
    copies = [3, 10, 11, 12, 13, 14]
    for self_edges in (True, False):
        expected = oracle(x, 1e-9, self_edges=self_edges)
        pairs = {(a, b) for a in copies for b in copies if self_edges or a != b}
        pairs |= {(20, 40), (40, 20)} | ({(20, 20), (40, 40)} if self_edges else set())
        if self_edges:
            pairs |= {(i, i) for i in range(60)}
        s, r = zip(*sorted(pairs), strict=True)
        assert_edges(expected, sort_edges(s, r), "oracle")
        for method, got in search_all(x, 1e-9, self_edges=self_edges).items():
            assert_edges(got, expected, method)


@pytest.mark.parametrize("method", METHODS)
def test_self_edges_false_removes_only_self_loops(method):
    rng = np.random.default_rng(6)
    x = rng.random((500, 3))
    x[250:] = x[:250]  # every point duplicated
    radius = unit_radius(250, 3)
    with_self = gns.radius_graph(x, radius, method=method)
    without = gns.radius_graph(x, radius, method=method, self_edges=False)
    keep = with_self[0] != with_self[1]
    assert_edges(without, with_self[:, keep], method)
    assert np.count_nonzero(~keep) == 500


# ----------------------------------------------------------------------------- batches


@pytest.mark.parametrize(
    "n_node",
    [[0], [1], [50], [0, 0, 0], [3, 0, 47], [0, 1000, 0, 20, 0], [17] * 30, [2000, 0, 5, 3000, 1]],
)
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("dim", [2, 3])
def test_batches_match_per_graph_oracle(dim, dtype, n_node):
    rng = np.random.default_rng([dim, len(n_node), sum(n_node)])
    n = sum(n_node)
    # Every graph fills the same unit box, so a search that ignored n_node would cross graphs.
    x = uniform(rng, n, dim, dtype)
    radius = unit_radius(max(n_node), dim, 30.0)
    for self_edges in (True, False):
        expected = batched_oracle(x, radius, n_node, self_edges=self_edges)
        for method in METHODS:
            got = gns.radius_graph(
                x, radius, n_node=np.array(n_node), method=method, self_edges=self_edges
            )
            assert_edges(got, expected, method)
            bounds = np.cumsum([0, *n_node])
            graph = np.searchsorted(bounds, got, side="right") - 1
            assert np.array_equal(graph[0], graph[1])


def test_n_node_accepts_lists_and_int32():
    rng = np.random.default_rng(8)
    x = rng.random((30, 2))
    expected = batched_oracle(x, 0.3, [10, 20])
    assert_edges(gns.radius_graph(x, 0.3, n_node=[10, 20]), expected)
    assert_edges(gns.radius_graph(x, 0.3, n_node=np.array([10, 20], np.int32)), expected)


# ----------------------------------------------------------------------------- far outliers


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("dim", [2, 3])
def test_far_outliers_match_ckdtree(dim, dtype):
    rng = np.random.default_rng([dim, 17])
    n = 5000
    x = rng.random((n, dim))
    far = rng.choice(n, size=n // 100, replace=False)
    x[far] = 1e6 * (rng.random((len(far), dim)) * 2 - 1)
    x[far[:3]] = x[far[0]] + [1e-3, 0, 0][:dim]  # a few neighbours out there too
    x = x.astype(dtype)
    radius = unit_radius(n, dim)
    expected = oracle(x, radius)
    for method, got in search_all(x, radius).items():
        assert_edges(got, expected, method)


# ----------------------------------------------------------------------------- threads, reuse


@pytest.mark.parametrize("dim", [2, 3])
# 1000 particles: parallel since it is past the serial threshold (640), one cell-sort part;
# 24000: the counting sort split per thread too.
@pytest.mark.parametrize("n", [1000, 24000])
def test_thread_count_does_not_change_output(dim, n):
    rng = np.random.default_rng([dim, 18, n])
    x = clumped(rng, n, dim, np.float64, 0.5)
    radius = unit_radius(n, dim)
    expected = oracle(x, radius)
    n_node = [n * 7 // 24, 0, n - n * 7 // 24]
    box = [1.0] * dim
    results = {}
    for k in (1, 2, 3):
        searcher = gns.RadiusSearcher(num_threads=k)
        assert searcher.num_threads == k
        results[k] = (
            searcher(x, radius),
            searcher(x, radius, method="kdtree"),
            searcher(x, radius, n_node=n_node, self_edges=False),
            searcher(x * 3 - 1, radius, box=box, periodic=True, return_shifts=True),
        )
    assert_edges(results[1][0], expected)
    assert_edges(results[1][1], expected)
    for k in (2, 3):
        for a, b in zip(results[1][:3], results[k][:3], strict=True):
            assert_edges(b, a, f"{k} threads")
        for a, b in zip(results[1][3], results[k][3], strict=True):
            assert a.dtype == b.dtype and np.array_equal(a, b), f"{k} threads, periodic"


def test_searcher_reuse_across_sizes_and_dims():
    rng = np.random.default_rng(19)
    searcher = gns.RadiusSearcher()
    default = gns.RadiusSearcher(num_threads=None)
    assert default.num_threads is None
    calls = [
        (uniform(rng, 1000, 2, np.float64), 0.05, {}),
        (uniform(rng, 50, 3, np.float32), 0.3, {}),
        (uniform(rng, 0, 2, np.float64), 0.3, {}),
        (uniform(rng, 20000, 3, np.float64), unit_radius(20000, 3), {}),
        (uniform(rng, 5, 2, np.float64), 0.5, {"n_node": [2, 0, 3]}),
        (uniform(rng, 1, 3, np.float32), 0.1, {}),
        (uniform(rng, 3000, 2, np.float32), 0.03, {"self_edges": False}),
        (uniform(rng, 20000, 2, np.float64), unit_radius(20000, 2), {"method": "kdtree"}),
        (uniform(rng, 100, 3, np.float64), 0.2, {"method": "brute"}),
    ]
    for x, radius, kwargs in calls * 2:
        n_node = kwargs.get("n_node")
        self_edges = kwargs.get("self_edges", True)
        if n_node:
            expected = batched_oracle(x, radius, n_node, self_edges=self_edges)
        else:
            expected = oracle(x, radius, self_edges=self_edges)
        assert_edges(searcher(x, radius, **kwargs), expected, f"{x.shape} {kwargs}")
        assert_edges(default(x, radius, **kwargs), expected, f"{x.shape} {kwargs}")
    # A periodic call with shifts after the others, then a plain one again.
    x = rng.random((700, 3)) * 2
    got, shifts = searcher(x, 0.2, box=[1.0] * 3, periodic=True, return_shifts=True)
    assert_edges(got, periodic_oracle(x, 0.2, [1.0] * 3, [True] * 3))
    check_shifts(x, got, shifts, [1.0] * 3, [True] * 3, 0.2)
    assert_edges(searcher(calls[0][0], 0.05), oracle(calls[0][0], 0.05))


def test_searcher_results_are_independent_arrays():
    """A later call must not overwrite the arrays an earlier call returned."""
    rng = np.random.default_rng(20)
    searcher = gns.RadiusSearcher()
    a = rng.random((2000, 2))
    b = rng.random((2000, 2))
    first = searcher(a, 0.05)
    snapshot = first.copy()
    searcher(b, 0.05)
    assert np.array_equal(first, snapshot)


# ----------------------------------------------------------------------------- properties


def _cloud(draw, max_n=40):
    dim = draw(st.sampled_from([2, 3]))
    n = draw(st.integers(0, max_n))
    # Few distinct values per coordinate so duplicates and exact-radius ties are common.
    coord = st.one_of(
        st.floats(-4.0, 4.0, allow_nan=False, width=64),
        st.sampled_from([0.0, 0.25, 0.5, 1.0, -1.0, 3.0, 4.0]),
    )
    x = np.array(draw(st.lists(coord, min_size=n * dim, max_size=n * dim)), dtype=np.float64)
    return x.reshape(n, dim)


@st.composite
def clouds(draw):
    x = _cloud(draw)
    radius = draw(st.one_of(st.floats(1e-3, 6.0), st.sampled_from([0.25, 0.5, 1.0, 5.0])))
    dtype = draw(st.sampled_from(DTYPES))
    return x.astype(dtype), radius


@settings(max_examples=150, deadline=None)
@given(clouds(), st.booleans())
def test_property_matches_ckdtree(cloud, self_edges):
    x, radius = cloud
    expected = oracle(x, radius, self_edges=self_edges)
    for method, got in search_all(x, radius, self_edges=self_edges).items():
        assert_edges(got, expected, method)


@st.composite
def grid_clouds(draw):
    """Integer-grid points scaled by 1/8: translations by grid vectors keep distances exact."""
    dim = draw(st.sampled_from([2, 3]))
    n = draw(st.integers(0, 60))
    pts = draw(st.lists(st.integers(-64, 64), min_size=n * dim, max_size=n * dim))
    shift = draw(st.lists(st.integers(-(2**20), 2**20), min_size=dim, max_size=dim))
    r2 = draw(st.integers(1, 2000))  # radius**2 in units of (1/8)**2
    x = np.array(pts, dtype=np.float64).reshape(n, dim) / 8
    return x, np.array(shift, dtype=np.float64) / 8, math.sqrt(r2) / 8


@settings(max_examples=100, deadline=None)
@given(grid_clouds(), st.sampled_from(METHODS))
def test_property_translation_invariance(cloud, method):
    x, shift, radius = cloud
    moved = x + shift
    assert np.array_equal(moved - shift, x)  # exact on this grid
    got = gns.radius_graph(x, radius, method=method)
    assert_edges(gns.radius_graph(moved, radius, method=method), got, method)
    assert_edges(got, oracle(x, radius), method)


@settings(max_examples=100, deadline=None)
@given(clouds(), st.randoms(use_true_random=False), st.sampled_from(METHODS))
def test_property_permutation_equivariance(cloud, rnd, method):
    x, radius = cloud
    perm = np.array(rnd.sample(range(len(x)), len(x)), dtype=np.int64)
    got = gns.radius_graph(x, radius, method=method)
    permuted = gns.radius_graph(x[perm], radius, method=method)
    # Edge (s', r') of the permuted input is edge (perm[s'], perm[r']) of the original.
    assert_edges(sort_edges(perm[permuted[0]], perm[permuted[1]]), got, method)


@st.composite
def periodic_clouds(draw):
    x = _cloud(draw, max_n=30)
    dim = x.shape[1]
    box = np.array(
        draw(st.lists(st.sampled_from([1.0, 2.0, 4.0, 8.0]), min_size=dim, max_size=dim))
    )
    flags = draw(st.lists(st.booleans(), min_size=dim, max_size=dim))
    radius = draw(st.floats(1e-3, 1.0)) * box[np.array(flags)].min() / 2 if any(flags) else 1.0
    return x, box, flags, radius


@settings(max_examples=100, deadline=None)
@given(periodic_clouds(), st.sampled_from(METHODS))
def test_property_periodic(cloud, method):
    x, box, flags, radius = cloud
    got, shifts = gns.radius_graph(
        x, radius, box=box, periodic=flags, method=method, return_shifts=True
    )
    assert_edges(got, brute_min_image(x, radius, box, flags), method)
    check_shifts(x, got, shifts, box, flags, radius)


def test_torch_tensors_round_trip():
    torch = pytest.importorskip("torch")
    rng = np.random.default_rng(24)
    x = rng.random((500, 3))
    got = gns.radius_graph(torch.from_numpy(x), 0.2)
    assert isinstance(got, torch.Tensor) and got.dtype == torch.int64
    assert_edges(got.numpy(), oracle(x, 0.2))
