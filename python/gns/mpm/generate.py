"""`gns generate`: datasets in the DeepMind layout from the reference simulator (gns.mpm).

    generate("sand", "data/sand", n_train=100, n_valid=10, n_test=10, seed=0, workers=2)

Presets (the paper's scenes, docs/reference-simulator.md) are functions rng -> (MpmScene,
frames), `frames` counting frame 0, so a preset's sequence_length is the paper's (WaterDrop 1000,
Sand 320, Goop 400, WaterRamps 600, MultiMaterial 1000):
  waterdrop      one block of water at rest, width U(0.1, 0.3), height U(0.15, 0.35)
  water, sand, goop
                 1-3 non-overlapping blocks of side U(0.15, 0.3), velocity U(-2.5, 2.5) m/s per
                 axis (sand U(-4.5, 4.5): see SAND_SPEED)
  multimaterial  2-3 blocks of distinct materials among water, sand and goop
  ramps          water or sand blocks among 1-3 static ramps (kinematic particles, type 3)
  continuous     sand as above whose friction angle is U(20, 45) degrees per trajectory, stored
                 as the global feature tan(angle) (DeepMind's step_context)
  sand-taichi    sand2d-taichi's scenes: one 0.2 x 0.2 sand block at rest or thrown at up to
                 1 m/s per axis, friction U(20, 45) degrees as in continuous, 350 frames, at
                 that dataset's own resolution (grid 64, 4 particles a cell)
All but sand-taichi share one resolution (RESOLUTION: lattice spacing 0.01, grid dx 0.025),
chosen with `sand`'s speed so that waterdrop and sand match the paper's per-frame statistics
within a factor 1.5 (benches/mpm.py --calibrate).

Metadata bounds are where the simulator stops the particles (see `confinement`), the innermost
grid nodes of its walls, not the walls' nominal position MpmScene.bounds.

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
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gns import mpm
from gns.data.deepmind import write_tfrecord
from gns.data.metadata import DEFAULT_KINEMATIC_TYPES, Metadata
from gns.data.stats import StatisticsAccumulator
from gns.data.trajectory import Trajectory
from gns.files import atomic_file, atomic_folder, claim_folder
from gns.mpm import Block, Goop, MpmScene, Sand, Segment, Water

__all__ = [
    "PRESETS",
    "SPLITS",
    "Summary",
    "confinement",
    "generate",
    "preset_scene",
    "trajectory_seed",
]

SPLITS = ("train", "valid", "test")
# The paper's 2D connectivity radius: about 7 neighbours at the lattice spacing 0.01 below.
CONNECTIVITY_RADIUS = 0.015
# Draws of one trajectory before giving up: a preset that fails this often is broken, and
# silently skipping it would bias the dataset towards the scenes that happen to be stable.
MAX_DRAWS = 8
# Bump when the meaning of the cached files or of a seed changes, so old partial runs are refused.
CACHE_FORMAT = 1

# Where blocks may start: the walls (MpmScene's default bounds) less a margin, so no particle
# starts on a wall node, and a gap between blocks so that they start apart.
WALLS = ((0.1, 0.9), (0.1, 0.9))
MARGIN = 0.02
GAP = 0.02
SIDE = (0.15, 0.3)
SPEED = 2.5
# Sand blocks are thrown faster than the design's U(-2.5, 2.5): at 2.5 m/s their per-frame
# acceleration std was 0.47-0.57 of the paper's Sand data, at 4.5 m/s 0.87-0.95 (velocity std
# 1.1 of it); see benches/mpm.py --calibrate.
SAND_SPEED = 4.5
# Every preset's resolution: lattice spacing 0.01 (1e4 particles per unit area, as the design
# asks) on a grid of dx = 0.025, coarser than MpmScene's default 1 / 64. Grid resolution sets how
# sharply particles stop at a wall, and the per-frame acceleration std of WaterDrop is mostly
# (~90%) the 1% of samples at the splash: at dx = 1/64 it was 1.9x the paper's, at dx = 0.02
# 1.5-1.6x, at dx = 0.025 1.1-1.3x. The grid also has to be the same in every preset, so that
# datasets mixing materials see one numerical behaviour.
RESOLUTION: dict[str, Any] = {"grid": 40, "particles_per_cell": 6.25}

Placement = tuple[tuple[float, float], tuple[float, float]]  # (lower, size)
Preset = Callable[[np.random.Generator], tuple[MpmScene, int]]


# ----------------------------------------------------------------------------------- placement


def _overlaps(a: Placement, b: Placement, gap: float) -> bool:
    (ax, ay), (aw, ah) = a
    (bx, by), (bw, bh) = b
    return ax < bx + bw + gap and bx < ax + aw + gap and ay < by + bh + gap and by < ay + ah + gap


def _inside(points: np.ndarray, rect: Placement, gap: float) -> bool:
    (x, y), (w, h) = rect
    px, py = points[:, 0], points[:, 1]
    return bool(np.any((px > x - gap) & (px < x + w + gap) & (py > y - gap) & (py < y + h + gap)))


def place_blocks(
    rng: np.random.Generator,
    sizes: np.ndarray,
    keep_out: np.ndarray | None = None,
    keep_out_gap: float = GAP,
    attempts: int = 200,
) -> list[Placement]:
    """Non-overlapping rectangles of the given (k, 2) sizes inside the walls, GAP apart and
    `keep_out_gap` clear of the `keep_out` points. Sizes shrink by 10% until they fit."""
    scale = 1.0
    for _ in range(30):
        placed: list[Placement] = []
        for w, h in sizes * scale:
            hi_x, hi_y = WALLS[0][1] - MARGIN - w, WALLS[1][1] - MARGIN - h
            lo_x, lo_y = WALLS[0][0] + MARGIN, WALLS[1][0] + MARGIN
            if hi_x <= lo_x or hi_y <= lo_y:
                break
            for _ in range(attempts):
                rect = ((rng.uniform(lo_x, hi_x), rng.uniform(lo_y, hi_y)), (w, h))
                if any(_overlaps(rect, other, GAP) for other in placed):
                    continue
                if keep_out is not None and _inside(keep_out, rect, keep_out_gap):
                    continue
                placed.append(rect)
                break
            else:
                break
        if len(placed) == len(sizes):
            return [((float(x), float(y)), (float(w), float(h))) for (x, y), (w, h) in placed]
        scale *= 0.9
    raise ValueError(f"cannot place blocks of sizes {sizes.tolist()} without overlap")


def _blocks(
    rng: np.random.Generator,
    materials: Sequence[mpm.Material],
    speed: float,
    keep_out: np.ndarray | None = None,
    gap: float = GAP,
) -> list[Block]:
    """Blocks of side U(SIDE) of the given materials, velocity U(-speed, speed) per axis."""
    sizes = rng.uniform(SIDE[0], SIDE[1], (len(materials), 2))
    rects = place_blocks(rng, sizes, keep_out, gap)
    velocities = rng.uniform(-speed, speed, (len(materials), 2))
    return [
        Block(m, lower=lower, size=size, velocity=(float(v[0]), float(v[1])))
        for m, (lower, size), v in zip(materials, rects, velocities, strict=True)
    ]


def _scene(blocks: Sequence[Block], **settings: Any) -> MpmScene:
    return MpmScene(blocks, **RESOLUTION, **settings)


def _count(rng: np.random.Generator, lo: int = 1, hi: int = 3) -> int:
    return int(rng.integers(lo, hi + 1))


# ------------------------------------------------------------------------------------- presets


def waterdrop(rng: np.random.Generator) -> tuple[MpmScene, int]:
    """One block of water at rest, falling from a random place: WaterDrop."""
    w, h = rng.uniform(0.1, 0.3), rng.uniform(0.15, 0.35)
    x = rng.uniform(WALLS[0][0] + MARGIN, WALLS[0][1] - MARGIN - w)
    y = rng.uniform(WALLS[1][0] + MARGIN, WALLS[1][1] - MARGIN - h)
    block = Block(Water(), lower=(float(x), float(y)), size=(float(w), float(h)))
    return _scene([block]), 1001


def water(rng: np.random.Generator) -> tuple[MpmScene, int]:
    """1-3 blocks of water thrown in random directions."""
    return _scene(_blocks(rng, [Water()] * _count(rng), SPEED)), 1001


def sand(rng: np.random.Generator) -> tuple[MpmScene, int]:
    """1-3 blocks of sand (friction angle 30 degrees) thrown in random directions: Sand."""
    return _scene(_blocks(rng, [Sand()] * _count(rng), SAND_SPEED)), 321


def goop(rng: np.random.Generator) -> tuple[MpmScene, int]:
    """1-3 blocks of goop thrown in random directions: Goop."""
    return _scene(_blocks(rng, [Goop()] * _count(rng), SPEED)), 401


def multimaterial(rng: np.random.Generator) -> tuple[MpmScene, int]:
    """2-3 blocks, each of a different material among water, sand and goop: MultiMaterial."""
    kinds: list[mpm.Material] = [Water(), Sand(), Goop()]
    chosen = rng.permutation(3)[: _count(rng, 2, 3)]
    return _scene(_blocks(rng, [kinds[i] for i in chosen], SPEED)), 1001


def random_ramps(rng: np.random.Generator, count: int, spacing: float) -> list[Segment]:
    """Static ramps of length U(0.15, 0.35) tilted U(-40, 40) degrees, 0.05 apart from each other
    and clear of the walls (the obstacle particles' rows go below the segment, by `spacing`)."""
    segments: list[Segment] = []
    lines: list[np.ndarray] = []
    clearance = MARGIN + 2 * spacing
    lo, hi = np.array(WALLS)[:, 0] + clearance, np.array(WALLS)[:, 1] - clearance
    for _ in range(200 * count):
        if len(segments) == count:
            break
        length = rng.uniform(0.15, 0.35)
        angle = math.radians(rng.uniform(-40.0, 40.0))
        half = 0.5 * length * np.array([math.cos(angle), math.sin(angle)])
        centre = rng.uniform(lo, hi)
        start, end = centre - half, centre + half
        if np.any(np.minimum(start, end) < lo) or np.any(np.maximum(start, end) > hi):
            continue
        line = start + np.linspace(0, 1, 50)[:, None] * (end - start)
        if any(
            np.min(np.linalg.norm(line[:, None] - other[None], axis=2)) < 0.05 for other in lines
        ):
            continue
        segments.append(Segment((float(start[0]), float(start[1])), (float(end[0]), float(end[1]))))
        lines.append(line)
    if len(segments) < count:
        raise ValueError(f"cannot place {count} ramps apart from each other")
    return segments


def ramps(rng: np.random.Generator) -> tuple[MpmScene, int]:
    """Water or sand blocks among 1-3 static ramps: WaterRamps (and its sand twin)."""
    empty = _scene([])
    segments = random_ramps(rng, _count(rng), empty.spacing)
    material: mpm.Material = Water() if rng.random() < 0.5 else Sand()
    # Obstacle particles make the 3 x 3 grid nodes around them sticky: blocks keep clear of
    # those nodes too, or they would start stuck.
    probe = mpm.particles(_scene([], obstacles=segments))["positions"]
    gap = GAP + 2 / empty.grid
    blocks = _blocks(rng, [material] * _count(rng), SPEED, probe, gap)
    return _scene(blocks, obstacles=segments), 601


def continuous(rng: np.random.Generator) -> tuple[MpmScene, int]:
    """Sand with the friction angle U(20, 45) degrees per trajectory, given to the model as
    tan(angle), the Mohr-Coulomb friction coefficient (as sand2d-taichi's material_property)."""
    angle = float(rng.uniform(20.0, 45.0))
    blocks = _blocks(rng, [Sand(friction_angle_deg=angle)] * _count(rng), SAND_SPEED)
    return _scene(blocks, context=[math.tan(math.radians(angle))]), 321


# sand2d-taichi's setup (Taichi-Elements as geoelements ran it; the defaults of MpmScene): one
# 0.2 x 0.2 block anywhere in the walls, at rest or thrown at U(-1, 1) m/s per axis (its 12
# thrown runs reach 0.95), 350 frames 2.5 ms apart.
TAICHI_SIDE = 0.2
TAICHI_SPEED = 1.0
TAICHI_FRAMES = 350


def sand_taichi(rng: np.random.Generator) -> tuple[MpmScene, int]:
    """One 0.2 x 0.2 block of sand, friction angle U(20, 45) degrees given as tan(angle) (as
    `continuous`), half at rest and half thrown, at sand2d-taichi's resolution (grid 64, 4
    particles a cell, spacing 1/128): training data for a model of that dataset."""
    angle = float(rng.uniform(20.0, 45.0))
    # 0.005 inside the walls: Taichi's blocks come as close as 0.101.
    lo, hi = WALLS[0][0] + MARGIN / 4, WALLS[0][1] - MARGIN / 4 - TAICHI_SIDE
    lower = rng.uniform(lo, hi, 2)
    thrown = rng.random() < 0.5
    velocity = rng.uniform(-TAICHI_SPEED, TAICHI_SPEED, 2) if thrown else np.zeros(2)
    block = Block(
        Sand(friction_angle_deg=angle),
        lower=(float(lower[0]), float(lower[1])),
        size=(TAICHI_SIDE, TAICHI_SIDE),
        velocity=(float(velocity[0]), float(velocity[1])),
    )
    return MpmScene([block], context=[math.tan(math.radians(angle))]), TAICHI_FRAMES


PRESETS: dict[str, Preset] = {
    "waterdrop": waterdrop,
    "water": water,
    "sand": sand,
    "goop": goop,
    "multimaterial": multimaterial,
    "ramps": ramps,
    "continuous": continuous,
    "sand-taichi": sand_taichi,
}


def trajectory_seed(seed: int, split: str, index: int, draw: int = 0) -> np.random.SeedSequence:
    """The seed of one draw of one trajectory: a function of these four values only."""
    return np.random.SeedSequence(seed, spawn_key=(SPLITS.index(split), index, draw))


def preset_scene(
    preset: str, seed: int, split: str = "train", index: int = 0, draw: int = 0
) -> tuple[MpmScene, int, int]:
    """(scene, frames, lattice seed) of one draw, exactly as `generate` makes it."""
    rng = np.random.default_rng(trajectory_seed(seed, split, index, draw))
    scene, frames = _preset(preset)(rng)
    return scene, frames, int(rng.integers(2**63))


def _preset(name: str) -> Preset:
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; expected one of {sorted(PRESETS)}")
    return PRESETS[name]


def confinement(scene: MpmScene) -> tuple[tuple[float, float], ...]:
    """The box the simulator keeps the particles of `scene` in, per axis: from the innermost
    grid node of the lower wall to that of the upper wall. These are the dataset's bounds.

    MpmScene.bounds is not that box. The simulator (rust/mpm.rs, update_grid) enforces the walls
    on the grid nodes outside `bounds`, and a particle takes its velocity from the 3 x 3 nodes
    around it (quadratic B-splines), so one that has crossed `bounds` keeps moving with the
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
    step_context = None if context is None else np.tile(context, (len(positions), 1))
    return Trajectory(positions, types, step_context, key=index, source=str(path)), draw


def _simulate_one(
    preset: str,
    seed: int,
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
        scene, preset_frames, lattice_seed = preset_scene(preset, seed, split, index, draw)
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
    preset: str, counts: dict[str, int], seed: int, frames: int | None
) -> dict[str, Any]:
    """What a partial run must share with this one for its trajectories to be reused."""
    return {"format": CACHE_FORMAT, "preset": preset, "seed": seed, "frames": frames, **counts}


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
) -> Summary:
    """Simulate n_train / n_valid / n_test trajectories of `preset` and write the dataset folder
    `out` (metadata.json, {split}.tfrecord; a split of 0 trajectories gets no file).

    seed: any integer >= 0; the dataset depends on it and the other arguments, not on `workers`
    (threads, each running one trajectory). frames: frames per trajectory including frame 0
    (default: the preset's). progress: True for a progress line on stderr, or a function called
    as progress(done, total) after every finished trajectory (raising from it stops the run,
    which a re-run then resumes). Metadata statistics are those of the train split.
    """
    _preset(preset)
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
    _prepare_work(work, _arguments(preset, counts, seed, frames))

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
            pool.submit(_simulate_one, preset, seed, s, i, frames, work, stop, meter): s
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

    written, redrawn = _assemble(out, work, preset, per_split, seed)
    shutil.rmtree(work, ignore_errors=True)
    return Summary(written, redrawn, meter.reused, time.perf_counter() - meter.started)


def _assemble(
    out: Path,
    work: Path,
    preset: str,
    per_split: dict[str, int],
    seed: int,
) -> tuple[dict[str, int], int]:
    """Write the dataset folder from the cached trajectories, atomically; return the
    trajectories written per split and the number of rejected draws behind them."""
    accumulator = StatisticsAccumulator(DEFAULT_KINEMATIC_TYPES)
    written: dict[str, int] = {}
    draws: dict[str, list[int]] = {}
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
                    lengths.add(trajectory.num_frames)
                    if split == "train":
                        accumulator.add(trajectory)
                    yield trajectory

            written[split] = write_tfrecord(tmp / f"{split}.tfrecord", stream())
        if len(lengths) != 1:
            raise ValueError(f"cached trajectories in {work} differ in length: {sorted(lengths)}")
        scene = preset_scene(preset, seed)[0]
        metadata = Metadata(
            bounds=confinement(scene),
            sequence_length=lengths.pop() - 1,
            default_connectivity_radius=CONNECTIVITY_RADIUS,
            dim=2,
            dt=scene.frame_dt,
            extra={
                "generator": {
                    "preset": preset,
                    "seed": seed,
                    # Which draw each trajectory is (0 unless earlier draws failed).
                    "draws": {s: d for s, d in draws.items() if any(d)},
                }
            },
        )
        metadata = accumulator.result().apply_to(metadata)
        metadata.write_json(tmp / "metadata.json")
    return written, sum(sum(d) for d in draws.values())
