"""gns.radius_graph and gns.RadiusSearcher in periodic boxes, and the inputs they accept and
refuse.

Periodic boxes (axes periodic or not, positions outside the box and ~1e6 boxes away, a box
exactly 2 * radius wide, batches) against cKDTree with boxsize or brute-force minimum image,
with the returned shifts checked to give the minimum-image displacement; integer,
non-contiguous, empty and single-point positions; and the ValueErrors for non-finite positions,
bad arrays, radii, n_node, boxes, methods, thread counts and max_edges (a searcher stays usable
after one). The oracles and helpers are test_graph.py's.
"""

from __future__ import annotations

import gns
import numpy as np
import pytest
from test_graph import (
    DTYPES,
    METHODS,
    assert_edges,
    brute_min_image,
    check_shifts,
    min_image,
    oracle,
    periodic_oracle,
    search_all,
    unit_radius,
    wrap,
)

# ----------------------------------------------------------------------------- periodic


PERIODIC_CASES = [
    (2, [1.0, 1.0], [True, True]),
    (2, [0.75, 1.5], True),
    (2, [1.0, 2.0], [True, False]),
    (2, [1.0, 1.0], [False, True]),
    (3, [1.0, 1.0, 1.0], True),
    (3, [0.7, 1.3, 1.1], [True, False, True]),
    (3, [1.0, 1.0, 1.0], [False, False, True]),
]


def _flags(periodic, dim):
    return [periodic] * dim if isinstance(periodic, bool) else list(periodic)


@pytest.mark.parametrize("n", [0, 1, 2, 50, 2000])
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize(("dim", "box", "periodic"), PERIODIC_CASES)
def test_periodic_matches_ckdtree(dim, box, periodic, dtype, n):
    rng = np.random.default_rng([dim, n, int(1000 * box[0])])
    flags = _flags(periodic, dim)
    x = (rng.random((n, dim)) * box).astype(dtype)
    radius = 0.12
    expected = periodic_oracle(x, radius, box, flags)
    for method in METHODS:
        got, shifts = gns.radius_graph(
            x, radius, box=box, periodic=periodic, method=method, return_shifts=True
        )
        assert_edges(got, expected, method)
        check_shifts(x, got, shifts, box, flags, radius)
        plain = gns.radius_graph(x, radius, box=box, periodic=periodic, method=method)
        assert_edges(plain, expected, method)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize(("dim", "box", "periodic"), PERIODIC_CASES)
def test_periodic_positions_outside_box_are_wrapped(dim, box, periodic, dtype):
    rng = np.random.default_rng([dim, 99])
    flags = _flags(periodic, dim)
    n = 1500
    # Up to 3 box lengths below and 3 above on every axis (non-periodic axes are just wide).
    x = ((rng.random((n, dim)) * 7 - 3) * box).astype(dtype)
    radius = 0.1
    expected = periodic_oracle(x, radius, box, flags)
    for method in METHODS:
        got, shifts = gns.radius_graph(
            x, radius, box=box, periodic=periodic, method=method, return_shifts=True
        )
        assert_edges(got, expected, method)
        check_shifts(x, got, shifts, box, flags, radius)


@pytest.mark.parametrize("dim", [2, 3])
def test_periodic_far_outside_box(dim):
    """Positions ~1e6 box lengths away; dyadic values so wrapping is exact."""
    rng = np.random.default_rng(12)
    box = [1.0] * dim
    inside = rng.integers(0, 2**20, size=(800, dim)) / 2.0**20
    k = rng.integers(-(10**6), 10**6, size=(800, dim))
    x = inside + k
    assert np.array_equal(wrap(x, box, [True] * dim), inside)
    radius = 0.1
    expected = oracle(inside, radius, boxsize=box)
    for method in METHODS:
        got, shifts = gns.radius_graph(
            x, radius, box=box, periodic=True, method=method, return_shifts=True
        )
        assert_edges(got, expected, method)
        check_shifts(x, got, shifts, box, [True] * dim, radius)
        # The shifts carry the image count exactly: wrapped displacement = raw + shifts * L.
        s, r = got
        disp = x[s] - x[r] + shifts
        np.testing.assert_allclose(disp, min_image(inside[s] - inside[r], box, [True] * dim))


