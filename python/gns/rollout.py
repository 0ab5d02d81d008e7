"""Autoregressive rollouts of a LearnedSimulator, and the files they are saved in.

    rollout(simulator, trajectory)  the first C + 1 ground-truth frames, then num_steps frames
                                    each predicted from the C + 1 before it (section 3: the
                                    model is applied to its own outputs); kinematic particles
                                    are held to the ground truth at every step
    save_rollout / load_rollout     our npz schema (docs/formats.md, "Rollout files"), no pickle
    save_deepmind_pickle            DeepMind learning_to_simulate's rollout pickle layout

Every step is LearnedSimulator.predict_positions, timed in the four parts it marks: "graph"
(the Rust radius graph), "features" (the rest of the preprocess), "model" (the network:
EncodeProcessDecode or CConv) and "integration" (decoder postprocess, i.e. de-normalisation and
the Euler update, plus the walls and the kinematic override done here).

A non-finite prediction stops the rollout with `RolloutDiverged`, which carries the finite part;
NaN never travels on into later steps, metrics or files.

With enforce_walls (the model's config.scene.enforce_walls unless given), a free particle that a
step takes past a wall is put back on it, and the rollout's metadata counts what that changed
("wall_corrections": particle-steps moved, "wall_correction_max": the largest distance moved),
so a model kept in the box this way is never mistaken for one that stays there by itself.

How the steps run is measured, not assumed: torch's CPU thread count is chosen by timing the
steps (gns.threads; fixed when the user fixed it), and a model of precision "auto" runs in bf16
only where bf16 is native and `rollout_precision` timed it faster than fp32 for this model
within BF16_TOLERANCE. Both are recorded in the rollout's metadata ("torch_threads",
"precision"). Every tensor of a step stays on the simulator's device; only the most recent
positions go to the host (the Rust core's radius graph and distances) and their results back.
"""

from __future__ import annotations

import json
import math
import operator
import os
import pickle
import time
import weakref
import zipfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

import gns
from gns.batches import obstacle_shapes
from gns.config import Precision
from gns.data.trajectory import Trajectory
from gns.files import atomic_file
from gns.model import native_bf16, resolve_precision
from gns.simulator import LearnedSimulator
from gns.threads import StepTuner, thread_tuner, threads_fixed

__all__ = [
    "SCHEMA",
    "TIMING_PARTS",
    "Rollout",
    "RolloutDiverged",
    "frame_stride_metadata",
    "load_rollout",
    "rollout",
    "rollout_files",
    "rollout_path",
    "save_deepmind_pickle",
    "save_rollout",
]

TIMING_PARTS = ("graph", "features", "model", "integration")  # predict_positions' marks
# The network's arguments among LearnedSimulator.features' outputs, in order.
FEATURE_KEYS = ("node_features", "edge_features", "senders", "receivers", "global_features")
SCHEMA = "gns.rollout/1"

# npz keys of the schema; timings and array metrics get a prefix per entry.
_REQUIRED = ("schema", "initial_positions", "predicted_rollout", "particle_types", "metadata")
_OPTIONAL = ("ground_truth_rollout", "step_context", "metrics")
_TIMING, _METRIC = "timing_", "metric_"


