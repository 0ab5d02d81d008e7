"""Mirror augmentation (gns.augment) against hand-computed reflections and the wall features."""

from __future__ import annotations

import gns
import numpy as np
import pytest
from gns.augment import check_mirror_axes, mirror_batch
from gns.config import TrainConfig
from gns.data.windows import Batch


class Draws:
    """A stand-in generator whose random() returns the given values."""

    def __init__(self, values):
        self.values = np.asarray(values, dtype=float)

    def random(self, shape):
        assert shape == self.values.shape
        return self.values


def batch(seed: int = 0) -> Batch:
    rng = np.random.default_rng(seed)
    n_node = np.array([3, 4])
    return Batch(
        positions=rng.uniform(0.1, 0.9, (6, 7, 2)).astype(np.float32),
        particle_type=np.array([5, 5, 5, 6, 6, 6, 6]),
        n_node=n_node,
        step_context=np.array([[0.3], [0.7]], dtype=np.float32),
        material_property=None,
        trajectory=np.array([0, 1]),
        start=np.array([2, 5]),
    )


BOUNDS = ((0.1, 0.9), (0.0, 2.0))


def test_mirroring_reflects_the_chosen_graphs_about_the_box_centre():
    b = batch()
    # Graph 0 mirrored along axis 0 only, graph 1 along axis 1 only (draws < 0.5 flip).
    out = mirror_batch(b, (0, 1), BOUNDS, Draws([[0.1, 0.9], [0.6, 0.2]]))
    want = b.positions.copy()
    want[:, :3, 0] = 1.0 - b.positions[:, :3, 0]
    want[:, 3:, 1] = 2.0 - b.positions[:, 3:, 1]
    np.testing.assert_allclose(out.positions, want, rtol=0, atol=1e-6)
    assert out.positions.dtype == np.float32
    # Everything else is untouched, and so is the input batch.
    assert out.step_context is b.step_context and out.n_node is b.n_node
    assert not np.shares_memory(out.positions, b.positions)


def test_mirrored_velocities_flip_and_walls_swap_sides():
    b = batch(1)
    out = mirror_batch(b, (0,), BOUNDS, Draws([[0.0], [0.0]]))
    v, w = np.diff(b.positions, axis=0), np.diff(out.positions, axis=0)
    np.testing.assert_allclose(w[..., 0], -v[..., 0], atol=1e-6)
    np.testing.assert_allclose(w[..., 1], v[..., 1], atol=0)
    # The distance to the lower x wall becomes the distance to the upper one (and back).
    radius = 0.5
    before = gns.wall_features(b.positions[-1].astype(np.float64), BOUNDS, radius)
    after = gns.wall_features(out.positions[-1].astype(np.float64), BOUNDS, radius)
    np.testing.assert_allclose(after[:, 0], before[:, 2], atol=1e-6)
    np.testing.assert_allclose(after[:, 2], before[:, 0], atol=1e-6)
    np.testing.assert_allclose(after[:, [1, 3]], before[:, [1, 3]], atol=0)
    # Twice is the identity; without bounds the plane through 0 is used.
    again = mirror_batch(out, (0,), BOUNDS, Draws([[0.0], [0.0]]))
    np.testing.assert_allclose(again.positions, b.positions, atol=1e-6)
    free = mirror_batch(b, (1,), None, Draws([[0.0], [1.0]]))
    np.testing.assert_array_equal(free.positions[:, :3, 1], -b.positions[:, :3, 1])
    np.testing.assert_array_equal(free.positions[:, 3:], b.positions[:, 3:])


def test_no_flip_returns_the_batch_itself():
    b = batch()
    assert mirror_batch(b, (0,), BOUNDS, Draws([[0.7], [0.5]])) is b


def test_axes_that_are_not_symmetric_are_refused():
    # sand2d-like statistics: gravity along y, nothing steady along x.
    mean, std = (1e-6, -1.5e-4), (7.8e-5, 1.6e-4)
    check_mirror_axes((0,), 2, mean, std)
    check_mirror_axes((), 2, mean, std)
    check_mirror_axes((0, 1), 2, None, None)  # no statistics: only the axis range is checked
    with pytest.raises(ValueError, match="mirror_axes contains 1.*gravity"):
        check_mirror_axes((1,), 2, (1e-6, -2e-4), std)
    with pytest.raises(ValueError, match="contains 2; expected axes in 0..1"):
        check_mirror_axes((2,), 2, mean, std)
    with pytest.raises(ValueError, match="distinct axes >= 0"):
        TrainConfig(mirror_axes=(0, 0))
    with pytest.raises(ValueError, match="distinct axes >= 0"):
        TrainConfig(mirror_axes=(-1,))
