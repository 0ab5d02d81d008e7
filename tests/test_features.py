"""gns.wall_features and gns.obstacle_features against numpy formulas and analytic geometry."""

from __future__ import annotations

import itertools

import gns
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

DTYPES = (np.float32, np.float64)


def close(dtype):
    """Tolerances: float64 results agree to rounding, float32 to its precision."""
    if dtype == np.float64:
        return {"rtol": 1e-12, "atol": 1e-12}
    return {"rtol": 1e-6, "atol": 1e-6}


# ----------------------------------------------------------------------------- walls


def walls_oracle(x, bounds, radius, clip):
    x = np.asarray(x, dtype=np.float64)
    lo, hi = bounds[:, 0], bounds[:, 1]
    lower = np.clip((x - lo) / radius, -clip, clip)
    upper = np.clip((hi - x) / radius, -clip, clip)
    return np.concatenate([lower, upper], axis=1)


@pytest.mark.parametrize("clip", [1.0, 0.5, 3.0])
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("dim", [2, 3])
def test_wall_features_match_formula(dim, dtype, clip):
    rng = np.random.default_rng([dim, int(clip * 10)])
    bounds = np.array([[0.1, 0.9], [-1.0, 2.0], [0.0, 1.0]][:dim])
    # Inside, near the walls, and outside the box (negative distances).
    x = (rng.random((3000, dim)) * 4 - 1.5).astype(dtype)
    radius = 0.015 * 3
    got = gns.wall_features(x, bounds, radius, clip=clip)
    assert got.dtype == dtype
    assert got.shape == (3000, 2 * dim)
    expected = walls_oracle(x, bounds, radius, clip)
    np.testing.assert_allclose(got, expected.astype(dtype), **close(dtype))
    assert np.all(np.abs(got) <= clip)
    # Every regime occurs: clipped at +clip, clipped at -clip, and in between.
    assert (got == clip).any() and (got == -clip).any() and (np.abs(got) < clip).any()


def test_wall_features_exact_values():
    bounds = np.array([[0.0, 1.0], [0.0, 2.0]])
    x = np.array([[0.25, 1.0], [0.0, 2.0], [-0.5, 0.125], [1.5, 3.0]])
    got = gns.wall_features(x, bounds, 0.5)
    expected = np.array(
        [
            [0.5, 1.0, 1.0, 1.0],  # lower (x, y), then upper (x, y)
            [0.0, 1.0, 1.0, 0.0],
            [-1.0, 0.25, 1.0, 1.0],
            [1.0, 1.0, -1.0, -1.0],
        ]
    )
    np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(
        gns.wall_features(x, bounds, 0.5, clip=10.0)[2], [-1, 0.25, 3, 3.75]
    )


def test_wall_features_default_clip_is_one():
    x = np.array([[5.0, -5.0]])
    bounds = np.array([[0.0, 1.0], [0.0, 1.0]])
    np.testing.assert_array_equal(gns.wall_features(x, bounds, 0.1), [[1, -1, -1, 1]])


@pytest.mark.parametrize("dim", [2, 3])
def test_wall_features_empty_and_integer_positions(dim):
    bounds = np.array([[0.0, 4.0]] * dim)
    assert gns.wall_features(np.zeros((0, dim)), bounds, 1.0).shape == (0, 2 * dim)
    xi = np.arange(3 * dim).reshape(3, dim) % 5
    got = gns.wall_features(xi, bounds, 2.0, clip=5.0)
    np.testing.assert_array_equal(got, walls_oracle(xi, bounds, 2.0, 5.0))


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.floats(-10, 10), min_size=6, max_size=6),
    st.floats(-10, 10),
    st.floats(0.01, 5),
    st.floats(0.1, 4),
    st.sampled_from(DTYPES),
)
def test_wall_features_property(coords, lo, radius, clip, dtype):
    x = np.array(coords).reshape(3, 2).astype(dtype)
    bounds = np.array([[lo, lo + 1.5], [lo - 1, lo + 3]])
    got = gns.wall_features(x, bounds, radius, clip=clip)
    np.testing.assert_allclose(got, walls_oracle(x, bounds, radius, clip), **close(dtype))