@dataclass(eq=False)
class Rollout:
    """One rollout of S = num_steps predicted frames after C + 1 given ones.

    initial_positions: (C + 1, N, D), the ground-truth history the rollout starts from.
    predicted_rollout: (S, N, D), frames C + 1 ... C + S; kinematic particles are ground truth.
    ground_truth_rollout: (S, N, D), the same frames of the trajectory, or None when the
        rollout runs past the end of the trajectory.
    particle_type: (N,) int64.
    step_context: (C + S, K), the context of every frame that was an input (step t reads
        frame C + t, the last input frame, as in training), or None.
    metadata: plain JSON values (scene facts, trajectory, run info).
    timings: TIMING_PARTS -> (S,) float64 seconds per step.
    metrics: filled by the evaluation code; numbers, numpy arrays or plain JSON values.

    Positions are float32 or float64 (the simulator's precision, never below float32).
    `trajectory` properties give the whole (C + 1 + S, N, D) sequences.
    """

    initial_positions: np.ndarray
    predicted_rollout: np.ndarray
    ground_truth_rollout: np.ndarray | None
    particle_type: np.ndarray
    step_context: np.ndarray | None = None
    metadata: dict[str, Any] = field(default_factory=dict)
    timings: dict[str, np.ndarray] = field(default_factory=dict)
    metrics: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        history, predicted = self.initial_positions, self.predicted_rollout
        if history.ndim != 3 or history.shape[0] < 2:
            raise ValueError(f"initial_positions must be (C + 1, N, D), got {history.shape}")
        _, n, d = history.shape
        if predicted.ndim != 3 or predicted.shape[1:] != (n, d):
            raise ValueError(f"predicted_rollout must be (S, {n}, {d}), got {predicted.shape}")
        steps = predicted.shape[0]
        for name in ("initial_positions", "predicted_rollout", "ground_truth_rollout"):
            value = getattr(self, name)
            if value is not None and not np.issubdtype(value.dtype, np.floating):
                raise ValueError(f"{name} must be floating point, got {value.dtype}")
        truth = self.ground_truth_rollout
        if truth is not None and truth.shape != predicted.shape:
            raise ValueError(
                f"ground_truth_rollout must be {predicted.shape} like predicted_rollout, "
                f"got {truth.shape}"
            )
        if self.particle_type.shape != (n,) or not np.issubdtype(
            self.particle_type.dtype, np.integer
        ):
            raise ValueError(
                f"particle_type must be ({n},) integers, got {self.particle_type.shape} "
                f"{self.particle_type.dtype}"
            )
        c = history.shape[0] - 1
        context = self.step_context
        if context is not None and (context.ndim != 2 or context.shape[0] != c + steps):
            raise ValueError(f"step_context must be (C + S = {c + steps}, K), got {context.shape}")
        for part, seconds in self.timings.items():
            if seconds.shape != (steps,):
                raise ValueError(f"timings[{part!r}] must be ({steps},), got {seconds.shape}")

    @property
    def num_steps(self) -> int:
        """S, the number of predicted frames."""
        return int(self.predicted_rollout.shape[0])

    @property
    def predicted_trajectory(self) -> np.ndarray:
        """(C + 1 + S, N, D): the history followed by the prediction."""
        return np.concatenate([self.initial_positions, self.predicted_rollout])

    @property
    def ground_truth_trajectory(self) -> np.ndarray | None:
        """(C + 1 + S, N, D): the history followed by the ground truth, or None."""
        if self.ground_truth_rollout is None:
            return None
        return np.concatenate([self.initial_positions, self.ground_truth_rollout])


class RolloutDiverged(ValueError):
    """A step predicted non-finite positions, or particles far outside the domain (see
    `rollout`'s escape_distance). `rollout` holds the steps before it (all good); `step` is the
    0-based step (it predicted frame C + 1 + step); `num_nonfinite` counts the particles whose
    position is not finite, `particles` lists the offending particles (non-finite or escaped)."""

    def __init__(
        self,
        message: str,
        rollout: Rollout,
        step: int,
        num_nonfinite: int,
        particles: np.ndarray | None = None,
    ) -> None:
        super().__init__(message)
        self.rollout, self.step, self.num_nonfinite = rollout, step, num_nonfinite
        self.particles = np.zeros(0, dtype=np.int64) if particles is None else particles


def _domain(simulator: LearnedSimulator, first_frame: np.ndarray) -> tuple[Tensor, Tensor]:
    """(lo, hi) per axis: the scene's bounds, or without them the first frame's bounding box."""
    bounds = simulator.scene.bounds
    if bounds is not None:
        lo, hi = (np.array([b[k] for b in bounds], dtype=np.float64) for k in (0, 1))
    else:
        lo, hi = first_frame.min(axis=0).astype(np.float64), first_frame.max(axis=0)
    return torch.from_numpy(lo), torch.from_numpy(np.asarray(hi, dtype=np.float64))


