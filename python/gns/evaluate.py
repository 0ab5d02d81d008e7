"""Evaluation of a trained run: one-step MSE over a split, and the metrics of its rollouts next
to the constant-velocity baseline (every particle keeps its last velocity) on the same frames.

    one_step_errors(simulator, dataset)   position MSE of single steps from ground-truth inputs
    evaluate_rollouts(rollouts)           per-trajectory and mean rollout metrics (MSE over time
                                          and at horizons, OT, MMD), model and baseline, plus how
                                          far any particle left the box and how densely the
                                          last frame is packed against the ground truth
    rest_test(simulator, trajectory, steps)
                                          the trajectory's last frame held still and rolled
                                          out: does the model keep a settled pile in place?
The metrics themselves are gns.metrics; this module only decides what is compared with what.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from gns.data.trajectory import Trajectory
from gns.data.windows import collate, trajectory_windows, window_keys
from gns.metrics import DEFAULT_HORIZONS, constant_velocity_rollout, evaluate_rollout
from gns.rollout import Rollout, RolloutDiverged, rollout
from gns.simulator import LearnedSimulator

__all__ = ["evaluate_rollouts", "mean_neighbours", "one_step_errors", "outside_box", "rest_test"]

MODELS = ("model", "constant_velocity")


@torch.no_grad()
def one_step_errors(
    simulator: LearnedSimulator,
    trajectories: Sequence[Any],
    *,
    max_windows: int | None = None,
    device: torch.device | str = "cpu",
) -> dict[str, float]:
    """Mean one-step position MSE (per particle and axis, non-kinematic particles) of the model
    and of the constant-velocity baseline over the windows of `trajectories`: all of them, or
    `max_windows` spread evenly over the split."""
    from gns.train import batch_tensors

    history = simulator.config.model.velocity_history + 1
    pairs = window_keys(trajectories, history)
    if not pairs:
        raise ValueError(f"no trajectory has more than {history} frames: nothing to evaluate")
    if max_windows is not None and max_windows < len(pairs):
        pairs = [pairs[i] for i in np.linspace(0, len(pairs) - 1, max_windows).round().astype(int)]
    was_training = simulator.training
    simulator.eval()
    device = torch.device(device)
    sums = {name: 0.0 for name in MODELS}
    try:
        for k, start in pairs:
            window = next(trajectory_windows(trajectories[k], history, [start]))
            t = batch_tensors(collate([window]), device)
            sequence, truth = t["position_sequence"], t["next_position"]
            assert sequence is not None and truth is not None and t["particle_type"] is not None
            predicted = simulator.predict_positions(
                sequence, t["particle_type"], t["n_node"], t["context"], t["material_property"]
            )
            baseline = 2 * sequence[:, -1] - sequence[:, -2]
            free = ~simulator.kinematic_mask(t["particle_type"])
            for name, guess in (("model", predicted), ("constant_velocity", baseline)):
                error = (guess.double() - truth.double())[free].square().mean()
                sums[name] += float(error)
    finally:
        simulator.train(was_training)
    return {name: total / len(pairs) for name, total in sums.items()}


def outside_box(positions: np.ndarray, bounds: Sequence[Sequence[float]]) -> float:
    """How far (in position units) the farthest particle of (T, N, D) is outside the box;
    0 when every particle stays inside."""
    box = np.asarray(bounds, dtype=np.float64)
    below = box[:, 0] - positions
    above = positions - box[:, 1]
    return float(max(0.0, below.max(), above.max()))


def mean_neighbours(
    positions: np.ndarray,
    radius: float,
    bounds: Sequence[Sequence[float]] | None = None,
    periodic: Sequence[bool] | None = None,
) -> float:
    """The mean number of other particles within `radius` of a particle of one frame (N, D),
    minimum image on periodic axes: how densely the frame is packed."""
    from gns import radius_graph

    x = np.asarray(positions, dtype=np.float64)
    if len(x) == 0:
        return 0.0
    kwargs: dict[str, Any] = {"self_edges": False}
    if periodic is not None and any(periodic):
        if bounds is None:
            raise ValueError("mean_neighbours: periodic axes need the bounds of the box")
        box = np.asarray(bounds, dtype=np.float64)
        x = x - box[:, 0]
        kwargs.update(box=(box[:, 1] - box[:, 0]).tolist(), periodic=list(periodic))
    return radius_graph(x, radius, **kwargs).shape[1] / len(x)


def evaluate_rollouts(
    rollouts: Sequence[Rollout],
    *,
    horizons: Sequence[int | None] = DEFAULT_HORIZONS,
    distribution_every: int = 1,
    bandwidth: float = 0.1,
) -> dict[str, Any]:
    """Rollout metrics of the model and of the constant-velocity baseline.

    Each rollout needs its ground truth. Kinematic particles (metadata's
    kinematic_particle_types) are held to the ground truth in both and left out of every
    metric. Returns {"trajectories": [per-rollout dicts], "mean": {model: {metric: value}}}
    where a per-rollout dict holds, per model, the scalar metrics ("mse@h", "mse@full",
    "ot_mean", "mmd_mean", "outside_box", "finite", "density_ratio") and the per-frame "mse"
    curve. density_ratio is the last frame's mean neighbour count within the connectivity
    radius over the ground truth's: a simulator that loses volume packs its particles ever
    closer (above 1), one that lets them fly apart spreads them (below 1).
    """
    if not rollouts:
        raise ValueError("no rollouts to evaluate")
    per_rollout = [_evaluate_one(r, horizons, distribution_every, bandwidth) for r in rollouts]
    mean: dict[str, dict[str, float]] = {}
    for name in MODELS:
        entries = [entry[name] for entry in per_rollout if entry[name] is not None]
        keys = list(dict.fromkeys(key for e in entries for key in e if key != "mse"))
        mean[name] = {}
        for key in keys:
            # A diverged model rollout lacks the later horizons: they count as infinitely wrong.
            values = [e.get(key, np.inf) for e in entries]
            # The worst case, not the mean, is what "inside the box" must mean.
            mean[name][key] = float(np.max(values) if key == "outside_box" else np.mean(values))
    # The reference for "stays inside the box": an MPM ground truth itself sits a little
    # outside its nominal bounds (particles rest within a grid cell of the wall).
    truth_outside = [
        e["ground_truth_outside_box"] for e in per_rollout if "ground_truth_outside_box" in e
    ]
    if truth_outside:
        mean["ground_truth"] = {"outside_box": max(truth_outside)}
    return {"trajectories": per_rollout, "mean": mean}


def _evaluate_one(
    r: Rollout, horizons: Sequence[int | None], distribution_every: int, bandwidth: float
) -> dict[str, Any]:
    """Model and baseline figures of one rollout (see evaluate_rollouts)."""
    if r.ground_truth_rollout is None:
        raise ValueError(
            f"rollout of trajectory {r.metadata.get('trajectory')} has no ground truth"
        )
    diverged_at = r.metadata.get("diverged_at_step")
    entry: dict[str, Any] = {"trajectory": r.metadata.get("trajectory")}
    bounds = r.metadata.get("bounds")
    radius, periodic = r.metadata.get("connectivity_radius"), r.metadata.get("periodic")
    if bounds is not None and r.num_steps:
        entry["ground_truth_outside_box"] = outside_box(r.ground_truth_rollout, bounds)
    if diverged_at is not None:
        entry["diverged_at_step"] = int(diverged_at)
    if r.num_steps == 0:  # diverged at its first step: nothing to compare, all infinitely wrong
        entry["model"] = dict.fromkeys(("mse@full", "ot_mean", "mmd_mean"), np.inf)
        entry["model"]["finite"] = 0.0
        entry["constant_velocity"] = None
        return entry
    kinematic = np.isin(r.particle_type, r.metadata.get("kinematic_particle_types", [3]))
    baseline = constant_velocity_rollout(
        r.initial_positions,
        r.num_steps,
        kinematic_mask=kinematic,
        ground_truth=r.ground_truth_rollout,
    )
    free = ~kinematic
    # The ground truth's packing, the reference of both density ratios, counted once.
    truth_neighbours = None
    if radius is not None:
        last = r.ground_truth_rollout[-1, free]
        truth_neighbours = mean_neighbours(last, radius, bounds, periodic)
    for name, predicted in (("model", r.predicted_rollout), ("constant_velocity", baseline)):
        metrics = evaluate_rollout(
            predicted,
            r.ground_truth_rollout,
            mask=free,
            horizons=horizons,
            distribution_every=distribution_every,
            bandwidth=bandwidth,
            nonfinite="inf",
        )
        scalars = {
            key: float(value)
            for key, value in metrics.items()
            if key.startswith("mse@") or key in ("ot_mean", "mmd_mean")
        }
        finite = bool(np.isfinite(predicted).all())
        if name == "model" and diverged_at is not None:
            # The rollout stopped early: what lies beyond its last finite frame counts as
            # infinitely wrong, not as absent.
            finite = False
            scalars.update(dict.fromkeys(("mse@full", "ot_mean", "mmd_mean"), np.inf))
        scalars["finite"] = float(finite)
        if bounds is not None:
            scalars["outside_box"] = outside_box(predicted, bounds) if finite else np.inf
        if truth_neighbours is not None and finite:
            ours = mean_neighbours(predicted[-1, free], radius, bounds, periodic)
            scalars["density_ratio"] = ours / truth_neighbours if truth_neighbours else np.nan
        entry[name] = {**scalars, "mse": metrics["mse"].tolist()}
    return entry


def rest_test(
    simulator: LearnedSimulator,
    trajectory: Trajectory,
    steps: int,
    *,
    device: torch.device | str = "cpu",
) -> dict[str, float]:
    """Holds the trajectory's last frame still (C + 1 identical frames, so every input velocity
    is zero) and rolls the model out `steps` steps from it, with the last frame's step context.

    Sand that the data leaves at rest should stay where it is; a model that loses volume packs
    it ever closer and sinks it into the floor. Returns, over non-kinematic particles:
    density_ratio, the mean neighbour count within the connectivity radius after the rollout
    over that of the held frame (1 when the pile keeps its packing); max_displacement, how far
    the farthest particle moved (inf if the rollout diverged); outside_box (with bounds); and
    truth_speed, the largest displacement of the data's own last step, which says how still
    the held frame really was.
    """
    steps = int(steps)
    if steps < 1:
        raise ValueError(f"rest_test needs at least 1 step, got {steps}")
    history = simulator.config.model.velocity_history + 1
    frames = history + steps
    held = trajectory.positions[-1]
    context = trajectory.step_context
    still = Trajectory(
        positions=np.repeat(held[None], frames, axis=0),
        particle_type=trajectory.particle_type,
        step_context=None if context is None else np.repeat(context[-1:], frames, axis=0),
        material_property=trajectory.material_property,
        key=trajectory.key,
        source=f"{trajectory.source} (last frame held still)",
    )
    free = ~simulator.scene.kinematic_mask(trajectory.particle_type)
    scene = simulator.scene
    result = {"truth_speed": np.nan}  # a one-frame trajectory has no last step
    if trajectory.num_frames > 1:
        last_step = trajectory.positions[-1, free] - trajectory.positions[-2, free]
        result["truth_speed"] = float(np.linalg.norm(last_step, axis=-1).max(initial=0.0))
    try:
        final = rollout(simulator, still, num_steps=steps, device=device).predicted_rollout[-1]
    except RolloutDiverged:
        result.update(density_ratio=np.inf, max_displacement=np.inf)
        if scene.bounds is not None:
            result["outside_box"] = np.inf
        return result
    before = mean_neighbours(held[free], scene.radius, scene.bounds, scene.periodic)
    after = mean_neighbours(final[free], scene.radius, scene.bounds, scene.periodic)
    moved = np.linalg.norm(final[free].astype(np.float64) - held[free], axis=-1)
    result["density_ratio"] = after / before if before else np.nan
    result["max_displacement"] = float(moved.max(initial=0.0))
    if scene.bounds is not None:
        result["outside_box"] = outside_box(final[None], scene.bounds)
    return result
