"""The reference simulator (MLS-MPM in 2D and 3D in the Rust core), for ground truth and timing.

A scene is blocks of material on a lattice plus static obstacles, inside the walls `bounds` of
the [0, 1]^D domain:

    scene = MpmScene([Block(Sand(friction_angle_deg=30), lower=(0.4, 0.1), size=(0.2, 0.2))])
    result = simulate(scene, frames=350)
    result.positions        # (frames, N, 2) float32, frame 0 the initial state
    result.seconds          # wall-clock seconds per simulated frame
    result.to_trajectory()  # a gns.data.Trajectory with DeepMind particle types

A scene is 3D when its blocks are (lower, size and velocity of 3 values); bounds and gravity
default to [0.1, 0.9] on every axis and 9.81 m/s^2 down the y axis in both. A BOXBATH-style
scene, a rigid box dropped into water:

    scene = MpmScene([Block(Water(), (0.1, 0.1, 0.1), (0.8, 0.2, 0.8)),
                      Block(Rigid(), (0.4, 0.5, 0.4), (0.15, 0.15, 0.15))], grid=32)
    simulate(scene, frames=200).positions  # (200, N, 3)

A container shaken side to side (the paper's FLUIDSHAKE) is simulated in its own frame, where
its walls are at rest and the shaking is a fictitious force -a_c(t) added to gravity; the
positions are in the container's frame and the result's context gives, at every frame, the
container's position, velocity and acceleration (the paper's 6 global features in 2D):

    scene = MpmScene([Block(Water(), (0.2, 0.1), (0.3, 0.2))], shake=Shake(0.02, 2.0))
    simulate(scene, frames=100).context  # (100, 6): x, y, vx, vy, ax, ay of the container

Accuracy against cost is set by `grid` (cells per unit length), `particles_per_cell` (the
lattice spacing is dx / particles_per_cell^(1/D)) and `cfl` (substeps). Instead of the lattice,
the blocks can be filled with given points, e.g. another simulator's first frame, so that
particle i of the result is particle i of that data:

    result = simulate(scene, frames=350, positions=their_frame_0)

Units are SI: metres, seconds, kg/m^3, Pa. Particle types follow the DeepMind datasets (water 5,
sand 6, goop 7, obstacles 3, kinematic; rigid bodies 0, the type of "rigid solids" in DeepMind's
render_rollout.py and of BOXBATH's box).

This package is the reference simulator, kept apart from the learned model; its submodule
gns.mpm.generate draws scenes from presets and writes them as datasets (`gns generate`).
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from gns import _core
from gns.data.trajectory import Trajectory
from gns.threads import StepTuner

__all__ = [
    "DEFAULT_GRAVITY",
    "DEFAULT_WALLS",
    "Block",
    "Goop",
    "MpmResult",
    "MpmScene",
    "Rigid",
    "Sand",
    "Segment",
    "Shake",
    "Water",
    "simulate",
]

# MpmScene's walls on each axis when its bounds are not given (sand2d-taichi's box), and its
# gravity (m/s^2, down the y axis) when not given.
DEFAULT_WALLS = (0.1, 0.9)
DEFAULT_GRAVITY = 9.81

OBSTACLE_TYPE = 3
# DeepMind's id for rigid solids (0 "Rigid solids" in learning_to_simulate/render_rollout.py of
# github.com/google-deepmind/deepmind-research): BOXBATH's box. It means nothing else in their
# data (3 kinematic, 5 water, 6 sand, 7 goop), and a dataset of ours with a box reads like theirs.
RIGID_TYPE = 0


@dataclass(frozen=True)
class Water:
    """Weakly compressible fluid; wave speed sqrt(bulk_modulus / density) (31.6 m/s here)."""

    density: float = 1000.0
    bulk_modulus: float = 1e6
    particle_type = 5

    def core(self) -> tuple[str, float, list[float]]:
        return ("water", self.density, [self.bulk_modulus])


@dataclass(frozen=True)
class Sand:
    """Drucker-Prager sand without cohesion; the defaults are the sand2d-taichi dataset's."""

    density: float = 1800.0
    youngs_modulus: float = 2e6
    poisson_ratio: float = 0.3
    friction_angle_deg: float = 30.0
    particle_type = 6

    def core(self) -> tuple[str, float, list[float]]:
        params = [self.youngs_modulus, self.poisson_ratio, self.friction_angle_deg]
        return ("sand", self.density, params)