def _walls(simulator: LearnedSimulator) -> tuple[Tensor, Tensor]:
    """(lo, hi) per axis of the walls a rollout enforces: the scene's bounds on non-periodic
    axes, -inf/inf on periodic ones (they wrap instead)."""
    scene = simulator.scene
    if scene.bounds is None:
        raise ValueError("enforce_walls needs the scene's bounds, and this scene has none")
    sides = list(zip(scene.bounds, scene.periodic, strict=True))
    lo = [-math.inf if periodic else low for (low, _), periodic in sides]
    hi = [math.inf if periodic else high for (_, high), periodic in sides]
    return torch.tensor(lo, dtype=torch.float64), torch.tensor(hi, dtype=torch.float64)


def _listed(indices: np.ndarray, limit: int = 10) -> str:
    shown = ", ".join(str(int(i)) for i in indices[:limit])
    return shown + (f", ... ({len(indices)} in all)" if len(indices) > limit else "")


# ---------------------------------------------------------------------------------- rollout

# bf16 is used for a rollout only if its normalised acceleration (units of the data's
# acceleration std) differs from fp32's by at most this RMS over particles and axes on the
# first step: a tenth of the std, well below the one-step error of the trained models here.
BF16_TOLERANCE = 0.1
# ... and if it ran the network at least this much faster (timed forwards of the first step).
BF16_SPEEDUP = 1.1


def bf16_difference(model: torch.nn.Module, features: Mapping[str, Any]) -> float:
    """RMS over particles and axes of the network's bf16 output minus its fp32 output on
    `features` (LearnedSimulator.features' dict), in normalised acceleration units."""
    outputs = [_forward(model, features, p) for p in ("fp32", "bf16")]
    return float((outputs[1] - outputs[0]).square().mean().sqrt())


def _forward(model: torch.nn.Module, features: Mapping[str, Any], precision: str) -> Tensor:
    args = [features[k] for k in FEATURE_KEYS]
    # A padded edge list (LearnedSimulator.edge_bucket) comes with the mask of its padding.
    mask = features.get("edge_mask")
    padding = {} if mask is None else {"edge_mask": mask}
    saved, model.precision = model.precision, precision
    try:
        return model(*args, **padding)
    finally:
        model.precision = saved


def rollout_precision(
    model: torch.nn.Module,
    features: Mapping[str, Any],
    device: torch.device,
    clock: Callable[[], float] = time.perf_counter,
    repeats: int = 3,
) -> Precision:
    """What a rollout of `model` runs in: its precision when it is "fp32" or "bf16"; for
    "auto", bf16 only on a device where it is native, within BF16_TOLERANCE of fp32 on these
    features, and at least BF16_SPEEDUP times faster in `repeats` timed forwards of each
    (alternating, medians compared; the tolerance check's forwards warm both up); else fp32.
    Decided once, before the first step, so that one rollout never mixes precisions."""
    if model.precision != "auto":
        return resolve_precision(model.precision, device)
    if not native_bf16(device) or bf16_difference(model, features) > BF16_TOLERANCE:
        return "fp32"
    times: dict[str, list[float]] = {"fp32": [], "bf16": []}
    for _ in range(repeats):
        for precision, seconds in times.items():
            start = clock()
            _forward(model, features, precision)
            seconds.append(clock() - start)
    fp32, bf16 = (float(np.median(t)) for t in times.values())
    return "bf16" if fp32 >= BF16_SPEEDUP * bf16 else "fp32"


# Per simulator, kept between its rollouts (each trajectory of a split would otherwise measure
# again): the precision chosen, the thread tuner, and the facts they were chosen under.
_RUNTIME: weakref.WeakKeyDictionary[
    LearnedSimulator, tuple[tuple[Any, ...], Precision, StepTuner[int]]
] = weakref.WeakKeyDictionary()


def _runtime(
    simulator: LearnedSimulator,
    device: torch.device,
    features: Callable[[], Mapping[str, Any]],
    clock: Any,
) -> tuple[Precision, StepTuner[int]]:
    """The precision and thread tuner of `simulator`'s rollouts; `features` gives the first
    step's features, computed only when the precision is decided anew."""
    signature = (device, simulator.model.precision, threads_fixed())
    cached = _RUNTIME.get(simulator)
    if cached is None or cached[0] != signature:
        precision = rollout_precision(simulator.model, features(), device, clock)
        tuner = thread_tuner()
        cached = (signature, precision, tuner)
        _RUNTIME[simulator] = cached
    return cached[1], cached[2]


