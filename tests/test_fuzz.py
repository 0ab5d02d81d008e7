"""Fuzzing every public function of the Rust core with hypothesis (issue 7): arbitrary shapes,
dtypes and values, NaN, infinities, huge and subnormal numbers. Each call either returns the
right answer, checked against a numpy oracle, or raises ValueError; and it raises exactly when
the input is invalid by the documented rules, decided here independently of the code.

GNS_FUZZ_EXAMPLES sets the examples per test (default 150, derandomized so CI is repeatable);
`python benches/stability.py --only fuzz` runs this file with many more, randomized.
"""

from __future__ import annotations

import os

import gns
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

EXAMPLES = int(os.environ.get("GNS_FUZZ_EXAMPLES", "150"))
fuzz = settings(
    max_examples=EXAMPLES,
    derandomize="GNS_FUZZ_EXAMPLES" not in os.environ,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
)
DTYPES = [np.float32, np.float64, np.float16, np.int64]
# The widths the core widens exactly (integers, float16) or keeps (float32, float64).
FLOAT_KINDS = "fiu"


def any_floats(width: int = 64) -> st.SearchStrategy[float]:
    return st.floats(allow_nan=True, allow_infinity=True, width=width)


@st.composite
def arrays(draw, rows=None, dims=None) -> np.ndarray:
    """Mostly (N, D) with D in 1..4, sometimes 1-D or 3-D; any dtype of DTYPES; values from
    tame to absurd."""
    dtype = draw(st.sampled_from(DTYPES))
    if draw(st.integers(0, 9)) == 0:
        shape = draw(hnp.array_shapes(min_dims=1, max_dims=3, min_side=0, max_side=6))
    else:
        n = draw(st.integers(0, 30)) if rows is None else rows
        d = draw(st.integers(1, 4)) if dims is None else dims
        shape = (n, d)
    if dtype == np.int64:
        elements = st.integers(-(10**6), 10**6)
    else:
        tame = st.floats(-2.0, 2.0, width=np.dtype(dtype).itemsize * 8)
        elements = st.one_of(tame, any_floats(np.dtype(dtype).itemsize * 8))
    return draw(hnp.arrays(dtype, shape, elements=elements))


radii = st.one_of(st.floats(0.01, 1.0), any_floats())


def finite_float_rows(x: np.ndarray) -> bool:
    return x.ndim == 2 and x.dtype.kind in FLOAT_KINDS and bool(np.isfinite(x).all())


def valid_positions(x: np.ndarray) -> bool:
    return finite_float_rows(x) and x.shape[1] in (2, 3)


def valid_radius(r: float) -> bool:
    """Finite, > 0, and with a finite square (distances are compared squared)."""
    return np.isfinite(r) and r > 0 and np.isfinite(r * r)


def brute_pairs(x: np.ndarray, r: float, self_edges: bool) -> set[tuple[int, int]]:
    """(receiver, sender) of every pair within r, in float64 as the core measures."""
    y = x.astype(np.float64)
    with np.errstate(over="ignore", invalid="ignore"):
        d = y[None, :, :] - y[:, None, :]  # [i, j] = x_j - x_i
        d2 = np.zeros(d.shape[:2])
        for axis in range(y.shape[1]):  # summed axis by axis, as the core does
            d2 = d2 + d[..., axis] * d[..., axis]
    close = d2 <= r * r
    if not self_edges:
        np.fill_diagonal(close, False)
    return {(int(i), int(j)) for i, j in zip(*np.nonzero(close), strict=True)}


@fuzz
@given(x=arrays(), r=radii, self_edges=st.booleans(), method=st.sampled_from(["cells", "kdtree"]))
def test_radius_graph(x, r, self_edges, method):
    if not (valid_positions(x) and valid_radius(r)):
        with pytest.raises(ValueError):
            gns.radius_graph(x, r, self_edges=self_edges, method=method)
        return
    edges = gns.radius_graph(x, r, self_edges=self_edges, method=method)
    assert edges.dtype == np.int64 and edges.shape[0] == 2
    found = list(zip(edges[1].tolist(), edges[0].tolist(), strict=True))
    assert found == sorted(found), "sorted by (receiver, sender)"
    assert set(found) == brute_pairs(x, r, self_edges) and len(set(found)) == len(found)