@dataclass(frozen=True)
class Goop:
    """Elastoplastic: Hencky elasticity, von Mises yield stress (Pa)."""

    density: float = 1000.0
    youngs_modulus: float = 3e3
    poisson_ratio: float = 0.35
    yield_stress: float = 200.0
    particle_type = 7

    def core(self) -> tuple[str, float, list[float]]:
        params = [self.youngs_modulus, self.poisson_ratio, self.yield_stress]
        return ("goop", self.density, params)


@dataclass(frozen=True)
class Rigid:
    """A rigid body (BOXBATH's box): every Block of it is its own body, whose particles scatter
    mass and momentum to the grid like any material (no stress) and are then moved together,
    by the body's linear and angular velocity, keeping their shape exactly. The default
    density, half the water's, floats."""

    density: float = 500.0
    particle_type = RIGID_TYPE

    def core(self) -> tuple[str, float, list[float]]:
        return ("rigid", self.density, [])


Material = Water | Sand | Goop | Rigid


@dataclass(frozen=True)
class Block:
    """A box [lower, lower + size] filled with `material`, moving at `velocity` (m/s; default
    at rest). 2D or 3D: lower, size and velocity have 2 values each, or 3."""

    material: Material
    lower: tuple[float, ...]
    size: tuple[float, ...]
    velocity: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        dim = len(self.lower)
        if dim not in (2, 3):
            raise ValueError(f"Block.lower must have 2 values (2D) or 3 (3D), got {self.lower}")
        if self.velocity is None:
            object.__setattr__(self, "velocity", (0.0,) * dim)
        for name in ("size", "velocity"):
            value = getattr(self, name)
            if len(value) != dim:
                raise ValueError(
                    f"Block.{name} = {tuple(value)} has {len(value)} values but Block.lower = "
                    f"{tuple(self.lower)} has {dim}: a block is 2D or 3D on every count"
                )

    @property
    def dim(self) -> int:
        return len(self.lower)


@dataclass(frozen=True)
class Segment:
    """A static obstacle (a ramp or floor): kinematic particles from start to end, `layers`
    rows thick, that make the grid nodes they cover sticky."""

    start: tuple[float, float]
    end: tuple[float, float]
    layers: int = 2


