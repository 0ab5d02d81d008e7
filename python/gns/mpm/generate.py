"""`gns generate`: datasets in the DeepMind layout from the reference simulator (gns.mpm).

    generate("sand", "data/sand", n_train=100, n_valid=10, n_test=10, seed=0, workers=2)

Presets (the paper's scenes in 2D and 3D, drawn by gns.mpm.presets) are functions
rng -> (MpmScene, frames); `scale` multiplies a scene's particles by about that factor.

Metadata bounds are where the simulator stops the particles (see `confinement`), the innermost
grid nodes of its walls, not the walls' nominal position MpmScene.bounds. A preset whose scenes
have static obstacles (Segments) writes their shapes under metadata.json's "obstacles", per
split and trajectory key, each segment a 2-vertex polyline (`obstacles`).

Reproducibility: trajectory i of a split is drawn from SeedSequence(seed, spawn_key=(split,
i, draw)), so a dataset depends on the seed and the arguments only, never on the number of
workers or on the order trajectories finish in. A draw whose simulation fails (NaN, a particle
leaving the domain, too many substeps) is reported on stderr and replaced by the next draw; it
is never written.

Resuming: each finished trajectory is saved (atomically) under OUT.partial/ with the arguments
of the run; running the same command again reuses them, a different one is refused. The dataset
folder appears in one rename at the end and OUT.partial/ is then removed.
"""

from __future__ import annotations

import concurrent.futures as cf
import math
import os
import shutil
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gns import mpm
from gns.data.deepmind import write_tfrecord
from gns.data.metadata import DEFAULT_KINEMATIC_TYPES, Metadata, obstacles_json
from gns.data.stats import StatisticsAccumulator
from gns.data.trajectory import Trajectory
from gns.files import atomic_file, atomic_folder, claim_folder
from gns.mpm import MpmScene, step_context
from gns.mpm.presets import (
    PRESET_METADATA,
    PRESETS,
    SPLITS,
    check_scale,
    connectivity_radius,
    preset_scene,
)

__all__ = [
    "PRESETS",
    "SPLITS",
    "Summary",
    "confinement",
    "generate",
    "obstacles",
    "preset_scene",
]

# Draws of one trajectory before giving up: a preset that fails this often is broken, and
# silently skipping it would bias the dataset towards the scenes that happen to be stable.
MAX_DRAWS = 8
# Bump when the meaning of the cached files or of a seed changes, so old partial runs are refused.
CACHE_FORMAT = 2  # 2: continuous draws 1-80 degrees with a held-out band


def confinement(scene: MpmScene) -> tuple[tuple[float, float], ...]:
    """The box the simulator keeps the particles of `scene` in, per axis: from the innermost
    grid node of the lower wall to that of the upper wall. These are the dataset's bounds.

    MpmScene.bounds is not that box. The simulator (rust/mpm/solver.rs, update_grid) enforces
    the walls on the grid nodes outside `bounds`, and a particle takes its velocity from the 3^D
    nodes around it (quadratic B-splines), so one that has crossed `bounds` keeps moving with the
    nodes inside until its weights lie on wall nodes only: half a cell past the innermost wall
    node. Thrown sand went 0.027 past `bounds` at dx = 0.025, almost twice the connectivity
    radius `gns validate` allows. From the innermost wall nodes no particle gets farther out
    than half a cell (0.0125 at RESOLUTION's dx), and particles resting on a wall sit about on
    the bound, which is what the model's wall features (distances to the bounds) should say.
    Wall nodes are found as the simulator finds them: node k at k * (1 / grid), outside
    `bounds`."""
    dx = 1.0 / scene.grid
    nodes = np.arange(scene.grid + 1) * dx
    box = []
    for lo, hi in scene.bounds:
        # The simulator wants `bounds` 2 cells inside the domain: both walls have nodes.
        below, above = np.flatnonzero(nodes < lo)[-1], np.flatnonzero(nodes > hi)[0]
        box.append((float(below / scene.grid), float(above / scene.grid)))
    return tuple(box)


