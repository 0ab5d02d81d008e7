"""The scenes `gns generate` draws: presets rng -> (MpmScene, frames), `frames` counting frame 0,
so that a preset's sequence_length is the paper's (WaterDrop 1000, Sand 320, Goop 400,
WaterRamps 600, MultiMaterial 1000, FluidShake 2000, FluidShake-Box 1500, RandomFloor 600;
SAND-3D 350, GOOP-3D 300, BOXBATH 150).

2D (docs/reference-simulator.md):
  waterdrop      one block of water at rest, width U(0.1, 0.3), height U(0.15, 0.35)
  water, sand, goop
                 1-3 non-overlapping blocks of side U(0.15, 0.3), velocity U(-2.5, 2.5) m/s per
                 axis (sand U(-4.5, 4.5): see SAND_SPEED)
  multimaterial  2-3 blocks of distinct materials among water, sand and goop
  ramps          water or sand blocks among 1-3 static ramps (kinematic particles, type 3)
  waterramps, sandramps
                 the same with water only (600 frames) or sand only (400): WATERRAMPS, SANDRAMPS
  waterdrop-xl   waterdrop at 1.5 times the resolution, radius 0.01: WATERDROP-XL
  fluidshake     1-2 blocks of water at rest in a container shaken along x (amplitude
                 U(0.01, 0.04) m, frequency U(1, 4) Hz, phase U(0, 2 pi)), simulated and stored
                 in the container's frame, its position, velocity and acceleration the 6 global
                 features per frame: FLUIDSHAKE (2000 steps)
  fluidshake-box the same with a floating rigid 0.1 x 0.1 box (particle type 0) dropped onto
                 deeper water (blocks of side U(0.28, 0.36), so that the box floats clear of
                 the floor): FLUIDSHAKE-BOX (1500 steps)
  randomfloor    water blocks thrown above a random rough floor from wall to wall (a polyline
                 of 4-8 static segments, kinematic particles): RANDOMFLOOR
  continuous     sand as above whose friction angle is drawn per trajectory from 1-80 degrees,
                 30-55 held out of the train split (the metadata says so), stored as the global
                 feature tan(angle) (DeepMind's step_context): CONTINUOUS and its figure C.5
  sand-taichi    sand2d-taichi's scenes: one 0.2 x 0.2 sand block at rest or thrown at up to
                 1 m/s per axis, friction U(20, 45) degrees as in continuous, 350 frames, at
                 that dataset's own resolution (grid 64, 4 particles a cell)
  sand-taichi-floor
                 the same with the block's lower edge at most 0.05 above the floor (a short
                 drop, then a collapse): the regime sand-taichi draws in 1 trajectory of 13
  sand-taichi-throw
                 the same block thrown up at U(0.5, 1.5) m/s to turn 0.25-0.5 above the floor:
                 free flight and the top of a throw far from the walls (in 1 window of 300
                 of sand-taichi's), then a landing from height
3D (y up, gravity along -y, as in 2D; RESOLUTION_3D):
  water-3d, sand-3d, goop-3d
                 1-3 blocks of side U(0.15, 0.25) thrown as their 2D twins, starting at least
                 FLOOR_GAP_3D above the floor; water at 5 ms frames (the paper's WATER-3D)
  boxbath        a rigid cube (particle type 0) dropped into a pool of water in a smaller
                 container, 1/60 s frames: about the paper's 1k particles
All 2D presets but sand-taichi share one resolution (RESOLUTION: lattice spacing 0.01, grid dx
0.025), chosen with `sand`'s speed so that waterdrop and sand match the paper's per-frame
statistics within a factor 1.5 (benches/mpm.py --calibrate).

`scale` (gns generate --scale) multiplies a scene's particles by about that factor: the grid
and the lattice become finer by scale^(1/D) (particles per cell kept) and the connectivity
radius shrinks with the lattice spacing, so a particle keeps its number of neighbours. The
3D presets at scale 1 hold 1-3 k particles (minutes for a dataset on 2 cores); about 5 gives
the paper's 5-20 k.

Reproducibility: trajectory i of a split is drawn from SeedSequence(seed, spawn_key=(split,
i, draw)), so a dataset depends on the seed and the arguments only, never on the number of
workers or on the order trajectories finish in.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from gns import mpm
from gns.mpm import Block, Goop, MpmScene, Rigid, Sand, Segment, Shake, Water

__all__ = [
    "PRESETS",
    "SPLITS",
    "connectivity_radius",
    "preset_scene",
    "trajectory_seed",
]

SPLITS = ("train", "valid", "test")
# The paper's 2D connectivity radius: about 7 neighbours at the lattice spacing 0.01 below.
CONNECTIVITY_RADIUS = 0.015

# Where blocks may start: the walls (MpmScene's default bounds) less a margin, so no particle
# starts on a wall node, and a gap between blocks so that they start apart.
WALLS = ((0.1, 0.9), (0.1, 0.9))
WALLS_3D = WALLS + ((0.1, 0.9),)
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

Box = tuple[tuple[float, ...], tuple[float, ...]]  # (lower, size), one value per axis
Preset = Callable[[np.random.Generator], tuple[MpmScene, int]]


# ----------------------------------------------------------------------------------- placement


def _overlaps(a: Box, b: Box, gap: float) -> bool:
    return all(
        lo_a < lo_b + s_b + gap and lo_b < lo_a + s_a + gap
        for lo_a, s_a, lo_b, s_b in zip(a[0], a[1], b[0], b[1], strict=True)
    )


def _inside(points: np.ndarray, box: Box, gap: float) -> bool:
    lower, size = np.asarray(box[0]), np.asarray(box[1])
    near = (points > lower - gap) & (points < lower + size + gap)
    return bool(np.any(np.all(near, axis=1)))


def place_blocks(
    rng: np.random.Generator,
    sizes: np.ndarray,
    keep_out: np.ndarray | None = None,
    keep_out_gap: float = GAP,
    attempts: int = 200,
    walls: Sequence[tuple[float, float]] = WALLS,
    floor_gap: float = MARGIN,
) -> list[Box]:
    """Non-overlapping boxes of the given (k, D) sizes inside the walls (MARGIN from each,
    `floor_gap` above the floor, axis 1's lower wall), GAP apart and `keep_out_gap` clear of
    the `keep_out` points. Sizes shrink by 10% until they fit. Corners are drawn axis by axis,
    x first."""
    walls = walls[: sizes.shape[1]]
    lo = [w[0] + (floor_gap if a == 1 else MARGIN) for a, w in enumerate(walls)]
    scale = 1.0
    for _ in range(30):
        placed: list[Box] = []
        for size in sizes * scale:
            hi = [w[1] - MARGIN - s for w, s in zip(walls, size, strict=True)]
            if any(h <= low for h, low in zip(hi, lo, strict=True)):
                break
            for _ in range(attempts):
                box = (tuple(rng.uniform(low, h) for low, h in zip(lo, hi, strict=True)), size)
                if any(_overlaps(box, other, GAP) for other in placed):
                    continue
                if keep_out is not None and _inside(keep_out, box, keep_out_gap):
                    continue
                placed.append(box)
                break
            else:
                break
        if len(placed) == len(sizes):
            return [
                (tuple(float(c) for c in lower), tuple(float(s) for s in size))
                for lower, size in placed
            ]
        scale *= 0.9
    raise ValueError(f"cannot place blocks of sizes {sizes.tolist()} without overlap")


def _blocks(
    rng: np.random.Generator,
    materials: Sequence[mpm.Material],
    speed: float,
    keep_out: np.ndarray | None = None,
    gap: float = GAP,
    dim: int = 2,
    side: tuple[float, float] = SIDE,
    floor_gap: float = MARGIN,
    walls: Sequence[tuple[float, float]] | None = None,
) -> list[Block]:
    """Blocks of side U(side) of the given materials, velocity U(-speed, speed) per axis,
    inside `walls` (default the scene's)."""
    sizes = rng.uniform(side[0], side[1], (len(materials), dim))
    walls = WALLS_3D[:dim] if walls is None else walls
    boxes = place_blocks(rng, sizes, keep_out, gap, walls=walls, floor_gap=floor_gap)
    velocities = rng.uniform(-speed, speed, (len(materials), dim))
    return [
        Block(m, lower=lower, size=size, velocity=tuple(float(c) for c in v))
        for m, (lower, size), v in zip(materials, boxes, velocities, strict=True)
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


def _ramps(
    rng: np.random.Generator, material: mpm.Material | None, frames: int
) -> tuple[MpmScene, int]:
    """Blocks among 1-3 static ramps, of `material` or (None) water or sand drawn at random."""
    empty = _scene([])
    segments = random_ramps(rng, _count(rng), empty.spacing)
    if material is None:
        material = Water() if rng.random() < 0.5 else Sand()
    # Obstacle particles make the 3 x 3 grid nodes around them sticky: blocks keep clear of
    # those nodes too, or they would start stuck.
    probe = mpm.particles(_scene([], obstacles=segments))["positions"]
    gap = GAP + 2 / empty.grid
    blocks = _blocks(rng, [material] * _count(rng), SPEED, probe, gap)
    return _scene(blocks, obstacles=segments), frames


def ramps(rng: np.random.Generator) -> tuple[MpmScene, int]:
    """Water or sand blocks (drawn per trajectory) among 1-3 static ramps."""
    return _ramps(rng, None, 601)


def waterramps(rng: np.random.Generator) -> tuple[MpmScene, int]:
    """Water blocks among 1-3 static ramps, 600 frames: WATERRAMPS."""
    return _ramps(rng, Water(), 601)


def sandramps(rng: np.random.Generator) -> tuple[MpmScene, int]:
    """Sand blocks among 1-3 static ramps, 400 frames: SANDRAMPS."""
    return _ramps(rng, Sand(), 401)


def waterdrop_xl(rng: np.random.Generator) -> tuple[MpmScene, int]:
    """WaterDrop at 1.5 times the resolution (2.25 times the particles, radius 0.01, the
    paper's WATERDROP-XL's)."""
    scene, frames = waterdrop(rng)
    return dataclasses.replace(scene, grid=60), frames


# FLUIDSHAKE: the container's displacement along x is amplitude sin(2 pi f t + phase), drawn per
# trajectory. At 0.04 m and 4 Hz it accelerates at up to 25 m/s^2, 2.6 g.
SHAKE_AMPLITUDE = (0.01, 0.04)
SHAKE_FREQUENCY_HZ = (1.0, 4.0)
# The 6 global features of the shake presets, as simulate gives them (Shake.context).
SHAKE_CONTEXT = [
    "container_x",
    "container_y",
    "container_vx",
    "container_vy",
    "container_ax",
    "container_ay",
]
SHAKE_METADATA: dict[str, Any] = {
    "context": SHAKE_CONTEXT,
    "context_units": ["m", "m", "m/s", "m/s", "m/s^2", "m/s^2"],
    "frame": "container",
    "shake_amplitude_m": list(SHAKE_AMPLITUDE),
    "shake_frequency_hz": list(SHAKE_FREQUENCY_HZ),
}
# FLUIDSHAKE-BOX's box: a 0.1 x 0.1 rigid body of half the water's density (Rigid's default).
SHAKE_BOX = 0.1
# The water of fluidshake-box starts below this height and the box above the water.
SHAKE_BOX_WATER_TOP = 0.65
# fluidshake-box's water blocks are larger than SIDE: the box floats tilted, corner down (a
# square at half the water's density does), and needs about 0.07 m of water. With SIDE the pool
# was 0.04-0.13 deep and the box lay on the floor in 5 of 8 draws; with these sides (0.87-2.0 k
# water particles, the paper's FLUIDSHAKE-BOX has 1.5 k) it floated clear of the floor from
# step 200 to 1500 in 12 of 12 draws.
SHAKE_BOX_WATER_SIDE = (0.28, 0.36)


def _shake(rng: np.random.Generator) -> Shake:
    """The container's motion along x: amplitude, frequency and phase drawn uniformly."""
    return Shake(
        amplitude=float(rng.uniform(*SHAKE_AMPLITUDE)),
        frequency_hz=float(rng.uniform(*SHAKE_FREQUENCY_HZ)),
        phase=float(rng.uniform(0.0, 2.0 * math.pi)),
        axis=0,
    )


def fluidshake(rng: np.random.Generator) -> tuple[MpmScene, int]:
    """1-2 blocks of water in a container shaken along x, 2000 steps: FLUIDSHAKE. The blocks
    start at rest in the container, so that the shaking is what moves the water; positions are
    in the container's frame."""
    blocks = _blocks(rng, [Water()] * _count(rng, 1, 2), 0.0)
    return _scene(blocks, shake=_shake(rng)), 2001


def fluidshake_box(rng: np.random.Generator) -> tuple[MpmScene, int]:
    """fluidshake with a rigid 0.1 x 0.1 box (half water's density: it floats) dropped onto
    the water: the water starts below SHAKE_BOX_WATER_TOP, the box GAP above the highest
    block, anywhere across; 1500 steps: FLUIDSHAKE-BOX."""
    lower_walls = (WALLS[0], (WALLS[1][0], SHAKE_BOX_WATER_TOP))
    waters = [Water()] * _count(rng, 1, 2)
    water = _blocks(rng, waters, 0.0, walls=lower_walls, side=SHAKE_BOX_WATER_SIDE)
    top = max(b.lower[1] + b.size[1] for b in water)
    x = rng.uniform(WALLS[0][0] + MARGIN, WALLS[0][1] - MARGIN - SHAKE_BOX)
    y = rng.uniform(top + GAP, WALLS[1][1] - MARGIN - SHAKE_BOX)
    box = Block(Rigid(), (float(x), float(y)), (SHAKE_BOX, SHAKE_BOX))
    return _scene([*water, box], shake=_shake(rng)), 1501


# RANDOMFLOOR's floor: its vertices are at most this high, which leaves 0.5 above it for 1-3
# blocks of SIDE (GAP and the sticky nodes' 2 cells below them).
FLOOR_HIGH = 0.3


def random_floor(rng: np.random.Generator, spacing: float) -> list[Segment]:
    """A rough floor: a polyline of 4-8 segments whose vertices are evenly spaced in x from the
    left wall to the right one, at heights from the container's floor plus a clearance (as
    random_ramps keeps ramps clear of the walls: MARGIN and the particles' rows below the
    segment, 2 spacings) up to FLOOR_HIGH. It ends on the side walls: a gap of one grid node
    between its end and a wall would let water through (a particle there takes the free
    node's velocity with weight 3/4) and under the floor."""
    count = _count(rng, 4, 8)
    x = np.linspace(WALLS[0][0], WALLS[0][1], count + 1)
    y = rng.uniform(WALLS[1][0] + MARGIN + 2 * spacing, FLOOR_HIGH, count + 1)
    return [
        Segment((float(x[k]), float(y[k])), (float(x[k + 1]), float(y[k + 1])))
        for k in range(count)
    ]


def randomfloor(rng: np.random.Generator) -> tuple[MpmScene, int]:
    """1-3 blocks of water thrown (as `water`) above a random rough floor (random_floor),
    600 steps: RANDOMFLOOR."""
    floor = random_floor(rng, _scene([]).spacing)
    top = max(max(s.start[1], s.end[1]) for s in floor)
    # Above the floor's highest vertex, clear of the grid nodes its particles make sticky.
    above = (WALLS[0], (top, WALLS[1][1]))
    gap = GAP + 2 / _scene([]).grid
    blocks = _blocks(rng, [Water()] * _count(rng), SPEED, walls=above, floor_gap=gap)
    return _scene(blocks, obstacles=floor), 601


# CONTINUOUS (the paper's C.5): friction angles 0-80 degrees, with 30-55 held out of the train
# split to test interpolation; valid and test draw from the whole range. 1, not 0: the
# simulator's Drucker-Prager needs an angle above 0.
CONTINUOUS_ANGLES = (1.0, 80.0)
HELD_OUT_ANGLES = (30.0, 55.0)


def continuous(rng: np.random.Generator, split: str = "train") -> tuple[MpmScene, int]:
    """Sand with one friction angle per trajectory, in CONTINUOUS_ANGLES but outside
    HELD_OUT_ANGLES in the train split, given to the model as tan(angle), the Mohr-Coulomb
    friction coefficient (as sand2d-taichi's material_property)."""
    (lo, hi), (out_lo, out_hi) = CONTINUOUS_ANGLES, HELD_OUT_ANGLES
    if split == "train":
        # Uniform over the two bands: a draw over their joint width, then placed.
        u = float(rng.uniform(0.0, (out_lo - lo) + (hi - out_hi)))
        angle = lo + u if u < out_lo - lo else out_hi + (u - (out_lo - lo))
    else:
        angle = float(rng.uniform(lo, hi))
    blocks = _blocks(rng, [Sand(friction_angle_deg=angle)] * _count(rng), SAND_SPEED)
    return _scene(blocks, context=[math.tan(math.radians(angle))]), 401


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
    return _taichi_block(rng, WALLS[1][1] - MARGIN / 4 - TAICHI_SIDE), TAICHI_FRAMES


# sand-taichi-floor's blocks start with their lower edge at most this far above the floor.
TAICHI_FLOOR_GAP = 0.05


def sand_taichi_floor(rng: np.random.Generator) -> tuple[MpmScene, int]:
    """sand-taichi's block with its lower edge 0.005-0.05 above the floor: a short drop, then a
    collapse under its own weight (sand2d-taichi's sand_04, 13, 33), a regime that sand-taichi
    draws in 1 trajectory of 13 and its models brake (docs/probes.md)."""
    return _taichi_block(rng, WALLS[1][0] + TAICHI_FLOOR_GAP), TAICHI_FRAMES


# sand-taichi-throw: where the block's lower edge turns (0.25-0.5 above the floor, its top at
# least 0.1 below the ceiling), how fast it is thrown up, and its corner's x range and sideways
# speed (the block turns inside the side walls, at most 0.08 m from where it started).
THROW_APEX = (0.35, 0.6)
THROW_UP = (0.5, 1.5)
THROW_X = (0.2, 0.6)
THROW_SIDEWAYS = 0.5


def sand_taichi_throw(rng: np.random.Generator) -> tuple[MpmScene, int]:
    """sand-taichi's block thrown upwards to turn high in the box: free flight and the top of a
    throw, which the free-fall probe asks of a model (docs/probes.md), then a landing from up
    to 0.5 m."""
    angle = float(rng.uniform(20.0, 45.0))
    up = float(rng.uniform(*THROW_UP))
    apex = float(rng.uniform(*THROW_APEX))
    sideways = float(rng.uniform(-THROW_SIDEWAYS, THROW_SIDEWAYS))
    lower = (float(rng.uniform(*THROW_X)), apex - up**2 / (2 * mpm.DEFAULT_GRAVITY))
    block = Block(
        Sand(friction_angle_deg=angle),
        lower=lower,
        size=(TAICHI_SIDE, TAICHI_SIDE),
        velocity=(sideways, up),
    )
    return MpmScene([block], context=[math.tan(math.radians(angle))]), TAICHI_FRAMES


def _taichi_block(rng: np.random.Generator, top: float) -> MpmScene:
    """The block anywhere in x, its lower edge at most `top` high, at rest or (half the draws)
    thrown at U(-1, 1) m/s per axis."""
    angle = float(rng.uniform(20.0, 45.0))
    # 0.005 inside the walls: Taichi's blocks come as close as 0.101.
    lo, hi = WALLS[0][0] + MARGIN / 4, WALLS[0][1] - MARGIN / 4 - TAICHI_SIDE
    lower = rng.uniform((lo, lo), (hi, top))
    thrown = rng.random() < 0.5
    velocity = rng.uniform(-TAICHI_SPEED, TAICHI_SPEED, 2) if thrown else np.zeros(2)
    block = Block(
        Sand(friction_angle_deg=angle),
        lower=(float(lower[0]), float(lower[1])),
        size=(TAICHI_SIDE, TAICHI_SIDE),
        velocity=(float(velocity[0]), float(velocity[1])),
    )
    return MpmScene([block], context=[math.tan(math.radians(angle))])


# ------------------------------------------------------------------------------------------ 3D

# The 3D presets' resolution at scale 1: grid dx 1/24 and 8 particles a cell (2 a side), so a
# lattice spacing of 1/48 and about 1000 particles in a block of side 0.2. A 3D grid costs the
# cube of its resolution, so the 2D presets' dx 0.025 would cost 5 times as many nodes.
RESOLUTION_3D: dict[str, Any] = {"grid": 24, "particles_per_cell": 8.0}
# 1.5 lattice spacings: the 18 nearest lattice points (6 at one spacing, 12 at sqrt 2), in
# the paper's 10-20 neighbours, as its 3D radii (0.025-0.035) are at its finer resolutions.
RADIUS_3D = 1.5 / 48
SIDE_3D = (0.15, 0.25)
# Blocks start this high above the floor (not MARGIN): a block thrown down at 2.5 m/s falls
# 0.025 in its first 10 ms, and the first frames are free fall, which tests check against g.
FLOOR_GAP_3D = 0.06


def _scene_3d(blocks: Sequence[Block], **settings: Any) -> MpmScene:
    return MpmScene(blocks, **{**RESOLUTION_3D, **settings})


def water_3d(rng: np.random.Generator) -> tuple[MpmScene, int]:
    """1-3 blocks of water thrown in random directions, 5 ms frames: WATER-3D (whose 800
    frames of 5 ms the paper made with SPH)."""
    blocks = _blocks(
        rng, [Water()] * _count(rng), SPEED, dim=3, side=SIDE_3D, floor_gap=FLOOR_GAP_3D
    )
    return _scene_3d(blocks, frame_dt=0.005), 801


def sand_3d(rng: np.random.Generator) -> tuple[MpmScene, int]:
    """1-3 blocks of sand (friction angle 30 degrees) thrown in random directions: SAND-3D."""
    blocks = _blocks(
        rng, [Sand()] * _count(rng), SAND_SPEED, dim=3, side=SIDE_3D, floor_gap=FLOOR_GAP_3D
    )
    return _scene_3d(blocks), 351


def goop_3d(rng: np.random.Generator) -> tuple[MpmScene, int]:
    """1-3 blocks of goop thrown in random directions: GOOP-3D."""
    blocks = _blocks(
        rng, [Goop()] * _count(rng), SPEED, dim=3, side=SIDE_3D, floor_gap=FLOOR_GAP_3D
    )
    return _scene_3d(blocks), 301


# BOXBATH (the paper's, from Li et al. 2019, made with FleX: 960 water and 64 box particles,
# 150 frames of 1/60 s): a container of 0.5 x 0.8 x 0.5 on a coarser grid (dx 1/16, spacing
# 1/32) so that the pool holds about 800-1600 particles and the cube 4 x 4 x 4.
# The walls must be 2 cells inside the domain: 0.125 at grid 16.
BOXBATH_WALLS = ((0.25, 0.75), (0.125, 0.875), (0.25, 0.75))
BOXBATH_RESOLUTION: dict[str, Any] = {"grid": 16, "particles_per_cell": 8.0}
BOXBATH_CUBE = 0.125
BOXBATH_RADIUS = 1.5 / 32


def boxbath(rng: np.random.Generator) -> tuple[MpmScene, int]:
    """A rigid cube (half water's density: it floats) dropped from U(0.45, 0.6) high, with a
    sideways velocity U(-1, 1) m/s, into a pool of water U(0.1, 0.2) deep that fills the
    container's floor: BOXBATH. The water starts at rest."""
    (x_lo, x_hi), (floor, _), (z_lo, z_hi) = BOXBATH_WALLS
    depth = float(rng.uniform(0.1, 0.2))
    pool = Block(Water(), (x_lo, floor, z_lo), (x_hi - x_lo, depth, z_hi - z_lo))
    side = BOXBATH_CUBE
    corner = (
        float(rng.uniform(x_lo + MARGIN, x_hi - MARGIN - side)),
        float(rng.uniform(0.45, 0.6)),
        float(rng.uniform(z_lo + MARGIN, z_hi - MARGIN - side)),
    )
    velocity = (float(rng.uniform(-1, 1)), 0.0, float(rng.uniform(-1, 1)))
    cube = Block(Rigid(), corner, (side,) * 3, velocity)
    scene = MpmScene([pool, cube], bounds=BOXBATH_WALLS, frame_dt=1 / 60, **BOXBATH_RESOLUTION)
    return scene, 151


PRESETS: dict[str, Preset] = {
    "waterdrop": waterdrop,
    "water": water,
    "sand": sand,
    "goop": goop,
    "multimaterial": multimaterial,
    "ramps": ramps,
    "waterramps": waterramps,
    "sandramps": sandramps,
    "waterdrop-xl": waterdrop_xl,
    "fluidshake": fluidshake,
    "fluidshake-box": fluidshake_box,
    "randomfloor": randomfloor,
    "continuous": continuous,
    "sand-taichi": sand_taichi,
    "sand-taichi-floor": sand_taichi_floor,
    "sand-taichi-throw": sand_taichi_throw,
    "water-3d": water_3d,
    "sand-3d": sand_3d,
    "goop-3d": goop_3d,
    "boxbath": boxbath,
}
# What a preset's metadata says about how it was drawn (gns generate writes it).
PRESET_METADATA: dict[str, dict[str, Any]] = {
    "continuous": {"held_out_friction_angle_deg": list(HELD_OUT_ANGLES), "held_out_of": "train"},
    "fluidshake": SHAKE_METADATA,
    "fluidshake-box": SHAKE_METADATA,
}
# Each preset's connectivity radius at scale 1 (CONNECTIVITY_RADIUS when not named).
RADIUS = {
    "waterdrop-xl": 0.01,
    "water-3d": RADIUS_3D,
    "sand-3d": RADIUS_3D,
    "goop-3d": RADIUS_3D,
    "boxbath": BOXBATH_RADIUS,
}


def trajectory_seed(seed: int, split: str, index: int, draw: int = 0) -> np.random.SeedSequence:
    """The seed of one draw of one trajectory: a function of these four values only."""
    return np.random.SeedSequence(seed, spawn_key=(SPLITS.index(split), index, draw))


def check_scale(scale: float) -> float:
    if (
        isinstance(scale, bool)
        or not isinstance(scale, (int, float))
        or not (math.isfinite(scale) and scale > 0)
    ):
        raise ValueError(
            f"scale must be a positive number (about that many times the particles), got {scale!r}"
        )
    return float(scale)


def _scaled(scene: MpmScene, scale: float) -> MpmScene:
    """The scene on a grid scale^(1/D) times finer, at the same particles per cell."""
    if scale == 1.0:
        return scene
    return dataclasses.replace(scene, grid=max(1, round(scene.grid * scale ** (1 / scene.dim))))


def preset_scene(
    preset: str,
    seed: int,
    split: str = "train",
    index: int = 0,
    draw: int = 0,
    scale: float = 1.0,
) -> tuple[MpmScene, int, int]:
    """(scene, frames, lattice seed) of one draw, exactly as `generate` makes it."""
    rng = np.random.default_rng(trajectory_seed(seed, split, index, draw))
    # Presets that draw differently per split (a held-out band) say so by name.
    scene, frames = continuous(rng, split) if preset == "continuous" else _preset(preset)(rng)
    return _scaled(scene, check_scale(scale)), frames, int(rng.integers(2**63))


def connectivity_radius(preset: str, scale: float = 1.0) -> float:
    """The preset's connectivity radius at `scale`: shrunk with the lattice spacing."""
    scene = preset_scene(preset, 0)[0]
    return (
        RADIUS.get(preset, CONNECTIVITY_RADIUS)
        * scene.grid
        / _scaled(scene, check_scale(scale)).grid
    )


def _preset(name: str) -> Preset:
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; expected one of {sorted(PRESETS)}")
    return PRESETS[name]