@pytest.mark.parametrize(
    ("bounds", "pattern"),
    [
        (np.array([[0.0, 1.0]]), "bounds"),  # one axis for 2-D positions
        (np.array([[0.0], [1.0]]), "bounds"),
        (np.zeros((2, 3)), "bounds"),
        (np.array([[0.0, 1.0]] * 3), "bounds"),
        (np.array([[0.0, 1.0], [1.0, 1.0]]), "lower < upper"),  # lo == hi
        (np.array([[0.0, 1.0], [2.0, 1.0]]), "lower < upper"),  # lo > hi
        (np.array([[0.0, 1.0], [np.nan, 1.0]]), "bounds"),
        (np.array([[0.0, np.inf], [0.0, 1.0]]), "bounds"),
    ],
)
def test_wall_features_rejects_bad_bounds(bounds, pattern):
    x = np.random.default_rng(0).random((5, 2))
    with pytest.raises(ValueError, match=pattern):
        gns.wall_features(x, bounds, 0.1)


def test_wall_features_rejects_flat_bounds_with_value_error():
    x = np.random.default_rng(0).random((5, 2))
    with pytest.raises(ValueError, match="bounds"):
        gns.wall_features(x, np.array([0.0, 1.0, 0.0, 1.0]), 0.1)


@pytest.mark.parametrize("bad", [np.nan, np.inf])
@pytest.mark.parametrize("dtype", DTYPES)
def test_wall_features_rejects_bad_positions_and_radius(bad, dtype):
    bounds = np.array([[0.0, 1.0], [0.0, 1.0]])
    x = np.random.default_rng(0).random((5, 2)).astype(dtype)
    x[3, 1] = bad
    with pytest.raises(ValueError, match=r"positions\[3, 1\]"):
        gns.wall_features(x, bounds, 0.1)
    good = np.zeros((5, 2), dtype)
    for radius in (0.0, -1.0, np.nan, np.inf):
        with pytest.raises(ValueError, match="radius"):
            gns.wall_features(good, bounds, radius)
    for clip in (0.0, -1.0, np.nan):
        with pytest.raises(ValueError, match="clip"):
            gns.wall_features(good, bounds, 0.1, clip=clip)
    with pytest.raises(ValueError, match="2 or 3 columns"):
        gns.wall_features(np.zeros((5, 4)), np.array([[0.0, 1.0]] * 4), 0.1)
    with pytest.raises(ValueError, match="2-D"):
        gns.wall_features(np.zeros(5), bounds, 0.1)


# ----------------------------------------------------------------------------- geometry oracles


def closest_on_segment(p, a, b):
    """Nearest points on segment ab to each row of p (N, D)."""
    ab = b - a
    t = np.clip(((p - a) @ ab) / (ab @ ab), 0.0, 1.0)
    return a + t[:, None] * ab


def closest_on_polyline(p, vertices, closed):
    segments = list(zip(vertices[:-1], vertices[1:], strict=True))
    if closed:
        segments.append((vertices[-1], vertices[0]))
    candidates = np.stack([closest_on_segment(p, a, b) for a, b in segments])  # (S, N, D)
    dist = np.linalg.norm(candidates - p, axis=2)
    return candidates[np.argmin(dist, axis=0), np.arange(len(p))]