def obstacles(scene: MpmScene) -> list[dict[str, Any]]:
    """The scene's static obstacles as metadata.json's "obstacles" lists them for one
    trajectory: each Segment a 2-vertex polyline [start, end]."""
    return obstacles_json([[s.start, s.end] for s in scene.obstacles])


# ------------------------------------------------------------------------------------ progress


class _Stopped(Exception):
    """Raised inside a running simulation when the run is being abandoned."""


@dataclass
class _Progress:
    """One line on stderr: trajectories done per split, frames per second and time left."""

    totals: dict[str, int]
    frames: int
    enabled: bool
    done: dict[str, int] = field(default_factory=dict)
    frames_done: int = 0  # simulated in this process (not reused), rejected draws included
    redrawn: int = 0
    reused: int = 0
    started: float = field(default_factory=time.perf_counter)
    last_shown: float = field(default_factory=time.perf_counter)
    tty: bool = field(default_factory=lambda: sys.stderr.isatty())

    def line(self) -> str:
        splits = "  ".join(f"{s} {self.done.get(s, 0)}/{n}" for s, n in self.totals.items() if n)
        elapsed = time.perf_counter() - self.started
        rate = self.frames_done / elapsed if elapsed > 0 else 0.0
        # An estimate: trajectories under way count as not started.
        left_frames = (sum(self.totals.values()) - sum(self.done.values())) * self.frames
        left = left_frames / rate if rate > 0 else float("nan")
        eta = time.strftime("%H:%M:%S", time.gmtime(left)) if math.isfinite(left) else "--"
        extra = f"  {self.redrawn} redrawn" if self.redrawn else ""
        return f"{splits}  {rate:.0f} frames/s{extra}  left {eta}"

    def show(self, force: bool = False) -> None:
        now = time.perf_counter()
        if not self.enabled or (not force and now - self.last_shown < (0.5 if self.tty else 30)):
            return
        self.last_shown = now
        sys.stderr.write(("\r" + self.line() + "   ") if self.tty else self.line() + "\n")
        sys.stderr.flush()

    def note(self, message: str) -> None:
        """A message on its own line (always shown: rejected draws must not pass unnoticed)."""
        sys.stderr.write(("\r\x1b[K" if self.tty and self.enabled else "") + message + "\n")
        sys.stderr.flush()
        self.last_shown = 0.0

    def close(self) -> None:
        if self.enabled:
            self.show(force=True)
            if self.tty:
                sys.stderr.write("\n")


# ---------------------------------------------------------------------------------- generation


@dataclass(frozen=True)
class Summary:
    """What a `generate` call did: trajectories per split, draws replaced, trajectories taken
    from an earlier interrupted run, and the wall-clock seconds."""

    counts: dict[str, int]
    redrawn: int
    reused: int
    seconds: float