@pytest.mark.parametrize("periodic", [True, [True, False], [False, True]])
@pytest.mark.parametrize("dtype", DTYPES)
def test_periodic_box_exactly_twice_radius(periodic, dtype):
    rng = np.random.default_rng(13)
    box, radius = [1.0, 1.0], 0.5
    flags = _flags(periodic, 2)
    x = np.concatenate(
        [
            rng.random((300, 2)),
            # Hand-placed pairs at exactly half a box apart along a periodic axis: one pair,
            # whichever image, at distance exactly r.
            [[0.0, 0.0], [0.5, 0.0], [0.25, 0.0], [0.25, 0.5], [0.125, 0.875], [0.625, 0.875]],
        ]
    ).astype(dtype)
    for self_edges in (True, False):
        expected = brute_min_image(x, radius, box, flags, self_edges=self_edges)
        for method in METHODS:
            got, shifts = gns.radius_graph(
                x,
                radius,
                box=box,
                periodic=periodic,
                method=method,
                return_shifts=True,
                self_edges=self_edges,
            )
            assert_edges(got, expected, method)
            check_shifts(x, got, shifts, box, flags, radius)
    pairs = set(zip(*gns.radius_graph(x, radius, box=box, periodic=True), strict=True))
    assert (300, 301) in pairs and (301, 300) in pairs


@pytest.mark.parametrize("dim", [2, 3])
def test_periodic_box_exactly_twice_radius_3d_and_2d_brute(dim):
    rng = np.random.default_rng(14)
    box = [0.5] * dim
    x = rng.random((250, dim)) * 0.5 - 0.25  # half of it outside [0, L)
    expected = brute_min_image(x, 0.25, box, [True] * dim)
    for method in METHODS:
        got, shifts = gns.radius_graph(
            x, 0.25, box=box, periodic=True, method=method, return_shifts=True
        )
        assert_edges(got, expected, method)
        check_shifts(x, got, shifts, box, [True] * dim, 0.25)


@pytest.mark.parametrize("dim", [2, 3])
def test_periodic_batches(dim):
    rng = np.random.default_rng(15)
    n_node = [0, 400, 1, 0, 900]
    box = [1.0] * dim
    x = rng.random((sum(n_node), dim)) * 3 - 1
    expected_parts, start = [], 0
    for size in n_node:
        part = periodic_oracle(x[start : start + size], 0.15, box, [True] * dim)
        expected_parts.append(part + start)
        start += size
    expected = np.concatenate(expected_parts, axis=1)
    for method in METHODS:
        got, shifts = gns.radius_graph(
            x, 0.15, n_node=n_node, box=box, periodic=True, method=method, return_shifts=True
        )
        assert_edges(got, expected, method)
        check_shifts(x, got, shifts, box, [True] * dim, 0.15)


def test_box_without_periodic_axes_gives_zero_shifts():
    rng = np.random.default_rng(16)
    x = rng.random((300, 3))
    expected = oracle(x, 0.2)
    for periodic in (None, False, [False, False, False]):
        got, shifts = gns.radius_graph(
            x, 0.2, box=[1.0, 1.0, 1.0], periodic=periodic, return_shifts=True
        )
        assert_edges(got, expected)
        assert shifts.dtype == np.int32 and shifts.shape == (got.shape[1], 3)
        assert not shifts.any()
    assert_edges(gns.radius_graph(x, 0.2, periodic=False), expected)


# ----------------------------------------------------------------------------- inputs


@pytest.mark.parametrize("int_dtype", [np.int32, np.int64, np.uint8])
def test_integer_positions_are_accepted_exactly(int_dtype):
    rng = np.random.default_rng(21)
    xi = rng.integers(0, 40, size=(400, 3)).astype(int_dtype)
    expected = oracle(xi.astype(np.float64), 5.0)
    for method, got in search_all(xi, 5.0).items():
        assert_edges(got, expected, method)
    assert_edges(gns.radius_graph(np.array([[0, 0], [3, 4]]), 5.0), oracle([[0, 0], [3, 4]], 5))