def closest_on_triangle(p, a, b, c):
    """Ericson's closest point on triangle abc to the point p (Real-Time Collision Detection)."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = ab @ ap, ac @ ap
    if d1 <= 0 and d2 <= 0:
        return a
    bp = p - b
    d3, d4 = ab @ bp, ac @ bp
    if d3 >= 0 and d4 <= d3:
        return b
    vc = d1 * d4 - d3 * d2
    if vc <= 0 and d1 >= 0 and d3 <= 0:
        return a + d1 / (d1 - d3) * ab
    cp = p - c
    d5, d6 = ab @ cp, ac @ cp
    if d6 >= 0 and d5 <= d6:
        return c
    vb = d5 * d2 - d1 * d6
    if vb <= 0 and d2 >= 0 and d6 <= 0:
        return a + d2 / (d2 - d6) * ac
    va = d3 * d6 - d5 * d4
    if va <= 0 and d4 - d3 >= 0 and d5 - d6 >= 0:
        return b + (d4 - d3) / ((d4 - d3) + (d5 - d6)) * (c - b)
    denom = 1.0 / (va + vb + vc)
    return a + ab * (vb * denom) + ac * (vc * denom)


def closest_on_mesh(p, vertices, triangles):
    out = np.empty_like(p)
    for i, q in enumerate(p):
        cands = [closest_on_triangle(q, *vertices[t]) for t in triangles]
        out[i] = min(cands, key=lambda c: np.linalg.norm(c - q))
    return out


def closest_on_box(p, center, half):
    """Nearest point of the box's boundary: clamp outside; nearest face inside."""
    lo, hi = center - half, center + half
    q = np.clip(p, lo, hi)
    inside = np.all((p > lo) & (p < hi), axis=1)
    gaps = np.concatenate([p - lo, hi - p], axis=1)  # (N, 2D)
    k = np.argmin(gaps, axis=1)
    dim = p.shape[1]
    for i in np.flatnonzero(inside):
        axis = k[i] % dim
        q[i, axis] = lo[axis] if k[i] < dim else hi[axis]
    return q


def features_oracle(p, nearest, radius):
    v = (nearest - p) / radius
    far = np.linalg.norm(nearest - p, axis=1) > radius
    v[far] = 0.0
    return v


def unambiguous(p, nearest, radius, margin=1e-9):
    """Rows not within rounding of the radius (where in/out could legitimately flip)."""
    return np.abs(np.linalg.norm(nearest - p, axis=1) - radius) > margin


def check_features(got, p, nearest, radius, dtype):
    expected = features_oracle(p.astype(np.float64), nearest, radius)
    keep = unambiguous(p.astype(np.float64), nearest, radius)
    assert keep.mean() > 0.99
    np.testing.assert_allclose(got[keep], expected[keep], **close(dtype))
    # Both regimes occur, so the test sees the cut-off.
    assert (np.abs(expected[keep]).sum(axis=1) == 0).any()
    assert (np.abs(expected[keep]).sum(axis=1) > 0).any()


# ----------------------------------------------------------------------------- obstacles


@pytest.mark.parametrize("dtype", DTYPES)
def test_ramp_segment(dtype):
    vertices = np.array([[0.0, 0.0], [1.0, 1.0]])
    ramp = gns.Obstacle.polyline(vertices)
    assert ramp.dim == 2
    rng = np.random.default_rng(1)
    p = (rng.random((2000, 2)) * 2 - 0.5).astype(dtype)
    got = gns.obstacle_features(p, [ramp], 0.3)
    assert got.dtype == dtype and got.shape == (2000, 2)
    nearest = closest_on_segment(p.astype(np.float64), vertices[0], vertices[1])
    check_features(got, p, nearest, 0.3, dtype)


def test_ramp_hand_values():
    ramp = gns.Obstacle.polyline(np.array([[0.0, 0.0], [1.0, 1.0]]))
    p = np.array([[1.0, 0.0], [-0.25, 0.0], [2.0, 1.0], [0.5, 0.5], [0.0, 3.0]])
    got = gns.obstacle_features(p, [ramp], 1.0)
    expected = [[-0.5, 0.5], [0.25, 0.0], [-1.0, 0.0], [0.0, 0.0], [0.0, 0.0]]
    np.testing.assert_allclose(got, expected, atol=1e-15)


@pytest.mark.parametrize("closed", [True, False])
def test_square_polyline(closed):
    vertices = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    square = gns.Obstacle.polyline(vertices, closed=closed)
    rng = np.random.default_rng(2)
    p = rng.random((3000, 2)) * 1.6 - 0.3
    got = gns.obstacle_features(p, [square], 0.2)
    nearest = closest_on_polyline(p, vertices, closed)
    check_features(got, p, nearest, 0.2, np.float64)
    # Near the missing side (x = 0) only the closed square is seen.
    probe = np.array([[0.1, 0.5]])
    seen = gns.obstacle_features(probe, [square], 0.2)
    np.testing.assert_allclose(seen, [[-0.5, 0.0]] if closed else [[0.0, 0.0]], atol=1e-15)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("dim", [2, 3])