def _clock(device: torch.device) -> Callable[[], float]:
    """perf_counter that first waits for queued CUDA kernels, so each part is charged for the
    work it launched rather than for whatever happened to finish before the clock was read."""
    if device.type == "cuda":

        def now() -> float:
            torch.cuda.synchronize(device)
            return time.perf_counter()

        return now
    return time.perf_counter


def _check_num_steps(
    num_steps: int | None, trajectory: Trajectory, history: int, num_kinematic: int
) -> int:
    frames = trajectory.num_frames
    if frames < history:
        raise ValueError(
            f"a rollout needs the first C + 1 = {history} frames as history, but the trajectory "
            f"has {frames} frames"
        )
    available = frames - history  # frames of ground truth after the history
    if num_steps is None:
        num_steps = available
        if num_steps < 1:
            raise ValueError(
                f"the trajectory has only the {history} history frames; pass num_steps to "
                "predict beyond them"
            )
    num_steps = operator.index(num_steps)
    if num_steps < 1:
        raise ValueError(f"num_steps must be at least 1, got {num_steps}")
    if num_steps > available and num_kinematic:
        raise ValueError(
            f"num_steps = {num_steps} needs ground truth for the {num_kinematic} kinematic "
            f"particles up to frame {history + num_steps - 1}, but the trajectory has {frames} "
            f"frames (at most {available} steps)"
        )
    context = trajectory.step_context
    if context is not None and history - 1 + num_steps > frames:
        raise ValueError(
            f"num_steps = {num_steps} reads the step context up to frame {history + num_steps - 2}"
            f", but the trajectory has {frames} frames (at most {frames - history + 1} steps)"
        )
    return num_steps


def _run_metadata(
    simulator: LearnedSimulator,
    trajectory: Trajectory,
    num_steps: int,
    num_kinematic: int,
    device: torch.device,
    dtype: torch.dtype,
) -> dict[str, Any]:
    scene = simulator.scene
    c = simulator.config.model.velocity_history
    return {
        # Scene facts; "dim" and "bounds" are also what DeepMind's render_rollout.py reads.
        "dim": scene.dim,
        "bounds": None if scene.bounds is None else [list(pair) for pair in scene.bounds],
        "periodic": list(scene.periodic),
        "connectivity_radius": scene.radius,
        "kinematic_particle_types": list(scene.kinematic_particle_types),
        "velocity_history": c,
        "input_sequence_length": c + 1,
        # Where the rollout came from and what it is.
        "trajectory": trajectory.key,
        "source": trajectory.source,
        "num_steps": num_steps,
        "num_particles": trajectory.n_particles,
        "num_kinematic": num_kinematic,
        # How it ran (what the timings mean).
        "device": str(device),
        "dtype": str(dtype).removeprefix("torch."),
        "torch_threads": torch.get_num_threads(),
        "torch_version": torch.__version__,
        "gns_version": gns.__version__,
    }