def test_non_contiguous_positions():
    rng = np.random.default_rng(22)
    big = rng.random((600, 6))
    x = big[::2, 1:4]  # strided view
    assert not x.flags.c_contiguous
    assert_edges(gns.radius_graph(x, 0.2), oracle(np.ascontiguousarray(x), 0.2))
    xf = np.asfortranarray(rng.random((300, 2)))
    assert_edges(gns.radius_graph(xf, 0.1), oracle(xf, 0.1))


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("n", [0, 1])
def test_empty_and_single(n, dim):
    x = np.zeros((n, dim))
    for method in METHODS:
        got = gns.radius_graph(x, 0.5, method=method)
        assert_edges(got, np.stack([np.arange(n), np.arange(n)]), method)
        assert_edges(gns.radius_graph(x, 0.5, method=method, self_edges=False), np.zeros((2, 0)))
        got, shifts = gns.radius_graph(
            x, 0.5, method=method, box=[1.0] * dim, periodic=True, return_shifts=True
        )
        assert got.shape == (2, n) and shifts.shape == (n, dim) and shifts.dtype == np.int32


def test_default_max_edges():
    assert gns.DEFAULT_MAX_EDGES == 2**28


# ----------------------------------------------------------------------------- errors


def _rand(n=20, dim=2):
    return np.random.default_rng(0).random((n, dim))


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("method", METHODS)
# 21 particles: 42 values, so the check's lanes of 8 see whole chunks and a tail of 2.
@pytest.mark.parametrize(("i", "d"), [(0, 0), (7, 1), (20, 1)])
def test_rejects_non_finite_positions(bad, dtype, method, i, d):
    x = _rand(21).astype(dtype)
    x[i, d] = bad
    with pytest.raises(ValueError, match=rf"positions\[{i}, {d}\].*finite"):
        gns.radius_graph(x, 0.1, method=method)
    with pytest.raises(ValueError, match="finite"):
        gns.RadiusSearcher()(x, 0.1, method=method)
    with pytest.raises(ValueError, match="finite"):
        gns.radius_graph(x, 0.1, method=method, box=[1.0, 1.0], periodic=True)


@pytest.mark.parametrize(
    ("x", "pattern"),
    [
        (np.zeros(10), "2-D"),
        (np.zeros((10, 4)), "2 or 3 columns"),
        (np.zeros((10, 1)), "2 or 3 columns"),
        (np.zeros((4, 3, 2)), "2-D"),
        (np.zeros((10, 2), dtype=complex), "complex"),
        (np.zeros((10, 2), dtype=object), "object"),
        (np.full((10, 2), "a"), "real numbers"),
    ],
)
def test_rejects_bad_position_arrays(x, pattern):
    with pytest.raises(ValueError, match=pattern):
        gns.radius_graph(x, 0.1)
    with pytest.raises(ValueError, match=pattern):
        gns.RadiusSearcher()(x, 0.1)


@pytest.mark.parametrize("radius", [0.0, -1.0, -0.0, np.nan, np.inf, -np.inf])
def test_rejects_bad_radius(radius):
    with pytest.raises(ValueError, match="radius"):
        gns.radius_graph(_rand(), radius)
    with pytest.raises(ValueError, match="radius"):
        gns.radius_graph(np.zeros((0, 2)), radius)


@pytest.mark.parametrize(
    ("n_node", "pattern"),
    [
        ([5, 4], "n_node"),
        ([15, 6], "n_node"),
        ([25, -5], "n_node"),
        ([-1, 21], "n_node"),
        ([], "n_node"),
        (np.array([10.0, 10.0]), "n_node"),
        (np.array([[20]]), "n_node"),
    ],
)
def test_rejects_bad_n_node(n_node, pattern):
    with pytest.raises(ValueError, match=pattern):
        gns.radius_graph(_rand(), 0.1, n_node=n_node)


def test_n_node_error_names_the_sums():
    with pytest.raises(ValueError, match=r"9.*20|20.*9"):
        gns.radius_graph(_rand(), 0.1, n_node=[5, 4])