@fuzz
@given(x=arrays(), r=radii, lengths=st.tuples(any_floats(), any_floats()))
def test_periodic_radius_graph(x, r, lengths):
    box = list(lengths)
    ok = valid_positions(x) and valid_radius(r) and x.shape[1] == 2
    # Box lengths finite and > 0; the periodic one at least 2 r (the minimum image).
    # At most 2^20 radii long (wrapped positions round by < 2^-32 radii), positions fewer than
    # 2^29 box lengths away from it.
    ok = ok and all(np.isfinite(b) and b > 0 for b in box) and 2 * r <= box[0] <= 2**20 * r
    with np.errstate(over="ignore", invalid="ignore"):
        ok = ok and bool(np.all(np.abs(np.floor(x[:, 0] / box[0])) <= (2**31 - 1) // 4))
    if not ok:
        with pytest.raises(ValueError):
            gns.radius_graph(x, r, box=box, periodic=[True, False])
        return
    edges = gns.radius_graph(x, r, box=box, periodic=[True, False])
    # Every edge is within r under the minimum image along the periodic axis.
    y = x.astype(np.float64)
    d = y[edges[0]] - y[edges[1]]
    d[:, 0] -= np.round(d[:, 0] / box[0]) * box[0]
    assert np.all(np.hypot(d[:, 0], d[:, 1]) <= r * (1 + 1e-12) + 1e-300)


@fuzz
@given(x=arrays(), n_node=st.lists(st.integers(-3, 35), max_size=3), r=st.floats(0.01, 1.0))
def test_batched_radius_graph(x, n_node, r):
    ok = valid_positions(x) and all(k >= 0 for k in n_node) and sum(n_node) == x.shape[0]
    if not ok:
        with pytest.raises(ValueError):
            gns.radius_graph(x, r, n_node=n_node)
        return
    edges = gns.radius_graph(x, r, n_node=n_node)
    graph = np.repeat(np.arange(len(n_node)), n_node)
    assert np.array_equal(graph[edges[0]], graph[edges[1]]), "no edge between graphs"
    expected = set()
    start = 0
    for k in n_node:
        pairs = brute_pairs(x[start : start + k], r, True)
        expected |= {(i + start, j + start) for i, j in pairs}
        start += k
    assert set(zip(edges[1].tolist(), edges[0].tolist(), strict=True)) == expected


@fuzz
@given(x=arrays(), r=radii, upper=any_floats(), clip=st.one_of(st.just(1.0), any_floats()))
def test_wall_features(x, r, upper, clip):
    bounds = [(0.0, upper), (0.0, 1.0), (-1.0, 1.0)][: x.shape[-1] if x.ndim == 2 else 2]
    ok = valid_positions(x) and np.isfinite(r) and r > 0 and np.isfinite(upper) and upper > 0
    ok = ok and np.isfinite(clip) and clip > 0
    if not ok:
        with pytest.raises(ValueError):
            gns.wall_features(x, bounds, r, clip=clip)
        return
    got = gns.wall_features(x, bounds, r, clip=clip)
    b = np.asarray(bounds, dtype=np.float64)
    y = x.astype(np.float64)
    with np.errstate(over="ignore"):
        expected = np.concatenate([(y - b[:, 0]) / r, (b[:, 1] - y) / r], axis=1)
    expected = np.clip(expected, -clip, clip)
    out_dtype = x.dtype if x.dtype in (np.float32, np.float64) else np.float64
    assert got.shape == (x.shape[0], 2 * x.shape[1]) and got.dtype == out_dtype
    np.testing.assert_allclose(got, expected.astype(out_dtype), rtol=1e-6, atol=1e-30)


@fuzz
@given(x=arrays(dims=2), r=radii)
def test_obstacle_features(x, r):
    segment = gns.Obstacle.polyline([[0.1, 0.1], [0.9, 0.3]])
    # Obstacle radii stop at 1e100 (parry's squared distances overflow near 1e154).
    if not (valid_positions(x) and x.shape[1] == 2 and valid_radius(r) and r <= 1e100):
        with pytest.raises(ValueError):
            gns.obstacle_features(x, [segment], r)
        return
    got = np.asarray(gns.obstacle_features(x, [segment], r), dtype=np.float64)
    assert got.shape == (x.shape[0], 2) and np.isfinite(got).all()
    # The nearest point of the segment, by projection: the oracle.
    a, b = np.array([0.1, 0.1]), np.array([0.9, 0.3])
    y = x.astype(np.float64)
    t = np.clip(((y - a) @ (b - a)) / ((b - a) @ (b - a)), 0.0, 1.0)
    vector = (a + t[:, None] * (b - a) - y) / r
    within = np.linalg.norm(vector, axis=1) <= 1.0
    expected = np.where(within[:, None], vector, 0.0)
    # Exactly at the radius either answer is right; elsewhere the value must match.
    edge = np.abs(np.linalg.norm(vector, axis=1) - 1.0) < 1e-6
    tolerance = 1e-5 if x.dtype == np.float32 or x.dtype == np.float16 else 1e-9
    np.testing.assert_allclose(got[~edge], expected[~edge], atol=tolerance, rtol=1e-5)


@fuzz
@given(data=st.data(), dt=st.one_of(st.just(1.0), any_floats()))
def test_euler_step(data, dt):
    """The rules: three arrays of one shape (N, D), any D >= 1, in float32 or float64 (one dtype),
    finite, dt finite and > 0, and a finite result in that dtype. The oracle works in float64
    and rounds each new value to the dtype, as documented."""
    x = data.draw(arrays(), label="position")
    if x.ndim == 2 and data.draw(st.booleans(), label="same shape and dtype"):
        v = data.draw(hnp.arrays(x.dtype, x.shape), label="velocity")
        a = data.draw(hnp.arrays(x.dtype, x.shape), label="acceleration")
    else:
        v = data.draw(arrays(), label="velocity")
        a = data.draw(arrays(), label="acceleration")
    valid = x.ndim == 2 and x.shape[1] >= 1 and x.dtype in (np.float32, np.float64)
    valid = valid and np.isfinite(dt) and dt > 0
    valid = valid and all(
        y.shape == x.shape and y.dtype == x.dtype and np.isfinite(y).all() for y in (x, v, a)
    )
    if valid:
        with np.errstate(over="ignore", invalid="ignore"):
            v1 = (v.astype(np.float64) + dt * a.astype(np.float64)).astype(x.dtype)
            x1 = (x.astype(np.float64) + dt * v1.astype(np.float64)).astype(x.dtype)
        valid = bool(np.isfinite(v1).all() and np.isfinite(x1).all())
    if not valid:
        with pytest.raises(ValueError):
            gns.euler_step(x, v, a, dt=dt)
        return
    got_x, got_v = gns.euler_step(x, v, a, dt=dt)
    assert got_x.dtype == got_v.dtype == x.dtype
    np.testing.assert_array_equal(got_v, v1)
    np.testing.assert_array_equal(got_x, x1)