def rollout(
    simulator: LearnedSimulator,
    trajectory: Trajectory,
    *,
    num_steps: int | None = None,
    device: torch.device | str | None = None,
    metadata: Mapping[str, Any] | None = None,
    escape_distance: float | None = 1.0,
    enforce_walls: bool | None = None,
) -> Rollout:
    """Roll the simulator out from the first C + 1 frames of `trajectory`.

    trajectory: a gns.data Trajectory, positions (T, N, D). C = the simulator's
        model.velocity_history (5: six history frames).
    num_steps: S frames to predict; default all the trajectory has, T - (C + 1). More is allowed
        only without kinematic particles (they need ground truth at every step) and without a
        step context (it is read at every input frame); ground_truth_rollout is then None.
    device: where to run; the simulator is moved there in place (as nn.Module.to does) and
        stays. Default: the simulator's device.
    metadata: extra plain JSON entries (e.g. the dataset's name, a checkpoint) for
        Rollout.metadata, over the scene and run facts gathered here.
    escape_distance: a particle farther outside the domain (the scene's bounds, else the first
        frame's bounding box) than this many times the domain's longest side is taken as
        divergence; None: never. Positions that far off are garbage, and the model would only
        go on feeding them to the graph and the next step.
    enforce_walls: put every free particle that a step takes past a wall (the scene's bounds on
        a non-periodic axis) back on it before the next step; metadata["wall_corrections"]
        counts the particle-steps moved and metadata["wall_correction_max"] the largest
        distance moved. None: the simulator's config.scene.enforce_walls.

    Step t is `simulator.predict_positions` of frames t ... t + C (particle-major,
    (N, C + 1, D)), the step context of frame t + C (the last input frame, as training windows
    do) and the material property; kinematic particles are then set to ground-truth frame
    t + C + 1. Runs under torch.inference_mode() in eval mode; the simulator's previous mode is
    restored. Raises ValueError for unusable arguments and RolloutDiverged (a ValueError) at the
    first step with a non-finite position or an escaped particle, naming the step and particles.
    The rollout's precision is the simulator's (never below float32): `simulator.double()`
    rolls out in float64, e.g. to compare drift.
    """
    if escape_distance is not None and not (
        isinstance(escape_distance, (int, float))
        and math.isfinite(escape_distance)
        and escape_distance > 0
    ):
        raise ValueError(
            f"escape_distance must be a positive number of domain lengths or None, got "
            f"{escape_distance!r}"
        )
    c = simulator.config.model.velocity_history
    history = c + 1
    particle_type = trajectory.particle_type
    kinematic = simulator.scene.kinematic_mask(particle_type)
    num_kinematic = int(kinematic.sum())
    num_steps = _check_num_steps(num_steps, trajectory, history, num_kinematic)
    if enforce_walls is None:
        enforce_walls = simulator.config.scene.enforce_walls
    walls = _walls(simulator) if enforce_walls else None
    if trajectory.dim != simulator.scene.dim:
        raise ValueError(
            f"the trajectory is {trajectory.dim}D but the simulator's scene is "
            f"{simulator.scene.dim}D"
        )

    if device is not None:
        simulator.to(device)
    parameter = next(simulator.parameters())
    device = parameter.device
    # Positions in the network's precision but never below float32 (a rollout accumulates).
    dtype = torch.promote_types(parameter.dtype, torch.float32)
    n, d, frames = trajectory.n_particles, trajectory.dim, trajectory.num_frames

    positions = trajectory.positions  # (T, N, D) float32, time-major
    # The model reads particle-major sequences (N, C + 1, D), most recent last.
    window = torch.from_numpy(positions[:history].transpose(1, 0, 2).copy()).to(device, dtype)
    # A copy: trajectories may hold read-only arrays (memory-mapped or shared), which torch
    # refuses to wrap without a warning.
    types = torch.from_numpy(np.array(particle_type)).to(device)
    kinematic_index = torch.from_numpy(np.flatnonzero(kinematic)).to(device)
    kinematic_truth = torch.from_numpy(positions[:, kinematic]).to(device, dtype)  # (T, K, D)
    context = None
    if trajectory.step_context is not None:
        context = torch.from_numpy(trajectory.step_context).to(device)
    material = None
    if trajectory.material_property is not None:
        material = torch.from_numpy(trajectory.material_property).to(device)
    obstacles = None  # the simulator's own shapes, if any
    if trajectory.obstacles is not None:
        obstacles = [obstacle_shapes(trajectory.obstacles)]

    lo, hi = (x.to(device, dtype) for x in _domain(simulator, positions[0]))
    if escape_distance is not None:
        allowed = escape_distance * float((hi - lo).max().clamp_min(simulator.scene.radius))
    predicted = torch.empty(num_steps, n, d, dtype=dtype, device=device)
    seconds = np.zeros((len(TIMING_PARTS), num_steps), dtype=np.float64)
    now = _clock(device)
    run_metadata = _run_metadata(simulator, trajectory, num_steps, num_kinematic, device, dtype)
    run_metadata["enforce_walls"] = bool(enforce_walls)
    run_metadata.update(metadata or {})
    if walls is not None:
        walls = (walls[0].to(device, dtype), walls[1].to(device, dtype))
    # What the walls changed, summed on the device (read once, at the end).
    corrected = torch.zeros((), dtype=torch.int64, device=device)
    largest_correction = torch.zeros((), dtype=dtype, device=device)
    tuner: StepTuner[int] | None = None
    precision: Precision = "fp32"

    def result(steps: int) -> Rollout:
        truth = None
        if history + steps <= frames:
            truth = positions[history : history + steps].copy()
        step_context = None
        if trajectory.step_context is not None:
            step_context = trajectory.step_context[: c + steps].copy()
        ran: dict[str, Any] = {"num_steps": steps}
        if walls is not None:
            ran.update(
                wall_corrections=int(corrected), wall_correction_max=float(largest_correction)
            )
        if tuner is not None:  # what the steps ran with (in the end: see gns.threads)
            ran.update(precision=precision, torch_threads=tuner.chosen)
        return Rollout(
            initial_positions=positions[:history].copy(),
            predicted_rollout=predicted[:steps].cpu().numpy(),
            ground_truth_rollout=truth,
            particle_type=particle_type.copy(),
            step_context=step_context,
            metadata={**run_metadata, **ran},
            timings={part: seconds[i, :steps].copy() for i, part in enumerate(TIMING_PARTS)},
        )

    marks: dict[str, float] = {}  # when each part of a step ended (predict_positions marks)

    def mark(part: str) -> None:
        marks[part] = now()

    def context_at(frame: int) -> Tensor | None:
        return None if context is None else context[frame]

    was_training, saved_precision = simulator.training, simulator.model.precision
    simulator.eval()
    try:
        with torch.inference_mode():
            # Decided before the first step (from its features, when it must be measured)
            # and kept for the whole rollout, so that the steps never mix precisions.
            precision, tuner = _runtime(
                simulator,
                device,
                lambda: simulator.features(
                    window, types, None, context_at(c), material, obstacles=obstacles
                ),
                now,
            )
            tuner.__enter__()
            simulator.model.precision = precision
            for step in range(num_steps):
                frame = step + c  # the last input frame
                tuner.begin()  # outside the timed step: the tuner's own work is not charged
                start = now()
                next_position = simulator.predict_positions(
                    window, types, None, context_at(frame), material, mark=mark, obstacles=obstacles
                )
                if walls is not None:
                    placed = torch.maximum(torch.minimum(next_position, walls[1]), walls[0])
                    moved = (placed - next_position).norm(dim=-1)
                    next_position = placed
                if num_kinematic:
                    next_position[kinematic_index] = kinematic_truth[frame + 1]
                # Each part from the end of the one before; integration ends here, after the
                # kinematic override.
                ends = [*(marks[part] for part in TIMING_PARTS[:-1]), now()]
                seconds[:, step] = np.diff([start, *ends])
                tuner.end(seconds[:, step].sum())

                bad = ~torch.isfinite(next_position).all(dim=-1)
                nonfinite = int(bad.sum())
                escaped = 0
                if escape_distance is not None and not nonfinite:
                    outside = torch.maximum(lo - next_position, next_position - hi)
                    far = outside.amax(dim=-1) > allowed
                    escaped, bad = int(far.sum()), far
                if nonfinite or escaped:
                    particles = torch.nonzero(bad).flatten().cpu().numpy()
                    what = (
                        f"{nonfinite} of {n} particles have non-finite positions"
                        if nonfinite
                        else f"{escaped} of {n} particles are more than {allowed:.3g} outside "
                        f"the domain ({escape_distance} times its longest side)"
                    )
                    partial = result(step)
                    partial.metadata["diverged_at_step"] = step
                    raise RolloutDiverged(
                        f"rollout diverged at step {step} (predicting frame {frame + 1}): "
                        f"{what} (particles {_listed(particles)}); the {step} finite steps "
                        "before it are kept",
                        partial,
                        step,
                        nonfinite,
                        particles,
                    )
                if walls is not None:
                    if num_kinematic:  # held to the truth, not put on a wall
                        moved[kinematic_index] = 0
                    corrected += (moved > 0).sum()
                    largest_correction = torch.maximum(largest_correction, moved.max())
                predicted[step] = next_position
                window = torch.cat([window[:, 1:], next_position[:, None]], dim=1)
    finally:
        if tuner is not None:
            tuner.__exit__()
        simulator.model.precision = saved_precision
        simulator.train(was_training)
    return result(num_steps)