@dataclass(frozen=True)
class Shake:
    """The container shaken along `axis`: its displacement is amplitude sin(2 pi frequency_hz t
    + phase) (m, Hz, rad), t = frame * frame_dt, and zero on the other axes. The scene is
    simulated in the container's frame, as the paper gives FLUIDSHAKE's positions: there the
    walls are at rest and a fictitious force -a_c(t) per unit mass adds to gravity."""

    amplitude: float
    frequency_hz: float
    phase: float = 0.0
    axis: int = 0

    def __post_init__(self) -> None:
        for name in ("amplitude", "frequency_hz", "phase"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ValueError(f"Shake.{name} must be a number, got {value!r}")
            if not math.isfinite(value):
                raise ValueError(f"Shake.{name} must be finite, got {value}")
        if self.amplitude < 0:
            raise ValueError(f"Shake.amplitude must be >= 0 (m), got {self.amplitude}")
        if not self.frequency_hz > 0:
            raise ValueError(f"Shake.frequency_hz must be > 0, got {self.frequency_hz}")
        if isinstance(self.axis, bool) or not isinstance(self.axis, int) or self.axis < 0:
            raise ValueError(f"Shake.axis must be an axis index >= 0, got {self.axis!r}")

    @property
    def omega(self) -> float:
        """The angular frequency 2 pi f (rad/s)."""
        return 2.0 * math.pi * self.frequency_hz

    def position(self, t: np.ndarray) -> np.ndarray:
        """The container's displacement along `axis` at times t (s)."""
        return self.amplitude * np.sin(self.omega * np.asarray(t, np.float64) + self.phase)

    def velocity(self, t: np.ndarray) -> np.ndarray:
        return (
            self.amplitude
            * self.omega
            * np.cos(self.omega * np.asarray(t, np.float64) + self.phase)
        )

    def acceleration(self, t: np.ndarray) -> np.ndarray:
        return -(self.omega**2) * self.position(t)

    def context(self, t: np.ndarray, dim: int) -> np.ndarray:
        """(len(t), 3 dim) float64: the container's position (dim), velocity (dim) and
        acceleration (dim) at times t, zero on the axes it is not shaken along."""
        t = np.asarray(t, np.float64)
        out = np.zeros((len(t), 3 * dim))
        for k, motion in enumerate((self.position, self.velocity, self.acceleration)):
            out[:, k * dim + self.axis] = motion(t)
        return out


@dataclass(frozen=True)
class MpmScene:
    """What to simulate and how finely. The scene is 2D or 3D as its blocks are (2D without
    blocks; obstacles, Segments, are 2D only). bounds: the walls, one (lo, hi) per axis
    (default DEFAULT_WALLS on each); gravity: one value per axis (default DEFAULT_GRAVITY down y).
    wall: "coulomb" (friction wall_friction), "slip" or "sticky". jitter: random offset of
    each lattice point, as a fraction of the spacing. context: global features of the whole
    trajectory. shake: the container shaken (Shake), which gives a per-frame context instead."""

    blocks: Sequence[Block]
    obstacles: Sequence[Segment] = ()
    bounds: Sequence[tuple[float, float]] | None = None
    wall: str = "coulomb"
    wall_friction: float = 0.5
    gravity: Sequence[float] | None = None
    frame_dt: float = 0.0025
    grid: int = 64
    particles_per_cell: float = 4.0
    cfl: float = 0.4
    max_substeps: int = 2000
    jitter: float = 0.0
    context: Sequence[float] | None = field(default=None)
    shake: Shake | None = None

    def __post_init__(self) -> None:
        dims = {block.dim for block in self.blocks}
        if len(dims) > 1:
            described = ", ".join(f"block {k}: {b.dim}D" for k, b in enumerate(self.blocks))
            raise ValueError(f"the blocks mix 2D and 3D ({described}); a scene is one or the other")
        dim = dims.pop() if dims else 2
        if self.obstacles and dim != 2:
            raise ValueError(
                f"obstacles (Segment) are 2D, but this scene's blocks are {dim}D; a 3D scene "
                "cannot have obstacles yet"
            )
        if self.bounds is None:
            object.__setattr__(self, "bounds", (DEFAULT_WALLS,) * dim)
        if self.gravity is None:
            object.__setattr__(self, "gravity", (0.0, -DEFAULT_GRAVITY, 0.0)[:dim])
        assert self.bounds is not None and self.gravity is not None
        if len(self.bounds) != dim or any(len(pair) != 2 for pair in self.bounds):
            raise ValueError(
                f"MpmScene.bounds = {self.bounds} must be {dim} pairs (lo, hi), one per axis of "
                f"the scene's {dim}D blocks"
            )
        if len(self.gravity) != dim:
            raise ValueError(
                f"MpmScene.gravity = {self.gravity} must have {dim} values, one per axis of the "
                f"scene's {dim}D blocks"
            )
        if self.shake is not None:
            if self.context is not None:
                raise ValueError(
                    f"MpmScene has both shake = {self.shake} and context = {self.context}; the "
                    "global features come from one source: the shaken container's motion per "
                    "frame, or a fixed context, not both"
                )
            if self.shake.axis >= dim:
                raise ValueError(
                    f"Shake.axis = {self.shake.axis} but the scene is {dim}D (axes 0-{dim - 1})"
                )

    @property
    def dim(self) -> int:
        """2 or 3, the blocks' dimension (2 without blocks)."""
        return self.blocks[0].dim if self.blocks else 2

    @property
    def spacing(self) -> float:
        """The lattice spacing: dx / particles_per_cell^(1/D)."""
        if not self.particles_per_cell > 0:
            raise ValueError(f"particles_per_cell must be > 0, got {self.particles_per_cell}")
        if self.dim == 2:
            return 1.0 / self.grid / math.sqrt(self.particles_per_cell)
        # np.cbrt, not ** (1 / 3), so that 8 and 27 per cell give spacings dx / 2 and dx / 3.
        return 1.0 / self.grid / float(np.cbrt(self.particles_per_cell))


@dataclass(frozen=True)
class MpmResult:
    positions: np.ndarray  # (frames, N, D) float32
    particle_type: np.ndarray  # (N,) int64
    seconds: np.ndarray  # (frames - 1,) wall-clock seconds per frame
    substeps: np.ndarray  # (frames - 1,) substeps per frame
    # Global features, if the scene has any: (K,) for the whole trajectory (MpmScene.context)
    # or (frames, K) per frame (a Shake's container motion).
    context: np.ndarray | None = None

    def to_trajectory(self, key: int = 0) -> Trajectory:
        context = step_context(self.context, len(self.positions))
        return Trajectory(self.positions, self.particle_type, context, key=key)


def step_context(context: np.ndarray | None, frames: int) -> np.ndarray | None:
    """(frames, K) float32 per-frame global features from a context of (K,) (the same at
    every frame: tiled) or (frames, K) (taken as is); None stays None. ValueError for any other
    shape."""
    if context is None:
        return None
    context = np.asarray(context, np.float32)
    if context.ndim == 1:
        return np.tile(context, (frames, 1))
    if context.ndim == 2 and len(context) == frames:
        return context
    raise ValueError(
        f"context must be (K,) for the whole trajectory or (frames, K) = ({frames}, K) per "
        f"frame, got shape {context.shape}"
    )


def lattice(lower: Sequence[float], size: Sequence[float], spacing: float) -> np.ndarray:
    """Cell-centred lattice points of spacing `spacing` filling [lower, lower + size]."""
    counts = [max(1, round(s / spacing)) for s in size]
    axes = [
        lo + (np.arange(c) + 0.5) * (s / c) for lo, s, c in zip(lower, size, counts, strict=True)
    ]
    return np.stack([x.ravel() for x in np.meshgrid(*axes, indexing="ij")], axis=1)


def _segment_points(segment: Segment, spacing: float) -> np.ndarray:
    start, end = np.asarray(segment.start, float), np.asarray(segment.end, float)
    length = float(np.linalg.norm(end - start))
    if length == 0.0:
        raise ValueError(f"obstacle segment {segment} has zero length")
    if segment.layers < 1:
        raise ValueError(f"obstacle segment layers must be >= 1, got {segment.layers}")
    along = (end - start) / length
    normal = np.array([-along[1], along[0]])
    t = np.linspace(0.0, length, max(2, round(length / spacing) + 1))
    rows = [start + t[:, None] * along - k * spacing * normal for k in range(segment.layers)]
    return np.concatenate(rows)


def _block_of_each(blocks: Sequence[Block], points: np.ndarray, margin: float) -> np.ndarray:
    """(N,) the index of the block each point lies in: the nearest box (distance 0
    inside; the first of equally near ones), which must be at most `margin` away. ValueError
    naming the first point that no block holds, and the blocks."""
    if not blocks:
        raise ValueError("given positions need blocks to take their material and velocity from")
    distances = []
    for block in blocks:
        lower = np.asarray(block.lower, float)
        upper = lower + np.asarray(block.size, float)
        outside = np.maximum(np.maximum(lower - points, points - upper), 0.0)
        distances.append(np.linalg.norm(outside, axis=1))
    distance = np.stack(distances)  # (blocks, N)
    index = np.argmin(distance, axis=0)
    nearest = distance[index, np.arange(len(points))]
    if (far := np.flatnonzero(~(nearest <= margin))).size:
        i = int(far[0])
        rectangles = "; ".join(
            f"block {k}: lower {tuple(b.lower)}, size {tuple(b.size)}" for k, b in enumerate(blocks)
        )
        more = f" (and {far.size - 1} more)" if far.size > 1 else ""
        raise ValueError(
            f"given point {i} at {tuple(points[i].tolist())}{more} is in no block (nor within "
            f"{margin:g} of one): {rectangles}"
        )
    return index


def _given_volume(blocks: Sequence[Block], index: np.ndarray) -> float:
    """One particle's volume when the blocks hold given points: the blocks' volume over the
    number of points (the core takes one volume for all). ValueError when a block holds no
    point, or when the blocks are filled more than 10% more densely than one another (one
    volume would then give their particles the wrong mass)."""
    counts = np.bincount(index, minlength=len(blocks))
    areas = np.array([float(np.prod(b.size)) for b in blocks])
    if (empty := np.flatnonzero(counts == 0)).size:
        raise ValueError(f"block {int(empty[0])} ({blocks[int(empty[0])]}) holds no given point")
    each = areas / counts
    what = "area" if len(blocks[0].size) == 2 else "volume"
    if each.max() > 1.1 * each.min():
        raise ValueError(
            f"the blocks hold their given points at different densities ({what} per point "
            f"{', '.join(f'{a:.3g}' for a in each)}); one particle volume cannot fit them all"
        )
    return float(areas.sum() / counts.sum())


def particles(
    scene: MpmScene,
    seed: int | None = None,
    *,
    positions: np.ndarray | None = None,
    margin: float = 0.0,
) -> dict[str, Any]:
    """The initial particles of a scene: positions, velocities, material (index into
    materials), particle_type, the list of distinct materials and particle_volume.

    Without `positions` each block is a lattice of spacing scene.spacing (jittered by
    scene.jitter) and a particle's volume is spacing^D. With `positions` (N, D), the points
    are the particles, in their order, each with the material and velocity of the block whose
    box holds it (or lies within `margin` of it; ValueError naming the point and the blocks
    if none does), and the volume is the blocks' volume over the number of points: the
    data's, whatever the grid. Obstacles follow the blocks in both cases. Equal materials
    share an entry of materials, except Rigid: each rigid block is its own body, so its own
    entry."""
    spacing = scene.spacing
    dim = scene.dim
    rng = np.random.default_rng(seed)
    materials: list[Material] = []
    material_of: list[int] = []  # per block, its index into materials
    for block in scene.blocks:
        if isinstance(block.material, Rigid) or block.material not in materials:
            materials.append(block.material)
        material_of.append(
            len(materials) - 1
            if isinstance(block.material, Rigid)
            else materials.index(block.material)
        )
    x, v, mat, types = [], [], [], []
    if positions is not None:
        points = np.asarray(positions, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != dim or not len(points):
            raise ValueError(
                f"given positions must be (N, {dim}) with N > 0 for the scene's {dim}D blocks, "
                f"got {points.shape}"
            )
        if not np.isfinite(points).all():
            raise ValueError("given positions hold non-finite values")
        block_of = _block_of_each(scene.blocks, points, margin)
        volume = _given_volume(scene.blocks, block_of)
        x.append(points)
        v.append(np.array([scene.blocks[k].velocity for k in block_of], dtype=np.float64))
        mat.append(np.array([material_of[k] for k in block_of]))
        types.append(np.array([scene.blocks[k].material.particle_type for k in block_of]))
    else:
        volume = spacing**dim
        for k, block in enumerate(scene.blocks):
            points = lattice(block.lower, block.size, spacing)
            if scene.jitter:
                points = points + rng.uniform(-0.5, 0.5, points.shape) * scene.jitter * spacing
            x.append(points)
            v.append(np.tile(np.asarray(block.velocity, float), (len(points), 1)))
            mat.append(np.full(len(points), material_of[k]))
            types.append(np.full(len(points), block.material.particle_type))
    if scene.obstacles:
        index = len(materials)
        for segment in scene.obstacles:
            points = _segment_points(segment, spacing)
            x.append(points)
            v.append(np.zeros_like(points))
            mat.append(np.full(len(points), index))
            types.append(np.full(len(points), OBSTACLE_TYPE))
    if not x:
        raise ValueError("the scene has no blocks and no obstacles")
    return {
        "positions": np.ascontiguousarray(np.concatenate(x), dtype=np.float64),
        "velocities": np.ascontiguousarray(np.concatenate(v), dtype=np.float64),
        "material": np.concatenate(mat).astype(np.uint32),
        "particle_type": np.concatenate(types).astype(np.int64),
        "materials": materials,
        "particle_volume": volume,
    }


def _frame_threads() -> Callable[[float], int] | None:
    """For mpm_simulate's threads: the thread count of each next frame, chosen by timing the
    frames: 0 (all of rayon's) or 1. None when there is nothing to choose."""
    if os.environ.get("RAYON_NUM_THREADS") or (os.cpu_count() or 1) == 1:
        return None
    tuner = StepTuner([0, 1], lambda threads: None)
    tuner.begin()  # the first frame runs on all threads

    def after_frame(seconds: float) -> int:
        tuner.end(seconds)
        return tuner.begin()

    return after_frame


def simulate(
    scene: MpmScene,
    frames: int,
    *,
    seed: int | None = None,
    positions: np.ndarray | None = None,
    margin: float = 0.0,
    progress: Callable[[int], object] | None = None,
) -> MpmResult:
    """Run `scene` for `frames` frames (frame 0 the initial state), its blocks filled with the
    lattice or with the given `positions` (N, D) (see `particles`; `margin`: how far outside
    its block's box a given point may lie). A run that produces NaN,
    loses a particle out of the domain or needs more than max_substeps in a frame raises
    ValueError naming the frame. `progress(frame)` is called after every frame.

    Each frame runs on all of rayon's threads or on one, whichever the frames run faster on
    (gns.threads.StepTuner): with another program on one core, waiting for the pool's second
    thread made sand frames 2-2.5x slower than one thread (benches/mpm.py on 2 cores). The
    positions do not depend on it; RAYON_NUM_THREADS in the environment fixes the pool.

    With scene.shake the run is in the container's frame (positions there, walls at rest) under
    gravity - a_c(t), and the result's context is the container's motion per frame (frames,
    3 D): position, velocity and acceleration at t = frame * frame_dt."""
    start = particles(scene, seed, positions=positions, margin=margin)
    core_materials = [m.core() for m in start["materials"]]
    if scene.obstacles:
        core_materials.append(("obstacle", 0.0, []))
    positions, seconds, substeps = _core.mpm_simulate(
        start["positions"],
        start["velocities"],
        start["material"],
        core_materials,
        start["particle_volume"],
        frames,
        grid=scene.grid,
        bounds=[list(b) for b in scene.bounds or ()],
        wall=scene.wall,
        wall_friction=scene.wall_friction,
        gravity=list(scene.gravity or ()),
        frame_dt=scene.frame_dt,
        cfl=scene.cfl,
        max_substeps=scene.max_substeps,
        progress=progress,
        threads=_frame_threads(),
        frame_gravity=None if scene.shake is None else _shaken_gravity(scene, frames),
    )
    context: np.ndarray | None = None
    if scene.shake is not None:
        times = np.arange(frames) * scene.frame_dt
        context = scene.shake.context(times, scene.dim).astype(np.float32)
    elif scene.context is not None:
        context = np.asarray(scene.context, np.float32)
    return MpmResult(positions, start["particle_type"], seconds, substeps, context)


def _shaken_gravity(scene: MpmScene, frames: int) -> np.ndarray:
    """(frames - 1, D) the gravity of each frame in the shaken container's frame, gravity -
    a_c. a_c is taken at the middle of the frame and held over its substeps: by the midpoint
    rule the frame's change of velocity is the integral of -a_c over the frame to a relative
    (omega frame_dt)^2 / 24 (1.6e-4 at 4 Hz), and the core needs no notion of a shake.
    """
    assert scene.shake is not None and scene.gravity is not None
    middle = (np.arange(frames - 1) + 0.5) * scene.frame_dt
    rows = np.tile(np.asarray(scene.gravity, np.float64), (frames - 1, 1))
    rows[:, scene.shake.axis] -= scene.shake.acceleration(middle)
    return np.ascontiguousarray(rows)
