"""Probes of what a particle model can see and has learned, cheap enough to run on every
candidate before a long training (docs/probes.md; scripts/free_fall_probe.py and
scripts/probe.py run them):

    fall_in_g         a block in free fall far from every wall: its predicted acceleration
                      over g (every real simulator: 1)
    falling_in_data   the same asked of the data's own free-falling particles, one step from
                      the truth's frames: truth and model by surface, speed and wall distance
    kick_removed      how much of a kick to one particle's last input velocity in that
                      block a model undoes in one step: 1 where it takes the kick for
                      noise (as training's target does), 0 where it takes it for motion
    shift_undone      how much of a shift of the particles (the same in every input frame,
                      e.g. squeeze_toward_floor's) a model undoes in one step: whether it
                      restores the packing a rollout has lost
    reach_by_hop      how strongly a particle's prediction depends on the inputs of the
                      particles k graph hops away: how far the network carries information
    floor_shift       how much moving the floor 1 m away changes the predictions, by height
                      above it: how far up a block the floor is seen
    landing_timeline  acceleration and density by height band through a block's landing,
                      the truth against the model's one-step predictions and its rollout
    spreading         the outward horizontal acceleration of a deposit's outer particles as it
                      spreads, the truth against the model's one-step predictions, and
    launch_and_braking  from it, the outward speed they gain up to its peak (a landing or a
                      collapse launches the front) and how hard they brake after it
    starts_near_floor whether a trajectory starts as a block just above the floor and slow:
                      the regime (a short drop, then a collapse) to probe on its own
    rest_by_height    one step of a settled pile from the truth's last frames: the
                      acceleration it predicts by height above the floor (the truth: 0); a
                      model that pushes a pile down sinks it into the floor over a rollout

Positions are (N, C + 1, D) histories, most recent last, as LearnedSimulator takes them.
Accelerations are in units of g per step^2 (g = 9.81 m/s^2 times dt^2), positive upwards, so
a block in free fall reads -1 and a landing a large positive number.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor

import gns.ops as ops
from gns.mpm import DEFAULT_GRAVITY, lattice
from gns.noise import random_walk
from gns.simulator import LearnedSimulator

GRAVITY = DEFAULT_GRAVITY  # m/s^2, along -y: the reference MPM's

__all__ = [
    "GRAVITY",
    "approach_by_height",
    "approach_to_floor",
    "block_history",
    "fall_in_g",
    "falling_frames",
    "falling_history",
    "falling_in_data",
    "floor_shift",
    "g_step",
    "height_bands",
    "hop_counts",
    "kick_removed",
    "landing_frame",
    "landing_timeline",
    "launch_and_braking",
    "neighbour_counts",
    "probe_block",
    "probe_inputs",
    "reach_by_hop",
    "rest_by_height",
    "shift_undone",
    "spreading",
    "squeeze_toward_floor",
    "starts_near_floor",
    "surface",
    "untrained_copy",
]


def block_history(
    block: np.ndarray, frames: int, g_step: float, last_velocity: float = 0.0
) -> np.ndarray:
    """(N, frames, D) positions of `block` (N, D) in free fall, at `block` in the last frame:
    y_k = y + u k - g k (k + 1) / 2 for k = -(frames - 1) ... 0, so every step's acceleration
    is -g and the last step's velocity (y_0 - y_-1) is u = `last_velocity` (per step; 0: the
    top of a throw upwards)."""
    k = np.arange(-(frames - 1), 1)
    rise = last_velocity * k - 0.5 * g_step * k * (k + 1)
    up = np.zeros(block.shape[1])
    up[1] = 1.0  # y is up, in 2D and 3D alike
    return np.stack([block + d * up for d in rise], axis=1)


def probe_block(scene: Any, size: float, spacing: float, where: str = "middle") -> np.ndarray:
    """(N, D) the probes' block: a cube (a square in 2D) lattice of `spacing`, `size` wide,
    centred across the box, its middle at the box's middle height ("middle") or its lowest
    layer half a spacing above the floor ("floor"). y (axis 1) is up, in 2D and 3D alike."""
    if where not in ("middle", "floor"):
        raise ValueError(f"where must be 'middle' or 'floor', got {where!r}")
    bounds = scene.bounds or ((0.0, 1.0),) * scene.dim
    corner = [(lo + hi - size) / 2 for lo, hi in bounds]
    if where == "floor":
        corner[1] = bounds[1][0]
    if any(c < lo or c + size > hi for c, (lo, hi) in zip(corner, bounds, strict=True)):
        raise ValueError(f"a block {size} wide does not fit the box {bounds}")
    return lattice(corner, (size,) * scene.dim, spacing)


def probe_inputs(
    simulator: Any, friction_angle: float = 30.0, particle_type: int | None = None
) -> tuple[Tensor | None, int]:
    """The step context and the particle type a probe gives a model: tan(friction angle)
    when the scene has a context of one value (sand2d-taichi's), and the scene's one free
    (not kinematic) type unless `particle_type` says which."""
    scene = simulator.scene
    if scene.context_size > 1:
        raise ValueError(f"the scene has a context of {scene.context_size} values; probes give 1")
    context = None
    if scene.context_size:
        context = torch.tensor([[math.tan(math.radians(friction_angle))]], dtype=torch.float32)
    if particle_type is None:
        free = [t for t in scene.particle_types if t not in scene.kinematic_particle_types]
        if len(free) != 1:
            raise ValueError(f"free particle types {free}; say which one the probe gives")
        particle_type = free[0]
    return context, particle_type


def g_step(simulator: Any) -> float:
    """g in position units per step^2: the model steps dt, the data's frame spacing."""
    if simulator.scene.dt is None:
        raise ValueError("the probe needs a model that records its step (scene.dt)")
    return GRAVITY * simulator.scene.dt**2


def _accelerations(
    simulator: Any,
    history: np.ndarray,
    particle_type: int,
    context: Tensor | None,
    noise: float = 0.0,
    draws: int = 1,
) -> np.ndarray:
    """(N, D) predicted accelerations, float64, of one step from `history` (N, C + 1, D): the
    prediction's second difference with the history as the model sees it (float32). noise >
    0: the model is given the history with random-walk noise of that std, as training gives
    it (gns.noise.random_walk), and its prediction, averaged over `draws` seeded draws, is
    differenced with the clean history."""
    given = torch.tensor(history, dtype=torch.float32)
    inputs = [given]
    if noise > 0:
        generator = torch.Generator().manual_seed(0)
        inputs = [given + random_walk(given, noise, generator=generator) for _ in range(draws)]
    types = torch.full((len(history),), particle_type)
    with torch.no_grad():
        following = np.mean(
            [
                simulator.predict_positions(x, types, context=context).double().numpy()
                for x in inputs
            ],
            axis=0,
        )
    seen = given.double().numpy()
    return following - 2 * seen[:, -1] + seen[:, -2]


def falling_history(simulator: Any, block: np.ndarray, speed: float) -> np.ndarray:
    """The model's C + 1 input frames of `block` in free fall, falling at `speed` m/s at the
    last (block_history at the model's step)."""
    frames = simulator.config.model.velocity_history + 1
    return block_history(block, frames, g_step(simulator), -speed * simulator.scene.dt)


def fall_in_g(
    simulator: Any,
    block: np.ndarray,
    context: Tensor | None,
    particle_type: int,
    speed: float = 0.0,
    noise: float = 0.0,
    draws: int = 32,
):
    """The block's vertical acceleration in one predicted step of free fall (throughout the
    input frames), over g: (mean, bottom row, top row); positive is downward. speed: how fast
    (m/s) the block falls at the last input frame; 0, the top of a throw, is the hardest case,
    where every input velocity is within a few g dt of rest. noise: the std of random-walk
    input noise as training adds it (gns.noise.random_walk); the acceleration is then taken
    against the clean history and averaged over `draws` draws (seeded): the mean of the
    training target is g in every row, so a model that has learned to undo its noise reads 1."""
    history = falling_history(simulator, block, speed)
    acceleration = _accelerations(simulator, history, particle_type, context, noise, draws)
    fall = -acceleration[:, 1] / g_step(simulator)
    y = block[:, 1]
    return fall.mean(), fall[y == y.min()].mean(), fall[y == y.max()].mean()


def kick_removed(
    simulator: Any,
    block: np.ndarray,
    context: Tensor | None,
    particle_type: int,
    kick: float,
    speed: float = 0.0,
) -> dict[str, tuple[float, float]]:
    """How much of a vertical kick of `kick` (position units per step) to the last input
    velocity of one particle of a block in free fall (as fall_in_g's) the model undoes in one
    step: the change of that particle's predicted vertical acceleration, against the fall
    without the kick, over -kick. One particle in the middle of each of the bottom, middle and
    top rows; for each, (out, in): kicked out of the block and into it (the middle row's:
    down, up). 1 undoes the kick, as training's target asks of its input noise; 0 keeps it,
    as motion."""
    if not (math.isfinite(kick) and kick > 0):
        raise ValueError(f"kick must be a finite number > 0, got {kick}")
    history = falling_history(simulator, block, speed)
    clean = _accelerations(simulator, history, particle_type, context)[:, 1]
    x, y = block[:, 0], block[:, 1]
    rows = {"bottom": y.min(), "middle": y[np.argmin(abs(y - np.median(y)))], "top": y.max()}
    removed = {}
    for name, height in rows.items():
        row = np.flatnonzero(y == height)
        i = row[np.argmin(abs(x[row] - np.median(x[row])))]
        out = 1.0 if name == "top" else -1.0
        pair = []
        for sign in (out, -out):
            kicked = history.copy()
            kicked[i, -1, 1] += sign * kick
            change = _accelerations(simulator, kicked, particle_type, context)[i, 1] - clean[i]
            pair.append(float(-change / (sign * kick)))
        removed[name] = (pair[0], pair[1])
    return removed


def squeeze_toward_floor(frame: np.ndarray, floor: float, factor: float) -> np.ndarray:
    """(N, D) the shift that squeezes `frame` (N, D) vertically towards `floor`: each
    particle's height above it (y, axis 1) times `factor` (> 0; below 1 packs the sand closer,
    as a rollout that loses volume does)."""
    if not (math.isfinite(factor) and factor > 0):
        raise ValueError(f"factor must be a finite number > 0, got {factor}")
    frame = np.asarray(frame, dtype=np.float64)
    shift = np.zeros_like(frame)
    shift[:, 1] = (factor - 1.0) * (frame[:, 1] - floor)
    return shift


def shift_undone(
    simulator: Any,
    history: np.ndarray,
    shift: np.ndarray,
    particle_type: Tensor,
    context: Tensor | None = None,
) -> float:
    """How much of `shift` (N, D), added to every input frame of `history` (N, C + 1, D) (the
    particles moved, their velocities kept), the model undoes in one step: with p and p' its
    predictions without and with the shift, -sum((p' - p - shift) . shift) / sum(shift .
    shift). 1 puts the particles back where they were; 0 carries the shift along, as a model
    that reads only velocities does. A model that restores the data's packing when a rollout
    squeezes its sand (squeeze_toward_floor) reads above 0."""
    history = np.asarray(history, dtype=np.float64)
    shift = np.asarray(shift, dtype=np.float64)
    if shift.shape != history[:, -1].shape:
        raise ValueError(f"shift must be {history[:, -1].shape}, got {shift.shape}")
    size = float((shift * shift).sum())
    if not (math.isfinite(size) and size > 0):
        raise ValueError(f"shift must be finite and not all zero, got a squared size of {size}")
    with torch.no_grad():
        p, moved = (
            simulator.predict_positions(
                torch.tensor(x, dtype=torch.float32), particle_type, context=context
            )
            .double()
            .numpy()
            for x in (history, history + shift[:, None])
        )
    return float(-((moved - p - shift) * shift).sum() / size)


# ---------------------------------------------------------------------------------- reach


def hop_counts(senders: np.ndarray, receivers: np.ndarray, n: int, targets: Sequence[int]):
    """(len(targets), n) int64: the fewest edges a message needs from each particle to each
    target (0 for the target itself, -1 where none arrives), along senders -> receivers."""
    senders, receivers = np.asarray(senders), np.asarray(receivers)
    order = np.argsort(receivers, kind="stable")
    into = np.searchsorted(receivers[order], np.arange(n + 1))  # edges into r: order[into[r]:]
    from_ = senders[order]
    hops = np.full((len(targets), n), -1, dtype=np.int64)
    for row, target in enumerate(targets):
        hops[row, target] = 0
        frontier, k = np.array([target]), 0
        while len(frontier):
            k += 1
            incoming = np.concatenate([from_[into[r] : into[r + 1]] for r in frontier])
            fresh = np.unique(incoming[hops[row, incoming] < 0])
            hops[row, fresh] = k
            frontier = fresh
    return hops


def reach_by_hop(
    simulator: Any,
    history: np.ndarray,
    particle_type: int,
    context: Tensor | None,
    targets: Sequence[int],
    max_hop: int = 8,
) -> dict[str, np.ndarray]:
    """How much the network's output at each target particle depends on the node inputs of
    particles k hops away, k = 0 ... max_hop.

    The sensitivity of target i to particle j is the 2-norm of d(output_i) / d(node features_j)
    (the Jacobian of the normalised acceleration, D rows, by particle j's normalised node
    features: velocities, wall distances, context, type). Returns "mean" (the mean sensitivity
    of a particle at hop k, over the targets' pairs, divided by that at hop 0), "total" (the
    sum over all the particles at hop k, divided by hop 0's) and "pairs" (how many (target,
    particle) pairs are at hop k). A network of M message-passing steps reaches exactly M hops:
    beyond, the sensitivity is 0.
    """
    given = torch.tensor(history, dtype=torch.float32)
    types = torch.full((len(history),), particle_type)
    with torch.no_grad():
        f = simulator.features(given, types, context=context)
    nodes = f["node_features"].detach().requires_grad_(True)
    output = simulator.model(
        nodes, f["edge_features"], f["senders"], f["receivers"], f["global_features"], None
    )
    hops = hop_counts(f["senders"].numpy(), f["receivers"].numpy(), len(history), targets)
    total, pairs = np.zeros(max_hop + 1), np.zeros(max_hop + 1)
    for row, target in enumerate(targets):
        squared = torch.zeros(len(history), dtype=torch.float64)
        for d in range(output.shape[1]):
            (grad,) = torch.autograd.grad(output[target, d], nodes, retain_graph=True)
            squared += grad.double().pow(2).sum(dim=1)
        sensitivity = squared.sqrt().numpy()
        for k in range(max_hop + 1):
            at_k = hops[row] == k
            total[k] += sensitivity[at_k].sum()
            pairs[k] += at_k.sum()
    mean = np.divide(total, pairs, out=np.zeros_like(total), where=pairs > 0)
    return {"mean": mean / mean[0], "total": total / total[0], "pairs": pairs}


def untrained_copy(
    simulator: Any,
    seed: int = 0,
    model: dict[str, Any] | None = None,
    scene: dict[str, Any] | None = None,
) -> Any:
    """The same architecture with its network drawn afresh (torch's default initialisation,
    seeded), or with the ModelConfig fields in `model` and the Scene fields in `scene`
    changed: what a design sees before training. The normalisers are the simulator's, so the
    inputs are scaled as the trained model's are."""
    config = simulator.config
    config = dataclasses.replace(config, model=dataclasses.replace(config.model, **(model or {})))
    torch.manual_seed(seed)
    fresh = LearnedSimulator(dataclasses.replace(simulator.scene, **(scene or {})), config)
    for name in ("velocity_normalizer", "acceleration_normalizer", "context_normalizer"):
        ours = getattr(simulator, name)
        if ours is not None:
            getattr(fresh, name).load_state_dict(ours.state_dict())
    return fresh.eval()


# ---------------------------------------------------------------------------------- floor


def floor_shift(
    simulator: Any,
    history: np.ndarray,
    particle_type: int,
    context: Tensor | None,
    shift: float = 1.0,
) -> np.ndarray:
    """(N,) how much each particle's predicted acceleration changes, in g (the 2-norm of the
    change), when the floor (the lower bound of y, axis 1) is moved `shift` further down: all
    that a particle learns of the floor, directly or through its neighbours."""
    scene = simulator.scene
    if scene.bounds is None or 1 not in scene.wall_axes:
        raise ValueError("the floor probe needs a model with wall features on the vertical axis")
    before = _accelerations(simulator, history, particle_type, context)
    bounds = [list(pair) for pair in scene.bounds]
    bounds[1][0] -= shift
    simulator.scene = dataclasses.replace(scene, bounds=tuple(map(tuple, bounds)))
    try:
        after = _accelerations(simulator, history, particle_type, context)
    finally:
        simulator.scene = scene
    return np.linalg.norm(after - before, axis=1) / g_step(simulator)


# ---------------------------------------------------------------------------------- landing


def height_bands(first_frame: np.ndarray, bands: int) -> np.ndarray:
    """(N,) band of each particle by its height in the first frame (N, D): 0 the lowest
    1/bands of the particles ... bands - 1 the highest. Bands follow the particles
    (Lagrangian), so a band's density is that of the same sand before and after it lands."""
    rank = np.argsort(np.argsort(first_frame[:, 1], kind="stable"), kind="stable")
    return rank * bands // len(first_frame)


def neighbour_counts(frame: np.ndarray, radius: float) -> np.ndarray:
    """(N,) how many other particles are within `radius` of each (Rust radius graph)."""
    edges = ops.radius_graph(np.asarray(frame, dtype=np.float64), radius, self_edges=False)
    return np.bincount(edges[1], minlength=len(frame)).astype(np.float64)


def surface(frame: np.ndarray, radius: float) -> np.ndarray:
    """(N,) where each particle of `frame` (N, D; y, axis 1, is up) sits in the sand: 1 on
    top (no other particle within `radius` in the 45-degree cone above it), -1 at the bottom
    (none in the cone below, some above), 0 inside. A particle alone is on top."""
    frame = np.asarray(frame, dtype=np.float64)
    senders, receivers = ops.radius_graph(frame, radius, self_edges=False)
    offset = frame[senders] - frame[receivers]
    up = offset[:, 1]
    across = np.linalg.norm(np.delete(offset, 1, axis=1), axis=1)
    above = np.bincount(receivers[(up > 0) & (across <= up)], minlength=len(frame)) > 0
    below = np.bincount(receivers[(up < 0) & (across <= -up)], minlength=len(frame)) > 0
    return np.where(~above, 1, np.where(~below, -1, 0))


def _falling(y: np.ndarray, g: float, history: int, tol: float) -> list[np.ndarray]:
    """[t]: the particles whose every vertical acceleration within frames t - history ... t -
    1 of y (T, N) is within tol g of free fall (empty for t < history)."""
    if history < 3:
        raise ValueError(f"history must be at least 3 frames (an acceleration), got {history}")
    acceleration = (y[2:] - 2 * y[1:-1] + y[:-2]) / g  # [k]: centred on frame k + 1, up positive
    none = np.zeros(0, dtype=np.int64)
    return [none] * history + [
        np.flatnonzero(np.all(np.abs(acceleration[t - history : t - 2] + 1) <= tol, axis=0))
        for t in range(history, len(y))
    ]


def falling_frames(truth: np.ndarray, g: float, history: int, tol: float = 0.1) -> list[int]:
    """The frames t of truth (T, N, D) at which falling_in_data takes a sample: those with a
    particle that fell within tol g of g through the `history` frames before t."""
    y = np.asarray(truth, dtype=np.float64)[:, :, 1]
    return [t for t, falling in enumerate(_falling(y, g, history, tol)) if len(falling)]


def falling_in_data(
    truth: np.ndarray,
    one_step: np.ndarray,
    g: float,
    history: int,
    bounds: np.ndarray,
    radius: float,
    tol: float = 0.1,
) -> dict[str, np.ndarray]:
    """The data's own free fall, one step: the particles of a trajectory that fall freely
    through the model's input frames, and the acceleration the truth and the model give them
    next. The synthetic block of fall_in_g asks the same on a lattice; this asks it where the
    data has it (the top of a throw, a block dropped, sand leaving a ledge).

    truth: (T, N, D) frames; one_step: (T, N, D) each frame predicted from the `history`
    frames of the truth before it (read only at falling_frames; NaN elsewhere will do). A
    sample is a frame t >= history and a particle whose every vertical acceleration within
    frames t - history ... t - 1 is within `tol` g of free fall. bounds (D, 2): the walls
    (-inf, inf on an axis without them); g: per step^2. Returns, per sample: "truth",
    "model" (the vertical acceleration of frame t over g, downward positive: free fall reads
    1), and of the last input frame "surface"
    (surface() at `radius`: 1 top, -1 bottom, 0 inside), "wall" (the distance to the nearest
    wall), "floor" (the height above the lower bound of y, the vertical axis) and "speed"
    (downward, per step)."""
    truth = np.asarray(truth, dtype=np.float64)
    one_step = np.asarray(one_step, dtype=np.float64)
    if truth.ndim != 3 or one_step.shape != truth.shape:
        raise ValueError(
            f"truth and one_step must be (T, N, D) alike, got {truth.shape}, {one_step.shape}"
        )
    bounds = np.asarray(bounds, dtype=np.float64)
    y = truth[:, :, 1]
    keys = ("truth", "model", "surface", "wall", "floor", "speed")
    samples: dict[str, list[np.ndarray]] = {key: [] for key in keys}
    for t, falling in enumerate(_falling(y, g, history, tol)):
        if len(falling) == 0:
            continue
        last = truth[t - 1, falling]
        samples["truth"].append(-(y[t, falling] - 2 * last[:, 1] + y[t - 2, falling]) / g)
        samples["model"].append(-(one_step[t, falling, 1] - 2 * last[:, 1] + y[t - 2, falling]) / g)
        samples["surface"].append(surface(truth[t - 1], radius)[falling])
        samples["wall"].append(np.minimum(last - bounds[:, 0], bounds[:, 1] - last).min(axis=1))
        samples["floor"].append(last[:, 1] - bounds[1, 0])
        samples["speed"].append(y[t - 2, falling] - last[:, 1])
    return {
        key: np.concatenate(v) if v else np.zeros(0, dtype=np.int64 if key == "surface" else float)
        for key, v in samples.items()
    }


def approach_to_floor(
    samples: dict[str, np.ndarray],
    within: float,
    min_speed: float,
    edges: Sequence[float],
    tol: float,
) -> list[dict[str, Any]]:
    """The samples of falling_in_data on their way to the floor: within `within` of it and
    faster than `min_speed` (per step), by steps of travel to it at their last input speed
    (height / speed; bins at `edges`) and place in the sand. A landing is a step or two of
    large deceleration; a model that brakes the steps before it, where the truth still falls
    at g, stops the sand early and packs what falls onto it.

    Returns a row per non-empty (bin, place), in bin then place (bottom, inside, top) order:
    "bin" (0 below edges[0] ... len(edges) above the last), "place" (-1, 0, 1), "samples",
    "kept" (the share the truth keeps falling, within tol of g), "model_kept" (the model's
    acceleration over g there) and "truth_rest" / "model_rest" (both for the others; NaN
    where none)."""
    r = samples
    approach = (r["floor"] < within) & (r["speed"] > min_speed)
    steps = np.digitize(r["floor"] / np.where(approach, r["speed"], 1.0), np.asarray(edges))
    kept = np.abs(r["truth"] - 1) <= tol
    rows = []
    for b in range(len(edges) + 1):
        for place in (-1, 0, 1):
            k = approach & (steps == b) & (r["surface"] == place)
            if not k.any():
                continue
            on, rest = k & kept, k & ~kept
            rows.append(
                {
                    "bin": b,
                    "place": place,
                    "samples": int(k.sum()),
                    "kept": float(on.sum() / k.sum()),
                    "model_kept": float(r["model"][on].mean()) if on.any() else math.nan,
                    "truth_rest": float(r["truth"][rest].mean()) if rest.any() else math.nan,
                    "model_rest": float(r["model"][rest].mean()) if rest.any() else math.nan,
                }
            )
    return rows


def approach_by_height(
    samples: dict[str, np.ndarray],
    place: int,
    height_edges: Sequence[float],
    speed_edges: Sequence[float],
    tol: float,
) -> list[dict[str, Any]]:
    """The samples of falling_in_data at one `place` (-1 bottom, 0 inside, 1 top) by height
    above the floor (bins at `height_edges`, the samples' units) and speed (per step, bins at
    `speed_edges`). Where a landing starts is a height: a model that brakes above it, where
    the truth falls on at every speed, has smoothed the landing's step over the heights above.

    Returns a row per non-empty (height bin, speed bin), in that order: "height", "speed"
    (bin indices as np.digitize's), "samples", "kept" (the share the truth keeps falling,
    within tol of g), "truth" and "model" (their mean acceleration over g)."""
    r = samples
    heights = np.digitize(r["floor"], np.asarray(height_edges))
    speeds = np.digitize(r["speed"], np.asarray(speed_edges))
    here = r["surface"] == place
    rows = []
    for h in range(len(height_edges) + 1):
        for v in range(len(speed_edges) + 1):
            k = here & (heights == h) & (speeds == v)
            if not k.any():
                continue
            rows.append(
                {
                    "height": h,
                    "speed": v,
                    "samples": int(k.sum()),
                    "kept": float(np.mean(np.abs(r["truth"][k] - 1) <= tol)),
                    "truth": float(r["truth"][k].mean()),
                    "model": float(r["model"][k].mean()),
                }
            )
    return rows


def landing_frame(accelerations: np.ndarray, band: np.ndarray, threshold: float) -> int | None:
    """The first frame at which the lowest band's mean upward acceleration (accelerations:
    (T, N) in g, positive up) exceeds `threshold` g, or None."""
    bottom = accelerations[:, band == 0].mean(axis=1)
    hits = np.flatnonzero(bottom > threshold)
    return int(hits[0]) if len(hits) else None


def landing_timeline(
    truth: np.ndarray,
    rollout: np.ndarray,
    one_step: np.ndarray,
    radius: float,
    g: float,
    *,
    bands: int = 3,
    threshold: float = 3.0,
    before: int = 3,
    after: int = 8,
) -> dict[str, Any]:
    """Acceleration and density by height band around the landing, the truth against a model.

    truth: (T, N, D) true positions at the model's step. rollout: (T, N, D) the model's
    rollout, whose first frames are the truth's (NaN where it has no frame). one_step: (T, N, D)
    the model's prediction of each frame t from the truth's frames before it (NaN where none).
    g: gravity per step^2. The landing is the first frame at which the lowest band's mean
    upward acceleration in the truth exceeds `threshold` g.

    Returns "landing" (the frame, or None), "frames" (landing - before ... landing + after,
    within the trajectory), and, each (frames, bands): "truth", "one_step" and "rollout" (the
    band's mean vertical acceleration in g at that frame: the acceleration that arrives at
    it, x_t - 2 x_{t-1} + x_{t-2}), "density_truth" and "density_rollout" (the band's mean
    number of neighbours within the radius). Two summaries: "stopping_truth" and
    "stopping_one_step", (bands,), each band's acceleration summed over the frames where the
    truth's exceeds `threshold` g (how much of the stop one step from the truth gives each
    height: the upper layers' share is what a model that cannot see the landing up the block
    lacks), and "density_ratio", the largest rollout / truth density of any band and frame
    (NaN once the rollout has no frame).
    """
    truth = np.asarray(truth, dtype=np.float64)
    band = height_bands(truth[0], bands)
    arriving = np.full(truth.shape[:2], np.nan)  # the acceleration that arrives at frame t
    arriving[2:] = (truth[2:, :, 1] - 2 * truth[1:-1, :, 1] + truth[:-2, :, 1]) / g
    landing = landing_frame(np.nan_to_num(arriving, nan=-np.inf), band, threshold)
    result: dict[str, Any] = {"landing": landing, "bands": bands}
    if landing is None:
        return result
    frames = np.arange(max(2, landing - before), min(len(truth), landing + after + 1))
    result["frames"] = frames

    def by_band(values: np.ndarray) -> np.ndarray:  # (N,) -> (bands,)
        return np.array([values[band == b].mean() for b in range(bands)])

    def arriving_at(predicted: np.ndarray, t: int, given: np.ndarray) -> np.ndarray:
        # Frame t of `predicted` against the two frames before it in `given`: the model's own
        # (a rollout) or the truth's (one step from the truth).
        return (predicted[t, :, 1] - 2 * given[t - 1, :, 1] + given[t - 2, :, 1]) / g

    rollout, one_step = np.asarray(rollout, np.float64), np.asarray(one_step, np.float64)
    names = ("truth", "one_step", "rollout", "density_truth", "density_rollout")
    rows: dict[str, list[np.ndarray]] = {name: [] for name in names}
    for t in frames:
        rows["truth"].append(by_band(arriving[t]))
        rows["one_step"].append(by_band(arriving_at(one_step, t, truth)))
        rows["rollout"].append(by_band(arriving_at(rollout, t, rollout)))
        rows["density_truth"].append(by_band(neighbour_counts(truth[t], radius)))
        finite = np.isfinite(rollout[t]).all()
        density = by_band(neighbour_counts(rollout[t], radius)) if finite else np.nan
        rows["density_rollout"].append(np.broadcast_to(density, (bands,)))
    result.update({k: np.array(v) for k, v in rows.items()})
    stopping = result["truth"] > threshold
    result["stopping_truth"] = np.where(stopping, result["truth"], 0.0).sum(axis=0)
    result["stopping_one_step"] = np.where(stopping, result["one_step"], 0.0).sum(axis=0)
    result["density_ratio"] = (result["density_rollout"] / result["density_truth"]).max()
    return result


# ---------------------------------------------------------------------------------- spreading


def spreading(
    truth: np.ndarray, one_step: np.ndarray, g: float, outer: float = 0.2
) -> dict[str, np.ndarray]:
    """The outward horizontal acceleration of the outer particles, frame by frame.

    truth: (T, N, D) true positions at the model's step; one_step: (T, N, D) the model's
    prediction of each frame t from the truth's frames before it (NaN where none). At each
    frame t >= 2, the outer particles are the `outer` fraction farthest in x (axis 0) from
    the mean x of frame t - 1; "outward" is away from that mean. Returns, each (T,) and NaN
    for t < 2: "truth" and "one_step", the outer particles' mean outward acceleration that
    arrives at t (x_t - 2 x_{t-1} + x_{t-2}, over g; negative: braking), and "speed" their
    mean outward velocity at t - 1 (x_{t-1} - x_{t-2}, per step).
    """
    truth = np.asarray(truth, dtype=np.float64)
    one_step = np.asarray(one_step, dtype=np.float64)
    if truth.ndim != 3 or truth.shape != one_step.shape:
        raise ValueError(
            f"truth and one_step must be the same (T, N, D), got {truth.shape} and {one_step.shape}"
        )
    if not 0.0 < outer <= 1.0:
        raise ValueError(f"outer must be a fraction in (0, 1], got {outer}")
    rows = {name: np.full(len(truth), np.nan) for name in ("truth", "one_step", "speed")}
    x, ours = truth[..., 0], one_step[..., 0]
    for t in range(2, len(truth)):
        away = x[t - 1] - x[t - 1].mean()
        chosen = np.abs(away) >= np.quantile(np.abs(away), 1.0 - outer)
        sign = np.sign(away[chosen])
        coasting = 2 * x[t - 1, chosen] - x[t - 2, chosen]  # at frame t at constant velocity
        rows["truth"][t] = np.mean((x[t, chosen] - coasting) * sign) / g
        rows["one_step"][t] = np.mean((ours[t, chosen] - coasting) * sign) / g
        rows["speed"][t] = np.mean((x[t - 1, chosen] - x[t - 2, chosen]) * sign)
    return rows


def launch_and_braking(rows: dict[str, np.ndarray], flowing: float) -> dict[str, float]:
    """Split a `spreading` record at the outer particles' peak outward speed.

    rows: what `spreading` returns; flowing: a speed (per step) above which they count as
    flowing. The peak is the frame of the largest "speed" among the frames with a one-step
    prediction. Returns "peak" (that frame), "peak_speed" (per step), "launch_truth" and
    "launch_one_step" (the outward accelerations, in g, summed over the frames from the first
    with a prediction up to the peak: the speed gained, in g steps, by the truth and by the
    model from the truth's frames), and "braking_truth" and "braking_one_step" (their mean
    after the peak over the frames faster than `flowing`; NaN if none).
    """
    predicted = np.flatnonzero(np.isfinite(rows["one_step"]))
    if len(predicted) == 0:
        raise ValueError("no frame has a one-step prediction")
    first = predicted[0]
    peak = first + int(np.nanargmax(rows["speed"][first:]))
    after = (np.arange(len(rows["speed"])) > peak) & (rows["speed"] > flowing)
    after &= np.isfinite(rows["one_step"])

    def mean_after(values: np.ndarray) -> float:
        return float(values[after].mean()) if after.any() else math.nan

    return {
        "peak": int(peak),
        "peak_speed": float(rows["speed"][peak]),
        "launch_truth": float(rows["truth"][first:peak].sum()),
        "launch_one_step": float(rows["one_step"][first:peak].sum()),
        "braking_truth": mean_after(rows["truth"]),
        "braking_one_step": mean_after(rows["one_step"]),
    }


# ---------------------------------------------------------------------------------- rest


def rest_by_height(
    history: np.ndarray,
    predicted: np.ndarray,
    floor: float,
    radius: float,
    g: float,
    edges: Sequence[float] = (1.0, 3.0, 6.0),
) -> dict[str, np.ndarray]:
    """The vertical acceleration of one step, by height above the floor.

    history: (N, C + 1, D) the frames the step was predicted from (a settled pile's last
    frames), predicted: (N, D) the next frame (y, axis 1, is up). Heights above `floor` (the
    last frame's y minus floor, in radii) are binned at `edges`: [0, e0), [e0, e1), ...,
    [e_last, inf); a particle below the floor counts in the first bin. Returns "acceleration"
    (bins,) each bin's mean predicted acceleration in g (positive up; NaN for an empty bin),
    "truth" (bins,) the same of the acceleration in the history's last three frames (a settled
    pile's: about 0), and "count" (bins,) its particles.
    """
    history = np.asarray(history, dtype=np.float64)
    predicted = np.asarray(predicted, dtype=np.float64)
    if history.ndim != 3 or history.shape[1] < 3 or history.shape[2] not in (2, 3):
        raise ValueError(f"history must be (N, C + 1 >= 3, D = 2 or 3), got {history.shape}")
    if predicted.shape != (len(history), history.shape[2]):
        raise ValueError(
            f"predicted must be ({len(history)}, {history.shape[2]}), got {predicted.shape}"
        )
    y = history[:, :, 1]
    ours = (predicted[:, 1] - 2 * y[:, -1] + y[:, -2]) / g
    truth = (y[:, -1] - 2 * y[:, -2] + y[:, -3]) / g
    bins = np.digitize((y[:, -1] - floor) / radius, np.asarray(edges, dtype=np.float64))
    count = np.bincount(bins, minlength=len(edges) + 1)

    def mean(values: np.ndarray) -> np.ndarray:
        total = np.bincount(bins, weights=values, minlength=len(edges) + 1)
        with np.errstate(invalid="ignore"):
            return total / count

    return {"acceleration": mean(ours), "truth": mean(truth), "count": count}


def starts_near_floor(positions: np.ndarray, floor: float, gap: float, speed: float) -> bool:
    """Whether a trajectory starts near the floor and slow: the lowest particle of its first
    frame at most `gap` above `floor` (y, axis 1), and the particles' mean displacement from
    frame 0 to 1 at most `speed` (per frame) long.

    positions: (T >= 2, N, D). Such a block lands within a few frames at low speed, and what
    follows is its collapse, driven by its own weight rather than by an impact: a regime that
    is rare in data of blocks dropped anywhere in a box, and a model can brake it while it
    launches every high landing right.
    """
    frames = np.asarray(positions, dtype=np.float64)
    if frames.ndim != 3 or frames.shape[0] < 2 or frames.shape[2] < 2:
        raise ValueError(f"positions must be (T >= 2, N, D >= 2), got {frames.shape}")
    if not (gap >= 0.0 and speed >= 0.0):
        raise ValueError(f"gap and speed must be >= 0, got {gap} and {speed}")
    lowest = float(frames[0, :, 1].min()) - floor
    moved = float(np.linalg.norm((frames[1] - frames[0]).mean(axis=0)))
    return lowest <= gap and moved <= speed