# ---------------------------------------------------------------------------------- files


def frame_stride_metadata(dataset_dt: float, stride: int) -> dict[str, Any]:
    """What a rollout file records of the frames it ran on: every `stride`-th frame of a
    dataset whose frames are `dataset_dt` seconds apart (gns.data.at_frame_stride), so its
    frames are stride * dataset_dt apart."""
    return {"frame_stride": int(stride), "dataset_dt": float(dataset_dt)}


def _plain(value: Any) -> Any:
    """numpy scalars as Python numbers (json cannot write them), everything else as is."""
    return value.item() if isinstance(value, np.generic) else value


def _json(value: Mapping[str, Any], what: str) -> np.ndarray:
    try:
        text = json.dumps(value, default=_plain)
    except (TypeError, ValueError) as error:
        raise ValueError(f"rollout {what} must hold plain JSON values: {error}") from None
    return np.array(text)  # 0-d unicode: readable without pickle


def _arrays(r: Rollout) -> dict[str, np.ndarray]:
    """The npz members of a rollout (see load_rollout for the schema)."""
    arrays: dict[str, np.ndarray] = {
        "schema": np.array(SCHEMA),
        "initial_positions": r.initial_positions,
        "predicted_rollout": r.predicted_rollout,
        "particle_types": r.particle_type,
        "metadata": _json(r.metadata, "metadata"),
    }
    if r.ground_truth_rollout is not None:
        arrays["ground_truth_rollout"] = r.ground_truth_rollout
    if r.step_context is not None:
        arrays["step_context"] = r.step_context
    for part, seconds in r.timings.items():
        arrays[_TIMING + part] = np.asarray(seconds, dtype=np.float64)
    # Array metrics (e.g. an error per step) as arrays, everything else as one JSON object.
    plain = {k: v for k, v in r.metrics.items() if not isinstance(v, np.ndarray)}
    arrays["metrics"] = _json(plain, "metrics")
    for name, value in r.metrics.items():
        if isinstance(value, np.ndarray):
            if value.dtype.hasobject:
                raise ValueError(f"metric {name!r} is an object array; it would need pickle")
            arrays[_METRIC + name] = value
    return arrays