def test_cuboid_outside_and_inside(dim, dtype):
    center = np.array([0.5, -0.25, 0.25])[:dim]
    half = np.array([0.5, 0.25, 0.375])[:dim]
    box = gns.Obstacle.cuboid(list(center), list(half))
    assert box.dim == dim
    rng = np.random.default_rng(dim)
    p = (center + (rng.random((3000, dim)) * 2 - 1) * (half + 0.4)).astype(dtype)
    got = gns.obstacle_features(p, [box], 0.2)
    assert got.dtype == dtype and got.shape == (3000, dim)
    nearest = closest_on_box(p.astype(np.float64), center, half)
    inside = np.all(np.abs(p - center) < half, axis=1)
    assert inside.any() and (~inside).any()
    check_features(got, p, nearest, 0.2, dtype)
    # Deep inside (farther than the radius from every face): no feature.
    deep = np.array([center]).astype(dtype)
    np.testing.assert_array_equal(gns.obstacle_features(deep, [box], 0.2), np.zeros((1, dim)))


@pytest.mark.parametrize("dim", [2, 3])
def test_cuboid_hand_values(dim):
    box = gns.Obstacle.cuboid([0.0] * dim, [1.0] * dim)
    p = np.zeros((3, dim))
    p[0, 0] = 1.5  # outside, 0.5 from the +x face
    p[1, 0] = 0.75  # inside, 0.25 from the +x face: points out through it
    p[2, 0] = 2.0  # exactly at the radius (inclusive, like the radius graph)
    got = gns.obstacle_features(p, [box], 1.0)
    expected = np.zeros((3, dim))
    expected[0, 0], expected[1, 0], expected[2, 0] = -0.5, 0.25, -1.0
    np.testing.assert_array_equal(got, expected)
    p[2, 0] = np.nextafter(2.0, 3.0)
    assert not gns.obstacle_features(p, [box], 1.0)[2].any()


UNIT_SQUARE = (
    np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=np.float64),
    np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint32),
)
TETRAHEDRON = (
    np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float64),
    np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], dtype=np.uint32),
)


@pytest.mark.parametrize("dtype", DTYPES)
def test_trimesh_unit_square(dtype):
    vertices, triangles = UNIT_SQUARE
    mesh = gns.Obstacle.trimesh(vertices, triangles)
    assert mesh.dim == 3
    rng = np.random.default_rng(4)
    p = (rng.random((2000, 3)) * [1.6, 1.6, 0.8] - [0.3, 0.3, 0.4]).astype(dtype)
    got = gns.obstacle_features(p, [mesh], 0.25)
    p64 = p.astype(np.float64)
    # Independent of the triangle oracle: the square is [0, 1]^2 x {0}.
    nearest = np.column_stack([np.clip(p64[:, 0], 0, 1), np.clip(p64[:, 1], 0, 1), 0 * p64[:, 2]])
    check_features(got, p, nearest, 0.25, dtype)
    np.testing.assert_allclose(nearest, closest_on_mesh(p64, vertices, triangles), atol=1e-12)


def test_trimesh_tetrahedron():
    vertices, triangles = TETRAHEDRON
    mesh = gns.Obstacle.trimesh(vertices, triangles)
    rng = np.random.default_rng(5)
    p = rng.random((1500, 3)) * 1.6 - 0.3
    got = gns.obstacle_features(p, [mesh], 0.3)
    nearest = closest_on_mesh(p, vertices, triangles)
    inside = (p > 0).all(axis=1) & (p.sum(axis=1) < 1)
    assert inside.sum() > 50
    check_features(got, p, nearest, 0.3, np.float64)
    # Hand values: below the base face, beyond the slanted face, inside near a face.
    probe = np.array([[0.25, 0.25, -0.1], [0.5, 0.5, 0.5], [0.1, 0.3, 0.3]])
    want = np.array([[0.0, 0.0, 0.1], [-1 / 6, -1 / 6, -1 / 6], [-0.1, 0.0, 0.0]]) / 0.3
    np.testing.assert_allclose(gns.obstacle_features(probe, [mesh], 0.3), want, atol=1e-12)


