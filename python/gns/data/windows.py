"""Training windows, a streaming shuffle buffer, and batches packed by a particle budget.

A window is input_sequence_length + 1 consecutive frames (default 6 + 1: six input positions,
hence five velocities, and the target). Arrays stay time-major like `Trajectory.positions`;
`positions.transpose(1, 0, 2)` gives the paper's per-particle (N, T, D) layout.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import TypeVar

import numpy as np

from gns.data.errors import DatasetError
from gns.data.trajectory import Trajectory

INPUT_SEQUENCE_LENGTH = 6

T = TypeVar("T")


@dataclass(frozen=True, eq=False)
class Window:
    """One training example.

    positions: (input_sequence_length + 1, N, D) float32; the last frame is the target.
    particle_type: (N,) int64. step_context: (C,) float32, taken at the last input frame.
    material_property: () or (N,) float32. trajectory / start: where the window came from.
    """

    positions: np.ndarray
    particle_type: np.ndarray
    step_context: np.ndarray | None
    material_property: np.ndarray | None
    trajectory: int
    start: int

    @property
    def input_positions(self) -> np.ndarray:
        """(input_sequence_length, N, D)."""
        return self.positions[:-1]

    @property
    def target_position(self) -> np.ndarray:
        """(N, D)."""
        return self.positions[-1]

    @property
    def n_node(self) -> int:
        return int(self.positions.shape[1])


def num_windows(num_frames: int, input_sequence_length: int = INPUT_SEQUENCE_LENGTH) -> int:
    """How many windows a trajectory of `num_frames` frames yields."""
    return max(0, num_frames - input_sequence_length)


def trajectory_windows(
    trajectory: Trajectory,
    input_sequence_length: int = INPUT_SEQUENCE_LENGTH,
    starts: Iterable[int] | None = None,
) -> Iterator[Window]:
    """Windows of one trajectory, in order of `starts` (default: every start, ascending).

    Each window owns a copy of its frames, so a shuffle buffer full of windows does not keep
    whole trajectories alive.
    """
    if input_sequence_length < 1:
        raise ValueError(f"input_sequence_length must be at least 1, got {input_sequence_length}")
    count = num_windows(trajectory.num_frames, input_sequence_length)
    width = input_sequence_length + 1
    for start in range(count) if starts is None else starts:
        if not 0 <= start < count:
            raise IndexError(f"window start {start} out of range ({count} windows)")
        last_input = start + input_sequence_length - 1
        context = trajectory.step_context
        yield Window(
            positions=trajectory.positions[start : start + width].copy(),
            particle_type=trajectory.particle_type,
            step_context=None if context is None else context[last_input].copy(),
            material_property=trajectory.material_property,
            trajectory=trajectory.key,
            start=start,
        )


def shuffle_buffer(items: Iterable[T], buffer_size: int, rng: np.random.Generator) -> Iterator[T]:
    """tf.data-style shuffle: hold `buffer_size` items, emit a random one as each new one comes.

    Memory is bounded by the buffer; with buffer_size >= the number of items it is a full
    uniform shuffle.
    """
    if buffer_size < 1:
        raise ValueError(f"buffer_size must be at least 1, got {buffer_size}")
    buffer: list[T] = []
    for item in items:
        if len(buffer) < buffer_size:
            buffer.append(item)
            continue
        i = int(rng.integers(buffer_size))
        out, buffer[i] = buffer[i], item
        yield out
    order = rng.permutation(len(buffer))
    for i in order:
        yield buffer[i]


def training_windows(
    trajectories: Sequence[Trajectory],
    input_sequence_length: int = INPUT_SEQUENCE_LENGTH,
    *,
    shuffle_buffer_size: int = 10_000,
    seed: int = 0,
    epochs: int | None = 1,
) -> Iterator[Window]:
    """Shuffled windows of a dataset, streaming: one trajectory is read at a time.

    Each epoch visits trajectories in a fresh random order and feeds their windows (in random
    start order) through the shuffle buffer. epochs=None repeats forever. Deterministic in `seed`.
    """
    rng = np.random.default_rng(seed)

    def stream() -> Iterator[Window]:
        epoch = 0
        while epochs is None or epoch < epochs:
            for index in rng.permutation(len(trajectories)):
                trajectory = trajectories[int(index)]
                count = num_windows(trajectory.num_frames, input_sequence_length)
                starts = rng.permutation(count).tolist()
                yield from trajectory_windows(trajectory, input_sequence_length, starts)
            epoch += 1

    return shuffle_buffer(stream(), shuffle_buffer_size, rng)


@dataclass(frozen=True, eq=False)
class Batch:
    """Several windows as one disjoint graph.

    positions: (input_sequence_length + 1, sum(n_node), D) float32.
    particle_type: (sum(n_node),) int64. n_node: (B,) int64, particles per graph.
    step_context: (B, C) float32 or None.
    material_property: (sum(n_node),) float32 (scalars broadcast per particle) or None.
    trajectory, start: (B,) int64 provenance of each graph.
    """

    positions: np.ndarray
    particle_type: np.ndarray
    n_node: np.ndarray
    step_context: np.ndarray | None
    material_property: np.ndarray | None
    trajectory: np.ndarray
    start: np.ndarray

    @property
    def num_graphs(self) -> int:
        return int(self.n_node.shape[0])


def collate(windows: Sequence[Window]) -> Batch:
    """Concatenate windows along the particle axis."""
    if not windows:
        raise ValueError("cannot collate zero windows")
    has_context = {w.step_context is not None for w in windows}
    has_material = {w.material_property is not None for w in windows}
    if len(has_context) > 1 or len(has_material) > 1:
        raise ValueError("windows disagree on having step_context / material_property")
    context = None
    if has_context.pop():
        context = np.stack([w.step_context for w in windows if w.step_context is not None])
    material = None
    if has_material.pop():
        material = np.concatenate(
            [
                np.broadcast_to(w.material_property, (w.n_node,))
                for w in windows
                if w.material_property is not None
            ]
        ).astype(np.float32)
    return Batch(
        positions=np.concatenate([w.positions for w in windows], axis=1),
        particle_type=np.concatenate([w.particle_type for w in windows]),
        n_node=np.array([w.n_node for w in windows], dtype=np.int64),
        step_context=context,
        material_property=material,
        trajectory=np.array([w.trajectory for w in windows], dtype=np.int64),
        start=np.array([w.start for w in windows], dtype=np.int64),
    )


def pack_batches(
    windows: Iterable[Window],
    max_particles: int,
    *,
    max_graphs: int | None = None,
) -> Iterator[Batch]:
    """Greedy fixed-budget packing: add windows in order until the next would push the batch
    past `max_particles` (or `max_graphs` graphs), then emit the batch.

    Every window lands in exactly one batch; a window larger than the budget is an error, not
    a silent drop. The last batch may be smaller.
    """
    if max_particles < 1:
        raise ValueError(f"max_particles must be positive, got {max_particles}")
    pending: list[Window] = []
    total = 0
    for window in windows:
        if window.n_node > max_particles:
            raise DatasetError(
                "<batching>",
                f"window (start {window.start}) has {window.n_node} particles, more than the "
                f"particle budget {max_particles}",
                window.trajectory,
            )
        full = max_graphs is not None and len(pending) >= max_graphs
        if pending and (total + window.n_node > max_particles or full):
            yield collate(pending)
            pending, total = [], 0
        pending.append(window)
        total += window.n_node
    if pending:
        yield collate(pending)