def rollout_path(
    folder: str | os.PathLike[str], split: str, index: int, suffix: str = ".npz"
) -> Path:
    """Where trajectory `index` of `split` is kept in a folder of rollouts (and its .pkl, .gif):
    folder/rollout_{split}_{index}{suffix}, the name every command reads and writes."""
    return Path(folder) / f"rollout_{split}_{index}{suffix}"


def rollout_files(folder: str | os.PathLike[str], split: str) -> list[Path]:
    """The rollout files (.npz) of `split` in `folder`, by trajectory index."""
    found = Path(folder).glob(f"rollout_{split}_*.npz")
    return sorted(found, key=lambda p: int(p.stem.rsplit("_", 1)[-1]))


def save_rollout(path: str | os.PathLike[str], rollout: Rollout) -> None:
    """Write `rollout` as an npz of plain arrays (no pickle), atomically: a failure part way
    leaves an existing file at `path` untouched. `path` is used as given (no ".npz" added).

    Members: schema (0-d str), initial_positions, predicted_rollout, ground_truth_rollout (when
    known), particle_types, step_context (when present), metadata and metrics (0-d JSON str),
    timing_<part> (S,) float64, metric_<name> for metrics that are numpy arrays.
    """
    # dict[str, Any]: numpy's stubs would otherwise match the names against allow_pickle.
    arrays: dict[str, Any] = _arrays(rollout)
    with atomic_file(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, **arrays)


def _load_json(value: np.ndarray, key: str) -> dict[str, Any]:
    if value.shape != () or value.dtype.kind != "U":
        raise ValueError(f"{key} must be a 0-d JSON string, got {value.dtype} {value.shape}")
    try:
        loaded = json.loads(str(value))
    except json.JSONDecodeError as error:
        raise ValueError(f"{key} is not valid JSON: {error}") from None
    if not isinstance(loaded, dict):
        raise ValueError(f"{key} must be a JSON object, got {type(loaded).__name__}")
    return loaded