def test_several_obstacles_fill_their_own_columns():
    ramp = gns.Obstacle.polyline(np.array([[0.0, 0.0], [1.0, 1.0]]))
    box = gns.Obstacle.cuboid([2.0, 0.0], [0.5, 0.5])
    square = gns.Obstacle.polyline(np.array([[0.0, 2.0], [1.0, 2.0], [1.0, 3.0]]), closed=True)
    rng = np.random.default_rng(6)
    p = rng.random((500, 2)) * 3 - 0.25
    got = gns.obstacle_features(p, [ramp, box, square], 0.4)
    assert got.shape == (500, 6)
    for k, o in enumerate([ramp, box, square]):
        np.testing.assert_array_equal(got[:, 2 * k : 2 * k + 2], gns.obstacle_features(p, [o], 0.4))
    assert gns.obstacle_features(np.zeros((0, 2)), [ramp], 0.4).shape == (0, 2)


@pytest.mark.parametrize("dtype", DTYPES)
def test_no_obstacles_gives_n_by_zero(dtype):
    got = gns.obstacle_features(np.zeros((500, 2), dtype), [], 0.4)
    assert got.shape == (500, 0) and got.dtype == dtype


@pytest.mark.parametrize("dtype", DTYPES)
def test_obstacle_features_large_input_matches_small(dtype):
    """Above the serial threshold the rows are split across threads: same values."""
    box = gns.Obstacle.cuboid([0.5, 0.5, 0.5], [0.25, 0.25, 0.25])
    rng = np.random.default_rng(7)
    p = rng.random((20000, 3)).astype(dtype)
    whole = gns.obstacle_features(p, [box], 0.2)
    parts = np.concatenate([gns.obstacle_features(c, [box], 0.2) for c in np.split(p, 40)])
    np.testing.assert_array_equal(whole, parts)
    nearest = closest_on_box(p.astype(np.float64), np.full(3, 0.5), np.full(3, 0.25))
    check_features(whole, p, nearest, 0.2, dtype)


# ----------------------------------------------------------------------------- obstacle errors


def test_obstacle_dimension_mismatch():
    ramp = gns.Obstacle.polyline(np.array([[0.0, 0.0], [1.0, 1.0]]))
    cube = gns.Obstacle.cuboid([0.0, 0.0, 0.0], [1.0, 1.0, 1.0])
    mesh = gns.Obstacle.trimesh(*UNIT_SQUARE)
    with pytest.raises(ValueError, match="2D.*3D"):
        gns.obstacle_features(np.zeros((3, 3)), [cube, ramp], 0.1)
    for o in (cube, mesh):
        with pytest.raises(ValueError, match="3D.*2D"):
            gns.obstacle_features(np.zeros((3, 2)), [o], 0.1)


