"""gns.euler_step: semi-implicit Euler, v' = v + dt a, x' = x + dt v'."""

from __future__ import annotations

import gns
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

DTYPES = (np.float32, np.float64)


def euler_oracle(x, v, a, dt):
    """The update in float64, rounded to the input dtype (the new velocity moves the particle)."""
    dtype = x.dtype
    v_new = (v.astype(np.float64) + dt * a.astype(np.float64)).astype(dtype)
    x_new = (x.astype(np.float64) + dt * v_new.astype(np.float64)).astype(dtype)
    return x_new, v_new


def close(dtype):
    return {"rtol": 1e-15, "atol": 0} if dtype == np.float64 else {"rtol": 2e-7, "atol": 1e-30}


@pytest.mark.parametrize("dt", [1.0, 0.5, 1e-3, 2.5e-3])
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("dim", [2, 3])
def test_matches_formula(dim, dtype, dt):
    rng = np.random.default_rng([dim, int(dt * 1e4)])
    n = 5000
    x, v, a = (rng.normal(size=(n, dim)).astype(dtype) for _ in range(3))
    got_x, got_v = gns.euler_step(x, v, a, dt)
    assert got_x.dtype == dtype and got_v.dtype == dtype
    assert got_x.shape == (n, dim) and got_v.shape == (n, dim)
    want_x, want_v = euler_oracle(x, v, a, dt)
    np.testing.assert_allclose(got_v, want_v, **close(dtype))
    np.testing.assert_allclose(got_x, want_x, **close(dtype))
    # Semi-implicit, not explicit: the position moves with the new velocity.
    explicit_x = x.astype(np.float64) + dt * v
    assert not np.allclose(got_x, explicit_x, rtol=1e-3, atol=0)


def test_default_dt_is_one():
    x = np.array([[1.0, 2.0]])
    v = np.array([[0.5, -1.0]])
    a = np.array([[0.25, 0.125]])
    new_x, new_v = gns.euler_step(x, v, a)
    np.testing.assert_array_equal(new_v, [[0.75, -0.875]])
    np.testing.assert_array_equal(new_x, [[1.75, 1.125]])


@pytest.mark.parametrize("dtype", DTYPES)
def test_inputs_are_not_modified(dtype):
    rng = np.random.default_rng(1)
    x, v, a = (rng.normal(size=(100, 3)).astype(dtype) for _ in range(3))
    copies = [c.copy() for c in (x, v, a)]
    gns.euler_step(x, v, a, 0.1)
    for before, after in zip(copies, (x, v, a), strict=True):
        np.testing.assert_array_equal(before, after)


@pytest.mark.parametrize("dtype", DTYPES)
def test_gravity_matches_closed_form(dtype):
    """Constant acceleration from rest-ish: x_n = x_0 + n v_0 dt + dt^2 a n (n + 1) / 2.

    Dyadic values keep every intermediate exact in both precisions, so the comparison is exact.
    """
    dt = 1.0 / 64
    x0 = np.array([[0.5, 100.0], [0.25, 50.0], [-3.0, 0.0]], dtype=dtype)
    v0 = np.array([[0.25, 0.0], [-1.0, 2.0], [0.0, 0.0]], dtype=dtype)
    a = np.tile(np.array([0.0, -8.0], dtype=dtype), (3, 1))
    x, v = x0, v0
    for n in range(1, 1001):
        x, v = gns.euler_step(x, v, a, dt)
        if n % 250 == 0:
            closed_x = x0 + n * v0 * dt + dt * dt * a * n * (n + 1) / 2
            closed_v = v0 + n * dt * a
            np.testing.assert_array_equal(v, closed_v.astype(dtype))
            np.testing.assert_array_equal(x, closed_x.astype(dtype))
    assert x.dtype == dtype