def _from_arrays(arrays: dict[str, np.ndarray]) -> Rollout:
    keys = set(arrays)
    missing = [k for k in _REQUIRED if k not in keys]
    if missing:
        raise ValueError(f"missing members {missing}")
    known = {*_REQUIRED, *_OPTIONAL}
    unknown = sorted(k for k in keys - known if not k.startswith((_TIMING, _METRIC)))
    if unknown:
        raise ValueError(f"unknown members {unknown}")
    schema = arrays["schema"]
    if schema.shape != () or str(schema) != SCHEMA:
        raise ValueError(f"schema is {schema!r}, expected {SCHEMA!r}")
    for key in ("initial_positions", "predicted_rollout", "ground_truth_rollout"):
        if key in arrays and not np.isfinite(arrays[key]).all():
            raise ValueError(f"{key} holds non-finite values")
    timings = {k.removeprefix(_TIMING): v for k, v in arrays.items() if k.startswith(_TIMING)}
    for part, seconds in timings.items():
        if seconds.dtype != np.float64:
            raise ValueError(f"{_TIMING + part} must be float64 seconds, got {seconds.dtype}")
    metrics: dict[str, Any] = {}
    if "metrics" in arrays:
        metrics = _load_json(arrays["metrics"], "metrics")
    for key, value in arrays.items():
        if key.startswith(_METRIC):
            metrics[key.removeprefix(_METRIC)] = value
    return Rollout(
        initial_positions=arrays["initial_positions"],
        predicted_rollout=arrays["predicted_rollout"],
        ground_truth_rollout=arrays.get("ground_truth_rollout"),
        particle_type=arrays["particle_types"],
        step_context=arrays.get("step_context"),
        metadata=_load_json(arrays["metadata"], "metadata"),
        timings=timings,
        metrics=metrics,
    )


def load_rollout(path: str | os.PathLike[str]) -> Rollout:
    """Read a file written by save_rollout (np.load with allow_pickle=False). A damaged,
    truncated or foreign file raises ValueError naming the path and what is wrong."""
    try:
        with np.load(path, allow_pickle=False) as npz:
            # Reading every member checks its CRC, so damage shows here, not later.
            arrays = {key: npz[key] for key in npz.files}
    except FileNotFoundError:
        raise
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as error:
        raise ValueError(f"{os.fspath(path)}: not a readable rollout file ({error})") from None
    try:
        return _from_arrays(arrays)
    except ValueError as error:
        raise ValueError(f"{os.fspath(path)}: not a valid rollout file: {error}") from None


def save_deepmind_pickle(path: str | os.PathLike[str], rollout: Rollout) -> None:
    """Write `rollout` in the layout of DeepMind learning_to_simulate's rollout pickles
    (train.py, eval_rollout mode), atomically.

    A dict of numpy arrays: initial_positions (C + 1, N, D) time-major (render_rollout.py
    concatenates it with predicted_rollout along axis 0), predicted_rollout and
    ground_truth_rollout (S, N, D), particle_types (N,), metadata (a dict; render_rollout.py
    reads metadata["bounds"]) and, when the rollout has a step context, global_context
    (DeepMind stores the trajectory's whole context and reads frame step + C at step t; ours
    has frames 0 ... C + S - 1, so the same index works). DeepMind's rollouts always have
    ground truth, so one without it is refused.
    """
    if rollout.ground_truth_rollout is None:
        raise ValueError(
            "the DeepMind rollout layout needs ground_truth_rollout; this rollout ran past the "
            "end of its trajectory"
        )
    payload: dict[str, Any] = {
        "initial_positions": rollout.initial_positions,
        "predicted_rollout": rollout.predicted_rollout,
        "ground_truth_rollout": rollout.ground_truth_rollout,
        "particle_types": rollout.particle_type,
        "metadata": dict(rollout.metadata),
    }
    if rollout.step_context is not None:
        payload["global_context"] = rollout.step_context
    with atomic_file(path) as tmp, open(tmp, "wb") as f:
        pickle.dump(payload, f, protocol=4)  # protocol 4: readable by Python >= 3.4
