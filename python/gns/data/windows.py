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
    obstacles: the trajectory's static obstacle polylines, or None.
    """

    positions: np.ndarray
    particle_type: np.ndarray
    step_context: np.ndarray | None
    material_property: np.ndarray | None
    trajectory: int
    start: int
    obstacles: tuple[np.ndarray, ...] | None = None

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


def window_keys(
    trajectories: Sequence[Trajectory], input_sequence_length: int = INPUT_SEQUENCE_LENGTH
) -> list[tuple[int, int]]:
    """(trajectory index, start) of every window of `trajectories`, in order."""
    return [
        (k, start)
        for k, trajectory in enumerate(trajectories)
        for start in range(num_windows(trajectory.num_frames, input_sequence_length))
    ]


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
            obstacles=trajectory.obstacles,
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
    obstacles: each graph's obstacle polylines (B entries), or None when no window has any.
    """

    positions: np.ndarray
    particle_type: np.ndarray
    n_node: np.ndarray
    step_context: np.ndarray | None
    material_property: np.ndarray | None
    trajectory: np.ndarray
    start: np.ndarray
    obstacles: tuple[tuple[np.ndarray, ...], ...] | None = None

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
    obstacles = None
    if any(w.obstacles is not None for w in windows):
        obstacles = tuple(w.obstacles or () for w in windows)
    return Batch(
        positions=np.concatenate([w.positions for w in windows], axis=1),
        particle_type=np.concatenate([w.particle_type for w in windows]),
        n_node=np.array([w.n_node for w in windows], dtype=np.int64),
        step_context=context,
        material_property=material,
        trajectory=np.array([w.trajectory for w in windows], dtype=np.int64),
        start=np.array([w.start for w in windows], dtype=np.int64),
        obstacles=obstacles,
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


class WindowSampler:
    """The training order of windows: deterministic in the seed and resumable at any batch.

    Each epoch visits the trajectories in a fresh random order, `trajectories_in_memory` at a
    time (a chunk); the windows of a chunk are shuffled together and dealt out. The whole state
    is (epoch, chunk, position), so a checkpoint can restart the exact same sequence of batches
    without replaying the data (a streaming shuffle buffer could not be restored).

    early_steps and early_repeat: the windows whose first target is among a trajectory's first
    early_steps predicted frames (start < early_steps) are dealt early_repeat times per epoch,
    the others once; 0 and 1 (the default): every window once.

    With world_size > 1 (distributed training) every rank computes the same order and rank r
    takes the windows at positions r, r + world_size, ...: ranks see disjoint data. A chunk's
    order is cut to a multiple of world_size (at most world_size - 1 windows of each chunk go
    unused in that epoch) so the ranks move to the next chunk together.
    """

    def __init__(
        self,
        trajectories: Sequence[Trajectory],
        input_sequence_length: int = INPUT_SEQUENCE_LENGTH,
        *,
        seed: int = 0,
        trajectories_in_memory: int = 64,
        rank: int = 0,
        world_size: int = 1,
        early_steps: int = 0,
        early_repeat: int = 1,
    ) -> None:
        if len(trajectories) == 0:
            raise ValueError("WindowSampler needs at least one trajectory")
        if trajectories_in_memory < 1:
            raise ValueError(
                f"trajectories_in_memory must be at least 1, got {trajectories_in_memory}"
            )
        if early_steps < 0 or early_repeat < 1:
            raise ValueError(
                f"early_steps must be >= 0 and early_repeat >= 1, got {early_steps} and "
                f"{early_repeat}"
            )
        if not 0 <= rank < world_size:
            raise ValueError(f"rank {rank} is not in [0, world_size={world_size})")
        self.trajectories = trajectories
        self.input_sequence_length = input_sequence_length
        self.seed = seed
        self.trajectories_in_memory = trajectories_in_memory
        self.rank, self.world_size = rank, world_size
        self.early_steps, self.early_repeat = early_steps, early_repeat
        self.epoch = self.chunk = self.position = 0
        self._loaded: tuple[int, int] | None = None
        self._chunk: list[Trajectory] = []
        self._order: np.ndarray = np.empty((0, 2), dtype=np.int64)

    def state_dict(self) -> dict[str, int]:
        return {"epoch": self.epoch, "chunk": self.chunk, "position": self.position}

    def load_state_dict(self, state: dict[str, int]) -> None:
        self.epoch, self.chunk = int(state["epoch"]), int(state["chunk"])
        self.position = int(state["position"])

    def _load(self) -> None:
        """Make the chunk (epoch, chunk) current, moving to the next epoch past the last one."""
        per_chunk = self.trajectories_in_memory
        num_chunks = -(-len(self.trajectories) // per_chunk)
        if self.chunk >= num_chunks:
            self.epoch, self.chunk, self.position = self.epoch + 1, 0, 0
        if self._loaded == (self.epoch, self.chunk):
            return
        # A generator per (seed, epoch, chunk): any chunk can be rebuilt on its own.
        visit = np.random.default_rng([self.seed, self.epoch]).permutation(len(self.trajectories))
        members = visit[self.chunk * per_chunk : (self.chunk + 1) * per_chunk]
        self._chunk = [self.trajectories[int(i)] for i in members]
        pairs = window_keys(self._chunk, self.input_sequence_length)
        order = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        early = order[order[:, 1] < self.early_steps]
        order = np.concatenate([order, *[early] * (self.early_repeat - 1)])
        rng = np.random.default_rng([self.seed, self.epoch, self.chunk])
        order = order[rng.permutation(len(order))]
        self._order = order[: len(order) - len(order) % self.world_size]
        self._loaded = (self.epoch, self.chunk)

    def _peek(self) -> tuple[Trajectory, int]:
        """The next window of this rank as (trajectory, start), without taking it."""
        for _ in range(2 * len(self.trajectories) + 2):
            self._load()
            index = self.position + self.rank
            if index < len(self._order):
                k, start = self._order[index]
                return self._chunk[int(k)], int(start)
            self.chunk, self.position = self.chunk + 1, 0
        raise ValueError(
            f"no trajectory is longer than input_sequence_length={self.input_sequence_length} "
            "frames: there are no training windows"
        )

    def _take(self) -> Window:
        trajectory, start = self._peek()
        # Every rank steps over the whole group of world_size windows.
        self.position += self.world_size
        return next(trajectory_windows(trajectory, self.input_sequence_length, [start]))

    def next_batch(self, batch_size: int, max_particles: int = 0) -> Batch:
        """The next batch: up to batch_size windows and (if max_particles > 0) at most
        max_particles particles. A window larger than the particle budget is an error."""
        windows: list[Window] = []
        total = 0
        while len(windows) < batch_size:
            trajectory, start = self._peek()
            n = trajectory.n_particles
            if max_particles and n > max_particles:
                raise DatasetError(
                    "<batching>",
                    f"window (start {start}) has {n} particles, more than the particle budget "
                    f"{max_particles}",
                    trajectory.key,
                )
            if max_particles and windows and total + n > max_particles:
                break
            windows.append(self._take())
            total += n
        return collate(windows)