def test_gravity_generic_values_stay_close_to_closed_form():
    dt = 2.5e-3
    rng = np.random.default_rng(2)
    x0 = rng.random((50, 2))
    v0 = rng.normal(size=(50, 2))
    a = np.tile([0.0, -9.81], (50, 1))
    x, v = x0, v0
    steps = 400
    for _ in range(steps):
        x, v = gns.euler_step(x, v, a, dt)
    closed = x0 + steps * v0 * dt + dt * dt * a * steps * (steps + 1) / 2
    np.testing.assert_allclose(x, closed, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("dim", [2, 3])
def test_empty_and_integer_positions(dim):
    z = np.zeros((0, dim))
    new_x, new_v = gns.euler_step(z, z, z, 0.1)
    assert new_x.shape == (0, dim) and new_v.shape == (0, dim)
    x = np.arange(2 * dim, dtype=np.int64).reshape(2, dim)
    ones = np.ones((2, dim))
    new_x, new_v = gns.euler_step(x, ones, ones, 0.5)
    np.testing.assert_array_equal(new_v, 1.5 * ones)
    np.testing.assert_array_equal(new_x, x + 0.75)


@settings(max_examples=100, deadline=None)
@given(
    st.lists(st.floats(-1e6, 1e6), min_size=9, max_size=9),
    st.floats(1e-6, 10.0),
    st.sampled_from(DTYPES),
)
def test_property_matches_formula(values, dt, dtype):
    x, v, a = np.array(values).reshape(3, 1, 3).astype(dtype)
    got_x, got_v = gns.euler_step(x, v, a, dt)
    want_x, want_v = euler_oracle(x, v, a, dt)
    np.testing.assert_allclose(got_v, want_v, **close(dtype))
    np.testing.assert_allclose(got_x, want_x, **close(dtype))


# ----------------------------------------------------------------------------- errors


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("which", ["position", "velocity", "acceleration"])
@pytest.mark.parametrize("dtype", DTYPES)
def test_rejects_non_finite_inputs(dtype, which, bad):
    arrays = {k: np.zeros((10, 3), dtype) for k in ("position", "velocity", "acceleration")}
    arrays[which][4, 2] = bad
    with pytest.raises(ValueError, match=rf"{which}\[4, 2\]"):
        gns.euler_step(arrays["position"], arrays["velocity"], arrays["acceleration"], 0.1)


@pytest.mark.parametrize(
    ("shapes", "pattern"),
    [
        (((10, 3), (10, 2), (10, 3)), "velocity"),
        (((10, 3), (10, 3), (9, 3)), "acceleration"),
        (((10, 3), (30,), (10, 3)), "velocity"),
        (((30,), (30,), (30,)), "position"),
    ],
)
def test_rejects_mismatched_shapes(shapes, pattern):
    x, v, a = (np.zeros(s) for s in shapes)
    with pytest.raises(ValueError, match=pattern):
        gns.euler_step(x, v, a, 0.1)


@pytest.mark.parametrize("bad", [(3, 10), (15, 2)])
@pytest.mark.parametrize("which", ["velocity", "acceleration"])
def test_rejects_same_size_different_shape(which, bad):
    arrays = {k: np.zeros((10, 3)) for k in ("position", "velocity", "acceleration")}
    arrays[which] = np.zeros(bad)
    with pytest.raises(ValueError, match=which):
        gns.euler_step(arrays["position"], arrays["velocity"], arrays["acceleration"], 0.1)


def test_rejects_mixed_dtypes():
    x = np.zeros((4, 2), np.float32)
    with pytest.raises(ValueError, match="velocity.*dtype"):
        gns.euler_step(x, np.zeros((4, 2)), np.zeros((4, 2), np.float32), 0.1)
    with pytest.raises(ValueError, match="acceleration.*dtype"):
        gns.euler_step(x, x, np.zeros((4, 2)), 0.1)


@pytest.mark.parametrize("dt", [0.0, -0.1, np.nan, np.inf])
def test_rejects_bad_dt(dt):
    z = np.zeros((4, 2))
    with pytest.raises(ValueError, match="dt"):
        gns.euler_step(z, z, z, dt)


@pytest.mark.parametrize(
    ("dtype", "huge", "dt"),
    [
        (np.float64, 1e308, 2.0),  # dt * a overflows
        (np.float64, 1e308, 1.0),  # v + dt * a overflows (v is also huge)
        (np.float32, 1e38, 4.0),  # fine in float64, overflows when rounded to float32
        (np.float32, 1e38, 1.0),
    ],
)
def test_rejects_overflow(dtype, huge, dt):
    x = np.zeros((3, 2), dtype)
    v = np.zeros((3, 2), dtype)
    a = np.zeros((3, 2), dtype)
    a[1, 0] = huge
    if dt == 1.0:
        v[1, 0] = huge * 3 if dtype == np.float32 else huge
        v = v.astype(dtype)
    assert np.all(np.isfinite(v)) and np.all(np.isfinite(a))
    with pytest.raises(ValueError, match="overflow"):
        gns.euler_step(x, v, a, dt)


def test_position_overflow_is_rejected():
    """The velocity stays finite but the position does not."""
    x = np.array([[1.7e308, 0.0]])
    v = np.array([[1e308, 0.0]])
    a = np.zeros((1, 2))
    with pytest.raises(ValueError, match="position"):
        gns.euler_step(x, v, a, 1.0)