@pytest.mark.parametrize(
    ("kwargs", "pattern"),
    [
        ({"periodic": True}, "box"),
        ({"periodic": [True, False]}, "box"),
        ({"box": [1.0, 1.0, 1.0], "periodic": True}, "box"),
        ({"box": [1.0], "periodic": True}, "box"),
        ({"box": [1.0, 1.0], "periodic": [True, False, True]}, "periodic"),
        ({"box": [1.0, 1.0], "periodic": [True]}, "periodic"),
        ({"box": [1.0, 0.0], "periodic": True}, "box"),
        ({"box": [1.0, -1.0], "periodic": True}, "box"),
        ({"box": [1.0, np.nan], "periodic": True}, "box"),
        ({"box": [0.3, 1.0], "periodic": True}, "2 \\* radius"),
        ({"box": [1.0, 0.39], "periodic": [False, True]}, "2 \\* radius"),
        ({"method": "octree"}, "method"),
        ({"method": "Cells"}, "method"),
        ({"max_edges": -1}, "max_edges"),
        ({"max_edges": 1.5}, "max_edges"),
    ],
)
def test_rejects_bad_options(kwargs, pattern):
    with pytest.raises(ValueError, match=pattern):
        gns.radius_graph(_rand(), 0.2, **kwargs)
    with pytest.raises(ValueError, match=pattern):
        gns.RadiusSearcher()(_rand(), 0.2, **kwargs)


def test_narrow_box_is_fine_on_non_periodic_axis():
    x = _rand() * [0.3, 1.0]
    got = gns.radius_graph(x, 0.2, box=[0.3, 1.0], periodic=[False, True])
    assert_edges(got, periodic_oracle(x, 0.2, [0.3, 1.0], [False, True]))


@pytest.mark.parametrize("method", METHODS)
def test_max_edges_exceeded_names_the_count(method):
    rng = np.random.default_rng(23)
    for n, dim in ((1000, 2), (5000 if method == "brute" else 20000, 3)):
        x = rng.random((n, dim))
        radius = unit_radius(n, dim)
        count = oracle(x, radius).shape[1]
        assert gns.radius_graph(x, radius, method=method, max_edges=count).shape == (2, count)
        with pytest.raises(ValueError, match=rf"\b{count}\b.*max_edges = {count - 1}"):
            gns.radius_graph(x, radius, method=method, max_edges=count - 1)
        with pytest.raises(ValueError, match="max_edges"):
            gns.RadiusSearcher()(x, radius, method=method, max_edges=count - 1)
        # A small limit may stop counting early, but the number named is a true lower bound.
        with pytest.raises(ValueError, match="max_edges") as info:
            gns.radius_graph(x, radius, method=method, max_edges=10)
        named = int(str(info.value).split("at least ")[1].split()[0])
        assert 10 < named <= count


def test_max_edges_zero_allows_empty_graph():
    x = _rand()
    assert gns.radius_graph(x, 1e-9, self_edges=False, max_edges=0).shape == (2, 0)
    with pytest.raises(ValueError, match="max_edges"):
        gns.radius_graph(x, 1e-9, max_edges=0)


@pytest.mark.parametrize("method", ["cells", "kdtree"])
def test_coincident_clump_hits_default_memory_guard(method):
    """100k coincident particles would make 1e10 edges: a prompt ValueError, not an OOM."""
    x = np.zeros((100_000, 3))
    with pytest.raises(ValueError, match="max_edges"):
        gns.radius_graph(x, 0.1, method=method)


@pytest.mark.parametrize("periodic", [False, True])
def test_coincident_clump_hits_max_edges(periodic):
    x = np.zeros((30_000, 3))
    box = [1.0, 1.0, 1.0] if periodic else None
    with pytest.raises(ValueError, match="max_edges = 1000000"):
        gns.radius_graph(x, 0.1, box=box, periodic=periodic, max_edges=10**6)


def test_searcher_rejects_bad_thread_count():
    with pytest.raises(ValueError, match="num_threads"):
        gns.RadiusSearcher(num_threads=0)


def test_searcher_rejects_negative_thread_count_with_value_error():
    with pytest.raises(ValueError, match="num_threads"):
        gns.RadiusSearcher(num_threads=-1)


def test_error_leaves_searcher_usable():
    searcher = gns.RadiusSearcher()
    x = _rand(500, 3)
    with pytest.raises(ValueError):
        searcher(x, 0.3, max_edges=5)
    bad = x.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError):
        searcher(bad, 0.3)
    assert_edges(searcher(x, 0.3), oracle(x, 0.3))
