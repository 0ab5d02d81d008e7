"""Validation during training: one-step and rollout error on held-out trajectories, whether
the rollouts stayed in the box, and which validation is the best so far (best.pt).

Kept apart from gns.train's loop; gns.train re-exports validate and better_validation.
"""

from __future__ import annotations

import hashlib
import math
import os
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from gns.config import TrainConfig
from gns.data import at_frame_stride, open_dataset
from gns.simulator import LearnedSimulator

__all__ = [
    "better_validation",
    "stays_in_box",
    "validate",
    "validation_rank",
    "validation_trajectories",
]


def validate(
    simulator: LearnedSimulator,
    trajectories: Sequence[Any],
    config: TrainConfig,
    device: torch.device,
) -> dict[str, float]:
    """One-step position MSE over config.validation_windows windows of `trajectories`, mean
    rollout MSE (config.validation_rollout_steps steps) over the first
    config.validation_rollouts of them, both over non-kinematic particles, and, in a scene with
    bounds, how far the rollouts' farthest particle got outside the box and, for reference, how
    far the ground truth's did over the same frames; with the scene's walls enforced
    (config.scene.enforce_walls), how many particle-steps they put back (wall_corrections).
    Eval mode (no noise, no statistics)."""
    from gns.evaluate import one_step_errors, outside_box
    from gns.metrics import mse_over_time
    from gns.periodic import period_of
    from gns.rollout import RolloutDiverged, rollout

    figures: dict[str, float] = {}
    if trajectories and config.validation_windows:
        errors = one_step_errors(
            simulator, trajectories, max_windows=config.validation_windows, device=device
        )
        figures["one_step_mse"] = errors["model"]
    history = simulator.config.model.velocity_history + 1
    rollout_errors, excursions, truth_excursions, corrections = [], [], [], []
    bounds = simulator.scene.bounds
    period = period_of(bounds, simulator.scene.periodic)
    for trajectory in trajectories[: config.validation_rollouts]:
        steps = min(config.validation_rollout_steps, trajectory.num_frames - history)
        if steps < 1:
            continue
        free = ~simulator.scene.kinematic_mask(trajectory.particle_type)
        if bounds is not None:
            truth = trajectory.positions[history : history + steps]
            truth_excursions.append(outside_box(truth[:, free], bounds))
        try:
            result = rollout(simulator, trajectory, num_steps=steps, device=device)
        except RolloutDiverged:
            # A diverged rollout is the worst validation, not the end of training.
            rollout_errors.append(math.inf)
            excursions.append(math.inf)
            continue
        per_frame = mse_over_time(
            result.predicted_rollout, result.ground_truth_rollout, free, period=period
        )
        rollout_errors.append(float(per_frame.mean()))
        if result.metadata["enforce_walls"]:
            corrections.append(result.metadata["wall_corrections"])
        if bounds is not None:
            excursions.append(outside_box(result.predicted_rollout[:, free], bounds))
    if rollout_errors:
        figures["rollout_mse"] = float(np.mean(rollout_errors))
    if bounds is not None and rollout_errors:
        figures["rollout_outside_box"] = max(excursions)
        figures["truth_outside_box"] = max(truth_excursions)
    if corrections:
        figures["wall_corrections"] = float(sum(corrections))
    return figures


def stays_in_box(figures: dict[str, float], radius: float) -> bool:
    """Whether validation rollouts stayed in the box: no particle farther outside than the
    ground truth's own farthest (simulators let particles sit a little past the nominal
    bounds) plus half the connectivity radius. True when the scene has no bounds."""
    if "rollout_outside_box" not in figures:
        return True
    allowed = figures.get("truth_outside_box", 0.0) + 0.5 * radius
    return figures["rollout_outside_box"] <= allowed


def better_validation(
    figures: dict[str, float], best: dict[str, Any] | None, radius: float
) -> dict[str, Any] | None:
    """The record of `figures` ({"step", "value", "in_box"}, step left to the caller) when
    they beat `best`, else None. Rollouts that stay in the box beat any that leave it (a
    model whose particles fall through a wall has a low MSE early in training, before the
    pile spreads); among equals, the lower rollout MSE (one-step MSE without rollouts) wins.
    A record without "in_box" (written before it existed) counts as having left the box."""
    key = "rollout_mse" if "rollout_mse" in figures else "one_step_mse"
    if key not in figures:
        return None
    record = {"value": figures[key], "in_box": stays_in_box(figures, radius)}
    if best is None or validation_rank(record) < validation_rank(best):
        return record
    return None


def validation_rank(record: dict[str, Any]) -> tuple[bool, float]:
    """The sort key of a validation record ({"value", "in_box"}): lower is better, in the box
    before out of it, then the lower value (better_validation's order)."""
    return (not record.get("in_box", False), record["value"])


def trajectories_digest(trajectories: Sequence[Any]) -> str:
    """SHA-256 of what validation reads (each trajectory's frames, types, features and
    obstacles), so that a resumed run can tell its validation data at another path (another
    machine) from other data."""
    digest = hashlib.sha256()
    for trajectory in trajectories:
        arrays = (
            trajectory.positions,
            trajectory.particle_type,
            trajectory.step_context,
            trajectory.material_property,
            *(trajectory.obstacles or ()),
        )
        for array in arrays:
            if array is None:
                digest.update(b"none;")
                continue
            array = np.ascontiguousarray(array)
            digest.update(f"{array.dtype}{array.shape};".encode())
            digest.update(array.tobytes())
        digest.update(b"end;")
    return digest.hexdigest()


def validation_trajectories(
    path: str | os.PathLike[str],
    config: TrainConfig,
    simulator: LearnedSimulator,
    required: bool = False,
) -> list[Any]:
    """The valid split's trajectories at the frames the model steps between (every k-th frame
    of data whose frames are k times finer). None without validation, or without a valid split
    unless `required` (a dataset named for validation must have one)."""
    if not config.validate_every:
        return []
    try:
        dataset = open_dataset(path, "valid")
    except ValueError:
        if required:
            raise
        return []
    # Checked now, not at the first validation a thousand steps in.
    scene, trajectories = simulator.scene, list(dataset)
    widths = {0 if t.step_context is None else t.step_context.shape[1] for t in trajectories}
    if dataset.metadata.dim != scene.dim or (scene.context_size and widths != {scene.context_size}):
        raise ValueError(
            f"{path}: validation data of dimension {dataset.metadata.dim} with "
            f"{'/'.join(map(str, sorted(widths)))} global features, but the model is "
            f"{scene.dim}D with {scene.context_size}"
        )
    stride = simulator.frame_stride_for(dataset.metadata)
    return [at_frame_stride(trajectory, stride) for trajectory in trajectories]
