"""Training windows, the shuffle buffer and particle-budget packing."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest
from data_helpers import random_walk
from gns.data import (
    DatasetError,
    Trajectory,
    pack_batches,
    shuffle_buffer,
    training_windows,
    trajectory_windows,
)
from gns.data.windows import WindowSampler
from hypothesis import given, settings
from hypothesis import strategies as st


def test_windows_are_consecutive_frames_with_context_at_last_input():
    trajectory = random_walk(np.random.default_rng(0), 20, 5, context=2)
    windows = list(trajectory_windows(trajectory))
    assert len(windows) == 20 - 6  # starts 0..13, each 6 inputs + 1 target
    for start, window in enumerate(windows):
        assert window.start == start
        assert window.positions.shape == (7, 5, 2)
        np.testing.assert_array_equal(window.positions, trajectory.positions[start : start + 7])
        np.testing.assert_array_equal(window.target_position, trajectory.positions[start + 6])
        np.testing.assert_array_equal(window.step_context, trajectory.step_context[start + 5])
    # Windows own their frames: a shuffle buffer must not pin whole trajectories.
    assert not np.shares_memory(windows[0].positions, trajectory.positions)


def test_short_trajectory_has_no_windows():
    trajectory = random_walk(np.random.default_rng(1), 6, 3)
    assert list(trajectory_windows(trajectory)) == []
    assert len(list(trajectory_windows(trajectory, input_sequence_length=2))) == 4


def test_shuffle_buffer_is_a_deterministic_permutation():
    items = list(range(1000))
    a = list(shuffle_buffer(items, 64, np.random.default_rng(3)))
    b = list(shuffle_buffer(items, 64, np.random.default_rng(3)))
    c = list(shuffle_buffer(items, 64, np.random.default_rng(4)))
    assert sorted(a) == items and a == b and a != c and a != items
    # A buffer of 64 can delay an item arbitrarily but never emit it more than 63 places early.
    assert all(position >= item - 63 for position, item in enumerate(a))


def test_training_windows_cover_every_window_once_per_epoch():
    rng = np.random.default_rng(5)
    trajectories = [random_walk(rng, 12 + i, 3 + i, key=i) for i in range(4)]
    seen = Counter(
        (w.trajectory, w.start)
        for w in training_windows(trajectories, shuffle_buffer_size=10, seed=1, epochs=2)
    )
    expected = {(i, s) for i in range(4) for s in range(12 + i - 6)}
    assert set(seen) == expected and set(seen.values()) == {2}
    first = [(w.trajectory, w.start) for w in training_windows(trajectories, seed=9)]
    again = [(w.trajectory, w.start) for w in training_windows(trajectories, seed=9)]
    assert first == again


@settings(max_examples=40, deadline=None)
@given(
    sizes=st.lists(st.integers(1, 50), min_size=1, max_size=30),
    budget=st.integers(50, 200),
    max_graphs=st.one_of(st.none(), st.integers(1, 5)),
)
def test_packing_respects_the_budget_and_keeps_every_window(sizes, budget, max_graphs):
    rng = np.random.default_rng(0)
    trajectories = [
        Trajectory(rng.uniform(size=(7, n, 2)), np.arange(n) % 4, key=i)
        for i, n in enumerate(sizes)
    ]
    windows = [next(trajectory_windows(t)) for t in trajectories]
    batches = list(pack_batches(windows, budget, max_graphs=max_graphs))
    assert [int(t) for b in batches for t in b.trajectory] == list(range(len(sizes)))
    for batch in batches:
        assert batch.n_node.sum() <= budget
        assert max_graphs is None or batch.num_graphs <= max_graphs
        assert batch.positions.shape == (7, batch.n_node.sum(), 2)
    # Greedy: a batch was closed only because the next window would not fit.
    for this, following in zip(batches, batches[1:], strict=False):
        full = max_graphs is not None and this.num_graphs == max_graphs
        assert full or this.n_node.sum() + following.n_node[0] > budget
    # Concatenation keeps each graph's particles contiguous and in order.
    for batch in batches:
        start = 0
        for n, t in zip(batch.n_node, batch.trajectory, strict=True):
            np.testing.assert_array_equal(
                batch.positions[:, start : start + n], windows[t].positions
            )
            start += n


def test_batch_carries_context_and_broadcast_material():
    rng = np.random.default_rng(6)
    a = random_walk(rng, 8, 3, context=1, material="scalar", key=0)
    b = random_walk(rng, 8, 2, context=1, material="scalar", key=1)
    windows = [next(trajectory_windows(a)), next(trajectory_windows(b))]
    (batch,) = pack_batches(windows, 100)
    assert batch.step_context.shape == (2, 1)
    np.testing.assert_array_equal(batch.n_node, [3, 2])
    np.testing.assert_array_equal(
        batch.material_property, [a.material_property] * 3 + [b.material_property] * 2
    )


def test_window_larger_than_budget_is_an_error():
    trajectory = random_walk(np.random.default_rng(7), 8, 30, key=4)
    with pytest.raises(DatasetError, match="30 particles, more than the particle budget 20"):
        list(pack_batches(trajectory_windows(trajectory), 20))


def _sampler_trajectories():
    rng = np.random.default_rng(4)
    # Lengths 9..13 frames: 3..7 windows each with 6 input frames; 25 windows in all.
    return [random_walk(rng, 9 + k, 4 + k, key=k) for k in range(5)]


def test_window_sampler_visits_every_window_once_per_epoch():
    trajectories = _sampler_trajectories()
    sampler = WindowSampler(trajectories, seed=3, trajectories_in_memory=2)
    seen = []
    for _ in range(25):
        batch = sampler.next_batch(1)
        seen.append((int(batch.trajectory[0]), int(batch.start[0])))
        window = batch.positions
        np.testing.assert_array_equal(
            window, trajectories[seen[-1][0]].positions[seen[-1][1] : seen[-1][1] + 7]
        )
    expected = {(k, s) for k, t in enumerate(trajectories) for s in range(t.num_frames - 6)}
    assert sorted(seen) == sorted(expected)
    # The next epoch is a different order of the same windows.
    again = [sampler.next_batch(1) for _ in range(25)]
    second = [(int(b.trajectory[0]), int(b.start[0])) for b in again]
    assert sorted(second) == sorted(expected) and second != seen


def test_window_sampler_resumes_from_its_state():
    trajectories = _sampler_trajectories()
    a = WindowSampler(trajectories, seed=1, trajectories_in_memory=2)
    for _ in range(7):
        a.next_batch(3, max_particles=20)
    b = WindowSampler(trajectories, seed=1, trajectories_in_memory=2)
    b.load_state_dict(a.state_dict())
    for _ in range(10):
        x, y = a.next_batch(3, max_particles=20), b.next_batch(3, max_particles=20)
        np.testing.assert_array_equal(x.positions, y.positions)
        np.testing.assert_array_equal(x.start, y.start)
        assert x.positions.shape[1] <= 20


def _keys(sampler: WindowSampler, count: int) -> list[tuple[int, int]]:
    batches = [sampler.next_batch(1) for _ in range(count)]
    return [(int(b.trajectory[0]), int(b.start[0])) for b in batches]


def test_window_sampler_ranks_take_disjoint_halves_of_one_order():
    trajectories = _sampler_trajectories()
    order = _keys(WindowSampler(trajectories, seed=2, trajectories_in_memory=5), 24)
    ranks = [WindowSampler(trajectories, seed=2, rank=r, world_size=2) for r in (0, 1)]
    per_rank = [_keys(sampler, 12) for sampler in ranks]
    # All 25 windows are in one chunk: cut to 24 so both ranks move on together.
    assert per_rank[0] == order[0::2] and per_rank[1] == order[1::2]


def test_window_sampler_refuses_a_window_over_the_particle_budget():
    trajectories = _sampler_trajectories()
    with pytest.raises(ValueError, match="particle budget"):
        WindowSampler(trajectories).next_batch(2, max_particles=3)


def test_window_sampler_deals_early_windows_repeatedly():
    trajectories = _sampler_trajectories()
    sampler = WindowSampler(
        trajectories, seed=5, trajectories_in_memory=2, early_steps=2, early_repeat=3
    )
    # Per epoch: the 10 windows starting at 0 or 1 three times each, the other 15 once.
    counts = Counter(_keys(sampler, 45))
    expected = {
        (k, s): 3 if s < 2 else 1
        for k, t in enumerate(trajectories)
        for s in range(t.num_frames - 6)
    }
    assert counts == expected
    # Repeats are shuffled into the epoch, and the state still restores the same sequence.
    resumed = WindowSampler(
        trajectories, seed=5, trajectories_in_memory=2, early_steps=2, early_repeat=3
    )
    resumed.load_state_dict(sampler.state_dict())
    assert _keys(resumed, 20) == _keys(sampler, 20)
    # Off by default: the order is the one without these arguments.
    plain, off = (
        WindowSampler(trajectories, seed=5),
        WindowSampler(trajectories, seed=5, early_steps=4),
    )
    assert _keys(plain, 25) == _keys(off, 25)
    with pytest.raises(ValueError, match="early_repeat >= 1, got 0 and 0"):
        WindowSampler(trajectories, early_repeat=0)