def _check_count(name: str, value: Any, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def _cache_path(work: Path, split: str, index: int) -> Path:
    return work / split / f"{index:06d}.npz"


def _save(path: Path, result: mpm.MpmResult, draw: int) -> None:
    arrays: dict[str, np.ndarray] = {
        "positions": result.positions,
        "particle_type": result.particle_type,
        "draw": np.array(draw),
    }
    if result.context is not None:
        arrays["context"] = result.context
    # Through a file object: np.savez would append ".npz" to the temporary name.
    with atomic_file(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, allow_pickle=False, **arrays)


def _load(path: Path, index: int) -> tuple[Trajectory, int]:
    with np.load(path) as f:
        positions, types, draw = f["positions"], f["particle_type"], int(f["draw"])
        context = f["context"] if "context" in f.files else None
    return Trajectory(
        positions, types, step_context(context, len(positions)), key=index, source=str(path)
    ), draw


def _simulate_one(
    preset: str,
    seed: int,
    scale: float,
    split: str,
    index: int,
    frames: int | None,
    work: Path,
    stop: threading.Event,
    progress: _Progress,
) -> int:
    """Simulate trajectory (split, index), redrawing failed draws; cache it; return its draw."""

    def per_frame(frame: int) -> None:
        if stop.is_set():
            raise _Stopped
        progress.frames_done += 1  # display only: a lost increment between threads is harmless

    failures = []
    for draw in range(MAX_DRAWS):
        scene, preset_frames, lattice_seed = preset_scene(preset, seed, split, index, draw, scale)
        try:
            result = mpm.simulate(
                scene, frames or preset_frames, seed=lattice_seed, progress=per_frame
            )
        except ValueError as err:
            failures.append(f"draw {draw}: {err}")
            progress.redrawn += 1
            progress.note(f"gns generate: {split} trajectory {index}, draw {draw} rejected: {err}")
            continue
        _save(_cache_path(work, split, index), result, draw)
        return draw
    raise ValueError(
        f"{split} trajectory {index}: all {MAX_DRAWS} draws of preset {preset!r} failed to "
        f"simulate ({'; '.join(failures)}); the preset's settings are unstable"
    )


def _arguments(
    preset: str, counts: dict[str, int], seed: int, frames: int | None, scale: float
) -> dict[str, Any]:
    """What a partial run must share with this one for its trajectories to be reused."""
    arguments = {"format": CACHE_FORMAT, "preset": preset, "seed": seed, "frames": frames}
    # Named only when not 1, so that partial runs from before scale existed stay resumable.
    return {**arguments, **counts, **({"scale": scale} if scale != 1.0 else {})}


def _prepare_work(work: Path, arguments: dict[str, Any]) -> None:
    claim_folder(
        work,
        "arguments.json",
        arguments,
        holds="an interrupted run",
        resume="repeat that run's command to finish it, or delete the folder to start afresh",
        foreign="exists but is not a gns generate work folder; move it away",
    )
    for split in SPLITS:
        (work / split).mkdir(parents=True, exist_ok=True)


def _reusable(work: Path, split: str, index: int) -> bool:
    """Whether a cached trajectory can be taken as is. Files are written atomically, so only
    the zip directory is checked here (cheaply); the arrays are checked when assembling."""
    path = _cache_path(work, split, index)
    if not path.is_file():
        return False
    try:
        with np.load(path) as f:
            if {"positions", "particle_type", "draw"} <= set(f.files):
                return True
    except Exception:  # an unreadable cache file is simply simulated again
        pass
    sys.stderr.write(f"gns generate: {path} is unreadable; simulating it again\n")
    path.unlink()
    return False


def generate(
    preset: str,
    out: str | os.PathLike[str],
    n_train: int,
    n_valid: int,
    n_test: int,
    seed: int = 0,
    workers: int = 1,
    frames: int | None = None,
    progress: bool | Callable[[int, int], object] = True,
    scale: float = 1.0,
) -> Summary:
    """Simulate n_train / n_valid / n_test trajectories of `preset` and write the dataset folder
    `out` (metadata.json, {split}.tfrecord; a split of 0 trajectories gets no file).

    seed: any integer >= 0; the dataset depends on it and the other arguments, not on `workers`
    (threads, each running one trajectory). frames: frames per trajectory including frame 0
    (default: the preset's). progress: True for a progress line on stderr, or a function called
    as progress(done, total) after every finished trajectory (raising from it stops the run,
    which a re-run then resumes). scale: about this many times the preset's particles (a
    finer grid and lattice; gns.mpm.presets). Metadata statistics are those of the train split.
    """
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; expected one of {sorted(PRESETS)}")
    scale = check_scale(scale)
    counts = {
        "n_train": _check_count("n_train", n_train, 1),
        "n_valid": _check_count("n_valid", n_valid, 0),
        "n_test": _check_count("n_test", n_test, 0),
    }
    seed = _check_count("seed", seed, 0)
    workers = _check_count("workers", workers, 1)
    if frames is not None:
        # Three frames are the fewest that have an acceleration (the train split's statistics).
        frames = _check_count("frames", frames, 3)
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ValueError(f"{out}: exists and is not an empty folder; choose a new --out")
    work = out.with_name(out.name + ".partial")
    _prepare_work(work, _arguments(preset, counts, seed, frames, scale))

    per_split = dict(zip(SPLITS, counts.values(), strict=True))
    meter = _Progress(per_split, frames or preset_scene(preset, seed)[1], progress is True)
    callback = progress if callable(progress) else None
    todo = []
    for split, n in per_split.items():
        for index in range(n):
            if _reusable(work, split, index):
                meter.done[split] = meter.done.get(split, 0) + 1
                meter.reused += 1
            else:
                todo.append((split, index))
    total = sum(per_split.values())

    stop = threading.Event()
    pool = cf.ThreadPoolExecutor(max_workers=workers, thread_name_prefix="gns-generate")
    try:
        pending = {
            pool.submit(_simulate_one, preset, seed, scale, s, i, frames, work, stop, meter): s
            for s, i in todo
        }
        while pending:
            finished, _ = cf.wait(pending, timeout=0.5, return_when=cf.FIRST_COMPLETED)
            for future in finished:
                split = pending.pop(future)
                future.result()
                meter.done[split] = meter.done.get(split, 0) + 1
                if callback is not None:
                    callback(sum(meter.done.values()), total)
            meter.show()
    finally:
        # On an error or an interrupt the running simulations stop at their next frame; what
        # finished is cached for the next run.
        stop.set()
        pool.shutdown(wait=True, cancel_futures=True)
        meter.close()

    written, redrawn = _assemble(out, work, preset, per_split, seed, scale)
    shutil.rmtree(work, ignore_errors=True)
    return Summary(written, redrawn, meter.reused, time.perf_counter() - meter.started)


def _assemble(
    out: Path,
    work: Path,
    preset: str,
    per_split: dict[str, int],
    seed: int,
    scale: float,
) -> tuple[dict[str, int], int]:
    """Write the dataset folder from the cached trajectories, atomically; return the
    trajectories written per split and the number of rejected draws behind them."""
    accumulator = StatisticsAccumulator(DEFAULT_KINEMATIC_TYPES)
    written: dict[str, int] = {}
    draws: dict[str, list[int]] = {}
    shapes: dict[str, dict[str, list[dict[str, Any]]]] = {}
    lengths: set[int] = set()
    with atomic_folder(out) as tmp:
        for split, n in per_split.items():
            if n == 0:
                continue
            draws[split] = []

            def stream(split: str = split, n: int = n) -> Iterator[Trajectory]:
                for index in range(n):
                    trajectory, draw = _load(_cache_path(work, split, index), index)
                    draws[split].append(draw)
                    drawn = preset_scene(preset, seed, split, index, draw, scale)[0]
                    shapes.setdefault(split, {})[str(trajectory.key)] = obstacles(drawn)
                    lengths.add(trajectory.num_frames)
                    if split == "train":
                        accumulator.add(trajectory)
                    yield trajectory

            written[split] = write_tfrecord(tmp / f"{split}.tfrecord", stream())
        if len(lengths) != 1:
            raise ValueError(f"cached trajectories in {work} differ in length: {sorted(lengths)}")
        scene = preset_scene(preset, seed, scale=scale)[0]
        metadata = Metadata(
            bounds=confinement(scene),
            sequence_length=lengths.pop() - 1,
            default_connectivity_radius=connectivity_radius(preset, scale),
            dim=scene.dim,
            dt=scene.frame_dt,
            extra={
                "generator": {
                    "preset": preset,
                    "seed": seed,
                    **({"scale": scale} if scale != 1.0 else {}),
                    **PRESET_METADATA.get(preset, {}),
                    # Which draw each trajectory is (0 unless earlier draws failed).
                    "draws": {s: d for s, d in draws.items() if any(d)},
                },
                # The static shapes, for a reader that gives the model distances to them; only
                # for presets with obstacles, which then have an entry for every trajectory.
                **(
                    {"obstacles": shapes}
                    if any(entry for split in shapes.values() for entry in split.values())
                    else {}
                ),
            },
        )
        metadata = accumulator.result().apply_to(metadata)
        metadata.write_json(tmp / "metadata.json")
    return written, sum(sum(d) for d in draws.values())