@pytest.mark.parametrize(
    ("make", "pattern"),
    [
        (lambda: gns.Obstacle.polyline(np.zeros((3, 3))), r"\(K, 2\)"),
        (lambda: gns.Obstacle.polyline(np.zeros((1, 2))), "at least 2"),
        (lambda: gns.Obstacle.polyline(np.zeros((0, 2))), "vertices"),
        (lambda: gns.Obstacle.polyline(np.array([[0.0, 0.0], [np.nan, 1.0]])), "vertices"),
        (lambda: gns.Obstacle.polyline(np.array([[0.0, np.inf], [0.0, 1.0]])), "vertices"),
        (lambda: gns.Obstacle.cuboid([0.0, 0.0], [1.0, 1.0, 1.0]), "half_extents"),
        (lambda: gns.Obstacle.cuboid([0.0], [1.0]), "2 or 3"),
        (lambda: gns.Obstacle.cuboid([0.0] * 4, [1.0] * 4), "2 or 3"),
        (lambda: gns.Obstacle.cuboid([0.0, 0.0], [1.0, 0.0]), "half_extents"),
        (lambda: gns.Obstacle.cuboid([0.0, 0.0], [1.0, -1.0]), "half_extents"),
        (lambda: gns.Obstacle.cuboid([0.0, 0.0], [1.0, np.nan]), "half_extents"),
        (lambda: gns.Obstacle.cuboid([np.nan, 0.0], [1.0, 1.0]), "center"),
        (lambda: gns.Obstacle.trimesh(UNIT_SQUARE[0][:, :2], UNIT_SQUARE[1]), r"\(V, 3\)"),
        (lambda: gns.Obstacle.trimesh(UNIT_SQUARE[0], UNIT_SQUARE[1][:, :2]), r"\(T, 3\)"),
        (
            lambda: gns.Obstacle.trimesh(UNIT_SQUARE[0], np.array([[0, 1, 4]], np.uint32)),
            "vertex 4",
        ),
        (
            lambda: gns.Obstacle.trimesh(UNIT_SQUARE[0][:3], UNIT_SQUARE[1]),
            "vertex 3",
        ),
        (lambda: gns.Obstacle.trimesh(UNIT_SQUARE[0], np.zeros((0, 3), np.uint32)), "triangles"),
        (
            lambda: gns.Obstacle.trimesh(np.array([[np.nan, 0, 0]] * 3), UNIT_SQUARE[1][:1]),
            "vertices",
        ),
    ],
)
def test_obstacle_construction_errors(make, pattern):
    with pytest.raises(ValueError, match=pattern):
        make()


@pytest.mark.parametrize(
    "make",
    [
        lambda: gns.Obstacle.trimesh(*TETRAHEDRON[:1], TETRAHEDRON[1].astype(np.int64)),
        lambda: gns.Obstacle.trimesh(TETRAHEDRON[0].astype(np.float32), TETRAHEDRON[1]),
        lambda: gns.Obstacle.polyline(np.array([[0, 0], [1, 1]])),
        lambda: gns.Obstacle.polyline(np.zeros(4)),
    ],
)
def test_obstacle_other_dtypes_convert_or_raise_value_error(make):
    try:
        obstacle = make()
    except ValueError:
        return
    # Accepted: then it must be the same shape as the float64 / uint32 original.
    ref = (
        gns.Obstacle.trimesh(*TETRAHEDRON)
        if obstacle.dim == 3
        else gns.Obstacle.polyline(np.array([[0.0, 0.0], [1.0, 1.0]]))
    )
    rng = np.random.default_rng(8)
    p = rng.random((200, obstacle.dim)) * 2 - 0.5
    np.testing.assert_array_equal(
        gns.obstacle_features(p, [obstacle], 0.3), gns.obstacle_features(p, [ref], 0.3)
    )


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_obstacle_features_rejects_bad_positions_and_radius(bad):
    ramp = gns.Obstacle.polyline(np.array([[0.0, 0.0], [1.0, 1.0]]))
    p = np.zeros((4, 2))
    p[2, 0] = bad
    with pytest.raises(ValueError, match=r"positions\[2, 0\]"):
        gns.obstacle_features(p, [ramp], 0.1)
    for radius in (0.0, -0.1, np.nan, np.inf):
        with pytest.raises(ValueError, match="radius"):
            gns.obstacle_features(np.zeros((4, 2)), [ramp], radius)
    with pytest.raises(ValueError, match="2 or 3 columns"):
        gns.obstacle_features(np.zeros((4, 4)), [], 0.1)


def test_cuboid_corners_outside():
    """Outside a corner the nearest point is the corner itself, for every corner."""
    box = gns.Obstacle.cuboid([0.0, 0.0, 0.0], [1.0, 2.0, 0.5])
    for signs in itertools.product([-1.0, 1.0], repeat=3):
        corner = np.array(signs) * [1.0, 2.0, 0.5]
        p = (corner + np.array(signs) * 0.125)[None, :]
        got = gns.obstacle_features(p, [box], 0.5)
        np.testing.assert_allclose(got, (corner - p) / 0.5, atol=1e-15)
